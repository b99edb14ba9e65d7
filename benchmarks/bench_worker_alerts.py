"""Cost of the alerts on a worker: one partition's ingest with and without :class:`AlertingIngestor`.

The same messages (one-fix Teltonika messages of ``--devices`` devices, ``--batch`` per
transaction, as a worker's fetch hands them over) are stored by a plain
:class:`iotnav.service.ingest.Ingestor` and by :class:`iotnav.service.workers.AlertingIngestor`
(default group: every zone, overspeed at 30 km/h; one circular zone) into two fresh databases
of a throw-away PostgreSQL. Reported: this process's CPU per message (the worker's side) and
the PostgreSQL processes' CPU per message, for each; and the same after a failover (a new
ingestor: the first batch of each device rebuilds its rule state from the database).

    PYTHONPATH=src python benchmarks/bench_worker_alerts.py --devices 200 --per-device 20
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _cluster_helpers import new_database
from _service_helpers import Postgres
from bench_workers import messages, pg_cpu
from iotnav.alerts import ALERT_KINDS
from iotnav.service import store
from iotnav.service.alerts_delivery import AlertSettings
from iotnav.service.ingest import Ingestor
from iotnav.service.workers import AlertingIngestor, open_database


def run(pg: Postgres, name: str, alerts: bool, msgs: list, batch: int, engine: str) -> dict[str, float]:
    db = open_database(new_database(pg, name), 4)
    with db.begin() as con:
        con.execute(store.geofences.insert().values(name="z", area="CIRCLE (45.05 7.0, 3000)", attributes={}))
    settings = AlertSettings.load({"groups": {"default": {"geofences": True, "overspeed_kmh": 30}}})

    def make() -> Ingestor:
        if alerts:
            return AlertingIngestor(db, engine, alert_settings=settings)
        return Ingestor(db, engine)

    out = {}
    half = len(msgs) // 2
    for label, part, ing in (("first", msgs[:half], make()), ("failover", msgs[half:], make())):
        ing.warm_up()
        c0, p0, t0 = time.process_time(), pg_cpu(pg), time.perf_counter()
        for b in range(0, len(part), batch):
            res = ing.ingest_batch(part[b : b + batch])
            assert not any(isinstance(r, Exception) for r in res), res
        out[f"{label}_worker_ms"] = 1e3 * (time.process_time() - c0) / len(part)
        out[f"{label}_pg_ms"] = 1e3 * (pg_cpu(pg) - p0) / len(part)
        out[f"{label}_wall_ms"] = 1e3 * (time.perf_counter() - t0) / len(part)
        if alerts:
            got = sum(ing.alerts.counts.get(f"alerts_{k}", 0) for k in ALERT_KINDS)
            out["alerts"] = out.get("alerts", 0) + got
    db.dispose()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=200)
    ap.add_argument("--per-device", type=int, default=20)
    ap.add_argument("--batch", type=int, default=200)
    ap.add_argument("--engine", default="none")
    args = ap.parse_args()
    msgs = messages(args.devices, args.per_device)
    pg = Postgres().start()
    try:
        rows = {a: run(pg, f"bench_alerts_{int(a)}", a, msgs, args.batch, args.engine) for a in (False, True)}
    finally:
        pg.stop()
    print(f"{len(msgs)} messages, {args.devices} devices, batches of {args.batch}, engine {args.engine}")
    print("| ingest | phase | worker CPU ms/msg | PostgreSQL CPU ms/msg | wall ms/msg |")
    print("|---|---|---|---|---|")
    for a, r in rows.items():
        for ph in ("first", "failover"):
            name = "AlertingIngestor" if a else "Ingestor"
            w, p, t = r[f"{ph}_worker_ms"], r[f"{ph}_pg_ms"], r[f"{ph}_wall_ms"]
            print(f"| {name} | {ph} | {w:.3f} | {p:.3f} | {t:.3f} |")
    print(f"alerts raised: {rows[True].get('alerts', 0)}")


if __name__ == "__main__":
    main()
