"""Reading anchor tracks and RSSI logs (counted skips, clear errors) and the ``nodes`` CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from iotnav.cli import nodes as nodes_cli
from iotnav.io.errors import IngestError
from iotnav.nodes.io import anchor_id_for, read_anchor_tracks, read_rssi

RSSI_BAD = """# exported by a gateway
t,anchor_id,node_id,rssi_dbm,snr_db,gateway
0,A01,N1,-80,10,gw1
1,A01,N1,-81,9
2,A01,N1,nan,9,gw1
3,A01,N1,-201,9,gw1
4,A01,N1,12x,9,gw1
-0.5,A01,N1,-82,8,gw1
5,A02,N2,-90,1,gw1,extra
6,A02,N2,-91,1,gw1

7,A02,,-91,1,gw1
"""


def test_rssi_reader_counts_every_bad_line(tmp_path: Path) -> None:
    p = tmp_path / "rssi.csv"
    p.write_text(RSSI_BAD)
    df, rep = read_rssi(p)
    assert df["t"].tolist() == [0.0, 6.0]
    assert rep.records["rssi report"] == 2
    assert rep.skipped == {
        "truncated": 1,
        "NaN field": 1,
        "out-of-range value": 1,
        "malformed fields": 3,  # non-numeric RSSI, overlong line, empty node id
        "non-monotonic time": 1,
    }
    assert rep.examples["truncated"][0][0] == 4  # line number of the truncated line
    assert any("gateway" in n for n in rep.notes)  # unknown column reported, not fatal
    assert rep.ignored["blank or comment"] == 2


def test_missing_column_names_file_and_expectation(tmp_path: Path) -> None:
    p = tmp_path / "r.csv"
    p.write_text("t,anchor,node_id,rssi\n0,A,N,-80\n")
    with pytest.raises(IngestError, match=r"r\.csv.*missing column\(s\) anchor_id, rssi_dbm.*expected"):
        read_rssi(p)
    q = tmp_path / "track.csv"
    q.write_text("time,lat,lon\n0,47,8\n")
    with pytest.raises(IngestError, match="missing column"):
        read_anchor_tracks([q])


def test_anchor_ids(tmp_path: Path) -> None:
    (tmp_path / "van7").mkdir()
    run = tmp_path / "van7" / "track.csv"
    run.write_text(
        "t,lat,lon,height,north,east,down,std_north,std_east,source\n0,47,8,400,0,0,0,2,2,gnss\n1,47.0001,8,400,0,0,0,2,2,gnss\n"
    )
    plain = tmp_path / "bike3.csv"
    plain.write_text("t,lat,lon\n0,47,8\n0.5,47,8\n0.4,47,8\n")
    multi = tmp_path / "fleet.csv"
    multi.write_text("t,anchor_id,lat,lon\n0,X1,47,8\n0,X2,47.1,8\n")
    assert anchor_id_for(run) == "van7"
    assert anchor_id_for(plain) == "bike3"
    df, reps = read_anchor_tracks([run, plain, multi], default_std_m=4.0)
    assert sorted(df["anchor_id"].unique()) == ["X1", "X2", "bike3", "van7"]
    assert df.loc[df["anchor_id"] == "bike3", "std_north"].tolist() == [4.0, 4.0]
    assert reps[1].skipped == {"non-monotonic time": 1}
    df2, _ = read_anchor_tracks([f"CAR={plain}"])
    assert set(df2["anchor_id"]) == {"CAR"}
    with pytest.raises(IngestError, match="also comes from"):
        read_anchor_tracks([plain, f"bike3={run}"])


def _app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Test root."""

    nodes_cli.register(app)
    return app


def test_cli_simulate_then_locate(tmp_path: Path) -> None:
    runner = CliRunner()
    app = _app()
    sim = tmp_path / "sim"
    r = runner.invoke(
        app, ["nodes", "simulate", "--out", str(sim), "--seed", "4", "--anchors", "4", "--nodes", "8"]
    )
    assert r.exit_code == 0, r.output
    tracks = sorted(str(p) for p in (sim / "anchors").glob("*/track.csv"))
    assert len(tracks) == 4
    # an RSSI line from an unknown anchor and a node nobody usable hears
    with open(sim / "rssi.csv", "a") as fh:
        fh.write("599,A99,N001,-80,20\n599,A99,GHOST,-80,20\n")
    out = tmp_path / "loc"
    args = ["nodes", "locate", "--rssi", str(sim / "rssi.csv"), "--out", str(out), "--anchors", *tracks]
    r = runner.invoke(app, [*args, "--truth", str(sim / "nodes_truth.csv"), "--node-height", "408"])
    assert r.exit_code == 0, r.output
    assert "unknown anchor id" in r.output and "node heard by nobody" in r.output
    pos = pd.read_csv(out / "nodes.csv")
    assert len(pos) == 9
    assert pos.loc[pos["node_id"] == "GHOST", "status"].item() == "no_data"
    ok = pos[pos["status"] == "ok"]
    assert len(ok) >= 7
    assert {"lat", "lon", "std_north", "std_east", "semi_major_95_m"} <= set(pos.columns)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["skipped"]["unknown anchor id"] == 2
    assert summary["truth_errors"]["median_m"] < 40.0
    gj = json.loads((out / "nodes.geojson").read_text())
    assert gj["type"] == "FeatureCollection" and len(gj["features"]) == 9
    ghost = next(f for f in gj["features"] if f["properties"]["node_id"] == "GHOST")
    assert ghost["geometry"] is None
    # directory form and the tracking filter
    r = runner.invoke(
        app,
        [
            "nodes",
            "locate",
            "--rssi",
            str(sim / "rssi.csv"),
            "--out",
            str(out / "trk"),
            "--anchors",
            str(sim / "anchors"),
            "--method",
            "track",
        ],
    )
    assert r.exit_code == 0, r.output
    assert (out / "trk" / "nodes_track.csv").is_file()


def test_cli_errors_are_messages(tmp_path: Path) -> None:
    runner = CliRunner()
    app = _app()
    r = runner.invoke(
        app,
        [
            "nodes",
            "locate",
            "--rssi",
            str(tmp_path / "no.csv"),
            "--out",
            str(tmp_path),
            "--anchors",
            str(tmp_path / "none.csv"),
        ],
    )
    assert r.exit_code == 2
    assert "not found" in r.output
    bad = tmp_path / "a.csv"
    bad.write_text("t,lat,lon\n0,47,8\n1,47,8\n")
    rs = tmp_path / "r.csv"
    rs.write_text("t,anchor_id,node_id,rssi_dbm\n0,a,N1,-80\n")
    r = runner.invoke(
        app,
        [
            "nodes",
            "locate",
            "--rssi",
            str(rs),
            "--out",
            str(tmp_path / "o"),
            "--anchors",
            str(bad),
            "--method",
            "magic",
        ],
    )
    assert r.exit_code == 2 and "unknown method" in r.output
