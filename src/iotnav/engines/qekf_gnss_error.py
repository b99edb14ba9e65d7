"""GNSS error states of the quaternion EKF (option ``gnss_error_states``, designed here; default
off, the paper's form): the model, its exact discretisation and the engine's handling of it.

The paper takes the GNSS position error as white in ``R``. A consumer receiver's is not: a
Gauss-Markov error of minutes seen through the receiver's own low-pass (the simulator's
``open-sky``: 150 s horizontal, 200 s vertical, through 2 s). The option appends the second-order
model of ``eskf`` (:mod:`iotnav.engines.eskf_models`, "GNSS error model (receiver smoothing)")
as six total states after ``SA``, ``GNE`` (22-24, the error ``e`` the fix carries) and ``GNM``
(25-27, the Gauss-Markov error ``e_gm`` before the receiver's filter), NED, m::

    d(e_gm)/dt = -e_gm / T_e + w,   de/dt = (e_gm - e) / t_f      (per axis)
    a = exp(-dt/T_e), b = exp(-dt/t_f):  e_gm' = a e_gm,  e' = b e + T_e (a - b) / (T_e - t_f) e_gm

discretised exactly over each prediction step (:func:`gnss_error_transition`; the estimates
propagate with it too), ``c = T_e (a - b) / (T_e - t_f)`` written without cancellation
(``(dt/t_f) a`` at ``t_f = T_e``). The process noise is integrated exactly: ``var(e_gm)(1 - a^2)``
on ``GNM`` and the ``O(dt^3)`` ``e`` part (closed form; within 0.1 % of ``t_f = T_e`` that of
``t_f = T_e``). ``t_f = 0``: ``GNE`` is the first-order Gauss-Markov error itself, ``GNM`` inert.
``T_e`` is ``gnss_corr_time_s`` (north, east) and ``gnss_corr_time_v_s`` (down), ``t_f``
``gnss_receiver_filter_s``; ``var(e_gm) =
sigma_e^2 (T_e + t_f) / T_e`` (Gelb 1974, sec. 3.8) so that ``e`` has the variance
``sigma_e^2`` of the fix. Per axis ``sigma_p`` is the fix's sigma as ``R`` above (hAcc / vAcc,
else DOP x UERE), ``sigma_e = sqrt(1 - f^2) sigma_p`` with ``f = gnss_white_fraction`` (0), and
``R`` keeps the white remainder ``max(f sigma_p, floor)^2``, the floor the larger of
``gnss_white_floor_m`` (5 mm) and the fix's output rounding
(:class:`~iotnav.engines.gnss_resolution.PositionResolution`, ``summary()["gnss_resolution"]``).
The measurements::

    position  z = r + e + w,                 H: I on POS, I on GNE
    velocity  z = v + (e_gm - e) / t_f + w_D,  H: I on VEL, -I/t_f on GNE, +I/t_f on GNM

(rows 0-1 for speed and course; ``R`` the white Doppler part, sAcc). The paper's 22-column
models are padded with zero columns (the TRIAD, norm and non-holonomic observations do not
depend on the GNSS error). At the end of the initialisation ``[GNE, GNM]`` start with the
stationary covariance (``var(e) = cov(e, e_gm) = sigma_e^2``, ``var(e_gm) = sigma_e^2 (T_e +
t_f) / T_e``), and the position, 0 at the mean of the initialisation's fixes, with the error of
that mean under the model, correlated with ``e`` (:meth:`QekfEngine._init_gnss_error`; taking
the paper's uncorrelated ``P_POS = R`` instead changed the Monte Carlo NEES (qekf_history.md) from 4.8 to
5.1, nothing else). The fallback's horizontal re-initialisations from a fix set ``r = z``,
``e = e_gm = 0`` with ``var(r) = var_e + var_w``, ``cov(r, e) = cov(r, e_gm) = -var_e``. The
prediction multiplies the 28 x 28 covariance by a block-diagonal ``F`` (about 5 % slower than
22 states: 3450 against 3650 samples/s on car-magnetometer).

The figures behind these choices: ``benchmarks/results/qekf_history.md``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from iotnav.engines import qekf_kernel as K
from iotnav.engines.eskf_models import gm_variance_factor, stationary_gnss_error_cov
from iotnav.engines.qekf_models import (
    _I3,
    GNE,
    GNM,
    N_STATES,
    POS,
    FloatArray,
    position_measurement,
    velocity_measurement,
)

if TYPE_CHECKING:
    from iotnav.engines.qekf import QekfEngine

__all__ = ["gnss_error_transition"]


def gnss_error_transition(dt: float, corr_time_s: float, filter_s: float) -> tuple[FloatArray, FloatArray]:
    """Exact discretisation of one axis of the GNSS error model over ``dt`` (module docstring).

    State ``[e, e_gm]`` (the error the fix carries, the Gauss-Markov error before the receiver's
    low-pass): ``d(e_gm)/dt = -e_gm / T_e + w``, ``de/dt = (e_gm - e) / t_f``.

    Parameters
    ----------
    dt : float
        Step, s.
    corr_time_s : float
        Correlation time ``T_e`` of ``e_gm``, s.
    filter_s : float
        Receiver filter time constant ``t_f``, s; 0: none (``e`` is then the Gauss-Markov
        process itself and ``e_gm`` is inert).

    Returns
    -------
    Phi : numpy.ndarray
        Transition (2, 2): ``[[b, c], [0, a]]``, ``a = exp(-dt/T_e)``, ``b = exp(-dt/t_f)``,
        ``c = T_e (a - b) / (T_e - t_f)`` (``(dt / t_f) a`` when ``t_f = T_e``).
    Q : numpy.ndarray
        Process noise (2, 2) per unit ``var(e_gm)`` (driving intensity ``2 var(e_gm) / T_e``),
        integrated exactly; its ``e_gm`` element is ``1 - a^2``. Without a receiver filter
        ``[[1 - a^2, 0], [0, 0]]`` per unit ``var(e)``.
    """
    g = np.empty(6)
    K.gnss_error_step(dt, corr_time_s, filter_s, g)  # the engine's compiled prediction uses it too
    b, c, a, q_ee, q_eg, q_gg = g.tolist()
    return np.array([[b, c], [0.0, a]]), np.array([[q_ee, q_eg], [q_eg, q_gg]])


def _gnss_error_correlation(lag_s: FloatArray, corr_time_s: float, filter_s: float) -> FloatArray:
    """Autocorrelation ``cov(e(t), e(t + L)) / var(e)`` of the model's ``e`` at lags ``L >= 0``."""
    L = np.abs(lag_s)
    Te, tf = corr_time_s, filter_s
    if tf <= 0.0:
        return np.exp(-L / Te)
    if abs(Te - tf) <= 1e-6 * Te:
        return (1.0 + L / Te) * np.exp(-L / Te)
    return (Te * np.exp(-L / Te) - tf * np.exp(-L / tf)) / (Te - tf)


