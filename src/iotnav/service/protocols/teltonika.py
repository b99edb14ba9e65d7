"""Teltonika Codec 8 and Codec 8 Extended over TCP (pure decoders).

Source: Teltonika, "Teltonika Data Sending Protocols", sections Codec 8 and Codec 8 Extended,
https://wiki.teltonika-gps.com/view/Teltonika_Data_Sending_Protocols (layout only; no code
of any decoder was used).

Session
    The device opens a TCP connection and sends its IMEI: a 2-byte big-endian length then the
    IMEI as ASCII digits (``000F`` + 15 digits). The server answers ``01`` to accept, ``00`` to
    refuse (:func:`decode_imei`, :func:`imei_answer`).

AVL data packet (:func:`decode_avl`)
    ``00000000`` preamble (4 bytes), data field length (4 bytes, counts codec id up to and
    including the second record count), codec id (``08`` or ``8E``), number of data 1 (1 byte),
    the AVL records, number of data 2 (1 byte, equal to number of data 1), CRC-16/IBM of the
    data field (4 bytes, the upper two zero). The server answers the number of records
    accepted as a 4-byte big-endian integer (:func:`avl_answer`).

AVL record
    timestamp (8 bytes, ms since 1970 UTC), priority (1), GPS element (15: longitude and
    latitude int32 in 1e-7 degrees, altitude int16 m, angle uint16 degrees from North,
    satellites uint8, speed uint16 km/h), IO element. Codec 8: event IO id (1), total count
    (1), then four groups of 1, 2, 4 and 8-byte values, each a count (1) and (id (1), value)
    pairs. Codec 8 Extended: ids and counts are 2 bytes and a fifth group of variable-length
    values follows, each (id (2), length (2), bytes).

Every IO element is kept in :attr:`Fix.attributes` under ``io`` (id as a string -> unsigned
value; variable-length values as hex); the ones the service uses are also named
(:data:`IO_NAMES`).
"""

from __future__ import annotations

import math
import struct
from typing import Any

from iotnav.service.protocols.common import (
    KMH_MPS,
    Decoded,
    Fix,
    Incomplete,
    Rejected,
    Result,
    plausible_time,
    record_key,
)

CODEC8 = 0x08
CODEC8_EXTENDED = 0x8E

#: Largest AVL packet accepted by default, bytes (a generous bound, configurable on the
#: listener; it keeps a hostile length field from making the server buffer gigabytes).
MAX_PACKET_BYTES = 65536

#: Longest IMEI field accepted, bytes (an IMEI has 15 digits; IMEISV 16).
MAX_IMEI_BYTES = 20

#: IO element ids named in :attr:`Fix.attributes` (Teltonika FMB AVL ID list, e.g.
#: https://wiki.teltonika-gps.com/view/FMB020_Teltonika_Data_Sending_Parameters_ID): id ->
#: (name, signed, multiplier to the unit in the name).
IO_NAMES: dict[int, tuple[str, bool, float]] = {
    239: ("ignition", False, 1.0),
    240: ("movement", False, 1.0),
    16: ("odometer_m", False, 1.0),
    66: ("external_voltage_v", False, 1e-3),
    67: ("battery_voltage_v", False, 1e-3),
    113: ("battery_level_pct", False, 1.0),
    17: ("acc_x_mg", True, 1.0),
    18: ("acc_y_mg", True, 1.0),
    19: ("acc_z_mg", True, 1.0),
    181: ("pdop", False, 0.1),
    182: ("hdop", False, 0.1),
    21: ("gsm_signal", False, 1.0),
}

_IMEI = struct.Struct(">H")
_HEAD = struct.Struct(">II")
_GPS = struct.Struct(">QBiihHBH")  # timestamp, priority, lon, lat, alt, angle, sats, speed


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16_ibm(data: bytes) -> int:
    """CRC-16/IBM (also CRC-16/ARC): reflected polynomial 0x8005 (0xA001), initial value 0.

    Table-driven, a byte at a time. Catalogue check value: ``crc16_ibm(b"123456789") ==
    0xBB3D`` (Greg Cook, "Catalogue of parametrised CRC algorithms", CRC-16/ARC).
    """
    crc = 0
    table = _CRC_TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def decode_imei(buf: bytes) -> Result:
    """The IMEI handshake at the start of ``buf``.

    Returns
    -------
    Decoded
        ``device`` the IMEI, no records, ``answer`` empty (the caller decides with
        :func:`imei_answer` whether the device is known), ``consumed`` the handshake's length.
    Incomplete
        Fewer bytes than the handshake announces.
    Rejected
        ``imei_length`` (announced length 0 or above :data:`MAX_IMEI_BYTES`) or
        ``imei_not_digits``; answered ``00``.
    """
    if len(buf) < 2:
        return Incomplete(2 - len(buf))
    (n,) = _IMEI.unpack_from(buf)
    if n == 0 or n > MAX_IMEI_BYTES:
        return Rejected("imei_length", f"IMEI length {n} (expected 1..{MAX_IMEI_BYTES})", b"\x00")
    if len(buf) < 2 + n:
        return Incomplete(2 + n - len(buf))
    raw = bytes(buf[2 : 2 + n])
    if not raw.isdigit():
        return Rejected("imei_not_digits", f"IMEI {raw[:32]!r} is not ASCII digits", b"\x00")
    return Decoded([], b"", 2 + n, device=raw.decode("ascii"))


def imei_answer(accept: bool) -> bytes:
    """``01`` to accept the device, ``00`` to refuse it."""
    return b"\x01" if accept else b"\x00"


def avl_answer(n_records: int) -> bytes:
    """The acknowledgement of ``n_records`` records: 4-byte big-endian count."""
    return struct.pack(">I", n_records)


