"""State layout, configuration and fix samples of the ``absfix`` engine (:mod:`iotnav.engines.absfix`).

The named slices of the flat state array (STYLE §5; indices of
:mod:`iotnav.engines.absfix_kernel`), the frozen :class:`AbsfixConfig` (``[absfix]`` TOML
table; defaults from Dabove et al. 2015, see :mod:`iotnav.engines.absfix`), the absolute fix
:class:`AbsFixSample` (WGS-84 position, optional attitude ``C_nb``, valid at ``t_valid``,
arriving at ``t_arrival``, s) and :func:`fixes_from_table`, which builds fixes from a table.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, cast

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.engines import absfix_kernel as K
from iotnav.engines.config import config_from_toml, dataclass_from_dict
from iotnav.techniques import decoupled_bias as db

FloatArray = npt.NDArray[np.float64]

#: Named state layout of the flat state array (STYLE §5; indices of :mod:`~iotnav.engines.absfix_kernel`).
POS = slice(K.X_POS, K.X_POS + 3)  # p_n, m
VEL = slice(K.X_VEL, K.X_VEL + 3)  # v_n, m/s
ATT = slice(K.X_ATT, K.X_ATT + 9)  # C_nb, row-major
BA = slice(K.X_BA, K.X_BA + 3)  # accelerometer bias b_a, m/s^2, in b
BG = slice(K.X_BG, K.X_BG + 3)  # gyro drift d_g, rad/s, in b
ACC = slice(K.X_ACC, K.X_ACC + db.N_ACC)  # interval integrals since the last fix (decoupled_bias.ACC_*)
ALIGN_T0 = K.X_ALIGN_T0  # time of the first IMU sample, s
ALIGN_N = K.X_ALIGN_N  # samples averaged for the alignment
ALIGN_F = slice(K.X_ALIGN_F, K.X_ALIGN_F + 3)  # sum of f_b over the alignment, m/s^2
GAPS = K.X_GAPS  # IMU gaps skipped
N_STATE = K.N_X  # then the started flag, the previous IMU sample and the fix-history version

_MODES = ("none", "fixes", "reference")
_DENOISE = ("off", "batch", "streaming")


@dataclass(frozen=True)
class AbsfixConfig:
    """Configuration of :class:`AbsfixEngine` (``[absfix]`` table of a TOML file).

    Attributes
    ----------
    align_s : float
        Initial alignment, s (paper: about 3 s).
    bias_mode, drift_mode : {"none", "fixes", "reference"}
        How the accelerometer bias and the gyro drift are obtained (module docstring).
    bias_window_fixes : int
        Fixes used for velocity and bias (paper: 3; more gives least squares).
    drift_window_fixes : int
        Fixes whose attitudes give the drift (paper: 2, consecutive; more: longer baseline).
    reference_acc_bias_mps2 : tuple of float
        Accelerometer bias for ``bias_mode = "reference"``, m/s^2, in ``b``.
    reference_gyro_bias_rads : tuple of float
        Gyro drift for ``drift_mode = "reference"``, rad/s, in ``b``.
    attitude_reset : bool
        Reset the attitude to the fix attitude at each fix (paper: yes).
    initial_yaw_rad : float
        Yaw when the first fix has no attitude, rad.
    max_latency_s : float
        Oldest fix validity accepted, s before the newest IMU sample (paper: up to 2 s).
    buffer_capacity : int
        Maximum IMU epochs buffered for latency compensation.
    max_imu_gap_s : float
        Longer gaps between IMU samples are not integrated (counted in the summary).
    denoise : {"off", "batch", "streaming"}
        Wavelet denoising of the IMU channels (Daubechies 4, level 7).
    denoise_window, denoise_delay : int
        Streaming denoiser window and output delay, samples.
    origin_lat_deg, origin_lon_deg, origin_height_m : float
        Geodetic origin of NED fixes (for lat/lon output and gravity); NaN: outputs in NED only.
    """

    align_s: float = 3.0
    bias_mode: str = "fixes"
    drift_mode: str = "fixes"
    bias_window_fixes: int = 3
    drift_window_fixes: int = 2
    reference_acc_bias_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reference_gyro_bias_rads: tuple[float, float, float] = (0.0, 0.0, 0.0)
    attitude_reset: bool = True
    initial_yaw_rad: float = 0.0
    max_latency_s: float = 2.0
    buffer_capacity: int = 4096
    max_imu_gap_s: float = 0.5
    denoise: str = "off"
    denoise_window: int = 1024
    denoise_delay: int = 256
    origin_lat_deg: float = math.nan
    origin_lon_deg: float = math.nan
    origin_height_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("bias_mode", "drift_mode"):
            if getattr(self, name) not in _MODES:
                raise ValueError(f"{name}: expected one of {', '.join(_MODES)}, got {getattr(self, name)!r}")
        if self.denoise not in _DENOISE:
            raise ValueError(f"denoise: expected one of {', '.join(_DENOISE)}, got {self.denoise!r}")
        if self.bias_window_fixes < 3:
            raise ValueError("bias_window_fixes must be >= 3 (six equations need three fixes)")
        if self.drift_window_fixes < 2:
            raise ValueError("drift_window_fixes must be >= 2")
        if self.align_s < 0 or self.max_latency_s < 0:
            raise ValueError("align_s and max_latency_s must be >= 0")
        for name in ("reference_acc_bias_mps2", "reference_gyro_bias_rads"):
            if len(getattr(self, name)) != 3:
                raise ValueError(f"{name}: expected three values")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AbsfixConfig:
        """Build from a mapping (unknown keys raise ValueError)."""
        return cast(AbsfixConfig, dataclass_from_dict(cls(), data, "absfix"))

    @classmethod
    def from_toml(cls, path: str | Path) -> AbsfixConfig:
        """Load ``[absfix]`` (or top-level keys) from a TOML file."""
        return cast(AbsfixConfig, config_from_toml(path, cls(), "absfix"))

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``summary.json``)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}

    def replace(self, **changes: Any) -> AbsfixConfig:
        """Copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


