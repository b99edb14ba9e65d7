"""``iotnav nodes``: locate non-GNSS nodes from anchor tracks and RSSI logs; simulate such logs."""

from __future__ import annotations

import glob
import json
from collections import Counter
from dataclasses import asdict
from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
import typer
from rich.table import Table

from iotnav.cli._common import console, user_errors
from iotnav.geo import LocalFrame
from iotnav.io.report import FileReport
from iotnav.nodes.io import (
    local_frame_for,
    parse_anchor_spec,
    positions_to_geodetic,
    read_anchor_tracks,
    read_rssi,
    write_anchor_tracks,
    write_positions_csv,
    write_positions_geojson,
    write_rssi_csv,
)
from iotnav.nodes.locate import LocateConfig, locate_nodes
from iotnav.nodes.multilateration import SolverConfig
from iotnav.nodes.ranging import RADIOS, radio
from iotnav.nodes.simulate import (
    RadioSimConfig,
    beacon_interval_s,
    fleet_scenario,
    tracks_from_geodetic,
    tracks_to_geodetic,
)
from iotnav.nodes.tracking import TrackerConfig

METHODS = ("wls", "huber", "ransac", "track")


def expand_anchor_specs(specs: list[str]) -> list[str]:
    """Expand anchor arguments: ``ID=PATH`` and files as given, directories to every
    ``*/track.csv`` below them (or their ``*.csv`` when there is none), quoted glob patterns
    to their matches."""
    out: list[str] = []
    for spec in specs:
        ident, path = parse_anchor_spec(spec)
        if ident is not None:
            out.append(spec)
        elif path.is_dir():
            found = sorted(path.glob("*/track.csv")) or sorted(path.glob("*.csv"))
            if not found:
                raise ValueError(f"{path}: directory holds no */track.csv or *.csv anchor track")
            out.extend(str(p) for p in found)
        elif any(ch in str(path) for ch in "*?["):
            matches = sorted(glob.glob(str(path)))
            if not matches:
                raise ValueError(f"{path}: pattern matches no file")
            out.extend(matches)
        else:
            out.append(str(path))
    return out


def _print_file_reports(reports: list[FileReport]) -> None:
    for f in reports:
        table = Table(title=f"{f.path} [{f.format}]", title_justify="left")
        table.add_column("kind")
        table.add_column("what")
        table.add_column("count", justify="right")
        for k, v in sorted(f.records.items()):
            table.add_row("record", k, str(v))
        for k, v in sorted(f.skipped.items()):
            ex = f.examples.get(k, [])
            where = f" (e.g. line {ex[0][0]}: {ex[0][1][:40]!r})" if ex else ""
            table.add_row("[yellow]skipped[/]", f"{k}{where}", str(v))
        console.print(table)
        for note in f.notes:
            console.print(f"  note: {note}")


def _print_counts(title: str, counts: Counter[str]) -> None:
    table = Table(title=title, title_justify="left")
    table.add_column("what")
    table.add_column("count", justify="right")
    for k, v in sorted(counts.items()):
        table.add_row(k, str(v))
    console.print(table)


