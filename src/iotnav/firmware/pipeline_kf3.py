"""ctypes bindings of the Forno pipeline's block 2 in C: the gyro-bias, tilt and yaw KFs and the cascade.

Moved out of :mod:`iotnav.firmware.pipeline` unchanged (that module has the blocks' generated
configuration header, the builds, the replay records and blocks 1, 3 and 4):
:class:`GyroBiasBlock`, :class:`TiltBlock`, :class:`YawBlock` (``pipeline_gyrobias.h``,
``pipeline_tilt.h``, ``pipeline_yaw.h``, sharing ``pipeline_kf3.h``) and :class:`CascadeBlock`
(``pipeline_cascade.h``), each on a library built by :func:`iotnav.firmware.pipeline.build`.
"""

from __future__ import annotations

import ctypes
import math
import typing
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.firmware.config_header import c_fields
from iotnav.firmware.pipeline import StaticBlock, _Block, _check_size, ctypes_struct, yaw_gate
from iotnav.techniques.gyro_bias_kf import GyroBiasConfig
from iotnav.techniques.tilt_kf import TiltConfig
from iotnav.techniques.yaw_kf import YawConfig

if typing.TYPE_CHECKING:
    from iotnav.techniques.cascade import CascadeConfig

FloatArray = npt.NDArray[np.float64]

__all__ = ["CascadeBlock", "GyroBiasBlock", "TiltBlock", "YawBlock"]


def _state_type(prefix: str, real: Any) -> type[ctypes.Structure]:
    """The :mod:`ctypes` layout of ``<prefix>_state`` (``pipeline_gyrobias.h``, ``pipeline_tilt.h``,
    ``pipeline_yaw.h``, ``pipeline_cascade.h``), member by member."""
    i32 = ctypes.c_int32
    fields: list[tuple[str, Any]]
    if prefix == "pl_cascade":
        fields = [
            ("bias", _state_type("pl_gyrobias", real)),
            ("tilt", _state_type("pl_tilt", real)),
            ("yaw", _state_type("pl_yaw", real)),
            ("C", real * 9),
            ("omega", real * 3),
        ]
        return type("pl_cascade_state", (ctypes.Structure,), {"_fields_": fields})
    fields = [("cfg", ctypes_struct(prefix, real)), ("x", real * 3), ("P", real * 9)]
    if prefix == "pl_gyrobias":
        fields += [("q_b", real), ("r", real)]
    elif prefix == "pl_tilt":
        fields += [("initialised", i32), ("nis", real), ("gyro_var", real), ("acc_var", real)]
    elif prefix == "pl_yaw":
        fields += [("initialised", i32), ("nis", real), ("gated", i32), ("gate", real)]
        fields += [(n, real) for n in ("gyro_var", "mag_var", "cos_decl", "sin_decl")]
    else:
        raise ValueError(f"no state layout for {prefix}")
    return type(f"{prefix}_state", (ctypes.Structure,), {"_fields_": fields})


class _ThreeStateBlock(_Block):
    """A block whose C state holds a three-state KF's ``x`` (3) and ``P`` (3 x 3, row-major)."""

    state: Any

    @property
    def x(self) -> FloatArray:
        """The state: the Python filter's ``x`` (the gyro bias, rad/s; the down or North axis in ``b``)."""
        return np.array(self.state.x[:], dtype=float)

    @property
    def P(self) -> FloatArray:
        """Its covariance (3, 3), in the units of ``x`` squared."""
        return np.array(self.state.P[:], dtype=float).reshape(3, 3)

    @P.setter
    def P(self, value: FloatArray) -> None:
        self.state.P[:] = [float(v) for v in np.asarray(value, float).reshape(9)]


