"""Host build and :mod:`ctypes` binding of the Forno et al. 2020 pipeline's block 5 in C.

``firmware/pipeline_mount.c`` (the yaw mounting-angle alignment, :mod:`iotnav.techniques.mount`,
method ``"lsq"``: Eq. 2's levelled acceleration with the least-squares rotation in place of Eq. 3)
is compiled by :func:`iotnav.firmware.pipeline.build` (the flags of blocks 1-4) into a shared
library; :class:`MountBlock` drives one ``pl_mount_state`` with the calls of
:class:`~iotnav.techniques.mount.MountAligner` and returns its events as dictionaries with the
same keys, so the tests can feed both the same inputs (``tests/test_firmware_mount.py``).
:func:`build_replay_mount` builds ``firmware/host/replay_mount.c``, the same calls from a byte
stream, for the AddressSanitizer / UndefinedBehaviorSanitizer run. The configuration struct is
generated from :class:`~iotnav.techniques.mount.MountConfig`
(:func:`iotnav.firmware.pipeline_blocks56.nav_config_header`).
"""

from __future__ import annotations

import ctypes
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.firmware.host import FIRMWARE_DIR, SANITIZE_FLAGS, WARN_FLAGS, run_gcc
from iotnav.firmware.pipeline import build
from iotnav.firmware.pipeline_blocks56 import (
    MOUNT_BUF_MAX,
    MOUNT_HIST_MAX,
    MOUNT_REF_MAX,
    MOUNT_SMOOTH_ROWS_MAX,
    nav_config_type,
    nav_values,
)
from iotnav.techniques.mount import MountConfig

FloatArray = npt.NDArray[np.float64]

#: The C sources of block 5 (repository root ``firmware/``).
MOUNT_SOURCES = ("pipeline_mount.c",)
#: Return codes of ``pl_mount_init`` (``pipeline_mount.h``).
MOUNT_OK, MOUNT_ERR_UNSUPPORTED = 0, -1
#: Columns of a C buffer row (``PL_MOUNT_COLS``: AS_X, AS_Y, DV, DT, AV_Y).
MOUNT_COLS = 5
#: ``pl_mount_event``'s flags and values, in member order.
EVENT_FLAGS = ("accepted", "applied", "provisional", "settled", "buffer_outlier", "demeaned")
EVENT_VALUES = (
    "mount_yaw_rad",
    "candidate_rad",
    "std_rad",
    "coherence",
    "excitation_mps2",
    "consistency",
    "buffer_mount_yaw_rad",
    "buffer_coherence",
    "buffer_std_rad",
    "buffer_excitation_mps2",
)


def build_mount(out: Path, double: bool = False, src: Path = FIRMWARE_DIR) -> Path:
    """Compile :data:`MOUNT_SOURCES` into the shared library ``out`` (``double``: float64).

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    return build(out, double=double, src=src, sources=MOUNT_SOURCES)


def build_replay_mount(out: Path, src: Path = FIRMWARE_DIR) -> Path:
    """Compile ``host/replay_mount.c`` with block 5 (float32) under AddressSanitizer +
    UndefinedBehaviorSanitizer (``-O0``) into the executable ``out``
    (:func:`iotnav.firmware.host.replay_sanitized` runs it).

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    args = [*WARN_FLAGS, "-O0", "-I", str(src), str(src / "host" / "replay_mount.c"), *SANITIZE_FLAGS]
    return run_gcc([*args, "-o", str(out), *(str(src / s) for s in MOUNT_SOURCES), "-lm"], out)


def _time_type(real: Any) -> type[ctypes.Structure]:
    return type("iotnav_time", (ctypes.Structure,), {"_fields_": [("s", ctypes.c_int32), ("frac", real)]})


def split_time(t: float) -> tuple[int, float]:
    """Device time ``t`` (s) as whole seconds and the fraction (the firmware's ``iotnav_time``)."""
    s = math.floor(t)
    return int(s), t - s


def mount_event_type(real: Any) -> type[ctypes.Structure]:
    """``pl_mount_event`` (``pipeline_mount.h``)."""
    fields = [(n, ctypes.c_int32) for n in EVENT_FLAGS] + [(n, real) for n in EVENT_VALUES]
    return type("pl_mount_event", (ctypes.Structure,), {"_fields_": fields})


