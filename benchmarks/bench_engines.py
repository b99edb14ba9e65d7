"""Every available engine on car-tunnel (outage drift) and car-magnetometer (attitude), seeded.

Rows: each engine of :func:`iotnav.engines.registry.available_engines` with its default
configuration, forward and RTS-smoothed (:func:`iotnav.engines.smoother.smooth_output`, for
engines that keep a smoothing log), plus a GNSS-only baseline that holds the last valid fix.

* car-tunnel (600 s, MPU-6050 at 100 Hz, 1 Hz GNSS, five tunnels of 12-60 s): horizontal drift
  at the end of each outage as a percentage of the distance driven in it, median and worst over
  the 30-60 s outages and over all; horizontal RMS outside the outages; forward samples/s.
* car-magnetometer (40 s static, town driving, 4 s gap, magnetometer): roll / pitch / yaw RMS
  after the initialisation (sensor attitude against truth; mount is zero in this scenario) and
  the largest horizontal error in the gap.

Run ``python benchmarks/bench_engines.py``; with ``IOTNAV_WRITE_RESULTS=1`` the markdown is
also written to ``benchmarks/results/engines.md``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from iotnav import sim
from iotnav.engines.base import run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.engines.qekf import QekfConfig, QekfEngine
from iotnav.engines.registry import available_engines, make_engine
from iotnav.engines.smoother import smooth_output
from iotnav.eval.metrics import outage_drift, track_errors
from iotnav.io import ingest
from iotnav.io.log import Log

SEED = 0


def _scenario(name: str, tmp: Path) -> tuple[sim.SimResult, Log]:
    r = sim.build(name, seed=SEED, overrides={})
    sim.write(r, tmp / name)
    return r, ingest([tmp / name])


def _gnss_hold(log: Log, t_out: np.ndarray) -> pd.DataFrame:
    """Baseline: the last valid fix held at every IMU time."""
    g = log.gnss[log.gnss["valid"].astype(bool)].sort_values("t")
    k = np.searchsorted(g["t"].to_numpy(), t_out, side="right") - 1
    ok = k >= 0
    kk = np.clip(k, 0, len(g) - 1)
    lat = np.where(ok, g["lat_deg"].to_numpy()[kk], np.nan)
    lon = np.where(ok, g["lon_deg"].to_numpy()[kk], np.nan)
    h = np.where(ok, g["height_m"].to_numpy()[kk], np.nan)
    return pd.DataFrame({"t": t_out, "lat": lat, "lon": lon, "height": h})


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return np.degrees(np.angle(np.exp(1j * a)))


def _attitude_rms(df: pd.DataFrame, truth: pd.DataFrame, t_min: float) -> dict[str, float]:
    if "roll" not in df:
        return {c: float("nan") for c in ("roll", "pitch", "yaw")}
    d = df[df["t"] >= t_min].dropna(subset=["roll"])
    out = {}
    for c in ("roll", "pitch", "yaw"):
        ref = np.interp(d["t"], truth["t"], np.unwrap(truth[c].to_numpy()))
        out[c] = float(np.sqrt(np.mean(_wrap_deg(d[c].to_numpy() - ref) ** 2)))
    return out


def _tunnel_row(r: sim.SimResult, df: pd.DataFrame) -> dict[str, Any]:
    ok = df.dropna(subset=["lat"])
    err = track_errors(ok, r.truth)
    outs = list(r.config.gnss.outages_s)
    drift = outage_drift(err, r.truth, outs)
    pct = np.array([d["drift_pct"] for d in drift])
    long_ = np.array([d["drift_pct"] for d in drift if 30.0 <= d["length_s"] <= 60.0])
    inside = np.zeros(len(err.t), bool)
    for a, b in outs:
        inside |= (err.t >= a) & (err.t <= b + 5.0)
    largest = [float(err.h_err[(err.t >= a) & (err.t <= b)].max()) for a, b in outs]
    return {
        "largest": largest,
        "drift_each": " / ".join(f"{p:.1f}" for p in pct),
        "drift_med_long": float(np.median(long_)) if long_.size else float("nan"),
        "drift_max_long": float(np.max(long_)) if long_.size else float("nan"),
        "rms_out": float(np.sqrt(np.mean(err.h_err[~inside] ** 2))),
    }


def _mag_row(r: sim.SimResult, df: pd.DataFrame, t_init: float) -> dict[str, Any]:
    ok = df.dropna(subset=["lat"])
    err = track_errors(ok, r.truth)
    a, b = r.config.gnss.outages_s[0]
    m = (err.t >= a) & (err.t <= b + 0.5)
    rms = _attitude_rms(df, r.truth, t_init)
    return {**rms, "gap_max": float(err.h_err[m].max()) if m.any() else float("nan")}


def _runs(name: str, r: sim.SimResult, log: Log) -> list[tuple[str, pd.DataFrame, str]]:
    """(label, output, note) for every engine, forward and smoothed, and the baseline (note: why no result)."""
    out: list[tuple[str, pd.DataFrame, str]] = []
    smooth = {"pipeline", "anchor", "qekf", "eskf"}  # engines with an RTS pass: keep its records
    factories: dict[str, Callable[[], Any]] = {
        e: partial(make_engine, e, smoothing=e in smooth) for e in available_engines()
    }
    if "qekf" in factories and name == "car-magnetometer":
        hard, soft = r.mag_calibration()  # the user's calibration and the date for the field model
        cfg = QekfConfig(
            mag_hard_iron_ut=hard,
            mag_soft_iron=soft,
            wmm_year=2020.45,
            smoothing=True,
        )
        factories["qekf"] = lambda: QekfEngine(cfg)
    if "qekf" in factories:  # the consistent form (QekfConfig.consistent), the same calibration
        ccfg = QekfConfig.consistent(smoothing=True)
        if name == "car-magnetometer":
            ccfg = dataclasses.replace(ccfg, mag_hard_iron_ut=hard, mag_soft_iron=soft, wmm_year=2020.45)
        factories["qekf consistent"] = lambda: QekfEngine(ccfg)
    if "eskf" in factories and name == "car-magnetometer":
        hard, soft = r.mag_calibration()  # the same calibration; the declination instead of the date
        ecfg = EskfConfig(
            mag_hard_iron_ut=hard,
            mag_soft_iron=soft,
            mag_declination_rad=math.radians(r.config.mag.declination_deg),
            smoothing=True,
        )
        factories["eskf"] = lambda: EskfEngine(ecfg)
    for eng_name, make in factories.items():
        if eng_name == "pdr":
            out.append(
                (
                    eng_name,
                    pd.DataFrame(),
                    "pedestrian (step) engine: not for a car; see the walk outage study",
                )
            )
            continue
        eng = make()
        try:
            fwd = run_batch(eng, log)
        except Exception as exc:
            print(f"{eng_name} on {name}: {type(exc).__name__}: {exc}")
            continue
        if not fwd["lat"].notna().any():
            out.append((eng_name, fwd, "no position: needs absolute position+attitude fixes"))
            continue
        out.append((eng_name, fwd, ""))
        if getattr(eng, "smoothing_log", None) is not None:
            try:
                out.append((f"{eng_name} + smooth", smooth_output(eng, fwd), ""))
            except Exception as exc:
                print(f"{eng_name} smoothing on {name}: {type(exc).__name__}: {exc}")
    out.append(("GNSS-only hold", _gnss_hold(log, log.imu["t"].to_numpy()), ""))
    return out


def main() -> str:
    """Run the benchmark and return the markdown."""
    lines = [
        "# Engines on car-tunnel and car-magnetometer",
        "",
        f"Seed {SEED}, default configurations (on car-magnetometer, `qekf` and `eskf` get the "
        "user's magnetometer calibration); `qekf consistent` is `QekfConfig.consistent()` "
        '(`form = "consistent"`); `+ smooth` is the RTS smoother over the forward run. '
        "Speed: see the engine speed section.",
        "",
    ]
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        r, log = _scenario("car-tunnel", tmp)
        outs = ", ".join(f"{a:.0f}-{b:.0f}" for a, b in r.config.gnss.outages_s)
        lines += [
            f"## car-tunnel (600 s, MPU-6050 100 Hz, GNSS 1 Hz; outages {outs} s)",
            "",
            "Largest error in each outage: the largest horizontal error inside it; for `+ smooth` "
            "rows, in brackets, its ratio to the forward run's (issue #5 target: at most 0.25).",
            "",
            "| engine | drift % per outage | median % (30-60 s) | worst % (30-60 s) | RMS outside (m) "
            "| largest error in each outage (m) |",
            "|---|---|---|---|---|---|",
        ]
        forward: dict[str, list[float]] = {}
        for label, df, note in _runs("car-tunnel", r, log):
            if note:
                lines.append(f"| {label} | {note} | | | | |")
                continue
            row = _tunnel_row(r, df)
            base = label.removesuffix(" + smooth")
            if base != label and base in forward:
                largest = " / ".join(
                    f"{s:.1f} ({s / f:.2f})" for s, f in zip(row["largest"], forward[base], strict=True)
                )
            else:
                forward[label] = row["largest"]
                largest = " / ".join(f"{s:.1f}" for s in row["largest"])
            lines.append(
                f"| {label} | {row['drift_each']} | {row['drift_med_long']:.1f} | {row['drift_max_long']:.1f} "
                f"| {row['rms_out']:.2f} | {largest} |"
            )
        r, log = _scenario("car-magnetometer", tmp)
        t_init = 41.0
        lines += [
            "",
            "## car-magnetometer (40 s static, town driving, 4 s GNSS gap, magnetometer 6 Hz)",
            "",
            f"Attitude RMS after t = {t_init:.0f} s (sensor attitude; mount zero).",
            "",
            "| engine | roll RMS (deg) | pitch RMS (deg) | yaw RMS (deg) | max error in gap (m) |",
            "|---|---|---|---|---|",
        ]
        for label, df, note in _runs("car-magnetometer", r, log):
            if note:
                lines.append(f"| {label} | {note} | | | |")
                continue
            row = _mag_row(r, df, t_init)
            lines.append(
                f"| {label} | {row['roll']:.2f} | {row['pitch']:.2f} | {row['yaw']:.2f} | {row['gap_max']:.2f} |"
            )
    md = "\n".join(lines) + "\n"
    return md


if __name__ == "__main__":
    text = main()
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "engines.md"
        out.write_text(text)
        print(f"written {out}")
