"""Live IMU fusion of raw GNSS + IMU batches: through a real ``iotnav serve`` and mosquitto, and in process.

The drive is a short simulated car run (``car-tunnel``, 100 Hz IMU, 1 Hz GNSS) written to
``gnss.nmea`` + ``imu.csv`` and read back with :func:`iotnav.io.ingest`, the reader of
``iotnav run``. The expected positions are the offline batch run of the same log with the same
engine (``run_batch(make_engine("pipeline"), log)``, what ``iotnav run --engine pipeline``
computes): the service must store exactly those values at its output times.
"""

from __future__ import annotations

import asyncio
import math
import sqlite3
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx
import numpy as np
import pandas as pd
import pytest

from _service_helpers import Mosquitto, Service

DEVICE = "car-1"


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, pd.DataFrame]:
    """The log of a 24 s drive (starts moving at 4 s) and its offline pipeline run."""
    from iotnav import sim
    from iotnav.engines.base import run_batch
    from iotnav.engines.registry import make_engine
    from iotnav.io import ingest

    out = tmp_path_factory.mktemp("drive")
    res = sim.build("car-tunnel", seed=5, overrides={"duration_s": 24.0, "motion.wait_start_s": 4.0})
    sim.write(res, out)
    log = ingest([out])
    return log, run_batch(make_engine("pipeline"), log)


def _expected_times(log, offline: pd.DataFrame, interval: float = 1.0) -> list[float]:
    """Output times of the documented rule: the first output at or after each fix, one per interval."""
    t = offline["t"].to_numpy()
    fixes = log.gnss["t"].to_numpy()
    out, nxt, want, j = [], -math.inf, False, 0
    for k in range(len(t)):
        while j < len(fixes) and fixes[j] <= t[k]:
            want, j = True, j + 1
        if offline["source"].iloc[k] == "none" or not math.isfinite(offline["lat"].iloc[k]):
            continue
        if want or t[k] >= nxt:
            out.append(float(t[k]))
            want, nxt = False, (math.floor(t[k] / interval) + 1) * interval
    return out


def _rows(db: Path | str, engine: str) -> list[tuple]:
    con = sqlite3.connect(db, timeout=10)
    try:
        return con.execute(
            "SELECT json_extract(attributes, '$.t_device'), latitude, longitude, altitude, accuracy_m, fix_time"
            " FROM positions WHERE engine = ? ORDER BY fix_time",
            (engine,),
        ).fetchall()
    finally:
        con.close()


def _assert_equal_to_offline(rows: list[tuple], log, offline: pd.DataFrame) -> None:
    t = offline["t"].to_numpy()
    assert [r[0] for r in rows] == _expected_times(log, offline)
    for t_dev, lat, lon, alt, acc, fix_time in rows:
        k = int(np.searchsorted(t, t_dev))
        o = offline.iloc[k]
        assert t[k] == t_dev
        assert (lat, lon, alt) == (o["lat"], o["lon"], o["height"])  # bit for bit
        assert acc == math.hypot(o["std_north"], o["std_east"])
        assert fix_time == t_dev + log.utc_offset_s


def _count(db: Path, sql: str) -> int:
    con = sqlite3.connect(db, timeout=10)
    try:
        return int(con.execute(sql).fetchone()[0])
    finally:
        con.close()


