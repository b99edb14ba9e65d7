"""The Forno et al. 2020 pipeline in C (``firmware/pipeline_*.c``): blocks 1 to 4 so far.

What is ported (issue 20, "the Forno pipeline in C"): block 1, the last known position's fix
acceptance, settling gate, "moved while off" test and save timing
(:mod:`iotnav.techniques.last_position`, ``firmware/pipeline_lastpos.c``; the store itself is
the caller's), block 2's gyro-bias, tilt and yaw filters (:mod:`iotnav.techniques.gyro_bias_kf`,
:mod:`iotnav.techniques.tilt_kf`, :mod:`iotnav.techniques.yaw_kf`; ``firmware/pipeline_gyrobias.c``,
``pipeline_tilt.c``, ``pipeline_yaw.c``) and their cascade with the per-sample front end of blocks
2 and 3 (:mod:`iotnav.techniques.cascade`, ``firmware/pipeline_cascade.c``), block
3, the static case determination (:mod:`iotnav.techniques.static`, ``firmware/pipeline_static.c``),
and block 4, the three-level low-pass GPS filter (:mod:`iotnav.techniques.lowpass3`,
``firmware/pipeline_lowpass3.c``), each with an ``init`` / ``step`` API on a fixed-size state
struct. Blocks 5 and 6: :mod:`iotnav.firmware.pipeline_mount`, :mod:`~iotnav.firmware.pipeline_blocks56`;
the pipeline's wiring (:class:`~iotnav.engines.pipeline.Pipeline`) as one C engine:
:mod:`iotnav.firmware.pipeline_engine` (``firmware/pipeline.c``).

The configuration header ``firmware/pipeline_config.h`` is generated here from the Python
dataclasses (:class:`~iotnav.techniques.static.StaticConfig`,
:class:`~iotnav.techniques.lowpass3.Lowpass3Config`,
:class:`~iotnav.techniques.last_position.LastPositionConfig`,
:class:`~iotnav.techniques.gyro_bias_kf.GyroBiasConfig`,
:class:`~iotnav.techniques.tilt_kf.TiltConfig`, :class:`~iotnav.techniques.yaw_kf.YawConfig`;
with the yaw filter's NIS gate as ``PL_YAW_GATE_NIS``, :func:`yaw_gate`): one C member per field, in declaration order
(``int`` / ``bool`` -> ``int32_t``, ``float`` -> ``IOTNAV_REAL``), their defaults as
``PL_<BLOCK>_CONFIG_DEFAULTS``; a test checks the checked-in header against a fresh
:func:`config_header`, and :func:`ctypes_struct` builds the matching :mod:`ctypes` structures
from the same field lists. :class:`StaticBlock`, :class:`Lowpass3Block`,
and :class:`LastPositionBlock` run blocks 1, 3 and 4 through :mod:`ctypes` (host build,
:func:`build`); block 2's bindings are in :mod:`iotnav.firmware.pipeline_kf3`.
"""

from __future__ import annotations

import ctypes
import math
import struct
import typing
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.firmware.config_header import c_fields, c_literal, config_struct
from iotnav.firmware.host import FIRMWARE_DIR, SANITIZE_FLAGS, WARN_FLAGS, run_gcc
from iotnav.techniques.gyro_bias_kf import GyroBiasConfig
from iotnav.techniques.last_position import LastPositionConfig
from iotnav.techniques.lowpass3 import Lowpass3Config
from iotnav.techniques.static import StaticConfig
from iotnav.techniques.tilt_kf import TiltConfig
from iotnav.techniques.yaw_kf import YawConfig

if typing.TYPE_CHECKING:
    pass

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "FIX_REASONS",
    "HEADER_NAME",
    "LASTPOS_HIST_MAX",
    "LOWPASS3_N_MAX",
    "SOURCES",
    "STATIC_SPEED_WINDOW_MAX",
    "LastPositionBlock",
    "Lowpass3Block",
    "StaticBlock",
    "build",
    "build_replay",
    "config_header",
    "ctypes_struct",
    "yaw_gate",
]

