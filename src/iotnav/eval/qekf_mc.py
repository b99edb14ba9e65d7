"""Monte Carlo consistency of the quaternion EKF (:mod:`iotnav.engines.qekf`) on simulated drives.

Each run simulates a short ``car-magnetometer`` drive (:mod:`iotnav.sim`), writes it as files,
reads it back through :func:`iotnav.io.ingest` (the user's path) and runs
:class:`~iotnav.engines.qekf.QekfEngine` sample by sample. From 20 s on (after the
initialisation's transient) it takes, once per second just after the GNSS epoch, the normalised
estimation error squared (NEES) of the navigation states (position and velocity in the
engine's local NED frame, m and m/s: 6 degrees of freedom), and every GNSS-position normalised
innovation squared (NIS, 3 dof), and the whitened GNSS-position innovations on the epoch grid
for the whiteness test (Bar-Shalom, Li and Kirubarajan 2001, *Estimation with Applications to
Tracking and Navigation*, sec. 5.4-5.5: run-averaged NEES/NIS against chi-square intervals,
innovation autocorrelation).

The test suite runs a few seeds (``tests/test_qekf_consistency.py``); the 20-run study with
every form of the filter is ``benchmarks/bench_qekf_consistency.py``.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import chi2

from iotnav import sim
from iotnav.engines.base import ImuSample, iter_samples
from iotnav.engines.qekf import POS, VEL, QekfConfig, QekfEngine
from iotnav.eval.consistency import epoch_grid
from iotnav.eval.metrics import track_errors
from iotnav.geo import geodetic_to_ecef
from iotnav.io import ingest
from iotnav.io.log import Log

#: Short car-magnetometer runs whose GNSS position errors are white (the filter's model):
#: correlation times far below the 1 s epoch, (almost) no receiver smoothing, no disturbance,
#: no gap. The simulator's GNSS velocity error is the derivative of the receiver-filtered
#: position error, which is huge without that filter, so these runs use positions only.
MC_OVERRIDES: dict[str, object] = {
    "motion.wait_start_s": 12.0,
    "duration_s": 75.0,
    "gnss.tau_h_s": 0.25,
    "gnss.tau_v_s": 0.25,
    "gnss.receiver_filter_s": 0.1,
    "gnss.outages_s": "[]",
    "mag.disturbances": "[]",
}

#: The same runs with the simulator's own receiver error (``open-sky``: Gauss-Markov, 150 s
#: horizontal and 200 s vertical, through the receiver's 2 s low-pass), what the
#: ``gnss_error_states`` option models; positions only, as above.
MC_OVERRIDES_RECEIVER: dict[str, object] = {
    k: v
    for k, v in MC_OVERRIDES.items()
    if k not in ("gnss.tau_h_s", "gnss.tau_v_s", "gnss.receiver_filter_s")
}

#: First sample time used (s): after the 12 s wait and the 10 s initialisation's transient.
T_FROM_S = 20.0


def simulate(tmp: Path, seed: int, overrides: dict[str, object] | None = None) -> tuple[sim.SimResult, Log]:
    """Simulate a ``car-magnetometer`` drive, write it to ``tmp`` and read it back.

    Parameters
    ----------
    tmp
        Folder for the simulated log files (created).
    seed
        Simulator seed.
    overrides
        Scenario settings (dotted keys of :func:`iotnav.sim.build`).

    Returns
    -------
    tuple
        The simulation (with its truth) and the log as :func:`iotnav.io.ingest` reads it.
    """
    r = sim.build("car-magnetometer", seed=seed, overrides=overrides or {})
    sim.write(r, tmp)
    return r, ingest([tmp])


def car_config(r: sim.SimResult, consistent: bool = False, **kw: object) -> QekfConfig:
    """The user's configuration for a simulated car drive.

    The magnetometer calibration ("previously calibrated", paper Sec. 3.1) is the simulation's,
    and the date for the World Magnetic Model is the simulated start, 2020-06-15 (decimal year
    2020.45).

    Parameters
    ----------
    r
        The simulation.
    consistent
        Use :meth:`QekfConfig.consistent` (its defaults are the simulated MPU-6050's datasheet)
        instead of the paper's form.
    **kw
        Further :class:`QekfConfig` fields.

    Returns
    -------
    QekfConfig
        The configuration.
    """
    hard, soft = r.mag_calibration()
    hx, hy, hz = hard
    return (QekfConfig.consistent if consistent else QekfConfig)(
        mag_hard_iron_ut=(hx, hy, hz),
        mag_soft_iron=soft,  # type: ignore[arg-type]
        wmm_year=2020.45,
        **kw,  # type: ignore[arg-type]
    )


def nees_run(
    tmp: Path, seed: int, receiver: bool = False, gnss_error_states: bool = False, consistent: bool = False
) -> tuple[list[float], list[float], np.ndarray]:
    """One Monte Carlo run: NEES samples, GNSS-position NIS values and whitened innovations.

    Parameters
    ----------
    tmp
        Folder for the simulated files.
    seed
        Simulator seed.
    receiver
        Use the simulator's correlated receiver error (:data:`MC_OVERRIDES_RECEIVER`) instead of
        white errors (:data:`MC_OVERRIDES`).
    gnss_error_states
        The filter's GNSS error states option.
    consistent
        Use :meth:`QekfConfig.consistent`.

    Returns
    -------
    tuple
        NEES of position and velocity (6 dof, one per second from :data:`T_FROM_S`), every
        GNSS-position NIS (3 dof), and the whitened GNSS-position innovations on the 1 s epoch
        grid (rows epochs, columns N / E / D; NaN where an epoch has none).
    """
    r, log = simulate(tmp, seed, MC_OVERRIDES_RECEIVER if receiver else MC_OVERRIDES)
    eng = QekfEngine(
        car_config(
            r,
            consistent,
            init_duration_s=10.0,
            uere_m=2.0,
            smoothing=False,
            use_gnss_velocity=False,
            gnss_error_states=gnss_error_states,
        ),
        record_innovations=True,
    )
    truth = r.truth
    t_truth = truth["t"].to_numpy()
    nees: list[float] = []
    idx = np.r_[7:10, 4:7]  # position, velocity in the 22-state vector's P ordering
    for s in iter_samples(log):
        eng.step(s)
        if not (isinstance(s, ImuSample) and eng.initialised) or s.t < T_FROM_S:
            continue
        if abs(s.t - np.floor(s.t) - 0.02) > 0.005:
            continue  # one sample per second, just after the GNSS epoch
        k = int(np.argmin(np.abs(t_truth - s.t)))
        row = truth.iloc[k]
        r_e = geodetic_to_ecef(row["lat"], row["lon"], row["height"])
        p_true = eng.C_en.T @ (r_e - eng.r_e0)
        v_true = row[["vn", "ve", "vd"]].to_numpy(float)
        e = np.concatenate([eng.x[POS] - p_true, eng.x[VEL] - v_true])  # navigation states only
        P = eng.P[np.ix_(idx, idx)]
        nees.append(float(e @ np.linalg.solve(P, e)))
    nis = [n[2] for n in eng.nis if n[1] == "gnss_pos"]
    pos = eng.innovations["gnss_pos"]
    late = pos.t >= T_FROM_S  # after the initialisation's transient, as the NEES
    white = epoch_grid(pos.t[late], pos.whitened()[late], r.config.gnss.rate_hz)
    return nees, nis, white


@dataclass(frozen=True)
class MonteCarlo:
    """Per-run results of :func:`monte_carlo`.

    Attributes
    ----------
    nees
        Each run's mean NEES (6 dof).
    nis
        Each run's mean GNSS-position NIS (3 dof).
    white
        Each run's whitened GNSS-position innovations on the epoch grid.
    """

    nees: np.ndarray
    nis: np.ndarray
    white: list[np.ndarray]

    @property
    def n_runs(self) -> int:
        """Number of runs."""
        return int(self.nees.size)

    def interval(self, dof: int, level: float = 0.95) -> tuple[float, float]:
        """Two-sided interval of the run-average of a chi-square(``dof``) statistic.

        For ``N`` runs the average of one epoch's statistic is ``chi2(dof N) / N``; averaging over
        the epochs too (correlated) keeps the interval of one epoch, a conservative choice.

        Parameters
        ----------
        dof
            Degrees of freedom of one statistic (6 for the NEES, 3 for the NIS).
        level
            Probability inside the interval.

        Returns
        -------
        tuple of float
            Lower and upper bounds.
        """
        n = self.n_runs
        lo, hi = chi2.ppf([(1 - level) / 2, (1 + level) / 2], dof * n) / n
        return float(lo), float(hi)


def monte_carlo(
    first_seed: int,
    n_runs: int,
    receiver: bool = False,
    gnss_error_states: bool = False,
    consistent: bool = False,
) -> MonteCarlo:
    """Run :func:`nees_run` on seeds ``first_seed .. first_seed + n_runs - 1``.

    Parameters
    ----------
    first_seed
        First simulator seed.
    n_runs
        Number of runs.
    receiver, gnss_error_states, consistent
        As in :func:`nees_run`.

    Returns
    -------
    MonteCarlo
        Each run's mean NEES, mean NIS and whitened innovations.
    """
    nees_runs, nis_runs, white_runs = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(n_runs):
            nees, nis, white = nees_run(
                Path(tmp) / f"r{i}", first_seed + i, receiver, gnss_error_states, consistent
            )
            nees_runs.append(np.mean(nees))
            nis_runs.append(np.mean(nis))
            white_runs.append(white)
    return MonteCarlo(np.array(nees_runs), np.array(nis_runs), white_runs)


def attitude_rms_deg(
    df: pd.DataFrame, truth: pd.DataFrame, t_min: float, rate_hz: float = 50.0
) -> dict[str, float]:
    """RMS of the roll, pitch and yaw errors (deg) on the samples both tables share.

    Parameters
    ----------
    df
        Engine output with ``t`` (s) and ``roll``, ``pitch``, ``yaw`` (rad, body to NED).
    truth
        The simulation's truth, same columns.
    t_min
        First time used (s).
    rate_hz
        The IMU rate (Hz): rows are matched on ``round(t * rate_hz)``.

    Returns
    -------
    dict
        ``roll``, ``pitch``, ``yaw`` RMS in degrees (angle differences wrapped to +-180 deg).
    """
    a = df.set_index(np.round(df["t"].to_numpy() * rate_hz).astype(int))
    b = truth.set_index(np.round(truth["t"].to_numpy() * rate_hz).astype(int))
    j = a.index.intersection(b.index)
    j = j[j >= t_min * rate_hz]
    out = {}
    for c in ("roll", "pitch", "yaw"):
        e = np.angle(np.exp(1j * (a.loc[j, c].to_numpy() - b.loc[j, c].to_numpy())))
        out[c] = float(np.degrees(np.sqrt(np.mean(e**2))))
    return out


def car_seed_run(tmp: Path, seed: int, consistent: bool = False) -> dict[str, float]:
    """The full ``car-magnetometer`` drive (40 s static, 220 s of town driving, a 4 s GNSS gap,
    a magnetic disturbance) through the forward filter, as a user configures it.

    Parameters
    ----------
    tmp
        Folder for the simulated files.
    seed
        Simulator seed.
    consistent
        Use :meth:`QekfConfig.consistent`.

    Returns
    -------
    dict
        ``roll``, ``pitch``, ``yaw``: RMS errors after the initialisation (deg, from 41 s);
        ``gap_max_m``: the largest horizontal error in the GNSS gap (m).
    """
    r, log = simulate(tmp, seed)
    eng = QekfEngine(car_config(r, consistent, smoothing=False))
    fwd = pd.DataFrame([o for s in iter_samples(log) if (o := eng.step(s)) is not None])
    out = attitude_rms_deg(fwd, r.truth, 41.0)
    gap = r.config.gnss.outages_s[0]
    err = track_errors(fwd.dropna(subset=["lat"]), r.truth)
    in_gap = (err.t >= gap[0]) & (err.t <= gap[1] + 0.5)
    out["gap_max_m"] = float(err.h_err[in_gap].max())
    return out
