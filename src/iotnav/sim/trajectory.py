"""Trajectories from motion primitives, and the true IMU signals that reproduce them.

Construction (vectorised, at the internal truth rate ``R``, samples ``t_k = k / R``)
---------------------------------------------------------------------------------
:class:`TrajectoryBuilder` appends motion primitives (stand, change speed, cruise, turn at a
rate, arc of a radius, slope, straights with an accelerate/brake profile). Each primitive
writes, per sample, the along-track speed ``s_k`` (m/s), the yaw rate ``r_k`` (rad/s) and the
vehicle pitch (grade) ``theta_k``. Overlays add the walking gait (vertical bob at the step
frequency, lateral sway at the stride frequency, a forward surge, small body roll/pitch) as a
velocity perturbation ``dv`` in the heading frame, and a slowly varying carry attitude (bag).
Then

* heading ``psi_{k+1} = psi_k + r_k / R`` (a turn of ``n`` samples turns by exactly its angle);
* velocity ``v_n = s [cos(theta) cos(psi), cos(theta) sin(psi), -sin(theta)] + R_z(psi) dv``;
* position by the trapezoidal rule, ``p_{k+1} = p_k + (v_k + v_{k+1}) / (2 R)``;
* vehicle attitude ``C_nv = euler_to_dcm(roll, pitch, yaw)``, sensor attitude
  ``C_nb = C_nv @ C_vb @ C_carry`` (mount, then carry);

and the true IMU signals (:func:`derive_imu`), sample ``k`` being the mean over
``[t_k, t_{k+1})``:

* ``omega_b_k = log(C_nb_k^T C_nb_{k+1}) R`` (rotation vector, rad/s);
* ``f_b_k = (C_nb_k exp([omega_b_k / (2R) x]))^T ((v_{k+1} - v_k) R - g_n)``.

These are the inverse of the discretisation of :mod:`iotnav.strapdown`, so integrating the true
``f_b``, ``omega_b`` from the true initial state reproduces the truth to rounding error
(consistent by construction). Angular rate and specific force are piecewise constant on the
``1/R`` grid, as a real IMU's delta-angle / delta-velocity outputs are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

FloatArray = npt.NDArray[np.float64]

__all__ = ["Profile", "TrajectoryBuilder", "Truth", "add_gait", "bag_carry", "derive_imu", "make_truth"]


@dataclass
class Profile:
    """Per-sample motion description at the internal rate.

    Attributes
    ----------
    rate_hz : float
        Internal rate ``R``.
    speed : numpy.ndarray
        Along-track speed, m/s, ``(N,)``.
    yaw_rate : numpy.ndarray
        Heading rate, rad/s (positive clockwise seen from above), ``(N,)``.
    pitch, roll : numpy.ndarray
        Vehicle pitch (grade) and roll, rad, ``(N,)``.
    heading0 : float
        Initial heading, rad.
    dv_h : numpy.ndarray or None
        Velocity perturbation in the heading frame (x forward, y right, z down), m/s, ``(N, 3)``.
    body_pitch : numpy.ndarray or None
        Pitch of the body added to the grade (gait), rad, ``(N,)``; does not tilt the velocity.
    """

    rate_hz: float
    speed: FloatArray
    yaw_rate: FloatArray
    pitch: FloatArray
    roll: FloatArray
    heading0: float
    dv_h: FloatArray | None = None
    body_pitch: FloatArray | None = None

    @property
    def n(self) -> int:
        """Number of samples."""
        return len(self.speed)

    @property
    def t(self) -> FloatArray:
        """Sample times, s."""
        return np.arange(self.n) / self.rate_hz


class TrajectoryBuilder:
    """Append motion primitives; :meth:`build` returns a :class:`Profile`.

    Parameters
    ----------
    rate_hz : float
        Internal rate, Hz.
    heading_rad : float
        Initial heading (clockwise from North), rad.
    """

    def __init__(self, rate_hz: float, heading_rad: float = 0.0) -> None:
        self.rate = float(rate_hz)
        self.heading0 = float(heading_rad)
        self.speed = 0.0
        self.grade = 0.0
        self._s: list[FloatArray] = []
        self._r: list[FloatArray] = []
        self._p: list[FloatArray] = []

    @property
    def duration_s(self) -> float:
        """Duration of the primitives appended so far, s."""
        return sum(len(a) for a in self._s) / self.rate

    def _n(self, duration_s: float) -> int:
        return max(round(duration_s * self.rate), 0)

    def _push(self, s: FloatArray, r: FloatArray | float, p: FloatArray | float) -> None:
        n = len(s)
        self._s.append(np.asarray(s, float))
        self._r.append(np.broadcast_to(np.asarray(r, float), (n,)).copy())
        self._p.append(np.broadcast_to(np.asarray(p, float), (n,)).copy())

    def stand(self, duration_s: float) -> TrajectoryBuilder:
        """Stand still (speed 0) for ``duration_s``."""
        if self.speed != 0.0:
            raise ValueError("stand() needs speed 0: decelerate first")
        n = self._n(duration_s)
        self._push(np.zeros(n), 0.0, self.grade)
        return self

    def change_speed(
        self, to_speed_mps: float, accel_mps2: float, yaw_rate_rad_s: float = 0.0
    ) -> TrajectoryBuilder:
        """Accelerate or brake to ``to_speed_mps`` with a raised-cosine speed profile.

        The mean acceleration magnitude is ``accel_mps2`` (peak ``pi/2`` times that).
        """
        dv = to_speed_mps - self.speed
        if dv == 0.0:
            return self
        n = max(self._n(abs(dv) / accel_mps2), 1)
        u = np.arange(n) / n
        s = self.speed + dv * 0.5 * (1.0 - np.cos(np.pi * u))
        self._push(s, yaw_rate_rad_s, self.grade)
        self.speed = float(to_speed_mps)
        return self

    def cruise(self, duration_s: float | None = None, distance_m: float | None = None) -> TrajectoryBuilder:
        """Keep speed and heading for a time or a distance."""
        if distance_m is not None:
            if self.speed <= 0.0:
                raise ValueError("cruise(distance_m=...) needs a positive speed")
            duration_s = distance_m / self.speed
        if duration_s is None:
            raise ValueError("cruise() needs duration_s or distance_m")
        n = self._n(duration_s)
        self._push(np.full(n, self.speed), 0.0, self.grade)
        return self

    def turn(self, angle_rad: float, rate_rad_s: float) -> TrajectoryBuilder:
        """Turn by ``angle_rad`` (positive clockwise) at ``|rate_rad_s|`` and the current speed.

        The rate is adjusted slightly so that the whole samples turn by exactly the angle.
        """
        n = max(self._n(abs(angle_rad) / abs(rate_rad_s)), 1)
        self._push(np.full(n, self.speed), angle_rad * self.rate / n, self.grade)
        return self

    def arc(self, angle_rad: float, radius_m: float) -> TrajectoryBuilder:
        """Follow a circular arc of ``radius_m`` through ``angle_rad`` at the current speed."""
        if self.speed <= 0.0:
            raise ValueError("arc() needs a positive speed")
        return self.turn(angle_rad, self.speed / radius_m)

    def slope(self, grade_rad: float, duration_s: float) -> TrajectoryBuilder:
        """Change the grade (vehicle pitch) to ``grade_rad`` smoothly over ``duration_s``."""
        n = max(self._n(duration_s), 1)
        u = np.arange(n) / n
        p = self.grade + (grade_rad - self.grade) * 0.5 * (1.0 - np.cos(np.pi * u))
        self._push(np.full(n, self.speed), 0.0, p)
        self.grade = float(grade_rad)
        return self

    def surge_straight(self, distance_m: float, peak_gain_mps: float) -> TrajectoryBuilder:
        """A straight driven as accelerate-then-brake: ``s = s0 + gain sin^2(pi u)``.

        Starts and ends at the current speed; covers ``distance_m``.
        """
        if self.speed + 0.5 * peak_gain_mps <= 0.0:
            raise ValueError("surge_straight() needs a positive mean speed")
        T = distance_m / (self.speed + 0.5 * peak_gain_mps)
        n = max(self._n(T), 1)
        u = np.arange(n) / n
        s = self.speed + peak_gain_mps * np.sin(np.pi * u) ** 2
        self._push(s, 0.0, self.grade)
        return self

    def build(self, duration_s: float | None = None) -> Profile:
        """Concatenate the primitives (plus one final sample) into a :class:`Profile`.

        Parameters
        ----------
        duration_s : float, optional
            Cut to this duration, or extend it (standing if stopped, else cruising).
        """
        if duration_s is not None and duration_s > self.duration_s:
            extra = duration_s - self.duration_s
            if self.speed == 0.0:
                self.stand(extra + 1.0 / self.rate)
            else:
                self.cruise(extra + 1.0 / self.rate)
        s = np.concatenate([*self._s, [self.speed]])
        r = np.concatenate([*self._r, [0.0]])
        p = np.concatenate([*self._p, [self.grade]])
        if duration_s is not None:
            n = round(duration_s * self.rate) + 1
            s, r, p = s[:n], r[:n], p[:n]
        return Profile(self.rate, s, r, p, np.zeros_like(s), self.heading0)


def add_gait(
    profile: Profile,
    cadence_hz: float,
    vertical_amp_m: float,
    lateral_amp_m: float,
    speed_ref_mps: float,
    surge_frac: float = 0.12,
    roll_amp_rad: float = 0.03,
    pitch_amp_rad: float = 0.02,
) -> FloatArray:
    """Add a walking gait to ``profile`` (in place); returns the walking weight ``w(t)``.

    While walking (weight ``w = clip(speed / speed_ref, 0, 1)``) the body bobs vertically by
    ``vertical_amp_m sin(2 pi f t)`` (one cycle per step, ``f = cadence_hz``), sways laterally
    by ``lateral_amp_m sin(pi f t)`` (one per stride), surges forward by ``surge_frac`` of the
    speed at the step frequency, and rolls / pitches by small angles at the stride / step
    frequency. The perturbation is written as the velocity ``dv_h`` (derivative of the
    displacement); position follows from integrating the total velocity.
    """
    t = profile.t
    w = np.clip(profile.speed / speed_ref_mps, 0.0, 1.0)
    ws = 2.0 * np.pi * cadence_hz
    dv = np.zeros((profile.n, 3))
    dv[:, 0] = w * surge_frac * speed_ref_mps * np.sin(ws * t)
    dv[:, 1] = w * lateral_amp_m * 0.5 * ws * np.cos(0.5 * ws * t)
    dv[:, 2] = w * vertical_amp_m * ws * np.cos(ws * t)
    profile.dv_h = dv if profile.dv_h is None else profile.dv_h + dv
    profile.roll = profile.roll + w * roll_amp_rad * np.sin(0.5 * ws * t)
    bp = w * pitch_amp_rad * np.sin(ws * t + 0.5)
    profile.body_pitch = bp if profile.body_pitch is None else profile.body_pitch + bp
    return w


def bag_carry(
    t: FloatArray, active: FloatArray, sigma_rad: float, knot_s: float, rng: np.random.Generator
) -> Rotation:
    """Slow random attitude of a device in a bag, ``C_carry`` per sample.

    Roll, pitch and yaw follow cubic splines through ``N(0, sigma_rad^2)`` knots spaced
    ``knot_s`` apart on a clock that advances only while ``active`` (0..1, e.g. the walking
    weight): the bag is still when the carrier stands.
    """
    clock = np.concatenate([[0.0], np.cumsum(active[:-1])]) * (t[1] - t[0]) if len(t) > 1 else np.zeros(1)
    n_knots = int(np.ceil(clock[-1] / knot_s)) + 4
    knots = np.arange(n_knots) * knot_s
    angles = rng.normal(0.0, sigma_rad, size=(n_knots, 3))
    spline = CubicSpline(knots, angles, axis=0)
    a = spline(clock)
    return Rotation.from_euler("ZYX", a[:, ::-1])


# --- vectorised quaternions, scalar-last [x, y, z, w] (scipy's order); faster than Rotation ops


def _qmul(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product ``a * b`` (rotation ``b`` then ``a``), broadcasting over rows."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def _qconj(q: FloatArray) -> FloatArray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def _q_from_euler(roll: FloatArray, pitch: FloatArray, yaw: FloatArray) -> FloatArray:
    """Quaternion of ``C = Rz(yaw) Ry(pitch) Rx(roll)`` (ZYX)."""
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    return np.stack(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ],
        axis=-1,
    )


def _q_to_rotvec(q: FloatArray) -> FloatArray:
    q = np.where(q[..., 3:4] < 0, -q, q)
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1)
    ang = 2.0 * np.arctan2(s, q[..., 3])
    small = s < 1e-12
    k = np.where(small, 2.0 / np.where(small, q[..., 3], 1.0), ang / np.where(small, 1.0, s))
    return v * k[..., None]


def _q_from_rotvec(rv: FloatArray) -> FloatArray:
    a = np.linalg.norm(rv, axis=-1)
    small = a < 1e-8
    a_safe = np.where(small, 1.0, a)
    k = np.where(small, 0.5 - a**2 / 48.0, np.sin(0.5 * a) / a_safe)
    return np.concatenate([rv * k[..., None], np.cos(0.5 * a)[..., None]], axis=-1)


def _q_rotate_inv(q: FloatArray, v: FloatArray) -> FloatArray:
    """``C(q)^T v`` for rows of ``q`` and ``v``."""
    u = -q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


@dataclass
class Truth:
    """True trajectory and IMU signals at the internal rate.

    Attributes
    ----------
    t : numpy.ndarray
        Device time, s, ``(N,)``.
    p_n, v_n : numpy.ndarray
        IMU position (NED about the origin, m) and velocity (m/s), ``(N, 3)``.
    euler_nv : numpy.ndarray
        Vehicle roll, pitch, yaw (rad; yaw wrapped to (-pi, pi]), ``(N, 3)``.
    q_nb : numpy.ndarray
        Sensor attitude ``C_nb`` as scalar-last quaternions (scipy order), ``(N, 4)``.
    f_b, omega_b : numpy.ndarray
        True specific force (m/s^2) and angular rate (rad/s) in ``b``, mean over
        ``[t_k, t_{k+1})``, ``(N, 3)``.
    speed : numpy.ndarray
        Along-track speed, m/s, ``(N,)``.
    g_n : numpy.ndarray
        Gravity used, m/s^2.
    """

    t: FloatArray
    p_n: FloatArray
    v_n: FloatArray
    euler_nv: FloatArray
    q_nb: FloatArray
    f_b: FloatArray
    omega_b: FloatArray
    speed: FloatArray
    g_n: FloatArray

    def C_nb(self, idx: slice | npt.NDArray[np.intp] | int = slice(None)) -> FloatArray:
        """Sensor attitude matrices at ``idx``."""
        return Rotation.from_quat(self.q_nb[idx]).as_matrix()


def derive_imu(
    q_nb: FloatArray, v_n: FloatArray, rate_hz: float, g_n: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """True ``(f_b, omega_b)`` of sampled attitudes (scalar-last quaternions of ``C_nb``) and
    velocities (see the module docstring). The last sample repeats the previous one.
    """
    n = len(v_n)
    if n < 2:
        f = _q_rotate_inv(q_nb, -np.broadcast_to(g_n, (n, 3)))
        return f, np.zeros((n, 3))
    dt = 1.0 / rate_hz
    rel = _qmul(_qconj(q_nb[:-1]), q_nb[1:])
    rv = _q_to_rotvec(rel)
    omega = np.empty((n, 3))
    omega[:-1] = rv / dt
    omega[-1] = omega[-2]
    half = _qmul(q_nb[:-1], _q_from_rotvec(0.5 * rv))
    a = np.diff(v_n, axis=0) / dt
    f = np.empty((n, 3))
    f[:-1] = _q_rotate_inv(half, a - g_n)
    f[-1] = f[-2]
    return f, omega


def make_truth(
    profile: Profile,
    C_vb: FloatArray,
    g_n: FloatArray,
    carry: Rotation | None = None,
    p0_n: FloatArray | None = None,
) -> Truth:
    """Integrate a :class:`Profile` into a :class:`Truth` (position, velocity, attitudes, IMU).

    Parameters
    ----------
    profile : Profile
        Motion at the internal rate.
    C_vb : numpy.ndarray
        Mount rotation (``b`` to ``v``), ``(3, 3)``.
    g_n : numpy.ndarray
        Gravity in ``n``, m/s^2.
    carry : scipy Rotation, optional
        Per-sample extra rotation after the mount (``C_nb = C_nv C_vb C_carry``).
    p0_n : numpy.ndarray, optional
        Initial position, m (default the origin).
    """
    R = profile.rate_hz
    yaw = profile.heading0 + np.concatenate([[0.0], np.cumsum(profile.yaw_rate[:-1])]) / R
    s = profile.speed
    th = profile.pitch
    v_n = np.stack([s * np.cos(th) * np.cos(yaw), s * np.cos(th) * np.sin(yaw), -s * np.sin(th)], axis=1)
    if profile.dv_h is not None:
        cy, sy = np.cos(yaw), np.sin(yaw)
        dv = profile.dv_h
        v_n[:, 0] += cy * dv[:, 0] - sy * dv[:, 1]
        v_n[:, 1] += sy * dv[:, 0] + cy * dv[:, 1]
        v_n[:, 2] += dv[:, 2]
    p_n = np.empty_like(v_n)
    p_n[0] = 0.0 if p0_n is None else p0_n
    p_n[1:] = p_n[0] + np.cumsum(0.5 * (v_n[:-1] + v_n[1:]), axis=0) / R
    body_pitch = th if profile.body_pitch is None else th + profile.body_pitch
    euler = np.stack([profile.roll, body_pitch, yaw], axis=1)
    q_nb = _qmul(_q_from_euler(euler[:, 0], euler[:, 1], euler[:, 2]), Rotation.from_matrix(C_vb).as_quat())
    if carry is not None:
        q_nb = _qmul(q_nb, carry.as_quat())
    f_b, omega_b = derive_imu(q_nb, v_n, R, g_n)
    euler[:, 2] = np.pi - np.mod(np.pi - yaw, 2.0 * np.pi)
    return Truth(
        t=profile.t,
        p_n=p_n,
        v_n=v_n,
        euler_nv=euler,
        q_nb=q_nb,
        f_b=f_b,
        omega_b=omega_b,
        speed=np.abs(s),
        g_n=np.asarray(g_n, float),
    )