HEADER_NAME = "pipeline_config.h"
#: The C sources of the ported blocks (``firmware/``).
SOURCES = (
    "pipeline_static.c",
    "pipeline_lowpass3.c",
    "pipeline_lastpos.c",
    "pipeline_gyrobias.c",
    "pipeline_tilt.c",
    "pipeline_yaw.c",
    "pipeline_cascade.c",
)
#: Fixed sizes of the C state: the longest GPS-speed moving average and low-pass level (the
#: Python buffers follow the configuration; ``*_init`` refuses larger ones).
STATIC_SPEED_WINDOW_MAX = 16
LOWPASS3_N_MAX = 16
#: The settling gate's (t, PDOP) history of block 1 (Python keeps all within ``settle_window_s``;
#: C drops the oldest beyond this and counts it): 64 = the 10 s default window at up to 6 Hz.
LASTPOS_HIST_MAX = 64

#: Per block: the C type prefix and the Python dataclass it is generated from.
_BLOCKS: dict[str, type] = {
    "pl_static": StaticConfig,
    "pl_lowpass3": Lowpass3Config,
    "pl_lastpos": LastPositionConfig,
    "pl_gyrobias": GyroBiasConfig,
    "pl_tilt": TiltConfig,
    "pl_yaw": YawConfig,
}


def config_header(
    static: StaticConfig | None = None,
    lowpass3: Lowpass3Config | None = None,
    last_position: LastPositionConfig | None = None,
    gyro_bias: GyroBiasConfig | None = None,
    tilt: TiltConfig | None = None,
    yaw: YawConfig | None = None,
) -> str:
    """Text of ``pipeline_config.h`` with ``static``, ``lowpass3``, ``last_position``, ``gyro_bias``,
    ``tilt`` and ``yaw`` (defaults: the dataclasses') as defaults, and ``yaw``'s NIS gate."""
    cfgs: dict[str, Any] = {
        "pl_static": static or StaticConfig(),
        "pl_lowpass3": lowpass3 or Lowpass3Config(),
        "pl_lastpos": last_position or LastPositionConfig(),
        "pl_gyrobias": gyro_bias or GyroBiasConfig(),
        "pl_tilt": tilt or TiltConfig(),
        "pl_yaw": yaw or YawConfig(),
    }
    out = [
        "/* Generated by iotnav.firmware.pipeline from iotnav.techniques.static.StaticConfig,",
        " * iotnav.techniques.lowpass3.Lowpass3Config, iotnav.techniques.last_position.LastPositionConfig and",
        " * iotnav.techniques.gyro_bias_kf.GyroBiasConfig, iotnav.techniques.tilt_kf.TiltConfig and",
        " * iotnav.techniques.yaw_kf.YawConfig.",
        " * Do not edit: tests check it against a fresh generation (iotnav.firmware.pipeline.config_header). */",
        "#ifndef IOTNAV_PIPELINE_CONFIG_H",
        "#define IOTNAV_PIPELINE_CONFIG_H",
        "",
        '#include "iotnav_real.h"',
        "",
        "/* Fixed sizes of the C state (the *_init functions refuse larger configurations). */",
        f"#define PL_STATIC_SPEED_WINDOW_MAX {STATIC_SPEED_WINDOW_MAX}",
        f"#define PL_LOWPASS3_N_MAX {LOWPASS3_N_MAX}",
        f"#define PL_LASTPOS_HIST_MAX {LASTPOS_HIST_MAX}",
    ]
    for prefix, cls in _BLOCKS.items():
        fields = c_fields(cls)
        out += config_struct(prefix, cls, fields, [c_literal(getattr(cfgs[prefix], n), k) for n, k in fields])
    out += [
        "",
        "/* The yaw filter's NIS gate: the chi-square quantile (3 dof) of gate_probability, for",
        " * pl_yaw_init (0: no gate; iotnav.kalman.gate_threshold). */",
        f"#define PL_YAW_GATE_NIS {c_literal(yaw_gate(cfgs['pl_yaw']), 'real')}",
        "",
        "#endif",
        "",
    ]
    return "\n".join(out)


