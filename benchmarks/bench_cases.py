"""Issue 16 cases: every position engine through GNSS outages on logs it was never tuned on.

Run: ``.venv/bin/python benchmarks/bench_cases.py [CASE ...]`` (default: every case of
:data:`iotnav.eval.cases.CASES`); with ``IOTNAV_WRITE_RESULTS=1`` the markdown is written to
``benchmarks/results/cases.md``. ``IOTNAV_CASES_VARIANTS`` (default ``raw,guarded``) chooses
the engines' variants: ``raw`` (the engine alone, :func:`iotnav.engines.registry.make_engine`
with ``integrity=False``) and ``guarded`` (wrapped by :mod:`iotnav.engines.integrity`, what
``make_engine`` builds by default); ``IOTNAV_CASES_ENGINES`` (comma-separated, default all) runs
only some engines, for short checks: their rows replace theirs in the case's JSON, the other
engines' rows are kept, and each case's markdown says which commit measured which rows
(``measured``). Each case's tables are also kept as JSON in
``benchmarks/results/cases/`` so that the markdown can be rebuilt without a rerun
(``IOTNAV_CASES_REUSE=1``).

Targets (issue 16): in every outage window of every case each engine no worse than ``hold``
(end error at most the hold's), its median no worse than ``dr-velocity``, no NaN. Do no harm,
counted as ``harmful``: no window worse than ``hold`` whose claimed horizontal sigma at the
window's end (``end_sigma_m``, :func:`iotnav.eval.outages.study`) does not cover the error
(error above :data:`COVER_K` times it, the 2-D 99 % radius).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import chi2

from iotnav.engines.base import Engine
from iotnav.eval.cases import CASES, load_case
from iotnav.eval.outages import BASELINES, DR_VELOCITY, HOLD, OutageResult, engine_factories, study

RESULTS = Path(__file__).parent / "results"
CACHE = RESULTS / "cases"
ENGINES = ("pipeline", "anchor", "qekf", "eskf")
#: An end error beyond this many times the claimed horizontal 1-sigma ``hypot(std_n, std_e)`` is
#: not covered: the 99 % radius of a 2-D Gaussian, ``sqrt(chi2.ppf(0.99, 2) / 2)``.
COVER_K = math.sqrt(chi2.ppf(0.99, 2) / 2.0)


def factories(profile, variants: tuple[str, ...]) -> dict[str, Callable[[], Engine]]:  # type: ignore[no-untyped-def]
    """``name`` (raw) and ``name+guard`` builders for the engines that apply to the profile."""
    names = ENGINES + tuple(e for e in profile.extra_engines if e not in ENGINES)
    only = os.environ.get("IOTNAV_CASES_ENGINES")
    if only:  # a short run on some engines (their JSON then holds only those)
        names = tuple(n for n in names if n in only.split(","))
    out: dict[str, Callable[[], Engine]] = {}
    if "raw" in variants:
        out.update(engine_factories(profile, names, integrity=False))
    if "guarded" in variants:
        for k, f in engine_factories(profile, names, integrity=True).items():
            out[f"{k}+guard"] = f
    return out


def verdicts(windows: pd.DataFrame) -> pd.DataFrame:
    """Per engine and length: windows worse than hold, median vs dr-velocity, NaN count."""
    rows = []
    base = windows[windows.engine.isin(BASELINES)].set_index(["engine", "length_s", "start"])
    for (eng, L), w in windows.groupby(["engine", "length_s"], sort=False):
        if eng in BASELINES:
            continue
        h = base.loc[HOLD].loc[L].end_error_m.reindex(w.start.to_numpy())
        d = base.loc[DR_VELOCITY].loc[L]
        e = w.end_error_m.to_numpy(float)
        is_worse = ~(e <= h.to_numpy(float) + 1e-9)
        worse = int(is_worse.sum())
        sig = w.end_sigma_m.to_numpy(float) if "end_sigma_m" in w.columns else np.full(len(w), np.nan)
        # harm: worse than hold while claiming better (the claimed sigma does not cover the error)
        harmful = int((is_worse & ~(e <= COVER_K * sig)).sum())
        med = float(pd.Series(e).median())
        rows.append(
            {
                "engine": eng,
                "length_s": L,
                "windows": len(w),
                "worse_than_hold": worse,
                "harmful": harmful,
                "nan": int(pd.isna(w.end_error_m).sum()),
                "median_end_error_m": med,
                "dr_velocity_median_m": float(d.end_error_m.median()),
                "hold_median_m": float(base.loc[HOLD].loc[L].end_error_m.median()),
                "median_ok": bool(med <= float(d.end_error_m.median()) + 1e-9),
            }
        )
    return pd.DataFrame(rows)


def _f(x: float, nd: int = 1) -> str:
    return "-" if not math.isfinite(x) else f"{x:.{nd}f}"


def case_markdown(name: str, res: OutageResult, seconds: float) -> list[str]:
    v = verdicts(res.windows)
    s = res.summary.set_index(["engine", "length_s"])
    md = [
        f"### {name}",
        "",
        f"{res.meta['duration_s']:.0f} s, moving part {res.meta['moving_part_s'][0]:.0f}-"
        f"{res.meta['moving_part_s'][1]:.0f} s, fed GNSS {res.gnss['epochs']} fixes (error vs truth: "
        f"horizontal RMS {res.gnss['rms_h_m']:.2f} m), {seconds:.0f} s to run.",
        "",
        "| engine | outage (s) | windows | worse than hold | harmful | NaN | median end error (m) | "
        "dr-velocity median (m) | hold median (m) | median <= dr-velocity | median drift (%) | worst drift (%) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for b in BASELINES:
        for L in sorted(set(res.windows.length_s)):
            w = res.windows[(res.windows.engine == b) & (res.windows.length_s == L)]
            md.append(
                f"| {b} | {L:g} | {len(w)} | - | - | - | {_f(float(w.end_error_m.median()))} | - | - | - | "
                f"{_f(s.loc[(b, L), 'median_drift_pct'])} | {_f(s.loc[(b, L), 'worst_drift_pct'])} |"
            )
    for r in v.itertuples():
        md.append(
            f"| {r.engine} | {r.length_s:g} | {r.windows} | {r.worse_than_hold} | {r.harmful} | {r.nan} | "
            f"{_f(r.median_end_error_m)} | {_f(r.dr_velocity_median_m)} | {_f(r.hold_median_m)} | "
            f"{'yes' if r.median_ok else 'no'} | {_f(s.loc[(r.engine, r.length_s), 'median_drift_pct'])} | "
            f"{_f(s.loc[(r.engine, r.length_s), 'worst_drift_pct'])} |"
        )
    md.append("")
    return md


def _to_json(res: OutageResult) -> dict:  # type: ignore[type-arg]
    return {
        "windows": res.windows.to_dict("records"),
        "summary": res.summary.to_dict("records"),
        "mount": res.mount.to_dict("records"),
        "gnss": res.gnss,
        "meta": res.meta,
    }


def _from_json(d: dict) -> OutageResult:  # type: ignore[type-arg]
    return OutageResult(
        windows=pd.DataFrame(d["windows"]),
        summary=pd.DataFrame(d["summary"]),
        mount=pd.DataFrame(d["mount"]),
        gnss=d["gnss"],
        meta=d["meta"],
    )


_REVISION: list[str] = []  # the code's commit, taken once when the run starts (main)


def _revision() -> str:
    """The commit of the code this process runs (``+changes``: with uncommitted changes in src)."""
    if _REVISION:
        return _REVISION[0]
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True, cwd=RESULTS
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "src"], capture_output=True, text=True, cwd=RESULTS
        )
        rev += "+changes" if dirty.stdout.strip() else ""
    except (OSError, subprocess.CalledProcessError):
        rev = "unknown"
    _REVISION.append(rev)
    return rev


def _measured(res: OutageResult) -> dict[str, str]:
    """Per engine of ``res``: the commit and UTC date its rows were measured at."""
    when = time.strftime("%Y-%m-%d", time.gmtime())
    return {e: f"{_revision()} {when}" for e in dict.fromkeys(res.windows.engine) if e not in BASELINES}


def _merge_json(old: dict, new: dict) -> dict:  # type: ignore[type-arg]
    """A short run on some engines (``IOTNAV_CASES_ENGINES``) merged into the case's earlier JSON:
    their rows replace theirs, the other engines' rows are kept with their own ``measured``."""
    fresh = {e for e in new["measured"]}
    out = dict(old)
    for key in ("windows", "summary", "mount"):
        keep = [
            r
            for r in old[key]
            if r["engine"] not in fresh and (key == "mount" or r["engine"] not in BASELINES)
        ]
        out[key] = (
            [r for r in new[key] if r["engine"] in BASELINES or r["engine"] in fresh] + keep
            if key != "mount"
            else keep + [r for r in new[key] if r["engine"] in fresh]
        )
    before = old.get("measured") or {
        e: "earlier run" for e in dict.fromkeys(r["engine"] for r in old["windows"])
    }
    out["measured"] = {**{e: m for e, m in before.items() if e not in BASELINES}, **new["measured"]}
    out["seconds"] = float(old.get("seconds", math.nan))  # of the run that measured every engine
    out["rerun_seconds"] = {**old.get("rerun_seconds", {}), ",".join(sorted(fresh)): float(new["seconds"])}
    out["gnss"], out["meta"] = new["gnss"], {**new["meta"], "engines": old["meta"].get("engines")}
    return out


