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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from iotnav.techniques.gyro_bias_kf import GyroBiasConfig, GyroBiasKF
from iotnav.techniques.tilt_kf import TiltConfig, TiltKF
from iotnav.techniques.yaw_kf import YawConfig, YawKF, dcm_from_rows, yaw_of_dcm

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class CascadeConfig:
    """The three filters' configurations."""

    tilt: TiltConfig = field(default_factory=TiltConfig)
    yaw: YawConfig = field(default_factory=YawConfig)
    gyro_bias: GyroBiasConfig = field(default_factory=GyroBiasConfig)


class CascadeKF:
    """Block 2: tilt, yaw and gyro-bias filters producing ``C_nb`` at the IMU rate."""

    def __init__(self, config: CascadeConfig | None = None) -> None:
        self.config = config or CascadeConfig()
        self.tilt = TiltKF(self.config.tilt)
        self.yaw = YawKF(self.config.yaw)
        self.bias = GyroBiasKF(self.config.gyro_bias)
        self.C_nb = np.eye(3)
        self.omega_b = np.zeros(3)

    def step(
        self,
        acc_b: FloatArray,
        gyro_b: FloatArray,
        dt: float,
        static: bool,
        g: float,
        vehicle_acc_mps2: float = 0.0,
    ) -> FloatArray:
        """Process one IMU sample.

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
            ``C_nb`` (3, 3).
        """
        self.bias.predict(dt)
        if static:
            self.bias.update_static(gyro_b)
        self.omega_b = gyro_b - self.bias.x
        bias_var = float(np.trace(self.bias.P)) / 3.0
        self.tilt.predict(self.omega_b, dt, bias_var)
        self.tilt.update(acc_b, g, vehicle_acc_mps2)
        self.yaw.predict(self.omega_b, dt, bias_var)
        self.C_nb = dcm_from_rows(self.yaw.x, self.tilt.x)
        self.yaw.x = self.C_nb[0].copy()
        return self.C_nb

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