class AbsFixSample(NamedTuple):
    """One absolute fix.

    Attributes
    ----------
    t_valid : float
        Device time the fix refers to, s.
    t_arrival : float
        Device time it became available, s (``>= t_valid``).
    pos_n : numpy.ndarray
        Position in the local NED frame ``n``, m, ``(3,)``; NaN when given geodetically.
    lat_deg, lon_deg, height_m : float
        Geodetic position (degrees, ellipsoidal m); NaN when given in NED.
    att : numpy.ndarray
        Roll, pitch, yaw of ``b`` in ``n`` (ZYX), rad, ``(3,)``; NaN without attitude.
    sigma_pos_m, sigma_att_rad : float
        Stated 1-sigma accuracies (informative: the decoupled method uses no noise model).
    """

    t_valid: float
    t_arrival: float
    pos_n: FloatArray
    lat_deg: float
    lon_deg: float
    height_m: float
    att: FloatArray
    sigma_pos_m: float = math.nan
    sigma_att_rad: float = math.nan

    @property
    def t(self) -> float:
        """Merge time in a sample stream: the arrival time, s."""
        return self.t_arrival

    @property
    def has_attitude(self) -> bool:
        """True when roll, pitch and yaw are all given."""
        return bool(np.all(np.isfinite(self.att)))

    @property
    def geodetic(self) -> bool:
        """True when the position is given as latitude / longitude / height."""
        return math.isfinite(self.lat_deg) and math.isfinite(self.lon_deg)


def fixes_from_table(df: pd.DataFrame) -> list[AbsFixSample]:
    """Fixes from a :func:`iotnav.io.fixes.read_fixes` table or a simulator ``fixes`` table.

    Parameters
    ----------
    df : pandas.DataFrame
        Columns ``t_valid``, ``t_arrival`` and either ``lat_deg, lon_deg, height_m`` (or ``lat,
        lon, height``) or ``north_m, east_m, down_m``; optional ``roll, pitch, yaw`` (rad),
        ``sigma_pos_m``, ``sigma_att_rad``.

    Returns
    -------
    list of AbsFixSample
        In table order.
    """
    n = len(df)

    def col(*names: str) -> FloatArray:
        for c in names:
            if c in df.columns:
                return df[c].to_numpy(dtype=float)
        return np.full(n, math.nan)

    tv, ta = col("t_valid"), col("t_arrival")
    lat, lon, h = col("lat_deg", "lat"), col("lon_deg", "lon"), col("height_m", "height")
    ned = np.column_stack([col("north_m", "north"), col("east_m", "east"), col("down_m", "down")])
    att = np.column_stack([col("roll"), col("pitch"), col("yaw")])
    sp, sa = col("sigma_pos_m"), col("sigma_att_rad")
    h = np.where(np.isfinite(lat) & ~np.isfinite(h), 0.0, h)
    return [
        AbsFixSample(
            float(tv[i]),
            float(ta[i]),
            ned[i].copy(),
            float(lat[i]),
            float(lon[i]),
            float(h[i]),
            att[i].copy(),
            float(sp[i]),
            float(sa[i]),
        )
        for i in range(n)
    ]


class _FixRecord(NamedTuple):
    """A fix as remembered for the decoupled solution (immutable)."""

    t: float
    X: FloatArray
    C: FloatArray | None
    interval: db.IntervalIntegrals | None  # from the previous fix to this one
