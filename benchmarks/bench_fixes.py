"""Benchmark the ``fixes`` engine (GNSS fixes alone): sparse fixes on real trajectories, speed.

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/fixes.md``.

What is measured
----------------
* **Sparse fixes** (issue 17 item 2, the S4 fix-interval study for GNSS alone): the
  rtklibexplorer ``drive_0708`` car drive (RTK solution as truth, :func:`iotnav.eval.outages.
  rtk_truth`) with tracker-grade fixes at 1 Hz (:func:`~iotnav.eval.outages.degrade_rtk`, the
  simulator's receiver model on the real trajectory; ``open-sky`` and ``urban-canyon``), speed
  and course as NMEA gives them (no NED velocity), thinned to one fix every 1, 10, 30, 60 s.
  Horizontal error (rms / p95, m) of the raw fixes, the forward and the RTS-smoothed track at
  the fix times, and of the smoothed track resampled at 1 Hz against the truth at every second
  (the error *between* fixes); ``cover`` is the fraction of the 1 Hz rows whose error is inside
  the 95 % circle of the reported per-axis sigma (``2.45 std_north``, equal axes).
* **Simulated urban drive**: 150 s of the ``car-tunnel`` route in an ``urban-canyon`` with 200
  outliers an hour (seeds 1-3), fixes with speed and course, and with positions only.
* **Parked**: the longest static captures of the gpsd NMEA corpus (the device did not move):
  apparent path of the raw fixes and of the output (an odometer), share of static rows,
  largest distance from the median position.
* **Husky** (robot_localization test bag, 2.5 Hz NavSatFix): path length of the raw fixes,
  forward and smoothed tracks against the 359 m of wheel odometry, every fix and thinned.
* **Speed**: batch fixes per second of :func:`iotnav.engines.base.run_batch` on a synthetic
  1 M-fix drive (CPU time of this process, one thread; the kernel alone apart), and the time of
  one streaming ``step(GnssSample)`` (median, p99). Targets: >= 1 M fixes/s, < 5 us a step.

Usage::

    python benchmarks/bench_fixes.py [--fixes 1000000]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from assemble import machine
from iotnav.engines import fixes_kernel as fk
from iotnav.engines.base import TangentPlane, iter_samples, run_batch
from iotnav.engines.fixes import FixesConfig, FixesEngine, FixesKFConfig
from iotnav.eval.cases import load_husky
from iotnav.eval.outages import OutageConfig, degrade_rtk, rtk_truth
from iotnav.io import ingest
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, coerce

DATA = Path("/work/shared/datasets")
OUT = Path(__file__).resolve().parent / "results" / "fixes.md"
SMOOTH = FixesConfig(kf=FixesKFConfig(smoothing=True))


def _err(df: pd.DataFrame, truth: pd.DataFrame, lat: str = "lat", lon: str = "lon") -> np.ndarray:
    f = TangentPlane(float(truth["lat"].iloc[0]), float(truth["lon"].iloc[0]), 0.0)
    tl = np.interp(df["t"], truth["t"], truth["lat"])
    to = np.interp(df["t"], truth["t"], truth["lon"])
    return np.hypot((df[lat].to_numpy() - tl) * f.k_n, (df[lon].to_numpy() - to) * f.k_e)


def _rp(e: np.ndarray) -> str:
    return f"{np.sqrt(np.mean(e**2)):.2f} / {np.percentile(e, 95):.2f}"


def sparse_study() -> list[str]:
    """Rows of the sparse-fix table on drive_0708."""
    truth = rtk_truth(ingest([DATA / "rtklibexplorer_gnss_imu" / "drive_0708" / "gnss_1934_sf.pos"]).gnss)
    rows = [
        "| environment | fix every (s) | fixes | raw | forward | smoothed | smoothed at 1 Hz | cover 95 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for env in ("open-sky", "urban-canyon"):
        g, _ = degrade_rtk(truth, OutageConfig(gnss_rate_hz=1.0, environment=env, seed=0))
        g = g.assign(vn=np.nan, ve=np.nan, vd=np.nan)
        for step in (1, 10, 30, 60):
            sub = g.iloc[::step].reset_index(drop=True)
            eng = FixesEngine(SMOOTH)
            fwd = run_batch(eng, Log(gnss=sub))
            sm = eng.smoothed_output(fwd)
            rs = eng.resample(1.0, smoothed=True, forward=fwd)
            er = _err(rs, truth)
            cover = float(np.mean(er <= 2.4477 * rs["std_north"].to_numpy()))
            rows.append(
                f"| {env} | {step} | {len(sub)} | {_rp(_err(sub, truth, 'lat_deg', 'lon_deg'))} | "
                f"{_rp(_err(fwd, truth))} | {_rp(_err(sm, truth))} | {_rp(er)} | {cover:.2f} |"
            )
    return rows


def urban_study(seeds: tuple[int, ...] = (1, 2, 3)) -> list[str]:
    """Rows of the simulated urban-canyon drive with outliers: NMEA-like and position-only fixes."""
    from iotnav import sim

    rows = [
        "| seed | fixes carry | raw | forward | smoothed | gated |",
        "|---|---|---|---|---|---|",
    ]
    for seed in seeds:
        r = sim.build(
            "car-tunnel",
            seed=seed,
            overrides={
                "duration_s": 150.0,
                "imu.enabled": False,
                "gnss.outages_s": [],
                "gnss.environment": "urban-canyon",
                "gnss.outliers_per_hour": 200.0,
            },
        )
        nmea = r.gnss.assign(vn=np.nan, ve=np.nan, vd=np.nan)
        for what, g in (("speed, course", nmea), ("position only", nmea.assign(course_valid=False))):
            eng = FixesEngine(SMOOTH)
            fwd = run_batch(eng, Log(gnss=g))
            sm = eng.smoothed_output(fwd)
            gated = eng.summary()["event_counts"].get("fix_rejected", 0)
            rows.append(
                f"| {seed} | {what} | {_rp(_err(g, r.truth, 'lat_deg', 'lon_deg'))} | {_rp(_err(fwd, r.truth))} | "
                f"{_rp(_err(sm, r.truth))} | {gated} |"
            )
    return rows


def held_out_study() -> list[str]:
    """Do no harm on real trajectories the gate and rollback were not tuned on (tuned on the urban table).

    drive_0708 (car), walk_0827 (hand-held) and the Husky (robot; its own fixes as truth, about
    1 m) degraded with the simulator's receiver model (:func:`~iotnav.eval.outages.degrade_rtk`,
    1 Hz, seed 0; drive_0708 seeds 0 and 1), speed and course as NMEA gives them or positions
    only (course invalid; the speed then serves only the static test).
    """
    rows = [
        "| trajectory | platform | environment | seed | fixes carry | raw | forward | worse than raw? |",
        "|---|---|---|---|---|---|---|---|",
    ]
    drive = rtk_truth(ingest([DATA / "rtklibexplorer_gnss_imu" / "drive_0708" / "gnss_1934_sf.pos"]).gnss)
    walk = rtk_truth(ingest([DATA / "rtklibexplorer_gnss_imu" / "walk_0827" / "gnss_1730_sf.pos"]).gnss)
    husky = load_husky(DATA / "robot_localization_husky")[1]
    for name, truth, platform, seeds in (
        ("drive_0708", drive, "car", (0, 1)),
        ("walk_0827", walk, "pedestrian", (0,)),
        ("husky", husky, "pedestrian", (0,)),
    ):
        for env in ("open-sky", "urban-canyon"):
            for seed in seeds:
                g, _ = degrade_rtk(truth, OutageConfig(gnss_rate_hz=1.0, environment=env, seed=seed))
                g = g.assign(vn=np.nan, ve=np.nan, vd=np.nan)
                for what, gg in (("speed, course", g), ("position only", g.assign(course_valid=False))):
                    fwd = run_batch(
                        FixesEngine(FixesConfig(kf=FixesKFConfig(platform=platform))), Log(gnss=gg)
                    )
                    raw = _err(gg[gg["t"].isin(fwd["t"])], truth, "lat_deg", "lon_deg")
                    ef = _err(fwd, truth)
                    worse = [
                        w
                        for w, a, b in (
                            ("rms", np.sqrt(np.mean(ef**2)), np.sqrt(np.mean(raw**2))),
                            ("p95", np.percentile(ef, 95), np.percentile(raw, 95)),
                        )
                        if a > b + 0.005
                    ]
                    rows.append(
                        f"| {name} | {platform} | {env} | {seed} | {what} | {_rp(raw)} | {_rp(ef)} | "
                        f"{' and '.join(worse) if worse else 'no'} |"
                    )
    return rows


def forward_cover_study() -> list[str]:
    """Cover of the forward (live) rows' 95 % circle on the held-out trajectories (1 Hz, seed 0).

    The same receiver model and trajectories as :func:`held_out_study` (speed and course as NMEA
    gives them); cover: share of the forward rows whose horizontal error is inside
    ``2.4477 x std_north`` (the 95 % circle of equal per-axis sigmas), plus the rejected rows'.
    """
    rows = [
        "| trajectory | platform | environment | fixes | forward | median sigma (m) | cover 95 % | rejected rows | their cover |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    drive = rtk_truth(ingest([DATA / "rtklibexplorer_gnss_imu" / "drive_0708" / "gnss_1934_sf.pos"]).gnss)
    walk = rtk_truth(ingest([DATA / "rtklibexplorer_gnss_imu" / "walk_0827" / "gnss_1730_sf.pos"]).gnss)
    husky = load_husky(DATA / "robot_localization_husky")[1]
    for name, truth, platform in (
        ("drive_0708", drive, "car"),
        ("walk_0827", walk, "pedestrian"),
        ("husky", husky, "pedestrian"),
    ):
        for env in ("open-sky", "urban-canyon"):
            g, _ = degrade_rtk(truth, OutageConfig(gnss_rate_hz=1.0, environment=env, seed=0))
            g = g.assign(vn=np.nan, ve=np.nan, vd=np.nan)
            fwd = run_batch(FixesEngine(FixesConfig(kf=FixesKFConfig(platform=platform))), Log(gnss=g))
            ef = _err(fwd, truth)
            sig = fwd["std_north"].to_numpy()
            inside = ef <= 2.4477 * sig
            rej = (fwd["source"] == "dr").to_numpy()
            rc = f"{np.mean(inside[rej]):.2f}" if rej.any() else "-"
            rows.append(
                f"| {name} | {platform} | {env} | {len(fwd)} | {_rp(ef)} | {np.median(sig):.2f} | "
                f"{np.mean(inside):.2f} | {int(rej.sum())} | {rc} |"
            )
    return rows


GPSD_STATIC = (
    "ublox-zed-f9p_hpg1.11.log",
    "telit-he910.log",
    "nmea-rtk.log",
    "ublox-neo-m9n-nmea.log",
    "quectel-l76k-nmea.log",
)


def parked_study() -> list[str]:
    """Rows of the parked table: gpsd's static captures (the device did not move)."""
    rows = [
        "| log | fixes | raw path (m) | output path (m) | output / raw | rows static | raw max from median (m) |"
        " output max from median (m) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in GPSD_STATIC:
        log = ingest([DATA / "gpsd_nmea_corpus" / "logs" / name])
        g = log.gnss[log.gnss["valid"]]
        eng = FixesEngine()
        out = run_batch(eng, log)
        raw_lat, raw_lon = g["lat_deg"].to_numpy(), g["lon_deg"].to_numpy()
        f = TangentPlane(float(np.median(raw_lat)), float(np.median(raw_lon)), 0.0)

        def spread(lat: np.ndarray, lon: np.ndarray, f: TangentPlane = f) -> float:
            return float(np.max(np.hypot((lat - f.lat0_deg) * f.k_n, (lon - f.lon0_deg) * f.k_e)))

        lr = _length(g, "lat_deg", "lon_deg")
        lo = _length(out)
        rows.append(
            f"| `{name}` | {len(g)} | {lr:.1f} | {lo:.1f} | {lo / lr:.3f} | {out['static'].mean():.2f} | "
            f"{spread(raw_lat, raw_lon):.1f} | {spread(out['lat'].to_numpy(), out['lon'].to_numpy()):.1f} |"
        )
    return rows


def _length(df: pd.DataFrame, lat: str = "lat", lon: str = "lon") -> float:
    f = TangentPlane(float(df[lat].iloc[0]), float(df[lon].iloc[0]), 0.0)
    return float(np.sum(np.hypot(np.diff(df[lat]) * f.k_n, np.diff(df[lon]) * f.k_e)))


def husky_study() -> list[str]:
    """Rows of the Husky path-length table."""
    g = load_husky(DATA / "robot_localization_husky")[0].gnss
    g = g.assign(vn=np.nan, ve=np.nan, vd=np.nan, speed_mps=np.nan, course_valid=False)  # fixes only
    rows = [
        "| platform | fix every | raw (m) | forward (m) | smoothed (m) | smoothed vs odometry |",
        "|---|---|---|---|---|---|",
    ]
    for platform in ("car", "pedestrian"):
        for step in (1, 3, 25):
            sub = g.iloc[::step].reset_index(drop=True)
            eng = FixesEngine(FixesConfig(kf=FixesKFConfig(smoothing=True, platform=platform)))
            fwd = run_batch(eng, Log(gnss=sub))
            ls = _length(eng.smoothed_output(fwd))
            rows.append(
                f"| {platform} | {0.4 * step:.1f} s | {_length(sub, 'lat_deg', 'lon_deg'):.1f} | "
                f"{_length(fwd):.1f} | {ls:.1f} | {100 * (ls / 359.0 - 1):+.1f} % |"
            )
    return rows


def synthetic_drive(n: int, seed: int = 0) -> pd.DataFrame:
    """``n`` fixes at 1 Hz of a wandering drive (0-20 m/s), 2 m white errors, HDOP to 0.1."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    heading = np.cumsum(rng.normal(0, 0.05, n))
    speed = np.abs(10 + np.cumsum(rng.normal(0, 0.2, n)) % 40 - 20)
    north = np.cumsum(speed * np.cos(heading))
    east = np.cumsum(speed * np.sin(heading))
    f = TangentPlane(45.0, 7.0, 100.0)
    return coerce(
        pd.DataFrame(
            {
                "t": t,
                "utc": t + 1.7e9,
                "lat_deg": 45.0 + (north + rng.normal(0, 2, n)) / f.k_n,
                "lon_deg": 7.0 + (east + rng.normal(0, 2, n)) / f.k_e,
                "height_m": 100.0,
                "hdop": np.round(rng.uniform(0.6, 2.0, n), 1),
                "pdop": 2.0,
                "num_sv": 10,
                "speed_mps": speed,
                "course_rad": np.mod(heading, 2 * np.pi),
                "course_valid": True,
                "valid": True,
            }
        ),
        GNSS_COLUMNS,
    )


def speed(n: int) -> list[str]:
    """Rows of the speed table."""
    g = synthetic_drive(n)
    log = Log(gnss=g)
    run_batch(FixesEngine(), Log(gnss=g.iloc[:100]))  # load the compiled kernels
    best_cpu, best_wall, kernel = np.inf, np.inf, np.inf
    for _ in range(3):
        eng = FixesEngine()
        w0, c0 = time.perf_counter(), time.process_time()
        run_batch(eng, log)
        best_wall = min(best_wall, time.perf_counter() - w0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    # the kernel alone: the input rows prepared once, then one call over them
    from iotnav.engines.base import OutputBlock, _SampleSource
    from iotnav.engines.fixes import _FIELDS

    for _ in range(3):
        eng = FixesEngine()
        src = _SampleSource(log, eng.guard)
        inp = np.zeros((n, fk.N_INPUT))
        eng._fill_columns(inp, dict(zip(_FIELDS, src.gcols, strict=True)))
        out = OutputBlock(n)
        c0 = time.process_time()
        eng._process(
            inp, out, np.zeros(n, np.int8), np.zeros(n, np.int32), np.zeros(n), np.zeros((1, fk.REC_SIZE))
        )
        kernel = min(kernel, time.process_time() - c0)
    eng = FixesEngine()
    samples = list(iter_samples(Log(gnss=g.iloc[:20_000])))
    for s in samples[:100]:
        eng.step(s)
    ts = np.empty(len(samples) - 100)
    for i, s in enumerate(samples[100:]):
        a = time.perf_counter()
        eng.step(s)
        ts[i] = time.perf_counter() - a

    def med_us(f: Any, items: list[Any]) -> float:
        t = np.empty(len(items))
        for i, x in enumerate(items):
            a = time.perf_counter()
            f(x)
            t[i] = time.perf_counter() - a
        return float(np.median(t) * 1e6)

    # the parts of one step, each timed alone on the same engine (median over 4000 fixes)
    row, part = eng._row, samples[100:4100]
    fill = med_us(lambda s: eng._fill_row(row[0], s), part)
    proc = med_us(lambda s: eng._step_row(), part)
    return [
        "| what | value | target |",
        "|---|---|---|",
        f"| batch `run_batch`, CPU time | {n / best_cpu:,.0f} fixes/s | >= 1,000,000 |",
        f"| batch `run_batch`, wall clock | {n / best_wall:,.0f} fixes/s | |",
        f"| kernel alone (prepared rows), CPU time | {n / kernel:,.0f} fixes/s | |",
        f"| streaming `step(GnssSample)` median / p99 | {np.median(ts) * 1e6:.1f} / {np.percentile(ts, 99) * 1e6:.1f} us | < 5 us |",
        f"| of which: input row from the sample (`_fill_row`), median | {fill:.1f} us | |",
        f"| of which: the compiled kernel on the row, its Python wrapper and the `Output` (`_step_row`), median | {proc:.1f} us | |",
    ]


def main() -> None:
    """Run the studies; print (and write) the section."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fixes", type=int, default=1_000_000, help="fixes of the speed run")
    ap.add_argument("--forward-cover", action="store_true", help="print only the forward cover table")
    args = ap.parse_args()
    if args.forward_cover:
        print("\n".join(forward_cover_study()))
        return
    lines = [
        "## GNSS fixes alone: the `fixes` engine",
        "",
        f"Machine: {machine()}. `python benchmarks/bench_fixes.py --fixes {args.fixes}`.",
        "",
        "### Sparse fixes on a real drive (drive_0708, RTK truth, tracker-grade fixes)",
        "",
        "Horizontal error rms / p95, m. Raw, forward and smoothed at the fix times; smoothed at 1 Hz"
        " against the truth every second; cover: share of those 1 Hz rows inside the 95 % circle of"
        " the reported sigma.",
        "",
        *sparse_study(),
        "",
        "### Simulated urban drive with outliers (car-tunnel route, 150 s, urban canyon, 200 outliers/h)",
        "",
        "Horizontal error rms / p95, m, at the fix times.",
        "",
        *urban_study(),
        "",
        "### Do no harm on trajectories not tuned on (real trajectories, simulated receiver errors)",
        "",
        "Horizontal error rms / p95, m, at the fix times; raw = the fixes = holding the last fix. The gate,"
        " the rollback and the static rules were tuned on the simulated urban drive above.",
        "",
        *held_out_study(),
        "",
        "### Forward (live) sigma on the same trajectories (1 Hz, seed 0, speed and course)",
        "",
        "Cover: share of the forward rows inside the 95 % circle of the reported sigma (at least the"
        " last accepted fix's, grown by the model between fixes; `FixesEngine` docstring).",
        "",
        *forward_cover_study(),
        "",
        "### Parked: gpsd's static captures (real receivers standing still)",
        "",
        "Output path: the odometer a track would give (sum of row-to-row distances).",
        "",
        *parked_study(),
        "",
        "### Husky (real GNSS, 2.5 Hz): path length against 359 m of wheel odometry",
        "",
        *husky_study(),
        "",
        "### Speed",
        "",
        *speed(args.fixes),
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        OUT.write_text(text)


if __name__ == "__main__":
    main()
