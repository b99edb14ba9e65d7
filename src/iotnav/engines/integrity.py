"""Do no harm (issue 16): one integrity guard around every position engine.

:class:`IntegrityEngine` wraps any engine (``make_engine`` applies it by default) and has the
same ``step()``; batch (:func:`iotnav.engines.base.run_batch`), streaming and later the live
service and the firmware get it the same way. It watches the engine against the fixes and
against the vehicle's own recent motion, and never reports a solution that either disagrees
with them beyond chance. The guard itself is a small pure state machine
(:class:`IntegrityGuard`), no I/O.

Consistency watch (fixes present)
    At each valid fix the engine's latest output (moved to the fix time with its own velocity)
    is compared with the fix: innovation ``d = p_fix - p_eng`` (north, east), covariance
    ``S = diag(std_eng^2 + sigma_fix^2)`` with ``sigma_fix = max(h_acc / sqrt(2),
    min_sigma_m)`` per axis, ``NIS = d^T S^-1 d`` (chi-square, 2 degrees of freedom, for a
    consistent engine). The engine is *re-initialised* -- replaced by a fresh one from the same
    builder, which starts over from the next samples -- when

    * the sum of the last ``nis_window`` NIS exceeds the chi-square bound with ``2 nis_window``
      degrees of freedom at ``nis_probability`` (windowed NIS: the two disagree beyond chance),
      or
    * ``max_consecutive`` fixes in a row each exceed the 2-dof bound at ``fix_probability``
      (an engine that rejects fixes -- or ignores them -- drifts away from them and never
      comes back), or
    * its output is not finite.

    Each re-initialisation is an event ``reinitialised`` (``reason``, the figures, the fix
    count) in ``events``; at most one per ``reinit_holdoff_s``, and not before the fresh engine
    has a position and ``nis_window`` fixes of its own. So fixes are never rejected forever.

Outage guard (no fix for ``outage_after_s``)
    ``tau`` is the time since the last fix ``(t_f, p_f, v_f)``; the *dr-velocity* solution is
    ``p_dr = p_f + v_f tau``, the last fix moved on at its own reported velocity. What the
    vehicle did before the outage is summarised from the fixes of the last
    ``dynamics_window_s``: the largest rate of change of speed ``a_s``, of the horizontal
    velocity vector ``a_h`` and of the course ``w`` seen between fixes, each times
    ``dynamics_margin`` and at least its floor. The engine's output is kept while

    * its speed is within ``|s_f| +- (a_s tau + 3 sigma_s)``,
    * its course is within ``w tau + 3 sigma_course`` of the fix's (when both move faster than
      ``min_course_speed_mps``),
    * its position is within ``0.5 a_h tau^2 + 3 sigma_dr`` of ``p_dr``, and within
      ``dynamics_margin s_max tau + 3 sigma_f`` of the last fix, ``s_max`` the highest speed
      of the fixes of the last ``dynamics_window_s`` (the vehicle cannot have gone farther
      than its recent top speed, with the margin, allows);

    otherwise the output switches to ``p_dr`` for the rest of the outage (``source``
    ``dr_velocity``, an event ``integrity_fallback`` with the check that failed), with the
    honest 1-sigma per axis ``sqrt(sigma_f^2 + tau^2 sigma_v^2 + (a_rms tau^2 / 2)^2)``:
    the fix's error, its velocity error carried forward, and the unknown acceleration (the RMS
    of what the vehicle did before the outage, at least ``accel_floor_mps2``). The fixes'
    ``s_acc_mps`` gives ``sigma_v`` (``default_speed_acc_mps`` when absent).

    Before the engine has a position (a fresh engine after a re-initialisation, or a cold
    start), and when its output is not finite, the output is the dr-velocity solution too.

Defaults and their sources
    * ``accel_floor_mps2`` 0.5 m/s^2: median horizontal acceleration of the real drive
      (drive_0708 RTK: 0.58 m/s^2) and walk (walk_0827: 0.47 m/s^2) over 1 s; the Husky's is
      0.26.
    * ``yaw_rate_floor_rad_s`` 0.1 rad/s and ``dynamics_margin`` 1.5: the 99th percentiles
      of |d speed / dt| and of the course rate are 1.4 times their 95th on the drive (2.2 vs
      1.5 m/s^2; 0.52 vs 0.45 rad/s above 2 m/s), on the walk 1.6 / 1.3 and on the Husky 1.4 /
      2.0 (``benchmarks/bench_cases.py`` inputs; measured once on the RTK truths and fixes).
    * chi-square probabilities 0.999 (windowed) and 0.9999 (per fix): a consistent engine
      re-initialises about once in 1000 windows, once in 10^4 fixes for the run of 5.
    * ``min_sigma_m`` 0.3 m: below the scatter of a standing tracker's fixes (Husky at rest
      0.30 m N), so that a centimetre ``h_acc`` (RTK) does not make metre-level engines
      "inconsistent".
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.stats import chi2

from iotnav.engines.base import Engine, GnssSample, ImuSample, Output, Sample, TangentPlane, output_at

__all__ = ["DR_VELOCITY_SOURCE", "IntegrityConfig", "IntegrityEngine", "IntegrityGuard"]

#: ``source`` of the rows where the guard reports the last fix moved on at its velocity.
DR_VELOCITY_SOURCE = "dr_velocity"


@dataclass(frozen=True)
class IntegrityConfig:
    """Tunables of the integrity guard (SI; sources in the module docstring).

    Attributes
    ----------
    nis_window : int
        Fixes in the windowed NIS.
    nis_probability : float
        Chi-square probability of the windowed bound (``2 nis_window`` dof).
    fix_probability : float
        Chi-square probability of the per-fix bound (2 dof) for the consecutive count.
    max_consecutive : int
        Fixes in a row beyond the per-fix bound that re-initialise the engine.
    min_sigma_m : float
        Floor of the fix's per-axis 1-sigma in the NIS, m.
    default_h_acc_m : float
        Fix 2D 1-sigma when the fix gives none, m (UERE 2 m x HDOP 1.5 / sqrt(2) x sqrt(2)).
    default_speed_acc_mps : float
        Fix speed 1-sigma when the fix gives none, m/s.
    reinit_holdoff_s : float
        Least time between two re-initialisations, s.
    outage_after_s : float
        No fix for this long is an outage, s.
    dynamics_window_s : float
        Fixes of this last span describe what the vehicle did before an outage, s.
    dynamics_margin : float
        Factor on the largest rates seen in that span.
    accel_floor_mps2 : float
        Least acceleration bound, m/s^2.
    yaw_rate_floor_rad_s : float
        Least course-rate bound, rad/s.
    min_course_speed_mps : float
        Course checks only above this speed, m/s.
    dynamics_min_dt_s : float
        Rates of the dynamics bounds are taken between fixes at least this far apart, s (rates
        of fixes a fraction of a second apart measure the fixes' noise).
    """

    nis_window: int = 10
    nis_probability: float = 0.999
    fix_probability: float = 0.9999
    max_consecutive: int = 5
    min_sigma_m: float = 0.3
    default_h_acc_m: float = 3.0
    default_speed_acc_mps: float = 0.3
    reinit_holdoff_s: float = 20.0
    outage_after_s: float = 2.5
    dynamics_window_s: float = 60.0
    dynamics_margin: float = 1.5
    accel_floor_mps2: float = 0.5
    yaw_rate_floor_rad_s: float = 0.1
    min_course_speed_mps: float = 1.0
    dynamics_min_dt_s: float = 1.0


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class _Fix:
    """The guard's view of one fix: time, NED position, velocity and their 1-sigma."""

    __slots__ = ("p", "sigma", "sigma_v", "t", "v")

    def __init__(self, t: float, p: np.ndarray, v: np.ndarray, sigma: float, sigma_v: float) -> None:
        self.t, self.p, self.v, self.sigma, self.sigma_v = t, p, v, sigma, sigma_v


def fix_velocity(s: GnssSample) -> np.ndarray:
    """North and East velocity a fix reports (m/s): ``vn``/``ve``, else speed and course, else 0."""
    if math.isfinite(s.vn) and math.isfinite(s.ve):
        return np.array([s.vn, s.ve])
    if s.course_valid and math.isfinite(s.speed_mps) and math.isfinite(s.course_rad):
        return np.array([s.speed_mps * math.cos(s.course_rad), s.speed_mps * math.sin(s.course_rad)])
    return np.zeros(2)


class IntegrityGuard:
    """The guard's state machine (pure: samples and engine outputs in, decisions out).

    Parameters
    ----------
    config : IntegrityConfig, optional
        Tunables.
    """

    def __init__(self, config: IntegrityConfig | None = None) -> None:
        c = self.config = config or IntegrityConfig()
        self.window_bound = float(chi2.ppf(c.nis_probability, 2 * c.nis_window))
        self.fix_bound = float(chi2.ppf(c.fix_probability, 2))
        self.frame: TangentPlane | None = None
        self.fix: _Fix | None = None
        self.history: deque[_Fix] = deque()
        self.nis: deque[float] = deque(maxlen=c.nis_window)
        self.consecutive = 0
        self.fixes_since_reinit = 0
        self.t_reinit = -math.inf
        self.last_out: Output | None = None
        self.fallback_reason: str | None = None  # set while falling back in this outage
        self.bounds: tuple[float, float, float, float] = (c.accel_floor_mps2,) * 2 + (
            c.yaw_rate_floor_rad_s,
            c.accel_floor_mps2,
        )
        self.speed_max = 0.0
        self.counts = {"fixes_checked": 0, "reinitialised": 0, "fallback_rows": 0, "engine_rows": 0}

    # ----------------------------------------------------------------- fixes
    def on_fix(self, s: GnssSample) -> dict[str, Any] | None:
        """Take a valid fix; a re-initialisation request (event dict) when the engine disagrees."""
        c = self.config
        if self.fix is not None and s.t < self.fix.t:
            return None  # out of order: the engine's own input guard counts and drops it
        if self.frame is None:
            self.frame = TangentPlane(s.lat_deg, s.lon_deg, s.height_m if math.isfinite(s.height_m) else 0.0)
        h = s.height_m if math.isfinite(s.height_m) else self.frame.h0_m
        p = self.frame.to_ned(s.lat_deg, s.lon_deg, h)
        h_acc = s.h_acc_m if math.isfinite(s.h_acc_m) and s.h_acc_m > 0 else c.default_h_acc_m
        s_acc = s.s_acc_mps if math.isfinite(s.s_acc_mps) and s.s_acc_mps > 0 else c.default_speed_acc_mps
        fix = _Fix(s.t, p, fix_velocity(s), max(h_acc / math.sqrt(2.0), c.min_sigma_m), s_acc)
        request = self._check(fix)
        self.fix = fix
        self.fallback_reason = None
        self.history.append(fix)
        while self.history and self.history[0].t < s.t - c.dynamics_window_s:
            self.history.popleft()
        self.bounds = self._dynamics()
        self.speed_max = max(math.hypot(*h.v) for h in self.history)
        return request

    def _check(self, fix: _Fix) -> dict[str, Any] | None:
        c = self.config
        o = self.last_out
        if o is None or o.source == "none" or not math.isfinite(o.lat + o.lon) or self.frame is None:
            return None
        if not math.isfinite(o.std_north + o.std_east):
            return None
        p_e = self.frame.to_ned(o.lat, o.lon, o.height if math.isfinite(o.height) else self.frame.h0_m)
        dt = fix.t - o.t
        if math.isfinite(o.vn + o.ve) and abs(dt) < 1.0:
            p_e = p_e + np.array([o.vn * dt, o.ve * dt, 0.0])
        d = fix.p[:2] - p_e[:2]
        s_n = o.std_north**2 + fix.sigma**2
        s_e = o.std_east**2 + fix.sigma**2
        nis = float(d[0] ** 2 / s_n + d[1] ** 2 / s_e)
        self.counts["fixes_checked"] += 1
        self.fixes_since_reinit += 1
        self.nis.append(nis)
        self.consecutive = self.consecutive + 1 if nis > self.fix_bound else 0
        ready = self.fixes_since_reinit >= c.nis_window and fix.t - self.t_reinit >= c.reinit_holdoff_s
        if not ready:
            return None
        win = float(sum(self.nis))
        reason = None
        if len(self.nis) == c.nis_window and win > self.window_bound:
            reason = "windowed_nis"
        elif self.consecutive >= c.max_consecutive:
            reason = "consecutive_rejections"
        if reason is None:
            return None
        return {
            "type": "reinitialised",
            "t": float(fix.t),
            "reason": reason,
            "nis_window_sum": win,
            "nis_window_bound": self.window_bound,
            "nis_window_fixes": len(self.nis),
            "consecutive_beyond_bound": self.consecutive,
            "fix_bound": self.fix_bound,
            "distance_m": float(math.hypot(d[0], d[1])),
        }

    def reinitialised(self, t: float) -> None:
        """The engine was replaced at ``t`` (s): start the watch over."""
        self.t_reinit = t
        self.nis.clear()
        self.consecutive = 0
        self.fixes_since_reinit = 0
        self.last_out = None
        self.counts["reinitialised"] += 1

    def _dynamics(self) -> tuple[float, float, float, float]:
        """Bounds from the fixes of the last window: speed rate, velocity rate, course rate, accel RMS."""
        c = self.config
        a_s = a_h = w = 0.0
        sq = 0.0
        n = 0
        spaced: list[_Fix] = []
        for f in self.history:
            if not spaced or f.t - spaced[-1].t >= c.dynamics_min_dt_s:
                spaced.append(f)
        for f0, f1 in itertools.pairwise(spaced):
            dt = f1.t - f0.t
            dv = f1.v - f0.v
            a = math.hypot(dv[0], dv[1]) / dt
            a_h = max(a_h, a)
            sq += a * a
            n += 1
            s0, s1 = math.hypot(*f0.v), math.hypot(*f1.v)
            a_s = max(a_s, abs(s1 - s0) / dt)
            if min(s0, s1) > c.min_course_speed_mps:
                w = max(w, abs(_wrap(math.atan2(f1.v[1], f1.v[0]) - math.atan2(f0.v[1], f0.v[0]))) / dt)
        m = c.dynamics_margin
        rms = math.sqrt(sq / n) if n else 0.0
        return (
            max(m * a_s, c.accel_floor_mps2),
            max(m * a_h, c.accel_floor_mps2),
            max(m * w, c.yaw_rate_floor_rad_s),
            max(rms, c.accel_floor_mps2),
        )

    # ----------------------------------------------------------------- outputs
    def dr_velocity(self, t: float) -> tuple[np.ndarray, np.ndarray, float] | None:
        """``(p_n, v_n, sigma)``: the last fix moved on to ``t``, with its per-axis 1-sigma (m)."""
        f = self.fix
        if f is None:
            return None
        tau = max(t - f.t, 0.0)
        p = f.p + np.array([f.v[0] * tau, f.v[1] * tau, 0.0])
        a_rms = self.bounds[3]
        sigma = math.sqrt(f.sigma**2 + (tau * f.sigma_v) ** 2 + (0.5 * a_rms * tau * tau) ** 2)
        return p, np.array([f.v[0], f.v[1], 0.0]), sigma

    def judge(self, o: Output) -> str | None:
        """None to keep the engine's output ``o``, else why the dr-velocity solution replaces it."""
        c = self.config
        if o.source == "none" or not math.isfinite(o.lat + o.lon):
            return "no_position" if o.source == "none" else "nonfinite"
        f = self.fix
        if f is None or self.frame is None:
            return None
        tau = o.t - f.t
        if tau <= c.outage_after_s:
            self.fallback_reason = None
            return None
        if self.fallback_reason is not None:
            return self.fallback_reason
        a_s, a_h, w, _ = self.bounds
        v = np.array([o.vn, o.ve]) if math.isfinite(o.vn + o.ve) else np.zeros(2)
        s_e, s_f = math.hypot(*v), math.hypot(*f.v)
        reason = None
        if abs(s_e - s_f) > a_s * tau + 3.0 * f.sigma_v:
            reason = "speed"
        elif min(s_e, s_f) > c.min_course_speed_mps:
            sig_c = f.sigma_v / s_f
            dpsi = abs(_wrap(math.atan2(v[1], v[0]) - math.atan2(f.v[1], f.v[0])))
            if dpsi > w * tau + 3.0 * sig_c:
                reason = "course"
        if reason is None:
            dr = self.dr_velocity(o.t)
            assert dr is not None
            p_dr, _, _sig = dr
            p_e = self.frame.to_ned(o.lat, o.lon, o.height if math.isfinite(o.height) else self.frame.h0_m)
            dev = math.hypot(p_e[0] - p_dr[0], p_e[1] - p_dr[1])
            sig_tau = math.sqrt(f.sigma**2 + (tau * f.sigma_v) ** 2)
            reach = math.hypot(p_e[0] - f.p[0], p_e[1] - f.p[1])
            if dev > 0.5 * a_h * tau * tau + 3.0 * sig_tau:
                reason = "position"
            elif reach > self.speed_max * c.dynamics_margin * tau + 3.0 * f.sigma:
                reason = "reach"
        self.fallback_reason = reason
        return reason


class IntegrityEngine:
    """Any engine behind :class:`IntegrityGuard` (module docstring), with the same ``step()``.

    Parameters
    ----------
    factory : callable
        Builds a fresh engine (called once now and at each re-initialisation).
    config : IntegrityConfig, optional
        Guard tunables.

    Attributes not defined here (``mount_rpy_rad``, ``config``, ...) are the current engine's.
    """

    def __init__(self, factory: Callable[[], Engine], config: IntegrityConfig | None = None) -> None:
        self._factory = factory
        self._inner = factory()
        self._guard = IntegrityGuard(config)
        self._own_events: list[dict[str, Any]] = []
        self._past_events: list[dict[str, Any]] = []
        self._past_skipped: dict[str, int] = {}
        self._attitude = (math.nan, math.nan, math.nan)

    def __getattr__(self, name: str) -> Any:
        # never hand out the engine's compiled block step: run_batch would bypass the guard
        if name.startswith("_") or name in ("imu_block", "smoothing_log"):
            raise AttributeError(name)
        return getattr(self._inner, name)

    @property
    def engine(self) -> Engine:
        """The engine currently guarded."""
        return self._inner

    @property
    def events(self) -> list[dict[str, Any]]:
        """Events of every engine guarded so far and the guard's own, in time order."""
        evs = self._past_events + list(self._inner.events) + self._own_events
        return sorted(evs, key=lambda e: float(e.get("t", -math.inf)))

    @events.setter
    def events(self, value: list[dict[str, Any]]) -> None:
        self._past_events, self._own_events = [], []
        self._inner.events = value

    @property
    def mount_yaw_rad(self) -> float:
        """The current engine's mount-yaw estimate, rad."""
        return float(self._inner.mount_yaw_rad)

    def step(self, sample: Sample) -> Output | None:
        """One sample through the engine and the guard (an output per IMU sample)."""
        g = self._guard
        if (
            isinstance(sample, GnssSample)
            and sample.valid
            and math.isfinite(sample.t + sample.lat_deg + sample.lon_deg)
        ):
            request = g.on_fix(sample)
            if request is not None:
                self._reinit(request)
        out = self._inner.step(sample)
        if out is None or not isinstance(sample, ImuSample):
            return out
        if g.frame is None and out.source != "none" and math.isfinite(out.lat + out.lon):
            g.frame = TangentPlane(out.lat, out.lon, out.height if math.isfinite(out.height) else 0.0)
        reason = g.judge(out)
        # a fresh engine may not know its attitude yet: the last one known is reported meanwhile
        r0, p0, y0 = self._attitude
        att = (
            out.roll if math.isfinite(out.roll) else r0,
            out.pitch if math.isfinite(out.pitch) else p0,
            out.yaw if math.isfinite(out.yaw) else y0,
        )
        self._attitude = att
        if reason is None:
            g.last_out = out
            g.counts["engine_rows"] += 1
            return self._reframe(out._replace(roll=att[0], pitch=att[1], yaw=att[2]))
        if reason == "nonfinite" and g.fix is not None and out.t - g.t_reinit >= g.config.reinit_holdoff_s:
            self._reinit({"type": "reinitialised", "t": float(out.t), "reason": "nonfinite_output"})
        dr = g.dr_velocity(out.t)
        if dr is None or g.frame is None:
            return out  # nothing better known (no fix yet)
        if reason not in ("no_position", "nonfinite") and (
            not self._own_events or self._own_events[-1].get("t_fix") != g.fix.t  # type: ignore[union-attr]
        ):
            self._own_events.append(
                {"type": "integrity_fallback", "t": float(out.t), "reason": reason, "t_fix": g.fix.t}  # type: ignore[union-attr]
            )
        g.counts["fallback_rows"] += 1
        if reason not in ("no_position", "nonfinite"):
            g.last_out = out  # the watch keeps comparing the engine itself with the next fix
        p, v, sig = dr
        return output_at(out.t, g.frame, p, v, att, out.static, (sig, sig), DR_VELOCITY_SOURCE)

    def _reframe(self, out: Output) -> Output:
        """``out`` with north/east/down about the guard's frame (one frame for every row)."""
        f = self._guard.frame
        if f is None:
            return out
        r = f.to_ned(out.lat, out.lon, out.height if math.isfinite(out.height) else f.h0_m)
        return out._replace(north=float(r[0]), east=float(r[1]), down=float(r[2]))

    def _reinit(self, event: dict[str, Any]) -> None:
        self._past_events += list(self._inner.events)
        for k, n in dict(self._inner.summary().get("skipped", {})).items():
            self._past_skipped[k] = self._past_skipped.get(k, 0) + int(n)
        self._inner = self._factory()
        self._guard.reinitialised(float(event["t"]))
        self._own_events.append(event)

    def summary(self) -> dict[str, Any]:
        """The current engine's summary plus ``integrity`` (configuration and counts)."""
        out = dict(self._inner.summary())
        if self._past_skipped:  # samples skipped by the engines replaced so far count too
            skipped = dict(out.get("skipped", {}))
            for k, n in self._past_skipped.items():
                skipped[k] = skipped.get(k, 0) + n
            out["skipped"] = skipped
        out["integrity"] = {"config": asdict(self._guard.config), **self._guard.counts}
        return out