def set_gnss_noise(
    eng: QekfEngine,
    R: FloatArray,
    lat_deg: float,
    kind: tuple[str, str] | None = None,
) -> None:
    """Split a fix's position variance ``R`` (diagonal, m^2) into the correlated part carried
    by the states and the white part of the measurement (``gnss_error_states``); ``kind``:
    the figures that gave it (:func:`~iotnav.engines.anchor.gnss_position_noise_source`)."""
    c = eng.config
    var_p = np.diag(R).copy()
    f = c.gnss_white_fraction
    eng._noise_kind = kind
    eng._var_e = max(1.0 - f * f, 0.0) * var_p
    eng._var_gm[:] = gm_variance_factor(eng._te, c.gnss_receiver_filter_s) * eng._var_e
    floor = np.maximum(c.gnss_white_floor_m, np.asarray(eng.resolution.sigma_ned_m(lat_deg)))
    eng._var_white = np.maximum(f * np.sqrt(var_p), floor) ** 2


def scale_gnss_error(eng: QekfEngine, steps: tuple[float, float, float]) -> None:
    """The correlated-error states follow the reported accuracy (per NED axis); ``steps``:
    the relative rounding of the figures behind the fix's sigma.

    A receiver re-acquiring after a tunnel reports a larger sigma and its fixes are that
    much further off (in the simulator exactly ``e = sigma(t) y``). As ``eskf``
    (:meth:`iotnav.engines.eskf.EskfEngine._scale_gnss_error`) the estimates and the
    covariance rows of ``[e, e_gm]`` are scaled by the ratio ``k`` of the fix's sigma to
    the level they were scaled to (``x' = T x``, ``P' = T P T^T``), of the same kind of
    figures (hAcc / vAcc, or DOPs), at once for continuous figures and jumps, low-passed
    over the figures' rounding steps
    (:class:`~iotnav.engines.gnss_resolution.AccuracyScaling`). Scaled at once by every
    rounding step of the DOPs (0.01, +-1 %) the states took those steps for information
    about ``e``: on the tests' receiver-error runs the position sigma fell from 1.22 to
    0.75 m with the error unchanged (NEES 5.5 -> 8.0); adding only the variance increase
    instead left the innovations correlated (Box-Pierce 10.5 / 22.0 / 21.6). For the
    smoother the scaling is a step of the transition into the fix's record
    (``Phi' = T Phi``).
    """
    kr = eng._scaling.ratio(eng.t_x, np.sqrt(eng._var_e), eng._noise_kind, steps)
    if kr is None:
        return
    k = np.array(kr)
    if eng._prior is not None:  # an update at this time already: its record ends here
        eng._flush_record()
    d = np.ones(eng.n)
    d[GNE] = k
    d[GNM] = k
    eng.x *= d
    eng.P *= np.outer(d, d)
    if eng.smoothing_log is not None:
        eng._Phi = d[:, None] * eng._Phi


