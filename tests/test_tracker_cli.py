"""``iotnav run`` writes the tracker's vocabulary: trips.csv, new events, summary counts, --geofences."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from iotnav.cli import app
from iotnav.tracker import TRIP_COLUMNS

runner = CliRunner()


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("walk")
    res = runner.invoke(app, ["simulate", "walk-cold-boot", "--out", str(d), "--seed", "3"])
    assert res.exit_code == 0, res.output
    return d


def test_run_writes_trips_and_geofence_events(sim_dir: Path, tmp_path: Path) -> None:
    # the walk starts at (45.0628, 7.662) and goes 70 m out: a 10 m zone there is left
    zones = tmp_path / "zones.geojson"
    zones.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {"name": "start", "radius": 10},
                        "geometry": {"type": "Point", "coordinates": [7.662, 45.0628]},
                    }
                ],
            }
        )
    )
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(out), "--geofences", str(zones)])
    assert res.exit_code == 0, res.output
    trips = pd.read_csv(out / "trips.csv")
    assert list(trips.columns) == list(TRIP_COLUMNS)
    # a 150 s, 200 m walk is shorter than Traccar's 300 s / 500 m trip: one stop, odometer 0
    assert trips["kind"].tolist() == ["stop"]
    summary = json.loads((out / "summary.json").read_text())
    tk = summary["tracker"]
    assert (tk["trips"], tk["stops"], tk["odometer_m"]) == (0, 1, 0.0)
    assert tk["zones_initial"] == {"start": True}
    events = json.loads((out / "events.json").read_text())
    fence = [e for e in events if e["type"].startswith("geofence_")]
    assert fence and fence[0]["type"] == "geofence_exit" and fence[0]["zone"] == "start"
    assert tk["geofence_events"] == len(fence)
    assert any(e["type"] == "boot" for e in events)  # the engine's events are still there
    assert summary["counts"]["events"] == len(events)
    assert "trips / stops" in res.output


def test_run_bad_geofence_file_is_a_clear_error(sim_dir: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "FeatureCollection", "features": [')
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(tmp_path / "o"), "--geofences", str(bad)])
    assert res.exit_code == 2 and "bad.geojson" in res.output and "not JSON" in res.output
    bad.write_text('{"type": "Point", "coordinates": [7, 45]}')
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(tmp_path / "o"), "--geofences", str(bad)])
    assert res.exit_code == 2 and "radius" in res.output
    assert not (tmp_path / "o").exists()  # refused before any work