def mount_state_type(real: Any) -> type[ctypes.Structure]:
    """``pl_mount_state`` (``pipeline_mount.h``), member by member."""
    i32 = ctypes.c_int32
    tt: Any = _time_type(real)
    fusion: Any = type(
        "pl_mount_fusion",
        (ctypes.Structure,),
        {"_fields_": [("acc", real * 4), *((n, real) for n in ("n", "w2", "z2", "nz")), ("demean", i32)]},
    )
    fields: list[tuple[str, Any]] = [
        ("cfg", nav_config_type("pl_mount", real)),
        ("mount_yaw_rad", real),
        *((n, i32) for n in ("known", "provisional", "accepted_once", "done")),
        ("buf", (real * MOUNT_COLS) * MOUNT_BUF_MAX),
        ("n_buf", i32),
        ("k", i32),
        ("fu", fusion * 2),
        ("hist_t", tt * MOUNT_HIST_MAX),
        ("hist_mu", real * MOUNT_HIST_MAX),
        *((n, i32) for n in ("hist_first", "hist_n", "n_hist_dropped")),
        *((n, real) for n in ("sx", "sy", "sr", "ssq")),
        ("n_imu", i32),
        ("body", i32),
        ("fb", real * 3),
        ("t_prev", tt),
        ("have_prev", i32),
        ("v_prev", real),
        ("ring", (real * 7) * MOUNT_REF_MAX),
        ("ring_ok", i32 * MOUNT_REF_MAX),
        *((n, i32) for n in ("n_ring", "i_ring", "ring_full")),
        ("f_ref", real * 3),
        ("t_ref", tt),
        ("have_ref", i32),
        ("sm", (real * MOUNT_COLS) * MOUNT_SMOOTH_ROWS_MAX),
        ("smooth_w", real * MOUNT_SMOOTH_ROWS_MAX),
        ("n_sm", i32),
        ("k_sm", i32),
        ("sw", real),
        ("overlap", real),
    ]
    return type("pl_mount_state", (ctypes.Structure,), {"_fields_": fields})


class MountBlock:
    """One ``pl_mount_state`` (block 5) driven through :mod:`ctypes`, as
    :class:`~iotnav.techniques.mount.MountAligner` (units and frames as there: sensor frame,
    m/s^2, rad/s, rad, s).

    Attributes
    ----------
    init_rc : int
        ``pl_mount_init``'s return code: :data:`MOUNT_OK`, or :data:`MOUNT_ERR_UNSUPPORTED` (the
        paper method, or sizes beyond the ``PL_MOUNT_*_MAX`` of ``pipeline_nav_config.h``); the
        other methods must not be called then.

    Raises
    ------
    RuntimeError
        When the library's state layout differs from the binding's.
    """

    def __init__(self, lib: Path, config: MountConfig | None = None, double: bool = False) -> None:
        self.lib = ctypes.CDLL(str(lib))
        self.real: Any = ctypes.c_double if double else ctypes.c_float
        self.config = config or MountConfig()
        self.st = mount_state_type(self.real)()
        self.lib.pl_mount_sizeof.restype = ctypes.c_int32
        n = int(self.lib.pl_mount_sizeof())
        if n != ctypes.sizeof(self.st):
            raise RuntimeError(f"pl_mount_state has {n} bytes, the ctypes binding {ctypes.sizeof(self.st)}")
        self.time_t = _time_type(self.real)
        self.lib.pl_mount_wrap.restype = self.real
        self.lib.pl_mount_wrap.argtypes = [self.real]
        self.lib.pl_mount_add_gnss.argtypes = [
            ctypes.c_void_p,
            self.time_t,
            self.real,
            self.real,
            ctypes.c_int,
            ctypes.c_int,
            ctypes.c_void_p,
        ]
        self.lib.pl_mount_set_gravity_reference.argtypes = [ctypes.c_void_p, ctypes.c_void_p, self.time_t]
        self.lib.pl_mount_add_imu.argtypes = [ctypes.c_void_p, *(self.real,) * 3]
        self.lib.pl_mount_add_imu_body.argtypes = [ctypes.c_void_p, *(self.real,) * 4]
        self.lib.pl_mount_set_stored.argtypes = [ctypes.c_void_p, self.real]
        c = nav_config_type("pl_mount", self.real)(*nav_values(self.config))
        self.init_rc = int(self.lib.pl_mount_init(ctypes.byref(self.st), ctypes.byref(c)))
        self.ev = mount_event_type(self.real)()
        self._p = ctypes.addressof(self.st)

    def _time(self, t: float) -> ctypes.Structure:
        return self.time_t(*split_time(t))

    @property
    def mount_yaw_rad(self) -> float:
        """The angle in use, rad."""
        return float(self.st.mount_yaw_rad)

    @property
    def known(self) -> bool:
        """An estimate (or stored angle) has been applied."""
        return bool(self.st.known)

    @property
    def provisional(self) -> bool:
        """The angle in use is a provisional estimate."""
        return bool(self.st.provisional)

    @property
    def done(self) -> bool:
        """The one-off calibration has ended."""
        return bool(self.st.done)

    @property
    def n_hist_dropped(self) -> int:
        """Settle-history entries C dropped beyond ``PL_MOUNT_HIST_MAX`` (Python keeps them)."""
        return int(self.st.n_hist_dropped)

    def wrap(self, a: float) -> float:
        """``pl_mount_wrap``: an angle (rad) to (-pi, pi]."""
        return float(self.lib.pl_mount_wrap(a))

    def set_stored(self, mount_yaw_rad: float) -> None:
        """A stored (accepted) calibration at boot, rad."""
        self.lib.pl_mount_set_stored(self._p, mount_yaw_rad)

    def add_imu(self, a_s: FloatArray, r: float) -> None:
        """One IMU sample, levelled: ``a_s`` (m/s^2), yaw rate ``r`` (rad/s)."""
        self.lib.pl_mount_add_imu(self._p, float(a_s[0]), float(a_s[1]), r)

    def add_imu_body(self, f_b: FloatArray, r: float) -> None:
        """One IMU sample in the sensor frame: ``f_b`` (m/s^2), yaw rate ``r`` (rad/s)."""
        self.lib.pl_mount_add_imu_body(self._p, float(f_b[0]), float(f_b[1]), float(f_b[2]), r)

    def set_gravity_reference(self, f_b: FloatArray, t: float) -> None:
        """Gravity reference ``f_b`` (m/s^2) measured up to ``t`` (s)."""
        v = (self.real * 3)(*(float(a) for a in f_b))
        self.lib.pl_mount_set_gravity_reference(self._p, ctypes.byref(v), self._time(t))

    def add_gnss(
        self, t: float, speed_mps: float, course_rad: float, course_valid: bool, static: bool
    ) -> dict[str, Any] | None:
        """Close the GPS interval ending at ``t`` (s); the event (``MountAligner.add_gnss``'s keys
        that C reports) when a buffer was evaluated, else None."""
        rc = self.lib.pl_mount_add_gnss(
            self._p,
            self._time(t),
            speed_mps,
            course_rad,
            int(bool(course_valid)),
            int(bool(static)),
            ctypes.addressof(self.ev),
        )
        if not rc:
            return None
        ev: dict[str, Any] = {"type": "mount_estimate", "t": t, "method": self.config.method}
        ev.update({n: bool(getattr(self.ev, n)) for n in EVENT_FLAGS})
        ev.update({n: float(getattr(self.ev, n)) for n in EVENT_VALUES})
        return ev


