"""Offline outputs of the ``fixes`` engine: the RTS-smoothed track and the resampled track.

:class:`FixesOffline` holds :class:`~iotnav.engines.fixes.FixesEngine`'s methods that read its
smoothing records (moved out of :mod:`iotnav.engines.fixes` unchanged); the compiled passes are
:mod:`iotnav.engines.fixes_rts`. The model and the reported uncertainty are described in
:mod:`iotnav.engines.fixes`.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.engines import fixes_kernel as fk
from iotnav.engines import fixes_rts as fr
from iotnav.engines.base import FLOAT_COLUMNS
from iotnav.engines.fixes_config import FixesConfig
from iotnav.engines.tangent_plane import TangentPlane

FloatArray = npt.NDArray[np.float64]

__all__ = ["FixesOffline"]


class FixesOffline:
    """Smoothed and resampled tracks from the forward run's records (mixed into ``FixesEngine``).

    Attributes read (set by the engine): ``config``, ``frame`` (its tangent plane), ``q_h`` and
    ``q_v`` (horizontal and vertical acceleration PSD, m^2/s^3) and ``_records`` (the record
    blocks, ``fixes_kernel.REC_*`` layout).
    """

    config: FixesConfig
    frame: TangentPlane | None
    q_h: float
    q_v: float
    _records: list[FloatArray]

    def _all_records(self) -> FloatArray:
        if not self.config.kf.smoothing:
            raise ValueError(
                "smoothing and resampling need [kf] smoothing = true (iotnav run --smooth / --rate)"
            )
        return np.concatenate(self._records) if self._records else np.zeros((0, fk.REC_SIZE))

    def smoothed_states(self) -> tuple[FloatArray, FloatArray]:
        """Records and RTS-smoothed states (``(n, 15)``, the ``kf`` layout; NaN on boot rows)."""
        rec = self._all_records().copy()
        fr.retract_records(rec, rec.shape[0], self.q_h, self.q_v)
        sm = np.zeros((rec.shape[0], fk.KF_SIZE))
        fr.rts_records(rec, rec.shape[0], sm)
        return rec, sm

    def smoothed_output(self, forward: pd.DataFrame) -> pd.DataFrame:
        """The RTS-smoothed track at the rows of ``forward`` (this engine's :func:`~iotnav.engines.base.run_batch` output)."""
        rec, sm = self.smoothed_states()
        if rec.shape[0] != len(forward):
            raise ValueError(f"forward track has {len(forward)} rows, the engine recorded {rec.shape[0]}")
        df = forward.copy()
        df.attrs = dict(forward.attrs)
        filt = rec[:, fk.REC_KIND] != fk.K_BOOT
        self._write_states(df, sm, filt, rec[:, fk.REC_STATIC] != 0.0, rec[:, fk.REC_SIG])
        return df

    def resample(
        self, rate_hz: float, smoothed: bool = True, forward: pd.DataFrame | None = None
    ) -> pd.DataFrame:
        """The track at ``rate_hz`` from the first to the last filter record (module docstring).

        Rows between fixes carry source ``dr`` (``lowpass`` when both neighbours are static);
        rows at a fix time keep that fix's source when ``forward`` is given.
        """
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"--rate must be a positive number of Hz, got {rate_hz}")
        rec, sm = self.smoothed_states()
        filt = np.flatnonzero(rec[:, fk.REC_KIND] != fk.K_BOOT)
        if filt.size == 0:
            return pd.DataFrame(columns=list(forward.columns) if forward is not None else None)
        t0, t1 = rec[filt[0], fk.REC_T], rec[filt[-1], fk.REC_T]
        ks = np.arange(math.ceil(t0 * rate_hz - 1e-9), math.floor(t1 * rate_hz + 1e-9) + 1)
        times = ks / rate_hz
        states = np.zeros((times.size, fk.KF_SIZE))
        fr.interpolate_records(rec, sm, rec.shape[0], times, self.q_h, self.q_v, smoothed, states)
        j = np.clip(np.searchsorted(rec[:, fk.REC_T], times, side="right") - 1, 0, rec.shape[0] - 1)
        j1 = np.minimum(j + 1, rec.shape[0] - 1)
        static = (rec[j, fk.REC_STATIC] != 0.0) & (rec[j1, fk.REC_STATIC] != 0.0)
        # floor between fixes: the smaller of the neighbouring fixes' sigmas
        floor = np.fmin(rec[j, fk.REC_SIG], rec[j1, fk.REC_SIG])
        df = pd.DataFrame({c: np.full(times.size, np.nan) for c in FLOAT_COLUMNS})
        df["t"] = times
        df.insert(13, "static", static)
        source = np.where(static, "lowpass", "dr").astype(object)
        if forward is not None and len(forward):
            ft = forward["t"].to_numpy(float)
            at = np.searchsorted(ft, times)
            hit = (at < ft.size) & (ft[np.minimum(at, ft.size - 1)] == times)
            source[hit] = forward["source"].astype(str).to_numpy()[at[hit]]
        df["source"] = source
        self._write_states(df, states, np.isfinite(states[:, fk.AX_N]), static, floor)
        df = df.loc[np.isfinite(states[:, fk.AX_N])].reset_index(drop=True)
        if forward is not None:
            df.attrs = dict(forward.attrs)
        return df

    def _write_states(
        self, df: pd.DataFrame, x: FloatArray, use: np.ndarray, static: np.ndarray, floor: FloatArray
    ) -> None:
        """Position, velocity, sigma and geodetic columns of rows ``use`` from states ``x`` (``kf`` layout).

        The reported per-axis sigma is at least ``floor`` (m; NaN: no floor), the fixes' own
        (module docstring, "Reported uncertainty of the offline outputs").
        """
        if self.frame is None or not use.any():
            return
        n, e, d = x[use, fk.AX_N], x[use, fk.AX_E], x[use, fk.AX_D]
        st = static[use]
        vel = {
            c: np.where(st, 0.0, x[use, a + 1])
            for c, a in (("vn", fk.AX_N), ("ve", fk.AX_E), ("vd", fk.AX_D))
        }
        has_d = np.isfinite(df.loc[use, "down"].to_numpy(float)) | (x[use, fk.AX_D + 2] < 1e10)
        f = self.frame
        df.loc[use, "north"] = n
        df.loc[use, "east"] = e
        df.loc[use, "down"] = np.where(has_d, d, np.nan)
        df.loc[use, "lat"] = f.lat0_deg + n / f.k_n
        df.loc[use, "lon"] = f.lon0_deg + e / f.k_e
        df.loc[use, "height"] = np.where(has_d, f.h0_m - d, np.nan)
        df.loc[use, "vn"] = vel["vn"]
        df.loc[use, "ve"] = vel["ve"]
        df.loc[use, "vd"] = np.where(has_d, vel["vd"], np.nan)
        fl = np.nan_to_num(floor[use], nan=0.0)
        df.loc[use, "std_north"] = np.maximum(np.sqrt(x[use, fk.AX_N + 2]), fl)
        df.loc[use, "std_east"] = np.maximum(np.sqrt(x[use, fk.AX_E + 2]), fl)
