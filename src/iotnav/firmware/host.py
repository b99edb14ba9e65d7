"""Build the firmware's anchor KF for the host (``gcc``) and run it through :mod:`ctypes`.

:class:`AnchorFirmware` wraps one ``anchor_state``; :func:`run_beside` feeds the same samples
to a Python :class:`~iotnav.engines.anchor.AnchorEngine` and to the C library, the C filter
taking its attitude input (``C_nb`` and the tilt / yaw covariance traces) from the Python
engine's cascade after each IMU sample: the C library holds the paper's KF, not the attitude
filters (``firmware/README.md``).

Time stamps go to C as whole seconds plus a fraction, latitudes and longitudes as integer
1e-7 degrees plus the exact remainder (:func:`split_e7`), as a receiver gives them.
"""

from __future__ import annotations

import ctypes
import math
import os
import shutil
import subprocess
from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.engines.anchor import AnchorEngine, AnchorKFConfig
from iotnav.engines.base import GnssSample, ImuSample, Sample
from iotnav.firmware.gen import config_values, ctypes_config
from iotnav.techniques.cascade import CS_C

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "FIRMWARE_DIR",
    "WARN_FLAGS",
    "AnchorFirmware",
    "build",
    "replay_sanitized",
    "run_beside",
    "split_e7",
]

#: The C sources (repository root ``firmware/``).
FIRMWARE_DIR = Path(__file__).resolve().parents[3] / "firmware"
#: Warnings every build uses (issue 20).
WARN_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
SANITIZE_FLAGS = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer")

#: Return codes of anchor_step_gnss (anchor.h) and the Python engine's rejection reasons.
RC_OK, RC_INVALID, RC_NUM_SV_UNKNOWN, RC_NUM_SV = 0, 1, 2, 3
RC_UNSUPPORTED, RC_NUMERIC = -1, -2
REJECT_REASON = {RC_INVALID: "invalid", RC_NUM_SV_UNKNOWN: "num_sv_unknown", RC_NUM_SV: "num_sv"}


#: Per engine: the library source and the host replay driver (``firmware/``).
ENGINE_SOURCES = {"anchor": ("anchor.c", "host/replay.c"), "fixes": ("fixes.c", "host/replay_fixes.c")}


def build(
    out: Path,
    double: bool = False,
    sanitize: bool = False,
    src: Path = FIRMWARE_DIR,
    replay: bool = False,
    defines: tuple[str, ...] = (),
    engine: str = "anchor",
    opt: str = "-O2",
) -> Path:
    """Compile the engine's library (``src/anchor.c`` or ``src/fixes.c``) into the shared library
    ``out`` with :data:`WARN_FLAGS` (with ``replay``: the executable of its host replay driver,
    :data:`ENGINE_SOURCES`, instead).

    Parameters
    ----------
    out : Path
        Library to write.
    double : bool
        ``-DIOTNAV_REAL_DOUBLE`` (float64 build).
    sanitize : bool
        Add AddressSanitizer and UndefinedBehaviorSanitizer (load with ``libasan`` preloaded).
    src : Path
        Folder holding ``anchor.c`` and its headers.
    replay : bool
        Build the executable of ``host/replay.c``.
    defines : tuple of str
        Extra ``-D`` macros, e.g. ``("IOTNAV_REAL_DOUBLE",)``.
    engine : str
        ``anchor`` or ``fixes`` (:data:`ENGINE_SOURCES`).
    opt : str
        Optimisation flag (``-O0`` makes a sanitized build 4x cheaper to compile).

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    lib_c, replay_c = ENGINE_SOURCES[engine]
    args = [*WARN_FLAGS, opt, "-I", str(src)]
    args += [str(src / replay_c)] if replay else ["-fPIC", "-shared"]
    args += ["-DIOTNAV_REAL_DOUBLE"] if double else []
    args += list(SANITIZE_FLAGS) if sanitize else []
    args += [f"-D{d}" for d in defines]
    return run_gcc([*args, "-o", str(out), str(src / lib_c), "-lm"], out)


def run_gcc(args: list[str], out: Path) -> Path:
    """Run the host ``gcc`` with ``args`` (which write ``out``); ``out``.

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    gcc = shutil.which("gcc")
    if gcc is None:
        raise RuntimeError("gcc not found: the firmware host build needs it")
    cmd = [gcc, *args]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr}")
    return out


def replay_sanitized(exe: Path, stream: bytes, timeout: float = 120.0) -> bytes:
    """Run a sanitized replay program (:func:`build` with ``sanitize=True, replay=True``) on ``stream``;
    its standard output.

    Raises
    ------
    RuntimeError
        When it fails or AddressSanitizer / UndefinedBehaviorSanitizer report anything.
    """
    env = {
        **os.environ,
        "ASAN_OPTIONS": "detect_leaks=0",
        "UBSAN_OPTIONS": "halt_on_error=1:print_stacktrace=1",
    }
    p = subprocess.run([str(exe)], input=stream, capture_output=True, env=env, timeout=timeout, check=False)
    if p.returncode != 0 or b"runtime error" in p.stderr or b"Sanitizer" in p.stderr:
        raise RuntimeError(f"{exe} failed ({p.returncode}):\n{p.stderr[-3000:].decode(errors='replace')}")
    return p.stdout


