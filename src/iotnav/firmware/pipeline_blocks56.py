"""Host build and :mod:`ctypes` binding of the Forno et al. 2020 pipeline's block 6 in C.

``firmware/pipeline_fusion.c`` (the 9-state fusion Kalman filter,
:mod:`iotnav.techniques.fusion_kf`) is compiled with the warning flags of
:mod:`iotnav.firmware.host` into a shared library; :class:`FusionBlock` drives one
``pl_fusion_state`` with the calls of :class:`~iotnav.techniques.fusion_kf.FusionKF`, so the tests
can feed both the same inputs (``tests/test_firmware_blocks56.py``). Block 5 (mount alignment,
``firmware/pipeline_mount.c``) is not bound yet.
"""

from __future__ import annotations

import ctypes
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.firmware.host import FIRMWARE_DIR
from iotnav.firmware.pipeline import build
from iotnav.techniques.fusion_kf import N_STATES, FusionConfig

FloatArray = npt.NDArray[np.float64]

#: The C sources of block 6 (repository root ``firmware/``).
FUSION_SOURCES = ("pipeline_fusion.c",)
#: Return codes of ``pl_fusion_update_*`` (``pipeline_fusion.h``).
FUSION_OK, FUSION_REJECTED, FUSION_ERR_NUMERIC, FUSION_ERR_UNSUPPORTED = 0, 1, -2, -1


def build_fusion(out: Path, double: bool = False, sanitize: bool = False, src: Path = FIRMWARE_DIR) -> Path:
    """Compile :data:`FUSION_SOURCES` into the shared library ``out``
    (:func:`iotnav.firmware.pipeline.build`: the same flags as blocks 1-4).

    Raises
    ------
    RuntimeError
        When ``gcc`` is missing or the compilation fails (its messages included).
    """
    return build(out, double=double, sanitize=sanitize, src=src, sources=FUSION_SOURCES)


def fusion_config_type(real: Any) -> type[ctypes.Structure]:
    """``pl_fusion_config`` (``pipeline_nav_config.h``): :class:`FusionConfig`'s fields in order,
    ``bool``/``int`` as ``int32_t``, ``float`` as the build's scalar."""
    members = [
        (f.name, ctypes.c_int32 if f.type in ("int", "bool") else real)
        for f in dataclasses.fields(FusionConfig)
    ]
    return type("pl_fusion_config", (ctypes.Structure,), {"_fields_": members})


def fusion_state_type(real: Any) -> type[ctypes.Structure]:
    """``pl_fusion_state`` (``pipeline_fusion.h``), member by member."""
    i32 = ctypes.c_int32
    fields = [
        ("cfg", fusion_config_type(real)),
        ("x", real * N_STATES),
        ("P", real * (N_STATES * N_STATES)),
        ("initialised", i32),
        ("n_rejected", i32),
        ("gate", real),
        ("nis", real),
    ]
    return type("pl_fusion_state", (ctypes.Structure,), {"_fields_": fields})


class FusionBlock:
    """One ``pl_fusion_state`` (block 6) driven through :mod:`ctypes`, as
    :class:`~iotnav.techniques.fusion_kf.FusionKF` (units and frames as there: NED, m, m/s, m/s^2).

    Raises
    ------
    RuntimeError
        When the library's state layout differs from the binding's, or ``pl_fusion_init``
        refuses the configuration (``smoothing``).
    """

    def __init__(self, lib: Path, config: FusionConfig | None = None, double: bool = False) -> None:
        self.lib = ctypes.CDLL(str(lib))
        self.real: Any = ctypes.c_double if double else ctypes.c_float
        cfg = config or FusionConfig()
        self.st = fusion_state_type(self.real)()
        self.lib.pl_fusion_sizeof.restype = ctypes.c_int32
        n = int(self.lib.pl_fusion_sizeof())
        if n != ctypes.sizeof(self.st):
            raise RuntimeError(f"pl_fusion_state has {n} bytes, the ctypes binding {ctypes.sizeof(self.st)}")
        c = fusion_config_type(self.real)(*(getattr(cfg, f.name) for f in dataclasses.fields(FusionConfig)))
        gate = kalman.gate_threshold(3, cfg.gate_probability) if cfg.gate_probability > 0.0 else 0.0
        rc = self.lib.pl_fusion_init(ctypes.byref(self.st), ctypes.byref(c), self.real(gate))
        if rc != FUSION_OK:
            raise RuntimeError(f"pl_fusion_init refused the configuration ({rc})")

    def _vec(self, v: FloatArray | None, n: int) -> Any:
        if v is None:
            return None
        return (self.real * n)(*(float(a) for a in np.asarray(v, float).reshape(-1)))

    @property
    def x(self) -> FloatArray:
        """State ``[r_n, v_n, b_a]`` (copy)."""
        return np.array(self.st.x[:], float)

    @property
    def P(self) -> FloatArray:
        """Covariance (9, 9) (copy)."""
        return np.array(self.st.P[:], float).reshape(N_STATES, N_STATES)

    @property
    def n_rejected(self) -> int:
        """Consecutive gated fixes."""
        return int(self.st.n_rejected)

    @property
    def nis(self) -> float:
        """NIS of the latest update."""
        return float(self.st.nis)

    def initialise(self, r_n: FloatArray, r_var: FloatArray, v_n: FloatArray | None = None) -> None:
        """Start at ``r_n`` (m) with the position variances ``r_var`` (m^2, R's diagonal)."""
        self.lib.pl_fusion_initialise(
            ctypes.byref(self.st), self._vec(r_n, 3), self._vec(r_var, 3), self._vec(v_n, 3)
        )

    def predict(self, acc_n: FloatArray, C_nb: FloatArray, dt: float, q_a: float) -> None:
        """One IMU step: ``acc_n = C_nb f_b + g_n`` (m/s^2), ``dt`` (s), PSD ``q_a`` (m^2/s^3)."""
        a = np.asarray(acc_n, float)
        r = self.real
        self.lib.pl_fusion_predict(
            ctypes.byref(self.st), r(a[0]), r(a[1]), r(a[2]), self._vec(C_nb, 9), r(dt), r(q_a)
        )

    def update_position(self, r_n: FloatArray, r_var: FloatArray, stale: bool = False) -> int:
        """GNSS position update (NED, m; variances m^2): a ``FUSION_*`` return code."""
        return int(
            self.lib.pl_fusion_update_position(
                ctypes.byref(self.st), self._vec(r_n, 3), self._vec(r_var, 3), ctypes.c_int(int(stale))
            )
        )

    def update_velocity(self, v_ne: FloatArray, sigma_mps: float) -> int:
        """Horizontal velocity update ``[v_N, v_E]`` (m/s)."""
        r = self.real
        return int(
            self.lib.pl_fusion_update_velocity(ctypes.byref(self.st), r(v_ne[0]), r(v_ne[1]), r(sigma_mps))
        )

    def update_velocity_ned(self, v_n: FloatArray, sigma_mps: float) -> int:
        """Velocity update ``[v_N, v_E, v_D]`` (m/s)."""
        return int(
            self.lib.pl_fusion_update_velocity_ned(
                ctypes.byref(self.st), self._vec(v_n, 3), self.real(sigma_mps)
            )
        )
