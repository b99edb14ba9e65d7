"""Load on ``iotnav serve`` from devices streaming 100 Hz IMU: raw batches over MQTT, live pipeline.

Issue #18's figure "100 devices streaming 100 Hz IMU". The benchmark starts a real mosquitto
(Debian ``mosquitto``) and a real ``iotnav serve`` subprocess (``raw_engine = "pipeline"``,
SQLite in a temporary directory, free 127.0.0.1 ports), then ``--devices`` MQTT clients each
publish, once a second (phases spread over the second), one raw batch
(:mod:`iotnav.service.protocols.iotnav_raw`, JSON or ``--binary``) on ``iotnav/<id>/raw``
with QoS 1: 100 IMU samples and one GNSS fix of a car driving straight North at 10 m/s
(specific force ``g`` up plus white noise of an MPU-6050 class sensor, 400 ug/sqrt(Hz) and
0.005 deg/s/sqrt(Hz) from its datasheet; fixes with 2.5 m noise), for ``--duration`` s. A
listener on ``/api/socket`` (own process) timestamps every clean position; measured:

- *visible*: from the publish of batch ``k`` to the arrival of its first position on the
  socket (commit and broadcast done);
- *stored*: the raw batches and IMU samples in the database at the end (every published batch
  must be stored once the service has drained the broker's queue: ``lost`` must be 0);
- *drain*: seconds after the last publish until the last batch is stored (backlog);
- service CPU from ``/proc/PID/stat`` over the run.

Run: ``.venv/bin/python benchmarks/bench_service_imu_load.py --devices 100 --duration 30``;
with ``IOTNAV_WRITE_RESULTS=1`` the table goes to ``benchmarks/results/service_imu_load.md``.
Bounded: at most 500 devices and 300 s, localhost only.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing as mp
import os
import sqlite3
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from _service_helpers import Mosquitto, Service
from iotnav.service.protocols.iotnav_raw import GnssRecord, encode_binary, encode_json

T0 = 1_700_000_000.0  # device time of second 0 (Unix time: utc_offset_s = 0)
RATE_HZ = 100
ACC_NOISE_MPS2 = 400e-6 * 9.80665 * math.sqrt(RATE_HZ / 2)  # 400 ug/sqrt(Hz) (MPU-6050 datasheet)
GYRO_NOISE_RADS = math.radians(0.005) * math.sqrt(RATE_HZ / 2)  # 0.005 deg/s/sqrt(Hz)
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def batches(i: int, seconds: int, binary: bool) -> list[bytes]:
    """Device ``i``'s batch of each second: 100 IMU samples and the fix at the second's start."""
    rng = np.random.default_rng(i)
    out = []
    lat0, lon0 = 45.0 + 1e-3 * i, 7.6
    for k in range(seconds):
        t = T0 + k + np.arange(RATE_HZ) / RATE_HZ
        imu = np.column_stack(
            [
                t,
                rng.normal(0.0, ACC_NOISE_MPS2, (RATE_HZ, 2)),
                9.80665 + rng.normal(0.0, ACC_NOISE_MPS2, RATE_HZ),
                rng.normal(0.0, GYRO_NOISE_RADS, (RATE_HZ, 3)),
            ]
        )
        north = 10.0 * k + rng.normal(0.0, 2.5)
        lat = lat0 + math.degrees(north / 6_378_137.0)
        g = GnssRecord(T0 + k, lat, lon0, 300.0, 2.5, speed_mps=10.0, course_rad=0.0, hdop=0.9, num_sv=10)
        if binary:
            out.append(encode_binary(T0 + k, imu, [g]))
        else:
            fix = {"t": g.t, "lat": lat, "lon": lon0, "alt": 300.0, "acc": 2.5, "speed": 10.0, "course": 0.0}
            out.append(encode_json(imu, [fix | {"hdop": 0.9, "nsat": 10}]))
    return out


def _listen(url: str, token: str, until: float, out: str, ready: Any, stop: Any) -> None:
    """WebSocket client (own process): (deviceId, fixTime s, receive time) of each position."""
    import websockets

    async def run() -> None:
        got: list[tuple[int, float, float]] = []
        async with websockets.connect(url, additional_headers={"Authorization": f"Bearer {token}"}) as ws:
            ready.set()
            while time.time() < until and not stop.is_set():
                try:
                    msg = await asyncio.wait_for(ws.recv(), timeout=0.5)
                except TimeoutError:
                    continue
                now = time.time()
                for p in json.loads(msg).get("positions", []):
                    t = datetime.fromisoformat(p["fixTime"].replace("Z", "+00:00")).timestamp()
                    got.append((int(p["deviceId"]), t, now))
        Path(out).write_text(json.dumps(got))

    asyncio.run(run())


async def _publish(port: int, payloads: list[list[bytes]]) -> tuple[list[list[float]], float]:
    """Publish each device's batch ``k`` at second ``k`` (phases spread); the publish times."""
    import aiomqtt

    n = len(payloads)
    sent: list[list[float]] = [[] for _ in range(n)]
    t_start = time.time() + 2.0

    async def device(i: int) -> None:
        async with aiomqtt.Client("127.0.0.1", port, identifier=f"imu-{i}") as c:
            for k, p in enumerate(payloads[i]):
                await asyncio.sleep(max(0.0, t_start + k + i / n - time.time()))
                sent[i].append(time.time())
                await c.publish(f"iotnav/imu-{i:04d}/raw", p, qos=1)

    await asyncio.gather(*(device(i) for i in range(n)))
    return sent, time.time() - t_start


