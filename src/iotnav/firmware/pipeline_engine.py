"""The Forno et al. 2020 pipeline wired as one C engine (``firmware/pipeline.c``): header, build,
:mod:`ctypes` binding, export.

``firmware/pipeline.h`` mirrors :class:`~iotnav.engines.pipeline.Pipeline`'s step (its IMU
kernel and its GNSS code) over the C blocks 1-6 (:mod:`iotnav.firmware.pipeline`,
:mod:`~iotnav.firmware.pipeline_mount`, :mod:`~iotnav.firmware.pipeline_blocks56`). Its
configuration ``pl_pipeline_config`` holds every block's struct plus ``pl_engine_config``
(generated here from :class:`~iotnav.engines.config.EngineConfig`) and the two NIS gates the C
cannot compute (the chi-square quantiles of the yaw and fusion ``gate_probability``):
``firmware/pipeline_engine_config.h`` is :func:`engine_config_header` of a
:class:`~iotnav.engines.config.PipelineConfig`, with its values as ``PL_PIPELINE_CONFIG_DEFAULTS``
(a test checks the checked-in header against ``PipelineConfig()``). :class:`PipelineFirmware`
drives one ``pl_state`` (an opaque buffer of ``pl_sizeof(0)`` bytes) through :mod:`ctypes`;
:func:`export` writes the library and its headers holding a tuned configuration.
"""

from __future__ import annotations

import ctypes
import math
import os
import shutil
import struct
import subprocess
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.engines.base import IMU_GAP_S, GnssSample, ImuSample, MagSample, Sample
from iotnav.engines.config import EngineConfig, PipelineConfig
from iotnav.engines.pipeline import _G_STD, UNRESOLVED_CORR_S
from iotnav.engines.tangent_plane import REANCHOR_DISTANCE_M
from iotnav.firmware.config_header import c_fields, c_literal, config_struct
from iotnav.firmware.host import FIRMWARE_DIR, SANITIZE_FLAGS, WARN_FLAGS, run_gcc, split_e7
from iotnav.firmware.pipeline import SOURCES as BLOCK_SOURCES
from iotnav.firmware.pipeline import config_header as blocks_header
from iotnav.firmware.pipeline import ctypes_struct, yaw_gate
from iotnav.firmware.pipeline_blocks56 import (
    _nav_literal,
    nav_config_header,
    nav_config_type,
    nav_fields,
    nav_values,
)

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "COST_SOURCES",
    "ENGINE_HEADER_NAME",
    "EV",
    "FIX_REASONS",
    "SOURCES",
    "PipelineFirmware",
    "build",
    "check_cost_run",
    "engine_config_header",
    "export",
    "fusion_gate",
    "parse_replay",
    "refusal",
    "replay",
    "replay_input",
]

ENGINE_HEADER_NAME = "pipeline_engine_config.h"
#: The wired engine's C sources (``firmware/``): ``pipeline.c`` and the blocks'.
SOURCES = ("pipeline.c", *BLOCK_SOURCES, "pipeline_mount.c", "pipeline_fusion.c")
#: Headers of the library (written by :func:`export` with the generated ones).
HEADERS = (
    "iotnav_real.h",
    "iotnav_common.h",
    "pipeline.h",
    "pipeline_cascade.h",
    "pipeline_fusion.h",
    "pipeline_gyrobias.h",
    "pipeline_kf3.h",
    "pipeline_lastpos.h",
    "pipeline_lowpass3.h",
    "pipeline_mount.h",
    "pipeline_static.h",
    "pipeline_tilt.h",
    "pipeline_yaw.h",
)
#: ``pl_pipeline_config``'s members: (member, PipelineConfig field, C prefix), in order.
_MEMBERS = (
    ("last_position", "last_position", "pl_lastpos"),
    ("tilt", "tilt", "pl_tilt"),
    ("yaw", "yaw", "pl_yaw"),
    ("gyro_bias", "gyro_bias", "pl_gyrobias"),
    ("static_case", "static", "pl_static"),
    ("lowpass3", "lowpass3", "pl_lowpass3"),
    ("mount", "mount", "pl_mount"),
    ("fusion", "fusion", "pl_fusion"),
    ("pipeline", "pipeline", "pl_engine"),
)
#: ``PL_EV_*`` bits of ``pipeline.h``.
EV = {
    "fix_rejected": 0x001,
    "moved_while_off": 0x002,
    "first_fix": 0x004,
    "vertical_reset": 0x008,
    "mount_estimate": 0x010,
    "save": 0x020,
    "static_start": 0x040,
    "static_end": 0x080,
    "boot_movement_before_fix": 0x100,
    "skipped": 0x200,
    "imu_gap": 0x400,
    "course_repaired": 0x800,
    "numeric": 0x1000,
}
#: ``st->fix_reason`` (``PL_FIX_*`` of ``pipeline_lastpos.h`` and ``PL_FIX_NIS``) as Python's reasons.
FIX_REASONS = {
    1: "invalid",
    2: "no_position",
    3: "pdop",
    4: "pdop_unknown",
    5: "num_sv",
    6: "settling",
    7: "nis",
}
PL_OK, PL_ERR_UNSUPPORTED = 0, -1


