"""RSSI multilateration of a non-GNSS node from anchors with uncertain positions.

Second step of the anchor-node mechanism of Zorkany et al. (2022, section 4, Fig. 3): anchors
localized by GNSS + IMU fusion broadcast their positions; a cheaper node without a receiver
is placed from the RSSI of what it hears (or what hears it). Following Kumar and Arablouei
(2022, cited by the paper), each anchor position is itself an estimate with a covariance.

Model (local NED frame ``n``, metres). The node's horizontal position ``p = [north, east]``
is the unknown; its down coordinate ``z_node`` is given (nodes lie near the ground). Report
``k`` comes from an anchor at reported position ``a_k = [a_N, a_E, a_D]`` whose horizontal
error ``e_k ~ N(0, Sigma_k)`` (from the fusion engine's covariance) is independent between
reports:

.. math::

    r_k = h_k(p) + w_k, \\qquad
    h_k(p) = P_0 - 10\\,n\\,\\log_{10}(d_k / d_0), \\qquad
    d_k = \\sqrt{\\lVert p - a_k \\rVert^2 + (z_{node} - a_{D,k})^2}              \\quad (M1)

    g_k = \\frac{\\partial h_k}{\\partial p}
        = -\\frac{10\\,n}{\\ln 10}\\,\\frac{p - a_k}{d_k^2}, \\qquad
    \\frac{\\partial h_k}{\\partial a_k} = -g_k                                   \\quad (M2)

Linearising in the anchor error, the report's effective variance is

.. math::

    s_k^2 = \\sigma^2 + g_k^T \\Sigma_k\\, g_k                                   \\quad (M3)

Weighted least squares / Gauss-Newton minimises ``sum_k (r_k - h_k(p))^2 / s_k^2`` with the
step ``dp = (G^T W G)^{-1} G^T W (r - h)``, ``W = diag(1/s_k^2)`` refreshed every iteration,
and reports ``P = (G^T W G)^{-1}`` at the solution.

Cramer-Rao bound. Treat each anchor error ``e_k`` as a Gaussian nuisance parameter (hybrid
Fisher information). The joint information of ``(p, e_k)`` contributed by report ``k`` is
``[g; -g][g; -g]^T / sigma^2`` plus the prior ``Sigma_k^{-1}`` on ``e_k``; its Schur complement
over ``e_k`` (Woodbury identity) leaves

.. math::

    J(p) = \\sum_k \\frac{g_k g_k^T}{\\sigma^2 + g_k^T \\Sigma_k g_k}, \\qquad
    \\mathrm{CRB}(p) = J(p)^{-1}, \\qquad
    \\mathrm{E}\\lVert \\hat p - p\\rVert^2 \\ge \\operatorname{tr} \\mathrm{CRB}(p)  \\quad (M4)

so the anchor uncertainty enters exactly as the extra variance (M3): the WLS covariance at the
true position equals the CRB, and the estimator is asymptotically efficient. Anchor errors
matter when ``|g_k| sigma_a`` approaches ``sigma``, i.e. at short range (BLE): with
``sigma_a = 3 m``, ``n = 2.7`` and ``sigma = 6 dB`` they add 10 % of variance at about 11 m.

Reported covariance. The Laplace form ``(G^T W G)^{-1}`` is the CRB evaluated at the
estimate. When the information comes mostly from a few close passes (distance comparable to
the error), the likelihood is curved and the Laplace covariance is optimistic (NEES well above
2 in Monte Carlo). The default is therefore the likelihood's second moment about the estimate,
computed on a grid ``p_ij`` spanning +-6 Laplace standard deviations along its principal axes:

.. math::

    P = \\sum_{ij} \\pi_{ij} (p_{ij} - \\hat p)(p_{ij} - \\hat p)^T, \\qquad
    \\pi_{ij} \\propto \\exp(-\\chi^2(p_{ij}) / 2)                              \\quad (M5)

(with the final robust weights for Huber), which equals ``(G^T W G)^{-1}`` when the model is
linear over the uncertainty region.

Robust variants for NLOS reports (RSSI far below the LOS prediction):

* Huber M-estimator: IRLS with weights ``psi(u)/u``, ``u_k = (r_k - h_k)/s_k``,
  ``psi(u) = clip(u, -c, c)``, ``c = 1.345``; covariance
  ``P = E[psi^2] / E[psi'] (sum_{|u_k|<=c} g_k g_k^T / s_k^2)^{-1}`` (Huber 1981, 7.6),
  which reduces to ``1.05 J^{-1}`` for Gaussian reports.
* RANSAC: random minimal sets of three reports, consensus ``|u_k| <= t``, WLS refit on the
  largest consensus set.

Geometry checks: no reports (``no_data``), fewer than three reports or a singular/ill-conditioned
``J`` (``underdetermined``), and a mirror test: anchors on (nearly) one line cannot tell the
node from its reflection across that line, so the reflection's cost is evaluated and the
estimate flagged ``ambiguous`` when it converges to a separate minimum (more than
``ambiguity_separation`` standard deviations away) that fits as well (``Delta chi^2`` below
``ambiguity_dchi2``).

Everything here is pure: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import numpy.typing as npt
from scipy.stats import norm

from iotnav.nodes.ranging import DB_PER_LN, PathLossModel, distance_from_rssi

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Horizontal position in the state of every solver: ``x[POS] = [north, east]`` (m).
POS = slice(0, 2)


class Status(StrEnum):
    """Quality flag of a node position."""

    OK = "ok"
    AMBIGUOUS = "ambiguous"
    UNDETERMINED = "underdetermined"
    NO_DATA = "no_data"
    NOT_CONVERGED = "not_converged"


class Method(StrEnum):
    """Batch solvers."""

    WLS = "wls"
    HUBER = "huber"
    RANSAC = "ransac"


@dataclass(frozen=True)
class SolverConfig:
    """Tunables of the batch solvers.

    Attributes
    ----------
    max_iter : int
        Gauss-Newton iteration limit.
    tol_m : float
        Convergence threshold on the step length, m.
    huber_c : float
        Huber threshold in effective standard deviations (95 % Gaussian efficiency at 1.345).
    ransac_iterations : int
        Random minimal sets tried by RANSAC.
    ransac_threshold : float
        RANSAC consensus threshold on ``|u_k|`` (effective standard deviations).
    ransac_seed : int
        Seed of RANSAC's sampler (results are deterministic).
    grid_points : int
        Points per axis of the coarse start-up grid search.
    ambiguity_dchi2 : float
        A mirror position whose cost exceeds the solution's by less than this is a competing
        solution: the estimate is flagged ``ambiguous``.
    ambiguity_separation : float
        ...provided both minima are this many standard deviations apart (Mahalanobis distance
        in the solution's covariance); closer minima are one broad minimum, already covered by
        the covariance.
    max_condition : float
        Largest acceptable condition number of the information matrix.
    min_distance_m : float
        Distances are clamped below at this value, m (avoids log of zero).
    covariance : {"posterior", "laplace"}
        ``laplace`` reports ``(G^T W G)^{-1}`` at the solution; ``posterior`` (default) the
        second moment about the solution of the normalised likelihood ``exp(-chi^2(p) / 2)``
        on a grid (equation M5), which stays honest when a few close reports make the
        likelihood curved or skewed.
    posterior_half_width : float
        Half width of the posterior grid in Laplace standard deviations along each principal
        axis.
    posterior_points : int
        Grid points per axis of the posterior grid.
    """

    max_iter: int = 50
    tol_m: float = 1e-3
    huber_c: float = 1.345
    ransac_iterations: int = 100
    ransac_threshold: float = 2.5
    ransac_seed: int = 0
    grid_points: int = 25
    ambiguity_dchi2: float = 9.0
    ambiguity_separation: float = 5.0
    max_condition: float = 1e8
    min_distance_m: float = 0.1
    covariance: str = "posterior"
    posterior_half_width: float = 6.0
    posterior_points: int = 21


@dataclass(frozen=True)
class PositionEstimate:
    """A node position with its uncertainty.

    Attributes
    ----------
    p_ne : numpy.ndarray
        ``[north, east]`` in the local frame, m (NaN when no estimate exists).
    P : numpy.ndarray
        ``(2, 2)`` covariance of ``p_ne``, m^2 (NaN when undetermined).
    status : Status
        Quality flag.
    iterations : int
        Gauss-Newton iterations of the final fit.
    n_reports : int
        Reports given.
    n_used : int
        Inliers: reports at full weight (all for WLS, |u| <= c for Huber, the consensus set for
        RANSAC).
    chi2 : float
        ``sum_k w_k (r_k - h_k)^2 / s_k^2`` at the solution.
    inliers : numpy.ndarray
        Boolean mask of reports used at full weight.
    mirror_ne : numpy.ndarray
        The competing mirror solution when ``status`` is ``ambiguous``, else NaN.
    """

    p_ne: FloatArray
    P: FloatArray
    status: Status
    iterations: int
    n_reports: int
    n_used: int
    chi2: float
    inliers: BoolArray
    mirror_ne: FloatArray

    @property
    def std_ne(self) -> FloatArray:
        """Standard deviations of north and east, m."""
        return np.sqrt(np.diag(self.P))

    @property
    def drms_m(self) -> float:
        """``sqrt(trace(P))``, m (distance root mean square)."""
        return float(np.sqrt(np.trace(self.P)))


def _as_cov(anchor_cov_ne: npt.ArrayLike | None, n: int) -> FloatArray:
    if anchor_cov_ne is None:
        return np.zeros((n, 2, 2))
    c = np.asarray(anchor_cov_ne, dtype=float)
    if c.ndim == 1:  # per-report isotropic standard deviation, m
        return (c**2)[:, None, None] * np.eye(2)[None]
    if c.ndim == 2 and c.shape[1] == 2:  # per-report [std_north, std_east], m
        out = np.zeros((n, 2, 2))
        out[:, 0, 0] = c[:, 0] ** 2
        out[:, 1, 1] = c[:, 1] ** 2
        return out
    return c.reshape(n, 2, 2)


def predict_rssi(
    p_ne: FloatArray,
    anchor_n: FloatArray,
    model: PathLossModel,
    node_down_m: float = 0.0,
    min_distance_m: float = 0.1,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted RSSI, its gradient and the distances (equations M1, M2).

    Parameters
    ----------
    p_ne : numpy.ndarray
        Node ``[north, east]``, m.
    anchor_n : numpy.ndarray
        ``(K, 3)`` anchor NED positions, m.
    model : PathLossModel
        Radio parameters.
    node_down_m : float
        Node down coordinate, m.
    min_distance_m : float
        Lower clamp of the distance, m.

    Returns
    -------
    h : numpy.ndarray
        ``(K,)`` predicted RSSI, dBm.
    G : numpy.ndarray
        ``(K, 2)`` gradient ``dh/dp``, dB/m.
    d : numpy.ndarray
        ``(K,)`` 3-D distances, m.
    """
    delta = p_ne[None, :] - anchor_n[:, :2]
    dz = node_down_m - anchor_n[:, 2]
    d2 = np.maximum(np.einsum("ki,ki->k", delta, delta) + dz**2, min_distance_m**2)
    d = np.sqrt(d2)
    h = model.p0_dbm - 10.0 * model.n * np.log10(d / model.d0_m)
    G = -(model.n * DB_PER_LN) * delta / d2[:, None]
    return h, G, d


def effective_variance(G: FloatArray, anchor_cov_ne: FloatArray, shadowing_db: float) -> FloatArray:
    """Per-report variance with the anchor position error propagated (equation M3), dB^2."""
    return shadowing_db**2 + np.einsum("ki,kij,kj->k", G, anchor_cov_ne, G)


def crb(
    p_ne: npt.ArrayLike,
    anchor_n: npt.ArrayLike,
    model: PathLossModel,
    anchor_cov_ne: npt.ArrayLike | None = None,
    node_down_m: float = 0.0,
) -> FloatArray:
    """Cramer-Rao bound of the horizontal node position (equation M4), m^2.

    Parameters
    ----------
    p_ne : array_like
        True node ``[north, east]``, m.
    anchor_n : array_like
        ``(K, 3)`` anchor NED positions of the reports, m.
    model : PathLossModel
        Radio parameters (``shadowing_db`` is ``sigma``).
    anchor_cov_ne : array_like, optional
        Horizontal anchor covariance per report: ``(K, 2, 2)`` in m^2, ``(K, 2)`` standard
        deviations ``[std_north, std_east]`` in m, or ``(K,)`` isotropic standard deviations, m.
    node_down_m : float
        Node down coordinate, m.

    Returns
    -------
    numpy.ndarray
        ``(2, 2)`` bound; ``inf`` entries when the information matrix is singular.
    """
    A = np.asarray(anchor_n, dtype=float).reshape(-1, 3)
    C = _as_cov(anchor_cov_ne, A.shape[0])
    _, G, _ = predict_rssi(np.asarray(p_ne, dtype=float), A, model, node_down_m)
    s2 = effective_variance(G, C, model.shadowing_db)
    J = G.T @ (G / s2[:, None])
    if np.linalg.matrix_rank(J) < 2:
        return np.full((2, 2), np.inf)
    return np.asarray(np.linalg.inv(J), dtype=np.float64)


def _huber_weights(u: FloatArray, c: float) -> FloatArray:
    a = np.abs(u)
    return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))


