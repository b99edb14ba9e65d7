"""u-blox UBX reader (binary, possibly mixed with NMEA): NAV-PVT epochs and ESF IMU samples.

Frames are decoded by `pyubx2 <https://github.com/semuconsulting/pyubx2>`_; the framing
(finding frames and resynchronising after garbage) is done here so that every byte is accounted.

Input units
-----------
The stream is scanned for the UBX sync ``b5 62`` and for ``$``/``!``. A unit is one of

* a UBX frame: sync, class, id, little-endian length, payload and a correct 8-bit Fletcher
  checksum. NAV-PVT, ESF-RAW and ESF-MEAS are records (``"UBX NAV-PVT"``...); every other class
  is counted under ``ignored`` by its pyubx2 name (``"UBX RXM-RAWX"``; ``"UBX 0x..."`` when
  pyubx2 does not know it). A frame pyubx2 cannot decode is :attr:`SkipReason.MALFORMED`.
* an NMEA sentence ``$ADDRESS,...*hh``: handled exactly as by :func:`iotnav.io.nmea.read_nmea`
  (same counting) and assembled into epochs by :class:`iotnav.io.nmea.NmeaEpochAssembler`;
  a ``$``-fragment that is not a complete sentence is TRUNCATED or GARBAGE as there;
* a *garbage chunk*: a maximal run of bytes that belongs to neither (a sync pair whose length or
  checksum does not fit starts no frame; its bytes join the chunk). Line ends between sentences
  and frames are not garbage. Each chunk is one :attr:`SkipReason.GARBAGE` unit.

NAV-PVT epochs
--------------
``t = utc`` = the NAV-PVT UTC date and time plus ``nano`` when ``validDate`` and ``validTime``
are set (otherwise the frame is skipped, :attr:`SkipReason.NO_TIME`); lat/lon (``invalidLlh``
set -> NaN), ``height_m`` = ``height`` (ellipsoid), ``alt_msl_m`` = ``hMSL``, ``geoid_sep_m`` =
their difference, ``vn, ve, vd`` = ``velN, velE, velD``, ``speed_mps`` = ``gSpeed``,
``h_acc_m``/``v_acc_m``/``s_acc_mps`` from ``hAcc``/``vAcc``/``sAcc``, ``pdop``, ``num_sv``,
``valid`` = ``gnssFixOK``. ``mode``: fixType 0 (no fix) -> 1, 1 (dead reckoning only) and
2 -> 2, 3, 4 (GNSS + DR) and 5 (time only: a timing receiver holding its surveyed position) -> 3,
as gpsd reports them. ``quality`` (GGA code): carrSoln 2 -> 4 (RTK fixed), 1 -> 5 (float), else
fixType 0 -> 0, 1 -> 6 (dead reckoning), 5 -> 7 (fixed/manual position), ``diffSoln`` -> 2,
else 1. ``course_rad`` = ``headMot``; ``course_valid`` when ``gnssFixOK`` and ``gSpeed`` is at
least twice its 1-sigma ``sAcc`` (below that the receiver's heading of motion is frozen or noise;
``headVehValid`` is about the vehicle heading ``headVeh``, not used here).

NMEA in the same stream: its cycles are assembled on the UTC clock; a cycle within 5 ms of a
NAV-PVT epoch (NMEA times are rounded to the output resolution, NAV-PVT carries the exact
``nano``) is dropped in favour of NAV-PVT and its sentences are counted under ``ignored`` as
``"GGA (duplicate of UBX NAV-PVT)"``; NMEA cycles with no NAV-PVT counterpart are kept
(``source = "nmea"``).

IMU (ESF)
---------
ESF-RAW and ESF-MEAS data words are decoded here (pyubx2 leaves them as bit fields): a 24-bit
signed value and a 6-bit type; types 14/13/5 are gyro x/y/z (2^-12 deg/s), 16/17/18 accel x/y/z
(2^-10 m/s^2); other types (temperature, wheel ticks) are not used. Samples sharing a sensor
time tag form one row. Sensor time tags are in ms on the receiver's own clock, with no link to UTC
in these messages; iotnav anchors them to UTC by taking the first ESF message to be at the UTC of
the last NAV-PVT before it (the next one when none precedes). ``t`` of the IMU table is therefore
on the UTC clock up to one navigation epoch of constant offset, which the report notes.
"""

from __future__ import annotations