def fusion_gate(cfg: PipelineConfig) -> float:
    """``pl_fusion_init``'s gate: the chi-square quantile (3 dof) of ``fusion.gate_probability``
    (:func:`iotnav.kalman.gate_threshold`), 0.0 when it is not positive (no gate)."""
    from iotnav import kalman

    p = cfg.fusion.gate_probability
    return kalman.gate_threshold(3, p) if p > 0.0 else 0.0


def refusal(cfg: PipelineConfig) -> str | None:
    """Why the C engine refuses ``cfg`` at ``pl_init`` (None when it implements it).

    The export refuses the same configurations (``firmware/pipeline.h``, "Refused").
    """
    from iotnav.firmware.pipeline import LOWPASS3_N_MAX, STATIC_SPEED_WINDOW_MAX
    from iotnav.firmware.pipeline_blocks56 import MOUNT_BUF_MAX, MOUNT_REF_MAX, MOUNT_SMOOTH_ROWS_MAX

    if cfg.fusion.smoothing:
        return "fusion.smoothing = true: the RTS smoother's log is not in the C library"
    if cfg.mount.method != "lsq":
        return f'mount.method = "{cfg.mount.method}": the C block 5 implements only "lsq"'
    lp = cfg.lowpass3
    if not all(1 <= n <= LOWPASS3_N_MAX for n in (lp.n1, lp.n2, lp.n3)):
        return f"lowpass3 levels must be 1..{LOWPASS3_N_MAX} (the C state's fixed size)"
    if cfg.static.speed_window > STATIC_SPEED_WINDOW_MAX:
        return f"static.speed_window above {STATIC_SPEED_WINDOW_MAX} (the C state's fixed size)"
    m = cfg.mount
    if max(2, m.buffer_epochs) > MOUNT_BUF_MAX or 2 * max(1, m.smooth_epochs) - 1 > MOUNT_SMOOTH_ROWS_MAX:
        return f"mount buffers beyond the C sizes (buffer_epochs <= {MOUNT_BUF_MAX}, smooth_epochs <= 8)"
    if m.ref_window_epochs > MOUNT_REF_MAX:
        return f"mount.ref_window_epochs above {MOUNT_REF_MAX} (the C state's fixed size)"
    return None


def _block_literals(prefix: str, cfg: Any) -> list[str]:
    if prefix in ("pl_fusion", "pl_mount"):
        return [_nav_literal(v, k) for (_, k), v in zip(nav_fields(type(cfg)), nav_values(cfg), strict=True)]
    return [c_literal(getattr(cfg, n), k) for n, k in c_fields(type(cfg))]


