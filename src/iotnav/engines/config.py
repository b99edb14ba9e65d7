"""Typed, frozen configuration of the Forno pipeline; paper values as defaults; TOML in, dict out.

One table per block, named as the attributes of :class:`PipelineConfig`::

    [last_position]  max_pdop = 10.0
    [tilt] [yaw] [gyro_bias]
    [static]         theta_a_mps2 = 0.125
    [lowpass3]       n1 = 10
    [mount]          method = "lsq"
    [fusion]         uere_m = 3.0
    [pipeline]       gravity_mps2 = 0.0   # 0: WGS84 normal gravity at the origin

Keys are the dataclass field names (SI units, as the names say). Unknown tables or keys raise
``ValueError`` naming them.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from iotnav.techniques.fusion_kf import FusionConfig
from iotnav.techniques.gyro_bias_kf import GyroBiasConfig
from iotnav.techniques.last_position import LastPositionConfig
from iotnav.techniques.lowpass3 import Lowpass3Config
from iotnav.techniques.mount import MountConfig
from iotnav.techniques.static import StaticConfig
from iotnav.techniques.tilt_kf import TiltConfig
from iotnav.techniques.yaw_kf import YawConfig


def read_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a syntax error becomes a ``ValueError`` naming the file."""
    with open(path, "rb") as f:
        try:
            return tomllib.load(f)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{path}: {exc}") from exc


#: Keys that configuration files of earlier versions may carry, and why they are gone.
REMOVED_KEYS: dict[str, str] = {
    "vertical_ratio": "[fusion] vertical_ratio was removed: every engine reads the receiver's "
    "accuracy one way (iotnav.gnss_accuracy; without vAcc the vertical sigma is 1.5 x hAcc)",
}


def dataclass_from_dict(base: Any, data: dict[str, Any], where: str) -> Any:
    """Copy of the frozen dataclass ``base`` with the keys of ``data`` replaced.

    Nested dataclass fields take sub-tables (recursively); TOML arrays become tuples (of floats
    when numeric). Unknown keys raise ``ValueError`` naming the table ``where`` and the keys it
    accepts, so a typo in a configuration file is never silently ignored.

    Parameters
    ----------
    base : dataclass instance
        The defaults (an engine's own, which may differ from the class defaults).
    data : dict
        One TOML table.
    where : str
        The table's name, for messages.
    """
    if not isinstance(data, dict):
        raise ValueError(f"[{where}] must be a table")
    known = {f.name for f in fields(base)}
    bad = set(data) - known
    if bad:
        why = "".join(f"; {REMOVED_KEYS[k]}" for k in sorted(bad) if k in REMOVED_KEYS)
        raise ValueError(f"unknown key(s) in [{where}]: {sorted(bad)}{why}; expected some of {sorted(known)}")
    changes: dict[str, Any] = {}
    for k, v in data.items():
        current = getattr(base, k)
        if dataclasses.is_dataclass(current) and not isinstance(current, type):
            changes[k] = dataclass_from_dict(current, v, f"{where}.{k}")
        elif isinstance(v, list):
            numeric = all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in v)
            changes[k] = tuple(float(a) for a in v) if numeric else tuple(v)
        else:
            changes[k] = v
    return dataclasses.replace(base, **changes)


def config_from_toml(path: str | Path, base: Any, table: str) -> Any:
    """Load ``[table]`` of a TOML file (or its top-level keys when there is no such table) onto ``base``."""
    data = read_toml(path)
    try:
        return dataclass_from_dict(base, data.get(table, data), table)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from exc


@dataclass(frozen=True)
class EngineConfig:
    """Wiring options of the pipeline itself.

    Attributes
    ----------
    gravity_mps2 : float
        Gravity magnitude, m/s^2; 0 uses WGS84 normal gravity at the NED origin.
    fix_hold_s : float
        Output ``source`` is ``fix`` up to this long after an applied fix, then ``dr``, s.
    zupt_noise_mps : float
        Standard deviation of the zero-velocity update applied at each GPS epoch while
        static, m/s.
    use_lowpass : bool
        Enable block 4 (False feeds raw fixes while static, for comparisons).
    static_hold : bool
        While static with block 4 active, do not propagate the fusion filter: the device does
        not move, so position and covariance hold between low-pass measurements (sleep mode).
    lowpass_corr_time_s : float
        Correlation time assumed for GNSS position errors when weighting a low-pass output:
        ``R_lp = R_fix / (1 + N dt / (2 tau))`` for ``N`` fixes ``dt`` apart, s.
    use_mount : bool
        Enable block 5.
    """

    gravity_mps2: float = 0.0
    fix_hold_s: float = 1.5
    zupt_noise_mps: float = 0.05
    use_lowpass: bool = True
    use_mount: bool = True
    static_hold: bool = True
    lowpass_corr_time_s: float = 60.0


