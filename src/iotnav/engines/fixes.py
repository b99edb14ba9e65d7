"""Tracks from GNSS fixes alone: the ``fixes`` engine (issue 17).

Most fleet trackers, phones and tracking apps send GNSS fixes only (1 Hz down to one fix a
minute, with some of: accuracy or DOP, satellites, speed, course, an ignition or motion flag).
This engine gives such a stream a motion model, a gate that tells glitches from relocations,
static detection with the 3-level low-pass of Forno et al. 2020, the last-known-position boot,
and forward (live) and RTS-smoothed (offline) tracks at the fix times or at any rate. It is
the default of ``iotnav run`` for a log without IMU samples.

Motion model (tangent plane of :class:`~iotnav.engines.tangent_plane.TangentPlane`, NED)
--------------------------------------------------------------------------------
Constant velocity with white acceleration noise per axis (Bar-Shalom, Li and Kirubarajan
2001, sec. 6.2.2)::

    x = [p, v] per axis,  F = [[1, dt], [0, 1]],  Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]

``q`` (m^2/s^3) is the manoeuvre noise of the platform (``[kf] platform``, table
:data:`PLATFORMS`). Groves, "Principles of GNSS, Inertial, and Multisensor Integrated
Navigation Systems", 2nd ed. 2013, sec. 9.4.2.2, gives for the acceleration PSD of a GNSS
navigation filter "around 1 m^2 s^-3 for a pedestrian or ship, 10 m^2 s^-3 for a car": those
are the ``pedestrian`` and ``car`` presets. No value is published for bicycles and
e-scooters; ``bike`` / ``scooter`` take 3 m^2/s^3, the geometric middle, since their
accelerations (urban cycling 0.2-1.5 m/s^2) lie between walking and driving. The vertical
axis takes ``vertical_psd_ratio`` (0.1) of it: land vehicles' vertical accelerations follow
the road grade and are an order smaller than the horizontal ones (an assumption, stated). The
model and a diagonal ``R`` keep the axes uncorrelated, so the filter is three 2-state filters
(:mod:`iotnav.engines.fixes_kernel`), exactly.

Measurements
------------
* Position: ``R`` from the receiver's accuracy, read once for every engine by
  :func:`iotnav.gnss_accuracy.position_sigmas` (``h_acc`` / ``v_acc``, else DOP x UERE).
* Velocity: ``vn, ve[, vd]`` when reported, else speed and course (above
  ``min_course_speed_mps``, where the course means something), sigma ``s_acc`` or
  ``vel_noise_mps``; gated at ``velocity_probability`` (a rejected velocity is only skipped).

Gate and recovery
-----------------
Each fix's horizontal NIS ``y^T S^-1 y`` (2 dof) is tested against the chi-square quantile
of ``[gate] probability``. A rejected fix is a ``fix_rejected`` event (reason ``nis``, its NIS)
and gives an output row with the prediction (source ``dr``). Rejected fixes that agree with
each other (each within ``sqrt(gate) x`` their combined sigma plus ``max_speed x dt`` of the
previous one) but not with the filter are a *relocation* candidate: after
``relocation_fixes`` of them spanning at least ``relocation_min_s`` the filter is
re-initialised at the latest (velocity from the first to the last candidate), event
``relocated`` with the jump. A glitch (one or a few fixes off and back) never gathers that
many. So that nothing is rejected forever, ``max_rejections`` consecutive rejections of any
kind re-initialise at the latest fix (event ``reinitialised``).

Rollback (do no harm)
---------------------
A multipath jump of 15-60 m that the gate lets through (its NIS within the gate, or accepted
after a rejection raised ``q``) teaches the filter a velocity that carries the track away once
the jump ends; the good fixes after it are then rejected (forward rms 21-23 m against the raw
fixes' 15-21 m on the simulated urban drive, positions only). So a *doubtful* accepted fix (NIS
above the ``soft_probability`` quantile, or accepted after fewer than ``relocation_fixes``
rejections) leaves behind a snapshot: the predicted state without it. While the snapshot is
less than ``rollback_s`` old, a fix the state rejects is tested against the snapshot predicted
to its time (plain ``q``): when the snapshot accepts it and explains it better (smaller
``NIS + ln det S``, the Gaussian log-likelihood of the two hypotheses), the state returns to
the snapshot and takes that fix, event ``fixes_retracted``. The forward rows already written
stay (live output); for RTS the retracted rows are rewritten as predictions of the snapshot
(:func:`~iotnav.engines.fixes_rts.retract_records`), so the smoother treats them as
rejected. Tuned on the simulated urban drive (seeds 1-3); measured on drive_0708, walk_0827
and the Husky (``benchmarks/bench_fixes.py``).

Static detection from GNSS alone, and the low-pass
---------------------------------------------------
*Entering.* At each accepted fix of a moving device it becomes *static* when there is evidence
and no veto:

* evidence: reported speed below ``speed_threshold_mps``, the device's motion flag 0 or
  ignition 0, or the spread test: the accepted fixes of the last ``window_s`` (at least
  ``min_fixes``, spanning ``window_s``; at most 256) have ``sum |r_i - mean|^2 / s_i^2`` below
  the ``spread_probability`` chi-square quantile of ``2 (n - 1)`` dof (a device that does not
  move; gross outliers, beyond the 1 - 1e-6 quantile from the window's median, left out), or
  the accelerometer (when the log has IMU samples) quiet: the standard deviation of ``|f_b|``
  between two fixes below ``acc_std_threshold_mps2`` (Forno et al.'s theta_A = 0.125 m/s^2 as
  the scale of motion-induced acceleration; a MEMS sensor at rest shows 0.01-0.03 m/s^2);
* veto: reported speed above that threshold (or above it on ``exit_speed_fixes`` consecutive
  fixes), motion flag 1, the spread test failing, or the accelerometer above
  ``acc_move_threshold_mps2`` (1 m/s^2: a walking gait's vertical acceleration swings several
  m/s^2). Between the two the accelerometer says nothing: an idling engine shakes the device
  (0.2-0.5 m/s^2) as much as driving does.

*Leaving* (the departure test, :func:`~iotnav.engines.fixes_departure._departed`). Parked, neither
the reported speed nor the spread of the fixes ends the static state: in an urban canyon a
parked receiver's speed reads 0.7 m/s (median) and up to 2-3 m/s, and its fixes wander 10-20 m
with multipath and jump 50-500 m, which ended the static period thousands of times a day
(2701 static starts in the simulated 8 parked hours, seed 1; the moving filter then followed the
errors out of a 15 m fence 41 times). The static state ends on the motion flag 1, the
accelerometer above ``acc_move_threshold_mps2``, or a confirmed departure: every fix, accepted or
not, is compared with the held position (the row output) using the fix's and the state's
covariance; *displaced* fixes (beyond the ``departure_probability`` chi-square quantile, bound
``b``) that follow each other are a run, which is a departure when

* its first fix is reachable from inside the bound in the time since the last fix that was not
  displaced (``b + v dt + a dt^2 / 2``, ``a = departure_acc_mps2``, ``v = sqrt(2 a b)`` the
  fastest a device starting from rest can be on leaving the bound, or the reported speed plus
  three sigmas when that is smaller): a jump far beyond the bound is multipath;
* it does not step off the fixes before it: each displaced fix lies within
  ``sqrt(2 g R (1 - exp(-dt / tau))) + v dt`` of the last fix that was no jump, ``dt`` s before
  (``g`` the departure gate, ``R`` the fix's variance per axis, ``tau`` = ``lowpass_corr_time_s``
  the errors' correlation time: a first-order Gauss-Markov error changes by at most that, at the
  gate's probability, while the device moves at most ``v dt``, ``v`` the reach bound's speed). A
  fix beyond it is a jump, and so is every fix that goes on from the latest jump fix within the
  same bound (the same outlier, moving with the receiver's error), until a fix returns to the
  fixes before the jump. Without it a lasting outlier (the canyon's 15-60 m ones last 4 s on
  average, the fleet days' 50-500 m ones 5 s) became reachable as the reach bound grew with the
  time since the last still fix, and three of its fixes moving away confirmed a departure: fence
  exits on the parked fleet days with seeds 0, 4, 5 and 6 (no parameter of its own; the test's
  seeds are in ``benchmarks/bench_tracker.py``'s results);
* a fix reporting a speed above ``exit_speed_mps`` (the platform's: 1.5 m/s for vehicles, 0.5
  for a pedestrian) counts as displaced without the bound (a car pulls away faster than its
  fixes leave a canyon's bound of 30-45 m);
* it has ``exit_speed_fixes`` fixes and moves away: the latest fix is farther from the held
  position than the first by ``speed_threshold_mps`` times the run's span (a jump's offset
  stays put, wander goes either way);
* or, whatever the above, it has lasted ``lowpass_corr_time_s``, the correlation time of the
  GNSS errors: an excursion longer than that is not multipath (the safety net of a departure
  hidden by a jump; no forced re-initialisation by ``max_rejections`` while parked, and a
  relocation while parked is left to this test).

At a departure the filter re-initialises at the fix (event ``departure`` with ``since_s``, the
run's span: the departure began at least that long before), velocity measured or the run's.
The run's velocity is at most the reported speed plus three sigmas (the reach bound's): when it
is faster the run ended on a jump fix (a canyon's claimed 10-15 m accuracy lets a 40 m jump pass
every gate). After every departure the next static period needs ``exit_speed_fixes`` fixes with
static evidence (counted since the departure, not necessarily consecutive), or the spread test,
not one slow fix: as many fixes park the device again as leave it, so the track is not parked
at a jump fix that confirmed the departure (the Husky urban-canyon row: 55-62 m off for 12 s
before). The rule holds after every departure, not only after one confirmed on a jump: only
after a jump the Husky urban-canyon do-no-harm row was worse than the raw fixes (forward rms
17.55 m against 16.64 m raw), after every departure it is better (16.43 m), for two more
fence exits on ``parked-canyon`` (4 forward / 2 smoothed against 2 / 1; measured by
``benchmarks/bench_fixes.py`` and ``benchmarks/bench_tracker.py``).
While static the low-pass output's reported uncertainty is at least its own variance
``R / (1 + N dt / (2 tau))`` (the repeated updates with one correlated average would shrink the
filter's covariance without bound). Tuned on the simulated fleet days ``parked-canyon`` and
``stop-and-go`` with seeds 0 and 2; measured on seed 1 (``benchmarks/bench_tracker.py``) and on
the real and other trajectories of ``benchmarks/bench_fixes.py``.

Reported uncertainty
    Every output reports a per-axis sigma of at least the fix's own. Forward (live, and the
    firmware): the last accepted fix's variance (``S_FLOOR_N`` / ``S_FLOOR_E``), set at each
    accepted fix or re-initialisation and grown by each prediction as ``P_pp`` is, so a rejected
    fix's row is no surer than the last fix moved on by the model. Smoothed and resampled: the
    fix's (``REC_SIG``; between fixes the smaller of the two neighbours'). A receiver's position
    error is time-correlated (multipath, atmosphere: a first-order Gauss-Markov error with a
    correlation time of minutes), not white; averaging consecutive fixes whose errors are
    correlated does not shrink the error as the white-noise posterior claims, and in the limit
    of a long correlation time the error of the average is that of one fix (Groves 2013,
    *Principles of GNSS, Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed.,
    sect. 3.4.3, time-correlated measurement noise). Positions are unchanged. Cover of the 95 %
    circle (``benchmarks/bench_fixes.py``, 1 s fixes on drive_0708): smoothed at 1 Hz 0.55 ->
    1.00 open-sky, 0.13 -> 0.97 urban canyon; forward rows 0.78 -> 0.99, 0.32 -> 0.97.

While static the filter holds (no process noise in the prediction, as the pipeline's
``static_hold``, also after rejected fixes; the gate still uses the moving model's spread) and the 3-level low-pass of :mod:`iotnav.techniques.lowpass3` (same rules, compiled
in its compiled form :func:`~iotnav.techniques.lowpass3.lowpass3_push`) takes the accepted fixes; the filter
gets a zero-velocity update (``zupt_noise_mps``) and, each time the low-pass output changes,
that output with ``R / (1 + N dt / (2 tau))`` (as the pipeline). Rows while static have
source ``lowpass``, zero velocity and the low-pass position (the position at the start of
the static period until a level is full). At driving speed the spread test (and the speed)
veto.

Boot (Forno et al. 2020, block 1; :mod:`iotnav.techniques.last_position`)
-------------------------------------------------------------------------
With a stored last position it is the NED origin and the output (source ``last_position``,
std ``stored_std_m``, growing at ``boot_walk_speed_mps`` once a speed or motion flag shows
movement) for every epoch before the first acceptable fix (PDOP <= ``max_pdop``); the first
fix far from it raises ``moved_while_off``. Without one the first fix must also pass the
settling gate. The engine saves the latest position to its store every ``save_interval_s``.

Bad input (``summary["skipped"]``, first of each reason an ``input_skipped`` event)
-----------------------------------------------------------------------------------
``gnss_nonfinite`` (the :class:`~iotnav.engines.base.InputGuard` rule), ``gnss_duplicate``
(same time and coordinates as the previous epoch), ``gnss_time_repeat`` (same time, other
coordinates), ``gnss_time_backwards``, ``gnss_future`` / ``gnss_past`` (``utc - t`` off the
log's reference offset by more than ``clock_tolerance_s``; ``relocation_fixes`` consecutive
epochs that agree with each other become the new reference, event ``clock_reset``),
``gnss_invalid`` (receiver flag), ``gnss_zero_position`` ((0, 0)), ``gnss_pdop``,
``gnss_pdop_unknown``, ``gnss_num_sv``, ``gnss_settling``. Skipped epochs give no row.

Outputs
-------
One row per processed epoch (accepted, rejected by the gate, or a boot row), columns
:data:`~iotnav.engines.base.OUTPUT_COLUMNS` (attitude NaN: no IMU attitude here).
:meth:`FixesEngine.smoothed_output` is the RTS-smoothed track at the same times and
:meth:`FixesEngine.resample` the forward or smoothed track at any rate, the state between
fixes predicted (forward) or smoothed with one RTS step from the next fix, so ``std_north`` /
``std_east`` grow between sparse fixes. Both need ``[kf] smoothing = true`` (``iotnav run
--smooth`` / ``--rate``), which keeps 280 bytes of records per row.

Implementation: the per-fix step is the compiled :func:`~iotnav.engines.fixes_kernel.
fixes_kernel` over a block of epochs; ``step(GnssSample)`` runs it on a one-row block and
:meth:`FixesEngine.run_log` (used by :func:`~iotnav.engines.base.run_batch`) on the whole
log, so streaming and batch give the same rows, bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import numba
import numpy as np
import numpy.typing as npt
import pandas as pd
from scipy.special import ndtri

from iotnav import kalman
from iotnav.engines import fixes_kernel as fk
from iotnav.engines.base import (
    _GNSS_FIELDS,
    C_STD_NORTH,
    GnssSample,
    ImuSample,
    InputGuard,
    MagSample,
    Output,
    OutputBlock,
    Sample,
    TangentPlane,
    _SampleSource,
    iter_samples,
)
from iotnav.engines.fixes_acc import acc_add, acc_between_fixes
from iotnav.engines.fixes_checkpoint import complete_state
from iotnav.engines.fixes_config import (
    PLATFORMS,
    FixesConfig,
    FixesGateConfig,
    FixesInputConfig,
    FixesKFConfig,
    FixesStaticConfig,
    Platform,
)
from iotnav.engines.fixes_offline import FixesOffline
from iotnav.gnss_accuracy import position_sigmas
from iotnav.io.log import Log
from iotnav.techniques.last_position import (
    LastPositionLogic,
    LastPositionStore,
    StoredPosition,
)

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "PLATFORMS",
    "FixesConfig",
    "FixesEngine",
    "FixesGateConfig",
    "FixesInputConfig",
    "FixesKFConfig",
    "FixesStaticConfig",
    "Platform",
]


@functools.lru_cache(maxsize=4096)
def _sigmas(
    h_acc: float, v_acc: float, hdop: float, pdop: float, uere: float, dflt: float
) -> tuple[float, float]:
    """Per-axis horizontal and vertical sigma (m): :func:`iotnav.gnss_accuracy.position_sigmas`, cached.

    Callers pass -1 for a missing figure (NaN would defeat the cache); ``position_sigmas``
    reads any value that is not a positive number as "not reported".
    """
    s = position_sigmas(h_acc, v_acc, hdop, pdop, uere, dflt)
    return s.north_east_m, s.down_m


def _known(x: float) -> float:
    return x if x == x else -1.0


_EVENT_NAMES = (
    (fk.EV_INIT, "filter_initialised"),
    (fk.EV_REJECT, "fix_rejected"),
    (fk.EV_RELOCATE, "relocated"),
    (fk.EV_FORCED, "reinitialised"),
    (fk.EV_STATIC_START, "static_start"),
    (fk.EV_STATIC_END, "static_end"),
    (fk.EV_CLOCK, "clock_reset"),
    (fk.EV_BOOT_MOVE, "boot_movement_before_fix"),
    (fk.EV_ROLLBACK, "fixes_retracted"),
    (fk.EV_DEPART, "departure"),
)


class FixesEngine(FixesOffline):
    """GNSS-only engine (module docstring).

    Parameters
    ----------
    config : FixesConfig, optional
        Tunables.
    stored : StoredPosition, optional
        Last known position at boot (overrides ``store.load()``).
    store : LastPositionStore, optional
        Where the latest position is saved every ``save_interval_s``.
    """

    def __init__(
        self,
        config: FixesConfig | None = None,
        stored: StoredPosition | None = None,
        store: LastPositionStore | None = None,
    ) -> None:
        self.config = c = config or FixesConfig()
        plat = c.platform()
        if stored is None and store is not None:
            stored = store.load()
        self.store = store
        self.events: list[dict[str, Any]] = []
        self.guard = InputGuard(self.events)
        self.boot = LastPositionLogic(c.last_position, stored)
        self.frame: TangentPlane | None = None
        self.q_h = plat.acc_psd_m2_s3
        self.q_v = plat.acc_psd_m2_s3 * c.kf.vertical_psd_ratio
        lp = c.lowpass3
        g, s = c.gate, c.static
        self._prm = np.zeros(fk.PRM_SIZE)
        p = self._prm
        p[fk.P_Q_H], p[fk.P_Q_V] = self.q_h, self.q_v
        p[fk.P_GATE] = kalman.gate_threshold(2, g.probability)
        p[fk.P_VEL_GATE] = kalman.gate_threshold(2, g.velocity_probability)
        p[fk.P_RELOC_N], p[fk.P_RELOC_MIN_S], p[fk.P_MAX_REJ] = (
            g.relocation_fixes,
            g.relocation_min_s,
            g.max_rejections,
        )
        p[fk.P_MAX_SPEED] = plat.max_speed_mps
        p[fk.P_REJECT_QF] = g.reject_q_factor
        p[fk.P_SOFT_GATE] = kalman.gate_threshold(2, g.soft_probability)
        p[fk.P_ROLLBACK_S] = g.rollback_s
        p[fk.P_MAX_PDOP] = c.last_position.max_pdop
        p[fk.P_MIN_SV] = c.last_position.min_num_sv
        p[fk.P_ACCEPT_UNKNOWN_PDOP] = float(c.last_position.accept_unknown_pdop)
        p[fk.P_SPEED_THR] = s.speed_threshold_mps
        p[fk.P_DEP_ACC] = s.departure_acc_mps2
        p[fk.P_EXIT_SPEED] = max(s.exit_speed_mps or plat.exit_speed_mps, s.speed_threshold_mps)
        p[fk.P_DEP_GATE] = kalman.gate_threshold(2, s.departure_probability)
        p[fk.P_EXIT_RUN] = max(1, s.exit_speed_fixes)
        p[fk.P_WINDOW_S], p[fk.P_MIN_FIXES] = s.window_s, max(2, s.min_fixes)
        p[fk.P_SPREAD_Z] = float(
            ndtri(s.spread_probability)
        )  # = scipy.stats.norm.ppf, without importing scipy.stats
        p[fk.P_ACC_THR], p[fk.P_ZUPT], p[fk.P_LP_TAU] = (
            s.acc_std_threshold_mps2,
            s.zupt_noise_mps,
            s.lowpass_corr_time_s,
        )
        p[fk.P_USE_LOWPASS] = float(s.use_lowpass)
        p[fk.P_ACC_MOVE] = s.acc_move_threshold_mps2
        p[fk.P_MIN_COURSE_SPEED], p[fk.P_VEL_SIGMA] = c.kf.min_course_speed_mps, c.kf.vel_noise_mps
        p[fk.P_USE_VEL] = float(c.kf.use_velocity)
        p[fk.P_INIT_VEL_STD] = plat.init_vel_std_mps
        p[fk.P_STORED_STD], p[fk.P_BOOT_WALK] = (
            c.last_position.stored_std_m,
            c.last_position.boot_walk_speed_mps,
        )
        p[fk.P_CLOCK_TOL] = c.input.clock_tolerance_s
        p[fk.P_RECORD] = float(c.kf.smoothing)
        p[fk.P_LP_N1], p[fk.P_LP_N2], p[fk.P_LP_N3] = lp.n1, lp.n2, lp.n3
        self._st = np.zeros(fk.ST_SIZE)
        st = self._st
        st[fk.S_T_LAST] = -math.inf
        st[fk.S_LAT_LAST] = st[fk.S_LON_LAST] = st[fk.S_OFF_REF] = st[fk.S_T_MOVE] = math.nan
        st[fk.S_T_FIX] = -math.inf
        self._frame = np.zeros(5)
        self._kf = np.zeros(fk.KF_SIZE)
        self._cand = np.zeros((fk.CAND_MAX, 5))
        self._ring = np.zeros((fk.RING_MAX, 4))
        self._lp = (np.zeros((lp.n1, 3)), np.zeros((lp.n2, 3)), np.zeros((lp.n3, 3)))
        self._acc = np.zeros(3)
        self._records: list[FloatArray] = []
        self._record = c.kf.smoothing
        self._uere, self._dflt_hdop = c.kf.uere_m, c.kf.default_hdop
        # one-row buffers of step()
        self._row = np.zeros((1, fk.N_INPUT))
        self._one = OutputBlock(1)
        self._codes1 = np.zeros(1, np.int8)
        self._ev1 = np.zeros(1, np.int32)
        self._evv1 = np.zeros(1)
        self._rec1 = np.zeros((1, fk.REC_SIZE))
        self._bind_step()
        if stored is not None:
            self._set_frame(
                stored.lat_deg, stored.lon_deg, stored.height_m if math.isfinite(stored.height_m) else 0.0
            )
            self.events.append({"type": "boot", "t": math.nan, "decision": "stored_position", **vars(stored)})

    # ------------------------------------------------------------------ protocol
    @property
    def mount_yaw_rad(self) -> float:
        """No IMU attitude here: NaN."""
        return math.nan

    @property
    def initialised(self) -> bool:
        """True once the filter holds a state."""
        return bool(self._st[fk.S_INIT] != 0.0)

    def summary(self) -> dict[str, Any]:
        """Configuration and final state."""
        counts: dict[str, int] = {}
        for e in self.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        plat = self.config.platform()
        return {
            "engine": "fixes",
            "skipped": dict(self.guard.skipped),
            "config": self.config.to_dict(),
            "platform": {"name": self.config.kf.platform, **dataclasses.asdict(plat)},
            "acc_psd_vertical_m2_s3": self.q_v,
            "mount_yaw_rad": math.nan,
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
            "fixes_used": int(self._st[fk.S_N_USED]),
            "event_counts": counts,
        }

    def step(self, sample: Sample) -> Output | None:
        """Process one sample: an :class:`Output` for a processed GNSS epoch, None otherwise."""
        if isinstance(sample, GnssSample):
            if not math.isfinite(sample.t) or (
                sample.valid and not math.isfinite(sample.lat_deg + sample.lon_deg)
            ):
                self.guard.skip("gnss_nonfinite", sample.t)
                return None
            self._fill_row(self._row0, sample)
            acc = self._acc
            acc[0] = acc[1] = acc[2] = 0.0
            return self._step_row()
        s = self.guard.admit(sample)
        if isinstance(s, ImuSample):
            a = s.acc_b
            acc_add(self._acc, float(a[0]), float(a[1]), float(a[2]))
        elif isinstance(s, MagSample):
            pass  # no use for a magnetometer without attitude
        return None

    def _bind_step(self) -> None:
        """The views and the argument tuple of :meth:`_step_row` (every array reused: no allocation a step)."""
        self._row0 = self._row[0]
        self._col0 = self._one.floats[:, 0]
        lp1, lp2, lp3 = self._lp
        o = self._one
        self._args1 = (
            self._row, 0, 1, 0, self._st, self._prm, self._frame, self._kf, self._cand, self._ring,
            lp1, lp2, lp3, o.floats, o.static, o.source, self._rec1, self._codes1, self._ev1, self._evv1,
        )  # fmt: skip
        self._kernel1: Any = None  # the compiled entry point for those argument types

    def __getstate__(self) -> dict[str, Any]:
        # copies and pickles (the service's template engine, its checkpoints) rebuild the views and
        # the argument tuple: a view would come back as a detached copy, the entry point not at all
        d = dict(self.__dict__)
        for k in ("_row0", "_col0", "_args1", "_kernel1"):
            d.pop(k, None)
        return d

    def __setstate__(self, d: dict[str, Any]) -> None:
        """Unpickling; a state of an earlier layout is completed or refused (:func:`complete_state`)."""
        self.__dict__.update(complete_state(d))
        self._bind_step()

    def _step_row(self) -> Output | None:
        """:meth:`_process` on the one-row buffer of :meth:`step`, with less Python per epoch.

        The same kernel on the same arrays (so the same rows, bit for bit): the arguments are
        built once, the compiled entry point for their types is looked up once (the
        dispatcher's type resolution costs about 0.4 us a call), and the ``Output`` is made from
        a column view.
        """
        kernel = self._kernel1
        if kernel is None:
            kernel = fk.fixes_kernel
        _, r, flag = kernel(*self._args1)
        if flag == fk.F_NEED_BOOT:
            self._boot_decision(self._row0)
            _, r, flag = kernel(*self._args1)
        if self._kernel1 is None:
            sig = tuple(numba.typeof(a) for a in self._args1)
            ovl = fk.fixes_kernel.overloads.get(sig)
            self._kernel1 = getattr(ovl, "entry_point", None) or fk.fixes_kernel
        code, bits = int(self._codes1[0]), int(self._ev1[0])
        if code:
            self.guard.skip(fk.REASONS[code], float(self._row0[fk.I_T]))
        if bits:
            self._events(self._row, self._ev1, self._evv1, _ROW0)
        if not r:
            return None
        if self._record:
            self._records.append(self._rec1.copy())
        if self.store is not None and self.initialised:
            self._save(float(self._col0[0]))
        o = self._one
        f = self._col0.tolist()
        f.insert(C_STD_NORTH, bool(o.static[0]))
        f.append(o.names[o.source[0]])
        return Output._make(f)

    def _save(self, t: float) -> None:
        """Save the latest position to the store when due (``save_interval_s``)."""
        if self.boot.due(t) and self.frame is not None:
            lat, lon, h = self.frame.from_ned(self._kf[[fk.AX_N, fk.AX_E, fk.AX_D]])
            self.store.save(StoredPosition(lat, lon, h, t))  # type: ignore[union-attr]

    # ------------------------------------------------------------------ batch
    def run_log(self, log: Log, progress: Any = None) -> OutputBlock:
        """Every sample of ``log`` through the kernel in one call (:func:`~iotnav.engines.base.run_batch`).

        The same rows as ``step()`` over :func:`~iotnav.engines.base.iter_samples` (IMU samples
        count only for the accelerometer test). Logs whose IMU times go backwards take the
        ``step()`` loop, so the guard counts them as streaming would.
        """
        imu_t = log.imu["t"].to_numpy(float) if len(log.imu) else np.empty(0)
        unordered = imu_t.size > 0 and (
            not bool(np.all(np.diff(imu_t) >= 0.0)) or imu_t[0] < self.guard.t_imu
        )
        if unordered:
            out = OutputBlock(len(log.gnss))
            for s in iter_samples(log):
                o = self.step(s)
                if o is not None:
                    out.add(o)
            if progress is not None:
                progress(len(log.gnss) + len(log.imu) + len(log.mag))
            return out
        src = _SampleSource(log, self.guard)
        cols = dict(zip(_FIELDS, src.gcols, strict=True)) if src.gcols else {}
        n = len(cols["t"]) if cols else 0
        inp = np.zeros((n, fk.N_INPUT))
        if n:
            self._fill_columns(inp, cols)
        if src.imu_t.size:
            acc = np.zeros((n, 3))
            ax, ay, az = src.acc
            acc_between_fixes(src.imu_t, ax, ay, az, inp[:, fk.I_T].copy(), self._acc, acc)
            inp[:, fk.I_ACC_N : fk.I_ACC_S2 + 1] = acc
            self.guard.t_imu = max(self.guard.t_imu, float(src.imu_t[-1]))
        elif n:
            inp[0, fk.I_ACC_N : fk.I_ACC_S2 + 1] = self._acc
            self._acc[:] = 0.0
        out = OutputBlock(n)
        rec = np.zeros((n if self.config.kf.smoothing else 1, fk.REC_SIZE))
        out.n = self._process(inp, out, np.zeros(n, np.int8), np.zeros(n, np.int32), np.zeros(n), rec)
        if progress is not None:
            progress(n + len(log.imu) + len(log.mag))
        return out

    # ------------------------------------------------------------------ core
    def _set_frame(self, lat: float, lon: float, h: float) -> None:
        self.frame = TangentPlane(lat, lon, h)
        self._frame[:] = self.frame.constants()
        self._st[fk.S_HAVE_FRAME] = 1.0

    def _fill_row(self, row: FloatArray, s: GnssSample) -> None:
        """One input row from a sample (the layout ``I_*``; the accelerometer sums from :attr:`_acc`)."""
        h, v, hd, pd_ = s.h_acc_m, s.v_acc_m, s.hdop, s.pdop
        # -1 for a missing figure (NaN would defeat the cache), as _known
        sh, sv = _sigmas(
            h if h == h else -1.0,
            v if v == v else -1.0,
            hd if hd == hd else -1.0,
            pd_ if pd_ == pd_ else -1.0,
            self._uere,
            self._dflt_hdop,
        )
        a = self._acc
        # one assignment of the whole row, in I_* order (element by element costs 3x more)
        row[:] = (
            s.t,
            s.utc,
            s.lat_deg,
            s.lon_deg,
            s.height_m,
            s.valid,
            s.pdop,
            s.num_sv,
            sh,
            sv,
            s.speed_mps,
            s.course_rad,
            s.course_valid,
            s.vn,
            s.ve,
            s.vd,
            s.s_acc_mps,
            s.motion,
            s.ignition,
            a[0],
            a[1],
            a[2],
        )

    def _fill_columns(self, inp: FloatArray, cols: dict[str, np.ndarray]) -> None:
        """Input rows from a log's columns (what :meth:`_fill_row` does per sample)."""
        c = self.config.kf
        for name, col in _DIRECT:
            inp[:, col] = cols[name]
        figs = pd.DataFrame(
            {k: cols[k].astype(float) for k in ("h_acc_m", "v_acc_m", "hdop", "pdop")}
        ).fillna(-1.0)
        # one call of the accuracy reading per distinct set of figures (hash grouping)
        inv = figs.groupby(list(figs.columns), sort=False).ngroup().to_numpy()
        first = np.full(int(inv.max()) + 1 if inv.size else 0, -1)
        first[inv[::-1]] = np.arange(inv.size)[::-1]
        uniq = figs.to_numpy()[first]
        sig = np.array([_sigmas(*map(float, u), c.uere_m, c.default_hdop) for u in uniq]).reshape(-1, 2)
        inp[:, fk.I_SIG_H] = sig[inv, 0]
        inp[:, fk.I_SIG_V] = sig[inv, 1]

    def _process(
        self,
        inp: FloatArray,
        out: OutputBlock,
        codes: npt.NDArray[np.int8],
        ev: npt.NDArray[np.int32],
        evv: FloatArray,
        rec: FloatArray,
    ) -> int:
        """Run the kernel over all rows of ``inp``; the boot decisions in between. Returns the rows written."""
        m = inp.shape[0]
        lp1, lp2, lp3 = self._lp
        k, r = 0, 0
        while k < m:
            k, r, flag = fk.fixes_kernel(
                inp,
                k,
                m,
                r,
                self._st,
                self._prm,
                self._frame,
                self._kf,
                self._cand,
                self._ring,
                lp1,
                lp2,
                lp3,
                out.floats,
                out.static,
                out.source,
                rec,
                codes,
                ev,
                evv,
            )
            if flag == fk.F_NEED_BOOT:
                self._boot_decision(inp[k])
        if m == 1:
            if codes[0]:
                self.guard.skip(fk.REASONS[codes[0]], float(inp[0, fk.I_T]))
            if ev[0]:
                self._events(inp, ev, evv, np.array([0]))
        else:
            counts = np.bincount(codes.astype(np.int64), minlength=len(fk.REASONS))
            for c in np.flatnonzero(counts[1:]) + 1:
                first = int(np.argmax(codes == c))
                self.guard.skip(fk.REASONS[c], float(inp[first, fk.I_T]), n=int(counts[c]))
            self._events(inp, ev, evv, np.flatnonzero(ev))
        if self.config.kf.smoothing and r:
            self._records.append(rec[:r].copy())
        if r and self.store is not None and self.initialised:
            self._save(float(out.floats[0, r - 1]))
        return r

    def _boot_decision(self, row: FloatArray) -> None:
        """Block 1 on an acceptable epoch before the first fix: settling gate, origin, moved-while-off."""
        t, lat, lon = float(row[fk.I_T]), float(row[fk.I_LAT]), float(row[fk.I_LON])
        reason = self.boot.check_fix(True, lat, lon, float(row[fk.I_PDOP]), int(row[fk.I_NSV]), t)
        if reason is not None:
            self._st[fk.S_DECIDED] = 2.0
            return
        ev = self.boot.first_fix(t, lat, lon)
        if ev is not None:
            self.events.append(ev)
        if self.frame is None:
            h = float(row[fk.I_H])
            self._set_frame(lat, lon, h if math.isfinite(h) else 0.0)
        self.events.append(
            {"type": "first_fix", "t": t, "pdop": float(row[fk.I_PDOP]), "num_sv": int(row[fk.I_NSV])}
        )
        self._st[fk.S_DECIDED] = 1.0

    def _events(self, inp: FloatArray, ev: npt.NDArray[np.int32], evv: FloatArray, idx: np.ndarray) -> None:
        for k in idx.tolist():
            bits = int(ev[k])
            t = float(inp[k, fk.I_T])
            for bit, name in _EVENT_NAMES:
                if bits & bit:
                    e: dict[str, Any] = {"type": name, "t": t}
                    if bit == fk.EV_REJECT:
                        e.update(
                            reason="nis",
                            nis=float(evv[k]) if not bits & (fk.EV_RELOCATE | fk.EV_FORCED) else None,
                        )
                    elif bit in (fk.EV_RELOCATE, fk.EV_FORCED):
                        e["jump_m"] = float(evv[k])
                    elif bit == fk.EV_ROLLBACK:
                        e["nis_at_snapshot"] = float(evv[k])
                    elif bit == fk.EV_DEPART:
                        e["since_s"] = float(evv[k])
                    elif bit == fk.EV_CLOCK:
                        e["offset_change_s"] = float(evv[k])
                    self.events.append(e)

    # ------------------------------------------------------------------ offline


_ROW0 = np.array([0])
#: GNSS sample fields in :class:`~iotnav.engines.base._SampleSource` column order.
_FIELDS = _GNSS_FIELDS
#: Sample fields copied into input columns unchanged.
_DIRECT = (
    ("t", fk.I_T),
    ("utc", fk.I_UTC),
    ("lat_deg", fk.I_LAT),
    ("lon_deg", fk.I_LON),
    ("height_m", fk.I_H),
    ("valid", fk.I_VALID),
    ("pdop", fk.I_PDOP),
    ("num_sv", fk.I_NSV),
    ("speed_mps", fk.I_SPEED),
    ("course_rad", fk.I_COURSE),
    ("course_valid", fk.I_COURSE_VALID),
    ("vn", fk.I_VN),
    ("ve", fk.I_VE),
    ("vd", fk.I_VD),
    ("s_acc_mps", fk.I_SACC),
    ("motion", fk.I_MOTION),
    ("ignition", fk.I_IGNITION),
)