def engine_config_header(cfg: PipelineConfig | None = None) -> str:
    """Text of ``pipeline_engine_config.h``: ``pl_engine_config`` (:class:`EngineConfig`), the
    engine's constants and ``pl_pipeline_config`` with ``cfg`` (default ``PipelineConfig()``) as
    ``PL_PIPELINE_CONFIG_DEFAULTS``."""
    c = cfg or PipelineConfig()
    out = [
        "/* Generated by iotnav.firmware.pipeline_engine from iotnav.engines.config.PipelineConfig",
        " * (the wired Forno pipeline, firmware/pipeline.h). Do not edit: tests check it against a",
        " * fresh generation (iotnav.firmware.pipeline_engine.engine_config_header). */",
        "#ifndef IOTNAV_PIPELINE_ENGINE_CONFIG_H",
        "#define IOTNAV_PIPELINE_ENGINE_CONFIG_H",
        "",
        '#include "pipeline_config.h"',
        '#include "pipeline_nav_config.h"',
        "",
        "/* iotnav.engines.tangent_plane.REANCHOR_DISTANCE_M, m */",
        f"#define PL_REANCHOR_DISTANCE_M {REANCHOR_DISTANCE_M!r}",
        "/* iotnav.engines.pipeline.UNRESOLVED_CORR_S, s */",
        f"#define PL_UNRESOLVED_CORR_S {UNRESOLVED_CORR_S!r}",
        "/* standard gravity (gravity_mps2 <= 0 before an origin: iotnav.engines.pipeline._G_STD), m/s^2 */",
        f"#define PL_G_STD {_G_STD!r}",
        "/* iotnav.engines.base.IMU_GAP_S, s */",
        f"#define PL_IMU_GAP_S {IMU_GAP_S!r}",
    ]
    out += config_struct(
        "pl_engine", EngineConfig, c_fields(EngineConfig), _block_literals("pl_engine", c.pipeline)
    )
    out += [
        "",
        "/* Every tunable of the wired pipeline (iotnav.engines.config.PipelineConfig) and the NIS gates",
        " * of its yaw and fusion filters (chi-square quantiles, 3 dof, of their gate_probability; 0: none). */",
        "typedef struct {",
        *(f"    {p}_config {m};" for m, _, p in _MEMBERS),
        "    IOTNAV_REAL yaw_gate_nis;",
        "    IOTNAV_REAL fusion_gate_nis;",
        "} pl_pipeline_config;",
        "",
        "/* The PipelineConfig this header was generated with. */",
        "#define PL_PIPELINE_CONFIG_DEFAULTS { \\",
    ]
    for m, f, p in _MEMBERS:
        lits = _block_literals(p, getattr(c, f))
        out.append(f"    {{ {', '.join(lits)} }} /* {m} */, \\")
    out += [
        f"    {c_literal(yaw_gate(c.yaw), 'real')} /* yaw_gate_nis */, \\",
        f"    {c_literal(fusion_gate(c), 'real')} /* fusion_gate_nis */ \\",
        "}",
        "",
        "#endif",
        "",
    ]
    return "\n".join(out)


def build(
    out: Path,
    double: bool = False,
    sanitize: bool = False,
    src: Path = FIRMWARE_DIR,
    replay: bool = False,
    opt: str = "-O2",
) -> Path:
    """Compile the wired engine (:data:`SOURCES` in ``src``) into the shared library ``out`` (with
    ``replay``: the executable of ``host/replay_pipeline_wired.c`` instead), with
    :data:`~iotnav.firmware.host.WARN_FLAGS`; ``double``: ``-DIOTNAV_REAL_DOUBLE``; ``sanitize``:
    AddressSanitizer + UndefinedBehaviorSanitizer.

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    args = [*WARN_FLAGS, opt, "-I", str(src)]
    args += [str(src / "host" / "replay_pipeline_wired.c")] if replay else ["-fPIC", "-shared"]
    args += ["-DIOTNAV_REAL_DOUBLE"] if double else []
    args += list(SANITIZE_FLAGS) if sanitize else []
    return run_gcc([*args, "-o", str(out), *(str(src / s) for s in SOURCES), "-lm"], out)


def config_type(real: Any) -> type[ctypes.Structure]:
    """The :mod:`ctypes` layout of ``pl_pipeline_config``."""
    fields: list[tuple[str, Any]] = []
    for m, _, p in _MEMBERS:
        if p in ("pl_fusion", "pl_mount"):
            fields.append((m, nav_config_type(p, real)))
        elif p == "pl_engine":
            members = [(n, ctypes.c_int32 if k == "int" else real) for n, k in c_fields(EngineConfig)]
            fields.append((m, type("pl_engine_config", (ctypes.Structure,), {"_fields_": members})))
        else:
            fields.append((m, ctypes_struct(p, real)))
    fields += [("yaw_gate_nis", real), ("fusion_gate_nis", real)]
    return type("pl_pipeline_config", (ctypes.Structure,), {"_fields_": fields})


def _member_type(t: type[ctypes.Structure], name: str) -> Any:
    """The ctypes type of member ``name`` of the structure type ``t``."""
    return next(f[1] for f in t._fields_ if f[0] == name)


def config_struct_of(cfg: PipelineConfig, real: Any) -> ctypes.Structure:
    """``cfg`` as a ``pl_pipeline_config`` of the build's scalar ``real``."""
    t = config_type(real)
    parts = []
    for m, f, p in _MEMBERS:
        ft = _member_type(t, m)
        block = getattr(cfg, f)
        vals = (
            nav_values(block)
            if p in ("pl_fusion", "pl_mount")
            else [getattr(block, n) for n, _ in c_fields(type(block))]
        )
        parts.append(ft(*vals))
    return t(*parts, yaw_gate(cfg.yaw), fusion_gate(cfg))