def register(app: typer.Typer) -> None:
    """Register the ``nodes`` sub-app (``locate``, ``simulate``) on ``app``."""
    nodes_app = typer.Typer(
        name="nodes",
        help="Localize non-GNSS nodes from anchor tracks and RSSI reports (anchor-node mechanism).",
        no_args_is_help=True,
    )
    app.add_typer(nodes_app, name="nodes")

    @nodes_app.command("locate")
    @user_errors
    def locate_cmd(
        rssi: Annotated[
            Path, typer.Option("--rssi", help="RSSI log CSV t,anchor_id,node_id,rssi_dbm[,snr_db].")
        ],
        out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")],
        anchors: Annotated[
            list[str] | None,
            typer.Option(
                "--anchors",
                "-a",
                help="Anchor track CSV (t,lat,lon[,height,std_north,std_east,anchor_id]); ID=PATH names "
                "the anchor; a directory means its */track.csv; repeatable.",
            ),
        ] = None,
        more: Annotated[
            list[str] | None, typer.Argument(help="More anchor tracks (so that --anchors a.csv b.csv works).")
        ] = None,
        radio_name: Annotated[
            str, typer.Option("--radio", help=f"Radio preset: {', '.join(RADIOS)}.")
        ] = "lora-sf7",
        p0_dbm: Annotated[
            float | None, typer.Option("--p0-dbm", help="RSSI at 1 m, dBm (overrides the preset).")
        ] = None,
        exponent: Annotated[float | None, typer.Option("--exponent", help="Path-loss exponent n.")] = None,
        shadowing_db: Annotated[
            float | None, typer.Option("--shadowing-db", help="Shadowing sigma, dB.")
        ] = None,
        method: Annotated[str, typer.Option("--method", help=f"Solver: {', '.join(METHODS)}.")] = "huber",
        anchor_std_m: Annotated[
            float | None,
            typer.Option("--anchor-std-m", help="Anchor std (m) for tracks without std columns."),
        ] = None,
        node_height: Annotated[
            float | None,
            typer.Option("--node-height", help="Node ellipsoidal height, m (default: anchors' median)."),
        ] = None,
        truth: Annotated[
            Path | None,
            typer.Option("--truth", help="True node positions CSV node_id,lat,lon: print errors."),
        ] = None,
    ) -> None:
        """Locate every node of an RSSI log; write nodes.csv and nodes.geojson with uncertainty."""
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
        specs = expand_anchor_specs([*(anchors or []), *(more or [])])
        tracks_geo, reports = read_anchor_tracks(specs, anchor_std_m)
        if tracks_geo.empty:
            raise ValueError("no usable anchor epoch in the anchor tracks (see the report above)")
        model = radio(radio_name)
        model = model.__class__(
            **{
                **asdict(model),
                **({"p0_dbm": p0_dbm} if p0_dbm is not None else {}),
                **({"n": exponent} if exponent is not None else {}),
                **({"shadowing_db": shadowing_db} if shadowing_db is not None else {}),
            }
        )
        reports_rssi, rep = read_rssi(rssi)
        _print_file_reports([*reports, rep])
        frame = local_frame_for(tracks_geo)
        tracks = tracks_from_geodetic(tracks_geo, frame)
        h_node = float(np.median(tracks_geo["height"])) if node_height is None else float(node_height)
        node_down = float(frame.to_ned(frame.lat0_deg, frame.lon0_deg, h_node)[2])
        cfg = LocateConfig(method=method, solver=SolverConfig(), tracker=TrackerConfig())
        res = locate_nodes(tracks, reports_rssi, model, cfg, node_down_m=node_down)
        skipped = Counter(res.skipped)
        no_data = int(res.status_counts.get("no_data", 0))
        if no_data:
            skipped["node heard by nobody (no usable report)"] += no_data
        _print_counts("reports and nodes skipped while locating", skipped)
        _print_counts("nodes by status", res.status_counts)
        pos = positions_to_geodetic(res.positions, frame, node_down)
        out.mkdir(parents=True, exist_ok=True)
        p1 = write_positions_csv(pos, out / "nodes.csv")
        p2 = write_positions_geojson(pos, out / "nodes.geojson")
        console.print(f"wrote {p1} and {p2} ({len(pos)} nodes)")
        if res.track is not None:
            lat, lon, _ = frame.from_ned(
                np.column_stack([res.track["north"], res.track["east"], np.full(len(res.track), node_down)])
            )
            trk = res.track.copy()
            trk.insert(2, "lat", lat)
            trk.insert(3, "lon", lon)
            p3 = write_positions_csv(trk, out / "nodes_track.csv")
            console.print(f"wrote {p3} ({len(trk)} states)")
        summary = {
            "radio": asdict(model),
            "locate": cfg.to_dict(),
            "frame": asdict(frame),
            "anchors": sorted(tracks_geo["anchor_id"].astype(str).unique().tolist()),
            "inputs": {"rssi": rep.to_dict(), "anchors": [r.to_dict() for r in reports]},
            "skipped": dict(skipped),
            "status": dict(res.status_counts),
        }
        if truth is not None:
            tru = pd.read_csv(truth, dtype={"node_id": str})
            missing = [c for c in ("node_id", "lat", "lon") if c not in tru]
            if missing:
                raise ValueError(f"{truth}: missing column(s) {', '.join(missing)}; expected node_id,lat,lon")
            ned = frame.to_ned(
                tru["lat"].to_numpy(float), tru["lon"].to_numpy(float), np.full(len(tru), h_node)
            )
            m = res.positions.merge(
                pd.DataFrame({"node_id": tru["node_id"].astype(str), "tn": ned[:, 0], "te": ned[:, 1]}),
                on="node_id",
            )
            ok = m["status"] == "ok"
            err = np.hypot(m["north"] - m["tn"], m["east"] - m["te"])[ok]
            if len(err):
                stats = {
                    "nodes": int(ok.sum()),
                    "median_m": float(np.median(err)),
                    "p95_m": float(np.percentile(err, 95)),
                    "rms_m": float(np.sqrt(np.mean(err**2))),
                }
                summary["truth_errors"] = stats
                console.print(
                    f"error against truth over {stats['nodes']} ok nodes: median {stats['median_m']:.1f} m, "
                    f"95 % {stats['p95_m']:.1f} m, rms {stats['rms_m']:.1f} m"
                )
        (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))

    @nodes_app.command("simulate")
    @user_errors
    def simulate_cmd(
        out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")],
        seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
        n_anchors: Annotated[int, typer.Option("--anchors", help="Number of mobile anchors (vehicles).")] = 5,
        n_nodes: Annotated[int, typer.Option("--nodes", help="Number of unknown nodes.")] = 20,
        shadowing_db: Annotated[float, typer.Option("--shadowing-db", help="Shadowing sigma, dB.")] = 6.0,
        radio_name: Annotated[
            str, typer.Option("--radio", help=f"Radio preset: {', '.join(RADIOS)}.")
        ] = "lora-sf7",
        anchor_std_m: Annotated[
            float, typer.Option("--anchor-std-m", help="Anchor position error per axis, m.")
        ] = 3.0,
        area_m: Annotated[float, typer.Option("--area-m", help="Side of the square area, m.")] = 1000.0,
        duration_s: Annotated[float, typer.Option("--duration-s", help="Simulated time, s.")] = 600.0,
        packet_loss: Annotated[float, typer.Option("--packet-loss", help="Packet loss probability.")] = 0.1,
        beacon_s: Annotated[float, typer.Option("--beacon-interval-s", help="Beacon interval, s.")] = 10.0,
        duty_cycle: Annotated[float, typer.Option("--duty-cycle", help="LoRa duty-cycle limit.")] = 0.01,
        nlos: Annotated[
            float, typer.Option("--nlos", help="Probability of an NLOS report (20 dB extra loss).")
        ] = 0.0,
    ) -> None:
        """Simulate mobile anchors, unknown nodes and RSSI reports (anchors/*/track.csv, rssi.csv, nodes_truth.csv)."""
        if n_anchors < 1 or n_nodes < 1:
            raise ValueError("--anchors and --nodes must be at least 1")
        if not 0.0 <= packet_loss < 1.0 or not 0.0 <= nlos <= 1.0:
            raise ValueError("--packet-loss must be in [0, 1) and --nlos in [0, 1]")
        model = radio(radio_name).with_shadowing(shadowing_db)
        cfg = RadioSimConfig(
            beacon_interval_s=beacon_s, duty_cycle=duty_cycle, packet_loss=packet_loss, nlos_probability=nlos
        )
        frame = LocalFrame(47.3769, 8.5417, 408.0)
        sc = fleet_scenario(
            n_anchors, n_nodes, model, cfg, seed, area_m, duration_s, anchor_std_m=anchor_std_m, frame=frame
        )
        out.mkdir(parents=True, exist_ok=True)
        paths = write_anchor_tracks(tracks_to_geodetic(sc.tracks_reported, frame), out / "anchors")
        write_rssi_csv(sc.rssi, out / "rssi.csv")
        lat, lon, h = frame.from_ned(sc.nodes[["north", "east", "down"]].to_numpy(float))
        truth = pd.DataFrame(
            {
                "node_id": sc.nodes["node_id"],
                "lat": lat,
                "lon": lon,
                "height": h,
                "north": sc.nodes["north"],
                "east": sc.nodes["east"],
            }
        )
        truth.to_csv(out / "nodes_truth.csv", index=False, float_format="%.10g")
        scenario = {
            "seed": seed,
            "anchors": n_anchors,
            "nodes": n_nodes,
            "area_m": area_m,
            "duration_s": duration_s,
            "anchor_std_m": anchor_std_m,
            "radio": asdict(model),
            "link": cfg.to_dict(),
            "effective_beacon_interval_s": beacon_interval_s(model, cfg),
            "frame": asdict(frame),
        }
        (out / "scenario.json").write_text(json.dumps(scenario, indent=1))
        console.print(
            f"wrote {len(paths)} anchor tracks under {out / 'anchors'}, {len(sc.rssi)} reports in {out / 'rssi.csv'}, "
            f"truth in {out / 'nodes_truth.csv'}"
        )
