"""The firmware's GNSS-only engine (``firmware/fixes.c``) on the host through :mod:`ctypes`, beside Python.

:class:`FixesFirmware` wraps one ``fixes_state`` of a host build (:func:`iotnav.firmware.host.build`
with ``engine="fixes"``); :func:`run_beside` feeds the same samples to a
:class:`~iotnav.engines.fixes.FixesEngine` (its streaming ``step()``) and to the C library and
returns, per GNSS epoch, both decisions (row or skip reason), both event lists and both rows.
Times go to C as whole seconds plus a fraction, coordinates as integer 1e-7 degrees plus the
exact remainder (:func:`~iotnav.firmware.host.split_e7`), as a receiver gives them.
"""

from __future__ import annotations

import ctypes
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from iotnav.engines import fixes_kernel as fk
from iotnav.engines.base import SOURCES, GnssSample, ImuSample, Sample
from iotnav.engines.fixes import _EVENT_NAMES, FixesConfig, FixesEngine
from iotnav.firmware.gen import fixes_ctypes_config, fixes_values
from iotnav.firmware.host import _split_t, split_e7

__all__ = [
    "EVENT_ORDER",
    "IMU_REASONS",
    "REASONS",
    "FixesFirmware",
    "c_events",
    "decode",
    "decode_stream",
    "gnss_samples",
    "python_events",
    "run_beside",
    "with_faults",
]

#: Skip reason of each ``fixes_step_gnss`` return code (``FIXES_R_*``; 0 a row).
REASONS: tuple[str, ...] = (*fk.REASONS, "gnss_nonfinite")
#: Guard reason of each ``fixes_step_imu`` return code (0 used).
IMU_REASONS = ("", "imu_nonfinite", "imu_time_backwards", "imu_gap")
#: Event bits and names in the order the Python engine appends them (the boot's ``first_fix``
#: first, then the kernel's in :data:`iotnav.engines.fixes._EVENT_NAMES` order).
EV_FIRST_FIX = 2 * max(b for b, _ in _EVENT_NAMES)
EVENT_ORDER: tuple[tuple[int, str], ...] = ((EV_FIRST_FIX, "first_fix"), *_EVENT_NAMES)
#: The value each event carries (``event_value``), as the Python engine names it.
_EVENT_VALUE = {
    "fix_rejected": "nis",
    "relocated": "jump_m",
    "reinitialised": "jump_m",
    "fixes_retracted": "nis_at_snapshot",
    "clock_reset": "offset_change_s",
}


def _flag(x: float) -> int:
    """A device flag (1, 0) as int32; NaN or anything else is -1 (unknown, as the kernel reads it)."""
    return int(x) if x in (0, 1) else -1


