"""NMEA 0183 fix cycles: sentences grouped into GNSS epochs (part of :mod:`iotnav.io.nmea`).

:class:`NmeaEpochAssembler` groups decoded sentences into fix cycles the way gpsd does and
builds one row of :data:`iotnav.io.schema.GNSS_COLUMNS` per cycle that holds a fix sentence;
the grouping, field precedence, validity and time rules are stated in :mod:`iotnav.io.nmea`
("Epochs (fix cycles)" and "Time").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd
from pynmeagps import NMEAMessage

from iotnav.io.log import Clock
from iotnav.io.nmea_sentence import Sentence, _kind_label, _system_of_prn, sentence_from_message
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.schema import GNSS_COLUMNS, coerce, empty_table

_NAN = math.nan
_FIX_KINDS = ("GGA", "GNS", "RMC", "GLL")
_HALF_DAY = 43200.0
_DAY = 86400.0


# --------------------------------------------------------------------------------------------
# Epoch assembly
# --------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Cycle:
    tod: float
    t_device: float
    parts: dict[str, Sentence] = field(default_factory=dict)
    gsa: list[Sentence] = field(default_factory=list)
    units: list[tuple[str, int]] = field(default_factory=list)  # (kind, unit number)


class NmeaEpochAssembler:
    """Group decoded sentences into fix cycles and build GNSS epoch rows.

    Feed sentences in stream order with :meth:`add`; :meth:`finish` returns the epochs table
    and counts every sentence in the report (records, ignored, or skipped with a reason). The
    grouping, precedence and time rules are in the module docstring.

    Parameters
    ----------
    report : FileReport
        Where counts go.
    source : str
        Value of the ``source`` column.
    """

    def __init__(self, report: FileReport, source: str = "nmea") -> None:
        self.report = report
        self.source = source
        self._cur: _Cycle | None = None
        self._rows: list[dict[str, Any]] = []
        self._row_units: list[list[tuple[str, int]]] = []
        self._day_index = 0
        self._date: int | None = None
        self._last_tod: float | None = None

    # -- input ------------------------------------------------------------------------------
    def add(self, msg: Sentence | NMEAMessage, t_device: float = _NAN, unit_no: int = -1) -> None:
        """Add one sentence.

        Parameters
        ----------
        msg : Sentence or pynmeagps.NMEAMessage
            A decoded sentence (unused types are counted as ignored).
        t_device : float
            Device time of the sentence in the caller's unit (NaN when none); scaled in
            :meth:`finish`.
        unit_no : int
            Input unit number (for examples in the report).
        """
        if isinstance(msg, NMEAMessage):
            s = sentence_from_message(msg)
            if s is None:
                self.report.ignore(_kind_label(msg.talker, msg.msgID))
                return
        else:
            s = msg
        bad = self._check(s)
        if bad is not None:
            self.report.skip(bad, unit_no, f"{s.talker}{s.kind} lat={s.lat_deg} lon={s.lon_deg}")
            return
        cur = self._cur
        timed = s.tod == s.tod
        if cur is not None:
            if timed:
                if cur.tod == s.tod:
                    self._merge(cur, s, unit_no)
                    return
                if cur.tod != cur.tod and s.kind not in cur.parts:
                    cur.tod = s.tod
                    self._merge(cur, s, unit_no)
                    return
            elif s.kind == "GSA" or s.kind not in cur.parts:
                self._merge(cur, s, unit_no)
                return
            self._close(cur)
        self._cur = _Cycle(tod=s.tod, t_device=t_device)
        self._merge(self._cur, s, unit_no)

    @staticmethod
    def _check(s: Sentence) -> SkipReason | None:
        # NaN/inf written out ("nan", "inf") are refused by the framer before decoding.
        if abs(s.lat_deg) > 90.0 or abs(s.lon_deg) > 180.0:
            return SkipReason.OUT_OF_RANGE
        if (s.lat_deg != s.lat_deg) != (s.lon_deg != s.lon_deg):
            return SkipReason.NAN_FIELD  # one coordinate without the other
        return None

    @staticmethod
    def _merge(cur: _Cycle, s: Sentence, unit_no: int) -> None:
        if s.kind == "GSA":
            cur.gsa.append(s)
        elif s.kind not in cur.parts:
            cur.parts[s.kind] = s
        cur.units.append((s.kind, unit_no))

    # -- cycle to row -----------------------------------------------------------------------
    def _close(self, cur: _Cycle) -> None:
        self._cur = None
        tod = cur.tod
        explicit = -1
        for k in ("RMC", "ZDA"):
            p = cur.parts.get(k)
            if p is not None and p.date_days >= 0:
                explicit = p.date_days
                break
        if tod == tod:
            if self._last_tod is not None:
                if tod < self._last_tod - _HALF_DAY:
                    self._day_index += 1
                    if self._date is not None:
                        self._date += 1
                elif tod > self._last_tod + _HALF_DAY:
                    self._day_index -= 1
                    if self._date is not None:
                        self._date -= 1
            self._last_tod = tod
            if explicit >= 0:
                self._date = explicit
        has_fix = not cur.parts.keys().isdisjoint(_FIX_KINDS)
        if not has_fix:
            for kind, _unit in cur.units:
                if kind == "ZDA":
                    self.report.record(kind)
                else:
                    self.report.ignore(kind)
            return
        utc = self._date * _DAY + tod if (self._date is not None and tod == tod) else _NAN
        tod_unwrapped = self._day_index * _DAY + tod
        row = self._row(cur)
        row["utc"] = utc
        row["_tod_unwrapped"] = tod_unwrapped
        row["_t_device"] = cur.t_device
        self._rows.append(row)
        self._row_units.append(cur.units)

    def _row(self, cur: _Cycle) -> dict[str, Any]:
        p = cur.parts
        gga, gns, rmc, gll, vtg = p.get("GGA"), p.get("GNS"), p.get("RMC"), p.get("GLL"), p.get("VTG")
        lat = lon = _NAN
        for s in (gga, gns, rmc, gll):
            if s is not None and s.lat_deg == s.lat_deg:
                lat, lon = s.lat_deg, s.lon_deg
                break
        alt = sep = _NAN
        for s in (gga, gns):
            if s is not None and s.alt_msl_m == s.alt_msl_m:
                alt, sep = s.alt_msl_m, s.geoid_sep_m
                break
        has_pos = lat == lat
        # validity and mode
        if gga is not None and gga.quality >= 0:
            valid = gga.quality > 0
        elif rmc is not None and rmc.status:
            valid = rmc.status == "A" and rmc.pos_mode != "N"
        elif gns is not None and gns.pos_mode:
            valid = gns.pos_mode.strip("N") != ""
        elif gll is not None and gll.status:
            valid = gll.status == "A" and gll.pos_mode != "N"
        else:
            valid = False
        valid = valid and has_pos
        mode = 0
        nav = [g.nav_mode for g in cur.gsa if g.nav_mode in (1, 2, 3)]
        if nav:
            mode = max(nav)
        elif gga is not None and gga.quality >= 0:
            mode = 1 if gga.quality == 0 else (3 if alt == alt else 2)
        elif gns is not None and gns.pos_mode:
            mode = 1 if gns.pos_mode.strip("N") == "" else (3 if alt == alt else 2)
        else:
            for s in (rmc, gll):
                if s is not None and s.status:
                    mode = 1 if (s.status != "A" or s.pos_mode == "N") else 2
                    break
        # satellites and DOPs
        num_sv = -1
        for s in (gga, gns):
            if s is not None and s.num_sv >= 0:
                num_sv = s.num_sv
                break
        if num_sv < 0 and cur.gsa:
            used = {(g.system or _system_of_prn(prn), prn) for g in cur.gsa for prn in g.prns if prn > 0}
            num_sv = len(used)
        pdop = next((g.pdop for g in cur.gsa if g.pdop == g.pdop), _NAN)
        vdop = next((g.vdop for g in cur.gsa if g.vdop == g.vdop), _NAN)
        hdop = next((g.hdop for g in cur.gsa if g.hdop == g.hdop), _NAN)
        if hdop != hdop:
            for s in (gga, gns):
                if s is not None and s.hdop == s.hdop:
                    hdop = s.hdop
                    break
        # speed and course
        speed = course = _NAN
        course_valid = False
        for s in (rmc, vtg):
            if s is None:
                continue
            if speed != speed and s.speed_mps == s.speed_mps:
                speed = s.speed_mps
            if course != course and s.course_deg == s.course_deg:
                course = s.course_deg
                flagged_bad = s.pos_mode == "N" or (s.kind == "RMC" and s.status != "A")
                course_valid = not flagged_bad
        course_rad = math.radians(course % 360.0) if course == course else _NAN
        if course_rad >= 2 * math.pi:
            course_rad = 0.0
        if not valid:
            # Receivers fill the fields of a no-fix cycle with the last, a default or a zero
            # position (SkyTraq: 0 N 0 E); gpsd reports no position then, nor does iotnav.
            lat = lon = alt = sep = _NAN
        return {
            "lat_deg": lat,
            "lon_deg": lon,
            "height_m": alt + sep,
            "alt_msl_m": alt,
            "geoid_sep_m": sep,
            "quality": gga.quality if gga is not None else -1,
            "mode": mode,
            "num_sv": num_sv,
            "pdop": pdop,
            "hdop": hdop,
            "vdop": vdop,
            "speed_mps": speed,
            "course_rad": course_rad,
            "course_valid": course_valid,
            "valid": valid,
        }

    # -- output -----------------------------------------------------------------------------
    def finish(
        self,
        clock: Clock = "utc",
        t_scale: float = 1.0,
        drop_utc: npt.ArrayLike | None = None,
        drop_tol_s: float = 0.005,
        drop_label: str = "duplicate of UBX NAV-PVT",
    ) -> pd.DataFrame:
        """Close the last cycle, count every sentence and return the epochs table.

        Parameters
        ----------
        clock : {"utc", "device"}
            ``utc``: ``t`` is UTC (see module docstring); ``device``: ``t`` is the device time
            of each cycle's first sentence times ``t_scale``.
        t_scale : float
            Seconds per device-time tick given to :meth:`add`.
        drop_utc : array_like, optional
            UTC times (s) of epochs already known from a better source; cycles within
            ``drop_tol_s`` of one are dropped and their sentences counted as ignored under
            ``"<type> (<drop_label>)"``.
        drop_tol_s : float
            Tolerance of that match, s.
        drop_label : str
            Text of the ignored kind.

        Returns
        -------
        pandas.DataFrame
            GNSS epochs, :data:`iotnav.io.schema.GNSS_COLUMNS`, ``t`` strictly increasing.
        """
        if self._cur is not None:
            self._close(self._cur)
        rows, units = self._rows, self._row_units
        self._rows, self._row_units = [], []
        rep = self.report
        if not rows:
            return empty_table(GNSS_COLUMNS)
        df = pd.DataFrame(rows)
        utc = df["utc"].to_numpy(dtype=float)
        if clock == "device":
            t = df["_t_device"].to_numpy(dtype=float) * t_scale
        else:
            unwrapped = df["_tod_unwrapped"].to_numpy(dtype=float)
            dated = np.nonzero(np.isfinite(utc))[0]
            if dated.size:
                t = utc.copy()
                i0 = dated[0]
                before = np.arange(len(t)) < i0
                t[before] = utc[i0] + (unwrapped[before] - unwrapped[i0])
                # later cycles with no date known (cannot happen once a date is set) keep NaN
            else:
                t = unwrapped
                rep.notes.append(
                    "no date (RMC/ZDA) in the NMEA: t is seconds of day (unwrapped over midnight), utc is NaN"
                )
        df["t"] = t
        keep = np.ones(len(df), dtype=bool)
        drop_set = np.sort(np.asarray(drop_utc, dtype=float)) if drop_utc is not None else None
        last = -math.inf
        for i in range(len(df)):
            ti = t[i]
            # On the UTC clock, t also places cycles from before the first date.
            u = ti if clock == "utc" else utc[i]
            if drop_set is not None and drop_set.size and u == u:
                j = int(np.searchsorted(drop_set, u))
                near = [drop_set[k] for k in (j - 1, j) if 0 <= k < drop_set.size]
                if any(abs(x - u) <= drop_tol_s for x in near):
                    keep[i] = False
                    for kind, _u in units[i]:
                        rep.ignore(f"{kind} ({drop_label})")
                    continue
            if ti != ti:
                keep[i] = False
                for _kind, u in units[i]:
                    rep.skip(SkipReason.NO_TIME, u, "fix cycle without a usable time")
                continue
            if ti <= last:
                keep[i] = False
                for _kind, u in units[i]:
                    rep.skip(SkipReason.NON_MONOTONIC, u, f"cycle time {ti!r} <= previous {last!r}")
                continue
            last = ti
            for kind, _u in units[i]:
                rep.record(kind)
        df = df.loc[keep]
        df["source"] = self.source
        return coerce(df, GNSS_COLUMNS)
