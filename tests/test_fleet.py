"""``iotnav run-many`` / :mod:`iotnav.fleet`: device discovery, local pool, Dask, failures (layer c).

A small simulated fleet (three 20 s car drives, one walk with a stored last position) plus one
broken device is processed by a local pool of 2 workers and by a local Dask cluster; every
output file of a good device must equal, byte for byte, what ``iotnav run`` writes for that
device in this process (``summary.json`` apart from its ``runtime_s``), and the broken device
must be counted and reported, not stop the fleet.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from iotnav import sim
from iotnav.cli import app as main_app
from iotnav.cli import fleet as fleet_cli
from iotnav.fleet import FLEET_SUMMARY, discover_devices, process_device, run_fleet

runner = CliRunner()
GOOD = ("car0", "car1", "car2", "walk")
SAME_FILES = ("track.csv", "events.json", "gnss.csv", "track.geojson", "track.gpx")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fleet")
    for i in range(3):
        sim.write(sim.build("car-tunnel", seed=10 + i, overrides={"duration_s": 20}), root / f"car{i}")
    sim.write(sim.build("walk-cold-boot", seed=3), root / "walk")
    (root / "broken").mkdir()
    (root / "broken" / "gnss.nmea").write_text("this is not a log\n")
    return root


@pytest.fixture(scope="module")
def reference(fleet: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``iotnav run DEVICE --out REF/DEVICE`` for every good device, in this process."""
    ref = tmp_path_factory.mktemp("reference")
    for name in GOOD:
        res = runner.invoke(
            main_app, ["run", str(fleet / name), "--engine", "pipeline", "--out", str(ref / name)]
        )
        assert res.exit_code == 0, res.output
    return ref


def _assert_same_as_reference(out: Path, ref: Path) -> None:
    for name in GOOD:
        for f in SAME_FILES:
            assert (out / name / f).read_bytes() == (ref / name / f).read_bytes(), f"{name}/{f}"
        a = json.loads((out / name / "summary.json").read_text())
        b = json.loads((ref / name / "summary.json").read_text())
        a.pop("runtime_s")
        b.pop("runtime_s")
        assert a == b, name


def _assert_fleet_summary(out: Path, executor: str) -> dict:
    s = json.loads((out / FLEET_SUMMARY).read_text())
    assert s["executor"] == executor
    assert (s["devices_total"], s["devices_ok"], s["devices_failed"]) == (5, 4, 1)
    assert [f["device"] for f in s["failures"]] == ["broken"]
    assert "gnss.nmea" in s["failures"][0]["reason"]  # the reason names the file
    assert [d["device"] for d in s["devices"]] == sorted([*GOOD, "broken"])
    for d in s["devices"]:
        if d["ok"]:
            assert d["counts"]["imu_samples_in"] > 0
            assert d["timings_s"]["total"] >= d["timings_s"]["run"] > 0
    assert s["devices_per_min"] > 0
    return s


def test_discover_devices_rule(fleet: Path, tmp_path: Path) -> None:
    # a parent: every non-hidden subdirectory is a device, sorted by name
    assert [j.name for j in discover_devices([fleet])] == sorted([*GOOD, "broken"])
    # device directories given directly, and a device with non-standard file names
    other = tmp_path / "tracker7"
    other.mkdir()
    shutil.copy(fleet / "car0" / "gnss.nmea", other / "trip.nmea")
    shutil.copy(fleet / "car0" / "imu.csv", other / "trip_imu.csv")
    (other / "notes.md").write_text("not a log")
    jobs = discover_devices([fleet / "car1", other])
    assert [(j.name, j.log_dir) for j in jobs] == [("car1", fleet / "car1"), ("tracker7", other)]
    # a parent with an empty device, a hidden directory and the output directory inside it
    parent = tmp_path / "parent"
    (parent / "empty").mkdir(parents=True)
    (parent / ".cache").mkdir()
    (parent / "out").mkdir()
    shutil.copytree(fleet / "car2", parent / "car2")
    assert [j.name for j in discover_devices([parent], out=parent / "out")] == ["car2", "empty"]
    with pytest.raises(ValueError, match="two devices named 'car1'"):
        discover_devices([fleet, fleet / "car1"])
    with pytest.raises(FileNotFoundError, match="not a directory"):
        discover_devices([fleet / "car0" / "imu.csv"])
    with pytest.raises(FileNotFoundError, match="neither log files nor device subdirectories"):
        discover_devices([parent / "empty"])


def test_process_device_captures_errors(fleet: Path, tmp_path: Path) -> None:
    res = process_device(fleet / "broken", tmp_path / "broken")
    assert not res["ok"]
    assert res["error"]["type"] == "IngestError"
    assert "Traceback" in res["error"]["traceback"]
    res = process_device(tmp_path / "missing", tmp_path / "missing-out")
    assert not res["ok"] and "not a directory" in res["error"]["reason"]


def test_local_pool_two_workers(fleet: Path, reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    done: list[str] = []
    result = run_fleet(discover_devices([fleet]), out, workers=2, on_done=lambda r: done.append(r["device"]))
    assert sorted(done) == sorted([*GOOD, "broken"])
    assert (result.ok, result.failed, result.workers) == (4, 1, 2)
    _assert_same_as_reference(out, reference)
    s = _assert_fleet_summary(out, "local-pool")
    pids = {d["pid"] for d in s["devices"]}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2  # ran in the pool's processes


def test_unknown_engine_fails_before_any_device(fleet: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown engine"):
        run_fleet(discover_devices([fleet]), tmp_path / "o", engine="nope", workers=0)
    assert not (tmp_path / "o").exists()


def _cli_app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def _root() -> None:
        """Test application holding only run-many."""

    fleet_cli.register(app)
    return app


def test_cli_run_many(fleet: Path, reference: Path, tmp_path: Path) -> None:
    app = _cli_app()
    out = tmp_path / "cli"
    res = runner.invoke(app, ["run-many", str(fleet), "--out", str(out), "--workers", "0"])
    assert res.exit_code == 1, res.output  # one device failed
    assert "failed devices" in res.output and "broken" in res.output
    assert "devices per minute" in res.output
    _assert_same_as_reference(out, reference)
    _assert_fleet_summary(out, "inline")
    res = runner.invoke(
        app,
        [
            "run-many",
            str(fleet / "car0"),
            str(fleet / "walk"),
            "--out",
            str(tmp_path / "c2"),
            "--workers",
            "0",
        ],
    )
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "c2").iterdir()) == ["car0", FLEET_SUMMARY, "walk"]
    res = runner.invoke(app, ["run-many", str(fleet), "--out", str(tmp_path / "c3"), "--engine", "nope"])
    assert res.exit_code == 2


def test_dask_local_cluster(fleet: Path, reference: Path, tmp_path: Path) -> None:
    # processes=True: worker processes as on a real cluster (starts in about 2 s here)
    import distributed  # the dev extra installs Dask: fail, not skip, without it

    out = tmp_path / "dask"
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        result = run_fleet(discover_devices([fleet]), out, scheduler=cluster.scheduler_address)
    assert cluster.status == distributed.core.Status.closed
    assert (result.ok, result.failed, result.workers, result.executor) == (4, 1, 2, "dask")
    _assert_same_as_reference(out, reference)
    _assert_fleet_summary(out, "dask")