class FixesFirmware:
    """One C ``fixes_state`` loaded from a host build.

    Parameters
    ----------
    lib_path : Path
        The shared library (``host.build(..., engine="fixes")``).
    config : FixesConfig
        The engine's configuration (passed as the parameter vector of :func:`~iotnav.firmware.gen.fixes_values`).
    double : bool
        The library is the float64 build.
    record : bool
        Keep the bytes of every input and output in :attr:`inputs` / :attr:`outputs` (the stream
        ``firmware/host/replay_fixes.c`` reads and writes).
    """

    def __init__(
        self, lib_path: Path, config: FixesConfig | None = None, double: bool = False, record: bool = False
    ) -> None:
        real = ctypes.c_float if not double else ctypes.c_double
        i32 = ctypes.c_int32
        self.lib = lib = ctypes.CDLL(str(lib_path))

        class Time(ctypes.Structure):
            _fields_ = [("s", i32), ("frac", real)]

        class GnssIn(ctypes.Structure):
            _fields_ = [
                ("t", Time),
                ("utc", Time),
                *[(n, i32) for n in ("has_utc", "valid", "num_sv", "course_valid", "motion", "ignition")],
                ("lat_e7", i32),
                ("lon_e7", i32),
                *[(n, real) for n in ("lat_frac_e7", "lon_frac_e7", "height_m", "h_acc_m", "v_acc_m")],
                *[
                    (n, real)
                    for n in ("hdop", "pdop", "speed_mps", "course_rad", "vn", "ve", "vd", "s_acc_mps")
                ],
            ]

        class Out(ctypes.Structure):
            _fields_ = [
                ("events", i32),
                ("event_value", real),
                ("source", i32),
                ("is_static", i32),
                ("has_down", i32),
                ("r_n", real * 3),
                ("v_n", real * 3),
                ("std_north", real),
                ("std_east", real),
                ("lat_e7", i32),
                ("lon_e7", i32),
                ("lat_frac_e7", real),
                ("lon_frac_e7", real),
                ("height_m", real),
            ]

        class ImuRec(ctypes.Structure):
            _fields_ = [("t", Time), ("f_b", real * 3), ("w_b", real * 3)]

        Cfg = fixes_ctypes_config(real)
        lib.fixes_sizeof.restype = ctypes.c_int32
        lib.fixes_sizeof.argtypes = [ctypes.c_int32]
        for which, cls in ((1, Cfg), (2, GnssIn), (3, Out)):
            if lib.fixes_sizeof(which) != ctypes.sizeof(cls):
                raise RuntimeError(f"{lib_path}: struct {cls.__name__} layout differs from the C header")
        for fn in ("fixes_init", "fixes_step_imu", "fixes_step_gnss"):
            getattr(lib, fn).restype = ctypes.c_int
        lib.fixes_step_imu.argtypes = [ctypes.c_void_p, Time, ctypes.c_void_p, ctypes.c_void_p]
        self._state = ctypes.create_string_buffer(lib.fixes_sizeof(0))
        self._gnss, self._out, self._imu = GnssIn(), Out(), ImuRec()
        self._cfg = Cfg(*fixes_values(config or FixesConfig()))
        self.record = record
        self.inputs: list[bytes] = [bytes(self._cfg)]
        self.outputs: list[bytes] = []
        self.init_rc = int(lib.fixes_init(self._state, ctypes.byref(self._cfg)))

    def step_imu(self, s: ImuSample) -> int:
        """One IMU sample (``fixes_step_imu``); the return code (:data:`IMU_REASONS`)."""
        m = self._imu
        m.t.s, m.t.frac = _split_t(s.t)
        m.f_b[:] = [float(v) for v in s.acc_b]
        m.w_b[:] = [float(v) for v in s.gyro_b]
        rc = int(self.lib.fixes_step_imu(self._state, m.t, ctypes.byref(m.f_b), ctypes.byref(m.w_b)))
        if self.record:
            self.inputs.append(b"I" + bytes(m))
            self.outputs.append(rc.to_bytes(4, "little", signed=True))
        return rc

    def step_gnss(self, s: GnssSample) -> tuple[int, dict[str, Any]]:
        """One GNSS epoch (``fixes_step_gnss``): the return code (:data:`REASONS`) and the output."""
        m = self._gnss
        m.t.s, m.t.frac = _split_t(s.t)
        m.has_utc = int(math.isfinite(s.utc))
        m.utc.s, m.utc.frac = _split_t(s.utc)
        m.valid = int(bool(s.valid))
        m.num_sv = int(s.num_sv) if math.isfinite(s.num_sv) else -1
        m.course_valid = int(bool(s.course_valid))
        m.motion, m.ignition = _flag(s.motion), _flag(s.ignition)
        for ax in ("lat", "lon"):
            deg = float(getattr(s, ax + "_deg"))
            e7, frac = split_e7(deg) if math.isfinite(deg) else (0, math.nan)
            setattr(m, ax + "_e7", e7)
            setattr(m, ax + "_frac_e7", frac)
        for name in ("height_m", "h_acc_m", "v_acc_m", "hdop", "pdop", "speed_mps", "course_rad"):
            setattr(m, name, float(getattr(s, name)))
        for name in ("vn", "ve", "vd", "s_acc_mps"):
            setattr(m, name, float(getattr(s, name)))
        o = self._out
        rc = int(self.lib.fixes_step_gnss(self._state, ctypes.byref(m), ctypes.byref(o)))
        if self.record:
            self.inputs.append(b"G" + bytes(m))
            self.outputs.append(rc.to_bytes(4, "little", signed=True) + bytes(o))
        return rc, decode(o)


def decode(o: Any) -> dict[str, Any]:
    """A ``fixes_output_t`` (ctypes structure or numpy record) as a dict: ``events`` (names in
    :data:`EVENT_ORDER`), ``event_value``, ``source`` (name), ``static``, ``ned`` and ``vel``
    (m, m/s; down and vd NaN without a height), ``std`` (north, east, m), ``lat``, ``lon`` (deg), ``height`` (m)."""
    bits = int(o["events"] if isinstance(o, np.void) else o.events)

    def get(name: str) -> Any:
        return o[name] if isinstance(o, np.void) else getattr(o, name)

    return {
        "events": [name for bit, name in EVENT_ORDER if bits & bit],
        "event_value": float(get("event_value")),
        "source": SOURCES[int(get("source"))],
        "static": bool(get("is_static")),
        "ned": np.array(get("r_n")[:], float),
        "vel": np.array(get("v_n")[:], float),
        "std": np.array([float(get("std_north")), float(get("std_east"))]),
        "lat": (int(get("lat_e7")) + float(get("lat_frac_e7"))) * 1e-7,
        "lon": (int(get("lon_e7")) + float(get("lon_frac_e7"))) * 1e-7,
        "height": float(get("height_m")),
    }


