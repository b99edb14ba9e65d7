"""Input pre-processing: the cascaded Kalman filter (Forno et al. 2020, block 2, Fig. 2).

Composition (after Zihajehzadeh et al. 2015) of three [n, m, p] = [3, 3, 3] filters run at
the IMU rate, in this order for each sample with bias-corrected rate
``omega_b = omega_meas_b - b_g``:

1. gyro-bias KF (:mod:`~iotnav.techniques.gyro_bias_kf`): predict; update with the raw
   gyroscope while the static detector (block 3) says static;
2. tilt KF (:mod:`~iotnav.techniques.tilt_kf`): predict with ``omega_b``, update with the
   accelerometer -> third row ``x3`` of ``C_nb``;
3. yaw KF (:mod:`~iotnav.techniques.yaw_kf`): predict with ``omega_b``; aided by the GPS
   course plus the mount angle of block 5 (or the magnetometer) when available -> first row
   ``x1`` of ``C_nb``.

Output: ``C_nb = [x1; x3 x x1; x3]`` (re-orthonormalised) at the IMU rate.

The per-sample step is the compiled :func:`cascade_step` on the three filters' state arrays
(:mod:`iotnav.techniques.kf3`); :meth:`CascadeKF.step` and the engines' compiled IMU kernels
call the same function (STYLE §7). The course and magnetometer aids run at the GNSS rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numba
import numpy as np
import numpy.typing as npt

from iotnav.techniques.gyro_bias_kf import GyroBiasConfig, GyroBiasKF, gyro_bias_predict, gyro_bias_update
from iotnav.techniques.static import StaticDetector, static_step
from iotnav.techniques.tilt_kf import TiltConfig, TiltKF, tilt_predict, tilt_update
from iotnav.techniques.yaw_kf import YawConfig, YawKF, dcm_from_rows, dcm_rows_into, yaw_of_dcm, yaw_predict

FloatArray = npt.NDArray[np.float64]

#: The cascade's own state array: ``C_nb`` (row-major, 9) then the corrected rate ``omega_b`` (3).
CS_C, CS_OMEGA = 0, 9
STATE_SIZE = 12


@dataclass(frozen=True)
class CascadeConfig:
    """The three filters' configurations."""

    tilt: TiltConfig = field(default_factory=TiltConfig)
    yaw: YawConfig = field(default_factory=YawConfig)
    gyro_bias: GyroBiasConfig = field(default_factory=GyroBiasConfig)


@numba.njit(cache=True)
def cascade_step(
    bias_s: FloatArray,
    bias_p: FloatArray,
    tilt_s: FloatArray,
    tilt_p: FloatArray,
    yaw_s: FloatArray,
    yaw_p: FloatArray,
    cs: FloatArray,
    ax: float,
    ay: float,
    az: float,
    gx: float,
    gy: float,
    gz: float,
    dt: float,
    static: bool,
    g: float,
    a_veh: float,
) -> None:
    """Block 2 for one IMU sample on the filters' state arrays (compiled, in place).

    Parameters
    ----------
    bias_s, bias_p, tilt_s, tilt_p, yaw_s, yaw_p : numpy.ndarray
        State and parameter arrays of the gyro-bias, tilt and yaw filters.
    cs : numpy.ndarray
        Cascade state (``CS_*`` layout): receives ``C_nb`` and ``omega_b``.
    ax, ay, az : float
        Specific force in ``b``, m/s^2.
    gx, gy, gz : float
        Raw angular rate in ``b``, rad/s.
    dt : float
        Time since the previous sample, s (0 for the first).
    static : bool
        Block 3's decision (enables the gyro-bias update).
    g : float
        Gravity magnitude, m/s^2.
    a_veh : float
        Vehicle acceleration magnitude from GNSS and gyro, m/s^2.
    """
    gyro_bias_predict(bias_s, bias_p, dt)
    if static:
        gyro_bias_update(bias_s, bias_p, gx, gy, gz)
    wx, wy, wz = gx - bias_s[0], gy - bias_s[1], gz - bias_s[2]
    cs[CS_OMEGA] = wx
    cs[CS_OMEGA + 1] = wy
    cs[CS_OMEGA + 2] = wz
    bias_var = (bias_s[3] + bias_s[7] + bias_s[11]) / 3.0
    tilt_predict(tilt_s, tilt_p, wx, wy, wz, dt, bias_var)
    tilt_update(tilt_s, tilt_p, ax, ay, az, g, a_veh)
    yaw_predict(yaw_s, yaw_p, wx, wy, wz, dt, bias_var)
    dcm_rows_into(yaw_s[0:3], tilt_s[0:3], cs[CS_C : CS_C + 9])
    yaw_s[0] = cs[CS_C]
    yaw_s[1] = cs[CS_C + 1]
    yaw_s[2] = cs[CS_C + 2]