def _time(real: Any) -> type[ctypes.Structure]:
    return type("iotnav_time", (ctypes.Structure,), {"_fields_": [("s", ctypes.c_int32), ("frac", real)]})


def _split_time(t: float) -> tuple[int, float]:
    """Device time ``t`` (s) as whole seconds plus the fraction (``iotnav_time``); ``(0, nan)``
    for a time that is not finite (the C engine refuses it, as InputGuard)."""
    if not math.isfinite(t):
        return 0, math.nan
    s = math.floor(t)
    return int(s), t - s


def io_types(real: Any) -> dict[str, type[ctypes.Structure]]:
    """The :mod:`ctypes` layouts of ``pl_imu_in``, ``pl_gnss_in``, ``pl_geo``, ``pl_output_t``."""
    tt = _time(real)
    i32 = ctypes.c_int32
    imu = type(
        "pl_imu_in", (ctypes.Structure,), {"_fields_": [("t", tt), ("f_b", real * 3), ("w_b", real * 3)]}
    )
    gnss_fields = [("t", tt), ("valid", i32), ("num_sv", i32), ("lat_e7", i32), ("lon_e7", i32)]
    gnss_fields += [(n, real) for n in ("lat_frac_e7", "lon_frac_e7", "height_m", "h_acc_m", "v_acc_m")]
    gnss_fields += [(n, real) for n in ("s_acc_mps", "pdop", "hdop", "speed_mps", "course_rad")]
    gnss_fields += [("course_valid", i32), ("vn", real), ("ve", real), ("vd", real)]
    gnss = type("pl_gnss_in", (ctypes.Structure,), {"_fields_": gnss_fields})
    geo_fields = [
        ("lat_e7", i32),
        ("lon_e7", i32),
        ("lat_frac_e7", real),
        ("lon_frac_e7", real),
        ("height_m", real),
    ]
    geo = type("pl_geo", (ctypes.Structure,), {"_fields_": geo_fields})
    out_fields = [("t", tt), ("source", i32), ("is_static", i32), ("has_position", i32)]
    out_fields += [
        ("r_n", real * 3),
        ("v_n", real * 3),
        ("std_north", real),
        ("std_east", real),
        ("geo", geo),
    ]
    out_fields += [("roll", real), ("pitch", real), ("yaw", real)]
    out = type("pl_output_t", (ctypes.Structure,), {"_fields_": out_fields})
    return {"imu": imu, "gnss": gnss, "geo": geo, "out": out}


def gnss_in(s: GnssSample, t: Any) -> ctypes.Structure:
    """A :class:`GnssSample` as a ``pl_gnss_in`` of layout ``t`` (degrees split by :func:`split_e7`;
    no position: NaN fractions)."""
    if math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg):
        la, lf = split_e7(s.lat_deg)
        lo, of = split_e7(s.lon_deg)
    else:
        la, lf, lo, of = 0, math.nan, 0, math.nan
    sec, frac = _split_time(s.t)
    num_sv = int(s.num_sv) if math.isfinite(float(s.num_sv)) else -1
    return t(
        (sec, frac), int(bool(s.valid)), num_sv, la, lo, lf, of, s.height_m, s.h_acc_m, s.v_acc_m,
        s.s_acc_mps, s.pdop, s.hdop, s.speed_mps, s.course_rad, int(bool(s.course_valid)), s.vn, s.ve, s.vd,
    )  # fmt: skip


