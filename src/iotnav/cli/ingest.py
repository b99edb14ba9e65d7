"""``iotnav ingest`` and ``iotnav export``: read tracker logs, merge, report, write tracks."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import pandas as pd
import typer
from rich.markup import escape
from rich.table import Table

from iotnav.cli._common import console, user_errors
from iotnav.io import IngestReport, Log, ingest
from iotnav.io.export import FORMATS as EXPORT_FORMATS
from iotnav.io.export import export_track


def reader_options(
    time_unit: str | None,
    acc_unit: str | None,
    gyro_unit: str | None,
    mag_unit: str | None,
    imu_columns: str | None,
    imu_preset: str | None,
) -> dict[str, Any]:
    """Collect the reader options given on the command line (only those set)."""
    opts: dict[str, Any] = {}
    if time_unit:
        opts["time_unit"] = time_unit
    if acc_unit:
        opts["acc_unit"] = acc_unit
    if gyro_unit:
        opts["gyro_unit"] = gyro_unit
    if mag_unit:
        opts["mag_unit"] = mag_unit
    if imu_columns:
        opts["column_order"] = [c.strip() for c in imu_columns.split(",")]
    if imu_preset:
        opts["preset"] = imu_preset
    return opts


def print_report(report: IngestReport) -> None:
    """Print an ingest report: per file records, ignored and skipped units; timeline facts."""
    for f in report.files:
        title = escape(f"{Path(f.path).name} ({f.format}): {f.units} input units")
        table = Table(title=title, title_justify="left")
        table.add_column("kind")
        table.add_column("what")
        table.add_column("count", justify="right")
        for k, v in sorted(f.records.items()):
            table.add_row("record", k, str(v))
        for k, v in sorted(f.ignored.items()):
            table.add_row("ignored", k, str(v))
        for k, v in sorted(f.skipped.items()):
            ex = f.examples.get(k, [])
            where = f" (e.g. unit {ex[0][0]}: {ex[0][1][:40]!r})" if ex else ""
            table.add_row("[yellow]skipped[/]", escape(f"{k}{where}"), str(v))
        console.print(table)
        for note in f.notes:
            console.print(f"  note: {escape(note)}")
    tl = report.timeline
    if tl:
        table = Table(title=f"timeline (clock: {tl.get('clock')}, utc - t = {tl.get('utc_offset_s')})")
        for col in ("table", "count", "start", "end", "span s", "rate Hz", "gaps"):
            table.add_column(col, justify="right" if col != "table" else "left")
        for kind in ("gnss", "imu", "mag"):
            d = tl.get(kind)
            if d:
                gaps = d["gaps"]
                longest = max((g["length_s"] for g in gaps), default=0.0)
                table.add_row(
                    kind,
                    str(d["count"]),
                    f"{d['start']:.3f}",
                    f"{d['end']:.3f}",
                    f"{d['span_s']:.1f}",
                    f"{d['rate_hz']:.2f}",
                    f"{len(gaps)} (longest {longest:.1f} s)" if gaps else "0",
                )
        console.print(table)


def write_merged(log: Log, out: Path) -> None:
    """Write the merged timeline as CSV or Parquet (by extension)."""
    df = log.to_frame()
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".parquet":
        df.to_parquet(out, index=False)
    elif out.suffix.lower() == ".csv":
        df.to_csv(out, index=False, float_format="%.10g")
    else:
        raise ValueError(f"{out}: expected a .csv or .parquet output file")


TimeUnit = Annotated[str | None, typer.Option(help="Device time unit: s, ms, us, ns (detected if omitted).")]
AccUnit = Annotated[str | None, typer.Option(help="Accelerometer unit of IMU CSV: g, mg, m/s^2.")]
GyroUnit = Annotated[str | None, typer.Option(help="Gyroscope unit of IMU CSV: deg/s, mdps, rad/s.")]
MagUnit = Annotated[str | None, typer.Option(help="Magnetometer unit of IMU CSV: uT, mG, gauss, nT.")]
ImuColumns = Annotated[
    str | None,
    typer.Option(help="Column order of a header-less IMU CSV, e.g. t,acc_x,acc_y,acc_z,gyro_x,..."),
]
ImuPreset = Annotated[str | None, typer.Option(help="Named IMU CSV layout, e.g. rtklib-demo5.")]


def register(app: typer.Typer) -> None:
    """Register ``ingest`` and ``export`` on ``app``."""

    @app.command("ingest")
    @user_errors
    def ingest_cmd(
        files: Annotated[
            list[Path], typer.Argument(help="Log files of one device (NMEA, UBX, .pos, IMU CSV, ...).")
        ],
        out: Annotated[Path | None, typer.Option("--out", "-o", help="merged.csv or merged.parquet")] = None,
        fmt: Annotated[str | None, typer.Option("--format", help="Force a format for every file.")] = None,
        report: Annotated[Path | None, typer.Option(help="Also write the ingest report as JSON.")] = None,
        utc_offset: Annotated[
            float | None, typer.Option(help="UTC minus device time, s, if not in the logs.")
        ] = None,
        time_unit: TimeUnit = None,
        acc_unit: AccUnit = None,
        gyro_unit: GyroUnit = None,
        mag_unit: MagUnit = None,
        imu_columns: ImuColumns = None,
        imu_preset: ImuPreset = None,
    ) -> None:
        """Read tracker logs, merge them into one timeline, print the ingest report."""
        opts = reader_options(time_unit, acc_unit, gyro_unit, mag_unit, imu_columns, imu_preset)
        log = ingest(files, fmt=fmt, utc_offset_s=utc_offset, **opts)
        print_report(log.report)
        if out is not None:
            write_merged(log, out)
            console.print(
                f"wrote {out} ({len(log.gnss)} GNSS epochs, {len(log.imu)} IMU, {len(log.mag)} mag rows)"
            )
        if report is not None:
            report.parent.mkdir(parents=True, exist_ok=True)
            report.write_text(json.dumps(log.report.to_dict(), indent=1, default=str))

    @app.command("export")
    @user_errors
    def export_cmd(
        source: Annotated[
            Path, typer.Argument(help="A track CSV (t/utc, lat, lon[, height]) or any GNSS log.")
        ],
        out: Annotated[
            list[Path], typer.Option("--out", "-o", help="Output file(s): .csv .geojson .gpx .kml")
        ],
        fmt: Annotated[
            str | None, typer.Option("--format", help=f"One of {', '.join(EXPORT_FORMATS)}.")
        ] = None,
        valid_only: Annotated[
            bool, typer.Option(help="GNSS logs: only epochs the receiver marks valid.")
        ] = True,
    ) -> None:
        """Export a track to CSV, GeoJSON, GPX 1.1 or KML."""
        df, offset = load_track(source, valid_only)
        for o in out:
            res = export_track(df, o, fmt, name=source.stem, utc_offset_s=offset)
            skipped = f", {res.skipped} rows without a position left out" if res.skipped else ""
            console.print(f"wrote {res.path} ({res.format}, {res.points} points{skipped})")


def load_track(source: Path, valid_only: bool = True) -> tuple[pd.DataFrame, float | None]:
    """Load a track table: a CSV with lat/lon columns as it is, or a log's GNSS epochs.

    Returns
    -------
    table, utc_offset_s
        The track and the UTC offset of its device time (None when the table has UTC).
    """
    if source.suffix.lower() == ".csv" and source.is_file():
        head = source.open("r", errors="replace").readline()
        cols = {c.strip() for c in head.split(",")}
        if {"lat", "lon"} <= cols or {"lat_deg", "lon_deg"} <= cols:
            return pd.read_csv(source), None
    log = ingest([source])
    g = log.gnss
    if valid_only:
        g = g.loc[g["valid"]]
    return g.reset_index(drop=True), log.utc_offset_s