def c_events(o: dict[str, Any]) -> list[tuple[str, float]]:
    """``(type, value)`` of a decoded C output's events, valued as the Python engine reports them
    (a rejection that re-initialised carries no NIS: the kernel's one value is then the jump)."""
    reset = "relocated" in o["events"] or "reinitialised" in o["events"]
    return [
        (n, o["event_value"] if n in _EVENT_VALUE and not (reset and n == "fix_rejected") else math.nan)
        for n in o["events"]
    ]


def _new_skip(engine: FixesEngine, before: dict[str, int]) -> str:
    """The guard reason whose count this step raised ('' for none)."""
    for k, v in engine.guard.skipped.items():
        if v > before.get(k, 0):
            return k
    return ""


def python_events(events: list[dict[str, Any]]) -> list[tuple[str, float]]:
    """``(type, value)`` of a step's engine events, the guard's ``input_skipped`` left out (C returns the reason)."""
    out = []
    for e in events:
        if e["type"] == "input_skipped":
            continue
        v = e.get(_EVENT_VALUE.get(e["type"], ""), math.nan)
        out.append((str(e["type"]), math.nan if v is None else float(v)))
    return out


def run_beside(engine: FixesEngine, fw: FixesFirmware, samples: Iterable[Sample]) -> dict[str, Any]:
    """Feed ``samples`` to the Python ``engine`` (``step()``) and to ``fw``; both outcomes per epoch.

    Returns
    -------
    dict
        Per GNSS epoch: ``t``; ``py_skip`` / ``c_skip`` (reason, '' for a row); ``py_events`` /
        ``c_events`` (lists of ``(type, value)``); for the epochs with a row in both, ``row_t``,
        ``py`` / ``c`` ``(n, 11)`` ``[north, east, down, vn, ve, vd, std_north, std_east, lat,
        lon, height]``, ``py_source`` / ``c_source``, ``py_static`` / ``c_static``. Per IMU
        sample: ``imu_py`` / ``imu_c`` (guard reason, '' used).
    """
    res: dict[str, list[Any]] = {
        k: []
        for k in (
            "t",
            "py_skip",
            "c_skip",
            "py_events",
            "c_events",
            "row_t",
            "py",
            "c",
            "py_source",
            "c_source",
            "py_static",
            "c_static",
            "imu_py",
            "imu_c",
        )
    }
    for s in samples:
        n_ev = len(engine.events)
        before = dict(engine.guard.skipped)
        out = engine.step(s)
        if isinstance(s, ImuSample):
            res["imu_c"].append(IMU_REASONS[fw.step_imu(s)])
            res["imu_py"].append(_new_skip(engine, before))
            continue
        if not isinstance(s, GnssSample):
            continue
        rc, o = fw.step_gnss(s)
        res["t"].append(s.t)
        res["py_skip"].append("" if out is not None else _new_skip(engine, before) or "?")
        res["c_skip"].append(REASONS[rc] if rc > 0 else ("" if rc == 0 else f"error {rc}"))
        res["py_events"].append(python_events(engine.events[n_ev:]))
        res["c_events"].append(c_events(o))
        if out is not None and rc == 0:
            res["row_t"].append(s.t)
            res["py"].append([*out[4:10], out.std_north, out.std_east, out.lat, out.lon, out.height])
            res["c"].append([*o["ned"], *o["vel"], *o["std"], o["lat"], o["lon"], o["height"]])
            res["py_source"].append(out.source)
            res["c_source"].append(o["source"])
            res["py_static"].append(bool(out.static))
            res["c_static"].append(o["static"])
    return {k: np.array(v) if k in ("py", "c", "row_t", "t") else v for k, v in res.items()}