def imu_in(s: ImuSample, t: Any) -> ctypes.Structure:
    """An :class:`ImuSample` as a ``pl_imu_in`` of layout ``t``."""
    tt = _split_time(s.t)  # refused by pl_step_imu
    return t(tt, tuple(float(v) for v in s.acc_b), tuple(float(v) for v in s.gyro_b))


class PipelineFirmware:
    """One ``pl_state`` of the wired pipeline driven through :mod:`ctypes` (host build, :func:`build`).

    Raises
    ------
    RuntimeError
        When the library's struct sizes differ from the binding's, or ``pl_init`` refuses the
        configuration (the reason of :func:`refusal` in the message).
    """

    def __init__(self, lib: Path, config: PipelineConfig | None = None, double: bool = False) -> None:
        self.lib = ctypes.CDLL(str(lib))
        self.real: Any = ctypes.c_double if double else ctypes.c_float
        self.config = cfg = config or PipelineConfig()
        self.types = io_types(self.real)
        self.lib.pl_sizeof.restype = ctypes.c_int32
        c = config_struct_of(cfg, self.real)
        for which, obj in (
            (1, c),
            (2, self.types["imu"]()),
            (3, self.types["gnss"]()),
            (4, self.types["out"]()),
        ):
            n = int(self.lib.pl_sizeof(ctypes.c_int32(which)))
            if n != ctypes.sizeof(obj):
                raise RuntimeError(f"pl_sizeof({which}) = {n}, the ctypes binding has {ctypes.sizeof(obj)}")
        self.state = ctypes.create_string_buffer(int(self.lib.pl_sizeof(ctypes.c_int32(0))))
        self._cfg = c
        rc = int(self.lib.pl_init(self.state, ctypes.byref(c)))
        if rc != PL_OK:
            raise RuntimeError(f"pl_init refused the configuration ({rc}): {refusal(cfg)}")
        self._out = self.types["out"]()

    def set_stored(
        self, lat_deg: float, lon_deg: float, height_m: float, mount_yaw_rad: float = math.nan
    ) -> None:
        """A stored last position at boot (degrees, m; mount angle rad, NaN: none)."""
        la, lf = split_e7(lat_deg)
        lo, of = split_e7(lon_deg)
        geo = self.types["geo"](la, lo, lf, of, height_m)
        self.lib.pl_set_stored(self.state, ctypes.byref(geo), self.real(mount_yaw_rad))

    def step_imu(self, s: ImuSample) -> int:
        """One IMU sample: its ``PL_EV_*`` flags."""
        return int(self.lib.pl_step_imu(self.state, ctypes.byref(imu_in(s, self.types["imu"]))))

    def step_gnss(self, s: GnssSample) -> int:
        """One GNSS epoch: its ``PL_EV_*`` flags."""
        return int(self.lib.pl_step_gnss(self.state, ctypes.byref(gnss_in(s, self.types["gnss"]))))

    def step_mag(self, s: MagSample) -> int:
        """One magnetometer sample: its ``PL_EV_*`` flags."""
        sec, frac = _split_time(s.t)
        m = (self.real * 3)(*(float(v) for v in s.mag_b_ut))
        return int(self.lib.pl_step_mag(self.state, _time(self.real)(sec, frac), m))

    def output(self) -> dict[str, Any]:
        """The row of the latest IMU sample: t (s), source, static, north/east/down (m), vn/ve/vd
        (m/s), std_north/std_east (m), lat/lon (degrees), height (m), roll/pitch/yaw (rad)."""
        self.lib.pl_output(self.state, ctypes.byref(self._out))
        o = self._out
        g = o.geo
        row: dict[str, Any] = {
            "t": o.t.s + float(o.t.frac),
            "source": int(o.source),
            "static": bool(o.is_static),
        }
        for i, n in enumerate(("north", "east", "down")):
            row[n] = float(o.r_n[i])
        for i, n in enumerate(("vn", "ve", "vd")):
            row[n] = float(o.v_n[i])
        row.update(std_north=float(o.std_north), std_east=float(o.std_east))
        row.update(lat=(g.lat_e7 + float(g.lat_frac_e7)) * 1e-7, lon=(g.lon_e7 + float(g.lon_frac_e7)) * 1e-7)
        row.update(height=float(g.height_m), roll=float(o.roll), pitch=float(o.pitch), yaw=float(o.yaw))
        return row


