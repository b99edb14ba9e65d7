"""Report sections after the map (:mod:`iotnav.report.page`): accuracy, outages, static
drift, trips, mount, boot, states, biases, NIS, timeline and the configuration used.

Each builder returns a :class:`~iotnav.report.page_html.Section`, with a note instead of the
figure when it does not apply (no truth, no static period, nothing at boot, no mount estimate,
no NIS). Distances in metres in the local East/North frame of the report, angles in degrees.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pandas as pd

from iotnav.geo import LocalFrame
from iotnav.report import figures as F
from iotnav.report.load import Run, Truth
from iotnav.report.page_html import Section, _flatten, esc, fmt, table
from iotnav.report.page_map import _xy
from iotnav.report.prepare import (
    GNSS_ONLY,
    accuracy,
    boot_info,
    drift_table,
    mount_table,
    nis_table,
    positioned,
    rejected_fixes,
    static_periods,
    trips_table,
    valid_fixes,
)

STAT_COLUMNS = ("mean", "rms", "p67", "p95", "max")


def _accuracy_sections(
    runs: list[Run], truth: Truth | None, outages: list[tuple[float, float]]
) -> tuple[list[Section], dict[str, dict[str, float]]]:
    if truth is None:
        note = "No truth given (--truth): error figures and the accuracy table are left out."
        return [Section("errors", "Error against truth", note=note)], {}
    errs, stats = accuracy(runs, truth)
    base = GNSS_ONLY if GNSS_ONLY in errs else None
    rows = []
    for name, st in stats.items():
        rows.append(
            [name, int(st["n"])]
            + [st[f"h_err_{c}"] for c in STAT_COLUMNS]
            + [st[f"{a}_err_{c}"] for a in ("n", "e") for c in ("mean", "p67", "p95")]
        )
    header = ["solution", "epochs", *(f"h {c}" for c in STAT_COLUMNS)]
    header += [f"{a} {c}" for a in ("|N|", "|E|") for c in ("mean", "p67", "p95")]
    acc_table = table(header, rows, "stats")
    first = runs[0]
    pos = positioned(first.track)
    sigma = pos[["t", "std_north", "std_east"]] if {"std_north", "std_east"} <= set(pos.columns) else None
    drift = drift_table(errs[first.label], truth, outages)
    outside = {k: int(v["outside_truth"]) for k, v in stats.items() if v["outside_truth"] > 0}
    cap = (
        "Errors in metres, track minus truth interpolated to the track times, in the local NED frame of "
        "the first truth point (iotnav.eval.metrics). Grey: raw GNSS fixes. "
        + ("Shaded: GNSS outages; ▼ error at each outage end (dead-reckoning drift). " if outages else "")
        + (
            "Rows outside the truth's time span left out: "
            + ", ".join(f"{k} {v}" for k, v in outside.items())
            if outside
            else ""
        )
    )
    sec_t = Section(
        "errors",
        "Error against truth",
        F.error_time_figure(errs, base, sigma, outages, drift),
        cap,
        "<h3>Statistics, m</h3>" + acc_table,
    )
    sec_d = Section(
        "error-distribution",
        "Error distribution",
        F.error_distribution_figure(errs, base),
        "Share of epochs with an error below x (67 % and 95 % lines; dot: mean). Same statistics as the table above.",
    )
    secs = [sec_t, sec_d]
    if outages:
        if drift:
            rows_d = [
                [
                    d["start"],
                    d["end"],
                    d["length_s"],
                    d["distance_m"],
                    d["end_error_m"],
                    d["max_error_m"],
                    d["drift_pct"],
                ]
                for d in drift
            ]
            body = table(
                [
                    "start, s",
                    "end, s",
                    "length, s",
                    "distance, m",
                    "error at end, m",
                    "max error, m",
                    "drift, %",
                ],
                rows_d,
                "stats",
            )
        else:
            body = '<p class="note">No output epochs inside the outages.</p>'
        secs.append(Section("outages", f"GNSS outages: dead-reckoning drift ({first.label})", body=body))
    return secs, stats


def _outage_note(outages: list[tuple[float, float]], factor: float, run: Run) -> Section:
    if run.gnss is None:
        return Section("outage-list", "GNSS outages", note="No gnss.csv in the run: outages cannot be found.")
    if not outages:
        return Section(
            "outage-list",
            "GNSS outages",
            note=f"No gap between valid fixes longer than {factor:g} × the median interval.",
        )
    rows = [[a, b, b - a] for a, b in outages]
    return Section(
        "outage-list",
        "GNSS outages",
        body=f"<p>Gaps between valid fixes longer than {factor:g} × the median fix interval "
        "(a gap running to the end of the run ends at the last output):</p>"
        + table(["last fix before, s", "first fix after (or end), s", "gap, s"], rows, "stats"),
    )


def _static_section(run: Run, truth: Truth | None, frame: LocalFrame, fence_m: float) -> Section:
    per = static_periods(run)
    title = "Static cloud and geofence"
    if not per:
        return Section("static", title, note="No static period in this run: figure left out.")
    fixes_all = _xy(valid_fixes(run), frame, "lat_deg", "lon_deg")
    ft = fixes_all["t"].to_numpy(float)
    counts = [int(((ft >= a) & (ft <= b)).sum()) for a, b in per]
    k = int(np.argmax([(b - a) if c >= 3 else -1.0 for (a, b), c in zip(per, counts, strict=True)]))
    if counts[k] < 3:
        return Section("static", title, note="No static period holds three valid fixes: figure left out.")
    a, b = per[k]
    fixes = fixes_all.loc[(ft >= a) & (ft <= b)]
    out = _xy(positioned(run.track), frame)
    out = out.loc[(out["t"] >= a) & (out["t"] <= b)]
    if truth is not None:
        tr = _xy(truth.table, frame)
        tr = tr.loc[(tr["t"] >= a) & (tr["t"] <= b)]
    if truth is not None and len(tr):
        center = (float(tr["n_m"].mean()), float(tr["e_m"].mean()))
        what = "truth"
    else:
        center = (float(fixes["n_m"].mean()), float(fixes["e_m"].mean()))
        what = "mean of the raw fixes"
    d_fix = np.hypot(fixes["n_m"] - center[0], fixes["e_m"] - center[1])
    d_out = np.hypot(out["n_m"] - center[0], out["e_m"] - center[1])
    rows = [
        [
            "raw fixes",
            len(fixes),
            float(np.mean(d_fix)),
            float(np.percentile(d_fix, 95)),
            float(d_fix.max()),
            int((d_fix > fence_m).sum()),
        ],
    ]
    if len(out):
        rows.append(
            [
                "filtered output",
                len(out),
                float(np.mean(d_out)),
                float(np.percentile(d_out, 95)),
                float(d_out.max()),
                int((d_out > fence_m).sum()),
            ]
        )
    body = table(
        ["positions", "count", "mean distance, m", "p95, m", "max, m", f"outside {fence_m:g} m"],
        rows,
        "stats",
    )
    cap = (
        f"Longest static period of {run.label} ({len(per)} static period(s) in the run), {a:.1f}–{b:.1f} s; "
        f"geofence {fence_m:g} m around the {what}."
    )
    fig = F.static_figure(fixes, out, center, fence_m, what, (a, b))
    return Section("static", title, fig, cap, body)


def _trips_section(run: Run, frame: LocalFrame) -> Section:
    """Trips, stops, odometer and geofence events of the main run (``trips.csv``, events)."""
    title = "Trips, stops and geofences"
    trips, from_file = trips_table(run)
    tk = (run.summary.get("tracker") or {}) if from_file else {}
    rows = [
        [r.kind, r.t_start, r.t_end, r.duration_s, r.distance_m, r.max_speed_mps, r.open]
        for r in trips.itertuples(index=False)
    ]
    body = table(
        ["kind", "start, s", "end, s", "duration, s", "distance, m", "max speed, m/s", "open"], rows, "stats"
    )
    fence = [e for e in run.events if str(e.get("type", "")).startswith("geofence_")]
    if fence:
        body += table(
            ["event", "zone", "t, s", "border distance, m"],
            [[e["type"], e.get("zone", "?"), e["t"], e.get("border_m")] for e in fence],
            "stats",
        )
    passed = [e for e in run.events if e.get("type") in ("moved_while_off", "fix_rejected")]
    n_trip = int((trips["kind"] == "trip").sum())
    cap = (
        f"{n_trip} trip(s) and {int((trips['kind'] == 'stop').sum())} stop(s); odometer "
        f"{fmt(float(tk.get('odometer_m', trips.loc[trips['kind'] == 'trip', 'distance_m'].sum())))} m "
        f"(counted in trips only); {len(fence)} geofence event(s); "
        f"{sum(e['type'] == 'fix_rejected' for e in passed)} rejected fix(es), "
        f"{sum(e['type'] == 'moved_while_off' for e in passed)} moved-while-off event(s)."
        + ("" if from_file else " No trips.csv in the run: trips and stops computed from track.csv.")
    )
    tr = _xy(positioned(run.track), frame)
    if not n_trip or not len(tr):
        # no trip: the track figure above shows the stop; no figure, and nothing omitted
        return Section("trips", title, body=f"<p>{esc(cap)}</p>{body}")
    fig = F._new(8.0, 6.5)
    ax = fig.add_subplot()
    ax.plot(tr["e_m"], tr["n_m"], color="#bbbbbb", lw=0.8, label="track")
    t = tr["t"].to_numpy(float)
    for k, r in enumerate(trips.loc[trips["kind"] == "trip"].itertuples(index=False)):
        m = (t >= r.t_start) & (t <= r.t_end)
        ax.plot(tr["e_m"][m], tr["n_m"][m], lw=1.8, label=f"trip {k + 1}")
    stops = trips.loc[trips["kind"] == "stop"]
    if len(stops):
        ne = frame.to_ned(
            stops["lat_start"].to_numpy(float), stops["lon_start"].to_numpy(float), np.zeros(len(stops))
        )
        ax.scatter(ne[:, 1], ne[:, 0], marker="s", s=60, color="#d62728", zorder=5, label="stops")
        for j, (e, n) in enumerate(zip(ne[:, 1], ne[:, 0], strict=True)):
            ax.annotate(f"S{j + 1}", (e, n), textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.set_xlabel("East, m")
    ax.set_ylabel("North, m")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)
    return Section("trips", title, fig, cap, body)


def _mount_section(runs: list[Run], truth: Truth | None, frame: LocalFrame) -> Section:
    title = "Mounting angle"
    mounts = {r.label: mount_table(r) for r in runs}
    mounts = {k: v for k, v in mounts.items() if len(v)}
    if not mounts:
        return Section(
            "mount", title, note="No mount-angle estimate in the events of the run(s): figure left out."
        )
    first = runs[0]
    m0 = mount_table(first)
    acc = m0.loc[m0["accepted"]]
    if not len(acc):
        return Section(
            "mount", title, note=f"{first.label}: no accepted mount-angle estimate: figure left out."
        )
    t_cal = float(acc["t"].iloc[0])
    mu = float(first.summary.get("mount_yaw_rad", math.nan))
    if not math.isfinite(mu):
        mu = float(acc["mount_yaw_rad"].iloc[-1])
    path = _xy(positioned(first.track), frame)
    true_mu = truth.mount_yaw_rad if truth is not None else math.nan
    finals = {}
    for r in runs:
        if r.label in mounts and len(r.track):
            finals[r.label] = (float(r.track["t"].max()), float(r.summary.get("mount_yaw_rad", math.nan)))
    fig = F.mount_figure(mounts, path, t_cal, mu, true_mu, finals=finals)
    cap = (
        f"{first.label}: first accepted estimate at {t_cal:.1f} s, final {math.degrees(mu):.2f}°"
        + (f" (true {math.degrees(true_mu):.2f}°)" if math.isfinite(true_mu) else "")
        + f"; {len(acc)} of {len(m0)} estimates accepted. Arrows: the output yaw is the sensor heading "
        "before the angle is known and the vehicle heading after; after calibration the faint arrows show "
        "the sensor x-axis (vehicle heading + mount angle)."
    )
    return Section("mount", title, fig, cap)


def _boot_section(run: Run, truth: Truth | None, frame: LocalFrame) -> Section:
    title = "Boot sequence"
    boot = boot_info(run)
    if not boot.interesting:
        when = f"at {boot.first_fix_t:.1f} s" if math.isfinite(boot.first_fix_t) else "never"
        return Section(
            "boot",
            title,
            note=f"No stored position and no rejected fix before the first accepted fix ({when}): figure left out.",
        )
    t_ff = boot.first_fix_t
    t_end = t_ff + 30.0 if math.isfinite(t_ff) else float(run.track["t"].max())
    g = (
        run.gnss
        if run.gnss is not None
        else pd.DataFrame({"t": [], "lat_deg": [], "lon_deg": [], "pdop": []})
    )
    rej = rejected_fixes(run)
    ep = g.loc[
        g["t"] <= t_end, ["t", "lat_deg", "lon_deg"] + (["pdop"] if "pdop" in g.columns else [])
    ].copy()
    if "pdop" not in ep.columns:
        ep["pdop"] = np.nan
    rej_t = rej["t"].to_numpy(float)
    ep["rejected"] = np.isin(np.round(ep["t"].to_numpy(float), 3), np.round(rej_t, 3))
    if "valid" in g.columns:
        ep.loc[~g.loc[ep.index, "valid"].to_numpy(bool), "rejected"] = True
    ep["reason"] = ""
    pos = np.isfinite(ep["lat_deg"].to_numpy(float)) & np.isfinite(ep["lon_deg"].to_numpy(float))
    ep["n_m"] = np.nan
    ep["e_m"] = np.nan
    if pos.any():
        xy = _xy(ep.loc[pos], frame, "lat_deg", "lon_deg")
        ep.loc[pos, "n_m"] = xy["n_m"].to_numpy()
        ep.loc[pos, "e_m"] = xy["e_m"].to_numpy()
    tr = _xy(positioned(run.track), frame)
    tr = tr.loc[tr["t"] <= t_end]
    stored = None
    if boot.stored is not None:
        ned = frame.to_ned(boot.stored[0], boot.stored[1], 0.0)
        stored = (float(ned[0]), float(ned[1]))
    ff = None
    if math.isfinite(t_ff):
        hit = ep.loc[(np.abs(ep["t"] - t_ff) < 1e-3) & np.isfinite(ep["n_m"])]
        if len(hit):
            ff = (t_ff, float(hit["n_m"].iloc[0]), float(hit["e_m"].iloc[0]))
    max_pdop = (
        float(run.config.get("last_position", {}).get("max_pdop", math.nan)) if run.config else math.nan
    )
    tru = None
    if truth is not None:
        tru = _xy(truth.table, frame)
        tru = tru.loc[tru["t"] <= t_end]
    fig = F.boot_figure(ep, tr, stored, ff, max_pdop, tru)
    reasons = rej.loc[rej["t"] < t_ff] if math.isfinite(t_ff) else rej
    by_reason = reasons["reason"].value_counts().to_dict()
    cap = (
        ("Stored last position loaded at boot. " if boot.stored is not None else "No stored position. ")
        + f"{len(boot.rejected_before)} fixes rejected before the first accepted one"
        + (" (" + ", ".join(f"{k}: {v}" for k, v in by_reason.items()) + ")" if by_reason else "")
        + (f"; first accepted fix at {t_ff:.1f} s" if math.isfinite(t_ff) else "; no fix accepted")
        + (f"; moved while off: {boot.moved_m:.0f} m" if math.isfinite(boot.moved_m) else "")
        + f". Window: start to {t_end:.0f} s."
    )
    return Section("boot", title, fig, cap)


def _states_section(runs: list[Run], truth: Truth | None, outages: list[tuple[float, float]]) -> Section:
    tracks = {r.label: r.track for r in runs}
    need = {"roll", "pitch", "yaw", "vn", "ve"}
    lacking = [r.label for r in runs if not need <= set(r.track.columns)]
    if lacking:
        return Section(
            "states",
            "Attitude and speed",
            note=f"Track lacks attitude/velocity columns ({', '.join(lacking)}).",
        )
    g = valid_fixes(runs[0])
    fig = F.states_figure(tracks, truth.table if truth is not None else None, g if len(g) else None, outages)
    return Section(
        "states",
        "Attitude, speed and uncertainty",
        fig,
        "Roll, pitch, yaw of the output (vehicle attitude once the mount angle is known), horizontal speed, "
        "and 3σ of the North/East position from the track's std_north/std_east.",
    )


def _bias_section(runs: list[Run]) -> Section:
    rows = []
    keys = (
        ("gyro_bias_rad_s", "gyro bias, rad/s"),
        ("acc_bias_mps2", "accelerometer bias, m/s²"),
        ("gyro_scale", "gyro scale factor"),
        ("acc_scale", "accelerometer scale factor"),
    )
    for r in runs:
        es = r.summary.get("engine_summary") or {}
        for k, name in keys:
            v = es.get(k)
            if isinstance(v, list) and v:
                rows.append([r.label, name, *[fmt(x, 3) for x in v[:3]]])
    note = (
        '<p class="note">Bias time series and their σ are not recorded by runs (track.csv has no bias columns), '
        "so no bias plot with 3σ bounds is drawn; the final estimates from summary.json are listed.</p>"
    )
    if not rows:
        return Section("biases", "Sensor biases", note="No bias estimate in summary.json.")
    return Section(
        "biases",
        "Sensor biases (final estimates)",
        body=note + table(["run", "quantity", "x", "y", "z"], rows, "stats"),
    )


def _nis_section(runs: list[Run]) -> Section:
    nis = {r.label: nis_table(r) for r in runs}
    nis = {k: v for k, v in nis.items() if len(v)}
    rows = []
    for r in runs:
        es = r.summary.get("engine_summary") or {}
        for meas, d in (es.get("nis") or {}).items():
            if isinstance(d, dict):
                rows.append([r.label, meas, d.get("count"), d.get("accepted"), d.get("mean_nis_per_dof")])
    body = (
        table(["run", "measurement", "updates", "accepted", "mean NIS per dof"], rows, "stats")
        if rows
        else ""
    )
    if not nis and not rows:
        return Section("nis", "NIS", note="No NIS in the events or summary of the run(s): left out.")
    fig = F.nis_figure(nis) if nis else None
    note = "" if nis else "No event carries a NIS value: only the summary table is shown."
    return Section(
        "nis",
        "Normalised innovation squared",
        fig,
        "NIS of the updates whose events carry one (gated rejections). A consistent filter has a mean NIS per "
        "degree of freedom near 1.",
        body,
        note,
    )


def _timeline_section(run: Run, outages: list[tuple[float, float]]) -> Section:
    per = static_periods(run)
    t = run.track["t"].to_numpy(float)
    t_range = (float(np.nanmin(t)), float(np.nanmax(t))) if t.size else (0.0, 1.0)
    counts: dict[str, int] = {}
    for e in run.events:
        counts[e["type"]] = counts.get(e["type"], 0) + 1
    fig = F.timeline_figure(run.events, per, outages, t_range) if run.events or per or outages else None
    listing = []
    for e in run.events[:2000]:
        extra = {k: v for k, v in e.items() if k not in ("type", "t")}
        listing.append([e.get("t"), e["type"], json.dumps(extra, default=str)[:300]])
    more = f"<p>… {len(run.events) - 2000} more in events.json</p>" if len(run.events) > 2000 else ""
    body = (
        table(["event type", "count"], sorted(counts.items()), "stats")
        + f"<details><summary>All {len(run.events)} events of {esc(run.label)}</summary>"
        + table(["t, s", "type", "details"], listing, "events")
        + more
        + "</details>"
    )
    note = "" if fig is not None else "No events, static periods or outages: nothing on the timeline."
    return Section(
        "events",
        f"Events ({run.label})",
        fig,
        "Boot events without a time are listed below only.",
        body,
        note,
    )


def _config_section(runs: list[Run]) -> Section:
    parts = []
    for r in runs:
        s = r.summary
        c = s.get("counts", {}) or {}
        rates = s.get("rates_hz", {}) or {}
        mu = s.get("mount_yaw_rad")
        info: list[list[Any]] = [
            ["directory", str(r.path)],
            ["engine", r.engine],
            ["output rows", c.get("output_rows")],
            ["output rate, Hz", rates.get("output")],
            ["GNSS epochs in / rate, Hz", f"{c.get('gnss_epochs_in', '–')} / {fmt(rates.get('gnss'))}"],
            ["IMU samples in / rate, Hz", f"{c.get('imu_samples_in', '–')} / {fmt(rates.get('imu'))}"],
            ["rows by source", ", ".join(f"{k} {v}" for k, v in (c.get("rows_by_source") or {}).items())],
            ["static rows", c.get("static_rows")],
            ["mount yaw, deg", math.degrees(mu) if isinstance(mu, (int, float)) else None],
            ["runtime, s", s.get("runtime_s")],
        ]
        if r.missing:
            info.append(["missing files", ", ".join(r.missing)])
        cfg = _flatten(r.config)
        cfg_html = (
            table(["parameter", "value"], cfg, "config")
            if cfg
            else '<p class="note">No configuration in summary.json.</p>'
        )
        notes = []
        for f in (s.get("ingest") or {}).get("files", []) or []:
            for n in f.get("notes", []) or []:
                notes.append(f"{f.get('path', '?')}: {n}")
        notes_html = "<ul>" + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>" if notes else ""
        parts.append(
            f"<h3>{esc(r.label)}</h3>"
            + table(["what", "value"], info, "kv")
            + "<h4>Engine configuration</h4>"
            + cfg_html
            + (f"<h4>Ingest notes</h4>{notes_html}" if notes_html else "")
            + f"<details><summary>summary.json of {esc(r.label)}</summary><pre>{esc(json.dumps(s, indent=1))}</pre></details>"
        )
    return Section("config", "Runs and configuration used", body="".join(parts))
