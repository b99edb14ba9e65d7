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
    reaches ``min_snr``. Each estimate replaces the previous one (as in the paper). With
    body-frame input, ``R_b^n mean(y_b) - g_n`` is evaluated as the levelled difference from
    the gravity reference (below), which removes gravity without the tilt filter's errors.

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

    with ``dv/dt`` from consecutive GPS speeds (no course is needed: with
    ``require_course=False`` intervals count from ``min_speed_mps`` on whether or not the
    receiver flags its course valid). Per GPS interval the IMU samples give the
    mean ``a_s`` and mean ``r``; over a buffer of intervals the rotation that best maps
    ``a_v`` onto ``a_s`` (2-D Procrustes, least squares) is::

        mount_yaw = atan2(sum (a_s x a_v)_z, sum a_s . a_v)

    Sums are accumulated over all useful buffers (coherence and excitation above their
    thresholds) with a forgetting factor (per buffer, or per ``forget_ref_s`` seconds of buffer
    so that the memory does not depend on the GNSS rate), so the estimate uses the U-turns of a lap as well as
    accelerating or braking straights, needs no sign resolution, and keeps improving: a
    recursive estimate with its own variance rather than a replacement. Quality reported with
    each estimate: the coherence ``rho = |sum a_s a_v^*| / sqrt(sum |a_s|^2 sum |a_v|^2)``
    (1 = perfect), the excitation ``rms |a_v|`` (m/s^2) and the standard deviation
    ``sigma = sqrt(sum |res|^2 / (2 N) * overlap / sum |a_v|^2)`` (rad; half the residual
    energy lies across the signal). An estimate is *accepted* (applied) only when the fused
    ``sigma <= max_std_rad``. For the accumulated sums with forgetting weights ``w`` (1 for the
    newest buffer) the variance of a weighted least-squares angle is
    ``sigma_r^2 sum w^2 |a_v|^2 / (sum w |a_v|^2)^2``; with ``weighted_variance`` this is
    approximated (equal excitation per row) by multiplying ``overlap`` by ``sum w^2 / sum w``.
    With ``gate_sigma > 0`` a buffer whose own angle lies more than ``gate_sigma`` combined
    standard deviations from the fused one is reported (``buffer_outlier``) but not fused:
    on hilly roads a grade unlike the gravity reference's leaks gravity into a whole buffer
    and biases its angle far beyond its residual-based ``sigma``.

    Matched smoothing (``smooth_epochs = M > 1``). ``dv/dt`` from consecutive GPS speeds is the
    noisiest input (0.1 m/s speed noise gives 0.14 m/s^2 per 1 s interval; across a U-turn
    this noise, not the signal, sets the angle error). Rows are therefore triangular-weighted
    means over the last ``2M - 1`` contiguous intervals, ``w = [1, ..., M, ..., 1]``, of
    ``a_s``, ``v r`` *and* ``dv`` (``sum w dv / sum w dt`` is the difference of two ``M``-epoch
    speed means over ``M dt``): the same linear filter on both sides keeps
    ``a_s = R(-mount) a_v`` exact row by row while the speed noise is averaged over ``M``
    epochs. ``overlap = (sum w)^2 / sum w^2`` corrects ``sigma`` for the overlapping rows.