import calendar
import math
import os
import re
import struct

import numpy as np
import pandas as pd
from pyubx2 import UBXReader
from pyubx2.ubxtypes_core import UBX_MSGIDS

from iotnav.io.errors import IngestError
from iotnav.io.log import Part
from iotnav.io.nmea import NmeaEpochAssembler, _Framer, _load
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, coerce

__all__ = ["fletcher8", "read_ubx"]

_SYNC = b"\xb5\x62"
_SCAN_RE = re.compile(rb"\xb5\x62|\$|![A-Z]{2}")
_NMEA_END_RE = re.compile(rb"[\r\n]|\xb5\x62|\$")
_MAX_PAYLOAD = 8192
_NMEA_MAX = 1024
_DUP_TOL_S = 0.005

_GYRO = {14: "gyro_x", 13: "gyro_y", 5: "gyro_z"}
_ACC = {16: "acc_x", 17: "acc_y", 18: "acc_z"}
_GYRO_SCALE = math.radians(2.0**-12)  # rad/s per LSB
_ACC_SCALE = 2.0**-10  # m/s^2 per LSB


def fletcher8(data: bytes) -> bytes:
    """UBX 8-bit Fletcher checksum (``CK_A``, ``CK_B``) of class, id, length and payload.

    Parameters
    ----------
    data : bytes
        The bytes after the sync characters and before the checksum.

    Returns
    -------
    bytes
        Two bytes.
    """
    n = len(data)
    if n < 64:
        a = b = 0
        for x in data:
            a = (a + x) & 0xFF
            b = (b + a) & 0xFF
        return bytes((a, b))
    arr = np.frombuffer(data, dtype=np.uint8).astype(np.int64)
    a = int(arr.sum()) & 0xFF
    b = int((arr * np.arange(n, 0, -1, dtype=np.int64)).sum()) & 0xFF
    return bytes((a, b))


def _name(cls_id: bytes) -> str:
    n = UBX_MSGIDS.get(cls_id)
    return f"UBX {n}" if n else f"UBX 0x{cls_id[0]:02x} 0x{cls_id[1]:02x}"


def _pvt_row(msg: object) -> dict[str, float | int | bool | str] | None:
    g = msg.__dict__
    if not (g.get("validDate") and g.get("validTime")):
        return None
    try:
        whole = calendar.timegm((g["year"], g["month"], g["day"], g["hour"], g["min"], g["second"], 0, 0, 0))
    except (ValueError, OverflowError, KeyError):
        return None
    utc = whole + g.get("nano", 0) * 1e-9
    fix = int(g.get("fixType", 0))
    fix_ok = bool(g.get("gnssFixOk", 0))
    carr = int(g.get("carrSoln", 0))
    mode = {0: 1, 1: 2, 2: 2, 3: 3, 4: 3, 5: 3}.get(fix, 0)
    if carr == 2:
        quality = 4
    elif carr == 1:
        quality = 5
    elif fix == 0:
        quality = 0
    elif fix == 1:
        quality = 6
    elif fix == 5:
        quality = 7
    elif g.get("diffSoln"):
        quality = 2
    else:
        quality = 1
    lat, lon = float(g["lat"]), float(g["lon"])
    if g.get("invalidLlh"):
        lat = lon = math.nan
    height = g["height"] * 1e-3
    hmsl = g["hMSL"] * 1e-3
    speed = g["gSpeed"] * 1e-3
    s_acc = g["sAcc"] * 1e-3
    course = math.radians(float(g["headMot"]) % 360.0)
    return {
        "t": utc,
        "utc": utc,
        "lat_deg": lat,
        "lon_deg": lon,
        "height_m": height,
        "alt_msl_m": hmsl,
        "geoid_sep_m": height - hmsl,
        "quality": quality,
        "mode": mode,
        "num_sv": int(g["numSV"]),
        "pdop": float(g["pDOP"]),
        "speed_mps": speed,
        "course_rad": course if course < 2 * math.pi else 0.0,
        "course_valid": fix_ok and speed > 0 and speed >= 2.0 * s_acc,
        "vn": g["velN"] * 1e-3,
        "ve": g["velE"] * 1e-3,
        "vd": g["velD"] * 1e-3,
        "h_acc_m": g["hAcc"] * 1e-3,
        "v_acc_m": g["vAcc"] * 1e-3,
        "s_acc_mps": s_acc,
        "valid": fix_ok and lat == lat,
        "source": "ubx",
    }