class FrontEnd(NamedTuple):
    """The state and parameter arrays of blocks 2 and 3, passed to compiled kernels as one record.

    The gyro-bias, tilt and yaw KFs' ``state`` / ``params`` (:mod:`~iotnav.techniques.kf3`
    layouts), the cascade's own ``state`` (``CS_*``: ``C_nb`` row-major, the bias-corrected
    rate in rad/s) and the static detector's ``state``, ``speeds`` ring and ``params``
    (:mod:`~iotnav.techniques.static`). The arrays are the filters' own (views, not copies):
    a kernel that steps them updates the Python objects. Build it with :func:`front_end`.
    """

    bias_s: FloatArray
    bias_p: FloatArray
    tilt_s: FloatArray
    tilt_p: FloatArray
    yaw_s: FloatArray
    yaw_p: FloatArray
    cs: FloatArray
    stat_s: FloatArray
    speeds: FloatArray
    stat_p: FloatArray


def front_end(cascade: CascadeKF, detector: StaticDetector) -> FrontEnd:
    """The :class:`FrontEnd` record of a cascade (block 2) and a static detector (block 3)."""
    return FrontEnd(
        cascade.bias.state,
        cascade.bias.params,
        cascade.tilt.state,
        cascade.tilt.params,
        cascade.yaw.state,
        cascade.yaw.params,
        cascade.state,
        detector.state,
        detector.speeds,
        detector.params,
    )


@numba.njit(cache=True)
def front_end_step(
    fe: FrontEnd,
    t: float,
    ax: float,
    ay: float,
    az: float,
    gx: float,
    gy: float,
    gz: float,
    dt: float,
    static: bool,
    g: float,
    a_long: float,
    v_gnss: float,
    t_speed: float,
    v_dr: float,
) -> tuple[float, float, float, bool]:
    """Blocks 2 and 3 for one IMU sample, as the pipeline and the anchor engine run them.

    The vehicle acceleration that de-weights the tilt filter is ``hypot(a_long, v r)`` from the
    GNSS speed rate ``a_long`` (m/s^2), speed ``v_gnss`` (m/s) and the previous sample's yaw
    rate ``r`` while the speed is at most 2.5 s old (``t_speed``), and ``|v_dr r|`` with the
    filter's horizontal speed ``v_dr`` (m/s) when it is older (GNSS outage: without it a turn
    in a tunnel tilts the filter towards the centripetal acceleration); then
    :func:`cascade_step` gives ``C_nb``, ``y_n = C_nb y_b`` and
    :func:`~iotnav.techniques.static.static_step` the static decision (``v_dr`` again for stale
    GNSS speed).

    Returns
    -------
    tuple
        ``y_n`` North, East, Down (m/s^2) and the new static decision.
    """
    cs = fe.cs
    C = cs[CS_C : CS_C + 9]
    r_prev = C[6] * cs[CS_OMEGA] + C[7] * cs[CS_OMEGA + 1] + C[8] * cs[CS_OMEGA + 2]
    if t - t_speed <= 2.5:
        a_veh = math.hypot(a_long, v_gnss * r_prev)
    elif math.isfinite(v_dr):
        # GNSS speed stale (an outage, a tunnel): the centripetal part from the filter's own
        # speed, so that a turn does not tilt the filter towards the centripetal acceleration
        a_veh = abs(v_dr * r_prev)
    else:
        a_veh = 0.0
    cascade_step(
        fe.bias_s,
        fe.bias_p,
        fe.tilt_s,
        fe.tilt_p,
        fe.yaw_s,
        fe.yaw_p,
        cs,
        ax,
        ay,
        az,
        gx,
        gy,
        gz,
        dt,
        static,
        g,
        a_veh,
    )
    f0 = C[0] * ax + C[1] * ay + C[2] * az
    f1 = C[3] * ax + C[4] * ay + C[5] * az
    f2 = C[6] * ax + C[7] * ay + C[8] * az
    return f0, f1, f2, static_step(fe.stat_s, fe.speeds, fe.stat_p, t, f0, f1, v_dr)