def gnss_samples(gnss: Any) -> Iterable[GnssSample]:
    """The rows of a GNSS table (:data:`iotnav.io.schema.GNSS_COLUMNS`) as samples in row order,
    nothing dropped or sorted (:func:`~iotnav.engines.base.iter_samples` sorts by time and drops
    non-finite epochs: bad input is fed here as it is)."""
    fields = GnssSample._fields
    cols = {f: gnss[f].to_numpy() for f in fields if f in gnss}
    for k in range(len(gnss)):
        vals: dict[str, Any] = {}
        for f, c in cols.items():
            v = c[k]
            if f in ("course_valid", "valid"):
                vals[f] = bool(v)
            elif f in ("num_sv", "quality", "motion", "ignition"):
                vals[f] = int(v) if np.isfinite(v) else -1
            else:
                vals[f] = float(v)
        yield GnssSample(**vals)


def decode_stream(
    inputs: list[bytes], outputs: bytes, double: bool = False
) -> list[tuple[int, dict[str, Any] | None]]:
    """Split a replay's output stream (``replay_fixes.c``, host or board) by the input records:
    per record ``(return code, decoded output)`` (the output ``None`` for an IMU record).

    Raises
    ------
    ValueError
        When ``outputs`` does not hold exactly one result per record.
    """
    real = "<f8" if double else "<f4"
    dt = np.dtype(
        [
            ("events", "<i4"),
            ("event_value", real),
            ("source", "<i4"),
            ("is_static", "<i4"),
            ("has_down", "<i4"),
            ("r_n", real, 3),
            ("v_n", real, 3),
            ("std_north", real),
            ("std_east", real),
            ("lat_e7", "<i4"),
            ("lon_e7", "<i4"),
            ("lat_frac_e7", real),
            ("lon_frac_e7", real),
            ("height_m", real),
        ],
        align=True,
    )
    out: list[tuple[int, dict[str, Any] | None]] = []
    pos = 0
    for rec in inputs[1:]:
        if pos + 4 > len(outputs):
            raise ValueError(f"{len(outputs)} output bytes end before the record {len(out)}")
        rc = int.from_bytes(outputs[pos : pos + 4], "little", signed=True)
        pos += 4
        if rec[:1] == b"G":
            if pos + dt.itemsize > len(outputs):
                raise ValueError(f"{len(outputs)} output bytes end inside the output of record {len(out)}")
            out.append((rc, decode(np.frombuffer(outputs, dt, 1, pos)[0])))
            pos += dt.itemsize
        else:
            out.append((rc, None))
    if pos != len(outputs):
        raise ValueError(f"{len(outputs) - pos} output bytes left after the last record")
    return out


def with_faults(g: pd.DataFrame) -> pd.DataFrame:
    """A test stream: the 1 Hz fixes ``g`` (at least 1110 rows) without velocity, with every kind
    of bad epoch inserted (rows 300-370: duplicate, same time, backwards, invalid, (0, 0), PDOP 25,
    NaN time, NaN latitude), a 400 m relocation of 12 fixes (rows 700-711), 35 scattered 150-300 m
    jumps (rows 900-934, seeded) and a UTC jump of 2 h over 10 epochs (rows 1100-1109)."""
    g = g.copy().reset_index(drop=True)
    for c in ("speed_mps", "course_rad", "vn", "ve", "vd", "s_acc_mps"):
        g[c] = np.nan
    g["course_valid"] = False
    rng = np.random.default_rng(0)
    m_lat = 1.0 / 111_132.0
    m_lon = 1.0 / (111_320.0 * math.cos(math.radians(float(g.lat_deg.iloc[0]))))
    rows: list[dict[str, Any]] = []
    for k, rec in enumerate(g.to_dict("records")):
        r: dict[str, Any] = {str(c): v for c, v in rec.items()}
        if 700 <= k < 712:
            r["lat_deg"] += 400.0 * m_lat
        if 900 <= k < 935:
            a, s = rng.uniform(0, 2 * np.pi), rng.uniform(150.0, 300.0)
            r["lat_deg"] += s * math.cos(a) * m_lat
            r["lon_deg"] += s * math.sin(a) * m_lon
        if 1100 <= k < 1110:
            r["utc"] += 7200.0
        rows.append(r)
        t = float(r["t"])
        bad: dict[str, Any] | None = {
            300: {},  # duplicate
            310: {"lat_deg": r["lat_deg"] + 1e-5},  # same time, other coordinates
            320: {"t": t - 5.0},  # backwards
            330: {"t": t + 0.5, "valid": False},
            340: {"t": t + 0.5, "lat_deg": 0.0, "lon_deg": 0.0},
            350: {"t": t + 0.5, "pdop": 25.0},
            360: {"t": math.nan},
            370: {"t": t + 0.5, "lat_deg": math.nan},
        }.get(k)
        if bad is not None:
            rows.append({**r, **bad})
    return pd.DataFrame(rows, columns=g.columns)
