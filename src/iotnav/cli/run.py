"""``iotnav run`` (fuse a log with an engine) and ``iotnav cost`` (Forno et al. Table I)."""

from __future__ import annotations

import math
import time
from collections import Counter
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from iotnav.cli._common import console, err_console, progress, user_errors
from iotnav.engines.base import run_batch
from iotnav.engines.registry import ENGINE_NAMES, make_engine
from iotnav.io import ingest
from iotnav.io.export import MAP_RATE_HZ
from iotnav.runs import find_inputs, load_stored_position, load_zones, why_no_rows, write_run
from iotnav.techniques.last_position import LastPositionStore


def register(app: typer.Typer) -> None:
    """Register ``run`` and ``cost`` on ``app``."""

    @app.command("run")
    @user_errors
    def run_cmd(
        inputs: Annotated[
            list[Path] | None, typer.Argument(help="Log files, or a directory with gnss.nmea and imu.csv.")
        ] = None,
        out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")] = Path("out/run"),
        gnss: Annotated[Path | None, typer.Option(help="GNSS log (NMEA, UBX, .pos).")] = None,
        imu: Annotated[Path | None, typer.Option(help="IMU CSV.")] = None,
        mag: Annotated[Path | None, typer.Option(help="Magnetometer CSV.")] = None,
        engine: Annotated[
            str | None,
            typer.Option(
                help=f"One of {', '.join(ENGINE_NAMES)}; default: the engine that measures best for "
                "the inputs given (registry.default_engine; printed and written into summary.json)."
            ),
        ] = None,
        config: Annotated[Path | None, typer.Option(help="Engine configuration (TOML).")] = None,
        state: Annotated[
            Path | None,
            typer.Option(help="Device state directory: last known position is loaded and saved there."),
        ] = None,
        smooth: Annotated[
            bool,
            typer.Option(help="Post-process with the fixed-interval RTS smoother (engines that support it)."),
        ] = False,
        fixes: Annotated[
            Path | None,
            typer.Option(
                help="Absolute fixes (CSV or JSON lines: t_valid,t_arrival,lat,lon,height[,roll,pitch,yaw]); "
                "fused by the absfix engine (Dabove et al. 2016)."
            ),
        ] = None,
        geofences: Annotated[
            Path | None,
            typer.Option(help="Geofences (GeoJSON: Polygon, MultiPolygon, Point with a 'radius' in m)."),
        ] = None,
        rate: Annotated[
            float | None,
            typer.Option(help="Resample the track at this rate, Hz (fixes engine; smoothed with --smooth)."),
        ] = None,
        integrity: Annotated[
            bool,
            typer.Option(
                "--integrity/--no-integrity",
                help="The do-no-harm guard around the engine (iotnav.engines.integrity; on by default): "
                "re-initialise on inconsistency, fall back to the last fix moved on at its velocity in "
                "outages. --no-integrity runs the engine alone.",
            ),
        ] = True,
        track_format: Annotated[
            str, typer.Option("--format", help="Track table: csv (track.csv) or parquet (track.parquet).")
        ] = "csv",
        map_rate_hz: Annotated[
            float,
            typer.Option(help="Points per second in track.geojson / track.gpx; 0 writes every output row."),
        ] = MAP_RATE_HZ,
        map_at_fixes: Annotated[
            bool,
            typer.Option(
                help="Points of track.geojson / track.gpx at the log's fix times (the nearest rows) "
                "instead of --map-rate-hz."
            ),
        ] = False,
        gnss_latency_s: Annotated[
            float,
            typer.Option(
                help="Fix epoch to arrival latency of device-time-stamped GNSS, s (stamps moved back)."
            ),
        ] = 0.0,
    ) -> None:
        """Fuse a log with an engine; write OUT/track.csv, events.json, summary.json, trips.csv, GeoJSON, GPX."""
        zones = load_zones(geofences) if geofences is not None else None
        if track_format not in ("csv", "parquet"):
            raise ValueError(f"--format {track_format!r}: expected csv or parquet")
        if not map_rate_hz >= 0:
            raise ValueError(f"--map-rate-hz {map_rate_hz}: expected a rate >= 0 (0: every row)")
        files, state_file = find_inputs(list(inputs or []), gnss, imu, mag)
        log = ingest(files, gnss_latency_s=gnss_latency_s)
        store = None
        stored = None
        if state is not None:
            state.mkdir(parents=True, exist_ok=True)
            store = LastPositionStore(state / "last_position.json")
            stored = load_stored_position(store.path)
        elif state_file is not None:
            stored = load_stored_position(state_file)
        choice: dict[str, Any] = {"name": engine, "reason": "given with --engine", "default": False}
        if engine is None and fixes is None:
            from iotnav.engines.registry import default_engine

            engine, why = default_engine(log)
            choice = {"name": engine, "reason": why, "default": True}
            console.print(f"engine: {engine} ({why}); --engine NAME chooses another")
        if rate is not None and engine != "fixes":
            raise ValueError("--rate is available with the fixes engine only")
        if fixes is not None or engine == "absfix":
            if fixes is None:
                raise ValueError("--engine absfix needs --fixes FILE (absolute position/attitude fixes)")
            if smooth:
                raise ValueError(
                    "--smooth is not available with --fixes (the absfix engine has no covariance)"
                )
            from iotnav.cli.study import run_fixes

            if engine is None:
                choice = {"name": "absfix", "reason": "--fixes given: absfix fuses them", "default": True}
            engine = "absfix" if engine in (None, "pipeline") else engine  # the pipeline takes no fixes
            n = len(log.gnss) + len(log.imu) + len(log.mag)
            t0 = time.perf_counter()
            with progress("absfix", total=n) as advance:
                track = run_fixes(log, fixes, engine, config, advance)
        else:
            assert engine is not None  # chosen above when not given
            eng = make_engine(
                engine,
                config,
                stored=stored,
                store=store,
                smoothing=smooth or rate is not None,
                integrity=integrity,
            )
            n = len(log.gnss) + len(log.imu) + len(log.mag)
            t0 = time.perf_counter()
            own_smoother = getattr(eng, "smoothed_output", None)
            if smooth and getattr(eng, "smoothing_log", None) is None and own_smoother is None:
                raise ValueError(
                    f"engine {engine!r} does not support --smooth (its config disables the smoothing log)"
                )
            with progress(f"{engine}", total=n) as advance:
                track = run_batch(eng, log, progress=advance)
        assert engine is not None
        name = engine

        def _write(folder: Path, rows: Any, seconds: float) -> dict[str, Any]:
            """One run folder: ``rows`` with the log, engine and output settings of this run."""
            return write_run(
                folder,
                rows,
                log,
                name,
                seconds,
                engine_choice=choice if choice["default"] else None,
                zones=zones,
                track_format=track_format,
                map_rate_hz=map_rate_hz,
                map_at_fixes=map_at_fixes,
            )

        if smooth:
            from iotnav.engines.smoother import smooth_output

            forward = track
            track = own_smoother(forward) if own_smoother is not None else smooth_output(eng, forward)  # type: ignore[arg-type]
            _write(out / "forward", forward, time.perf_counter() - t0)
        if rate is not None:
            fwd = track
            track = eng.resample(rate, smoothed=smooth, forward=fwd)  # type: ignore[attr-defined]
            _write(out / "fixes", fwd, time.perf_counter() - t0)
        runtime = time.perf_counter() - t0
        summary = _write(out, track, runtime)
        table = Table(title=f"iotnav run --engine {engine}: {out}")
        table.add_column("what")
        table.add_column("value", justify="right")
        if choice["default"]:
            table.add_row("engine", f"{choice['name']}: {choice['reason']}")
        c = summary["counts"]
        table.add_row(
            "inputs", f"{c['gnss_epochs_in']} GNSS, {c['imu_samples_in']} IMU, {c['mag_samples_in']} mag"
        )
        not_read: Counter[str] = Counter()
        for f in summary["ingest"]["files"]:
            not_read.update(f["skipped"])
        for reason, count in sorted(not_read.items()):  # examples and lines in summary.json
            table.add_row(f"  not read ({reason})", str(count))
        table.add_row("output rows", f"{c['output_rows']} at {summary['rates_hz']['output']:.1f} Hz")
        for k, v in sorted(c["rows_by_source"].items()):
            table.add_row(f"  from {k}", str(v))
        table.add_row("static rows", str(c["static_rows"]))
        table.add_row("events", str(c["events"]))
        tk = summary["tracker"]
        table.add_row(
            "trips / stops", f"{tk['trips']} / {tk['stops']}, odometer {tk['odometer_m'] / 1000:.3f} km"
        )
        if zones:
            table.add_row("geofence events", str(tk["geofence_events"]))
        es = summary.get("engine_summary", {})
        for reason, count in sorted(es.get("skipped", {}).items()):
            table.add_row(f"  skipped ({reason})", str(count))
        if es.get("mag_unused"):
            table.add_row("magnetometer", f"{es['mag_unused']} samples unused: no calibration configured")
        res = es.get("gnss_resolution")
        if isinstance(res, dict) and res.get("fixes"):
            dec = res.get("minute_decimals")
            fmt = (
                "continuous"
                if res.get("continuous")
                else f"{dec} decimals of a minute"
                if dec is not None
                else "unknown"
            )
            table.add_row("GNSS position rounding", fmt)
        if math.isfinite(summary["mount_yaw_rad"]):
            table.add_row("mount yaw", f"{math.degrees(summary['mount_yaw_rad']):.2f} deg")
        table.add_row("runtime", f"{runtime:.2f} s ({n / max(runtime, 1e-9):,.0f} samples/s)")
        console.print(table)
        if c["output_rows"] == 0:
            err_console.print(f"[bold red]error:[/] {why_no_rows(summary)}")
            raise typer.Exit(code=2)

    @app.command("cost")
    @user_errors
    def cost_cmd(
        calls: Annotated[int, typer.Option(help="Calls timed per block.")] = 2000,
        config: Annotated[Path | None, typer.Option(help="Pipeline configuration (TOML).")] = None,
        imu_rate_hz: Annotated[float, typer.Option(help="IMU rate for block 5's counts, Hz.")] = 100.0,
        gnss_rate_hz: Annotated[float, typer.Option(help="GNSS rate for block 5's counts, Hz.")] = 1.0,
    ) -> None:
        """Print Table I of Forno et al. 2020 for the configured pipeline: ours / paper, and time per call.

        FLOPs = sums + multiplications (as in the paper); formulas in :mod:`iotnav.techniques.cost`.
        """
        from rich.console import Console
        from rich.markup import escape

        from iotnav.engines.config import PipelineConfig
        from iotnav.techniques.cost import TIMING_KEYS, full_table, time_blocks

        cfg = PipelineConfig.from_toml(config) if config is not None else PipelineConfig()
        rows = full_table(cfg, imu_rate_hz=imu_rate_hz, gnss_rate_hz=gnss_rate_hz)
        times = time_blocks(n_calls=calls)

        def pair(ours: object, paper: object) -> str:
            o = "-" if ours is None else str(ours)
            p = "-" if paper is None else f"{paper:g}" if isinstance(paper, float) else str(paper)
            return f"{o} / {p}"

        table = Table(
            title="Table I, Forno et al. 2020: computational effort per call (ours / paper)",
            caption=(
                f"FLOPs = sums + mults; ours: Joseph-form update, K = {imu_rate_hz:g} / {gnss_rate_hz:g} "
                f"IMU samples per GPS interval; totals: ours one predict + one update per filter, the "
                f"paper two predicts for tilt and yaw; measured: mean of {calls} calls on this machine"
            ),
        )
        for col in ("block", "module", "portion", "FLOPs", r"\[n,m,p]", "sum", "mul", "us per call"):
            table.add_column(
                col,
                justify="right" if col in ("FLOPs", "sum", "mul", "us per call") else "left",
                no_wrap=True,
            )
        for r in rows:
            pp = r["paper"]
            shape = escape(f"{r['shape_ours']} / {r['shape_paper']}") if r["shape_ours"] else ""
            keys = TIMING_KEYS.get(r["key"], ())
            us = f"{sum(times[k] for k in keys) * 1e6:.1f}" if keys else "-"
            table.add_row(
                r["block"],
                r["module"],
                r["portion"],
                pair(r["flops"], pp.get("flops")),
                shape,
                pair(r["sums"], pp.get("sums")),
                pair(r["mults"], pp.get("mults")),
                us,
            )
        # a pipe or a captured stdout would squeeze the 8 columns into 80 characters
        (console if console.is_terminal else Console(width=180)).print(table)
