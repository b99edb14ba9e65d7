"""Real cases an engine was never tuned on (issue 16): transforms of a log and named cases.

The engines are otherwise measured on logs that start static, with the sensor where the
profile says, a calibrated gyro and fixes stamped at their epoch. The transforms below make
real logs that break each of those assumptions; the named cases in :data:`CASES` combine them.

Transforms (pure functions of a :class:`~iotnav.io.log.Log`; the input is not modified)
    * :func:`cut_log`: drop everything before ``first time + start_s`` (a log that starts in
      motion);
    * :func:`add_gyro_bias`: a constant rate added to every gyro sample (a raw, uncalibrated
      gyro);
    * :func:`rotate_sensor`: the sensor turned a further roll, pitch, yaw on its mount;
    * :func:`gnss_arrival_stamps`: fixes stamped when they arrive, ``latency_s`` after their
      epoch.

Rotation convention (names of :mod:`iotnav`)
    The new sensor frame ``b'`` is the old one turned by the ZYX angles ``rpy``:
    ``C_bb' = euler_to_dcm(roll, pitch, yaw)`` maps ``b'`` vectors to ``b`` (as ``C_nb`` maps
    ``b`` to ``n``), so the attitude of the new sensor is ``C_nb' = C_nb C_bb'`` and every
    measured vector becomes ``f_b' = C_bb'^T f_b``, ``omega_ib_b' = C_bb'^T omega_ib_b``. A
    vehicle mount ``C_vb`` becomes ``C_vb' = C_vb C_bb'``. Rotating by ``C`` and then by
    ``C^T`` (``dcm_to_rpy(C.T)``) gives the log back.

Named cases (:data:`CASES`, loaded by :func:`load_case`)
    * ``drive_0708`` (rtklibexplorer car, RTK truth) cut to start in motion at 100 s (10.6 m/s)
      and at 220 s (9.6 m/s; at 200 s, the start issue 16 names, the car waits at 0 m/s from 200
      to 210 s, which would be a static start), with a constant gyro bias of 1 and of 3 deg/s on each axis, and the sensor turned a
      further 5 deg in roll and 10 deg in pitch; GNSS: the RTK degraded to 1 Hz tracker grade as
      in :mod:`iotnav.eval.outages`.
    * ``husky``: ``robot_localization_husky`` (Clearpath Husky, Microstrain 3DM-GX2 at 30 Hz on
      its side with +y up, 2.5 Hz SBAS fixes, starts in motion). There is no truth better than
      the fixes themselves (about 1 m, dataset README), so the unmasked fixes are the truth and
      the fed GNSS; outage errors below about 1 m are noise.
    * ``walk_0827`` (rtklibexplorer hand-held walk, RTK truth) as recorded.

:func:`load_case` returns the fed log, the truth, the profile and the outage settings, ready for
:func:`iotnav.eval.outages.study` (``fed=``) or a direct :func:`iotnav.engines.base.run_batch`.
Reading files happens only in :func:`load_husky` and :func:`load_case` (the ingest edge);
the transforms are pure.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.eval.outages import DATASETS, DatasetProfile, OutageConfig, degraded_feed, rtk_truth
from iotnav.geo import LocalFrame, dcm_to_euler, dcm_to_rpy, euler_to_dcm
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, coerce, empty_table

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "CASES",
    "DATA_ROOT",
    "HUSKY",
    "Case",
    "LoadedCase",
    "add_gyro_bias",
    "cut_log",
    "differenced_velocity",
    "gnss_arrival_stamps",
    "load_case",
    "load_husky",
    "rotate_sensor",
]

#: Where the shared real datasets live.
DATA_ROOT = Path("/work/shared/datasets")

_GYRO = ("gyro_x", "gyro_y", "gyro_z")
_ACC = ("acc_x", "acc_y", "acc_z")


# --------------------------------------------------------------------------- transforms


def _first_time(log: Log) -> float:
    starts = [float(df["t"].iloc[0]) for df in (log.gnss, log.imu, log.mag) if len(df)]
    if not starts:
        raise ValueError("the log is empty")
    return min(starts)


def cut_log(log: Log, start_s: float) -> Log:
    """The log without anything before ``first time + start_s``.

    Parameters
    ----------
    log : Log
        Input (not modified).
    start_s : float
        Seconds after the first sample of any table (>= 0).

    Returns
    -------
    Log
        GNSS, IMU and magnetometer rows at or after the cut, re-indexed.
    """
    if start_s < 0.0:
        raise ValueError(f"start_s must be >= 0, got {start_s}")
    t_cut = _first_time(log) + start_s

    def cut(df: pd.DataFrame) -> pd.DataFrame:
        return df[df["t"].to_numpy(float) >= t_cut].reset_index(drop=True)

    return dataclasses.replace(log, gnss=cut(log.gnss), imu=cut(log.imu), mag=cut(log.mag))


def add_gyro_bias(log: Log, bias_rad_s: float | npt.ArrayLike) -> Log:
    """The log with a constant rate added to every gyro sample.

    Parameters
    ----------
    log : Log
        Input (not modified).
    bias_rad_s : float or array_like of 3
        Bias about sensor x, y, z, rad/s (a scalar applies to each axis).
    """
    b = np.broadcast_to(np.asarray(bias_rad_s, float), (3,))
    imu = log.imu.copy()
    for c, bk in zip(_GYRO, b, strict=True):
        imu[c] = imu[c].to_numpy(float) + float(bk)
    return dataclasses.replace(log, imu=imu)


def rotate_sensor(log: Log, rpy_rad: tuple[float, float, float]) -> Log:
    """The log as a sensor turned a further ``rpy_rad`` on its mount would have measured it.

    Parameters
    ----------
    log : Log
        Input (not modified).
    rpy_rad : tuple of float
        Roll, pitch, yaw (rad, ZYX) of ``C_bb'``, the new sensor frame ``b'`` in the old ``b``
        (module docstring): ``f_b' = C_bb'^T f_b`` for the specific force, the angular rate and
        the magnetic field.
    """
    C_bbp = euler_to_dcm(*rpy_rad)
    imu = log.imu.copy()
    for cols in (_ACC, _GYRO):
        v_b = imu[list(cols)].to_numpy(float)
        imu[list(cols)] = v_b @ C_bbp  # rows: (C_bb'^T v_b)^T = v_b^T C_bb'
    mag = log.mag.copy()
    if len(mag):
        mcols = ["mag_x_ut", "mag_y_ut", "mag_z_ut"]
        mag[mcols] = mag[mcols].to_numpy(float) @ C_bbp
    return dataclasses.replace(log, imu=imu, mag=mag)


def rotated_mount_rpy_deg(
    author_rpy_deg: tuple[float, float, float], rpy_rad: tuple[float, float, float]
) -> tuple[float, float, float]:
    """A profile's ``author_mount_rpy_deg`` after :func:`rotate_sensor` by ``rpy_rad``.

    The profile stores ``C(rpy) = C_vb^T``; the turned sensor has ``C_vb' = C_vb C_bb'``, so
    ``C(rpy') = C_bb'^T C(rpy)``. Degrees.
    """
    C = euler_to_dcm(*rpy_rad).T @ euler_to_dcm(*np.radians(author_rpy_deg))
    r, p, y = dcm_to_rpy(C)
    return math.degrees(r), math.degrees(p), math.degrees(y)


def gnss_arrival_stamps(gnss: pd.DataFrame, latency_s: float) -> pd.DataFrame:
    """GNSS epochs stamped at their arrival: ``t + latency_s`` (the position stays the epoch's).

    Parameters
    ----------
    gnss : pandas.DataFrame
        GNSS table (:data:`iotnav.io.schema.GNSS_COLUMNS`; not modified).
    latency_s : float
        Delay from the fix epoch to its arrival at the logger, s (>= 0; u-blox at 10 Hz: about
        0.2 s, issue 16).
    """
    if latency_s < 0.0:
        raise ValueError(f"latency_s must be >= 0, got {latency_s}")
    g = gnss.copy()
    g["t"] = g["t"].to_numpy(float) + latency_s
    return g


# --------------------------------------------------------------------------- Husky

#: The Husky's profile. ``C_vb`` from the README's ``R_base_imu = Rz(-90) Rx(+90)`` (REP-103
#: base_link x forward, y left, z up): vehicle x = -imu z, y (right) = +imu x, z (down) = -imu y.
_HUSKY_C_VB = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _husky_profile() -> DatasetProfile:
    import warnings

    with warnings.catch_warnings():  # pitch is 90 deg: scipy warns of the gimbal lock, keeps roll + yaw
        warnings.simplefilter("ignore", UserWarning)
        r, p, y = (float(a) for a in dcm_to_euler(_HUSKY_C_VB.T))
    return DatasetProfile(
        name="husky",
        pos_file="gnss.csv",
        imu_file="imu.csv",
        vehicle="car",  # skid-steer, no side slip in the controller's model (README: vy = 0)
        imu_time_offset_s=0.0,
        author_mount_rpy_deg=(math.degrees(r), math.degrees(p), math.degrees(y)),
        # Microstrain 3DM-GX2, measured at the 10.5 s stop (README): gyro std 0.0026 rad/s on
        # the good axes, 0.020 rad/s on the broken x axis, at 30 Hz -> density 0.020 / sqrt(15)
        # = 5.2e-3 rad/s/rtHz = 296 mdps/rtHz (the worst axis); accelerometer std up to
        # 0.059 m/s^2 -> 0.015 m/s^2/rtHz = 1550 ug/rtHz.
        eskf={
            "acc_noise_density_ug_rthz": 1550.0,
            "gyro_noise_density_mdps_rthz": 300.0,
            "acc_turn_on_bias_mg": 20.0,
            "gyro_turn_on_bias_dps": 1.0,
        },
    )


HUSKY = _husky_profile()

#: Baseline of the backward-difference velocity of the Husky's fixes, s (NavSatFix has none).
#: 2 s (5 fixes): the fixes' scatter at rest (0.30 m N, README) gives about 0.2 m/s per axis.
HUSKY_VELOCITY_BASELINE_S = 2.0
#: 1-sigma speed accuracy given with that velocity, m/s (sqrt(2) 0.3 m / 2 s, rounded up).
HUSKY_SPEED_ACC_MPS = 0.25


def differenced_velocity(
    t: FloatArray, ned: FloatArray, baseline_s: float, causal: bool = True
) -> FloatArray:
    """NED velocity (m/s) of a fix track by differences over about ``baseline_s``.

    ``causal``: from the fix ``baseline_s`` earlier to this one (what a device can compute when
    the fix arrives); otherwise centred. The first fixes use the earliest one available; a fix
    with no other inside the baseline gets NaN.
    """
    n = len(t)
    lo = np.searchsorted(t, t - (baseline_s if causal else baseline_s / 2.0), side="left")
    hi = np.arange(n) if causal else np.searchsorted(t, t + baseline_s / 2.0, side="right") - 1
    lo = np.minimum(lo, np.arange(n))
    dt = t[hi] - t[lo]
    v = np.full((n, 3), np.nan)
    ok = dt > 0
    v[ok] = (ned[hi[ok]] - ned[lo[ok]]) / dt[ok, None]
    return v


def load_husky(folder: Path | None = None) -> tuple[Log, pd.DataFrame]:
    """The Husky recording as a log (fed GNSS = the fixes) and its truth (the same fixes).

    Parameters
    ----------
    folder : Path, optional
        ``robot_localization_husky`` folder (default under :data:`DATA_ROOT`).

    Returns
    -------
    log : Log
        IMU (``imu.csv``, sensor axes as recorded, +y up) and GNSS (``gnss.csv``): ``h_acc_m`` /
        ``v_acc_m`` from the stated covariance (``sqrt(cov_xx + cov_yy)``, ``sqrt(cov_zz)``),
        velocity by a causal :data:`HUSKY_VELOCITY_BASELINE_S` difference of the fixes (the
        NavSatFix message has none) with ``s_acc_mps`` :data:`HUSKY_SPEED_ACC_MPS`. Times are
        the ROS header stamps (Unix UTC, s).
    truth : pandas.DataFrame
        The fixes as a truth table (:func:`iotnav.eval.outages.rtk_truth` columns) with a
        centred velocity; about 1 m good (README), vertical unusable.

    Raises
    ------
    FileNotFoundError
        When a file is missing.
    """
    folder = folder or DATA_ROOT / "robot_localization_husky"
    for f in ("imu.csv", "gnss.csv"):
        if not (folder / f).exists():
            raise FileNotFoundError(f"{folder / f}: missing (expected the robot_localization_husky CSVs)")
    raw_imu = pd.read_csv(folder / "imu.csv")
    imu = coerce(raw_imu[list(IMU_COLUMNS)], IMU_COLUMNS)
    raw = pd.read_csv(folder / "gnss.csv")
    t = raw["t"].to_numpy(float)
    lat, lon, h = (raw[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
    frame = LocalFrame(float(lat[0]), float(lon[0]), float(h[0]))
    ned = frame.to_ned(lat, lon, h)
    v = differenced_velocity(t, ned, HUSKY_VELOCITY_BASELINE_S, causal=True)
    v[:, 2] = 0.0  # the vertical of these fixes is unusable (README); a ground robot on a lot
    speed = np.hypot(v[:, 0], v[:, 1])
    gnss = empty_table(GNSS_COLUMNS).reindex(range(len(t)))
    gnss = gnss.assign(
        t=t,
        utc=t,
        lat_deg=lat,
        lon_deg=lon,
        height_m=h,
        quality=np.where(raw["status"].to_numpy() >= 1, 2, 1),  # SBAS fix: GGA quality 2 (DGPS)
        mode=3,
        num_sv=-1,
        hdop=np.sqrt(raw["cov_xx_m2"].to_numpy(float)),
        speed_mps=speed,
        course_rad=np.mod(np.arctan2(v[:, 1], v[:, 0]), 2.0 * np.pi),
        course_valid=np.isfinite(speed) & (speed > 0.3),
        vn=v[:, 0],
        ve=v[:, 1],
        vd=v[:, 2],
        h_acc_m=np.sqrt(raw["cov_xx_m2"].to_numpy(float) + raw["cov_yy_m2"].to_numpy(float)),
        v_acc_m=np.sqrt(raw["cov_zz_m2"].to_numpy(float)),
        s_acc_mps=HUSKY_SPEED_ACC_MPS,
        valid=True,  # status 1 (SBAS fix) on every row
        source="husky-navsatfix",
    )
    gnss = coerce(gnss, GNSS_COLUMNS)
    vc = differenced_velocity(t, ned, HUSKY_VELOCITY_BASELINE_S, causal=False)
    truth = pd.DataFrame(
        {
            "t": t,
            "lat": lat,
            "lon": lon,
            "height": h,
            "vn": vc[:, 0],
            "ve": vc[:, 1],
            "vd": 0.0,
            "quality": gnss["quality"].to_numpy(),
        }
    )
    return Log(gnss=gnss, imu=imu, utc_offset_s=0.0), truth


# --------------------------------------------------------------------------- named cases


@dataclass(frozen=True)
class Case:
    """One named case (degrees and deg/s at this edge; converted in :func:`load_case`).

    Attributes
    ----------
    name : str
        Case name (key of :data:`CASES`).
    dataset : str
        ``drive_0708``, ``walk_0827`` (rtklibexplorer, RTK truth) or ``husky``.
    start_s : float
        Cut: the case starts this long after the recording's first sample, s.
    gyro_bias_dps : float
        Constant gyro bias added on each axis, deg/s.
    rotate_rpy_deg : tuple of float
        Further sensor rotation (:func:`rotate_sensor`), roll, pitch, yaw in degrees.
    gnss_latency_s : float
        Fixes stamped at arrival this long after their epoch, s.
    outages : OutageConfig
        Study settings for this case.
    """

    name: str
    dataset: str
    start_s: float = 0.0
    gyro_bias_dps: float = 0.0
    rotate_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gnss_latency_s: float = 0.0
    outages: OutageConfig = field(default_factory=OutageConfig)


def _drive_cases() -> dict[str, Case]:
    out = {}
    for start in (100.0, 220.0):
        for bias in (1.0, 3.0):
            name = f"drive_0708-start{start:.0f}-bias{bias:.0f}"
            out[name] = Case(
                name=name,
                dataset="drive_0708",
                start_s=start,
                gyro_bias_dps=bias,
                rotate_rpy_deg=(5.0, 10.0, 0.0),
                outages=OutageConfig(lengths_s=(15.0, 30.0), spacing_s=60.0, first_offset_s=60.0),
            )
    return out


#: The named cases of issue 16.
CASES: dict[str, Case] = {
    **_drive_cases(),
    "husky": Case(
        name="husky",
        dataset="husky",
        outages=OutageConfig(lengths_s=(15.0, 30.0), spacing_s=60.0, first_offset_s=60.0),
    ),
    "walk_0827": Case(
        name="walk_0827",
        dataset="walk_0827",
        outages=OutageConfig(lengths_s=(15.0, 30.0), spacing_s=30.0, first_offset_s=30.0),
    ),
}


class LoadedCase(NamedTuple):
    """A case ready to run: what the engines are fed, the truth, the profile, the settings."""

    fed: Log
    truth: pd.DataFrame
    profile: DatasetProfile
    config: OutageConfig
    case: Case


def _rtk_recording(dataset: str, root: Path) -> tuple[Log, DatasetProfile]:
    from iotnav.io import ingest

    prof = DATASETS[dataset]
    folder = root / "rtklibexplorer_gnss_imu" / dataset
    files = [folder / prof.pos_file, folder / prof.imu_file]
    for f in files:
        if not f.exists():
            raise FileNotFoundError(f"{f}: missing (expected the rtklibexplorer {dataset} files)")
    return ingest(files), prof


def load_case(case: str | Case, root: Path | None = None, max_duration_s: float | None = None) -> LoadedCase:
    """Load a named case: the fed log, the truth, the profile and the outage settings.

    Parameters
    ----------
    case : str or Case
        A key of :data:`CASES` or a :class:`Case`.
    root : Path, optional
        Datasets folder (default :data:`DATA_ROOT`).
    max_duration_s : float, optional
        Keep only the first this many seconds after the cut (short versions for tests), s.

    Returns
    -------
    LoadedCase
        ``fed`` (IMU cut, biased, rotated; GNSS degraded to tracker grade for the RTK
        recordings, the fixes for the Husky; arrival stamps if the case has a latency), the
        ``truth`` over the same span, the ``profile`` (its author mount turned with the sensor)
        and the ``config`` (the case's :class:`OutageConfig`).

    Raises
    ------
    KeyError
        For an unknown case name; FileNotFoundError when a dataset file is missing.
    """
    c = CASES[case] if isinstance(case, str) else case
    root = root or DATA_ROOT
    cfg = c.outages
    if c.dataset == "husky":
        log, truth = load_husky(root / "robot_localization_husky")
        prof = HUSKY
    else:
        rec, prof = _rtk_recording(c.dataset, root)
        truth = rtk_truth(rec.gnss)
        shifted = rec.imu.copy()
        shifted["t"] = shifted["t"].to_numpy(float) + prof.imu_time_offset_s
        log = dataclasses.replace(rec, gnss=empty_table(GNSS_COLUMNS), imu=shifted)
        prof = dataclasses.replace(prof, imu_time_offset_s=0.0)
    t0 = min(float(truth.t.iloc[0]), _first_time(log))
    t_cut = t0 + c.start_s
    t_end = t_cut + max_duration_s if max_duration_s is not None else math.inf
    truth = truth[(truth.t >= t_cut) & (truth.t < t_end)].reset_index(drop=True)
    log = cut_log(log, t_cut - _first_time(log)) if t_cut > _first_time(log) else log
    if math.isfinite(t_end):
        log = dataclasses.replace(
            log,
            gnss=log.gnss[log.gnss.t < t_end].reset_index(drop=True),
            imu=log.imu[log.imu.t < t_end].reset_index(drop=True),
            mag=log.mag[log.mag.t < t_end].reset_index(drop=True),
        )
    if c.gyro_bias_dps:
        log = add_gyro_bias(log, math.radians(c.gyro_bias_dps))
    rpy = tuple(math.radians(a) for a in c.rotate_rpy_deg)
    if any(rpy):
        log = rotate_sensor(log, rpy)  # type: ignore[arg-type]
        prof = dataclasses.replace(
            prof,
            author_mount_rpy_deg=rotated_mount_rpy_deg(prof.author_mount_rpy_deg, rpy),  # type: ignore[arg-type]
        )
    if c.dataset != "husky":
        log, _ = degraded_feed(log, truth, prof, cfg)
    if c.gnss_latency_s:
        log = dataclasses.replace(log, gnss=gnss_arrival_stamps(log.gnss, c.gnss_latency_s))
    prof = dataclasses.replace(prof, name=c.name)
    return LoadedCase(fed=log, truth=truth, profile=prof, config=cfg, case=c)


def case_summary(lc: LoadedCase) -> dict[str, Any]:
    """Facts of a loaded case (span, rates, speed at the start) for tables and tests."""
    tr = lc.truth
    sp = np.hypot(tr.vn.to_numpy(float), tr.ve.to_numpy(float))
    return {
        "case": lc.case.name,
        "duration_s": float(tr.t.iloc[-1] - tr.t.iloc[0]),
        "imu_rate_hz": float(1.0 / np.median(np.diff(lc.fed.imu.t.to_numpy(float)))),
        "gnss_epochs": len(lc.fed.gnss),
        "start_speed_mps": float(np.nanmedian(sp[:4])),
    }