def measure(n: int, duration: int, binary: bool) -> dict[str, Any]:
    """``n`` devices for ``duration`` s against a fresh service and broker; the numbers."""
    payloads = [batches(i, duration, binary) for i in range(n)]
    with tempfile.TemporaryDirectory(prefix="iotnav-imu-load-") as tmp:
        broker = Mosquitto(Path(tmp) / "broker")
        # no cap on the service session's queue (default 1000) nor on its unacknowledged messages
        # (default 20: with acknowledgement after commit, 20 batches a commit at most)
        conf = broker.dir / "mosquitto.conf"
        conf.write_text(conf.read_text() + "max_queued_messages 0\nmax_inflight_messages 0\n")
        broker.start()
        svc = Service(
            Path(tmp) / "data", mqtt=broker.url, mqtt_client_id="iotnav-imu-load", raw_engine="pipeline"
        ).start(timeout=300)
        db = Path(tmp) / "data" / "iotnav.sqlite"
        try:
            assert svc.proc is not None
            ctx = mp.get_context("spawn")
            ready, stop = ctx.Event(), ctx.Event()
            out = str(Path(tmp) / "ws.json")
            url = f"ws://127.0.0.1:{svc.api}/api/socket"
            ws = ctx.Process(
                target=_listen,
                args=(url, svc.admin_token, time.time() + 3 * duration + 300, out, ready, stop),
            )
            ws.start()
            if not ready.wait(60):
                raise RuntimeError("WebSocket listener did not connect")
            cpu0, w0 = _cpu_s(svc.proc.pid), time.time()
            sent, wall = asyncio.run(_publish(broker.port, payloads))
            t_last = time.time()
            cpu = (_cpu_s(svc.proc.pid) - cpu0) / (t_last - w0)  # over the load phase
            total = n * duration
            stored, t_drained = 0, math.nan
            while time.time() < t_last + 2 * duration + 120:
                con = sqlite3.connect(db, timeout=30)
                stored = con.execute("SELECT count(*) FROM raw_messages").fetchone()[0]
                con.close()
                if stored >= total:
                    t_drained = time.time()
                    break
                time.sleep(0.5)
            time.sleep(2.0)
            stop.set()
            ws.join(60)
            con = sqlite3.connect(db, timeout=30)
            ids = {int(v): k for k, v in con.execute("SELECT unique_id, id FROM devices").fetchall()}
            n_imu = con.execute("SELECT coalesce(sum(n_records), 0) FROM raw_messages").fetchone()[0]
            n_pos = con.execute("SELECT count(*) FROM positions WHERE engine = 'pipeline'").fetchone()[0]
            stored_at: dict[str, list[float]] = {}
            for uid, t in con.execute(
                "SELECT d.unique_id, r.received_at FROM raw_messages r JOIN devices d ON d.id = r.device_id"
                " ORDER BY r.id"
            ):
                stored_at.setdefault(uid, []).append(t)
            con.close()
        finally:
            svc.stop()
            broker.stop()
        got = json.loads(Path(out).read_text()) if Path(out).exists() else []
    first: dict[tuple[int, int], float] = {}
    for dev, t, recv in got:
        uid = ids.get(dev)
        if uid is not None:
            first.setdefault((int(uid.split("-")[1]), int(t - T0)), recv)
    vis = np.array([first[(i, k)] - sent[i][k] for i in range(n) for k in range(duration) if (i, k) in first])

    rec = np.array(
        [t - sent[i][k] for i in range(n) for k, t in enumerate(stored_at.get(f"imu-{i:04d}", []))]
    )

    def pct(q: float, a: np.ndarray = vis) -> float:
        return float(np.percentile(a, q)) if a.size else math.nan

    return {
        "devices": n,
        "encoding": "binary" if binary else "JSON",
        "bytes_per_batch": int(np.mean([len(p) for p in payloads[0]])),
        "duration_s": wall,
        "published": total,
        "stored": int(stored),
        "imu_samples": int(n_imu) - total,  # n_records counts the fix too
        "imu_per_s": (int(n_imu) - total) / max(wall, 1e-9),
        "positions": int(n_pos),
        "vis_p50": pct(50),
        "vis_p99": pct(99),
        "vis_max": float(vis.max()) if vis.size else math.nan,
        "recv_p50": pct(50, rec),
        "recv_p99": pct(99, rec),
        "seen": int(vis.size),
        "drain_s": t_drained - t_last,
        "lost": total - int(stored),
        "cpu_cores": cpu,
    }