def test_serve_runs_the_pipeline_live_on_raw_batches_equal_to_offline(tmp_path, drive) -> None:
    import aiomqtt

    from iotnav.service.raw_ingest import log_batches

    log, offline = drive
    batches = list(log_batches(log))
    broker = Mosquitto(tmp_path / "broker").start()
    svc = Service(tmp_path / "data", mqtt=broker.url, mqtt_client_id="iotnav-raw-test", raw_engine="pipeline")
    db = tmp_path / "data" / "iotnav.sqlite"
    try:
        svc.start()

        async def publish() -> None:
            async with aiomqtt.Client("127.0.0.1", broker.port, identifier="car-sim") as c:
                t_end = time.monotonic() + 60
                while _count(db, "SELECT count(*) FROM raw_messages") == 0 and time.monotonic() < t_end:
                    # until the service has subscribed; a batch resent is stored once (same bytes)
                    await c.publish(f"iotnav/{DEVICE}/raw", batches[0], qos=1)
                    await asyncio.sleep(0.5)
                for p in batches[1:]:
                    await c.publish(f"iotnav/{DEVICE}/raw", p, qos=1)
                await c.publish(f"iotnav/{DEVICE}/raw", b'{"v": 1, "imu": [[1, 2]]}', qos=1)  # rejected

        asyncio.run(publish())
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end and _count(db, "SELECT count(*) FROM raw_messages") < len(batches):
            time.sleep(0.2)
        assert _count(db, "SELECT count(*) FROM raw_messages WHERE protocol = 'iotnav_raw'") == len(batches)
        assert _count(db, "SELECT count(*) FROM positions WHERE engine = 'none'") == len(log.gnss)
        rows = _rows(db, "pipeline")
        assert len(rows) >= len(log.gnss) - 1  # at each fix but the last (no IMU sample after it)
        _assert_equal_to_offline(rows, log, offline)
        assert _count(db, "SELECT count(*) FROM engine_states WHERE engine = 'pipeline'") == 1
        # The API (and the map) show this device's fused track without being told its engine,
        # although the service's engine for fix-only devices is another one.
        api = f"http://127.0.0.1:{svc.api}"
        auth = {"Authorization": f"Bearer {svc.admin_token}"}
        (dev,) = httpx.get(f"{api}/api/devices", headers=auth).json()
        t0, t1 = rows[0][5], rows[-1][5]
        period = {"deviceId": dev["id"], "from": _iso(t0 - 1.0), "to": _iso(t1 + 1.0)}
        track = httpx.get(f"{api}/api/positions", params=period, headers=auth).json()
        assert len(track) == len(rows)
        assert [p["latitude"] for p in track] == [r[1] for r in rows]
        (last,) = httpx.get(f"{api}/api/positions", params={"deviceId": dev["id"]}, headers=auth).json()
        assert (last["latitude"], last["longitude"]) == (rows[-1][1], rows[-1][2])
        raw = httpx.get(f"{api}/api/positions", params={**period, "engine": "none"}, headers=auth).json()
        assert 0 < len(raw) != len(track)
    finally:
        svc.stop()
        broker.stop()


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).isoformat().replace("+00:00", "Z")


def test_checkpoint_resume_rerun_and_stale_batches_in_process(tmp_path, drive) -> None:
    """A restart half-way (a fresh processor, state from the checkpoint) and batches stored several to a
    transaction change nothing; the stored
    raw batches re-run offline give the same track; a resent or stale batch is not fed again."""
    from iotnav.engines.base import run_batch
    from iotnav.engines.registry import make_engine
    from iotnav.service import store
    from iotnav.service.checkpoint import load_key
    from iotnav.service.ingest import Ingestor
    from iotnav.service.protocols.iotnav_raw import RawBatch, decode
    from iotnav.service.raw_ingest import RawProcessor, log_batches, raw_log

    log, offline = drive
    batches = list(log_batches(log))
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    key = load_key(tmp_path)

    def processor() -> RawProcessor:
        return RawProcessor(Ingestor(db, "none", checkpoint_key=key))

    def send(rp: RawProcessor, p: bytes):
        b = decode(p, DEVICE)
        assert isinstance(b, RawBatch)
        return rp.ingest(p, b)

    rp = processor()
    half = len(batches) // 2
    for p in batches[:half]:
        send(rp, p)
    rp = processor()  # the service restarted: the device's state comes from its checkpoint
    assert send(rp, batches[half - 1]).duplicate  # a redelivered batch: stored once, not fed
    rest = batches[half:]
    for k in range(0, len(rest), 3):  # several batches in one transaction, as MQTT hands them over
        group = [(p, decode(p, DEVICE), None) for p in rest[k : k + 3]]
        assert all(r.accepted and not r.duplicate for r in rp.ingest_many(group))  # type: ignore[arg-type]
    assert rp.ingestor.counts["checkpoint_restored"] == 1
    stale = decode(batches[2], DEVICE)  # the same samples in a new message (other bytes)
    assert isinstance(stale, RawBatch)
    res = rp.ingest(batches[2] + b" ", stale)
    assert res.accepted and not res.duplicate and res.n_engine == 0
    assert rp.ingestor.counts["raw_imu_time_backwards"] == len(stale.imu)
    rows = _rows(str(db.url.database), "pipeline")
    _assert_equal_to_offline(rows, log, offline)
    again = run_batch(make_engine("pipeline"), raw_log(db, DEVICE))  # what `iotnav run` re-runs
    assert len(again) == len(offline)  # the stale copy is stored but, as live, not fed
    assert np.array_equal(again["lat"].to_numpy(), offline["lat"].to_numpy(), equal_nan=True)


def test_engine_per_device_and_group() -> None:
    from iotnav.service.raw_ingest import RawSettings

    s = RawSettings(engines={"truck-*": "eskf", "bike-?": "anchor:bike.toml"})
    assert s.choose("car-1", {}) == ("pipeline", None)
    assert s.choose("truck-12", None) == ("eskf", None)
    assert s.choose("bike-7", {}) == ("anchor", "bike.toml")
    assert s.choose("truck-12", {"engine": "qekf"}) == ("qekf", None)  # the device's own setting first
    with pytest.raises(ValueError, match="raw engine 'kalman'"):
        RawSettings(engines={"*": "kalman"})
