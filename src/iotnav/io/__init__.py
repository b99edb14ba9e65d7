"""Reading tracker logs: NMEA 0183, UBX, RTKLIB ``.pos``, IMU CSV, phone logs; merging; export.

The entry points are :func:`detect_format`, :func:`read_file` (one file -> :class:`Part`) and
:func:`ingest` (many files -> one :class:`Log` on a single device-time axis, with an
:class:`IngestReport`). Readers never crash on bad bytes: they raise :class:`IngestError`
naming the file and what was expected, or skip and count.
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from iotnav.io.errors import IngestError
from iotnav.io.log import Log, Part, merge
from iotnav.io.report import FileReport, IngestReport, SkipReason

__all__ = [
    "FORMATS",
    "FileReport",
    "IngestError",
    "IngestReport",
    "Log",
    "Part",
    "SkipReason",
    "detect_format",
    "ingest",
    "read_file",
]

#: Formats :func:`read_file` understands.
FORMATS = ("nmea", "ubx", "rtklib-pos", "imu-csv", "imu-npz", "gnsslogger", "sensor-logger")

_NMEA_TALKER = (b"$GP", b"$GN", b"$GL", b"$GA", b"$GB", b"$BD", b"$GQ", b"$GI", b"$II", b"$IN")


def _timetag_for(path: Path) -> Path | None:
    tag = path.with_name(path.name + ".tag")
    if tag.is_file():
        with open(tag, "rb") as fh:
            if fh.read(7) == b"TIMETAG":
                return tag
    return None


def _binary_kind(head: bytes) -> str | None:
    """Name the binary stream ``head`` looks like, or None when it is mostly text.

    Leading ``#`` comment lines (as in gpsd's captures) are left out. Sync patterns from the
    protocol manuals: SiRF binary frames ``A0 A2 ... B0 B3``; Garmin binary packets end in
    ``DLE ETX`` (``10 03``); Motorola Oncore messages start with ``@@``.
    """
    body = b"\n".join(ln for ln in head.split(b"\n") if not ln.startswith(b"#"))
    if not body:
        return None
    sample = body[:4096]
    text = sum(1 for b in sample if 32 <= b < 127 or b in (9, 10, 13))
    if text >= 0.7 * len(sample):
        return None
    if body.count(b"\xa0\xa2") >= 2 and body.count(b"\xb0\xb3") >= 2:
        return "SiRF binary (A0 A2 ... B0 B3 frames)"
    if body.count(b"\x10\x03") >= 2:
        return "Garmin binary (DLE ... DLE ETX packets)"
    if body.count(b"@@") >= 2:
        return "Motorola Oncore binary (@@ messages)"
    return f"binary data ({100 - 100 * text // len(sample)} % of its first bytes are not text)"


def detect_format(path: str | os.PathLike[str]) -> str:
    """Guess the format of a log file or directory from its name and first bytes.

    Parameters
    ----------
    path : path-like
        A file, a Sensor Logger export directory or ``.zip``.

    Returns
    -------
    str
        One of :data:`FORMATS`.

    Raises
    ------
    IngestError
        When the file is empty or matches no known format.
    """
    p = Path(path)
    if p.is_dir() or p.suffix.lower() == ".zip":
        return "sensor-logger"
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.suffix.lower() == ".npz":
        return "imu-npz"
    with open(p, "rb") as fh:
        head = fh.read(65536)
    if not head:
        raise IngestError(str(p), "the file is empty")
    if p.suffix.lower() == ".ubx" or head.count(b"\xb5\x62") >= 2:
        return "ubx"
    text = head.decode("latin-1")
    lines = [ln.strip() for ln in text.splitlines()[:60]]
    if any(ln.startswith("%") and ("GPST" in ln or "UTC" in ln) for ln in lines):
        return "rtklib-pos"
    if any(
        ln.startswith(("Fix,", "# Fix,", "UncalAccel,", "# UncalAccel", "Raw,", "# Raw,")) for ln in lines
    ):
        return "gnsslogger"
    if any(t in head for t in _NMEA_TALKER) or (b"$P" in head and b"*" in head):
        return "nmea"
    kind = _binary_kind(head)
    if kind is not None:
        raise IngestError(
            str(p),
            f"this looks like {kind}, which iotnav does not read; expected NMEA 0183, UBX, an RTKLIB "
            ".pos file, an IMU CSV, an Android GnssLogger file or a Sensor Logger export",
        )
    if "," in text or ";" in text or "\t" in text:
        return "imu-csv"
    raise IngestError(
        str(p),
        "not a recognised log: expected NMEA 0183, UBX, an RTKLIB .pos file, an IMU CSV, "
        "an Android GnssLogger file or a Sensor Logger export",
    )


def read_file(path: str | os.PathLike[str], fmt: str | None = None, **options: Any) -> Part:
    """Read one log file with the reader for its (given or detected) format.

    Parameters
    ----------
    path : path-like
        The file (or Sensor Logger directory).
    fmt : str, optional
        One of :data:`FORMATS`; detected when omitted.
    **options
        Passed to the reader (for example ``time_unit`` for NMEA, ``columns``, ``acc_unit``,
        ``gyro_unit``, ``time_unit``, ``preset`` for IMU CSV). Options a reader does not take
        are an error.

    Returns
    -------
    Part
        Tables, clock and report of the file.
    """
    p = Path(path)
    fmt = fmt or detect_format(p)
    reader = _reader(fmt)
    if fmt == "imu-csv":
        tag = _timetag_for(p)
        if tag is not None and "timetag" not in options:
            options = {**options, "timetag": tag}
    return reader(p, **options)


def _reader(fmt: str) -> Callable[..., Part]:
    """The reader function of a format."""
    if fmt == "nmea":
        from iotnav.io.nmea import read_nmea

        return read_nmea
    if fmt == "ubx":
        from iotnav.io.ubx import read_ubx

        return read_ubx
    if fmt == "rtklib-pos":
        from iotnav.io.rtklib import read_rtklib_pos

        return read_rtklib_pos
    if fmt == "imu-csv":
        from iotnav.io.imu_csv import read_imu_csv

        return read_imu_csv
    if fmt == "imu-npz":
        from iotnav.io.npz import read_imu_npz

        return read_imu_npz
    if fmt == "gnsslogger":
        from iotnav.io.phone import read_gnsslogger

        return read_gnsslogger
    if fmt == "sensor-logger":
        from iotnav.io.phone import read_sensor_logger

        return read_sensor_logger
    raise ValueError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")


def ingest(
    paths: Sequence[str | os.PathLike[str]],
    fmt: str | None = None,
    utc_offset_s: float | None = None,
    gnss_latency_s: float = 0.0,
    **options: Any,
) -> Log:
    """Read several files and merge them into one :class:`Log`.

    Parameters
    ----------
    paths : sequence of path-like
        Log files (GNSS and IMU of one device). A directory holding ``gnss.nmea`` and
        ``imu.csv`` (as ``iotnav simulate`` writes) is expanded to those files.
    fmt : str, optional
        Force one format for every file.
    utc_offset_s : float, optional
        ``utc - device time`` when it cannot be estimated from the GNSS epochs.
    gnss_latency_s : float
        Fix epoch to arrival latency of GNSS epochs stamped on the device clock, s
        (:func:`iotnav.io.log.merge`).
    **options
        Reader options (see :func:`read_file`).

    Returns
    -------
    Log
        Merged tables and the ingest report.
    """
    files: list[Path] = []
    for raw in paths:
        p = Path(raw)
        if p.is_dir() and any((p / n).exists() for n in ("gnss.nmea", "imu.csv")):
            files.extend(p / n for n in ("gnss.nmea", "imu.csv") if (p / n).exists())
        else:
            files.append(p)
    parts = []
    used: set[str] = set()
    for f in files:
        ff = fmt or detect_format(f)
        accepted = set(inspect.signature(_reader(ff)).parameters)
        mine = {k: v for k, v in options.items() if k in accepted}
        used.update(mine)
        parts.append(read_file(f, ff, **mine))
    unused = set(options) - used
    if unused:
        raise ValueError(f"option(s) {', '.join(sorted(unused))} apply to none of the files given")
    return merge(parts, imu_utc_offset_s=utc_offset_s, gnss_latency_s=gnss_latency_s)
