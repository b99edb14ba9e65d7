"""NMEA 0183 reader: sentences to GNSS epochs.

Sentences are decoded by `pynmeagps <https://github.com/semuconsulting/pynmeagps>`_, the
reference parser. The four sentence types that make up almost every byte of a real log (GGA,
RMC, GSA, VTG) also have a fast decoder, :func:`decode_fast`, written to give exactly what
pynmeagps gives (tested sentence by sentence on the whole gpsd corpus); it is what makes a day
of 1 Hz NMEA ingest in a few seconds. GNS, GLL and ZDA always go through pynmeagps.

Input units
-----------
The unit of accounting is the *fragment*. Each text line (split on ``\\n``; ``\\r`` and blanks
around it are stripped) is cut before every ``$`` and before every ``!`` that is followed by two
upper-case letters (AIS encapsulation, ``!AIVDM``). Then:

* a blank line is not a unit;
* a line starting with ``#`` is one unit, ignored as ``"comment"`` (gpsd log headers);
* a line holding only a number is one unit, a device timestamp (record ``"timestamp"``);
* a leading device timestamp ``12.345,`` / ``12345 `` / ``12.3<TAB>`` before the first ``$``
  is part of the line's first sentence, not a unit of its own;
* any other non-blank text before the first ``$``/``!`` is one unit, skipped as garbage;
* every piece starting at ``$``/``!`` is one unit (a sentence candidate).

So ``records + ignored + skipped == units`` where ``units`` can be counted with a regular
expression over the raw bytes (the tests do exactly that).

Sentence candidates are classified as

* ``[$!]ADDRESS,fields*hh`` with the right checksum (hex digits of either case): decoded.
  Used types (GGA, RMC, GSA, VTG, GNS, GLL, ZDA, any talker) become parts of an epoch and are
  counted under ``records`` by type without talker (``"GGA"``); types pynmeagps knows but
  iotnav does not use (GSV, TXT, GST, ``$PUBX``, ``!AIVDM`` ...) are counted under
  ``ignored`` (``"GSV"``, ``"PUBX"``, ``"VDM"``); types pynmeagps does not know are skipped as
  :attr:`SkipReason.UNKNOWN_SENTENCE`.
* wrong checksum: :attr:`SkipReason.BAD_CHECKSUM`.
* a well-formed address but no ``*hh``: :attr:`SkipReason.TRUNCATED`. Sentences without a
  checksum are *not* used: in real logs they are nearly always lines cut by a buffer overrun or
  the end of the capture, and their last field cannot be trusted.
* anything else (``$&bTXT``, binary that happens to contain ``$``): :attr:`SkipReason.GARBAGE`.
* fields that do not convert (``XXXXX`` where a number is due) or non-ASCII bytes:
  :attr:`SkipReason.MALFORMED`; latitude beyond +-90 or longitude beyond +-180:
  :attr:`SkipReason.OUT_OF_RANGE`; NaN/inf written in a number field: :attr:`SkipReason.NAN_FIELD`.

Bytes after a valid ``*hh`` up to the next ``$`` (rare; binary run-ons) do not invalidate the
sentence; their number is added to the report notes.

Epochs (fix cycles)
-------------------
:class:`NmeaEpochAssembler` groups sentences the way gpsd does: a sentence that carries a time
of day (GGA, RMC, GNS, GLL, ZDA with a non-empty time field) opens a new cycle when its time
differs from the current cycle's; a sentence without a time (GSA, VTG, or a timed type whose
time field is empty) joins the current cycle, unless that cycle already holds a sentence of the
same type (GSA excepted: one per constellation), in which case it opens a new, untimed cycle. A cycle that holds at
least one fix sentence (GGA, RMC, GNS, GLL) becomes one row of the GNSS table
(:data:`iotnav.io.schema.GNSS_COLUMNS`); cycles with no fix sentence (a lone ZDA, GSA or VTG)
give no row: ZDA still sets the date (record), the others are counted as ignored.

Field precedence inside a cycle: position from GGA, then GNS, RMC, GLL; altitude and geoid
separation from GGA then GNS (``height_m = alt_msl_m + geoid_sep_m``, NaN when the geoid
separation field is empty; iotnav applies no geoid model); speed and course from RMC, then VTG
(knots, else km/h); DOPs from the first GSA carrying them (HDOP falls back to GGA/GNS); satellites
used = GGA/GNS count, else the union of the GSA PRN lists keyed by constellation (NMEA 4.10
system id, else the talker, else the PRN range of ``GN`` sentences).
``mode`` follows gpsd: GSA's fix type when a GSA is in the cycle; else GGA (quality 0 -> 1 no
fix, else 3 with an altitude, 2 without); else GNS (all mode letters ``N`` -> 1); else RMC/GLL
(status ``V`` or mode ``N`` -> 1, else 2). ``valid`` is GGA quality > 0, else RMC/GLL status
``A`` with a mode other than ``N``, else a GNS mode other than all ``N`` -- and a position.
A cycle that is not valid keeps its row but no position (lat/lon/heights NaN): receivers fill
those fields with the last, a default or a zero position, and gpsd does not report them either.
``course_valid`` is False when the course field is empty or the receiver flags the fix invalid
(RMC status ``V``, mode ``N``).

Time
----
The date comes from RMC or ZDA. The assembler keeps the current date and moves it forward when
the time of day wraps (a time more than 12 h earlier than the previous cycle's: midnight; a time
more than 12 h later: a cycle from before midnight, the date goes back one day). ``utc`` is NaN
until a date is known. With clock ``"utc"`` (plain NMEA), ``t`` is the UTC time; cycles before
the first date get ``t`` extrapolated back from the first dated cycle over the unwrapped time of
day (their ``utc`` stays NaN); when no date is ever seen ``t`` is the unwrapped seconds of day
and the report says so. With clock ``"device"`` (timestamped logs) ``t`` is the device timestamp
of the *first* sentence of the cycle. Rows whose ``t`` does not increase past the last kept row
are dropped and their sentences counted as :attr:`SkipReason.NON_MONOTONIC`; rows with no usable
``t`` as :attr:`SkipReason.NO_TIME`.

Modules: one sentence is decoded in :mod:`iotnav.io.nmea_sentence`, cycles become epochs in
:mod:`iotnav.io.nmea_epochs`; this module frames the bytes into units and runs the reader
(public names re-exported here).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from iotnav.io.errors import IngestError
from iotnav.io.log import Clock, Part
from iotnav.io.nmea_epochs import (
    NmeaEpochAssembler,
)
from iotnav.io.nmea_sentence import (
    _USED_KINDS,
    KNOT_MPS,
    Sentence,
    _kind_label,
    _known_type,
    _split_address,
    decode_fast,
    decode_sentence,
    sentence_from_message,
)
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.timeutil import guess_time_unit, unit_scale

__all__ = [
    "KNOT_MPS",
    "NmeaEpochAssembler",
    "Sentence",
    "decode_fast",
    "decode_sentence",
    "read_nmea",
    "sentence_from_message",
]

_NAN = math.nan
_FAST_KINDS = frozenset(("GGA", "RMC", "GSA", "VTG"))

# Split a line before every '$' and every '!' followed by two capitals (AIS encapsulation).
_SPLIT_RE = re.compile(rb"\$|![A-Z]{2}")
_SENTENCE_RE = re.compile(rb"[$!]([A-Za-z0-9]{2,15})(,[^*]*)?\*([0-9A-Fa-f]{2})")
_ADDRESS_RE = re.compile(rb"[$!][A-Z0-9]{2,15}(,|\s*$)")
_TS_PREFIX_RE = re.compile(rb"\s*([+-]?\d+(?:\.\d*)?)\s*[,;\t ]\s*$")
_TS_LINE_RE = re.compile(rb"\s*[+-]?\d+(?:\.\d*)?\s*")
_HEX = frozenset(b"0123456789abcdefABCDEF")


# --------------------------------------------------------------------------------------------
# Framing and the reader
# --------------------------------------------------------------------------------------------


def _load(source: str | os.PathLike[str] | bytes, name: str | None) -> tuple[bytes, str]:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source), name or "<bytes>"
    path = Path(source)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise IngestError(name or str(path), f"cannot read file: {err.strerror or err}") from err
    return data, name or str(path)


class _Framer:
    """Line/fragment framing shared by :func:`read_nmea` and the UBX reader."""

    def __init__(self, report: FileReport, assembler: NmeaEpochAssembler) -> None:
        self.report = report
        self.asm = assembler
        self.units = 0
        self.well_formed = 0
        self.trailing = 0
        self.cumxor = b""

    def set_data(self, data: bytes) -> None:
        """Precompute ``cumxor[i] = data[0] ^ ... ^ data[i]`` for vectorised checksums."""
        if data:
            arr = np.frombuffer(data, dtype=np.uint8)
            self.cumxor = np.bitwise_xor.accumulate(arr).tobytes()

    def sentence(self, frag: bytes, t_raw: float, unit_no: int, offset: int = -1) -> None:
        """Classify and decode one ``$``/``!`` fragment (already stripped).

        ``offset`` is the fragment's position in the bytes given to :meth:`set_data`, when known:
        the checksum then comes from the cumulative XOR table instead of a Python loop.
        """
        rep = self.report
        m = _SENTENCE_RE.match(frag)
        if m is None:
            if _ADDRESS_RE.match(frag):
                rep.skip(SkipReason.TRUNCATED, unit_no, frag.decode("latin-1"))
            else:
                rep.skip(SkipReason.GARBAGE, unit_no, frag.decode("latin-1"))
            return
        self.well_formed += 1
        end = m.end()
        if end != len(frag):
            self.trailing += 1
        if offset >= 0:
            cx = self.cumxor
            ck = cx[offset + end - 4] ^ cx[offset]
        else:
            ck = 0
            for b in frag[1 : end - 3]:
                ck ^= b
        if ck != int(m.group(3), 16):
            rep.skip(SkipReason.BAD_CHECKSUM, unit_no, frag.decode("latin-1"))
            return
        try:
            text = frag[:end].decode("ascii")
        except UnicodeDecodeError:
            rep.skip(SkipReason.MALFORMED, unit_no, frag.decode("latin-1"))
            return
        address = m.group(1).decode("ascii")
        talker, msgid = _split_address(address)
        if talker != "P" and msgid in _USED_KINDS:
            low = text.lower()
            if "nan" in low or "inf" in low:  # float() would accept them
                rep.skip(SkipReason.NAN_FIELD, unit_no, text)
                return
        if talker != "P" and msgid in _FAST_KINDS:
            fields = text[len(address) + 2 : -3].split(",")
            try:
                s: Sentence | None = decode_fast(talker, msgid, fields)
            except ValueError:
                rep.skip(SkipReason.MALFORMED, unit_no, text)
                return
        elif talker != "P" and msgid in _USED_KINDS:
            try:
                s = decode_sentence(text)
            except ValueError:
                rep.skip(SkipReason.MALFORMED, unit_no, text)
                return
        elif _known_type(talker, msgid):
            rep.ignore(_kind_label(talker, msgid))
            return
        else:
            rep.skip(SkipReason.UNKNOWN_SENTENCE, unit_no, text)
            return
        if s is None:  # pragma: no cover - used kinds always decode to a Sentence
            rep.ignore(_kind_label(talker, msgid))
            return
        self.asm.add(s, t_raw, unit_no)


def _frame_lines(data: bytes, framer: _Framer) -> list[float]:
    """Walk the lines of ``data``; return the raw device timestamps seen."""
    rep = framer.report
    stamps: list[float] = []
    t_raw = _NAN
    unit = 0
    split = _SPLIT_RE
    framer.set_data(data)
    next_off = 0
    for raw_line in data.split(b"\n"):
        off = next_off
        next_off += len(raw_line) + 1
        line = raw_line.strip()
        if not line:
            continue
        c0 = line[0]
        if c0 == 0x24 and line.count(b"$") == 1 and b"!" not in line:  # the common case
            unit += 1
            framer.sentence(line, t_raw, unit, off + len(raw_line) - len(raw_line.lstrip()))
            continue
        if c0 == 0x23:  # '#'
            unit += 1
            rep.ignore("comment")
            continue
        dollar = line.find(b"$")
        if dollar > 0 and b"!" not in line and line.count(b"$") == 1:
            # one sentence after a device timestamp (``12.345,$GPGGA...``): what the general
            # path below does for it, with the checksum from the cumulative XOR table
            pm = _TS_PREFIX_RE.fullmatch(line, 0, dollar)
            if pm is not None:
                t_raw = float(pm.group(1))
                stamps.append(t_raw)
                unit += 1
                lead = len(raw_line) - len(raw_line.lstrip())
                framer.sentence(line[dollar:], t_raw, unit, off + lead + dollar)
                continue
        starts = [m.start() for m in split.finditer(line)]
        head = line[: starts[0]] if starts else line
        if head.strip():
            if not starts and _TS_LINE_RE.fullmatch(line):
                unit += 1
                t_raw = float(line)
                stamps.append(t_raw)
                rep.record("timestamp")
                continue
            pm = _TS_PREFIX_RE.fullmatch(head) if starts else None
            if pm is not None:
                t_raw = float(pm.group(1))
                stamps.append(t_raw)
            else:
                unit += 1
                rep.skip(SkipReason.GARBAGE, unit, head.decode("latin-1"))
        for i, a in enumerate(starts):
            b = starts[i + 1] if i + 1 < len(starts) else len(line)
            unit += 1
            framer.sentence(line[a:b].strip(), t_raw, unit)
    framer.units = unit
    return stamps


def read_nmea(
    source: str | os.PathLike[str] | bytes,
    *,
    time_unit: str | None = None,
    name: str | None = None,
) -> Part:
    """Read an NMEA 0183 log (plain or with device timestamps) into GNSS epochs.

    Parameters
    ----------
    source : str, os.PathLike or bytes
        A file path or the raw bytes.
    time_unit : {"s", "ms", "us", "ns"}, optional
        Unit of device timestamps, when the log has them; guessed from their steps
        (:func:`iotnav.io.timeutil.guess_time_unit`) when omitted.
    name : str, optional
        Name used in the report and errors (defaults to the path, or ``"<bytes>"``).

    Returns
    -------
    Part
        ``gnss`` epochs (one row per fix cycle; see the module docstring for the rules),
        clock ``"utc"`` for plain NMEA, ``"device"`` when lines carry device timestamps
        (prefix ``12.345,$GPGGA...`` / ``12345 $GPGGA...`` / tab, or timestamp-only lines
        applying to the sentences that follow). The report counts every unit (module docstring).

    Raises
    ------
    IngestError
        When the file cannot be read or holds no NMEA sentence at all.
    """
    data, label = _load(source, name)
    rep = FileReport(path=label, format="nmea")
    asm = NmeaEpochAssembler(rep, source="nmea")
    framer = _Framer(rep, asm)
    stamps = _frame_lines(data, framer)
    rep.units = framer.units
    if framer.well_formed == 0:
        raise IngestError(
            label,
            "no NMEA 0183 sentences found; expected lines like '$GPGGA,...*hh' "
            "(optionally prefixed by a device timestamp)",
        )
    if framer.trailing:
        rep.notes.append(f"{framer.trailing} sentences had bytes after their checksum (ignored)")
    clock: Clock = "utc"
    scale = 1.0
    if stamps:
        clock = "device"
        rep.format = "nmea-timestamped"
        unit = time_unit or guess_time_unit(np.asarray(stamps, dtype=float))
        scale = unit_scale(unit)
        how = "given" if time_unit else "detected"
        rep.notes.append(f"device timestamps in {unit} ({how}); epoch t = first sentence of the cycle")
    gnss = asm.finish(clock=clock, t_scale=scale)
    return Part.make(rep, clock, gnss=gnss)