def _merge(parts: list[OutageResult]) -> OutageResult:
    """One result from the raw and guarded runs of a case (the baselines once)."""

    def cat(attr: str) -> pd.DataFrame:
        df = pd.concat([getattr(p, attr) for p in parts], ignore_index=True)
        keys = [c for c in ("engine", "length_s", "start") if c in df.columns]
        return df.drop_duplicates(subset=keys, keep="first").reset_index(drop=True)

    return OutageResult(cat("windows"), cat("summary"), cat("mount"), parts[0].gnss, parts[0].meta)


def summary_table(results: dict[str, OutageResult]) -> list[str]:
    """Before (engine alone) -> after (guarded), per case and engine: windows worse than hold, median."""
    md = [
        "## Summary: engine alone -> guarded",
        "",
        "Per case and outage length: windows worse than hold (of all), harmful windows (worse than hold",
        f"while the claimed horizontal sigma does not cover the error: error > {COVER_K:.2f} hypot(std_n, std_e),",
        "the 2-D 99 % radius), and the median end error (m) beside the dr-velocity median. Cases with",
        "only one variant run show that one (`-`: not measured in that run).",
        "",
        "| case | outage (s) | engine | worse than hold | harmful | median end error (m) | dr-velocity median (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, res in results.items():
        v = verdicts(res.windows).set_index(["engine", "length_s"])
        for L in sorted(set(res.windows.length_s)):
            for eng in dict.fromkeys(e.removesuffix("+guard") for e, _ in v.index):
                raw, g = (eng, L), (f"{eng}+guard", L)
                key = raw if raw in v.index else g
                n = int(v.loc[key, "windows"])
                cells = []
                for col in ("worse_than_hold", "harmful", "median_end_error_m"):
                    pair = [float(v.loc[k, col]) if k in v.index else math.nan for k in (raw, g)]
                    if col in ("worse_than_hold", "harmful"):
                        txt = ["-" if not math.isfinite(x) else f"{int(x)}/{n}" for x in pair]
                    else:
                        txt = [_f(x) for x in pair]
                    cells.append(f"{txt[0]} -> {txt[1]}")
                dr = v.loc[key, "dr_velocity_median_m"]
                md.append(
                    f"| {name} | {L:g} | {eng} | {cells[0]} | {cells[1]} | {cells[2]} | {_f(float(dr))} |"
                )
    md.append("")
    return md


def run_case(name: str, variants: tuple[str, ...]) -> tuple[OutageResult, float]:
    lc = load_case(name)
    t0 = time.perf_counter()
    res = study(lc.fed, lc.truth, lc.profile, lc.config, factories(lc.profile, variants), fed=lc.fed)
    return res, time.perf_counter() - t0


def main() -> None:
    names = sys.argv[1:] or list(CASES)
    _revision()  # before the runs: the code imported is the code of now
    variants = tuple(os.environ.get("IOTNAV_CASES_VARIANTS", "raw,guarded").split(","))
    CACHE.mkdir(parents=True, exist_ok=True)
    md = [
        "# Cases of issue 16: do no harm through GNSS outages",
        "",
        "Regenerate: `IOTNAV_WRITE_RESULTS=1 .venv/bin/python benchmarks/bench_cases.py`.",
        "",
        "Cases (:mod:`iotnav.eval.cases`): drive_0708 cut to start in motion (100 s, 220 s) with 1 or",
        "3 deg/s of gyro bias on each axis and the sensor turned a further 5 deg roll, 10 deg pitch, fed",
        "the RTK degraded to 1 Hz tracker grade; the Husky (2.5 Hz SBAS fixes, also the truth: errors",
        "under ~1 m are noise); walk_0827. One run per outage window (:mod:`iotnav.eval.outages`).",
        "End error: horizontal error at the last output before the window ends. `X` is the engine",
        "alone, `X+guard` the same engine inside :mod:`iotnav.engines.integrity` (the default of",
        "`make_engine`). Targets: worse than hold in 0 windows, median <= dr-velocity's, no NaN.",
        "",
    ]
    header = list(md)
    merged: dict[str, OutageResult] = {}
    for name in names:
        parts: list[OutageResult] = []
        measured: dict[str, str] = {}
        rerun: dict[str, float] = {}
        sec = 0.0
        for variant in ("raw", "guarded"):
            f = CACHE / f"{name}-{variant}.json"
            if variant in variants and os.environ.get("IOTNAV_CASES_REUSE") != "1":
                res, s = run_case(name, (variant,))
                d_new = {**_to_json(res), "seconds": s, "measured": _measured(res)}
                if os.environ.get("IOTNAV_CASES_ENGINES") and f.exists():
                    d_new = _merge_json(json.loads(f.read_text()), d_new)
                f.write_text(json.dumps(d_new, default=float))
            if f.exists():
                d = json.loads(f.read_text())
                parts.append(_from_json(d))
                sec += float(d["seconds"])
                for e, m in (d.get("measured") or {}).items():
                    measured[e] = m
                for es, x in (d.get("rerun_seconds") or {}).items():
                    rerun[es] = x
        if not parts:
            md += [f"### {name}", "", "(not run for this table)", ""]
            continue
        res = _merge(parts)
        merged[name] = res
        part = case_markdown(name, res, sec)
        if measured:  # rows of engines re-run alone (IOTNAV_CASES_ENGINES) say when
            by: dict[str, list[str]] = {}
            for e, m in measured.items():
                by.setdefault(m, []).append(e)
            when = "; ".join(f"{', '.join(es)}: {m}" for m, es in by.items())
            again = "".join(f" {es} re-run alone in {x:.0f} s." for es, x in rerun.items())
            part[3:3] = [f"Rows measured at (commit, date): {when}.{again}", ""]
        print("\n".join(part), flush=True)
        md += part
    md[len(header) : len(header)] = summary_table(merged)
    text = "\n".join(md)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (RESULTS / "cases.md").write_text(text)


if __name__ == "__main__":
    main()
