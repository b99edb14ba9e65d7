"""``iotnav run`` writes the tracker's vocabulary: trips.csv, new events, summary counts, --geofences."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from iotnav.cli import app
from iotnav.geo import LocalFrame
from iotnav.report import build_report
from iotnav.tracker import TRIP_COLUMNS, describe

runner = CliRunner()


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("walk")
    res = runner.invoke(app, ["simulate", "walk-cold-boot", "--out", str(d), "--seed", "3"])
    assert res.exit_code == 0, res.output
    return d


@pytest.fixture(scope="module")
def run_out(sim_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """``iotnav run`` of the walk with a 10 m zone at its start (the walk goes 70 m out)."""
    tmp_path = tmp_path_factory.mktemp("run")
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
    res = runner.invoke(
        app, ["run", str(sim_dir), "--engine", "pipeline", "--out", str(out), "--geofences", str(zones)]
    )
    assert res.exit_code == 0, res.output
    return out, res.output


def test_run_writes_trips_and_geofence_events(run_out: tuple[Path, str]) -> None:
    out, output = run_out
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
    assert "trips / stops" in output


def _section(html_text: str, title: str) -> str:
    start = html_text.index(f"<h2>{title}</h2>")
    nxt = html_text.find("<section", start)
    return html_text[start : nxt if nxt > 0 else len(html_text)]


def test_report_shows_trips_table_and_geofence_events(run_out: tuple[Path, str], tmp_path: Path) -> None:
    out, _ = run_out
    rep = build_report([out], tmp_path / "report.html")
    sec = _section(rep.html.read_text(encoding="utf-8"), "Trips, stops and geofences")
    rows = re.findall(r"<tr>(.*?)</tr>", sec)
    cells = [re.findall(r"<t[dh]>(.*?)</t[dh]>", r) for r in rows]
    assert cells[0][:2] == ["kind", "start, s"]
    assert cells[1][0] == "stop" and cells[1][-1] == "yes"  # one open stop
    assert any(c[:2] == ["geofence_exit", "start"] for c in cells)
    assert "0 trip(s) and 1 stop(s)" in sec
    assert not (tmp_path / "report_trips.png").exists()  # no trip: the track figure shows the stop
    (out / "trips.csv").rename(out / "trips.bak")
    try:
        rep = build_report([out], tmp_path / "report2.html")
    finally:
        (out / "trips.bak").rename(out / "trips.csv")
    sec = _section(rep.html.read_text(encoding="utf-8"), "Trips, stops and geofences")
    assert "computed from track.csv" in sec and "0 trip(s) and 1 stop(s)" in sec


def test_run_bad_geofence_file_is_a_clear_error(sim_dir: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "FeatureCollection", "features": [')
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(tmp_path / "o"), "--geofences", str(bad)])
    # one line, the path whole: user_errors prints soft-wrapped, so a long path is not broken
    assert res.exit_code == 2 and f"{bad}: not JSON (line 1" in res.output, res.output
    bad.write_text('{"type": "Point", "coordinates": [7, 45]}')
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(tmp_path / "o"), "--geofences", str(bad)])
    assert res.exit_code == 2 and "radius" in res.output, res.output
    assert not (tmp_path / "o").exists()  # refused before any work


def test_report_draws_trips_and_stops(tmp_path: Path) -> None:
    """A hand-made run (park 20 min, drive 6 km, park): the section has the figure and 3 rows."""
    t = np.arange(0.0, 3600.0)
    v = np.where((t >= 1200) & (t < 1800), 10.0, 0.0)
    e = np.cumsum(v) - v
    lat, lon, _ = LocalFrame(45.0, 7.0, 0.0).from_ned(
        np.column_stack([np.zeros_like(t), e, np.zeros_like(t)])
    )
    track = pd.DataFrame({"t": t, "lat": lat, "lon": lon, "static": False, "std_north": 1.0, "std_east": 1.0})
    res = describe(track)
    run = tmp_path / "run"
    run.mkdir()
    track.to_csv(run / "track.csv", index=False)
    res.trips.to_csv(run / "trips.csv", index=False)
    (run / "summary.json").write_text(json.dumps({"engine": "hand", "tracker": res.summary()}))
    (run / "events.json").write_text(json.dumps(res.events))
    rep = build_report([run], tmp_path / "page.html")
    sec = _section(rep.html.read_text(encoding="utf-8"), "Trips, stops and geofences")
    kinds = [re.findall(r"<td>(.*?)</td>", r)[0] for r in re.findall(r"<tr>(<td>.*?)</tr>", sec)]
    assert kinds == ["stop", "trip", "stop"]
    assert "1 trip(s) and 2 stop(s)" in sec and "<img" in sec
    assert (tmp_path / "page_trips.png").stat().st_size > 0
