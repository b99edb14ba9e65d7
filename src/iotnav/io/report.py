"""Ingest reports: what was read, what was skipped and why.

Readers never drop input silently. Every unit of input (a text line or sentence, a binary
frame, a CSV row) ends up either as a record (counted in :attr:`FileReport.records` under its
kind, e.g. ``"GGA"`` or ``"UBX NAV-PVT"`` or ``"imu"``), as ignored-on-purpose (comments, headers,
recognised sentences iotnav does not use, under :attr:`FileReport.ignored`), or as a skip counted
under a :class:`SkipReason` with the first few examples kept for the user.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any


class SkipReason(StrEnum):
    """Why a unit of input was not used."""

    BAD_CHECKSUM = "bad checksum"
    TRUNCATED = "truncated"
    UNKNOWN_SENTENCE = "unknown sentence"
    NON_MONOTONIC = "non-monotonic time"
    DUPLICATE = "duplicate"
    NAN_FIELD = "NaN field"
    OUT_OF_RANGE = "out-of-range value"
    MALFORMED = "malformed fields"
    GARBAGE = "not a record (garbage bytes)"
    NO_TIME = "no usable time"


MAX_EXAMPLES = 3


@dataclass
class FileReport:
    """Counts for one input file.

    Attributes
    ----------
    path : str
        The file as given.
    format : str
        Detected or given format (``nmea``, ``nmea-timestamped``, ``ubx``, ``rtklib-pos``,
        ``imu-csv``, ``gnsslogger``, ``sensor-logger`` ...).
    units : int
        Number of input units examined (text lines for text formats, frames for binary).
    records : collections.Counter
        Used records by kind.
    ignored : collections.Counter
        Recognised and deliberately not used (comments, headers, unused sentence types), by kind.
    skipped : collections.Counter
        Unusable input by :class:`SkipReason` value.
    examples : dict
        Reason -> up to :data:`MAX_EXAMPLES` ``(line_or_offset, text)`` pairs.
    notes : list of str
        Human-readable remarks (detected units, time base, offsets).
    time_faults : collections.Counter
        Repaired time faults by kind (``wrap``, ``reset``, ``week_rollover``;
        :mod:`iotnav.io.timefaults`): the records are kept, their times corrected.
    """

    path: str
    format: str
    units: int = 0
    records: Counter[str] = field(default_factory=Counter)
    ignored: Counter[str] = field(default_factory=Counter)
    skipped: Counter[str] = field(default_factory=Counter)
    examples: dict[str, list[tuple[int, str]]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    time_faults: Counter[str] = field(default_factory=Counter)

    def record(self, kind: str, n: int = 1) -> None:
        """Count ``n`` used records of ``kind``."""
        self.records[kind] += n

    def ignore(self, kind: str, n: int = 1) -> None:
        """Count ``n`` deliberately unused units of ``kind``."""
        self.ignored[kind] += n

    def skip(self, reason: SkipReason | str, where: int = -1, text: str = "", n: int = 1) -> None:
        """Count ``n`` skipped units for ``reason``, keeping the first examples.

        Parameters
        ----------
        reason : SkipReason or str
            Why the unit is unusable.
        where : int
            1-based line number or byte offset of the unit, -1 if unknown.
        text : str
            The offending text (shortened to 120 characters).
        n : int
            How many units this call accounts for.
        """
        key = str(reason)
        self.skipped[key] += n
        ex = self.examples.setdefault(key, [])
        if len(ex) < MAX_EXAMPLES:
            ex.append((where, text[:120]))

    @property
    def n_records(self) -> int:
        """Total used records."""
        return sum(self.records.values())

    @property
    def n_skipped(self) -> int:
        """Total skipped units."""
        return sum(self.skipped.values())

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form of the report."""
        return {
            "path": self.path,
            "format": self.format,
            "units": self.units,
            "records": dict(self.records),
            "ignored": dict(self.ignored),
            "skipped": dict(self.skipped),
            "examples": {k: [list(e) for e in v] for k, v in self.examples.items()},
            "notes": list(self.notes),
            **({"time_faults": dict(self.time_faults)} if self.time_faults else {}),
        }


@dataclass
class IngestReport:
    """Reports of every file merged into one :class:`iotnav.io.Log`, plus timeline facts."""

    files: list[FileReport] = field(default_factory=list)
    timeline: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form of the report."""
        return {"files": [f.to_dict() for f in self.files], "timeline": dict(self.timeline)}
