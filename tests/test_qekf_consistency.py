"""Monte Carlo consistency of the quaternion EKF on a few held-out seeds.

The 20-run study on the design seeds (100-119) and the held-out ones (200-219), with whiteness
figures for every form, is ``benchmarks/bench_qekf_consistency.py`` (BENCHMARKS.md, section
"qekf Monte Carlo consistency"). Here :data:`N_RUNS` of the held-out seeds per form, with the
chi-square intervals of that many runs (:meth:`iotnav.eval.qekf_mc.MonteCarlo.interval`).
"""

from __future__ import annotations

import functools

import numpy as np

from iotnav.eval.consistency import innovation_autocorrelation
from iotnav.eval.qekf_mc import MonteCarlo, monte_carlo

N_RUNS = 8
FIRST_SEED = 200  # held out: seeds 100-119 were used in the design


@functools.cache
def _mc(receiver: bool = False, gnss_error_states: bool = False, consistent: bool = False) -> MonteCarlo:
    return monte_carlo(FIRST_SEED, N_RUNS, receiver, gnss_error_states, consistent)


def test_paper_form_mean_and_median_nees_and_nis() -> None:
    """White GNSS errors: the run-average NEES (6 dof) and GNSS-position NIS (3 dof), mean and
    median run, inside their 95 % intervals; the innovations nearly white (every lag 1-10 of
    every component below 0.2: the paper's form is not white, see the benchmark and the xfail
    reason in ``tests/test_qekf.py``).

    Observed (seeds 200-207): mean NEES 5.59 (median 5.46; interval 3.84-8.63), mean NIS 2.96
    (median 2.95; 1.55-4.92); largest lag correlation 0.19, Box-Pierce 32.6 / 49.7 / 11.3."""
    mc = _mc()
    lo6, hi6 = mc.interval(6)
    lo3, hi3 = mc.interval(3)
    for stat in (np.mean, np.median):
        assert lo6 < float(stat(mc.nees)) < hi6, (mc.nees, lo6, hi6)
        assert lo3 < float(stat(mc.nis)) < hi3, (mc.nis, lo3, hi3)
    ac = innovation_autocorrelation(mc.white, np.arange(1, 11))
    assert np.all(np.abs(ac.rho) < 0.2), ac.rho


def test_gnss_error_states_keep_the_nees_consistent_on_receiver_error() -> None:
    """The simulator's correlated receiver error (Gauss-Markov 150 s / 200 s through a 2 s
    low-pass): with ``gnss_error_states`` the NEES is inside its interval, without it the
    filter is over-confident (NEES above the interval). The NIS is low with the option, only its
    upper bound is asserted (1.6 over 20 runs, below that interval: the 1 s prediction is good
    to about 8 cm and the white process noise dominates ``S``; the module docstring of :mod:`iotnav.engines.qekf`, "GNSS error states").

    Observed (seeds 200-207): with the option NEES 5.04 (interval 3.84-8.63), NIS 1.69 (NIS
    interval 1.55-4.92); without it NEES 21.5, NIS 0.36."""
    on = _mc(True, True)
    lo6, hi6 = on.interval(6)
    assert lo6 < float(np.mean(on.nees)) < hi6, (on.nees, lo6, hi6)
    assert float(np.mean(on.nis)) < on.interval(3)[1], on.nis
    off = _mc(True, False)
    assert float(np.mean(off.nees)) > hi6, off.nees


def test_consistent_form_is_consistent_and_white() -> None:
    """:meth:`QekfConfig.consistent` on white errors (GNSS error states off) and on the
    receiver error (on): NEES and NIS inside their intervals and the innovations white
    (Box-Pierce over lags 1-10 against chi-square(10), N / E / D together at 95 %).

    Observed (seeds 200-207; NEES interval 3.84-8.63, NIS 1.55-4.92, Box-Pierce threshold
    21.7): white errors NEES 5.59, NIS 2.80, Box-Pierce 9.0 / 20.9 / 6.4 (N / E / D); receiver
    error NEES 5.56, NIS 2.84, Box-Pierce 6.6 / 10.6 / 12.0."""
    for receiver in (False, True):
        mc = _mc(receiver, receiver, True)
        lo6, hi6 = mc.interval(6)
        lo3, hi3 = mc.interval(3)
        assert lo6 < float(np.mean(mc.nees)) < hi6, (receiver, mc.nees, lo6, hi6)
        assert lo3 < float(np.mean(mc.nis)) < hi3, (receiver, mc.nis, lo3, hi3)
        ac = innovation_autocorrelation(mc.white, np.arange(1, 11))
        assert np.all(ac.portmanteau <= ac.portmanteau_threshold(familywise=True)), (receiver, ac.portmanteau)
