"""Column schemas of the tables every reader returns.

Each table is a :class:`pandas.DataFrame` with exactly these columns in this order and these
dtypes; :func:`empty_table` and :func:`coerce` build and check them. Missing values are NaN for
floats, ``-1`` for integer codes and ``False`` for flags.

GNSS epochs (one row per receiver fix cycle)
    ``t``             device time, s
    ``utc``           UTC, s since 1970-01-01 (NaN when the date is unknown)
    ``lat_deg``       geodetic latitude, degrees (WGS84)
    ``lon_deg``       geodetic longitude, degrees
    ``height_m``      ellipsoidal height, m (MSL altitude + geoid separation)
    ``alt_msl_m``     altitude above mean sea level, m
    ``geoid_sep_m``   geoid separation (ellipsoid - geoid), m
    ``quality``       GGA fix quality code (0 invalid, 1 GPS, 2 DGPS, 3 PPS, 4 RTK fixed,
                      5 RTK float, 6 dead reckoning, 7 manual, 8 simulator), -1 unknown
    ``mode``          fix mode as gpsd reports it: 0 unknown, 1 no fix, 2 2D, 3 3D
    ``num_sv``        satellites used, -1 unknown
    ``pdop``, ``hdop``, ``vdop``  dilutions of precision (NaN unknown)
    ``speed_mps``     speed over ground, m/s
    ``course_rad``    course over ground, rad from true North, clockwise, in [0, 2 pi)
    ``course_valid``  False when the receiver gives no course or flags it invalid
    ``vn``, ``ve``, ``vd``  NED velocity, m/s (NaN when the source has none)
    ``h_acc_m``, ``v_acc_m``  1-sigma horizontal / vertical accuracy, m (NaN unknown);
                      ``h_acc_m`` is the 2D figure, the root of the sum of the north and
                      east variances (u-blox hAcc, RTKLIB ``sqrt(sdn^2 + sde^2)``, UERE x
                      HDOP): each axis has ``h_acc / sqrt(2)`` (:mod:`iotnav.gnss_accuracy`)
    ``s_acc_mps``     1-sigma speed accuracy, m/s
    ``valid``         the receiver declares the fix valid (GGA quality > 0 / RMC 'A' / UBX gnssFixOK)
    ``source``        where the epoch came from: ``nmea``, ``ubx``, ``rtklib``, ``phone``, ``sim``
    ``motion``        the device's motion flag: 1 moving, 0 still, -1 unknown
    ``ignition``      the vehicle's ignition: 1 on, 0 off, -1 unknown

IMU samples
    ``t``; ``acc_x``, ``acc_y``, ``acc_z`` specific force in ``b``, m/s^2;
    ``gyro_x``, ``gyro_y``, ``gyro_z`` angular rate of ``b`` in ``b``, rad/s.

Magnetometer samples
    ``t``; ``mag_x_ut``, ``mag_y_ut``, ``mag_z_ut`` magnetic field in ``b``, microtesla.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

GNSS_COLUMNS: dict[str, str] = {
    "t": "float64",
    "utc": "float64",
    "lat_deg": "float64",
    "lon_deg": "float64",
    "height_m": "float64",
    "alt_msl_m": "float64",
    "geoid_sep_m": "float64",
    "quality": "int16",
    "mode": "int16",
    "num_sv": "int16",
    "pdop": "float64",
    "hdop": "float64",
    "vdop": "float64",
    "speed_mps": "float64",
    "course_rad": "float64",
    "course_valid": "bool",
    "vn": "float64",
    "ve": "float64",
    "vd": "float64",
    "h_acc_m": "float64",
    "v_acc_m": "float64",
    "s_acc_mps": "float64",
    "valid": "bool",
    "source": "object",
    "motion": "int16",
    "ignition": "int16",
}

IMU_COLUMNS: dict[str, str] = {
    "t": "float64",
    "acc_x": "float64",
    "acc_y": "float64",
    "acc_z": "float64",
    "gyro_x": "float64",
    "gyro_y": "float64",
    "gyro_z": "float64",
}

MAG_COLUMNS: dict[str, str] = {
    "t": "float64",
    "mag_x_ut": "float64",
    "mag_y_ut": "float64",
    "mag_z_ut": "float64",
}

_FILL: dict[str, Any] = {"float64": np.nan, "int16": -1, "bool": False, "object": ""}


def empty_table(columns: Mapping[str, str]) -> pd.DataFrame:
    """Return an empty table with the given schema.

    Parameters
    ----------
    columns : Mapping[str, str]
        Column name to dtype, e.g. :data:`GNSS_COLUMNS`.

    Returns
    -------
    pandas.DataFrame
        Zero rows, the schema's columns and dtypes.
    """
    return pd.DataFrame({k: pd.Series(dtype=v) for k, v in columns.items()})


def coerce(df: pd.DataFrame, columns: Mapping[str, str]) -> pd.DataFrame:
    """Return ``df`` with exactly the schema's columns, in order, with their dtypes.

    Columns missing from ``df`` are filled with the schema's missing value (NaN, -1, False, "");
    extra columns are dropped. Integer and flag columns holding NaN are filled before casting.

    Parameters
    ----------
    df : pandas.DataFrame
        A table from a reader.
    columns : Mapping[str, str]
        The schema, e.g. :data:`IMU_COLUMNS`.

    Returns
    -------
    pandas.DataFrame
        A new table, index reset.
    """
    out = {}
    n = len(df)
    for name, dtype in columns.items():
        fill = _FILL[dtype]
        if name in df.columns:
            col = df[name]
            if dtype in ("int16", "bool"):
                col = col.fillna(fill)
            out[name] = col.to_numpy().astype(dtype, copy=False)
        else:
            out[name] = np.full(n, fill, dtype=dtype)
    return pd.DataFrame(out)