def yaw_gate(cfg: YawConfig) -> float:
    """The ``gate_nis`` argument of ``pl_yaw_init``: :func:`iotnav.kalman.gate_threshold` (3 dof)
    of ``cfg.gate_probability``, or 0.0 when it is not positive (no gate, as :class:`YawKF`)."""
    from iotnav import kalman

    return kalman.gate_threshold(3, cfg.gate_probability) if cfg.gate_probability > 0.0 else 0.0


def ctypes_struct(prefix: str, real: Any = ctypes.c_float) -> type[ctypes.Structure]:
    """A :class:`ctypes.Structure` laid out as ``<prefix>_config`` (``pl_static``, ``pl_lowpass3``, ``pl_lastpos``, ``pl_gyrobias``, ``pl_tilt`` or ``pl_yaw``)."""
    members = [(n, ctypes.c_int32 if k == "int" else real) for n, k in c_fields(_BLOCKS[prefix])]
    return type(f"{prefix}_config", (ctypes.Structure,), {"_fields_": members})


def build(
    out: Path,
    double: bool = False,
    sanitize: bool = False,
    src: Path = FIRMWARE_DIR,
    sources: tuple[str, ...] = SOURCES,
) -> Path:
    """Compile the ported blocks (``sources``, :data:`SOURCES` by default) into the shared library ``out``.

    ``gcc`` with :data:`~iotnav.firmware.host.WARN_FLAGS` and ``-O2``; ``double``: the float64
    build (``-DIOTNAV_REAL_DOUBLE``); ``sanitize``: AddressSanitizer + UndefinedBehaviorSanitizer
    (the library must then be loaded into a process with ``libasan`` preloaded).

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    args = [*WARN_FLAGS, "-O2", "-fPIC", "-shared", "-I", str(src)]
    args += ["-DIOTNAV_REAL_DOUBLE"] if double else []
    args += list(SANITIZE_FLAGS) if sanitize else []
    return run_gcc([*args, "-o", str(out), *(str(src / s) for s in sources), "-lm"], out)


def _time_type(real: Any) -> type[ctypes.Structure]:
    return type("iotnav_time", (ctypes.Structure,), {"_fields_": [("s", ctypes.c_int32), ("frac", real)]})


def _split_time(t: float) -> tuple[int, float]:
    """Device time ``t`` (s) as whole seconds and the fraction (the firmware's ``iotnav_time``)."""
    s = math.floor(t)
    return int(s), t - s


def build_replay(out: Path, sanitize: bool = True, src: Path = FIRMWARE_DIR) -> Path:
    """Compile ``host/replay_pipeline.c`` with the blocks (float32; ``sanitize``: with
    AddressSanitizer + UndefinedBehaviorSanitizer, ``-O0``) into the executable ``out``.

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    args = [
        *WARN_FLAGS,
        "-O0" if sanitize else "-O2",
        "-I",
        str(src),
        str(src / "host" / "replay_pipeline.c"),
    ]
    args += list(SANITIZE_FLAGS) if sanitize else []
    return run_gcc([*args, "-o", str(out), *(str(src / s) for s in SOURCES), "-lm"], out)


def replay_config(
    static: StaticConfig,
    lowpass3: Lowpass3Config,
    last_position: LastPositionConfig | None = None,
    stored: tuple[float, float] | None = None,
    gyro_bias: GyroBiasConfig | None = None,
    b0: tuple[float, float, float] = (0.0, 0.0, 0.0),
    tilt: TiltConfig | None = None,
    yaw: YawConfig | None = None,
) -> bytes:
    """The float32 configurations as ``host/replay_pipeline.c`` reads them first: blocks 3 and 4,
    block 1 (with the stored position, degrees, or None), the gyro-bias KF (with ``b0``, rad/s),
    the tilt KF, the yaw KF (with its gate, :func:`yaw_gate`)."""
    lp, gb = last_position or LastPositionConfig(), gyro_bias or GyroBiasConfig()
    out = b""
    for prefix, cfg in (("pl_static", static), ("pl_lowpass3", lowpass3), ("pl_lastpos", lp)):
        out += bytes(ctypes_struct(prefix)(*(getattr(cfg, n) for n, _ in c_fields(type(cfg)))))
    out += struct.pack("<iff", stored is not None, *(stored if stored is not None else (math.nan, math.nan)))
    out += bytes(ctypes_struct("pl_gyrobias")(*(getattr(gb, n) for n, _ in c_fields(GyroBiasConfig))))
    tc = tilt or TiltConfig()
    out += struct.pack("<3f", *b0)
    out += bytes(ctypes_struct("pl_tilt")(*(getattr(tc, n) for n, _ in c_fields(TiltConfig))))
    yc = yaw or YawConfig()
    out += bytes(ctypes_struct("pl_yaw")(*(getattr(yc, n) for n, _ in c_fields(YawConfig))))
    return out + struct.pack("<f", yaw_gate(yc))


def replay_yaw(
    dt: float,
    omega_b: FloatArray,
    bias_var: float,
    x3: FloatArray,
    aid: int = 0,
    values: tuple[float, float, float] = (math.nan, math.nan, math.nan),
) -> bytes:
    """A yaw-KF record ``Y`` of ``host/replay_pipeline.c``: predict (``dt`` s, rate rad/s, bias
    variance (rad/s)^2), then with the tilt ``x3`` the aid ``aid`` (0 none, 1 heading: ``values``
    = psi_b rad, sigma rad (NaN: the configured one); 2 magnetometer: ``values`` = m_b)."""
    return b"Y" + struct.pack(
        "<8fi3f", dt, *(float(v) for v in omega_b), bias_var, *(float(v) for v in x3), int(aid), *values
    )


def replay_record(kind: str, t: float, values: tuple[float, ...]) -> bytes:
    """One record of ``host/replay_pipeline.c``: ``G`` (speed, r_n[3]) or ``I`` (acc_north, acc_east, fallback)."""
    s, frac = _split_time(t)
    return kind.encode() + struct.pack("<if", s, frac) + struct.pack(f"<{len(values)}f", *values)


def replay_fix(t: float, valid: bool, lat_deg: float, lon_deg: float, pdop: float, num_sv: int) -> bytes:
    """A block-1 record ``F`` of ``host/replay_pipeline.c`` (device time ``t``, s; degrees)."""
    s, frac = _split_time(t) if math.isfinite(t) else (0, math.nan)
    return b"F" + struct.pack("<ifi3fi", s, frac, int(bool(valid)), lat_deg, lon_deg, pdop, int(num_sv))


def replay_tilt(
    dt: float, omega_b: FloatArray, bias_var: float, f_b: FloatArray, g: float, a_veh: float
) -> bytes:
    """A tilt-KF record ``T`` of ``host/replay_pipeline.c`` (predict, then update; SI units)."""
    return b"T" + struct.pack(
        "<10f", dt, *(float(v) for v in omega_b), bias_var, *(float(v) for v in f_b), g, a_veh
    )


def replay_front_end(
    t: float,
    f_b: FloatArray,
    gyro_b: FloatArray,
    dt: float,
    static: bool,
    g: float,
    a_long: float,
    v_gnss: float,
    t_speed: float,
    v_dr: float,
    psi_b: float = math.nan,
) -> bytes:
    """A record ``K`` of ``host/replay_pipeline.c``: :meth:`~iotnav.firmware.pipeline_kf3.CascadeBlock.front_end_step`'s
    arguments (SI; ``t_speed`` NaN / -inf: no speed yet), then the course aid ``psi_b`` (rad; NaN: none)."""
    s, frac = _split_time(t)
    ss, sf = _split_time(t_speed) if math.isfinite(t_speed) else (0, t_speed)
    w = [float(v) for v in (*f_b, *gyro_b, dt)]
    tail = struct.pack("<if2f", ss, sf, v_dr, psi_b)
    return b"K" + struct.pack("<if7fi3f", s, frac, *w, int(bool(static)), g, a_long, v_gnss) + tail


def replay_gyro(dt: float, gyro_b: FloatArray, static: bool) -> bytes:
    """A gyro-bias record ``B`` of ``host/replay_pipeline.c`` (``dt`` s, raw rate rad/s, block 3's decision)."""
    return b"B" + struct.pack("<4fi", dt, *(float(v) for v in gyro_b), int(bool(static)))


def _check_size(lib: Any, fn: str, state: ctypes.Structure) -> None:
    """Refuse a binding whose struct layout differs from the library's (``*_sizeof``)."""
    getattr(lib, fn).restype = ctypes.c_int32
    n = int(getattr(lib, fn)())
    if n != ctypes.sizeof(state):
        raise RuntimeError(f"{fn}: the C state has {n} bytes, the ctypes binding {ctypes.sizeof(state)}")


class _Block:
    """A loaded library and the scalar type of its build."""

    def __init__(self, lib: Path, double: bool) -> None:
        self.lib = ctypes.CDLL(str(lib))
        self.real: Any = ctypes.c_double if double else ctypes.c_float
        self.time_t = _time_type(self.real)

    def _time(self, t: float) -> ctypes.Structure:
        s, frac = _split_time(t)
        return self.time_t(s, frac)


class StaticBlock(_Block):
    """One ``pl_static_state`` (block 3) driven through :mod:`ctypes`, as :class:`~iotnav.techniques.static.StaticDetector`."""

    def __init__(self, lib: Path, config: StaticConfig | None = None, double: bool = False) -> None:
        super().__init__(lib, double)
        cfg = config or StaticConfig()
        Cfg = ctypes_struct("pl_static", self.real)
        self._cfg = Cfg(*(getattr(cfg, n) for n, _ in c_fields(StaticConfig)))
        # pl_static_state (pipeline_static.h), member by member
        state = type(
            "pl_static_state",
            (ctypes.Structure,),
            {
                "_fields_": [
                    ("cfg", Cfg),
                    ("speeds", self.real * STATIC_SPEED_WINDOW_MAX),
                    ("ring", ctypes.c_int32),
                    ("n_speeds", ctypes.c_int32),
                    ("speed_avg", self.real),
                    ("t_speed", self.time_t),
                    ("t_prev", self.time_t),
                    ("acc_h", self.real),
                    ("is_static", ctypes.c_int32),
                    ("inv_tau", self.real),
                    ("exit_acc", self.real),
                    ("decay_dt", self.real),
                    ("decay", self.real),
                ]
            },
        )
        self.state = state()
        L = self.lib
        L.pl_static_init.restype = ctypes.c_int
        L.pl_static_update_speed.restype = None
        L.pl_static_update_speed.argtypes = [ctypes.c_void_p, self.time_t, self.real]
        L.pl_static_step.restype = ctypes.c_int
        L.pl_static_step.argtypes = [ctypes.c_void_p, self.time_t, self.real, self.real, self.real]
        L.pl_static_speed.restype = self.real
        _check_size(L, "pl_static_sizeof", self.state)
        self.init_rc = int(L.pl_static_init(ctypes.byref(self.state), ctypes.byref(self._cfg)))

    def update_speed(self, t: float, speed_mps: float) -> None:
        """:meth:`StaticDetector.update_speed`: a GPS speed (m/s) at device time ``t`` (s)."""
        self.lib.pl_static_update_speed(ctypes.byref(self.state), self._time(t), speed_mps)

    def step(self, t: float, acc_n: FloatArray, fallback_speed_mps: float = math.nan) -> bool:
        """:meth:`StaticDetector.step`: ``acc_n`` North, East (m/s^2; a third component is ignored); True when static."""
        st, tt = ctypes.byref(self.state), self._time(t)
        return bool(self.lib.pl_static_step(st, tt, float(acc_n[0]), float(acc_n[1]), fallback_speed_mps))

    @property
    def speed(self) -> float:
        """Smoothed GPS speed, m/s (NaN before any)."""
        return float(self.lib.pl_static_speed(ctypes.byref(self.state)))

    @property
    def acc_h(self) -> float:
        """The low-passed horizontal specific force, m/s^2."""
        return float(self.state.acc_h)


class Lowpass3Block(_Block):
    """One ``pl_lowpass3_state`` (block 4) driven through :mod:`ctypes`, as :class:`~iotnav.techniques.lowpass3.Lowpass3`."""

    def __init__(self, lib: Path, config: Lowpass3Config | None = None, double: bool = False) -> None:
        super().__init__(lib, double)
        cfg = config or Lowpass3Config()
        Cfg = ctypes_struct("pl_lowpass3", self.real)
        self._cfg = Cfg(*(getattr(cfg, n) for n, _ in c_fields(Lowpass3Config)))
        buf = self.real * 3 * LOWPASS3_N_MAX
        state = type(
            "pl_lowpass3_state",
            (ctypes.Structure,),
            {
                "_fields_": [
                    ("cfg", Cfg),
                    ("b1", buf),
                    ("b2", buf),
                    ("b3", buf),
                    ("out", self.real * 3),
                    ("have", ctypes.c_int32),
                    ("k1", ctypes.c_int32),
                    ("k2", ctypes.c_int32),
                    ("k3", ctypes.c_int32),
                    ("since2", ctypes.c_int32),
                ]
            },
        )
        self.state = state()
        L = self.lib
        for name, res in (("pl_lowpass3_init", ctypes.c_int), ("pl_lowpass3_push", ctypes.c_int)):
            getattr(L, name).restype = res
        L.pl_lowpass3_reset.restype = None
        L.pl_lowpass3_n_fixes.restype = ctypes.c_int32
        L.pl_lowpass3_level.restype = ctypes.c_int32
        self._r = self.real * 3
        _check_size(L, "pl_lowpass3_sizeof", self.state)
        self.init_rc = int(L.pl_lowpass3_init(ctypes.byref(self.state), ctypes.byref(self._cfg)))

    def reset(self) -> None:
        """:meth:`Lowpass3.reset`."""
        self.lib.pl_lowpass3_reset(ctypes.byref(self.state))

    def push(self, r_n: FloatArray) -> FloatArray | None:
        """:meth:`Lowpass3.push` of a fix (NED, m): the new output when it changed, else None."""
        changed = self.lib.pl_lowpass3_push(ctypes.byref(self.state), self._r(*(float(v) for v in r_n)))
        return np.array(self.state.out[:], dtype=float) if changed else None

    @property
    def n_fixes(self) -> int:
        """:attr:`Lowpass3.n_fixes`."""
        return int(self.lib.pl_lowpass3_n_fixes(ctypes.byref(self.state)))

    @property
    def level(self) -> int:
        """:attr:`Lowpass3.level`."""
        return int(self.lib.pl_lowpass3_level(ctypes.byref(self.state)))


#: ``pl_lastpos_check_fix``'s results as :meth:`LastPositionLogic.check_fix`'s reasons.
FIX_REASONS: tuple[str | None, ...] = (
    None,
    "invalid",
    "no_position",
    "pdop",
    "pdop_unknown",
    "num_sv",
    "settling",
)


class LastPositionBlock(_Block):
    """One ``pl_lastpos_state`` (block 1) driven through :mod:`ctypes`, as
    :class:`~iotnav.techniques.last_position.LastPositionLogic`.

    Parameters
    ----------
    lib : pathlib.Path
        The library (:func:`build`).
    config : LastPositionConfig, optional
        Thresholds.
    stored : tuple of float, optional
        The stored position's latitude and longitude, degrees (None: nothing stored).
    double : bool
        ``lib`` is the float64 build.
    """

    def __init__(
        self,
        lib: Path,
        config: LastPositionConfig | None = None,
        stored: tuple[float, float] | None = None,
        double: bool = False,
    ) -> None:
        super().__init__(lib, double)
        cfg = config or LastPositionConfig()
        Cfg = ctypes_struct("pl_lastpos", self.real)
        self._cfg = Cfg(*(getattr(cfg, n) for n, _ in c_fields(LastPositionConfig)))
        # pl_lastpos_state (pipeline_lastpos.h), member by member
        state = type(
            "pl_lastpos_state",
            (ctypes.Structure,),
            {
                "_fields_": [
                    ("cfg", Cfg),
                    ("has_stored", ctypes.c_int32),
                    ("stored_lat_deg", self.real),
                    ("stored_lon_deg", self.real),
                    ("first_fix_seen", ctypes.c_int32),
                    ("saved", ctypes.c_int32),
                    ("t_saved", self.time_t),
                    ("hist_t", self.time_t * LASTPOS_HIST_MAX),
                    ("hist_pdop", self.real * LASTPOS_HIST_MAX),
                    ("n_hist", ctypes.c_int32),
                    ("n_hist_dropped", ctypes.c_int32),
                ]
            },
        )
        self.state = state()
        L = self.lib
        L.pl_lastpos_init.restype = ctypes.c_int
        L.pl_lastpos_init.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, self.real, self.real]
        L.pl_lastpos_check_fix.restype = ctypes.c_int
        L.pl_lastpos_check_fix.argtypes = [
            ctypes.c_void_p,
            ctypes.c_int,
            self.real,
            self.real,
            self.real,
            ctypes.c_int32,
            self.time_t,
        ]
        L.pl_lastpos_first_fix.restype = ctypes.c_int
        L.pl_lastpos_first_fix.argtypes = [ctypes.c_void_p, self.real, self.real, ctypes.c_void_p]
        L.pl_lastpos_due.restype = ctypes.c_int
        L.pl_lastpos_due.argtypes = [ctypes.c_void_p, self.time_t]
        L.pl_horizontal_distance_m.restype = self.real
        L.pl_horizontal_distance_m.argtypes = [self.real] * 4
        _check_size(L, "pl_lastpos_sizeof", self.state)
        lat, lon = stored if stored is not None else (math.nan, math.nan)
        self.init_rc = int(
            L.pl_lastpos_init(ctypes.byref(self.state), ctypes.byref(self._cfg), stored is not None, lat, lon)
        )

    def _time(self, t: float) -> ctypes.Structure:
        # an unknown time (NaN, inf) as a NaN fraction: the C block's "not finite"
        return super()._time(t) if math.isfinite(t) else self.time_t(0, math.nan)

    def check_fix(
        self, valid: bool, lat_deg: float, lon_deg: float, pdop: float, num_sv: int, t: float = math.nan
    ) -> str | None:
        """:meth:`LastPositionLogic.check_fix`: the rejection reason, or None when acceptable."""
        rc = self.lib.pl_lastpos_check_fix(
            ctypes.byref(self.state), int(bool(valid)), lat_deg, lon_deg, pdop, int(num_sv), self._time(t)
        )
        return FIX_REASONS[rc]

    def first_fix(self, t: float, lat_deg: float, lon_deg: float) -> dict[str, Any] | None:
        """:meth:`LastPositionLogic.first_fix`: the "moved while off" event, or None."""
        d = self.real(math.nan)
        if self.lib.pl_lastpos_first_fix(ctypes.byref(self.state), lat_deg, lon_deg, ctypes.byref(d)):
            return {"type": "moved_while_off", "t": t, "distance_m": float(d.value)}
        return None

    def due(self, t: float) -> bool:
        """:meth:`LastPositionLogic.due`: True when a save is due at ``t`` (s); marks it done."""
        return bool(self.lib.pl_lastpos_due(ctypes.byref(self.state), self._time(t)))

    def distance_m(self, lat1: float, lon1: float, lat2: float, lon2: float) -> float:
        """``pl_horizontal_distance_m`` (degrees in, m out)."""
        return float(self.lib.pl_horizontal_distance_m(lat1, lon1, lat2, lon2))

    @property
    def first_fix_seen(self) -> bool:
        """:attr:`LastPositionLogic.first_fix_seen`."""
        return bool(self.state.first_fix_seen)

    @property
    def n_hist_dropped(self) -> int:
        """Settling-gate history entries dropped for want of room (0: the same as Python)."""
        return int(self.state.n_hist_dropped)