#: GnssSample fields copied as they are into ``anchor_gnss_in`` (its member order after the fractions).
_GNSS_REALS = ("height_m", "h_acc_m", "v_acc_m", "hdop", "pdop", "vn", "ve", "vd", "speed_mps", "course_rad")


def split_e7(deg: float) -> tuple[int, float]:
    """``deg`` as integer 1e-7 degrees plus the remainder in 1e-7 degrees (computed exactly)."""
    v = Fraction(deg) * 10**7
    i = round(v)
    return int(i), float(v - i)


def _split_t(t: float) -> tuple[int, float]:
    """``t`` as whole seconds plus a fraction (s); ``(0, nan)`` for a time that is not finite."""
    if not math.isfinite(t):
        return 0, math.nan
    s = math.floor(t)
    return s, t - s


class AnchorFirmware:
    """One C ``anchor_state`` loaded from a host build (:func:`build`).

    Parameters
    ----------
    lib_path : Path
        The shared library.
    config : AnchorKFConfig
        KF tunables (passed through ``anchor_config``, laid out by :func:`~iotnav.firmware.gen.ctypes_config`).
    double : bool
        The library is the float64 build.
    record : bool
        Keep the bytes of every input and output struct in :attr:`inputs` and :attr:`outputs`
        (the stream ``firmware/host/replay.c`` reads and writes).
    """

    def __init__(
        self, lib_path: Path, config: AnchorKFConfig, double: bool = False, record: bool = False
    ) -> None:
        real = ctypes.c_double if double else ctypes.c_float
        self.lib = lib = ctypes.CDLL(str(lib_path))

        class Time(ctypes.Structure):
            _fields_ = [("s", ctypes.c_int32), ("frac", real)]

        class ImuIn(ctypes.Structure):
            _fields_ = [
                ("t", Time),
                ("f_b", real * 3),
                ("C_nb", real * 9),
                ("tilt_p_trace", real),
                ("yaw_p_trace", real),
            ]

        gnss_fields: list[tuple[str, Any]] = [
            ("t", Time),
            ("valid", ctypes.c_int32),
            ("num_sv", ctypes.c_int32),
        ]
        gnss_fields += [("lat_e7", ctypes.c_int32), ("lon_e7", ctypes.c_int32)]
        gnss_fields += [(n, real) for n in ("lat_frac_e7", "lon_frac_e7", *_GNSS_REALS)]
        gnss_fields += [("course_valid", ctypes.c_int32), ("s_acc_mps", real)]

        class GnssIn(ctypes.Structure):
            _fields_ = gnss_fields

        class Out(ctypes.Structure):
            _fields_ = [
                ("has_position", ctypes.c_int32),
                ("source", ctypes.c_int32),
                ("r_n", real * 3),
                ("v_n", real * 3),
                ("std_north", real),
                ("std_east", real),
                ("lat_e7", ctypes.c_int32),
                ("lon_e7", ctypes.c_int32),
                ("lat_frac_e7", real),
                ("lon_frac_e7", real),
                ("height_m", real),
            ]

        Cfg = ctypes_config(real)
        lib.anchor_sizeof.restype = ctypes.c_int32
        lib.anchor_sizeof.argtypes = [ctypes.c_int32]
        for which, cls in ((1, Cfg), (2, ImuIn), (3, GnssIn), (4, Out)):
            if lib.anchor_sizeof(which) != ctypes.sizeof(cls):
                raise RuntimeError(f"{lib_path}: struct {cls.__name__} layout differs from the C header")
        self._state = ctypes.create_string_buffer(lib.anchor_sizeof(0))
        self._imu, self._gnss, self._out = ImuIn(), GnssIn(), Out()
        for fn in ("anchor_init", "anchor_step_imu", "anchor_step_gnss"):
            getattr(lib, fn).restype = ctypes.c_int
        lib.anchor_output.restype = None
        self._cfg = Cfg(*config_values(config))
        self.record = record
        self.inputs: list[bytes] = [bytes(self._cfg)]
        self.outputs: list[bytes] = []
        self.init_rc = int(lib.anchor_init(self._state, ctypes.byref(self._cfg)))

    def step_imu(
        self, t: float, f_b: FloatArray, C_nb: FloatArray, tilt_p_trace: float, yaw_p_trace: float
    ) -> int:
        """One IMU sample (``anchor_step_imu``): time s, specific force m/s^2, ``C_nb`` row-major, rad^2."""
        m = self._imu
        m.t.s, m.t.frac = _split_t(t)
        m.f_b[:] = [float(v) for v in f_b]
        m.C_nb[:] = [float(v) for v in np.asarray(C_nb).reshape(9)]
        m.tilt_p_trace, m.yaw_p_trace = tilt_p_trace, yaw_p_trace
        if self.record:
            self.inputs.append(b"I" + bytes(m))
        return int(self.lib.anchor_step_imu(self._state, ctypes.byref(m)))

    def step_gnss(self, s: GnssSample) -> int:
        """One GNSS epoch (``anchor_step_gnss``); the return code of anchor.h."""
        m = self._gnss
        m.t.s, m.t.frac = _split_t(s.t)
        m.valid = int(bool(s.valid) and math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg))
        m.num_sv = int(s.num_sv)
        if m.valid:
            m.lat_e7, m.lat_frac_e7 = split_e7(s.lat_deg)
            m.lon_e7, m.lon_frac_e7 = split_e7(s.lon_deg)
        for name in _GNSS_REALS:
            setattr(m, name, float(getattr(s, name)))
        m.course_valid = int(bool(s.course_valid))
        m.s_acc_mps = float(s.s_acc_mps)
        rc = int(self.lib.anchor_step_gnss(self._state, ctypes.byref(m)))
        if self.record:
            self.inputs.append(b"G" + bytes(m))
            self.outputs.append(rc.to_bytes(4, "little", signed=True))
        return rc

    def output(self) -> dict[str, Any]:
        """``anchor_output``: ``has_position``, ``source``, ``r_n``, ``v_n`` (m, m/s), ``std_north``, ``std_east`` (m),
        ``lat_deg``, ``lon_deg``, ``height_m``."""
        o = self._out
        self.lib.anchor_output(self._state, ctypes.byref(o))
        if self.record:
            self.outputs.append(bytes(o))
        return {
            "has_position": bool(o.has_position),
            "source": int(o.source),
            "r_n": np.array(o.r_n[:], float),
            "v_n": np.array(o.v_n[:], float),
            "std_north": float(o.std_north),
            "std_east": float(o.std_east),
            "lat_deg": (o.lat_e7 + float(o.lat_frac_e7)) * 1e-7,
            "lon_deg": (o.lon_e7 + float(o.lon_frac_e7)) * 1e-7,
            "height_m": float(o.height_m),
        }


