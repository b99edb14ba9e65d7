"""Raw NMEA 0183 over TCP (:mod:`iotnav.service.nmea_tcp`) with real sockets.

The sentences are the classic GGA / RMC example of the NMEA reference (position 48 deg
07.038' N, 011 deg 31.000' E, 545.4 m above MSL, geoid separation 46.9 m, 22.4 kn on course
84.4 deg), with the date moved to 2024-03-23 and the time stepped by a second per cycle;
checksums are XORs written by :func:`iotnav.io.nmea_writer.sentence`.
"""

from __future__ import annotations

import asyncio
import math
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime

import sqlalchemy as sa

from iotnav.io.nmea_writer import sentence
from iotnav.service import store
from iotnav.service.ingest import Ingestor
from iotnav.service.nmea_tcp import NmeaServer, NmeaSettings
from iotnav.service.store import devices, positions

LAT = 48 + 7.038 / 60
LON = 11 + 31.0 / 60


def _cycle(k: int) -> list[str]:
    hms = f"1235{19 + k:02d}"
    return [
        sentence(f"GPGGA,{hms},4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        sentence(f"GPRMC,{hms},A,4807.038,N,01131.000,E,022.4,084.4,230324,003.1,W"),
    ]


def _t(k: int) -> float:
    return datetime(2024, 3, 23, 12, 35, 19 + k, tzinfo=UTC).timestamp()


def test_nmea_over_tcp_ids_fixes_and_bad_sentences(tmp_path) -> None:
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ing = Ingestor(db, "none")
    executor = ThreadPoolExecutor(max_workers=1)

    async def main() -> None:
        plain = NmeaServer(ing, executor, NmeaSettings(device_id="receiver-1"))
        server = await plain.start("127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        no_id = NmeaServer(ing, executor)
        server2 = await no_id.start("127.0.0.1", 0)
        port2 = server2.sockets[0].getsockname()[1]

        async def send(p: int, lines: list[str]) -> bytes:
            r, w = await asyncio.open_connection("127.0.0.1", p)
            w.write("".join(line + "\r\n" for line in lines).encode())
            await w.drain()
            w.write_eof()
            answer = await asyncio.wait_for(r.read(), 10)  # the server closes after the last line
            w.close()
            return answer

        bad = [
            "$GPGGA,123530,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*00",  # wrong checksum
            "\x00\x01garbage",
            "$GPGGA,123531,4807.0",  # truncated
        ]
        tracker = ["356307042441013", *_cycle(0), bad[0], *_cycle(1), bad[1], *_cycle(2), bad[2]]
        await send(port, tracker)  # an id line first (a tracker's login)
        await send(port, [sentence("PGID,boat-7"), *_cycle(0), *_cycle(1)])  # Traccar T55's id sentence
        await send(port, [*_cycle(0)])  # a receiver that prints NMEA only: the port's configured id
        await send(port2, [*_cycle(0)])  # ... and without one: refused
        await send(port, ["bad id with blanks", *_cycle(0)])
        server.close()
        server2.close()

    asyncio.run(main())
    executor.shutdown(wait=True)
    with db.connect() as conn:
        got = conn.execute(
            sa.select(devices.c.unique_id, positions.c.fix_time, positions.c.latitude, positions.c.longitude)
            .join(devices, devices.c.id == positions.c.device_id)
            .order_by(devices.c.unique_id, positions.c.fix_time)
        ).all()
        alt, speed, course = conn.execute(
            sa.select(positions.c.altitude, positions.c.speed_mps, positions.c.course_rad).limit(1)
        ).one()
    by_dev: dict[str, list[float]] = {}
    for dev, t, lat, lon in got:
        assert math.isclose(lat, LAT, abs_tol=1e-12) and math.isclose(lon, LON, abs_tol=1e-12)
        by_dev.setdefault(dev, []).append(t)
    assert by_dev == {
        "356307042441013": [_t(0), _t(1), _t(2)],
        "boat-7": [_t(0), _t(1)],
        "receiver-1": [_t(0)],
    }
    assert math.isclose(alt, 545.4 + 46.9) and math.isclose(speed, 22.4 * 1852 / 3600)
    assert math.isclose(course, math.radians(84.4))
    c = ing.counts
    assert c["nmea_rejected_bad_checksum"] == 1
    assert c["nmea_rejected_not_a_record"] == 1
    assert c["nmea_rejected_truncated"] == 1
    assert c["nmea_rejected_no_device"] == 1 and c["nmea_rejected_bad_device_id"] == 1
    assert c["records"] == 6