class GyroBiasBlock(_ThreeStateBlock):
    """One ``pl_gyrobias_state`` (block 2's gyro-bias KF) driven through :mod:`ctypes`, as
    :class:`~iotnav.techniques.gyro_bias_kf.GyroBiasKF`.

    Parameters
    ----------
    lib : pathlib.Path
        The library (:func:`~iotnav.firmware.pipeline.build`).
    config : GyroBiasConfig, optional
        Noise and guard settings.
    b0 : numpy.ndarray, optional
        Initial bias, rad/s (None: zero).
    double : bool
        ``lib`` is the float64 build.
    """

    def __init__(
        self,
        lib: Path,
        config: GyroBiasConfig | None = None,
        b0: FloatArray | None = None,
        double: bool = False,
    ) -> None:
        super().__init__(lib, double)
        cfg = config or GyroBiasConfig()
        Cfg = ctypes_struct("pl_gyrobias", self.real)
        self._cfg = Cfg(*(getattr(cfg, n) for n, _ in c_fields(GyroBiasConfig)))
        self.state = _state_type("pl_gyrobias", self.real)()
        L = self.lib
        L.pl_gyrobias_init.restype = ctypes.c_int
        L.pl_gyrobias_predict.restype = None
        L.pl_gyrobias_predict.argtypes = [ctypes.c_void_p, self.real]
        L.pl_gyrobias_update.restype = ctypes.c_int
        L.pl_gyrobias_update.argtypes = [ctypes.c_void_p, self.real, self.real, self.real]
        _check_size(L, "pl_gyrobias_sizeof", self.state)
        b = None if b0 is None else (self.real * 3)(*(float(v) for v in b0))
        self.init_rc = int(L.pl_gyrobias_init(ctypes.byref(self.state), ctypes.byref(self._cfg), b))

    def predict(self, dt: float) -> None:
        """:meth:`GyroBiasKF.predict` over ``dt`` s."""
        self.lib.pl_gyrobias_predict(ctypes.byref(self.state), dt)

    def update_static(self, gyro_b: FloatArray) -> bool:
        """:meth:`GyroBiasKF.update_static` with a raw rate (rad/s); False when refused."""
        g = [float(v) for v in gyro_b]
        return bool(self.lib.pl_gyrobias_update(ctypes.byref(self.state), *g))


class TiltBlock(_ThreeStateBlock):
    """One ``pl_tilt_state`` (block 2's tilt KF) driven through :mod:`ctypes`, as
    :class:`~iotnav.techniques.tilt_kf.TiltKF`.

    Parameters
    ----------
    lib : pathlib.Path
        The library (:func:`~iotnav.firmware.pipeline.build`).
    config : TiltConfig, optional
        Tunables.
    x0 : numpy.ndarray, optional
        Initial down axis in ``b`` (None: the first accelerometer sample sets it).
    double : bool
        ``lib`` is the float64 build.
    """

    def __init__(
        self, lib: Path, config: TiltConfig | None = None, x0: FloatArray | None = None, double: bool = False
    ) -> None:
        super().__init__(lib, double)
        cfg = config or TiltConfig()
        Cfg = ctypes_struct("pl_tilt", self.real)
        self._cfg = Cfg(*(getattr(cfg, n) for n, _ in c_fields(TiltConfig)))
        self.state = _state_type("pl_tilt", self.real)()
        L = self.lib
        L.pl_tilt_init.restype = ctypes.c_int
        L.pl_tilt_predict.restype = None
        L.pl_tilt_predict.argtypes = [ctypes.c_void_p, *[self.real] * 5]
        L.pl_tilt_update.restype = ctypes.c_int
        L.pl_tilt_update.argtypes = [ctypes.c_void_p, *[self.real] * 5]
        _check_size(L, "pl_tilt_sizeof", self.state)
        x = None if x0 is None else (self.real * 3)(*(float(v) for v in x0))
        self.init_rc = int(L.pl_tilt_init(ctypes.byref(self.state), ctypes.byref(self._cfg), x))

    def predict(self, omega_b: FloatArray, dt: float, bias_var: float = 0.0) -> None:
        """:meth:`TiltKF.predict`: bias-corrected rate (rad/s), step (s), bias variance ((rad/s)^2)."""
        w = [float(v) for v in omega_b]
        self.lib.pl_tilt_predict(ctypes.byref(self.state), *w, float(dt), float(bias_var))

    def update(self, f_b: FloatArray, g: float, vehicle_acc_mps2: float = 0.0) -> bool:
        """:meth:`TiltKF.update`: specific force (m/s^2), gravity (m/s^2), ``|a_v|`` (m/s^2)."""
        f = [float(v) for v in f_b]
        return bool(self.lib.pl_tilt_update(ctypes.byref(self.state), *f, float(g), float(vehicle_acc_mps2)))

    @property
    def last_nis(self) -> float:
        """:attr:`TiltKF.last_nis`."""
        return float(self.state.nis)