@numba.njit(cache=True)
def _cascade_run(
    bias_s: FloatArray,
    bias_p: FloatArray,
    tilt_s: FloatArray,
    tilt_p: FloatArray,
    yaw_s: FloatArray,
    yaw_p: FloatArray,
    cs: FloatArray,
    acc: FloatArray,
    gyr: FloatArray,
    dt: float,
    static: npt.NDArray[np.bool_],
    g: float,
) -> FloatArray:
    n = acc.shape[0]
    out = np.empty((n, 9))
    for k in range(n):
        cascade_step(
            bias_s,
            bias_p,
            tilt_s,
            tilt_p,
            yaw_s,
            yaw_p,
            cs,
            acc[k, 0],
            acc[k, 1],
            acc[k, 2],
            gyr[k, 0],
            gyr[k, 1],
            gyr[k, 2],
            dt if k > 0 else 0.0,
            static[k],
            g,
            0.0,
        )
        out[k] = cs[CS_C : CS_C + 9]
    return out


class CascadeKF:
    """Block 2: tilt, yaw and gyro-bias filters producing ``C_nb`` at the IMU rate.

    Hot state: the three filters' :attr:`state` arrays and :attr:`state` here (``CS_*``);
    ``C_nb`` (3, 3) and ``omega_b`` (3,) are views of it.
    """

    def __init__(self, config: CascadeConfig | None = None) -> None:
        self.config = config or CascadeConfig()
        self.tilt = TiltKF(self.config.tilt)
        self.yaw = YawKF(self.config.yaw)
        self.bias = GyroBiasKF(self.config.gyro_bias)
        self.state = np.zeros(STATE_SIZE)
        self.C_nb = np.eye(3)

    @property
    def C_nb(self) -> FloatArray:
        """Latest ``C_nb`` (view)."""
        return self.state[CS_C : CS_C + 9].reshape(3, 3)

    @C_nb.setter
    def C_nb(self, value: FloatArray) -> None:
        self.state[CS_C : CS_C + 9] = np.asarray(value, float).reshape(9)

    @property
    def omega_b(self) -> FloatArray:
        """Latest bias-corrected angular rate in ``b``, rad/s (view)."""
        return self.state[CS_OMEGA : CS_OMEGA + 3]

    def step(
        self,
        acc_b: FloatArray,
        gyro_b: FloatArray,
        dt: float,
        static: bool,
        g: float,
        vehicle_acc_mps2: float = 0.0,
    ) -> FloatArray:
        """Process one IMU sample (runs :func:`cascade_step`).

        Parameters
        ----------
        acc_b : numpy.ndarray
            Specific force in ``b``, m/s^2.
        gyro_b : numpy.ndarray
            Raw angular rate in ``b``, rad/s.
        dt : float
            Time since the previous sample, s (0 for the first).
        static : bool
            Block 3's decision (enables the gyro-bias update).
        g : float
            Gravity magnitude, m/s^2.
        vehicle_acc_mps2 : float
            Vehicle acceleration magnitude known from GNSS and gyro (see the tilt filter), m/s^2.

        Returns
        -------
        numpy.ndarray
            ``C_nb`` (3, 3), a copy.
        """
        a = np.asarray(acc_b, float)
        w = np.asarray(gyro_b, float)
        cascade_step(
            self.bias.state,
            self.bias.params,
            self.tilt.state,
            self.tilt.params,
            self.yaw.state,
            self.yaw.params,
            self.state,
            float(a[0]),
            float(a[1]),
            float(a[2]),
            float(w[0]),
            float(w[1]),
            float(w[2]),
            float(dt),
            bool(static),
            float(g),
            float(vehicle_acc_mps2),
        )
        return self.C_nb.copy()

    def aid_heading(self, psi_b: float, sigma: float | None = None) -> bool:
        """Course aiding: sensor yaw ``psi_b`` = course + mount angle (rad)."""
        ok = self.yaw.update_heading(psi_b, self.tilt.x, sigma)
        self.C_nb = dcm_from_rows(self.yaw.x, self.tilt.x)
        return ok

    def aid_mag(self, m_b: FloatArray) -> bool:
        """Magnetometer aiding (Zihajehzadeh's original form)."""
        ok = self.yaw.update_mag(m_b, self.tilt.x)
        self.C_nb = dcm_from_rows(self.yaw.x, self.tilt.x)
        return ok

    def rotate_heading(self, delta_rad: float) -> None:
        """Add ``delta_rad`` to the sensor yaw (used when the mount estimate changes)."""
        if self.yaw.initialised:
            self.yaw.reset_heading(yaw_of_dcm(self.C_nb) + delta_rad, self.tilt.x, float(np.sqrt(self.P_yaw)))
            self.C_nb = dcm_from_rows(self.yaw.x, self.tilt.x)

    @property
    def P_yaw(self) -> float:
        """Approximate heading variance, rad^2 (trace of the yaw state covariance)."""
        return float(np.trace(self.yaw.P))

    @property
    def sensor_yaw(self) -> float:
        """Sensor yaw, rad."""
        return yaw_of_dcm(self.C_nb)


