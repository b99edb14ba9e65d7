"""Saving and reloading the last known position (Forno et al. 2020, block 1).

The latest good position is saved periodically to a persistent store; at boot it is loaded
and output as the position while the INS sees no movement and no acceptable fix has arrived
(devices are woken by the accelerometer, so the target has most likely not moved while off).

A GNSS fix is *acceptable* when the receiver declares it valid, its coordinates are finite,
``PDOP <= max_pdop`` (paper: 10) and, optionally, ``num_sv >= min_num_sv`` (the anchor-node
paper uses more than 4, i.e. ``min_num_sv = 5``). When the first acceptable fix is farther
than ``moved_threshold_m`` (horizontal) from the stored position, a "moved while off" event
is raised: the paper's anti-theft use.

Settling gate (added here; the paper gives only the PDOP threshold). After a cold start a
receiver's first fixes can lie tens of metres off while its PDOP, though already below 10, is
still falling steeply as it converges. When there is no stored position (nothing to fall back
on, and the first fix becomes the NED origin and the first output), a fix is used as the
*first* fix only once the PDOP has settled: it fell by less than ``settle_ratio`` over the
valid fixes of the last ``settle_window_s``, and, unless those fixes cover the whole window,
it is already at most ``settle_max_pdop`` (a receiver reporting a low PDOP from its first
fix is not converging)::

    PDOP(t) >= (1 - settle_ratio) * max(PDOP over [t - settle_window_s, t))
    and (history covers settle_window_s  or  PDOP(t) <= settle_max_pdop)

Fixes refused by this test carry the reason ``"settling"``. With a stored position the paper's
rule applies unchanged (the stored position is output until the first PDOP <= 10 fix).

:class:`LastPositionLogic` is pure (no I/O); :class:`LastPositionStore` is the tiny file store
(one JSON file per device, written atomically: temp file in the same folder, ``fsync``,
``os.replace``, so a power cut leaves either the old or the new file, never a torn one).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class LastPositionConfig:
    """Block-1 tunables.

    Attributes
    ----------
    max_pdop : float
        Fixes with larger PDOP are refused (paper: 10).
    min_num_sv : int
        Minimum satellites used (0: not checked; the anchor-node paper: 5).
    accept_unknown_pdop : bool
        Accept a valid fix whose PDOP is unknown (NaN).
    moved_threshold_m : float
        First-fix distance from the stored position that raises "moved while off", m.
    save_interval_s : float
        Minimum time between two saves, s.
    stored_std_m : float
        Horizontal 1-sigma assumed for the stored position, m.
    boot_walk_speed_mps : float
        Growth rate of that sigma once the INS sees movement before any fix, m/s.
    settle_ratio : float
        Largest relative PDOP decrease over ``settle_window_s`` for a first fix without a
        stored position (0: no settling gate).
    settle_window_s : float
        Window of the settling gate, s.
    settle_max_pdop : float
        A first fix with a shorter PDOP history must have at most this PDOP.
    """

    max_pdop: float = 10.0
    min_num_sv: int = 0
    accept_unknown_pdop: bool = True
    moved_threshold_m: float = 50.0
    save_interval_s: float = 60.0
    stored_std_m: float = 5.0
    boot_walk_speed_mps: float = 1.5
    settle_ratio: float = 0.05
    settle_window_s: float = 10.0
    settle_max_pdop: float = 4.0


@dataclass(frozen=True)
class StoredPosition:
    """A saved position: geodetic degrees, ellipsoidal metres, device time, optional mount angle."""

    lat_deg: float
    lon_deg: float
    height_m: float
    t: float = math.nan
    mount_yaw_rad: float = math.nan


def fix_rejection_reason(
    valid: bool, lat_deg: float, lon_deg: float, pdop: float, num_sv: int, config: LastPositionConfig
) -> str | None:
    """Why a fix is refused (``None`` when acceptable)."""
    if not valid:
        return "invalid"
    if not (math.isfinite(lat_deg) and math.isfinite(lon_deg)):
        return "no_position"
    if math.isfinite(pdop):
        if pdop > config.max_pdop:
            return "pdop"
    elif not config.accept_unknown_pdop:
        return "pdop_unknown"
    if config.min_num_sv > 0 and num_sv < config.min_num_sv:
        return "num_sv"
    return None


def horizontal_distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle (haversine, mean Earth radius) distance between two points in degrees, m."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    a = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2.0 * 6371008.8 * math.asin(min(1.0, math.sqrt(a)))


class LastPositionLogic:
    """Pure boot and save logic of block 1.

    Parameters
    ----------
    config : LastPositionConfig
        Thresholds.
    stored : StoredPosition, optional
        What the store returned at boot.
    """

    def __init__(
        self, config: LastPositionConfig | None = None, stored: StoredPosition | None = None
    ) -> None:
        self.config = config or LastPositionConfig()
        self.stored = stored
        self.first_fix_seen = False
        self.t_saved = -math.inf
        self._pdop_hist: list[tuple[float, float]] = []  # (t, PDOP) of valid fixes before the first

    def check_fix(
        self, valid: bool, lat_deg: float, lon_deg: float, pdop: float, num_sv: int, t: float = math.nan
    ) -> str | None:
        """Rejection reason of a fix, or None when acceptable (``t``: device time, s, for settling)."""
        reason = fix_rejection_reason(valid, lat_deg, lon_deg, pdop, num_sv, self.config)
        c = self.config
        if (
            reason is None
            and not self.first_fix_seen
            and self.stored is None
            and c.settle_ratio > 0.0
            and math.isfinite(t)
            and math.isfinite(pdop)
        ):
            hist = [(tk, p) for tk, p in self._pdop_hist if tk >= t - c.settle_window_s - 1e-9]
            covered = bool(self._pdop_hist) and self._pdop_hist[0][0] <= t - c.settle_window_s + 1e-9
            self._pdop_hist = [*hist, (t, pdop)]
            recent = [p for tk, p in hist if tk < t]
            falling = bool(recent) and pdop < (1.0 - c.settle_ratio) * max(recent)
            if falling or (not covered and pdop > c.settle_max_pdop):
                return "settling"
        return reason

    def first_fix(self, t: float, lat_deg: float, lon_deg: float) -> dict[str, Any] | None:
        """Call on the first acceptable fix; returns a "moved while off" event when applicable."""
        self.first_fix_seen = True
        if self.stored is None:
            return None
        d = horizontal_distance_m(self.stored.lat_deg, self.stored.lon_deg, lat_deg, lon_deg)
        if d > self.config.moved_threshold_m:
            return {"type": "moved_while_off", "t": t, "distance_m": d}
        return None

    def due(self, t: float) -> bool:
        """True when a save is due at time ``t`` (s); marks it done."""
        if t - self.t_saved >= self.config.save_interval_s:
            self.t_saved = t
            return True
        return False


class LastPositionStore:
    """One JSON file per device holding a :class:`StoredPosition`; atomic writes.

    Parameters
    ----------
    path : str or pathlib.Path
        The file (its folder must exist).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def load(self) -> StoredPosition | None:
        """The stored position, or None when there is no file or it cannot be read."""
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            return StoredPosition(**{k: float(v) for k, v in data.items()})
        except (OSError, ValueError, TypeError):
            return None

    def save(self, pos: StoredPosition) -> None:
        """Write atomically (temp file + fsync + ``os.replace``)."""
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".tmp", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(asdict(pos), f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