class YawBlock(_ThreeStateBlock):
    """One ``pl_yaw_state`` (block 2's yaw KF) driven through :mod:`ctypes`, as
    :class:`~iotnav.techniques.yaw_kf.YawKF`.

    Parameters
    ----------
    lib : pathlib.Path
        The library (:func:`~iotnav.firmware.pipeline.build`).
    config : YawConfig, optional
        Tunables (the NIS gate from ``gate_probability``, :func:`~iotnav.firmware.pipeline.yaw_gate`).
    double : bool
        ``lib`` is the float64 build.
    """

    def __init__(self, lib: Path, config: YawConfig | None = None, double: bool = False) -> None:
        super().__init__(lib, double)
        cfg = config or YawConfig()
        Cfg = ctypes_struct("pl_yaw", self.real)
        self._cfg = Cfg(*(getattr(cfg, n) for n, _ in c_fields(YawConfig)))
        r = self.real
        self.state = _state_type("pl_yaw", r)()
        L = self.lib
        p3 = ctypes.POINTER(r)
        L.pl_yaw_init.restype = ctypes.c_int
        L.pl_yaw_init.argtypes = [ctypes.c_void_p, ctypes.c_void_p, r]
        L.pl_yaw_predict.restype = None
        L.pl_yaw_predict.argtypes = [ctypes.c_void_p, *[r] * 5]
        L.pl_yaw_reset_heading.restype = None
        L.pl_yaw_reset_heading.argtypes = [ctypes.c_void_p, r, p3, r]
        L.pl_yaw_update_heading.restype = ctypes.c_int
        L.pl_yaw_update_heading.argtypes = [ctypes.c_void_p, r, p3, r]
        L.pl_yaw_update_mag.restype = ctypes.c_int
        L.pl_yaw_update_mag.argtypes = [ctypes.c_void_p, r, r, r, p3]
        L.pl_dcm_rows.restype = None
        L.pl_dcm_rows.argtypes = [p3, p3, p3]
        _check_size(L, "pl_yaw_sizeof", self.state)
        self.init_rc = int(L.pl_yaw_init(ctypes.byref(self.state), ctypes.byref(self._cfg), yaw_gate(cfg)))

    def _v3(self, v: FloatArray) -> Any:
        return (self.real * 3)(*(float(a) for a in v))

    def predict(self, omega_b: FloatArray, dt: float, bias_var: float = 0.0) -> None:
        """:meth:`YawKF.predict`: bias-corrected rate (rad/s), step (s), bias variance ((rad/s)^2)."""
        w = [float(v) for v in omega_b]
        self.lib.pl_yaw_predict(ctypes.byref(self.state), *w, float(dt), float(bias_var))

    def reset_heading(self, psi_b: float, x3: FloatArray, sigma: float | None = None) -> None:
        """:meth:`YawKF.reset_heading`: sensor yaw (rad) at the tilt ``x3``."""
        s = math.nan if sigma is None else float(sigma)
        self.lib.pl_yaw_reset_heading(ctypes.byref(self.state), float(psi_b), self._v3(x3), s)

    def update_heading(self, psi_b: float, x3: FloatArray, sigma: float | None = None) -> bool:
        """:meth:`YawKF.update_heading`: True when applied (False when gated out)."""
        s = math.nan if sigma is None else float(sigma)
        return bool(self.lib.pl_yaw_update_heading(ctypes.byref(self.state), float(psi_b), self._v3(x3), s))

    def update_mag(self, m_b: FloatArray, x3: FloatArray) -> bool:
        """:meth:`YawKF.update_mag`: a magnetometer sample (any unit) at the tilt ``x3``."""
        m = [float(v) for v in m_b]
        return bool(self.lib.pl_yaw_update_mag(ctypes.byref(self.state), *m, self._v3(x3)))

    def dcm(self, x3: FloatArray) -> FloatArray:
        """``pl_dcm_rows`` of :attr:`x` and ``x3``: ``C_nb`` (3, 3), as :func:`~iotnav.techniques.yaw_kf.dcm_from_rows`."""
        C = (self.real * 9)()
        self.lib.pl_dcm_rows(self._v3(self.x), self._v3(x3), C)
        return np.array(C[:], dtype=float).reshape(3, 3)

    @property
    def initialised(self) -> bool:
        """:attr:`YawKF.initialised`."""
        return bool(self.state.initialised)

    @property
    def last_nis(self) -> float:
        """:attr:`YawKF.last_nis`."""
        return float(self.state.nis)


