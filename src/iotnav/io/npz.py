"""Reader for IMU recordings stored as NumPy ``.npz`` in the BROAD layout.

BROAD (Laidig et al., "BROAD - A Benchmark for Robust Inertial Orientation Estimation", Data
6(7):72, 2021) trials converted to ``.npz`` carry ``imu_acc`` (m/s^2), ``imu_gyr`` (rad/s),
``imu_mag`` (microtesla), each ``(N, 3)`` in the sensor frame, and a scalar ``sampling_rate``
(Hz); samples are equally spaced, so device time is ``t = k / sampling_rate`` (clock
``device``). The VQF test-data layout (``acc``, ``gyr``, ``mag`` with ``sampling_rate``) is read
the same way. Rows with a non-finite accelerometer or gyroscope value are skipped and counted.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd

from iotnav.io.errors import IngestError
from iotnav.io.log import Part
from iotnav.io.report import FileReport, SkipReason

_REQUIRED = ("imu_acc", "imu_gyr", "sampling_rate")
_ALIASES = {"imu_acc": "acc", "imu_gyr": "gyr", "imu_mag": "mag"}


def read_imu_npz(source: str | os.PathLike[str], *, name: str | None = None) -> Part:
    """Read a BROAD-layout ``.npz`` IMU recording.

    Parameters
    ----------
    source : path-like
        The ``.npz`` file.
    name : str, optional
        Name used in the report (defaults to the path).

    Returns
    -------
    Part
        IMU (and magnetometer when ``imu_mag`` is present) on the ``device`` clock.

    Raises
    ------
    IngestError
        When the file is not a readable ``.npz`` or lacks ``imu_acc``/``imu_gyr``/``sampling_rate``.
    """
    path = Path(source)
    rep = FileReport(path=name or str(path), format="imu-npz")
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise IngestError(str(path), f"not a readable .npz file ({exc})") from None
    with data:
        keys = {k: k if k in data.files else _ALIASES.get(k, k) for k in (*_REQUIRED, "imu_mag")}
        missing = [k for k in _REQUIRED if keys[k] not in data.files]
        if missing:
            raise IngestError(
                str(path), f"an IMU .npz needs arrays {', '.join(_REQUIRED)}; missing {', '.join(missing)}"
            )
        try:
            acc = np.asarray(data[keys["imu_acc"]], dtype=float)
            gyr = np.asarray(data[keys["imu_gyr"]], dtype=float)
            fs = float(data["sampling_rate"])
            mag = np.asarray(data[keys["imu_mag"]], dtype=float) if keys["imu_mag"] in data.files else None
        except (ValueError, zipfile.BadZipFile, EOFError, OSError) as exc:
            raise IngestError(str(path), f"damaged .npz array ({exc})") from None
        ignored = [k for k in data.files if k not in keys.values()]
    if acc.ndim != 2 or acc.shape[1] != 3 or gyr.shape != acc.shape or not (fs > 0 and np.isfinite(fs)):
        raise IngestError(str(path), "imu_acc and imu_gyr must both be (N, 3) and sampling_rate positive")
    n = acc.shape[0]
    rep.units = n
    t = np.arange(n) / fs
    ok = np.isfinite(acc).all(axis=1) & np.isfinite(gyr).all(axis=1)
    if (~ok).any():
        rep.skip(SkipReason.NAN_FIELD, text="non-finite IMU sample", n=int((~ok).sum()))
    rep.record("imu", int(ok.sum()))
    if ignored:
        rep.notes.append(f"arrays not used by the reader: {', '.join(ignored)}")
    rep.notes.append(f"equally spaced samples at {fs:.3f} Hz; t = k / rate (device clock)")
    imu = pd.DataFrame(
        {
            "t": t[ok],
            "acc_x": acc[ok, 0],
            "acc_y": acc[ok, 1],
            "acc_z": acc[ok, 2],
            "gyro_x": gyr[ok, 0],
            "gyro_y": gyr[ok, 1],
            "gyro_z": gyr[ok, 2],
        }
    )
    mag_df = None
    if mag is not None and mag.shape == acc.shape:
        mok = np.isfinite(mag).all(axis=1)
        mag_df = pd.DataFrame(
            {"t": t[mok], "mag_x_ut": mag[mok, 0], "mag_y_ut": mag[mok, 1], "mag_z_ut": mag[mok, 2]}
        )
        rep.record("mag", int(mok.sum()))
    return Part.make(rep, "device", imu=imu, mag=mag_df)
