"""Write a :class:`~iotnav.sim.scenarios.SimResult` as the files ``iotnav ingest`` reads.

One directory holds

``gnss.nmea``
    timestamped NMEA log: ``<device time s, 3 decimals>,$GPGGA,...`` (GGA, RMC, GSA, VTG);
``gnss.ubx``
    UBX NAV-PVT (when ``gnss.write_ubx``);
``imu.csv``
    ``t,acc_x_mps2,acc_y_mps2,acc_z_mps2,gyro_x_rads,gyro_y_rads,gyro_z_rads`` (device time s,
    sensor frame ``b``) plus ``mag_x_ut,mag_y_ut,mag_z_ut`` when a magnetometer is simulated
    (filled on the rows where a magnetometer sample was taken, empty elsewhere); 6 decimals;
``truth.csv``
    ``t,lat,lon,height,north,east,down,vn,ve,vd,roll,pitch,yaw``: IMU position (lat/lon deg,
    ellipsoidal height m, NED m about the origin), velocity (m/s, NED) and vehicle attitude
    ``C_nv`` (rad), at ``max(imu.rate_hz, 10)`` Hz on the device clock; 9 decimals;
``scenario.json``
    every parameter, the seed, the origin, ``utc_offset_s`` (``utc = t + utc_offset_s``), the
    mounting angles ``mount_roll_rad``, ``mount_pitch_rad``, ``mount_yaw_rad``
    (``C_nb = C_nv @ C_vb``, ``C_vb = euler_to_dcm(mount angles)``; ``mount_yaw_rad`` is the
    angle of the sensor x axis from the vehicle forward axis, positive clockwise seen from
    above), the resolved sensor parameters and the constants drawn;
``last_position.json``
    ``{"lat", "lon", "height", "t_saved_utc"}`` when the scenario stores a last position;
``fixes.csv``
    absolute fixes ``t_valid,t_arrival,lat,lon,height,roll,pitch,yaw,sigma_pos_m,sigma_att_rad``
    (device attitude ``C_nb`` angles, rad) when the scenario has them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from iotnav.io.export import write_fixed_csv
from iotnav.io.nmea_writer import write_nmea_log
from iotnav.io.ubx_writer import write_nav_pvt
from iotnav.sim.config import config_to_dict
from iotnav.sim.scenarios import Progress, SimResult

__all__ = ["IMU_CSV_COLUMNS", "write"]

IMU_CSV_COLUMNS = ("t", "acc_x_mps2", "acc_y_mps2", "acc_z_mps2", "gyro_x_rads", "gyro_y_rads", "gyro_z_rads")
MAG_CSV_COLUMNS = ("mag_x_ut", "mag_y_ut", "mag_z_ut")


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def _imu_frame(result: SimResult) -> pd.DataFrame:
    imu = result.imu
    data = {
        "t": imu["t"].to_numpy(),
        "acc_x_mps2": imu["acc_x"].to_numpy(),
        "acc_y_mps2": imu["acc_y"].to_numpy(),
        "acc_z_mps2": imu["acc_z"].to_numpy(),
        "gyro_x_rads": imu["gyro_x"].to_numpy(),
        "gyro_y_rads": imu["gyro_y"].to_numpy(),
        "gyro_z_rads": imu["gyro_z"].to_numpy(),
    }
    if len(result.mag):
        pos = np.searchsorted(data["t"], result.mag["t"].to_numpy())
        for c in MAG_CSV_COLUMNS:
            col = np.full(len(imu), np.nan)
            col[pos] = result.mag[c].to_numpy()
            data[c] = col
    return pd.DataFrame(data)


def write(result: SimResult, out_dir: str | os.PathLike[str], progress: Progress | None = None) -> list[Path]:
    """Write the scenario files into ``out_dir`` (created if needed).

    Parameters
    ----------
    result : SimResult
        From :func:`iotnav.sim.build`.
    out_dir : path-like
        Output directory.
    progress : callable, optional
        Called with the fraction of writing done.

    Returns
    -------
    list of pathlib.Path
        The files written.
    """
    report = progress or (lambda _x: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = result.config
    files: list[Path] = []
    if cfg.gnss.enabled:
        p = out / "gnss.nmea"
        write_nmea_log(p, result.gnss, result.gnss_extras.get("prn"), talker=cfg.gnss.talker)
        files.append(p)
        if cfg.gnss.write_ubx:
            p = out / "gnss.ubx"
            write_nav_pvt(p, result.gnss)
            files.append(p)
    report(0.2)
    if cfg.imu.enabled:
        p = out / "imu.csv"
        write_fixed_csv(_imu_frame(result), p, 6)
        files.append(p)
    report(0.6)
    p = out / "truth.csv"
    write_fixed_csv(result.truth, p, 9)
    files.append(p)
    report(0.85)
    if result.fixes is not None:
        p = out / "fixes.csv"
        write_fixed_csv(result.fixes, p, 9)
        files.append(p)
    if result.last_position is not None:
        p = out / "last_position.json"
        p.write_text(json.dumps(result.last_position, indent=2) + "\n")
        files.append(p)
    p = out / "scenario.json"
    doc = {
        "scenario": cfg.name,
        "description": cfg.description,
        "seed": result.seed,
        "origin": {
            "lat_deg": cfg.origin_lat_deg,
            "lon_deg": cfg.origin_lon_deg,
            "height_m": cfg.origin_height_m,
        },
        "start_utc": cfg.start_utc,
        "utc_offset_s": result.utc_offset_s,
        "mount_roll_rad": cfg.mount_roll_rad,
        "mount_pitch_rad": cfg.mount_pitch_rad,
        "mount_yaw_rad": cfg.mount_yaw_rad,
        "conventions": (
            "n = local NED tangent frame at the origin; v = vehicle (x forward, y right, z down); "
            "b = IMU sensor frame; C_nb = C_nv @ C_vb with C_vb = euler_to_dcm(mount_roll_rad, "
            "mount_pitch_rad, mount_yaw_rad) (ZYX, yaw positive clockwise seen from above); "
            "truth.csv attitude is C_nv; utc = t + utc_offset_s; IMU sample k is the mean over "
            "[t_k, t_k + 1/rate)"
        ),
        "files": [f.name for f in files] + [p.name],
        "config": config_to_dict(cfg),
        "resolved": result.meta,
    }
    p.write_text(json.dumps(_jsonable(doc), indent=2) + "\n")
    files.append(p)
    report(1.0)
    return files