def _huber_factor(c: float) -> float:
    """``E[psi^2] / E[psi']`` for the Huber psi under a standard normal."""
    p_in = 2.0 * norm.cdf(c) - 1.0
    e_psi2 = p_in - 2.0 * c * norm.pdf(c) + c * c * (1.0 - p_in)
    return float(e_psi2 / p_in)


@dataclass
class _Problem:
    anchor_n: FloatArray
    rssi: FloatArray
    cov: FloatArray
    model: PathLossModel
    node_down_m: float
    cfg: SolverConfig

    def eval(self, p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Residuals, gradient and effective variances at ``p``."""
        h, G, _ = predict_rssi(p, self.anchor_n, self.model, self.node_down_m, self.cfg.min_distance_m)
        s2 = effective_variance(G, self.cov, self.model.shadowing_db)
        return self.rssi - h, G, s2


def _gauss_newton(
    prob: _Problem, p0: FloatArray, robust_c: float | None, mask: BoolArray | None = None
) -> tuple[FloatArray, int, bool]:
    """IRLS Gauss-Newton from ``p0``; Huber weights when ``robust_c`` is given."""
    p = p0.astype(float).copy()
    sel = np.ones(prob.rssi.size, dtype=bool) if mask is None else mask
    for it in range(1, prob.cfg.max_iter + 1):
        r, G, s2 = prob.eval(p)
        w = sel / s2
        if robust_c is not None:
            w = w * _huber_weights(r / np.sqrt(s2), robust_c)
        JtJ = G.T @ (G * w[:, None])
        Jtr = G.T @ (w * r)
        try:
            dp = np.linalg.solve(JtJ + 1e-12 * np.trace(JtJ) * np.eye(2), Jtr)
        except np.linalg.LinAlgError:
            return p, it, False
        cost0 = float(np.sum(w * r**2))
        step = 1.0
        for _ in range(30):
            r1, _, _ = prob.eval(p + step * dp)
            if float(np.sum(w * r1**2)) <= cost0 + 1e-12:
                break
            step *= 0.5
        p = p + step * dp
        if step * float(np.linalg.norm(dp)) < prob.cfg.tol_m:
            return p, it, True
    return p, prob.cfg.max_iter, False


def _grid_start(prob: _Problem, mask: BoolArray) -> FloatArray:
    """Coarse grid search of the clipped (outlier-tolerant) cost over the anchors' area."""
    idx = np.flatnonzero(mask)
    if idx.size > 300:  # an even subsample is plenty for a start point
        idx = idx[np.linspace(0, idx.size - 1, 300).astype(int)]
    A = prob.anchor_n[idx]
    rs = prob.rssi[idx]
    d_hat = distance_from_rssi(rs, prob.model)
    pad = float(np.clip(np.median(d_hat), 1.0, 10.0 * (np.ptp(A[:, 0]) + np.ptp(A[:, 1]) + 100.0)))
    lo = A[:, :2].min(axis=0) - pad
    hi = A[:, :2].max(axis=0) + pad
    g = prob.cfg.grid_points
    N, E = np.meshgrid(np.linspace(lo[0], hi[0], g), np.linspace(lo[1], hi[1], g), indexing="ij")
    pts = np.column_stack([N.ravel(), E.ravel()])
    dz = prob.node_down_m - A[:, 2]
    dn = pts[:, None, 0] - A[None, :, 0]
    de = pts[:, None, 1] - A[None, :, 1]
    d = np.sqrt(np.maximum(dn**2 + de**2 + dz[None, :] ** 2, prob.cfg.min_distance_m**2))
    h = prob.model.p0_dbm - 10.0 * prob.model.n * np.log10(d / prob.model.d0_m)
    u = (rs[None, :] - h) / prob.model.shadowing_db
    cost = np.sum(np.minimum(u**2, 9.0), axis=1)
    return pts[int(np.argmin(cost))]


def _info(prob: _Problem, p: FloatArray, weights: FloatArray) -> FloatArray:
    _, G, s2 = prob.eval(p)
    return G.T @ (G * (weights / s2)[:, None])


def _chi2(prob: _Problem, p: FloatArray, weights: FloatArray) -> float:
    r, _, s2 = prob.eval(p)
    return float(np.sum(weights * r**2 / s2))


def _posterior_cov(prob: _Problem, p: FloatArray, P: FloatArray, weights: FloatArray) -> FloatArray:
    """Second moment about ``p`` of ``exp(-chi^2/2)`` on a grid along ``P``'s axes (M5)."""
    cfg = prob.cfg
    lam, V = np.linalg.eigh(P)
    s = np.linspace(-cfg.posterior_half_width, cfg.posterior_half_width, cfg.posterior_points)
    a, b = np.meshgrid(s, s, indexing="ij")
    off = (a.ravel()[:, None] * np.sqrt(max(lam[0], 0.0))) * V[:, 0] + (
        b.ravel()[:, None] * np.sqrt(max(lam[1], 0.0))
    ) * V[:, 1]
    pts = p[None, :] + off
    A = prob.anchor_n
    dn = pts[:, None, 0] - A[None, :, 0]
    de = pts[:, None, 1] - A[None, :, 1]
    dz2 = (prob.node_down_m - A[:, 2]) ** 2
    d2 = np.maximum(dn**2 + de**2 + dz2[None, :], cfg.min_distance_m**2)
    kap = prob.model.n * DB_PER_LN
    h = prob.model.p0_dbm - 10.0 * prob.model.n * np.log10(np.sqrt(d2) / prob.model.d0_m)
    gn = -kap * dn / d2
    ge = -kap * de / d2
    C = prob.cov
    s2 = (
        prob.model.shadowing_db**2
        + gn**2 * C[None, :, 0, 0]
        + 2 * gn * ge * C[None, :, 0, 1]
        + ge**2 * C[None, :, 1, 1]
    )
    chi2 = np.sum(weights[None, :] * (prob.rssi[None, :] - h) ** 2 / s2, axis=1)
    w = np.exp(-0.5 * (chi2 - chi2.min()))
    w /= w.sum()
    out = np.einsum("k,ki,kj->ij", w, off, off)
    return 0.5 * (out + out.T)


def _mirror(prob: _Problem, p: FloatArray, mask: BoolArray) -> FloatArray:
    """Reflection of ``p`` across the principal line of the anchor positions used."""
    A = prob.anchor_n[mask, :2]
    c = A.mean(axis=0)
    X = A - c
    _, _, Vt = np.linalg.svd(X, full_matrices=False)
    u = Vt[0]
    v = p - c
    return c + 2.0 * (v @ u) * u - v


def solve_position(
    anchor_n: npt.ArrayLike,
    rssi_dbm: npt.ArrayLike,
    model: PathLossModel,
    anchor_cov_ne: npt.ArrayLike | None = None,
    node_down_m: float = 0.0,
    method: Method | str = Method.WLS,
    config: SolverConfig | None = None,
    p_init_ne: npt.ArrayLike | None = None,
) -> PositionEstimate:
    """Estimate a static node's horizontal position from RSSI reports (equations M1-M4).

    Parameters
    ----------
    anchor_n : array_like
        ``(K, 3)`` reported NED position of the anchor at each report, m.
    rssi_dbm : array_like
        ``(K,)`` RSSI of each report, dBm.
    model : PathLossModel
        Radio parameters; ``shadowing_db`` is the per-report standard deviation.
    anchor_cov_ne : array_like, optional
        Horizontal anchor position covariance per report (``(K, 2, 2)`` m^2, ``(K, 2)``
        standard deviations or ``(K,)`` isotropic standard deviations, m); zero when omitted.
    node_down_m : float
        The node's down coordinate in the same frame, m.
    method : {"wls", "huber", "ransac"}
        Solver (see the module docstring).
    config : SolverConfig, optional
        Tunables.
    p_init_ne : array_like, optional
        Start point ``[north, east]``, m; a coarse grid search when omitted.

    Returns
    -------
    PositionEstimate
        Position, covariance (m^2) and status flag.
    """
    cfg = config if config is not None else SolverConfig()
    meth = Method(method)
    A = np.asarray(anchor_n, dtype=float).reshape(-1, 3)
    r = np.asarray(rssi_dbm, dtype=float).ravel()
    K = r.size
    nan2 = np.full(2, np.nan)
    nan22 = np.full((2, 2), np.nan)
    if K == 0:
        return PositionEstimate(nan2, nan22, Status.NO_DATA, 0, 0, 0, np.nan, np.zeros(0, bool), nan2)
    if A.shape[0] != K:
        raise ValueError(f"{A.shape[0]} anchor positions for {K} RSSI values")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(r))):
        raise ValueError("anchor positions and RSSI must be finite (filter NaN reports first)")
    prob = _Problem(A, r, _as_cov(anchor_cov_ne, K), model, float(node_down_m), cfg)
    all_mask = np.ones(K, dtype=bool)
    distinct = np.unique(np.round(A[:, :2], 0), axis=0).shape[0]
    if K < 3 or distinct < 2:
        p_guess = A[:, :2].mean(axis=0)
        return PositionEstimate(p_guess, nan22, Status.UNDETERMINED, 0, K, K, np.nan, all_mask, nan2)

    if meth is Method.RANSAC:
        mask, start = _ransac(prob, cfg, p_init_ne)
    else:
        mask = all_mask
        start = np.asarray(p_init_ne, dtype=float) if p_init_ne is not None else _grid_start(prob, all_mask)
    robust_c = cfg.huber_c if meth is Method.HUBER else None
    p, iters, converged = _gauss_newton(prob, start, robust_c, mask)
    u, _, s2 = prob.eval(p)
    u = u / np.sqrt(s2)
    if robust_c is not None:
        w = mask * _huber_weights(u, robust_c)
        inl = mask & (np.abs(u) <= robust_c)
        J = _info(prob, p, inl.astype(float))
        factor = _huber_factor(robust_c)
    else:
        w = mask.astype(float)
        inl = mask.copy()
        J = _info(prob, p, w)
        factor = 1.0
    chi2 = _chi2(prob, p, w)
    status = Status.OK if converged else Status.NOT_CONVERGED
    eig = np.linalg.eigvalsh(J)
    if eig[0] <= 0.0 or eig[-1] / eig[0] > cfg.max_condition or int(inl.sum()) < 3:
        return PositionEstimate(p, nan22, Status.UNDETERMINED, iters, K, int(inl.sum()), chi2, inl, nan2)
    P = factor * np.linalg.inv(J)
    P = 0.5 * (P + P.T)
    if cfg.covariance == "posterior":
        P = _posterior_cov(prob, p, P, w)
    mirror = nan2
    pm = _mirror(prob, p, inl)
    dist = pm - p
    if float(dist @ np.linalg.solve(P, dist)) > 4.0:  # mirror is a distinct position
        pm_ref, _, conv_m = _gauss_newton(prob, pm, robust_c, mask)
        dm = pm_ref - p
        if conv_m and float(dm @ np.linalg.solve(P, dm)) > cfg.ambiguity_separation**2:
            chi2_m = _chi2(prob, pm_ref, w)
            if chi2_m < chi2:  # the mirror fits better: take it, the old one is the competitor
                p, pm_ref = pm_ref, p
                chi2, chi2_m = chi2_m, chi2
                J = _info(prob, p, inl.astype(float) if robust_c is not None else w)
                P = factor * np.linalg.inv(J)
                P = 0.5 * (P + P.T)
                if cfg.covariance == "posterior":
                    P = _posterior_cov(prob, p, P, w)
            if chi2_m - chi2 < cfg.ambiguity_dchi2:
                status = Status.AMBIGUOUS
                mirror = pm_ref
    return PositionEstimate(p, P, status, iters, K, int(inl.sum()), chi2, inl, mirror)


