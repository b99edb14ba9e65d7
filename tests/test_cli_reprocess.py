"""``iotnav reprocess``: device-days stored by the service re-run from the command line."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from typer.testing import CliRunner

from _service_helpers import codec8_packet
from iotnav.cli import app
from iotnav.service import store
from iotnav.service.ingest import Ingestor
from iotnav.service.protocols.teltonika import decode_avl

IMEIS = ["352100000000001", "352100000000002"]
DAY0 = 1_700_006_400.0  # 2023-11-15 00:00 UTC


def _stored_fleet(data: Path) -> None:
    """Two devices, 12 fixes each, 10 s apart, six before and six after midnight UTC."""
    db = store.make_engine(store.sqlite_url(data))
    store.upgrade(db)
    ing = Ingestor(db, "fixes")
    for k, imei in enumerate(IMEIS):
        for j in range(12):
            t_ms = int(1000 * (DAY0 - 60 + 10 * j))
            pkt = codec8_packet([(t_ms, 48.0 + 0.01 * k + 1e-4 * j, 16.0, 36, 9)])
            ing.ingest("teltonika", imei, pkt, decode_avl(pkt, imei, 65536).records)
    db.dispose()


def test_reprocess_writes_one_csv_per_device_day_and_a_summary(tmp_path: Path) -> None:
    """Every device-day becomes OUT/<imei>/<day>.csv with one row per fix; filters apply."""
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    _stored_fleet(data)
    res = CliRunner().invoke(app, ["reprocess", "--data", str(data), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "4 of 4 device-days re-run with fixes: 24 fixes read, 24 positions" in " ".join(res.output.split())
    for imei in IMEIS:
        for day in ("2023-11-14", "2023-11-15"):
            with open(out / imei / f"{day}.csv", newline="") as fh:
                rows = list(csv.DictReader(fh))
            assert len(rows) == 6
            times = [float(r["t"]) for r in rows]
            assert times == sorted(times) and all((day == "2023-11-14") == (t < DAY0) for t in times)
    summary = json.loads((out / "reprocess_summary.json").read_text())
    assert [(d["device"], d["day"], d["fixes"]) for d in summary["device_days"]] == [
        (m, d, 6) for m in IMEIS for d in ("2023-11-14", "2023-11-15")
    ]
    # one device, the second day only
    out2 = tmp_path / "out2"
    res = CliRunner().invoke(
        app,
        ["reprocess", "--data", str(data), "--out", str(out2), "--device", IMEIS[1], "--since", "2023-11-15"],
    )
    assert res.exit_code == 0, res.output
    assert sorted(p.relative_to(out2).as_posix() for p in out2.rglob("*.csv")) == [
        f"{IMEIS[1]}/2023-11-15.csv"
    ]


def test_reprocess_refuses_bad_options_with_a_message(tmp_path: Path) -> None:
    """No database, an unknown engine, a date that is not ISO 8601, nothing matching: exit 2, a message."""
    data = tmp_path / "data"
    data.mkdir()
    res = CliRunner().invoke(app, ["reprocess", "--data", str(data), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "no iotnav.sqlite" in res.output
    (data / "iotnav.sqlite").write_bytes(b"")  # an empty file: no service tables
    res = CliRunner().invoke(app, ["reprocess", "--data", str(data), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "cannot read the stored fixes" in " ".join(res.output.split()), res.output
    (data / "iotnav.sqlite").unlink()
    _stored_fleet(data)
    for extra, message in (
        (["--engine", "kalman9"], "unknown engine 'kalman9'"),
        (["--since", "yesterday"], "--since 'yesterday': expected an ISO 8601"),
        (["--until", "2000-01-01"], "no device-day with stored fixes matches"),
    ):
        res = CliRunner().invoke(
            app, ["reprocess", "--data", str(data), "--out", str(tmp_path / "o"), *extra]
        )
        assert res.exit_code == 2, (extra, res.output)
        assert message in " ".join(res.output.split()), (extra, res.output)
