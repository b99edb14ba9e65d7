"""Two ingest processes on one SQLite file: what the write lock costs (issue 18), A/B in one run.

``iotnav serve --processes 2`` runs one :class:`~iotnav.service.ingest.Ingestor` per worker
process on the same SQLite file, each transaction in ``BEGIN IMMEDIATE``. This benchmark
takes the network out: ``--writers`` processes start together, each with ``--devices`` devices
of its own (one Teltonika Codec 8 record per message, engine ``fixes``), register them, then
store ``--ticks`` messages per device by :meth:`~iotnav.service.ingest.Ingestor.ingest_batch`
in batches of ``--batch`` messages, as the group commit of a loaded service does. Each device
moves east at 0.74 m/s with a matching speed and course, as in ``bench_service_load.py`` (so
the engine accepts its fixes; before 2026-12-03 the track went north at 11 m/s with an eastward
course, and nearly every fix was a rejection event). Measured: the wall time of the timed part
(first start to last end), the messages per second of all writers together, and the writers'
CPU time per message (their own time, less sensitive to the machine's other jobs than the wall
time). This source tree and ``--reference-src`` alternate, ``--repeats`` times each; medians
reported.

Run: ``PYTHONPATH=src python benchmarks/bench_service_lock.py --reference-src REF/src``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SRC = str(Path(__file__).resolve().parent.parent / "src")
TESTS = str(Path(__file__).resolve().parent.parent / "tests")

WRITER = r"""
import json, sys, time
from _service_helpers import codec8_packet
from iotnav.service import store
from iotnav.service.ingest import Ingestor, Message
from iotnav.service.protocols.teltonika import decode_avl

url, index, n_dev, ticks, batch, start_at = sys.argv[1], int(sys.argv[2]), *map(int, sys.argv[3:6]), float(sys.argv[6])
db = store.make_engine(url, immediate=True)
ing = Ingestor(db, "fixes", checkpoint_key=b"k" * 32)
ing.warm_up()
imeis = [f"35{index:04d}{d:09d}" for d in range(n_dev)]
T0 = 1_700_000_000_000

def msgs(tick):
    out = []
    for d, imei in enumerate(imeis):
        lat, lon = 48.0 + 1e-3 * (d % 1000), 11.0 + 1e-3 * (d // 1000) + 1e-5 * tick
        p = codec8_packet([(T0 + 1000 * tick, lat, lon, 3, 9)])
        out.append(Message("teltonika", imei, p, decode_avl(p, imei).records))
    return out

work = [msgs(t) for t in range(ticks + 1)]
for b in range(0, n_dev, batch):
    ing.ingest_batch(work[0][b : b + batch])
while time.time() < start_at:
    time.sleep(0.001)
t0, c0 = time.time(), time.process_time()
n = 0
for m in work[1:]:
    for b in range(0, n_dev, batch):
        res = ing.ingest_batch(m[b : b + batch])
        assert not any(isinstance(r, Exception) for r in res), res
        n += len(res)
t1, c1 = time.time(), time.process_time()
print(json.dumps({"t0": t0, "t1": t1, "cpu": c1 - c0, "n": n, "counts": ing.counts}))
"""


def run(src: str, writers: int, devices: int, ticks: int, batch: int) -> dict[str, float]:
    """One run of ``writers`` processes of the service in ``src`` on a fresh SQLite file."""
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/iotnav.sqlite"
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([src, TESTS])}
        subprocess.run(
            [
                sys.executable,
                "-c",
                f"from iotnav.service import store; store.upgrade(store.make_engine({url!r}))",
            ],
            env=env,
            check=True,
        )
        start_at = time.time() + 15.0  # after every writer's imports, warm-up and registration
        procs = [
            subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    WRITER,
                    url,
                    str(i),
                    str(devices),
                    str(ticks),
                    str(batch),
                    str(start_at),
                ],
                env=env,
                stdout=subprocess.PIPE,
            )
            for i in range(writers)
        ]
        outs = [json.loads(p.communicate(timeout=600)[0].decode().strip().splitlines()[-1]) for p in procs]
        if any(p.returncode for p in procs):
            raise RuntimeError("a writer failed")
        if any(o["t0"] - start_at > 1.0 for o in outs):
            raise RuntimeError("a writer started late (registration longer than the head start)")
    wall = max(o["t1"] for o in outs) - min(o["t0"] for o in outs)
    n = sum(o["n"] for o in outs)
    cpu = sum(o["cpu"] for o in outs)
    return {"wall_s": wall, "msgs": n, "rate": n / wall, "cpu_us_per_msg": 1e6 * cpu / n}


def main() -> None:
    """Alternate this tree and the reference; print the medians (and the load average)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference-src", required=True)
    ap.add_argument("--writers", type=int, default=2)
    ap.add_argument("--devices", type=int, default=1000, help="devices per writer")
    ap.add_argument("--ticks", type=int, default=10, help="messages per device (timed)")
    ap.add_argument("--batch", type=int, default=500, help="messages per transaction")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if args.devices * args.ticks > 100_000 or args.repeats > 10:
        ap.error("bounded: at most 100,000 messages per writer and 10 repeats")
    res: dict[str, list[dict[str, float]]] = {"this": [], "reference": []}
    loads = [os.getloadavg()[0]]
    for _ in range(args.repeats):
        for name, src in (("this", SRC), ("reference", args.reference_src)):
            r = run(src, args.writers, args.devices, args.ticks, args.batch)
            print(name, json.dumps(r), f"load {os.getloadavg()[0]:.1f}", flush=True)
            res[name].append(r)
            loads.append(os.getloadavg()[0])
    for name, rs in res.items():
        rate = statistics.median(r["rate"] for r in rs)
        runs = ", ".join(f"{r['rate']:,.0f}" for r in rs)
        cpu = statistics.median(r["cpu_us_per_msg"] for r in rs)
        cpus = ", ".join(f"{r['cpu_us_per_msg']:.1f}" for r in rs)
        print(
            f"{name}: {args.writers} writers x {args.devices} devices x {args.ticks} messages, batches of "
            f"{args.batch}: median {rate:,.0f} messages/s (runs: {runs}); writers' CPU median "
            f"{cpu:.1f} us/message (runs: {cpus})"
        )
    print(f"load average (1 min) over the runs: {min(loads):.1f} to {max(loads):.1f}")


if __name__ == "__main__":
    main()