class _Truncated(Exception):
    """Raised inside the record parser when the data field ends early (caught by decode_avl)."""


_COUNTS_EXT = struct.Struct(">HH")  # Codec 8 Extended: event IO id, total count


def _io_value(ident: int, raw: bytes, named: dict[str, Any]) -> int:
    value = int.from_bytes(raw, "big")
    spec = IO_NAMES.get(ident)
    if spec is not None:
        name, signed, scale = spec
        v = int.from_bytes(raw, "big", signed=signed) if signed else value
        named[name] = v * scale if scale != 1.0 else v
    return value


def _record(data: bytes, pos: int, end: int, device: str, extended: bool) -> tuple[Fix, int]:
    """The record at ``data[pos:]`` (the data field ends at ``end``) and the position after it.

    Reads by index and :mod:`struct` (no reader object per field: the hot path of the
    listener); raises :class:`_Truncated` when the record runs past ``end``.
    """
    start = pos
    if pos + _GPS.size > end:
        raise _Truncated
    ts_ms, priority, lon, lat, alt, angle, sats, speed = _GPS.unpack_from(data, pos)
    pos += _GPS.size
    width = 2 if extended else 1
    if pos + 2 * width > end:
        raise _Truncated
    if extended:
        event_id, total = _COUNTS_EXT.unpack_from(data, pos)
    else:
        event_id, total = data[pos], data[pos + 1]
    pos += 2 * width
    io: dict[str, Any] = {}
    named: dict[str, Any] = {}
    for size in (1, 2, 4, 8):
        if pos + width > end:
            raise _Truncated
        count = (data[pos] << 8 | data[pos + 1]) if extended else data[pos]
        pos += width
        step = width + size
        if pos + count * step > end:
            raise _Truncated
        for _ in range(count):
            ident = (data[pos] << 8 | data[pos + 1]) if extended else data[pos]
            io[str(ident)] = _io_value(ident, data[pos + width : pos + step], named)
            pos += step
    if extended:
        if pos + 2 > end:
            raise _Truncated
        count = data[pos] << 8 | data[pos + 1]
        pos += 2
        for _ in range(count):
            if pos + 4 > end:
                raise _Truncated
            ident, n = _COUNTS_EXT.unpack_from(data, pos)
            pos += 4
            if pos + n > end:
                raise _Truncated
            io[str(ident)] = data[pos : pos + n].hex()
            pos += n
    attributes: dict[str, Any] = {
        "priority": priority,
        "event_io": event_id,
        "io_total": total,
        "io": io,
        **named,
    }
    # Teltonika sends the last known coordinates with 0 satellites when it has no fix
    valid = sats > 0
    fix = Fix(
        device=device,
        t=ts_ms / 1000.0,
        lat_deg=lat * 1e-7,
        lon_deg=lon * 1e-7,
        height_m=float(alt),
        speed_mps=speed * KMH_MPS,
        course_rad=math.radians(angle) if valid else math.nan,
        num_sv=sats,
        hdop=float(named["hdop"]) if "hdop" in named else math.nan,
        valid=valid,
        attributes=attributes,
        key=record_key(device, data[start:pos]),
    )
    return fix, pos


def decode_avl(buf: bytes, device: str, max_packet: int = MAX_PACKET_BYTES) -> Result:
    """One AVL data packet at the start of ``buf`` from the device ``device`` (its IMEI).

    Returns
    -------
    Decoded
        The records and the answer :func:`avl_answer` (the caller sends it only once the
        records are stored), ``consumed`` the packet's length.
    Incomplete
        The packet announced is not all in ``buf`` yet.
    Rejected
        ``preamble`` (not four zero bytes), ``length`` (data field shorter than a codec id
        and two counts, or the packet above ``max_packet``), ``crc`` (CRC-16/IBM mismatch),
        ``codec`` (not 8 or 8 Extended), ``count_mismatch`` (number of data 1 and 2 differ),
        ``truncated`` (records run past the data field), ``trailing`` (bytes left between the
        last record and number of data 2), ``time`` (a record time before 2000 or past 2100).
    """
    if len(buf) < 8:
        return Incomplete(8 - len(buf))
    preamble, length = _HEAD.unpack_from(buf)
    if preamble != 0:
        return Rejected("preamble", f"preamble {buf[:4].hex()} (expected 00000000)")
    total = 8 + length + 4
    if length < 3 or total > max_packet:
        return Rejected("length", f"data field length {length} (packet {total} bytes, limit {max_packet})")
    if len(buf) < total:
        return Incomplete(total - len(buf))
    data = bytes(buf[8 : 8 + length])
    (crc,) = struct.unpack_from(">I", buf, 8 + length)
    if crc != crc16_ibm(data):
        return Rejected("crc", f"CRC {crc:08x}, computed {crc16_ibm(data):08x}")
    codec, n1 = data[0], data[1]
    if codec not in (CODEC8, CODEC8_EXTENDED):
        return Rejected("codec", f"codec id 0x{codec:02x} (expected 0x08 or 0x8e)")
    if data[-1] != n1:
        return Rejected("count_mismatch", f"number of data 1 = {n1}, number of data 2 = {data[-1]}")
    pos, end, extended = 2, length - 1, codec == CODEC8_EXTENDED
    records = []
    try:
        for _ in range(n1):
            rec, pos = _record(data, pos, end, device, extended)
            records.append(rec)
    except _Truncated:
        return Rejected("truncated", f"record {len(records) + 1} of {n1} runs past the data field")
    if pos != end:
        return Rejected("trailing", f"{end - pos} bytes after the last record")
    for rec in records:
        if not plausible_time(rec.t):
            return Rejected("time", f"record time {rec.t} s is outside 2000..2100")
    return Decoded(records, avl_answer(n1), total, device=device)
