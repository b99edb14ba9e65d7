"""Configuration of the ``fixes`` engine (:mod:`iotnav.engines.fixes`, which re-exports it).

Moved out of :mod:`iotnav.engines.fixes` unchanged: the platforms' motion-model defaults
(:data:`PLATFORMS`) and the configuration blocks; the sources of the values are in the
docstrings below and in the engine module's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from iotnav.engines.config import dataclass_from_dict, read_toml
from iotnav.techniques.last_position import LastPositionConfig
from iotnav.techniques.lowpass3 import Lowpass3Config

__all__ = [
    "PLATFORMS",
    "FixesConfig",
    "FixesGateConfig",
    "FixesInputConfig",
    "FixesKFConfig",
    "FixesStaticConfig",
    "Platform",
]


@dataclass(frozen=True)
class Platform:
    """Motion-model figures of a platform (module docstring for the sources).

    Attributes
    ----------
    acc_psd_m2_s3 : float
        Horizontal manoeuvre (white acceleration) PSD, m^2/s^3.
    max_speed_mps : float
        Fastest plausible speed, m/s (consistency of relocation candidates).
    init_vel_std_mps : float
        Velocity 1-sigma at initialisation without a measured velocity, m/s.
    exit_speed_mps : float
        Parked, a reported speed above this counts towards a departure (departure test), m/s:
        1.5 for vehicles (the pipeline's block 3 exit speed; a parked receiver in an urban
        canyon reports up to 2-3 m/s, so the speed alone never decides), 0.5 for a pedestrian
        (below a slow walk, 0.6-0.8 m/s: a walker leaves slower than 1.5 m/s).
    """

    acc_psd_m2_s3: float
    max_speed_mps: float
    init_vel_std_mps: float
    exit_speed_mps: float = 1.5


#: Presets: car and pedestrian PSDs from Groves 2013 sec. 9.4.2.2; bike/scooter in between.
PLATFORMS: dict[str, Platform] = {
    "car": Platform(10.0, 70.0, 15.0),
    "bike": Platform(3.0, 20.0, 5.0),
    "scooter": Platform(3.0, 20.0, 5.0),
    "pedestrian": Platform(1.0, 7.0, 2.0, 0.5),
}


@dataclass(frozen=True)
class FixesKFConfig:
    """Motion model and measurement noise (SI).

    Attributes
    ----------
    platform : str
        ``car``, ``bike``, ``scooter`` or ``pedestrian`` (:data:`PLATFORMS`).
    acc_psd_m2_s3 : float
        Horizontal acceleration PSD, m^2/s^3 (0: the platform's).
    vertical_psd_ratio : float
        Vertical PSD as a fraction of the horizontal one.
    uere_m : float
        UERE multiplying the DOPs without a receiver accuracy, m (as the other engines).
    default_hdop : float
        HDOP assumed without any accuracy figure or DOP.
    vel_noise_mps : float
        Velocity 1-sigma per axis without ``s_acc``, m/s.
    min_course_speed_mps : float
        Speed and course give a velocity only at or above this speed, m/s.
    use_velocity : bool
        Use reported velocity (or speed and course).
    smoothing : bool
        Keep the records RTS smoothing and resampling need (280 bytes a row).
    """

    platform: str = "car"
    acc_psd_m2_s3: float = 0.0
    vertical_psd_ratio: float = 0.1
    uere_m: float = 3.0
    default_hdop: float = 2.0
    vel_noise_mps: float = 0.5
    min_course_speed_mps: float = 1.0
    use_velocity: bool = True
    smoothing: bool = False


@dataclass(frozen=True)
class FixesGateConfig:
    """NIS gate and recovery.

    Attributes
    ----------
    probability : float
        Chi-square probability of the horizontal position gate (2 dof).
    velocity_probability : float
        Chi-square probability of the velocity gate (2 dof).
    relocation_fixes : int
        Consistent rejected fixes that make a relocation (also: consistent UTC offsets that
        make a new clock reference).
    relocation_min_s : float
        They must span at least this long, s.
    max_rejections : int
        Consecutive rejections after which the filter re-initialises at the latest fix.
    reject_q_factor : float
        After ``n`` consecutive rejections the prediction uses ``q (1 + (f - 1) n)``: a
        rejection is as likely a manoeuvre the model missed as a glitch (adjustable-level
        process noise, Bar-Shalom, Li and Kirubarajan 2001, sec. 11.2).
    soft_probability : float
        Chi-square probability (2 dof) beyond which an accepted fix is doubtful (module
        docstring, "Rollback").
    rollback_s : float
        How long the state before a doubtful fix is kept to fall back on, s.
    """

    probability: float = 0.9973
    velocity_probability: float = 0.9973
    relocation_fixes: int = 5
    relocation_min_s: float = 5.0
    max_rejections: int = 30
    reject_q_factor: float = 10.0
    soft_probability: float = 0.95
    rollback_s: float = 10.0


@dataclass(frozen=True)
class FixesStaticConfig:
    """Static detection from GNSS (module docstring) and the filter while static.

    Attributes
    ----------
    speed_threshold_mps : float
        Reported speed below this is evidence of standing still, m/s (as block 3's default).
    exit_speed_mps : float
        Parked: a fix reporting a speed above this counts towards a departure as a displaced
        one does (departure test), m/s; 0: the platform's (:class:`Platform`).
    exit_speed_fixes : int
        Moving: a reported speed above ``speed_threshold_mps`` on this many consecutive fixes
        vetoes the static state (a walker or a robot moves at 1 m/s). Parked: the departure
        test needs this many consecutive displaced fixes (module docstring).
    departure_acc_mps2 : float
        Largest acceleration from rest of the departure test, m/s^2: the first displaced fix
        of a departure lies within the gate's bound plus ``a t^2 / 2`` of the held position, ``t``
        the time since the last fix that was not displaced. 3 m/s^2: above the maximum
        accelerations from standstill measured on cars (about 1.5-3 m/s^2, Bokare and Maurya
        2017, "Acceleration-deceleration behaviour of various vehicle types", Transportation
        Research Procedia 25) and far above a walker's start.
    departure_probability : float
        Chi-square probability (2 dof) beyond which a parked fix is displaced from the held
        position: the gate's (``[gate] probability``), so that a fix the parked state would
        accept is never a departure.
    window_s : float
        Span of the spread test, s.
    min_fixes : int
        Fewest fixes in the spread test.
    spread_probability : float
        Chi-square probability of the spread test.
    acc_std_threshold_mps2 : float
        Standard deviation of ``|f_b|`` between fixes below which the device is still, m/s^2.
    acc_move_threshold_mps2 : float
        Standard deviation of ``|f_b|`` between fixes above which the device moves, m/s^2.
    zupt_noise_mps : float
        Zero-velocity update sigma while static, m/s (as the pipeline).
    lowpass_corr_time_s : float
        GNSS error correlation time weighting the low-pass output, s (as the pipeline).
    use_lowpass : bool
        Feed the low-pass while static (False: zero-velocity updates only).
    """

    speed_threshold_mps: float = 0.5
    exit_speed_mps: float = 0.0
    exit_speed_fixes: int = 3
    departure_acc_mps2: float = 3.0
    departure_probability: float = 0.9973
    window_s: float = 20.0
    min_fixes: int = 3
    spread_probability: float = 0.99
    acc_std_threshold_mps2: float = 0.125
    acc_move_threshold_mps2: float = 1.0
    zupt_noise_mps: float = 0.05
    lowpass_corr_time_s: float = 60.0
    use_lowpass: bool = True


@dataclass(frozen=True)
class FixesInputConfig:
    """Input checks.

    Attributes
    ----------
    clock_tolerance_s : float
        Largest change of ``utc - t`` before an epoch is from the future / past, s: above
        leap-second steps (at most 37 s) and a device's clock corrections, far below the
        errors of a bad date (a day, a GPS week rollover's 19.6 years).
    """

    clock_tolerance_s: float = 600.0


@dataclass(frozen=True)
class FixesConfig:
    """Every tunable of the ``fixes`` engine, grouped per block (TOML tables of the same names)."""

    kf: FixesKFConfig = field(default_factory=FixesKFConfig)
    gate: FixesGateConfig = field(default_factory=FixesGateConfig)
    static: FixesStaticConfig = field(default_factory=FixesStaticConfig)
    lowpass3: Lowpass3Config = field(default_factory=Lowpass3Config)
    last_position: LastPositionConfig = field(default_factory=LastPositionConfig)
    input: FixesInputConfig = field(default_factory=FixesInputConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested plain dict (for ``summary.json``)."""
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_toml(cls, path: str | Path) -> FixesConfig:
        """Load a TOML file whose tables are the blocks (``[kf] platform = "bike"``)."""
        data = read_toml(path)
        try:
            cfg = dataclass_from_dict(cls(), data, "fixes")
            cfg.platform()
            return cfg  # type: ignore[no-any-return]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from exc

    def platform(self) -> Platform:
        """The platform preset with the configured overrides."""
        p = PLATFORMS.get(self.kf.platform)
        if p is None:
            raise ValueError(f"unknown platform {self.kf.platform!r}; expected one of {', '.join(PLATFORMS)}")
        if self.kf.acc_psd_m2_s3 > 0:
            p = dataclasses.replace(p, acc_psd_m2_s3=self.kf.acc_psd_m2_s3)
        return p
