"""Column roles, presets and units of IMU text files (the mapping half of :mod:`iotnav.io.imu_csv`).

Header names are matched to roles (``acc_x`` ... ``mag_z``, ``t``, ``tick``) through aliases,
with a unit carried in the name (``acc_x_g``, ``gx (deg/s)``, ``mag_x_ut``); bare ``x, y, z``
columns take their sensor from the file name. Unit factors convert to SI (m/s^2, rad/s) and to
microtesla once, on the way in (STYLE §2); when no unit is named, it is guessed from the median
norm of the samples. The rules and their precedence are stated in :mod:`iotnav.io.imu_csv`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from iotnav.io.imu_table import _Layout

G0 = 9.80665  # standard gravity, m/s^2

#: Unit name -> factor to SI (m/s^2, rad/s) or to microtesla.
ACC_UNITS: dict[str, float] = {"m/s^2": 1.0, "g": G0, "mg": G0 * 1e-3}
GYRO_UNITS: dict[str, float] = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "mdps": math.pi / 180.0 * 1e-3}
MAG_UNITS: dict[str, float] = {"uT": 1.0, "mG": 0.1, "gauss": 100.0, "nT": 1e-3, "T": 1e6}

#: Plausibility limits in SI units (a component beyond them is ``OUT_OF_RANGE``).
ACC_LIMIT = 50.0 * G0
GYRO_LIMIT = 50.0
MAG_LIMIT_UT = 10_000.0

_ACC_ALIASES = {
    "g": "g",
    "mg": "mg",
    **dict.fromkeys(
        ["m/s^2", "m/s2", "ms2", "mps2", "m_s2", "m_s^2", "ms^-2", "ms-2", "m/s/s", "mss", "ms^2", "m/s²"],
        "m/s^2",
    ),
}
_GYRO_ALIASES = {
    **dict.fromkeys(["deg/s", "dps", "degps", "deg_s", "°/s", "degs", "degree/s", "degrees/s"], "deg/s"),
    **dict.fromkeys(["mdps", "mdeg/s", "mdeg_s"], "mdps"),
    **dict.fromkeys(["rad/s", "rads", "rad_s", "radps", "rps", "rad/sec"], "rad/s"),
}
_MAG_ALIASES = {
    **dict.fromkeys(["ut", "µt", "μt", "microtesla", "utesla"], "uT"),
    **dict.fromkeys(["mg", "mgauss", "milligauss"], "mG"),
    **dict.fromkeys(["g", "gauss", "gs"], "gauss"),
    "nt": "nT",
    **dict.fromkeys(["t", "tesla"], "T"),
}
_TIME_ALIASES = {
    **dict.fromkeys(["s", "sec", "secs", "seconds"], "s"),
    **dict.fromkeys(["ms", "msec"], "ms"),
    **dict.fromkeys(["us", "µs", "μs", "usec"], "us"),
    **dict.fromkeys(["ns", "nsec"], "ns"),
}
_ALIASES: dict[str, dict[str, str]] = {
    "acc": _ACC_ALIASES,
    "gyro": _GYRO_ALIASES,
    "mag": _MAG_ALIASES,
    "t": _TIME_ALIASES,
    "tick": _TIME_ALIASES,
}
_ALL_UNIT_TOKENS = sorted({k for d in _ALIASES.values() for k in d}, key=len, reverse=True)
_SUFFIX_RE = re.compile(r"^(.+?)[_ ](" + "|".join(re.escape(u) for u in _ALL_UNIT_TOKENS) + r")$")
_BRACKET_RE = re.compile(r"^(.*?)\s*[\[\(\{]([^\]\)\}]*)[\]\)\}]\s*$")

_FAMILY_RES = {
    "acc": re.compile(
        r"^(?:acc|accel|accl|accelerometer|acceleration|a|f|linacc|totalacc|totalacceleration)([xyz])$"
        r"|^([xyz])(?:acc|accel)$"
    ),
    "gyro": re.compile(
        r"^(?:gyro|gyr|gyroscope|g|w|omega|angvel|angularvelocity|angularrate|rot|rotationrate|rate)([xyz])$"
        r"|^([xyz])(?:gyro|gyr)$"
    ),
    "mag": re.compile(r"^(?:mag|magn|magnetometer|magneticfield|magfield|m|b)([xyz])$|^([xyz])(?:mag)$"),
}
#: Time column names, by preference (absolute times first).
_TIME_NAMES = [
    "time",
    "timestamp",
    "t",
    "ts",
    "utc",
    "unixtime",
    "unix",
    "epoch",
    "gpst",
    "gpstime",
    "gpsts",
    "timeutc",
    "sampletime",
    "secondselapsed",
    "elapsed",
    "elapsedtime",
    "seconds",
    "sec",
]
_TICK_NAMES = ["tick", "ticks", "imutick", "systick", "tickms"]
_STEM_FAMILY = {
    "accelerometer": "acc",
    "totalacceleration": "acc",
    "gyroscope": "gyro",
    "magnetometer": "mag",
}

_ROLES = (*(f"{f}_{a}" for f in ("acc", "gyro", "mag") for a in "xyz"), "t", "tick")
_SKIP_ROLES = {"", "-", "skip", "ignore", "_"}


@dataclass(frozen=True)
class ImuPreset:
    """A named layout of a header-less IMU file.

    Attributes
    ----------
    column_order : tuple of str
        Role of each field (``acc_x`` ... ``gyro_z``, ``mag_x`` ..., ``t``, ``tick``, ``"-"`` to skip).
    acc_unit, gyro_unit, mag_unit, time_unit : str or None
        Units of the fields (see :data:`ACC_UNITS`, :data:`GYRO_UNITS`, :data:`MAG_UNITS`).
    description : str
        Where the layout comes from.
    """

    column_order: tuple[str, ...]
    acc_unit: str | None = None
    gyro_unit: str | None = None
    mag_unit: str | None = None
    time_unit: str | None = None
    description: str = ""


#: Named layouts usable as ``read_imu_csv(path, preset=...)``.
IMU_PRESETS: dict[str, ImuPreset] = {
    "rtklib-demo5": ImuPreset(
        column_order=("acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z", "tick"),
        acc_unit="g",
        gyro_unit="deg/s",
        time_unit="ms",
        description=(
            "rtklibexplorer GNSS_IMU logger: 7 fields, no header, acceleration in g, rate in deg/s, "
            "tick in ms since power-up; timed by the RTKLIB demo5 '.tag' file"
        ),
    ),
}


# --------------------------------------------------------------------------------------------
# Column names and units
# --------------------------------------------------------------------------------------------


def _canon_unit(family: str, unit: str | None) -> str | None:
    if unit is None:
        return None
    u = unit.strip().replace(" ", "")
    aliases = _ALIASES[family]
    if family == "mag" and u in ("mG", "MG"):
        return "mG"
    return aliases.get(u.lower()) if u.lower() in aliases else aliases.get(u)


def _check_unit(family: str, unit: str | None, where: str) -> str | None:
    """Validate an explicit unit (raises ValueError naming the allowed ones)."""
    if unit is None:
        return None
    table = {"acc": ACC_UNITS, "gyro": GYRO_UNITS, "mag": MAG_UNITS}.get(family)
    if table is not None and unit in table:
        return unit
    canon = _canon_unit(family, unit)
    if canon is None:
        allowed = sorted(table) if table is not None else ["s", "ms", "us", "ns"]
        raise ValueError(f"unknown {where} {unit!r}; expected one of {', '.join(allowed)}")
    return canon


def _norm(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", name.lower())


def _name_candidates(name: str) -> list[tuple[str, str | None]]:
    """``(normalised base, unit hint)`` readings of a header name, most specific first."""
    raw = name.strip().strip("\"'").strip()
    out: list[tuple[str, str | None]] = []
    m = _BRACKET_RE.match(raw)
    if m and m.group(1):
        out.append((_norm(m.group(1)), m.group(2).strip()))
    low = raw.lower()
    m2 = _SUFFIX_RE.match(low)
    if m2:
        # keep the original case of the unit (mG vs mg matters for magnetometers)
        unit = raw[len(raw) - len(m2.group(2)) :]
        out.append((_norm(m2.group(1)), unit))
    out.append((_norm(raw), None))
    return out


def _role_of(name: str, stem_family: str | None) -> tuple[str, str | None, bool] | None:
    """Role, unit hint and GPST flag of a header name, or None."""
    for base, unit in _name_candidates(name):
        if not base:
            continue
        for fam, rx in _FAMILY_RES.items():
            m = rx.match(base)
            if m:
                axis = m.group(1) or m.group(2)
                return f"{fam}_{axis}", unit, False
        if base in ("x", "y", "z") and stem_family is not None:
            return f"{stem_family}_{base}", unit, False
        if base in _TICK_NAMES:
            return "tick", unit, False
        if base in _TIME_NAMES or base.endswith("timestamp") or base in ("gpsts", "gpsttime"):
            return "t", unit, "gps" in base
    return None


def _stem_family(path: str) -> str | None:
    stem = _norm(Path(path).stem)
    for key, fam in _STEM_FAMILY.items():
        if stem.startswith(key):
            return fam
    return None


# --------------------------------------------------------------------------------------------
# Unit guesses
# --------------------------------------------------------------------------------------------


def _sample_norm(
    cols: Sequence[npt.NDArray[np.float64]], ok: npt.NDArray[np.bool_]
) -> npt.NDArray[np.float64]:
    idx = np.flatnonzero(ok)
    if idx.size > 200_000:
        idx = idx[:: idx.size // 200_000]
    return np.sqrt(sum(c[idx] ** 2 for c in cols))  # type: ignore[return-value]


def _guess_acc(norms: npt.NDArray[np.float64]) -> str | None:
    if norms.size == 0:
        return None
    m = float(np.median(norms))
    for lo, hi, unit in ((0.5, 2.0, "g"), (5.0, 20.0, "m/s^2"), (500.0, 2000.0, "mg")):
        if lo <= m <= hi:
            return unit
    return None


def _guess_mag(norms: npt.NDArray[np.float64]) -> str | None:
    if norms.size == 0:
        return None
    m = float(np.median(norms))
    for lo, hi, unit in (
        (5.0, 150.0, "uT"),
        (150.0, 2000.0, "mG"),
        (0.05, 1.5, "gauss"),
        (5e3, 2e5, "nT"),
        (5e-6, 2e-4, "T"),
    ):
        if lo <= m <= hi:
            return unit
    return None


# --------------------------------------------------------------------------------------------
# Column resolution
# --------------------------------------------------------------------------------------------


def _resolve_columns(
    layout: _Layout,
    columns: Mapping[str, str] | None,
    column_order: Sequence[str] | None,
    stem_family: str | None,
) -> tuple[dict[str, int], dict[str, str], bool, list[str]]:
    """Role -> field index, unit hints by family, GPST flag of the time column, ignored names."""
    roles: dict[str, int] = {}
    hints: dict[str, str] = {}
    gps = False
    ignored: list[str] = []
    if column_order is not None:
        for i, r in enumerate(column_order):
            rr = (r or "").strip()
            rr = "mag_" + rr[4] if rr.startswith("mag_") and rr.endswith("_ut") else rr
            rr = "t" if rr in ("time", "timestamp") else rr
            if rr.lower() in _SKIP_ROLES:
                continue
            if rr not in _ROLES:
                ignored.append(rr)
                continue
            roles[rr] = i
        return roles, hints, gps, ignored
    header = layout.header or []
    if columns is not None:
        lookup = {h: i for i, h in enumerate(header)}
        for role, col in columns.items():
            r = "mag_" + role[4] if role.startswith("mag_") and role.endswith("_ut") else role
            r = "t" if r in ("time", "timestamp") else r
            if r not in _ROLES:
                raise ValueError(f"unknown column role {role!r}; expected one of {', '.join(_ROLES)}")
            if col not in lookup:
                raise KeyError(col)
            roles[r] = lookup[col]
            got = _role_of(col, stem_family)
            if got is not None and got[1] is not None:
                hints.setdefault(r.split("_")[0] if r not in ("t", "tick") else r, got[1])
            if r == "t":
                gps = "gps" in _norm(col)
    time_rank: tuple[int, int] | None = None
    for i, h in enumerate(header):
        if i in roles.values():
            continue
        got = _role_of(h, stem_family)
        if got is None or (columns is not None and got[0] in roles):
            if h:
                ignored.append(h)
            continue
        role, unit, is_gps = got
        if role == "t":
            cands = [c for c, _ in _name_candidates(h)]
            rank = min((_TIME_NAMES.index(c) for c in cands if c in _TIME_NAMES), default=len(_TIME_NAMES))
            key = (rank, i)
            if time_rank is not None and key >= time_rank:
                ignored.append(h)
                continue
            if "t" in roles:
                ignored.append(header[roles["t"]])
            time_rank = key
            gps = is_gps
        elif role in roles:
            ignored.append(h)
            continue
        roles[role] = i
        fam = role if role in ("t", "tick") else role.split("_")[0]
        if unit is not None:
            if role in ("t", "tick"):
                hints[role] = unit
            else:
                hints.setdefault(fam, unit)
    return roles, hints, gps, ignored
