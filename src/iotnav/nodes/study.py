"""Monte Carlo studies of node localization against the Cramer-Rao bound.

Used by the seeded tests and by ``benchmarks/bench_nodes.py``. A geometry (anchor loops and
node positions, :func:`iotnav.nodes.simulate.fleet_scenario`) is drawn once from
``geometry_seed``; every run redraws shadowing, packet loss, beacon phases and the anchors'
reported-position errors, solves every node and records the error, the reported covariance
and the CRB (equation M4) of the reports actually received, evaluated at the truth with the
true anchor positions.

Summary statistics per study:

* ``rmse_m = sqrt(mean ||p_hat - p||^2)`` over runs and nodes, against
  ``crb_m = sqrt(mean tr CRB)`` (the bound on the same mean squared error);
* ``anees = mean (p_hat - p)^T P^{-1} (p_hat - p)``; for a consistent estimator ``N * anees``
  is chi-square with ``2 N`` degrees of freedom (``N`` estimates), which gives the two-sided
  95 % interval :func:`anees_interval`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.stats import chi2

from iotnav.nodes.locate import pair_reports
from iotnav.nodes.multilateration import Method, SolverConfig, Status, crb, solve_position
from iotnav.nodes.ranging import PathLossModel
from iotnav.nodes.simulate import RadioSimConfig, anchor_errors, fleet_scenario, simulate_rssi

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class StudyResult:
    """Per-estimate outcomes of a Monte Carlo study (``N`` = runs x nodes).

    Attributes
    ----------
    err_ne : numpy.ndarray
        ``(N, 2)`` estimate minus truth, m (NaN without estimate).
    P : numpy.ndarray
        ``(N, 2, 2)`` reported covariances, m^2.
    crb : numpy.ndarray
        ``(N, 2, 2)`` Cramer-Rao bounds at the truth, m^2.
    status : numpy.ndarray
        ``(N,)`` status strings.
    n_reports : numpy.ndarray
        ``(N,)`` reports per estimate.
    """

    err_ne: FloatArray
    P: FloatArray
    crb: FloatArray
    status: npt.NDArray[np.str_]
    n_reports: npt.NDArray[np.int_]

    def ok(self) -> npt.NDArray[np.bool_]:
        """Mask of estimates with status ``ok``."""
        return self.status == str(Status.OK)

    def errors_m(self, mask: npt.NDArray[np.bool_] | None = None) -> FloatArray:
        """Horizontal error norms, m."""
        m = self.ok() if mask is None else mask
        return np.linalg.norm(self.err_ne[m], axis=1)

    def rmse_m(self, mask: npt.NDArray[np.bool_] | None = None) -> float:
        """Root mean square horizontal error, m."""
        e = self.errors_m(mask)
        return float(np.sqrt(np.mean(e**2)))

    def crb_m(self, mask: npt.NDArray[np.bool_] | None = None) -> float:
        """``sqrt(mean tr CRB)``, m."""
        m = self.ok() if mask is None else mask
        return float(np.sqrt(np.mean(np.trace(self.crb[m], axis1=1, axis2=2))))

    def nees(self, mask: npt.NDArray[np.bool_] | None = None) -> FloatArray:
        """Normalised estimation error squared per estimate."""
        m = self.ok() if mask is None else mask
        e = self.err_ne[m]
        return np.einsum("ki,ki->k", e, np.linalg.solve(self.P[m], e[:, :, None])[:, :, 0])


def anees_interval(n_estimates: int, dof: int = 2, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided interval of the average NEES of ``n_estimates`` consistent estimates."""
    a = (1.0 - probability) / 2.0
    k = n_estimates * dof
    return float(chi2.ppf(a, k) / n_estimates), float(chi2.ppf(1.0 - a, k) / n_estimates)


def fleet_study(
    n_anchors: int,
    model: PathLossModel,
    n_runs: int,
    n_nodes: int = 10,
    anchor_std_m: float = 3.0,
    cfg: RadioSimConfig | None = None,
    method: Method | str = Method.WLS,
    geometry_seed: int = 0,
    noise_seed: int = 1,
    area_m: float = 1000.0,
    duration_s: float = 600.0,
    solver: SolverConfig | None = None,
    speed_mps: float = 10.0,
) -> StudyResult:
    """Monte Carlo over noise for one fixed fleet geometry (see the module docstring).

    Parameters
    ----------
    n_anchors : int
        Mobile anchors (each drives a loop of radius ``area_m / 4``).
    model : PathLossModel
        Radio; ``shadowing_db`` is simulated and assumed by the solver.
    n_runs : int
        Monte Carlo runs.
    n_nodes : int
        Static nodes uniform over the area.
    anchor_std_m : float
        Anchor position error per axis, m (simulated and reported).
    cfg : RadioSimConfig, optional
        Link settings.
    method : str
        Solver.
    geometry_seed, noise_seed : int
        Seeds of the geometry and of the noise.
    area_m, duration_s : float
        Side of the square area (m) and simulated time (s).
    solver : SolverConfig, optional
        Solver tunables.
    speed_mps : float
        Anchor speed, m/s.

    Returns
    -------
    StudyResult
        Outcomes of ``n_runs * n_nodes`` estimates.
    """
    c = cfg if cfg is not None else RadioSimConfig()
    base = fleet_scenario(
        n_anchors, n_nodes, model, c, geometry_seed, area_m, duration_s, speed_mps, anchor_std_m
    )
    rng = np.random.default_rng(noise_seed)
    errs, Ps, crbs, stats, nrep = [], [], [], [], []
    truth_ne = {
        str(k): (float(n), float(e), float(d))
        for k, n, e, d in zip(
            base.nodes["node_id"], base.nodes["north"], base.nodes["east"], base.nodes["down"], strict=True
        )
    }
    for _ in range(n_runs):
        rssi = simulate_rssi(base.tracks_true, base.nodes, model, c, rng)
        reported = anchor_errors(base.tracks_true, c, rng)
        paired = pair_reports(reported, rssi, 30.0, Counter())
        paired_true = pair_reports(base.tracks_true, rssi, 30.0, Counter())
        for nid, g in paired.groupby("node_id", sort=True):
            gt = paired_true.loc[g.index]
            A = g[["a_north", "a_east", "a_down"]].to_numpy(float)
            S = g[["a_std_north", "a_std_east"]].to_numpy(float)
            tn, te, z = truth_ne[str(nid)]
            p_true = np.array([tn, te])
            est = solve_position(A, g["rssi_dbm"].to_numpy(float), model, S, z, method, solver)
            errs.append(est.p_ne - p_true)
            Ps.append(est.P)
            crbs.append(crb(p_true, gt[["a_north", "a_east", "a_down"]].to_numpy(float), model, S, z))
            stats.append(str(est.status))
            nrep.append(len(g))
    return StudyResult(np.array(errs), np.array(Ps), np.array(crbs), np.array(stats), np.array(nrep))