def _event_types(real: Any) -> dict[str, type[ctypes.Structure]]:
    """``pl_mount_event`` and ``pl_save`` (``pipeline_mount.h``, ``pipeline.h``)."""
    from iotnav.firmware.pipeline_mount import EVENT_FLAGS, EVENT_VALUES

    ev_fields = [(n, ctypes.c_int32) for n in EVENT_FLAGS] + [(n, real) for n in EVENT_VALUES]
    ev = type("pl_mount_event", (ctypes.Structure,), {"_fields_": ev_fields})
    save_fields = [("pos", io_types(real)["geo"]), ("t", _time(real)), ("mount_yaw_rad", real)]
    return {"mount": ev, "save": type("pl_save", (ctypes.Structure,), {"_fields_": save_fields})}


def replay_input(
    cfg: PipelineConfig, samples: Iterable[Sample], double: bool = False, stored: Any = None
) -> bytes:
    """The stdin of ``host/replay_pipeline_wired.c``: ``cfg`` as ``pl_pipeline_config``, the
    stored position (a :class:`~iotnav.techniques.last_position.StoredPosition`, or None), then
    one record per sample (IMU, GNSS, magnetometer) in the given order."""
    real: Any = ctypes.c_double if double else ctypes.c_float
    t = io_types(real)
    parts = [bytes(config_struct_of(cfg, real))]
    if stored is not None:
        la, lf = split_e7(stored.lat_deg)
        lo, of = split_e7(stored.lon_deg)
        parts.append(
            b"S" + bytes(t["geo"](la, lo, lf, of, stored.height_m)) + bytes(real(stored.mount_yaw_rad))
        )
    for s in samples:
        if isinstance(s, ImuSample):
            parts.append(b"I" + bytes(imu_in(s, t["imu"])))
        elif isinstance(s, GnssSample):
            parts.append(b"G" + bytes(gnss_in(s, t["gnss"])))
        elif isinstance(s, MagSample):
            sec, frac = _split_time(s.t)
            m = (real * 3)(*(float(v) for v in s.mag_b_ut))
            parts.append(b"M" + bytes(_time(real)(sec, frac)) + bytes(m))
    return b"".join(parts)


def parse_replay(data: bytes, double: bool = False) -> dict[str, Any]:
    """The stdout of ``host/replay_pipeline_wired.c``.

    Returns
    -------
    dict
        ``rc`` (``pl_init``'s result); ``imu``: per IMU record ``(flags, pl_output_t)``;
        ``gnss``: per GNSS record ``(flags, fix_reason, nis, moved_distance_m, vertical_jump_m,
        pl_mount_event, pl_save)``; ``mag``: per magnetometer record its flags; ``order``: the
        kinds in record order.
    """
    real: Any = ctypes.c_double if double else ctypes.c_float
    t, e = io_types(real), _event_types(real)
    rs = ctypes.sizeof(real)
    rc = struct.unpack_from("<i", data, 0)[0]
    out: dict[str, Any] = {"rc": rc, "imu": [], "gnss": [], "mag": [], "order": []}
    k = 4
    n_out, n_ev, n_save = ctypes.sizeof(t["out"]), ctypes.sizeof(e["mount"]), ctypes.sizeof(e["save"])
    while k < len(data):
        kind = chr(data[k])
        flags = struct.unpack_from("<i", data, k + 1)[0]
        k += 5
        out["order"].append(kind)
        if kind == "I":
            out["imu"].append((flags, t["out"].from_buffer_copy(data, k)))
            k += n_out
        elif kind == "G":
            reason = struct.unpack_from("<i", data, k)[0]
            vals = struct.unpack_from("<3" + ("d" if double else "f"), data, k + 4)
            k += 4 + 3 * rs
            ev = e["mount"].from_buffer_copy(data, k)
            k += n_ev
            sv = e["save"].from_buffer_copy(data, k)
            k += n_save
            out["gnss"].append((flags, reason, *vals, ev, sv))
        elif kind == "M":
            out["mag"].append(flags)
        else:
            raise ValueError(f"replay output: unknown record {kind!r} at byte {k - 5}")
    return out