#: Block 5 as the pipeline uses it: the recursive lsq estimate on matched-smoothed rows, lower
#: speed floor (the lsq form needs no course), and acceptance only at a fused standard
#: deviation of 1 degree or less (see :mod:`iotnav.techniques.mount`). The forgetting factor
#: applies per 8 s of buffer (at 4 Hz GNSS a per-buffer factor forgot within 40 s and capped
#: the fused std at 2-3 degrees on a real car drive); buffers inconsistent with the fused
#: angle beyond 3 sigma are not fused (on hilly roads a grade unlike the gravity reference's
#: leaks gravity into whole buffers); the fused std carries the forgetting weights' variance
#: factor. Acceptance stays at a fused std of 1 degree: the first accepted estimate must be
#: within 2 degrees of the truth (issue #4), and at 1.5 or 2 degrees the first estimates on the
#: simulated scooter laps with constant-speed straights were 1.9-2.6 degrees off (5 laps, seed
#: 1). On the rtklibexplorer roof-mounted car drive (hilly, the gravity reference renewed only
#: at stops) the levelled buffers were inconsistent (errors between buffers 3-5 times each
#: buffer's residual sigma) and no mount was accepted at 1 Hz GNSS: ``auto_demean`` also fuses
#: the demeaned buffers and uses the form with the smaller consistency-scaled std, and
#: ``settle_s`` accepts an estimate of up to 2 degrees std once it has stayed within 1 degree for
#: 60 s (see :mod:`iotnav.techniques.mount`); the simulated laps are unchanged. The defaults of
#: :class:`MountConfig` itself are unchanged for the other engines.
PIPELINE_MOUNT = MountConfig(
    smooth_epochs=3,
    min_speed_mps=1.0,
    require_course=False,
    max_std_rad=math.radians(1.0),
    forget_ref_s=8.0,
    weighted_variance=True,
    gate_sigma=3.0,
    auto_demean=True,
    settle_s=60.0,
)

#: Block 5 as the pipeline navigates with it: :data:`PIPELINE_MOUNT`, plus provisional
#: estimates before the first acceptance (an angle in use that a useful estimate rejects at
#: 3 sigma is replaced; ``sigma`` at most 15 deg). See :mod:`iotnav.techniques.mount`.
PIPELINE_MOUNT_NAV = dataclasses.replace(PIPELINE_MOUNT, provisional_sigmas=3.0)

#: Block 3 as the pipeline uses it: static periods end on the accelerometer (the paper) or on a
#: smoothed GPS speed above 1.5 m/s, not on the GPS speed noise of a standing receiver.
PIPELINE_STATIC = StaticConfig(exit_speed_mps=1.5)

_BLOCKS: dict[str, type] = {
    "last_position": LastPositionConfig,
    "tilt": TiltConfig,
    "yaw": YawConfig,
    "gyro_bias": GyroBiasConfig,
    "static": StaticConfig,
    "lowpass3": Lowpass3Config,
    "mount": MountConfig,
    "fusion": FusionConfig,
    "pipeline": EngineConfig,
}


@dataclass(frozen=True)
class PipelineConfig:
    """Every tunable of the Forno pipeline, grouped per block."""

    last_position: LastPositionConfig = field(default_factory=LastPositionConfig)
    tilt: TiltConfig = field(default_factory=TiltConfig)
    yaw: YawConfig = field(default_factory=YawConfig)
    gyro_bias: GyroBiasConfig = field(default_factory=GyroBiasConfig)
    static: StaticConfig = field(default_factory=lambda: PIPELINE_STATIC)
    lowpass3: Lowpass3Config = field(default_factory=Lowpass3Config)
    mount: MountConfig = field(default_factory=lambda: PIPELINE_MOUNT_NAV)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    pipeline: EngineConfig = field(default_factory=EngineConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested plain dict (for ``summary.json``)."""
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PipelineConfig:
        """Build from a nested dict; missing keys keep their defaults."""
        unknown = set(data) - set(_BLOCKS)
        if unknown:
            raise ValueError(f"unknown configuration table(s): {sorted(unknown)}; expected {sorted(_BLOCKS)}")
        parts: dict[str, Any] = {}
        defaults = cls()
        for name in _BLOCKS:
            parts[name] = dataclass_from_dict(getattr(defaults, name), data.get(name, {}), name)
        return cls(**parts)

    @classmethod
    def from_toml(cls, path: str | Path) -> PipelineConfig:
        """Load a TOML file (tables as in the module docstring)."""
        data = read_toml(path)
        try:
            return cls.from_dict(data)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from exc

    def replace(self, **blocks: Any) -> PipelineConfig:
        """Copy with some blocks replaced (``cfg.replace(mount=MountConfig(method="paper"))``)."""
        return dataclasses.replace(self, **blocks)