def _esf_samples(cls_id: bytes, payload: bytes) -> list[tuple[int, dict[str, float]]]:
    """(sensor time tag in ms, {column: value}) per time tag of an ESF-RAW/ESF-MEAS payload."""
    out: dict[int, dict[str, float]] = {}
    if cls_id == b"\x10\x03":  # ESF-RAW: reserved U4, then (data X4, sTtag U4) * n
        body = payload[4:]
        for k in range(len(body) // 8):
            word, tag = struct.unpack_from("<II", body, 8 * k)
            _put(out.setdefault(tag, {}), word)
    else:  # ESF-MEAS: timeTag U4, flags X2, id U2, data X4 * numMeas [, calibTtag U4]
        tag, flags, _id = struct.unpack_from("<IHH", payload, 0)
        n = (flags >> 11) & 0x1F
        row = out.setdefault(tag, {})
        for k in range(min(n, (len(payload) - 8) // 4)):
            (word,) = struct.unpack_from("<I", payload, 8 + 4 * k)
            _put(row, word)
    return [(tag, row) for tag, row in out.items() if row]


def _put(row: dict[str, float], word: int) -> None:
    value = word & 0xFFFFFF
    if value & 0x800000:
        value -= 0x1000000
    dtype = (word >> 24) & 0x3F
    if dtype in _GYRO:
        row[_GYRO[dtype]] = value * _GYRO_SCALE
    elif dtype in _ACC:
        row[_ACC[dtype]] = value * _ACC_SCALE


def read_ubx(source: str | os.PathLike[str] | bytes, *, name: str | None = None) -> Part:
    """Read a u-blox UBX stream (optionally mixed with NMEA) into GNSS epochs and IMU samples.

    Parameters
    ----------
    source : str, os.PathLike or bytes
        A file path or the raw bytes.
    name : str, optional
        Name used in the report and errors.

    Returns
    -------
    Part
        ``gnss`` (NAV-PVT epochs, plus NMEA cycles with no NAV-PVT counterpart), ``imu`` (ESF),
        clock ``"utc"``. Units and rules are in the module docstring.

    Raises
    ------
    IngestError
        When the file cannot be read or holds neither a UBX frame nor an NMEA sentence.
    """
    data, label = _load(source, name)
    rep = FileReport(path=label, format="ubx")
    asm = NmeaEpochAssembler(rep, source="nmea")
    framer = _Framer(rep, asm)
    pvt_rows: list[dict[str, float | int | bool | str]] = []
    esf: list[tuple[float, int, dict[str, float]]] = []  # (utc anchor candidate, tag, row)
    n_frames = 0
    units = 0
    garbage_start = -1
    pos = 0
    size = len(data)
    last_pvt_utc = math.nan

    def flush_garbage(end: int) -> None:
        nonlocal garbage_start, units
        if garbage_start >= 0:
            chunk = data[garbage_start:end]
            if chunk.strip():
                units += 1
                rep.skip(SkipReason.GARBAGE, garbage_start, chunk[:40].hex(" "))
            garbage_start = -1

    while pos < size:
        m = _SCAN_RE.search(data, pos)
        if m is None:
            if garbage_start < 0:
                garbage_start = pos
            break
        start = m.start()
        if start > pos and garbage_start < 0:
            garbage_start = pos
        if data[start] == 0xB5:
            frame = _frame_at(data, start)
            if frame is None:
                if garbage_start < 0:
                    garbage_start = start
                pos = start + 1
                continue
            flush_garbage(start)
            units += 1
            n_frames += 1
            pos = start + len(frame)
            cls_id = frame[2:4]
            kind = _name(cls_id)
            if cls_id == b"\x01\x07":
                try:
                    msg = UBXReader.parse(frame)
                    row = _pvt_row(msg)
                except Exception as err:  # pyubx2 raises several types on bad payloads
                    rep.skip(SkipReason.MALFORMED, start, f"{kind}: {err}")
                    continue
                if row is None:
                    rep.skip(SkipReason.NO_TIME, start, "NAV-PVT without valid date/time")
                    continue
                pvt_rows.append(row)
                last_pvt_utc = float(row["utc"])  # type: ignore[arg-type]
                rep.record(kind)
            elif cls_id in (b"\x10\x02", b"\x10\x03"):
                try:
                    UBXReader.parse(frame)
                    samples = _esf_samples(cls_id, frame[6:-2])
                except Exception as err:
                    rep.skip(SkipReason.MALFORMED, start, f"{kind}: {err}")
                    continue
                for tag, row_imu in samples:
                    esf.append((last_pvt_utc, tag, row_imu))
                rep.record(kind)
            else:
                rep.ignore(kind)
            continue
        # NMEA candidate: up to the line end, the next sync or the next '$'
        e = _NMEA_END_RE.search(data, start + 1, min(size, start + _NMEA_MAX))
        end = e.start() if e is not None else min(size, start + _NMEA_MAX)
        frag = data[start:end]
        flush_garbage(start)
        units += 1
        framer.sentence(frag.strip(), math.nan, start)
        pos = end
        while pos < size and data[pos] in (0x0D, 0x0A):
            pos += 1
    flush_garbage(size)
    rep.units = units
    if n_frames == 0 and framer.well_formed == 0:
        raise IngestError(label, "no UBX frames or NMEA sentences found; expected a u-blox binary log")
    pvt = pd.DataFrame(pvt_rows)
    pvt_utc = pvt["utc"].to_numpy(dtype=float) if len(pvt) else np.empty(0)
    nmea = asm.finish(clock="utc", drop_utc=pvt_utc, drop_tol_s=_DUP_TOL_S)
    frames = [f for f in (pvt, nmea) if len(f)]
    gnss = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(GNSS_COLUMNS))
    gnss = _monotonic_pvt(gnss, rep)
    imu = _imu_table(esf, pvt_utc, rep)
    if framer.trailing:
        rep.notes.append(f"{framer.trailing} NMEA sentences had bytes after their checksum (ignored)")
    return Part.make(rep, "utc", gnss=gnss, imu=imu)


def _frame_at(data: bytes, i: int) -> bytes | None:
    """The complete, checksum-valid UBX frame starting at ``i``, or None."""
    if i + 8 > len(data):
        return None
    length = data[i + 4] | (data[i + 5] << 8)
    if length > _MAX_PAYLOAD or i + 8 + length > len(data):
        return None
    body = data[i + 2 : i + 6 + length]
    if fletcher8(body) != data[i + 6 + length : i + 8 + length]:
        return None
    return data[i : i + 8 + length]


def _monotonic_pvt(gnss: pd.DataFrame, rep: FileReport) -> pd.DataFrame:
    """Sort epochs by time; drop (and count) those that do not advance past the last one."""
    if len(gnss) == 0:
        return gnss
    order = np.argsort(gnss["t"].to_numpy(dtype=float), kind="stable")
    gnss = gnss.iloc[order].reset_index(drop=True)
    t = gnss["t"].to_numpy(dtype=float)
    keep = np.ones(len(t), dtype=bool)
    keep[1:] = np.diff(t) > 0
    # Only NAV-PVT epochs can repeat a time here: NMEA cycles are strictly increasing from the
    # assembler and those within 5 ms of a NAV-PVT epoch were already dropped.
    n_bad = int((~keep).sum())
    if n_bad:
        rep.records["UBX NAV-PVT"] -= n_bad
        rep.skip(SkipReason.NON_MONOTONIC, -1, f"{n_bad} NAV-PVT epochs repeat a time", n=n_bad)
    return coerce(gnss.loc[keep], GNSS_COLUMNS)


def _imu_table(
    esf: list[tuple[float, int, dict[str, float]]], pvt_utc: np.ndarray, rep: FileReport
) -> pd.DataFrame | None:
    if not esf:
        return None
    anchor_utc, tag0, _ = esf[0]
    if anchor_utc != anchor_utc:
        anchor_utc = float(pvt_utc[0]) if pvt_utc.size else math.nan
    if anchor_utc != anchor_utc:
        rep.notes.append("ESF samples but no NAV-PVT with a valid time: IMU t unknown (NaN)")
    rows = []
    for _anchor, tag, row in esf:
        dt = ((tag - tag0) & 0xFFFFFFFF) * 1e-3
        rows.append({"t": anchor_utc + dt, **row})
    rep.notes.append(
        "ESF sensor time tags (ms) anchored to the UTC of the NAV-PVT preceding the first ESF "
        "message; the IMU-GNSS offset is known to about one navigation epoch"
    )
    return coerce(pd.DataFrame(rows), IMU_COLUMNS)