def _ransac(
    prob: _Problem, cfg: SolverConfig, p_init_ne: npt.ArrayLike | None
) -> tuple[BoolArray, FloatArray]:
    """Largest consensus set of random minimal (3-report) fits, and its WLS start point."""
    K = prob.rssi.size
    rng = np.random.default_rng(cfg.ransac_seed)
    grid_p = _grid_start(prob, np.ones(K, dtype=bool)) if p_init_ne is None else np.asarray(p_init_ne)
    best_mask = np.zeros(K, dtype=bool)
    best_key = (-1, np.inf)
    best_p = grid_p
    small = SolverConfig(max_iter=10, tol_m=cfg.tol_m, min_distance_m=cfg.min_distance_m)
    for _ in range(cfg.ransac_iterations):
        idx = rng.choice(K, size=3, replace=False)
        sub = _Problem(prob.anchor_n[idx], prob.rssi[idx], prob.cov[idx], prob.model, prob.node_down_m, small)
        p, _, _ = _gauss_newton(sub, grid_p, None)
        r, _, s2 = prob.eval(p)
        u = np.abs(r) / np.sqrt(s2)
        cons = u <= cfg.ransac_threshold
        key = (int(cons.sum()), float(np.sum(np.minimum(u, cfg.ransac_threshold) ** 2)))
        if key[0] > best_key[0] or (key[0] == best_key[0] and key[1] < best_key[1]):
            best_key, best_mask, best_p = key, cons, p
    # refit on the consensus set and take its final consensus (one re-selection round)
    p, _, _ = _gauss_newton(prob, best_p, None, best_mask)
    r, _, s2 = prob.eval(p)
    cons = np.abs(r) / np.sqrt(s2) <= cfg.ransac_threshold
    if cons.sum() < 3:
        cons = best_mask
    return cons, p