def replay_stream(config: MountConfig, calls: list[tuple[Any, ...]]) -> bytes:
    """The float32 byte stream of ``host/replay_mount.c``: the ``pl_mount_config``, then per call
    ``("I", f_b (3,), r)`` an ``I`` record, ``("G", t, speed, course, course_valid, static)`` a
    ``G`` record, ``("R", f_b (3,), t)`` a gravity reference."""
    out = bytes(nav_config_type("pl_mount", ctypes.c_float)(*nav_values(config)))
    for c in calls:
        if c[0] == "I":
            out += b"I" + struct.pack("<4f", *(float(a) for a in c[1]), float(c[2]))
        elif c[0] == "G":
            out += b"G" + struct.pack("<if2f2i", *split_time(c[1]), c[2], c[3], int(c[4]), int(c[5]))
        else:
            out += b"R" + struct.pack("<3fif", *(float(a) for a in c[1]), *split_time(c[2]))
    return out


def parse_replay(out: bytes) -> list[dict[str, Any]]:
    """``host/replay_mount.c``'s output: per ``G`` record that evaluated a buffer, the event as
    :meth:`MountBlock.add_gnss` returns it (without ``type``, ``t``, ``method``)."""
    size = 4 * (len(EVENT_FLAGS) + len(EVENT_VALUES))
    fmt = f"<{len(EVENT_FLAGS)}i{len(EVENT_VALUES)}f"
    evs = []
    for k in range(0, len(out), size):
        v = struct.unpack(fmt, out[k : k + size])
        ev: dict[str, Any] = {n: bool(x) for n, x in zip(EVENT_FLAGS, v[: len(EVENT_FLAGS)], strict=True)}
        ev.update(dict(zip(EVENT_VALUES, v[len(EVENT_FLAGS) :], strict=True)))
        evs.append(ev)
    return evs
