"""iotnav's own raw GNSS + IMU batches (MQTT topic ``iotnav/<deviceId>/raw``): schema and decoder.

A device that streams its inertial samples publishes them in batches (typically one a
second) so that the service runs IMU fusion live (:mod:`iotnav.service.raw_ingest`). The
device id is the topic's middle level. Two encodings of the same content, told apart by the
first two bytes (``IR`` binary, anything else is parsed as JSON):

JSON (version 1)
----------------
::

    {"v": 1,
     "utc_offset_s": 0.0,
     "imu":  [[t, ax, ay, az, gx, gy, gz], ...],
     "mag":  [[t, mx, my, mz], ...],
     "gnss": [{"t": ..., "lat": ..., "lon": ..., "alt": ..., "acc": ..., "speed": ...,
               "course": ..., "hdop": ..., "pdop": ..., "vacc": ..., "nsat": ...,
               "quality": ..., "valid": true}, ...]}

* ``t``: device time of the sample, s (float). ``utc_offset_s`` (optional, default 0) is UTC
  minus device time: a device whose clock is disciplined to GNSS sends Unix time and no offset.
  The engine runs on device time; stored fix times are ``t + utc_offset_s``.
* ``imu`` rows: specific force ``ax, ay, az`` along the sensor's x, y, z axes, m/s^2 (at rest,
  z up: ``az`` = +9.8), angular rate ``gx, gy, gz`` about them, rad/s; a row of 10 numbers adds
  the magnetic field ``mx, my, mz``, microtesla, at the same time (or use ``mag``).
* ``gnss``: ``t``, ``lat``, ``lon`` (WGS84 degrees) required; optional ``alt`` ellipsoidal
  height, m; ``acc`` / ``vacc`` horizontal / vertical accuracy (1 sigma), m; ``speed`` ground
  speed, m/s; ``course`` over ground from North towards East, **rad** (omit when unknown);
  ``hdop``, ``pdop``; ``nsat`` satellites used; ``quality`` the GGA fix quality;
  ``valid`` (default true). Absent or ``null``: unknown.
* ``imu``, ``mag``, ``gnss`` are each optional; a message holds at most
  :data:`MAX_SAMPLES` samples and :data:`MAX_MESSAGE_BYTES` bytes.

Binary (version 1), little-endian, ``struct`` formats
-------------------------------------------------------
=======  ====================  ===============================================================
bytes    format                content
=======  ====================  ===============================================================
0-1      ``2s``                magic ``b"IR"``
2        ``B``                 version, 1
3        ``B``                 flags: bit 0 set, the IMU rows carry the magnetometer
4-11     ``d``                 ``t0``, device time of the batch, s
12-19    ``d``                 ``utc_offset_s``, s
20-21    ``H``                 ``n_imu``
22-23    ``H``                 ``n_gnss``
...      ``I6f`` / ``I9f``     IMU rows: ``dt`` (microseconds after ``t0``), ax, ay, az (m/s^2),
                               gx, gy, gz (rad/s)[, mx, my, mz (microtesla)]: 28 / 40 bytes
...      ``IddfffffBB``        GNSS rows: ``dt`` (us), lat, lon (degrees, float64), alt (m),
                               acc (m), speed (m/s), course (rad), hdop (float32, NaN
                               unknown), nsat (255 unknown), flags (bit 0 valid): 42 bytes
last 4   ``I``                 CRC-32 (IEEE 802.3, :func:`zlib.crc32`) of all preceding bytes
=======  ====================  ===============================================================

The length must equal ``24 + n_imu * row + n_gnss * 42 + 4`` exactly. At 100 Hz a second of
IMU is 2.8 kB binary (about 10 kB JSON).

Rejections and skips
--------------------
:func:`decode` never raises. A message that cannot be trusted as a whole is a
:class:`~iotnav.service.protocols.common.Rejected` with reason ``too_large``, ``bad_json``,
``bad_version``, ``bad_crc``, ``bad_length``, ``too_many_samples``, ``bad_offset`` or
``bad_schema`` (a row of the wrong shape, a non-number). Within a good message, a sample
that cannot be used is left out and counted in :attr:`RawBatch.skipped` by reason:
``imu_nonfinite`` / ``mag_nonfinite`` / ``gnss_nonfinite`` (NaN or infinite time or value),
``imu_time_backwards`` / ``mag_time_backwards`` / ``gnss_time_backwards`` (earlier than the
previous sample of the same stream in the message), ``gnss_bad_position`` (latitude beyond
90, longitude beyond 180 degrees) and ``gnss_bad_time`` (UTC outside 2000-2100).
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from iotnav.service.protocols.common import Fix, Rejected, plausible_time, record_key

PROTOCOL = "iotnav_raw"
MAX_MESSAGE_BYTES = 2_000_000
"""Largest message accepted, bytes (a minute of 100 Hz IMU in JSON is about 600 kB)."""
MAX_SAMPLES = 20_000
"""Most samples (IMU + magnetometer + GNSS) in one message."""

MAGIC = b"IR"
VERSION = 1
_HEAD = struct.Struct("<2sBBddHH")
_IMU = struct.Struct("<I6f")
_IMU_MAG = struct.Struct("<I9f")
_GNSS = struct.Struct("<IddfffffBB")
_CRC = struct.Struct("<I")
_NSAT_UNKNOWN = 255


class GnssRecord(NamedTuple):
    """One GNSS fix of a batch (device time ``t``, s; SI units and radians; NaN / -1 unknown)."""

    t: float
    lat_deg: float
    lon_deg: float
    height_m: float = math.nan
    h_acc_m: float = math.nan
    v_acc_m: float = math.nan
    speed_mps: float = math.nan
    course_rad: float = math.nan
    hdop: float = math.nan
    pdop: float = math.nan
    num_sv: int = -1
    quality: int = -1
    valid: bool = True


def _empty(cols: int) -> npt.NDArray[np.float64]:
    return np.empty((0, cols))


@dataclass(frozen=True)
class RawBatch:
    """A decoded raw batch.

    Attributes
    ----------
    device : str or None
        The device id (from the topic).
    utc_offset_s : float
        UTC minus device time, s.
    imu : numpy.ndarray
        ``(n, 7)``: device time (s), specific force x, y, z (m/s^2), rate x, y, z (rad/s).
    mag : numpy.ndarray
        ``(m, 4)``: device time (s), field x, y, z (microtesla).
    gnss : list of GnssRecord
        The fixes, device time.
    skipped : dict
        Samples left out, by reason (module docstring).
    keys : list of str
        De-duplication key of each GNSS record (device id and the record's bytes).
    """

    device: str | None
    utc_offset_s: float = 0.0
    imu: npt.NDArray[np.float64] = field(default_factory=lambda: _empty(7))
    mag: npt.NDArray[np.float64] = field(default_factory=lambda: _empty(4))
    gnss: list[GnssRecord] = field(default_factory=list)
    skipped: dict[str, int] = field(default_factory=dict)
    keys: list[str] = field(default_factory=list)

    @property
    def n_samples(self) -> int:
        """IMU, magnetometer and GNSS samples kept."""
        return len(self.imu) + len(self.mag) + len(self.gnss)

    def fixes(self) -> list[Fix]:
        """The GNSS records as :class:`Fix` (UTC times) for the fixes table."""
        out = []
        for g, key in zip(self.gnss, self.keys, strict=True):
            attrs: dict[str, Any] = {"t_device": g.t}
            if math.isfinite(g.pdop):
                attrs["pdop"] = g.pdop
            out.append(
                Fix(
                    self.device or "",
                    g.t + self.utc_offset_s,
                    g.lat_deg,
                    g.lon_deg,
                    g.height_m,
                    g.speed_mps,
                    g.course_rad,
                    g.h_acc_m,
                    g.num_sv,
                    g.hdop,
                    g.valid,
                    attrs,
                    key,
                )
            )
        return out


def device_from_topic(topic: str) -> str | None:
    """``deviceId`` from ``iotnav/<deviceId>/raw``, else None."""
    parts = topic.split("/")
    if len(parts) == 3 and parts[0] == "iotnav" and parts[1] and parts[2] == "raw":
        return parts[1]
    return None


# --- checks shared by both encodings ------------------------------------------------------


def _count(skipped: dict[str, int], reason: str, n: int = 1) -> None:
    if n:
        skipped[reason] = skipped.get(reason, 0) + n


def _clean_rows(
    rows: npt.NDArray[np.float64], stream: str, skipped: dict[str, int]
) -> npt.NDArray[np.float64]:
    """``rows`` without non-finite rows and rows earlier than the previous kept one (counted)."""
    if len(rows) == 0:
        return rows
    finite = np.isfinite(rows).all(axis=1)
    _count(skipped, f"{stream}_nonfinite", int((~finite).sum()))
    rows = rows[finite]
    if len(rows) > 1 and not bool(np.all(np.diff(rows[:, 0]) >= 0.0)):
        keep = rows[:, 0] >= np.maximum.accumulate(rows[:, 0])
        _count(skipped, f"{stream}_time_backwards", int((~keep).sum()))
        rows = rows[keep]
    return rows


def _gnss_kept(
    recs: list[tuple[GnssRecord, bytes]], device: str | None, off: float, skipped: dict[str, int]
) -> tuple[list[GnssRecord], list[str]]:
    """The GNSS records that can be used, with their de-duplication keys (the others counted)."""
    out: list[GnssRecord] = []
    keys: list[str] = []
    last = -math.inf
    for g, raw in recs:
        if not math.isfinite(g.t) or not (math.isfinite(g.lat_deg) and math.isfinite(g.lon_deg)):
            _count(skipped, "gnss_nonfinite")
        elif abs(g.lat_deg) > 90.0 or abs(g.lon_deg) > 180.0:
            _count(skipped, "gnss_bad_position")
        elif not plausible_time(g.t + off):
            _count(skipped, "gnss_bad_time")
        elif g.t < last:
            _count(skipped, "gnss_time_backwards")
        else:
            last = g.t
            out.append(g)
            keys.append(record_key(device or "", raw))
    return out, keys


# --- JSON -----------------------------------------------------------------------------------


class _SchemaError(ValueError):
    pass


def _number(v: Any, what: str) -> float:
    if v is None:
        return math.nan
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _SchemaError(f"{what}: expected a number, got {type(v).__name__}")
    try:
        return float(v)
    except OverflowError:  # an integer beyond float range
        return math.inf


def _int_or(v: Any, what: str) -> int:
    x = _number(v, what)
    return int(x) if math.isfinite(x) and abs(x) < 2**31 else -1


def _matrix(rows: Any, widths: tuple[int, ...], what: str) -> npt.NDArray[np.float64]:
    if rows is None:
        return _empty(widths[0])
    if not isinstance(rows, list):
        raise _SchemaError(f"{what}: expected a list of rows")
    if not rows:
        return _empty(widths[0])
    width = len(rows[0]) if isinstance(rows[0], list) else -1
    if width not in widths:
        raise _SchemaError(f"{what}: rows of {' or '.join(map(str, widths))} numbers expected")
    for r in rows:
        if not isinstance(r, list) or len(r) != width:
            raise _SchemaError(f"{what}: every row must hold {width} numbers")
    return np.array([[_number(v, what) for v in r] for r in rows], dtype=np.float64).reshape(-1, width)


_GNSS_KEYS = {
    "t",
    "lat",
    "lon",
    "alt",
    "acc",
    "vacc",
    "speed",
    "course",
    "hdop",
    "pdop",
    "nsat",
    "quality",
    "valid",
}


def _gnss_json(r: Any) -> GnssRecord:
    if not isinstance(r, dict):
        raise _SchemaError("gnss: expected objects")
    if any(k not in r for k in ("t", "lat", "lon")):
        raise _SchemaError("gnss: t, lat and lon are required")
    valid = r.get("valid", True)
    if not isinstance(valid, bool):
        raise _SchemaError("gnss: valid must be true or false")
    return GnssRecord(
        t=_number(r["t"], "gnss t"),
        lat_deg=_number(r["lat"], "gnss lat"),
        lon_deg=_number(r["lon"], "gnss lon"),
        height_m=_number(r.get("alt"), "gnss alt"),
        h_acc_m=_number(r.get("acc"), "gnss acc"),
        v_acc_m=_number(r.get("vacc"), "gnss vacc"),
        speed_mps=_number(r.get("speed"), "gnss speed"),
        course_rad=_number(r.get("course"), "gnss course"),
        hdop=_number(r.get("hdop"), "gnss hdop"),
        pdop=_number(r.get("pdop"), "gnss pdop"),
        num_sv=_int_or(r.get("nsat"), "gnss nsat"),
        quality=_int_or(r.get("quality"), "gnss quality"),
        valid=valid,
    )


def _decode_json(payload: bytes, device: str | None) -> RawBatch | Rejected:
    try:
        doc = json.loads(payload)
    except (ValueError, RecursionError) as exc:
        return Rejected("bad_json", f"not JSON: {str(exc)[:80]}")
    if not isinstance(doc, dict):
        return Rejected("bad_json", "the message is not a JSON object")
    if doc.get("v") != VERSION:
        return Rejected("bad_version", f"v = {str(doc.get('v'))[:20]!r}; expected {VERSION}")
    imu, mag, gnss = doc.get("imu"), doc.get("mag"), doc.get("gnss")
    n = sum(len(x) for x in (imu, mag, gnss) if isinstance(x, list))
    if n > MAX_SAMPLES:
        return Rejected("too_many_samples", f"{n} samples (limit {MAX_SAMPLES})")
    try:
        off = _number(doc.get("utc_offset_s", 0.0), "utc_offset_s")
        imu_rows = _matrix(imu, (7, 10), "imu")
        mag_rows = _matrix(mag, (4,), "mag")
        if gnss is not None and not isinstance(gnss, list):
            raise _SchemaError("gnss: expected a list")
        recs = [(_gnss_json(r), json.dumps(r, sort_keys=True).encode()) for r in gnss or []]
    except _SchemaError as exc:
        return Rejected("bad_schema", str(exc)[:120])
    return _batch(device, off, imu_rows, mag_rows, recs)


def _batch(
    device: str | None,
    off: float,
    imu_rows: npt.NDArray[np.float64],
    mag_rows: npt.NDArray[np.float64],
    recs: list[tuple[GnssRecord, bytes]],
) -> RawBatch | Rejected:
    if not math.isfinite(off) or abs(off) > 1e10:
        return Rejected("bad_offset", f"utc_offset_s {off}: expected a finite number of seconds")
    skipped: dict[str, int] = {}
    if imu_rows.shape[1] == 10:  # magnetometer in the IMU rows
        mag_rows = np.concatenate([mag_rows, imu_rows[:, [0, 7, 8, 9]]])
        mag_rows = mag_rows[np.argsort(mag_rows[:, 0], kind="stable")] if len(mag_rows) else mag_rows
        imu_rows = imu_rows[:, :7]
    imu_rows = _clean_rows(imu_rows, "imu", skipped)
    mag_rows = _clean_rows(mag_rows, "mag", skipped)
    gnss, keys = _gnss_kept(recs, device, off, skipped)
    return RawBatch(device, off, imu_rows, mag_rows, gnss, skipped, keys)


# --- binary ---------------------------------------------------------------------------------


def _decode_binary(payload: bytes, device: str | None) -> RawBatch | Rejected:
    if len(payload) < _HEAD.size + _CRC.size:
        return Rejected("bad_length", f"{len(payload)} bytes: shorter than a header")
    _magic, version, flags, t0, off, n_imu, n_gnss = _HEAD.unpack_from(payload)
    if version != VERSION:
        return Rejected("bad_version", f"version {version}; expected {VERSION}")
    (crc,) = _CRC.unpack_from(payload, len(payload) - _CRC.size)
    if zlib.crc32(payload[: -_CRC.size]) != crc:
        return Rejected("bad_crc", "CRC-32 does not match")
    if n_imu + n_gnss > MAX_SAMPLES:
        return Rejected("too_many_samples", f"{n_imu + n_gnss} samples (limit {MAX_SAMPLES})")
    row = _IMU_MAG if flags & 1 else _IMU
    need = _HEAD.size + n_imu * row.size + n_gnss * _GNSS.size + _CRC.size
    if len(payload) != need:
        return Rejected("bad_length", f"{len(payload)} bytes; the header announces {need}")
    if not math.isfinite(t0):
        return Rejected("bad_schema", "t0 is not finite")
    pos = _HEAD.size
    width = 10 if flags & 1 else 7
    imu_rows = np.empty((n_imu, width))
    for k, vals in enumerate(row.iter_unpack(payload[pos : pos + n_imu * row.size])):
        imu_rows[k, 0] = t0 + vals[0] * 1e-6
        imu_rows[k, 1:] = vals[1:]
    pos += n_imu * row.size
    recs = []
    for k in range(n_gnss):
        raw = payload[pos + k * _GNSS.size : pos + (k + 1) * _GNSS.size]
        dt, lat, lon, alt, acc, speed, course, hdop, nsat, gflags = _GNSS.unpack(raw)
        g = GnssRecord(
            t=t0 + dt * 1e-6,
            lat_deg=lat,
            lon_deg=lon,
            height_m=alt,
            h_acc_m=acc,
            speed_mps=speed,
            course_rad=course,
            hdop=hdop,
            num_sv=-1 if nsat == _NSAT_UNKNOWN else nsat,
            valid=bool(gflags & 1),
        )
        recs.append((g, struct.pack("<d", t0) + raw))
    return _batch(device, off, imu_rows, _empty(4), recs)


def decode(payload: bytes, device: str | None = None, topic: str | None = None) -> RawBatch | Rejected:
    """One raw batch, JSON or binary (module docstring); never raises.

    Parameters
    ----------
    payload : bytes
        The message.
    device : str, optional
        The device id; else taken from ``topic`` (``iotnav/<deviceId>/raw``).
    topic : str, optional
        The MQTT topic.

    Returns
    -------
    RawBatch or Rejected
        Rejected also with reason ``no_device`` when neither gives a device id.
    """
    dev = device if device is not None else device_from_topic(topic) if topic is not None else None
    if not dev:
        return Rejected("no_device", f"no device id (topic {str(topic)[:80]!r}; expected iotnav/<id>/raw)")
    if len(payload) > MAX_MESSAGE_BYTES:
        return Rejected("too_large", f"{len(payload)} bytes (limit {MAX_MESSAGE_BYTES})")
    if payload[:2] != MAGIC:
        return _decode_json(payload, dev)
    try:
        return _decode_binary(payload, dev)
    except struct.error as exc:  # a length already checked; kept so no input can raise
        return Rejected("bad_length", str(exc)[:80])


# --- encoders (devices, tests, the load generator) ------------------------------------------


def encode_json(
    imu: npt.ArrayLike | None = None,
    gnss: list[dict[str, Any]] | None = None,
    mag: npt.ArrayLike | None = None,
    utc_offset_s: float = 0.0,
) -> bytes:
    """A JSON batch: ``imu`` rows ``[t, ax, ay, az, gx, gy, gz]``, ``gnss`` dicts (module docstring).

    Floats are written with Python's shortest round-trip repr, so the service decodes the
    very float64 values given.
    """
    doc: dict[str, Any] = {"v": VERSION}
    if utc_offset_s:
        doc["utc_offset_s"] = float(utc_offset_s)
    if imu is not None:
        doc["imu"] = np.asarray(imu, dtype=np.float64).tolist()
    if mag is not None:
        doc["mag"] = np.asarray(mag, dtype=np.float64).tolist()
    if gnss:
        doc["gnss"] = [{k: v for k, v in g.items() if k in _GNSS_KEYS} for g in gnss]
    return json.dumps(doc, separators=(",", ":")).encode()


def encode_binary(
    t0: float,
    imu: npt.ArrayLike | None = None,
    gnss: list[GnssRecord] | None = None,
    utc_offset_s: float = 0.0,
) -> bytes:
    """A binary batch: ``imu`` rows ``[t, ax, ay, az, gx, gy, gz(, mx, my, mz)]`` (t >= ``t0``, s).

    Values are rounded to float32 and times to the microsecond after ``t0``.
    """
    rows = np.asarray(imu if imu is not None else _empty(7), dtype=np.float64).reshape(
        -1, 7 if imu is None else np.shape(imu)[-1]
    )
    mag = rows.shape[1] == 10
    row = _IMU_MAG if mag else _IMU
    recs = gnss or []
    parts = [_HEAD.pack(MAGIC, VERSION, 1 if mag else 0, t0, utc_offset_s, len(rows), len(recs))]
    for r in rows.tolist():
        parts.append(row.pack(round((r[0] - t0) * 1e6), *r[1:]))
    for g in recs:
        nsat = g.num_sv if 0 <= g.num_sv < _NSAT_UNKNOWN else _NSAT_UNKNOWN
        parts.append(
            _GNSS.pack(
                round((g.t - t0) * 1e6),
                g.lat_deg,
                g.lon_deg,
                g.height_m,
                g.h_acc_m,
                g.speed_mps,
                g.course_rad,
                g.hdop,
                nsat,
                1 if g.valid else 0,
            )
        )
    body = b"".join(parts)
    return body + _CRC.pack(zlib.crc32(body))