def replay(exe: Path, stdin: bytes, double: bool = False) -> dict[str, Any]:
    """Run the replay program ``exe`` on ``stdin`` (:func:`replay_input`) and parse its output.

    Raises
    ------
    RuntimeError
        When the program fails or writes to stderr (a sanitizer report fails it).
    """
    env = dict(os.environ)
    env["ASAN_OPTIONS"] = "detect_leaks=1:halt_on_error=1"
    env["UBSAN_OPTIONS"] = "halt_on_error=1:print_stacktrace=1"
    res = subprocess.run([str(exe)], input=stdin, capture_output=True, env=env, check=False)
    if res.returncode != 0 or res.stderr:
        raise RuntimeError(
            f"{exe.name} exited {res.returncode}: {res.stderr.decode(errors='replace')[:4000]}"
        )
    return parse_replay(res.stdout, double)


def export(out: Path, cfg: PipelineConfig, src: Path = FIRMWARE_DIR) -> list[Path]:
    """Write the wired pipeline's library into ``out``: its sources and headers, and the three
    generated configuration headers with ``cfg``'s values (``pipeline_config.h``,
    ``pipeline_nav_config.h``, ``pipeline_engine_config.h``).

    Raises
    ------
    ValueError
        When the C engine does not implement ``cfg`` (:func:`refusal`).
    """
    why = refusal(cfg)
    if why is not None:
        raise ValueError(f"the C pipeline refuses this configuration: {why}")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in (*HEADERS, *SOURCES):
        shutil.copyfile(src / name, out / name)
        written.append(out / name)
    gen = {
        "pipeline_config.h": blocks_header(
            cfg.static, cfg.lowpass3, cfg.last_position, cfg.gyro_bias, cfg.tilt, cfg.yaw
        ),
        "pipeline_nav_config.h": nav_config_header(cfg.fusion, cfg.mount),
        ENGINE_HEADER_NAME: engine_config_header(cfg),
    }
    for name, text in gen.items():
        (out / name).write_text(text, encoding="utf-8")
        written.append(out / name)
    return written


#: ``firmware/host/cycles_pipeline_wired.c`` (the wired pipeline's cost driver) and the library.
COST_SOURCES = ("host/cycles_pipeline_wired.c", *SOURCES)
#: Its final state's reals and the tolerance of a target against the host float32 build
#: (:func:`iotnav.firmware.targets.check`): position 1 mm, velocity 0.1 mm/s, accelerometer bias
#: 1e-5 m/s^2, the covariance diagonal 1e-3 relative, ``C_nb`` and the angles 1e-5 (rad): far
#: inside the contract with Python (1 cm, 0.01 deg); newlib's and avr-libc's float routines
#: differ from glibc's in the last bit.
COST_REALS: dict[str, tuple[str, float]] = {
    **{f"x{i}": ("abs", 1e-3) for i in range(3)},
    **{f"x{i}": ("abs", 1e-4) for i in range(3, 6)},
    **{f"x{i}": ("abs", 1e-5) for i in range(6, 9)},
    **{f"p{i}": ("rel", 1e-3) for i in range(9)},
    **{f"c{i}": ("abs", 1e-5) for i in range(9)},
    "mount_yaw": ("abs", 1e-5),
    "out_yaw": ("abs", 1e-5),
}
#: Its counts, equal on every target: calls, events (``PL_EV_*``), output sources, the mount's state.
COST_COUNTS: tuple[str, ...] = ("init_rc", "n_imu", "n_gnss", "mount_known", "sizeof_config")
COST_COUNTS += tuple(
    f"ev_{n}"
    for n in ("fix_rejected", "moved", "first_fix", "vertical", "mount", "save", "static_start", "static_end")
)
COST_COUNTS += ("ev_boot_move", "ev_skipped", "ev_imu_gap", "ev_course", "ev_numeric")
COST_COUNTS += ("src_none", "src_fix", "src_dr", "src_lowpass", "src_last_position")


def check_cost_run(out: dict[str, int], host: dict[str, int]) -> dict[str, float]:
    """:func:`iotnav.firmware.targets.check` of a ``cycles_pipeline_wired.c`` run against the host's.

    Raises
    ------
    RuntimeError
        When the run is incomplete, a count differs or a real is beyond :data:`COST_REALS`.
    """
    from iotnav.firmware import targets

    return targets.check(out, host, COST_REALS, COST_COUNTS)