def gnss_error_cov(eng: QekfEngine, rows: slice | list[int]) -> FloatArray:
    """Stationary covariance of ``[e, e_gm]`` on the given axes (2k, 2k): ``var(e) =
    cov(e, e_gm) = sigma_e^2``, ``var(e_gm) = sigma_e^2 (T_e + t_f) / T_e``."""
    c = eng.config
    return stationary_gnss_error_cov(eng._var_e[rows], eng._te[rows], c.gnss_receiver_filter_s)


def init_gnss_error(eng: QekfEngine, t: float) -> None:
    """Covariance of the position and GNSS error states at the end of the initialisation.

    The position state is 0 at the origin, the mean of the ``N`` initialisation fixes, so
    its error is minus the mean of their errors, ``-(mean_k e(t_k) + mean_k w_k)``, which is
    correlated with the error ``e(t)`` the next fixes carry: ``r + e`` is known better than
    either. Under the model (stationary ``e``, the latest fix's variances, device still)::

        P_POS     = var_e mean_jk rho(t_j - t_k) + sum_k var_w,k / N^2
        P_POS,GNE = -var_e mean_k rho(t - t_k),   P_POS,GNM = -var_e mean_k exp(-(t - t_k)/T_e)

    (``rho`` the autocorrelation of ``e``, :func:`_gnss_error_correlation`; ``cov(e(t_k),
    e_gm(t)) = var_e exp(-(t - t_k)/T_e)`` for ``t >= t_k``), and ``[GNE, GNM]`` the
    stationary covariance. Taking ``P_POS = R`` uncorrelated instead would claim the first
    fixes after the initialisation carry metres of new information on ``r + e`` that they
    do not; and a fix taken as a single one (``P_POS = var_e + var_w``,
    ``P_POS,GNE = -var_e``) would claim ``r + e`` known to ``var_w``, while ``e`` moves over
    the initialisation's 40 s.
    """
    c = eng.config
    n0 = N_STATES
    eng.P[n0:, n0:] = eng._gnss_error_cov(slice(0, 3))
    eng._scaling.reset(np.sqrt(eng._var_e), eng._noise_kind)
    tk = np.asarray(eng._init_fix_t, float)
    N = tk.size
    if N == 0:
        return
    tf = c.gnss_receiver_filter_s
    v = eng._var_e
    lag = np.maximum(t - tk, 0.0)
    m_ee, m_e, m_g = np.empty(3), np.empty(3), np.zeros(3)
    for i, Te in enumerate(eng._te):
        m_ee[i] = np.mean(_gnss_error_correlation(tk[:, None] - tk[None, :], Te, tf))
        m_e[i] = np.mean(_gnss_error_correlation(lag, Te, tf))
        m_g[i] = np.mean(np.exp(-lag / Te)) if tf > 0.0 else 0.0
    eng.P[POS, POS] = np.diag(v * m_ee + eng._init_var_white / N**2)
    for sl, m in ((GNE, m_e), (GNM, m_g)):
        eng.P[POS, sl] = -np.diag(v * m)
        eng.P[sl, POS] = eng.P[POS, sl]


def position_model(
    eng: QekfEngine, r_n: FloatArray, R: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """GNSS position ``(z, H, R)``; with ``gnss_error_states`` ``z = r + e + w``: ``H`` is ``I``
    on ``POS`` and on ``GNE``, ``R`` the white part (:meth:`_set_gnss_noise`), else the
    fix's whole ``R``."""
    if eng.n == N_STATES:
        return position_measurement(r_n, R)
    z, H, Rm = position_measurement(r_n, np.diag(eng._var_white))
    H = eng._pad(H)
    H[:, GNE] = _I3
    return z, H, Rm


def velocity_model(eng: QekfEngine, v: FloatArray, sigma: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """GNSS velocity ``(z, H, R)``; with ``gnss_error_states`` its error is the derivative of
    the smoothed position error plus white Doppler noise, ``z = v + (e_gm - e) / t_f + w``."""
    z, H, Rm = velocity_measurement(v, sigma)
    H = eng._pad(H)
    tf = eng.config.gnss_receiver_filter_s
    if eng.n > N_STATES and tf > 0.0:
        m = z.size
        H[:, GNE.start : GNE.start + m] = -np.eye(m) / tf
        H[:, GNM.start : GNM.start + m] = np.eye(m) / tf
    return z, H, Rm
