"""Yaw mounting-angle alignment from the non-holonomic constraint (Forno et al. 2020, block 5).

Convention: ``mount_yaw_rad`` is the angle of the sensor x axis from the vehicle's forward
axis, positive clockwise seen from above (as NED yaw), so ``sensor yaw = vehicle yaw +
mount_yaw`` and ``C_nv = C_nb R_z(mount_yaw)^T``.

Both methods work in the *levelled sensor frame* ``s``: the horizontal frame whose x axis is
the horizontal projection of the sensor x axis, ``a_s = (R_z(psi_b)^T C_nb f_b)[:2]`` (only
tilt enters). A horizontal vehicle-frame vector ``a_v`` appears there as
``a_s = R(-mount_yaw) a_v``.

Published method, ``method="paper"`` (Eqs. 2-3)
    While moving (not static), buffer the GPS course ``alpha`` and the accelerometer; when the
    buffer is full and ``var(alpha) < theta_alpha`` (a straight stretch)::

        [a_x a_y a_z]^T = R_b^n mean(y_b) - g_n                  (2)
        eps_alpha = arctan(a_y / a_x)                              (3)

    ``R_b^n`` is read here as the levelling (tilt) part of ``C_nb``: with the yaw included the
    angle would be measured from North instead of the sensor axis. On a straight the vehicle
    acceleration is longitudinal, so in our convention ``mount_yaw = -atan2(a_y, a_x)``.
    Ambiguities of the published form, resolved here: ``arctan`` of a ratio is only defined
    modulo pi -- braking (``a_v`` pointing backwards) flips the result by pi, so the sign of
    the GPS speed change over the buffer selects the branch (``+ pi`` when braking); and on a
    constant-speed straight the mean acceleration is ~0, so the estimate is accepted only when
    ``|a| >= min_accel_mps2`` and its signal-to-noise ratio ``|a| / (sigma_a / sqrt(N))``
    reaches ``min_snr``. Each estimate replaces the previous one (as in the paper).

Robust default, ``method="lsq"`` (designed here)
    On a straight at constant speed the horizontal specific force is ~0, and no function of
    accelerometer, gyroscope and GPS recorded there depends on the mount angle (rotating
    the sensor about the vertical changes nothing measurable): that stretch is unobservable
    for any method without an absolute heading sensor. Gyro-integrated sensor heading
    compared with the course does not help either, because without a magnetometer the
    absolute sensor heading is itself course + mount. What *is* observable is every
    horizontal acceleration of the vehicle, longitudinal *and centripetal*, whose
    vehicle-frame value follows from GPS and the gyroscope alone (mount-independent)::

        a_v = [dv/dt, v r],   r = x3 . omega_b  (yaw rate about the down axis, rad/s)

    with ``dv/dt`` from consecutive GPS speeds. Per GPS interval the IMU samples give the
    mean ``a_s`` and mean ``r``; over a buffer of intervals the rotation that best maps
    ``a_v`` onto ``a_s`` (2-D Procrustes, least squares) is::

        mount_yaw = atan2(sum (a_s x a_v)_z, sum a_s . a_v)

    Sums are accumulated over all accepted buffers with a forgetting factor, so the estimate
    uses the U-turns of a lap as well as accelerating or braking straights, needs no sign
    resolution, and keeps improving. Quality reported with each estimate: the coherence
    ``rho = |sum a_s a_v^*| / sqrt(sum |a_s|^2 sum |a_v|^2)`` (1 = perfect), the excitation
    ``rms |a_v|`` (m/s^2) and an approximate standard deviation ``sigma = rms residual /
    sqrt(sum |a_v|^2)`` (rad).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Columns of the interval buffer.
AS_X, AS_Y, DV, DT, V_MEAN, R_MEAN, COURSE, N_IMU, AS_SQ = range(9)
N_COLS = 9


@dataclass(frozen=True)
class MountConfig:
    """Mount-alignment tunables (SI).

    Attributes
    ----------
    method : {"lsq", "paper"}
        Robust least squares over longitudinal and centripetal acceleration, or Eqs. 2-3.
    buffer_epochs : int
        GPS intervals per buffer.
    theta_alpha_rad2 : float
        Course variance threshold of a straight stretch, rad^2 (paper method).
    min_speed_mps : float
        Both GPS speeds of an interval must reach this, m/s.
    min_accel_mps2 : float
        Minimum mean acceleration (paper) or rms vehicle acceleration (lsq), m/s^2.
    min_snr : float
        Minimum ``|a| / (sigma_a / sqrt(N))`` of the paper method.
    min_coherence : float
        Minimum buffer coherence of the lsq method.
    forget : float
        Factor applied to the accumulated lsq sums before adding a buffer (1: no forgetting).
    max_interval_s : float
        Longer GPS intervals break the buffer, s.
    initial_mount_yaw_rad : float
        Mount angle used before the first estimate (or a stored one-off calibration), rad.
    one_off : bool
        Stop after the first accepted estimate (the paper's one-off calibration).
    """

    method: Literal["lsq", "paper"] = "lsq"
    buffer_epochs: int = 8
    theta_alpha_rad2: float = 0.003
    min_speed_mps: float = 2.0
    min_accel_mps2: float = 0.3
    min_snr: float = 3.0
    min_coherence: float = 0.7
    forget: float = 0.95
    max_interval_s: float = 2.5
    initial_mount_yaw_rad: float = 0.0
    one_off: bool = False


def wrap(a: float) -> float:
    """Wrap an angle (rad) to (-pi, pi]."""
    w = math.atan2(math.sin(a), math.cos(a))
    return math.pi if w == -math.pi else w


def paper_estimate(a_s_mean: FloatArray, speed_change_mps: float) -> tuple[float, float]:
    """Eq. 3 in the package convention.

    Parameters
    ----------
    a_s_mean : numpy.ndarray
        Mean horizontal acceleration in the levelled sensor frame, ``[a_x, a_y]`` m/s^2.
    speed_change_mps : float
        GPS speed change over the buffer, m/s (negative: braking).

    Returns
    -------
    mount_yaw_rad, literal_rad : float
        The sign-resolved mount angle, and the literal ``arctan(a_y / a_x)`` of Eq. 3.
    """
    ax, ay = float(a_s_mean[0]), float(a_s_mean[1])
    literal = math.atan(ay / ax) if ax != 0.0 else math.copysign(math.pi / 2, ay)
    mu = -math.atan2(ay, ax)
    if speed_change_mps < 0.0:
        mu += math.pi
    return wrap(mu), literal


def lsq_sums(a_s: FloatArray, a_v: FloatArray) -> FloatArray:
    """``[sum cross, sum dot, sum |a_v|^2, sum |a_s|^2]`` for rows of 2-D vectors (m/s^2)."""
    cross = a_s[:, 0] * a_v[:, 1] - a_s[:, 1] * a_v[:, 0]
    dot = a_s[:, 0] * a_v[:, 0] + a_s[:, 1] * a_v[:, 1]
    return np.array([cross.sum(), dot.sum(), (a_v**2).sum(), (a_s**2).sum()])


def lsq_estimate(sums: FloatArray, n: int) -> tuple[float, dict[str, float]]:
    """Mount angle (rad) and quality figures from :func:`lsq_sums` over ``n`` rows."""
    c, d, evv, ess = (float(v) for v in sums)
    h = math.hypot(c, d)
    mu = math.atan2(c, d)
    coh = h / math.sqrt(evv * ess) if evv > 0 and ess > 0 else 0.0
    res = max(ess + evv - 2.0 * h, 0.0) / max(n, 1)
    sigma = math.sqrt(res) / math.sqrt(evv) * math.sqrt(max(n, 1)) if evv > 0 else math.inf
    return mu, {
        "coherence": coh,
        "excitation_mps2": math.sqrt(evv / max(n, 1)),
        "std_rad": min(sigma, math.pi),
        "n": float(n),
    }


class MountAligner:
    """Block 5; hot state in a numpy interval buffer and accumulators.

    Feed every IMU sample with :meth:`add_imu` and every GPS epoch with :meth:`add_gnss`.
    """

    def __init__(self, config: MountConfig | None = None) -> None:
        self.config = config or MountConfig()
        c = self.config
        self.mount_yaw_rad = c.initial_mount_yaw_rad
        self.known = False
        self.quality: dict[str, float] = {}
        self.buf = np.zeros((max(2, c.buffer_epochs), N_COLS))
        self.k = 0
        self.acc = np.zeros(4)  # accumulated lsq sums
        self.n_acc = 0.0
        self._int = np.zeros(4)  # sum a_s x, a_s y, r, |a_s|^2 over the current interval
        self._n = 0
        self._t_prev = math.nan
        self._v_prev = math.nan
        self._v_start = math.nan
        self.done = False

    def add_imu(self, a_s: FloatArray, r: float) -> None:
        """Accumulate one IMU sample: levelled horizontal specific force (m/s^2), yaw rate (rad/s)."""
        self._int[0] += a_s[0]
        self._int[1] += a_s[1]
        self._int[2] += r
        self._int[3] += a_s[0] * a_s[0] + a_s[1] * a_s[1]
        self._n += 1

    def _break(self) -> None:
        self.k = 0

    def add_gnss(
        self, t: float, speed_mps: float, course_rad: float, course_valid: bool, static: bool
    ) -> dict[str, Any] | None:
        """Close the current GPS interval; evaluate the buffer when full.

        Returns
        -------
        dict or None
            An estimate event ``{"t", "mount_yaw_rad", "accepted", "method", quality...}`` when a
            buffer was evaluated, else None.
        """
        c = self.config
        ok_prev = math.isfinite(self._v_prev)
        dt = t - self._t_prev
        good = (
            ok_prev
            and math.isfinite(speed_mps)
            and course_valid
            and not static
            and self._n > 0
            and 0.0 < dt <= c.max_interval_s
            and min(speed_mps, self._v_prev) >= c.min_speed_mps
        )
        event = None
        if good and not self.done:
            if self.k == 0:
                self._v_start = self._v_prev
            row = self.buf[self.k]
            row[AS_X] = self._int[0] / self._n
            row[AS_Y] = self._int[1] / self._n
            row[DV] = speed_mps - self._v_prev
            row[DT] = dt
            row[V_MEAN] = 0.5 * (speed_mps + self._v_prev)
            row[R_MEAN] = self._int[2] / self._n
            row[COURSE] = course_rad
            row[N_IMU] = self._n
            row[AS_SQ] = self._int[3]
            self.k += 1
            if self.k == self.buf.shape[0]:
                event = self._evaluate(t, speed_mps)
                self.k = 0
        elif not good and c.method == "paper":
            self._break()
        self._int[:] = 0.0
        self._n = 0
        self._t_prev = t
        self._v_prev = speed_mps if math.isfinite(speed_mps) else math.nan
        return event

    def _evaluate(self, t: float, speed_mps: float) -> dict[str, Any]:
        c = self.config
        b = self.buf
        if c.method == "paper":
            dev = np.array([wrap(a - b[0, COURSE]) for a in b[:, COURSE]])
            course_var = float(np.var(dev))
            n_tot = float(b[:, N_IMU].sum())
            a_bar = np.array([(b[:, AS_X] * b[:, N_IMU]).sum(), (b[:, AS_Y] * b[:, N_IMU]).sum()]) / n_tot
            var_a = max(float(b[:, AS_SQ].sum()) / n_tot - float(a_bar @ a_bar), 1e-12)
            mag = float(np.linalg.norm(a_bar))
            snr = mag / math.sqrt(var_a / n_tot)
            dv = speed_mps - self._v_start
            mu, literal = paper_estimate(a_bar, dv)
            accepted = course_var < c.theta_alpha_rad2 and mag >= c.min_accel_mps2 and snr >= c.min_snr
            quality = {
                "course_var_rad2": course_var,
                "accel_mps2": mag,
                "snr": snr,
                "speed_change_mps": dv,
                "literal_eq3_rad": literal,
            }
        else:
            a_s = b[:, [AS_X, AS_Y]]
            a_v = np.column_stack([b[:, DV] / b[:, DT], b[:, V_MEAN] * b[:, R_MEAN]])
            sums = lsq_sums(a_s, a_v)
            mu_buf, q_buf = lsq_estimate(sums, b.shape[0])
            accepted = q_buf["excitation_mps2"] >= c.min_accel_mps2 and q_buf["coherence"] >= c.min_coherence
            if accepted:
                self.acc = c.forget * self.acc + sums
                self.n_acc = c.forget * self.n_acc + b.shape[0]
            mu, quality = lsq_estimate(self.acc, round(self.n_acc)) if self.n_acc > 0 else (mu_buf, q_buf)
            quality = {**quality, "buffer_mount_yaw_rad": mu_buf, "buffer_coherence": q_buf["coherence"]}
        event: dict[str, Any] = {
            "type": "mount_estimate",
            "t": t,
            "method": c.method,
            "accepted": bool(accepted),
            "mount_yaw_rad": float(mu) if accepted else self.mount_yaw_rad,
            "candidate_rad": float(mu),
            **quality,
        }
        if accepted:
            self.mount_yaw_rad = float(mu)
            self.known = True
            self.quality = quality
            if c.one_off:
                self.done = True
        return event