def db_thread_ms(n_dev: int = 20, seconds: int = 10, binary: bool = False) -> float:
    """Steady time of one ``RawProcessor.ingest`` (the service's single database thread), ms a batch.

    In-process, SQLite in a temporary directory, after each device's first batch (registration,
    engine start): ``1000 / db_thread_ms`` is the ceiling of the service in batches per second.
    """
    from iotnav.service.app import ServiceConfig, _raw_processor, prepare
    from iotnav.service.protocols.iotnav_raw import decode

    with tempfile.TemporaryDirectory(prefix="iotnav-db-") as tmp:
        _, ing = prepare(ServiceConfig(data=tmp, engine="none"))
        raw = _raw_processor(ServiceConfig(data=tmp), ing)
        payloads = [batches(i, seconds, binary) for i in range(n_dev)]

        def send(k: int) -> None:
            for i in range(n_dev):
                p = payloads[i][k]
                raw.ingest(p, decode(p, f"imu-{i:04d}"))

        send(0)
        t = time.perf_counter()
        for k in range(1, seconds):
            send(k)
        return (time.perf_counter() - t) / (n_dev * (seconds - 1)) * 1e3


HEADER = [
    "## Service load, IMU devices (`benchmarks/bench_service_imu_load.py`)",
    "",
    "MQTT devices each publishing one raw batch a second (100 IMU samples at 100 Hz + one fix, QoS 1)",
    'on `iotnav/<id>/raw`; `iotnav serve` runs `raw_engine = "pipeline"` per device (clean positions',
    "stored at each fix and at 1 Hz), SQLite `synchronous=FULL`, the batches waiting in the MQTT queue",
    "stored in one transaction (each acknowledged after its commit); mosquitto with",
    "`max_queued_messages 0` and `max_inflight_messages 0` (its defaults, 1000 and 20, cap the backlog",
    "and the batches a commit can take); broker,",
    "load generator and WebSocket listener on the same 2-core machine shared with other jobs. *visible*:",
    "publish of a batch to its first position on `/api/socket`. *drain*: time after the last publish",
    "until every batch is stored. *lost*: published but not stored (must be 0).",
    "",
    "| devices | encoding | batch | duration | batches published / stored | IMU samples/s | positions | "
    "visible p50 / p99 / max | drain | lost | service CPU | keeps up |",
    "|---|---|---|---|---|---|---|---|---|---|---|---|",
]


def row(r: dict[str, Any]) -> str:
    """One markdown row of a :func:`measure` result; *keeps up*: visible p99 < 1 s, no backlog, none lost."""
    ok = r["vis_p99"] < 1.0 and r["drain_s"] < 2.0 and r["lost"] == 0
    return (
        f"| {r['devices']} | {r['encoding']} | {r['bytes_per_batch'] / 1000:.1f} kB | {r['duration_s']:.0f} s | "
        f"{r['published']:,} / {r['stored']:,} | {r['imu_per_s']:,.0f} | {r['positions']:,} | "
        f"{r['vis_p50'] * 1e3:.0f} / {r['vis_p99'] * 1e3:.0f} / {r['vis_max'] * 1e3:.0f} ms | "
        f"{r['drain_s']:.1f} s | {r['lost']} | {r['cpu_cores']:.2f} cores | {'yes' if ok else 'no'} |"
    )


def main() -> None:
    """Parse the options, run, print (and optionally write) the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, nargs="+", default=[100], help="device counts to run")
    ap.add_argument("--duration", type=int, default=30, help="seconds of load per run")
    ap.add_argument("--binary", action="store_true", help="binary batches instead of JSON")
    args = ap.parse_args()
    if max(args.devices) > 500 or args.duration > 300:
        ap.error("bounded: at most 500 devices and 300 s")
    load0 = os.getloadavg()[0]
    ms = db_thread_ms(binary=args.binary)
    rows = []
    for n in args.devices:
        r = measure(n, args.duration, args.binary)
        print(json.dumps(r), flush=True)
        rows.append(row(r))
    note = (
        f"\nDatabase thread alone (`RawProcessor.ingest` in-process, one transaction per batch with its "
        f"checkpoint, `synchronous=FULL`): {ms:.1f} ms a batch, a ceiling of {1000 / ms:,.0f} batches/s "
        f"(devices at 1 batch/s). Load average of the machine at the start: {load0:.1f} (2 cores).\n"
    )
    text = "\n".join([*HEADER, *rows]) + "\n" + note
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "service_imu_load.md"
        out.write_text(text)


if __name__ == "__main__":
    main()