class CascadeBlock(_Block):
    """One ``pl_cascade_state`` (block 2: the gyro-bias, tilt and yaw KFs wired as
    :func:`~iotnav.techniques.cascade.cascade_step`) driven through :mod:`ctypes`, as
    :class:`~iotnav.techniques.cascade.CascadeKF`.

    Parameters
    ----------
    lib : pathlib.Path
        The library (:func:`~iotnav.firmware.pipeline.build`).
    config : CascadeConfig, optional
        The three filters' configurations.
    double : bool
        ``lib`` is the float64 build.
    """

    def __init__(self, lib: Path, config: CascadeConfig | None = None, double: bool = False) -> None:
        from iotnav.techniques.cascade import CascadeConfig

        super().__init__(lib, double)
        cfg = config or CascadeConfig()
        r = self.real
        self._cfgs = [
            ctypes_struct(prefix, r)(*(getattr(c, n) for n, _ in c_fields(type(c))))
            for prefix, c in (("pl_gyrobias", cfg.gyro_bias), ("pl_tilt", cfg.tilt), ("pl_yaw", cfg.yaw))
        ]
        self.state = _state_type("pl_cascade", r)()
        L = self.lib
        L.pl_cascade_init.restype = ctypes.c_int
        L.pl_cascade_init.argtypes = [ctypes.c_void_p] * 4 + [r]
        L.pl_cascade_step.restype = None
        L.pl_cascade_step.argtypes = [ctypes.c_void_p, *[r] * 7, ctypes.c_int, r, r]
        L.pl_cascade_aid_heading.restype = ctypes.c_int
        L.pl_cascade_aid_heading.argtypes = [ctypes.c_void_p, r, r]
        L.pl_cascade_aid_mag.restype = ctypes.c_int
        L.pl_cascade_aid_mag.argtypes = [ctypes.c_void_p, r, r, r]
        L.pl_cascade_rotate_heading.restype = None
        L.pl_cascade_rotate_heading.argtypes = [ctypes.c_void_p, r]
        L.pl_front_end_step.restype = ctypes.c_int
        L.pl_front_end_step.argtypes = [ctypes.c_void_p, ctypes.c_void_p, self.time_t, *[r] * 7, ctypes.c_int]
        L.pl_front_end_step.argtypes += [r, r, r, self.time_t, r, ctypes.POINTER(r)]
        _check_size(L, "pl_cascade_sizeof", self.state)
        cfgs = [ctypes.byref(c) for c in self._cfgs]
        self.init_rc = int(L.pl_cascade_init(ctypes.byref(self.state), *cfgs, yaw_gate(cfg.yaw)))

    def step(
        self,
        acc_b: FloatArray,
        gyro_b: FloatArray,
        dt: float,
        static: bool,
        g: float,
        vehicle_acc_mps2: float = 0.0,
    ) -> FloatArray:
        """:meth:`CascadeKF.step`: specific force (m/s^2), raw rate (rad/s), ``dt`` (s), block 3's
        decision, gravity (m/s^2), ``|a_v|`` (m/s^2); returns ``C_nb`` (3, 3)."""
        a, w = [float(v) for v in acc_b], [float(v) for v in gyro_b]
        st = ctypes.byref(self.state)
        self.lib.pl_cascade_step(st, *a, *w, float(dt), int(bool(static)), float(g), float(vehicle_acc_mps2))
        return self.C_nb

    def front_end_step(
        self,
        det: StaticBlock,
        t: float,
        acc_b: FloatArray,
        gyro_b: FloatArray,
        dt: float,
        static: bool,
        g: float,
        a_long: float,
        v_gnss: float,
        t_speed: float,
        v_dr: float,
    ) -> tuple[float, float, float, bool]:
        """:func:`~iotnav.techniques.cascade.front_end_step` with block 3 ``det`` (same build):
        ``y_n`` (m/s^2, NED) and block 3's new decision; ``t_speed`` NaN or -inf: no GNSS speed yet."""
        a, w = [float(v) for v in acc_b], [float(v) for v in gyro_b]
        ts = self._time(t_speed) if math.isfinite(t_speed) else self.time_t(0, t_speed)
        y = (self.real * 3)()
        now = self.lib.pl_front_end_step(
            ctypes.byref(self.state),
            ctypes.byref(det.state),
            self._time(t),
            *a,
            *w,
            float(dt),
            int(bool(static)),
            float(g),
            float(a_long),
            float(v_gnss),
            ts,
            float(v_dr),
            y,
        )
        return float(y[0]), float(y[1]), float(y[2]), bool(now)

    def aid_heading(self, psi_b: float, sigma: float | None = None) -> bool:
        """:meth:`CascadeKF.aid_heading`: sensor yaw (rad)."""
        s = math.nan if sigma is None else float(sigma)
        return bool(self.lib.pl_cascade_aid_heading(ctypes.byref(self.state), float(psi_b), s))

    def aid_mag(self, m_b: FloatArray) -> bool:
        """:meth:`CascadeKF.aid_mag`."""
        return bool(self.lib.pl_cascade_aid_mag(ctypes.byref(self.state), *(float(v) for v in m_b)))

    def rotate_heading(self, delta_rad: float) -> None:
        """:meth:`CascadeKF.rotate_heading`."""
        self.lib.pl_cascade_rotate_heading(ctypes.byref(self.state), float(delta_rad))

    @property
    def C_nb(self) -> FloatArray:
        """``C_nb`` (3, 3), a copy."""
        return np.array(self.state.C[:], dtype=float).reshape(3, 3)

    @property
    def omega_b(self) -> FloatArray:
        """The latest bias-corrected rate, rad/s."""
        return np.array(self.state.omega[:], dtype=float)

    def filter_states(self) -> FloatArray:
        """The bias, tilt and yaw filters' ``x`` and ``P`` (36 values: x, P of each in that order)."""
        out = []
        for f in (self.state.bias, self.state.tilt, self.state.yaw):
            out += list(f.x[:]) + list(f.P[:])
        return np.array(out, dtype=float)
