"""Tunables of the integrity guard (:mod:`iotnav.engines.integrity`, which re-exports them).

Moved out of :mod:`iotnav.engines.integrity` unchanged; the sources of the values are in that
module's docstring.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["IntegrityConfig"]


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
    min_reinit_distance_m : float
        An engine is re-initialised (and a fresh one leaves its probation) only when its mean
        distance to the fixes of the window is beyond this too, m.
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
    min_reinit_distance_m: float = 10.0