def run_cascade_imu(
    acc_b: FloatArray,
    gyr_b: FloatArray,
    fs_hz: float,
    static: npt.NDArray[np.bool_],
    g: float = 9.81,
    config: CascadeConfig | None = None,
) -> FloatArray:
    """Block 2 alone over an IMU recording (no GNSS aid): a compiled loop over :func:`cascade_step`.

    Parameters
    ----------
    acc_b, gyr_b : numpy.ndarray
        ``(N, 3)`` specific force (m/s^2) and raw angular rate (rad/s) in ``b``.
    fs_hz : float
        Sampling rate, Hz (constant; the first sample gets ``dt = 0`` as in :meth:`CascadeKF.step`).
    static : numpy.ndarray
        ``(N,)`` bool, the static decision per sample (enables the gyro-bias update).
    g : float
        Gravity magnitude, m/s^2.
    config : CascadeConfig, optional
        The three filters' configurations.

    Returns
    -------
    numpy.ndarray
        ``(N, 3, 3)`` ``C_nb`` per sample, the same as :meth:`CascadeKF.step` sample by sample.
    """
    kf = CascadeKF(config)
    acc = np.ascontiguousarray(acc_b, dtype=float)
    gyr = np.ascontiguousarray(gyr_b, dtype=float)
    st = np.ascontiguousarray(static, dtype=np.bool_)
    if acc.shape != gyr.shape or acc.ndim != 2 or acc.shape[1] != 3 or st.shape != (len(acc),):
        raise ValueError(f"acc/gyr must be (N, 3) and static (N,); got {acc.shape}, {gyr.shape}, {st.shape}")
    out = _cascade_run(
        kf.bias.state,
        kf.bias.params,
        kf.tilt.state,
        kf.tilt.params,
        kf.yaw.state,
        kf.yaw.params,
        kf.state,
        acc,
        gyr,
        1.0 / fs_hz,
        st,
        float(g),
    )
    return out.reshape(-1, 3, 3)