def run_beside(engine: AnchorEngine, fw: AnchorFirmware, samples: Iterable[Sample]) -> dict[str, Any]:
    """Feed ``samples`` to the Python ``engine`` and to ``fw``; the two tracks side by side.

    Returns
    -------
    dict
        ``t`` (IMU times, s), ``py`` and ``c`` (N, 6) ``[north, east, down, vn, ve, vd]``
        where both have a position, ``py_std``/``c_std`` (N, 2), ``py_ll``/``c_ll`` (N, 3)
        latitude, longitude (degrees) and height (m), ``py_source``/``c_source``,
        ``py_has``/``c_has`` (bool per IMU sample), ``gnss_rc`` (C return codes per epoch) and
        ``gnss_py`` (the Python decision per epoch: ``ok`` or the rejection reason).
    """
    casc = engine.cascade
    t_l: list[float] = []
    rows: dict[str, list[Any]] = {
        k: [] for k in ("py", "c", "py_std", "c_std", "py_ll", "c_ll", "py_src", "c_src", "py_has", "c_has")
    }
    gnss_rc: list[int] = []
    gnss_py: list[str] = []
    for s in samples:
        n_ev = len(engine.events)
        out = engine.step(s)
        if isinstance(s, ImuSample):
            C = casc.state[CS_C : CS_C + 9]
            tilt_tr = float(casc.tilt.state[3] + casc.tilt.state[7] + casc.tilt.state[11])
            yaw_tr = float(casc.yaw.state[3] + casc.yaw.state[7] + casc.yaw.state[11])
            fw.step_imu(s.t, s.acc_b, C, tilt_tr, yaw_tr)
            o = fw.output()
            assert out is not None
            t_l.append(s.t)
            rows["py"].append([out.north, out.east, out.down, out.vn, out.ve, out.vd])
            rows["c"].append([*o["r_n"], *o["v_n"]])
            rows["py_std"].append([out.std_north, out.std_east])
            rows["c_std"].append([o["std_north"], o["std_east"]])
            rows["py_ll"].append([out.lat, out.lon, out.height])
            rows["c_ll"].append([o["lat_deg"], o["lon_deg"], o["height_m"]])
            rows["py_src"].append(out.source)
            rows["c_src"].append(o["source"])
            rows["py_has"].append(bool(np.isfinite(out.north)))
            rows["c_has"].append(o["has_position"])
        elif isinstance(s, GnssSample):
            gnss_rc.append(fw.step_gnss(s))
            rej = [e for e in engine.events[n_ev:] if e["type"] == "fix_rejected"]
            gnss_py.append(str(rej[0]["reason"]) if rej else "ok")
    res: dict[str, Any] = {k: np.array(v) for k, v in rows.items()}
    res["t"] = np.array(t_l)
    res["gnss_rc"] = np.array(gnss_rc, int)
    res["gnss_py"] = gnss_py
    return res