Consistency across buffers and the choice of form (``auto_demean``, designed here)
    The residual-based ``sigma`` only sees white errors. A levelling error that is constant over
    a buffer (a grade or bank unlike the gravity reference's, below) rotates that buffer's
    whole ``a_s`` and biases its angle beyond its ``sigma``: on the rtklibexplorer car drive
    (hilly streets, the reference renewed only at the three stops because the car is never
    unaccelerated for ``ref_window_epochs`` intervals while driving) the levelled buffers
    scatter by about 25 deg rms about the author's mount, several times their ``sigma``, and the
    fused angle wanders by +-10 deg with a ``sigma`` of 4 deg at 1 Hz GNSS. Removing each
    buffer's mean (``demean_buffers``) cancels that error but also the mean acceleration,
    which carries the signal of a U-turn or of a constant-acceleration straight (on the
    simulated scooter laps the demeaned form needs 2-3 laps). With ``auto_demean`` every
    buffer is fused in both forms, each with its own sums, gate and consistency: for each
    useful buffer the normalised innovation ``z = (mu_buf - mu_fused) / hypot(sigma_buf,
    sigma_fused)`` (before the buffer is fused), and the Birge ratio
    ``B = sqrt(max(1, (sum f z^2 + n0) / (sum f + n0)))`` with the same forgetting ``f`` and
    ``n0 = AUTO_MIN_BUFFERS`` consistent pseudo-innovations (so that a few buffers cannot
    declare a form consistent or not). Each form reports ``sigma B`` (the usual scaling of an
    inconsistent weighted mean), and the form with the smaller scaled ``sigma`` is used; the
    demeaned form only once it has ``n0`` innovations. On flat simulated ground the levelled
    form stays consistent and is used as before; on the real drive the demeaned form is
    (``B`` about 1), and its fused angle is within 0.1-1 deg of the author's.

Settled acceptance (``settle_s``, designed here)
    At 1 Hz GNSS the consistent ``sigma`` of that drive still levels off at 1.2-1.7 deg, above
    the 1 deg that the first estimate on the simulated laps needs. An estimate with
    ``max_std_rad < sigma <= settle_std_factor * max_std_rad`` is therefore also accepted when
    the fused angle has stayed within ``max_std_rad`` of it after every useful buffer over the
    last ``settle_s`` seconds (a useful buffer at least ``settle_s`` old included, and at least
    ``settle_min_buffers`` in that span: across a GNSS outage nothing settles). On the
    simulated laps (``benchmarks/bench_pipeline.py``) it accepts nothing before the 1 deg rule
    does, whereas accepting at 1.5 deg outright took first estimates 1.9-2.6 deg off there; on
    the real drive the estimate settles at -174.7 deg (author -174.6) from 382 s.

Provisional estimates (``provisional_sigmas``, designed here)
    Until an estimate is accepted the engine navigates with the configured initial angle
    (0 by default). On the real drive, where the sensor is mounted backwards (-174.6 deg),
    acceptance comes at 382 s and dead reckoning before it runs the wrong way, although the
    fused estimate is within 3-7 deg of the mount from the second buffer (t = 60 s, sigma 12.6
    deg). A useful estimate whose angle lies more than ``provisional_sigmas`` of its ``sigma``
    from the angle in use has rejected that angle at that significance: it is then applied as
    *provisional* (event ``provisional``; ``accepted`` stays False, so acceptance statistics
    keep their meaning), and each later useful estimate, which fuses more data, replaces it
    until the first acceptance. The estimate itself does not depend on the angle applied
    (body-frame levelling against the gravity reference), so accepted estimates and their
    times are unchanged.

Levelling against a gravity reference (body-frame input, :meth:`MountAligner.add_imu_body`)
    Levelling with the tilt filter's ``C_nb`` leaks gravity into ``a_s``: one degree of tilt
    error is 0.17 m/s^2, against a signal of 0.5-0.8 m/s^2. In a U-turn the tilt filter runs
    on the gyroscope alone (the accelerometer then measures the centripetal acceleration too),
    and the gyroscope's cross-axis coupling (0.3 % of a 0.15 rad/s yaw rate) tilts it by
    about 1 degree per turn, always towards the same side on a track: 5-12 degrees of mount
    error on the simulated scooter. With body-frame input the aligner keeps its own gravity
    reference instead: ``f_ref_b``, the mean specific force over the latest window of
    ``ref_window_epochs`` GPS intervals in which the vehicle was unaccelerated -- the norm of
    the window's mean vehicle acceleration ``[mean dv/dt, mean v r]`` below
    ``ref_max_accel_mps2`` *and* every interval's mean specific force within
    ``ref_max_spread_mps2`` of the window mean (the accelerometer itself confirms the GPS;
    standing still and cruising straight both qualify). Then::

        a_b = mean(f_b) - f_ref_b          (the vehicle acceleration, in b)
        a_s = [x_s . a_b, y_s . a_b],  u = -f_ref_b / |f_ref_b|  (down in b),
        x_s = (e_x - (e_x . u) u) / |.|,  y_s = u x x_s

    The accelerometer bias and the mount's roll and pitch cancel in the difference, and an
    error of the levelling axis ``u`` only enters to second order. This assumes that the
    vehicle's attitude relative to gravity (grade, bank) is the same as in the reference
    window; intervals more than ``ref_max_age_s`` after it are not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numba
import numpy as np
import numpy.typing as npt

# the buffer's columns and the per-interval IMU sums are declared with the compiled interval step
from iotnav.techniques.mount_interval import (  # noqa: F401  (re-exported layouts)
    AS_SQ,
    AS_X,
    AS_Y,
    AV_Y,
    COURSE,
    DT,
    DV,
    FULL,
    IMU_BODY,
    IMU_FB,
    IMU_N,
    IMU_N_SUMS,
    IMU_R,
    IMU_SQ,
    IMU_SX,
    IMU_SY,
    N_COLS,
    N_IMU,
    R_MEAN,
    V_MEAN,
    close_interval,
    interval_params,
    levelled_xy,
)

FloatArray = npt.NDArray[np.float64]

#: Buffer innovations the demeaned form of ``auto_demean`` needs before it can be selected.
AUTO_MIN_BUFFERS = 4


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
    forget_ref_s : float
        When > 0, ``forget`` is the factor per ``forget_ref_s`` seconds of buffer rather than per
        buffer: a buffer of duration ``T`` applies ``forget ** (T / forget_ref_s)``, so the
        memory in seconds does not shrink with the GNSS rate (0: per buffer), s.
    demean_buffers : bool
        Remove each buffer's mean from ``a_s`` and ``a_v`` before the lsq sums, so that a
        constant levelling error within a buffer (a grade or bank different from the gravity
        reference's) cancels; only the acceleration *changes* within the buffer are used.
    auto_demean : bool
        Fuse every buffer in both forms, as levelled and demeaned, each with its own sums, and
        use the form whose fused ``sigma`` scaled by its consistency across buffers (Birge
        ratio, see the module docstring) is smaller; ``demean_buffers`` is then ignored.
    weighted_variance : bool
        Fused ``sigma`` of the exponentially weighted sums with the weights' variance factor
        ``sum w^2 / sum w`` (see ``lsq_estimate``); False keeps the unweighted-count form, which
        overstates the variance by up to ``1 + forget``.
    gate_sigma : float
        When > 0, a useful buffer whose angle differs from the fused one by more than
        ``gate_sigma * hypot(sigma_buffer, sigma_fused)`` is not fused (``buffer_outlier`` in
        the event): a levelling error that is constant over a buffer (grade or bank unlike the
        gravity reference's) biases that buffer's angle well beyond its own ``sigma``.
    max_interval_s : float
        Longer GPS intervals break the buffer, s.
    initial_mount_yaw_rad : float
        Mount angle used before the first estimate (or a stored one-off calibration), rad.
    one_off : bool
        Stop after the first accepted estimate (the paper's one-off calibration).
    max_std_rad : float
        An lsq estimate is accepted only when its fused standard deviation is at most this, rad.
    settle_s : float
        When > 0, an lsq estimate whose fused ``sigma`` exceeds ``max_std_rad`` is also
        accepted when ``sigma <= settle_std_factor * max_std_rad`` and the fused angle after
        every useful buffer of the last ``settle_s`` seconds (the first such buffer at least
        ``settle_s`` old) lay within ``max_std_rad`` of it: the estimate has settled although
        its ``sigma`` improves no further, s (0: off).
    settle_std_factor : float
        Bound of the settled acceptance relative to ``max_std_rad``.
    settle_min_buffers : int
        Useful buffers (this one included) the last ``settle_s`` seconds must hold for the
        settled acceptance: a GNSS outage brings none, and an angle that merely was not
        updated has not settled.
    provisional_sigmas : float
        When > 0 and no estimate has been accepted yet, a useful lsq estimate that rejects the
        angle in use (``|mu - mount_yaw| > provisional_sigmas * sigma``) with
        ``sigma <= provisional_max_std_rad`` is applied *provisionally*, and every later useful
        estimate replaces it until one is accepted (0: off). See the module docstring.
    provisional_max_std_rad : float
        Largest fused ``sigma`` of a provisional estimate, rad.
    require_course : bool
        Use only intervals whose GPS course is flagged valid (the lsq form does not need the
        course; the paper form always does).
    smooth_epochs : int
        ``M`` of the matched triangular smoothing of the lsq rows (1: one row per GPS interval).
    ref_window_epochs : int
        GPS intervals of a gravity-reference window (body-frame input only).
    ref_max_accel_mps2 : float
        A window becomes the gravity reference when the norm of its mean vehicle acceleration
        (GPS and gyroscope) is below this, m/s^2.
    ref_max_spread_mps2 : float
        ... and every interval's mean specific force lies within this of the window's mean, m/s^2.
    ref_max_age_s : float
        Intervals further than this from the end of the latest reference window are not used, s.
    """

    method: Literal["lsq", "paper"] = "lsq"
    buffer_epochs: int = 8
    theta_alpha_rad2: float = 0.003
    min_speed_mps: float = 2.0
    min_accel_mps2: float = 0.3
    min_snr: float = 3.0
    min_coherence: float = 0.7
    forget: float = 0.95
    forget_ref_s: float = 0.0
    demean_buffers: bool = False
    auto_demean: bool = False
    weighted_variance: bool = False
    gate_sigma: float = 0.0
    max_interval_s: float = 2.5
    initial_mount_yaw_rad: float = 0.0
    one_off: bool = False
    max_std_rad: float = math.inf
    settle_s: float = 0.0
    settle_std_factor: float = 2.0
    settle_min_buffers: int = 4
    provisional_sigmas: float = 0.0
    provisional_max_std_rad: float = math.radians(15.0)
    require_course: bool = True
    smooth_epochs: int = 1
    ref_window_epochs: int = 5
    ref_max_accel_mps2: float = 0.05
    ref_max_spread_mps2: float = 0.1
    ref_max_age_s: float = 600.0


def wrap(a: float) -> float:
    """Wrap an angle (rad) to (-pi, pi]."""
    w = math.atan2(math.sin(a), math.cos(a))
    return math.pi if w == -math.pi else w


def levelled(a_b: FloatArray, down_b: FloatArray) -> FloatArray:
    """Horizontal components of ``a_b`` in the levelled sensor frame ``s``.

    ``s`` has its z axis along ``down_b`` (unit, in ``b``) and its x axis along the horizontal
    projection of the sensor x axis, so ``a_s = [x_s . a_b, y_s . a_b]`` with
    ``x_s = (e_x - (e_x . u) u) / |...|`` and ``y_s = u x x_s``.
    """
    return np.array(
        levelled_xy(
            float(a_b[0]), float(a_b[1]), float(a_b[2]), float(down_b[0]), float(down_b[1]), float(down_b[2])
        )
    )


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


def lsq_estimate(sums: FloatArray, n: int, overlap: float = 1.0) -> tuple[float, dict[str, float]]:
    """Mount angle (rad) and quality figures from :func:`lsq_sums` over ``n`` rows.

    ``std_rad`` is ``sqrt(sum |residual|^2 / (2 n) * overlap / sum |a_v|^2)``: half of the
    residual energy lies across the signal, and ``overlap`` (>= 1) is the factor by which
    overlapping smoothed rows understate the variance (``(sum w)^2 / sum w^2`` of the kernel).
    """
    c, d, evv, ess = (float(v) for v in sums)
    h = math.hypot(c, d)
    mu = math.atan2(c, d)
    coh = h / math.sqrt(evv * ess) if evv > 0 and ess > 0 else 0.0
    res = max(ess + evv - 2.0 * h, 0.0) / max(n, 1)
    sigma = math.sqrt(0.5 * res * overlap / evv) if evv > 0 else math.inf
    return mu, {
        "coherence": coh,
        "excitation_mps2": math.sqrt(evv / max(n, 1)),
        "std_rad": min(sigma, math.pi),
        "n": float(n),
    }


@numba.njit(cache=True)
def accumulate_levelled(sums: FloatArray, a_x: float, a_y: float, r: float) -> None:
    """Add one IMU sample with levelled horizontal specific force ``a_s`` (m/s^2) and yaw rate ``r`` (rad/s)."""
    sums[IMU_SX] += a_x
    sums[IMU_SY] += a_y
    sums[IMU_R] += r
    sums[IMU_SQ] += a_x * a_x + a_y * a_y
    sums[IMU_N] += 1.0


@numba.njit(cache=True)
def accumulate_body(sums: FloatArray, f_x: float, f_y: float, f_z: float, r: float) -> None:
    """Add one IMU sample with sensor-frame specific force ``f_b`` (m/s^2) and yaw rate ``r`` (rad/s)."""
    sums[IMU_BODY] = 1.0
    sums[IMU_FB] += f_x
    sums[IMU_FB + 1] += f_y
    sums[IMU_FB + 2] += f_z
    sums[IMU_R] += r
    sums[IMU_N] += 1.0


class _Fusion:
    """Exponentially forgotten lsq sums of one form of the buffers (levelled as is, or demeaned)."""

    def __init__(self, demean: bool) -> None:
        self.demean = demean
        self.acc = np.zeros(4)  # accumulated lsq sums
        self.n = 0.0  # forgetting-weighted row count
        self.w2 = 0.0  # sum of the squared forgetting weights of the accumulated rows
        self.z2 = 0.0  # forgetting-weighted sum of squared normalised buffer innovations
        self.nz = 0.0  # forgetting-weighted count of those innovations


class MountAligner:
    """Block 5; hot state in a numpy interval buffer and accumulators.

    Feed every IMU sample with :meth:`add_imu` (levelled input) or :meth:`add_imu_body`
    (sensor-frame input, levelled against the aligner's gravity reference), and every GPS
    epoch with :meth:`add_gnss`.
    """

    def __init__(self, config: MountConfig | None = None) -> None:
        self.config = config or MountConfig()
        c = self.config
        self.mount_yaw_rad = c.initial_mount_yaw_rad
        self.known = False
        self.provisional = False  # the angle in use is a provisional estimate
        self.accepted_once = False
        self.quality: dict[str, float] = {}
        self.buf = np.zeros((max(2, c.buffer_epochs), N_COLS))
        self.k = 0
        # fused lsq sums of the configured form; with auto_demean also of the other form
        self.fusions = (_Fusion(c.demean_buffers and not c.auto_demean), _Fusion(True))
        self.history: list[tuple[float, float]] = []  # (t, fused angle) after useful buffers
        # per-interval IMU sums (``IMU_*`` layout), filled by the compiled accumulators
        self.imu_sums = np.zeros(IMU_N_SUMS)
        self._t_prev = math.nan
        self._v_prev = math.nan
        self._v_start = math.nan
        self.done = False
        # body-frame input (add_imu_body): gravity reference from unaccelerated windows
        w = max(1, c.ref_window_epochs)
        self.ring = np.zeros((w, 7))  # f_b mean (3), n, dv, dt, v r (per interval)
        self.ring_ok = np.zeros(w, dtype=bool)
        self.k_ring = 0
        self.f_ref_b = np.full(3, np.nan)
        self.t_ref = -math.inf
        # matched smoothing of lsq rows: the last 2M - 1 contiguous good intervals
        m = max(1, c.smooth_epochs)
        self.smooth_w = np.concatenate([np.arange(1.0, m + 1.0), np.arange(m - 1.0, 0.0, -1.0)])
        self.sm = np.zeros((self.smooth_w.size, N_COLS))
        self.overlap = float(self.smooth_w.sum() ** 2 / (self.smooth_w**2).sum())
        self.k_sm = 0
        self._prm = interval_params(
            c.max_interval_s,
            c.min_speed_mps,
            c.ref_max_age_s,
            c.ref_max_accel_mps2,
            c.ref_max_spread_mps2,
            c.method == "paper",
            c.require_course or c.method == "paper",
        )

    @property
    def acc(self) -> FloatArray:
        """Accumulated lsq sums of the configured form (``lsq_sums`` layout)."""
        return self.fusions[0].acc

    @property
    def n_acc(self) -> float:
        """Forgetting-weighted row count of :attr:`acc`."""
        return self.fusions[0].n

    @property
    def w2_acc(self) -> float:
        """Sum of the squared forgetting weights of the rows in :attr:`acc`."""
        return self.fusions[0].w2

    @property
    def _int(self) -> FloatArray:
        """View of the sums of a_s x, a_s y, r, |a_s|^2 over the current interval."""
        return self.imu_sums[0:4]

    @property
    def _fb(self) -> FloatArray:
        """View of the sum of f_b over the current interval, m/s^2."""
        return self.imu_sums[IMU_FB : IMU_FB + 3]

    @property
    def _n(self) -> int:
        """IMU samples in the current interval."""
        return int(self.imu_sums[IMU_N])

    @property
    def _body(self) -> bool:
        """True once sensor-frame input (:meth:`add_imu_body`) has been fed."""
        return bool(self.imu_sums[IMU_BODY] != 0.0)

    def add_imu(self, a_s: FloatArray, r: float) -> None:
        """Accumulate one IMU sample: levelled horizontal specific force (m/s^2), yaw rate (rad/s)."""
        accumulate_levelled(self.imu_sums, float(a_s[0]), float(a_s[1]), float(r))

    def add_imu_body(self, f_b: FloatArray, r: float) -> None:
        """Accumulate one IMU sample in the sensor frame: specific force ``f_b`` (m/s^2), yaw rate (rad/s).

        Use instead of :meth:`add_imu`: the horizontal acceleration is then levelled against the
        aligner's own gravity reference (see the module docstring), not the tilt filter.
        """
        accumulate_body(self.imu_sums, float(f_b[0]), float(f_b[1]), float(f_b[2]), float(r))

    def set_gravity_reference(self, f_b: FloatArray, t: float) -> None:
        """Use ``f_b`` (mean sensor-frame specific force while unaccelerated, m/s^2) measured up to
        time ``t`` (s) as the gravity reference of body-frame input, e.g. an initialisation's
        static mean when the aligner is first fed after it."""
        self.f_ref_b = np.asarray(f_b, float).copy()
        self.t_ref = float(t)

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
        status, self._t_prev, self._v_prev, self._v_start, self.k, self.k_ring, self.t_ref, self.k_sm = (
            close_interval(
                self.imu_sums,
                self.ring,
                self.ring_ok,
                self.f_ref_b,
                self.sm,
                self.smooth_w,
                self.buf,
                self._prm,
                float(t),
                float(speed_mps),
                float(course_rad),
                bool(course_valid),
                bool(static),
                self.done,
                self._t_prev,
                self._v_prev,
                self._v_start,
                self.k,
                self.k_ring,
                self.t_ref,
                self.k_sm,
            )
        )
        event = None
        if status == FULL:
            event = self._evaluate(t, speed_mps)
            self.k = 0
        return event

    def _fuse(self, fu: _Fusion, a_s: FloatArray, a_v: FloatArray, f: float) -> dict[str, Any]:
        """Fuse one buffer's rows into ``fu`` (forgetting factor ``f``): the lsq step of
        :meth:`_evaluate` for one form (levelled as is, or demeaned)."""
        c = self.config
        if fu.demean:
            a_s = a_s - a_s.mean(axis=0)
            a_v = a_v - a_v.mean(axis=0)
        n_rows = a_s.shape[0]
        ov = self.overlap
        sums = lsq_sums(a_s, a_v)
        mu_buf, q_buf = lsq_estimate(sums, n_rows, ov)
        useful = q_buf["excitation_mps2"] >= c.min_accel_mps2 and q_buf["coherence"] >= c.min_coherence
        outlier = False
        if useful and fu.n > 0:
            mu_f, q_f = lsq_estimate(fu.acc, round(fu.n), self._ov_acc(fu))
            gap = abs(wrap(float(mu_buf) - float(mu_f)))
            var = q_buf["std_rad"] ** 2 + q_f["std_rad"] ** 2
            if c.auto_demean:
                fu.z2 = f * fu.z2 + gap * gap / var
                fu.nz = f * fu.nz + 1.0
            if c.gate_sigma > 0.0:
                outlier = bool(gap > c.gate_sigma * math.sqrt(var))
                useful = not outlier
        if useful:
            fu.acc = f * fu.acc + sums
            fu.n = f * fu.n + n_rows
            fu.w2 = f * f * fu.w2 + n_rows
        if fu.n > 0:
            mu, quality = lsq_estimate(fu.acc, round(fu.n), self._ov_acc(fu))
        else:
            mu, quality = mu_buf, dict(q_buf)
        if c.auto_demean:
            # Birge ratio, shrunk towards 1 by AUTO_MIN_BUFFERS consistent pseudo-innovations
            birge = math.sqrt(max(1.0, (fu.z2 + AUTO_MIN_BUFFERS) / (fu.nz + AUTO_MIN_BUFFERS)))
            quality = {**quality, "consistency": birge, "std_rad": min(quality["std_rad"] * birge, math.pi)}
        return {
            "mu": mu,
            "quality": quality,
            "useful": useful,
            "outlier": outlier,
            "mu_buf": mu_buf,
            "q_buf": q_buf,
            "demeaned": fu.demean,
        }

    def _settled(self, t: float, mu: float, std: float) -> bool:
        """Record the fused angle of a useful buffer; True when it has settled (``settle_s``)."""
        c = self.config
        if c.settle_s <= 0.0:
            return False
        self.history.append((t, mu))
        k = next((i for i, (ti, _) in enumerate(self.history) if ti >= t - c.settle_s), len(self.history))
        old_enough = k > 0  # a useful buffer at least settle_s before this one
        self.history = self.history[max(k - 1, 0) :]
        recent = [m for ti, m in self.history if ti >= t - c.settle_s]
        # the angle must have held over several new buffers, not over a gap without any (a GNSS
        # outage would otherwise "settle" whatever the last estimate was)
        if not old_enough or len(recent) < c.settle_min_buffers or std > c.settle_std_factor * c.max_std_rad:
            return False
        return all(abs(wrap(m - mu)) <= c.max_std_rad for m in recent)

    def _ov_acc(self, fu: _Fusion) -> float:
        """Overlap factor of the fused sums (with the forgetting weights' variance factor)."""
        if self.config.weighted_variance and fu.n > 0:
            return self.overlap * fu.w2 / fu.n
        return self.overlap

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
            provisional = False
            quality = {
                "course_var_rad2": course_var,
                "accel_mps2": mag,
                "snr": snr,
                "speed_change_mps": dv,
                "literal_eq3_rad": literal,
            }
        else:
            a_s = b[:, [AS_X, AS_Y]]
            a_v = np.column_stack([b[:, DV] / b[:, DT], b[:, AV_Y]])
            f = c.forget
            if c.forget_ref_s > 0.0:
                f = c.forget ** (float(b[:, DT].sum()) / c.forget_ref_s)
            forms = self.fusions if c.auto_demean else self.fusions[:1]
            res = [self._fuse(fu, a_s, a_v, f) for fu in forms]
            # the demeaned form takes over only once its consistency rests on a few buffers
            cand = [
                r for r, fu in zip(res, forms, strict=False) if fu is forms[0] or fu.nz >= AUTO_MIN_BUFFERS
            ]
            best = min(cand, key=lambda r: r["quality"]["std_rad"])
            mu, quality = best["mu"], best["quality"]
            useful = any(r["useful"] for r in res)
            accepted = useful and quality["std_rad"] <= c.max_std_rad
            settled = useful and not accepted and self._settled(t, float(mu), quality["std_rad"])
            accepted = accepted or settled
            provisional = (
                useful
                and not accepted
                and not self.accepted_once
                and c.provisional_sigmas > 0.0
                and quality["std_rad"] <= c.provisional_max_std_rad
                and (
                    self.provisional
                    or abs(wrap(float(mu) - self.mount_yaw_rad)) > c.provisional_sigmas * quality["std_rad"]
                )
            )
            q_buf = best["q_buf"]
            quality = {
                **quality,
                "buffer_mount_yaw_rad": best["mu_buf"],
                "buffer_coherence": q_buf["coherence"],
                "buffer_std_rad": q_buf["std_rad"],
                "buffer_excitation_mps2": q_buf["excitation_mps2"],
                "buffer_outlier": float(best["outlier"]),
                "demeaned": float(best["demeaned"]),
                "settled": float(settled),
                "provisional": float(provisional),
            }
        event: dict[str, Any] = {
            "type": "mount_estimate",
            "t": t,
            "method": c.method,
            "accepted": bool(accepted),
            "applied": bool(accepted or provisional),
            "mount_yaw_rad": float(mu) if accepted or provisional else self.mount_yaw_rad,
            "candidate_rad": float(mu),
            **quality,
        }
        if accepted or provisional:
            self.mount_yaw_rad = float(mu)
            self.known = True
            self.quality = quality
            self.provisional = provisional
            self.accepted_once = self.accepted_once or accepted
            if c.one_off and accepted:  # a provisional estimate never ends the calibration
                self.done = True
        return event
