"""The merged timeline: :class:`Part` (what one reader returns) and :class:`Log` (all merged).

Clocks
------
Each part says which clock its ``t`` column is on:

``device``
    the logger's own clock (a device timestamp in the file, converted to seconds);
``utc``
    UTC seconds since 1970-01-01 (files with no device time: plain NMEA with a date, UBX,
    RTKLIB ``.pos`` after GPST -> UTC, IMU logs time-tagged to GNSS time, phone logs).

:func:`merge` puts every part on one axis. Parts on the same clock merge as they are. When
GNSS is on the device clock and another part is on UTC, the UTC part is moved to device time
with the offset estimated from the GNSS epochs (``utc - t``); the reverse case (GNSS on UTC,
IMU on a device clock with no link) cannot be aligned and raises an error that says so unless
an explicit offset is given.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pandas as pd

from iotnav.io.errors import IngestError
from iotnav.io.report import FileReport, IngestReport, SkipReason
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, MAG_COLUMNS, coerce, empty_table
from iotnav.io.timefaults import rollover_shift

Clock = Literal["device", "utc"]


@dataclass
class Part:
    """What a reader returns for one file.

    Attributes
    ----------
    gnss, imu, mag : pandas.DataFrame
        Tables in the schemas of :mod:`iotnav.io.schema` (possibly empty).
    clock : {"device", "utc"}
        The clock of every ``t`` column in this part.
    report : FileReport
        Counts of what was read and skipped.
    """

    gnss: pd.DataFrame
    imu: pd.DataFrame
    mag: pd.DataFrame
    clock: Clock
    report: FileReport

    @classmethod
    def make(
        cls,
        report: FileReport,
        clock: Clock,
        gnss: pd.DataFrame | None = None,
        imu: pd.DataFrame | None = None,
        mag: pd.DataFrame | None = None,
    ) -> Part:
        """Build a part, coercing each given table to its schema and filling absent ones."""
        return cls(
            gnss=coerce(gnss, GNSS_COLUMNS) if gnss is not None else empty_table(GNSS_COLUMNS),
            imu=coerce(imu, IMU_COLUMNS) if imu is not None else empty_table(IMU_COLUMNS),
            mag=coerce(mag, MAG_COLUMNS) if mag is not None else empty_table(MAG_COLUMNS),
            clock=clock,
            report=report,
        )


@dataclass
class Log:
    """GNSS epochs, IMU and magnetometer samples on one device-time axis.

    Attributes
    ----------
    gnss, imu, mag : pandas.DataFrame
        Sorted by ``t`` (device time, s), strictly increasing within each table.
    utc_offset_s : float
        ``utc = t + utc_offset_s`` (NaN when no GNSS epoch carries a date).
    report : IngestReport
        Per-file reports and timeline facts (span, rates, gaps, offset).
    """

    gnss: pd.DataFrame = field(default_factory=lambda: empty_table(GNSS_COLUMNS))
    imu: pd.DataFrame = field(default_factory=lambda: empty_table(IMU_COLUMNS))
    mag: pd.DataFrame = field(default_factory=lambda: empty_table(MAG_COLUMNS))
    utc_offset_s: float = float("nan")
    report: IngestReport = field(default_factory=IngestReport)

    def to_frame(self) -> pd.DataFrame:
        """One time-ordered table: a ``kind`` column (``gnss``, ``imu``, ``mag``) plus all columns.

        Returns
        -------
        pandas.DataFrame
            Rows of every table, sorted by ``t`` (stable: GNSS before IMU at equal times).
        """
        frames = []
        for kind, df in (("gnss", self.gnss), ("imu", self.imu), ("mag", self.mag)):
            if len(df):
                frames.append(df.assign(kind=kind))
        if not frames:
            return pd.DataFrame({"kind": pd.Series(dtype=object), "t": pd.Series(dtype=float)})
        out = pd.concat(frames, ignore_index=True, sort=False)
        out = out.sort_values("t", kind="stable").reset_index(drop=True)
        cols = ["t", "kind"] + [c for c in out.columns if c not in ("t", "kind")]
        return out[cols]


def estimate_utc_offset(gnss: pd.DataFrame) -> float:
    """Median of ``utc - t`` over GNSS epochs with a known date (NaN if none).

    Parameters
    ----------
    gnss : pandas.DataFrame
        GNSS epochs table.

    Returns
    -------
    float
        Offset in seconds such that ``utc = t + offset``.
    """
    if len(gnss) == 0:
        return float("nan")
    d = (gnss["utc"] - gnss["t"]).to_numpy(dtype=float)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else float("nan")


def _monotonic(df: pd.DataFrame, rep: FileReport, kind: str) -> pd.DataFrame:
    """Sort by time; drop and count rows with NaN time and exact duplicate times."""
    if len(df) == 0:
        return df
    t = df["t"].to_numpy(dtype=float)
    bad = ~np.isfinite(t)
    if bad.any():
        rep.skip(SkipReason.NO_TIME, text=f"{int(bad.sum())} {kind} rows without time", n=int(bad.sum()))
        df = df.loc[~bad]
    df = df.sort_values("t", kind="stable")
    dup = df["t"].duplicated(keep="first").to_numpy()
    if dup.any():
        rep.skip(SkipReason.DUPLICATE, text=f"{int(dup.sum())} {kind} rows repeat a time", n=int(dup.sum()))
        df = df.loc[~dup]
    return df.reset_index(drop=True)


def _gaps(t: np.ndarray, factor: float = 3.0) -> list[dict[str, float]]:
    """Gaps longer than ``factor`` times the median step."""
    if t.size < 3:
        return []
    d = np.diff(t)
    med = float(np.median(d))
    idx = np.nonzero(d > factor * max(med, 1e-9))[0]
    return [{"start": float(t[i]), "end": float(t[i + 1]), "length_s": float(d[i])} for i in idx]


def _rate(t: np.ndarray) -> float:
    if t.size < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(t)))


def _repair_times(p: Part, gnss_latency_s: float, now_utc_s: float | None) -> Part:
    """``p`` with week-rollover dates moved on and device-clock GNSS moved back by the latency."""
    if len(p.gnss) == 0:
        return p
    shift = rollover_shift(p.gnss["utc"].to_numpy(dtype=float), now_utc_s)
    if shift == 0.0 and (gnss_latency_s == 0.0 or p.clock != "device"):
        return p
    gnss = p.gnss.copy()
    imu, mag = p.imu, p.mag
    if shift:
        weeks = round(shift / (7 * 86400.0))
        gnss["utc"] = gnss["utc"] + shift
        p.report.time_faults["week_rollover"] += 1
        p.report.notes.append(
            f"GNSS dates {weeks} weeks early (GPS week rollover): moved on by {weeks} weeks"
        )
        if p.clock == "utc":
            gnss["t"] = gnss["t"] + shift
            imu = imu.assign(t=imu["t"] + shift) if len(imu) else imu
            mag = mag.assign(t=mag["t"] + shift) if len(mag) else mag
    if gnss_latency_s and p.clock == "device":
        gnss["t"] = gnss["t"] - gnss_latency_s
        p.report.notes.append(
            f"GNSS arrival stamps moved back by the latency {gnss_latency_s} s to the fix epoch"
        )
    return Part(gnss=gnss, imu=imu, mag=mag, clock=p.clock, report=p.report)


def merge(
    parts: list[Part],
    imu_utc_offset_s: float | None = None,
    gnss_latency_s: float = 0.0,
    now_utc_s: float | None = None,
) -> Log:
    """Merge reader outputs onto one device-time axis.

    Two time faults are repaired here, once for every reader (:mod:`iotnav.io.timefaults`):
    dates that fell back by a 1024-week GPS rollover are moved on (the whole part when its
    clock is UTC; counted as ``week_rollover`` in the part's report), and GNSS epochs stamped
    at their arrival on the device clock are moved back by ``gnss_latency_s`` to their fix
    epoch (parts on UTC carry the epoch's own time and are left alone).

    Parameters
    ----------
    parts : list of Part
        Reader outputs.
    imu_utc_offset_s : float, optional
        Explicit ``utc - t`` of device-clock parts, used when it cannot be estimated from GNSS.
    gnss_latency_s : float
        Fix epoch to arrival latency of device-time-stamped GNSS epochs, s (a u-blox at 10 Hz
        delivers a fix about 0.1-0.2 s after its epoch); 0 keeps the stamps.
    now_utc_s : float, optional
        The present, UTC s (the system clock by default), bounding the week-rollover repair.

    Returns
    -------
    Log
        Sorted tables, the UTC offset, and a report with span, rates and gaps per table.

    Raises
    ------
    IngestError
        When device-clock and UTC parts cannot be aligned.
    """
    parts = [_repair_times(p, gnss_latency_s, now_utc_s) for p in parts]
    report = IngestReport(files=[p.report for p in parts])
    device_gnss = [p.gnss for p in parts if p.clock == "device" and len(p.gnss)]
    offset = float("nan")
    if device_gnss:
        offset = estimate_utc_offset(pd.concat(device_gnss, ignore_index=True))
    if imu_utc_offset_s is not None:
        offset = float(imu_utc_offset_s)
    clocks = {p.clock for p in parts if len(p.gnss) + len(p.imu) + len(p.mag)}
    target: Clock = "device" if "device" in clocks else "utc"
    if "device" in clocks and "utc" in clocks and not np.isfinite(offset):
        names = ", ".join(p.report.path for p in parts)
        raise IngestError(
            names,
            "some files carry device time and others UTC/GPS time, and no GNSS epoch with a "
            "date links the two clocks; give the offset explicitly (utc - device time, s)",
        )
    tables: dict[str, list[pd.DataFrame]] = {"gnss": [], "imu": [], "mag": []}
    for p in parts:
        shift = -offset if (p.clock == "utc" and target == "device") else 0.0
        for kind in tables:
            df = getattr(p, kind)
            if len(df):
                df = df.copy()
                df["t"] = df["t"] + shift
                tables[kind].append(df)
    schemas = {"gnss": GNSS_COLUMNS, "imu": IMU_COLUMNS, "mag": MAG_COLUMNS}
    merged: dict[str, pd.DataFrame] = {}
    tl_rep = FileReport(path="<timeline>", format="merge")
    for kind, frames in tables.items():
        df = pd.concat(frames, ignore_index=True) if frames else empty_table(schemas[kind])
        merged[kind] = coerce(_monotonic(df, tl_rep, kind), schemas[kind])
    if target == "utc":
        offset = 0.0 if any(len(merged[k]) for k in merged) else float("nan")
    log = Log(gnss=merged["gnss"], imu=merged["imu"], mag=merged["mag"], utc_offset_s=offset, report=report)
    tl: dict[str, object] = {"clock": target, "utc_offset_s": offset}
    for kind in ("gnss", "imu", "mag"):
        t = merged[kind]["t"].to_numpy(dtype=float)
        if t.size:
            tl[kind] = {
                "count": int(t.size),
                "start": float(t[0]),
                "end": float(t[-1]),
                "span_s": float(t[-1] - t[0]),
                "rate_hz": _rate(t),
                "gaps": _gaps(t),
            }
    if tl_rep.n_skipped:
        report.files.append(tl_rep)
    report.timeline = tl
    return log
