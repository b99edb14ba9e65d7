"""Why the demo's fused track is not better than its raw fixes (``iotnav demo``, ``make run``).

Run: ``.venv/bin/python benchmarks/bench_eskf_demo.py`` (the demo's own inputs: ``scooter-laps``,
seed 1, 240 s, written and ingested as ``iotnav demo`` does; the ``pipeline`` engine it fuses with,
guarded as ``make_engine`` builds it, and ``eskf`` beside it); with ``IOTNAV_WRITE_RESULTS=1`` the
markdown goes to ``benchmarks/results/eskf_demo.md``. Nothing is tuned here: it measures.

What it measures, per engine: the horizontal error of every output row and of the output at the
fix epochs (like with like: the raw fixes are scored at their epochs only), the correlation of the
engine's error with the fixes' own error at those epochs, the RMS of their difference (what the
engine adds to the fixes' error), the GNSS error's autocorrelation, the time shift of the truth
that best explains each track (a lag), and where the largest error is.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from iotnav import sim
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.eval.metrics import LocalFrame, track_errors
from iotnav.io import ingest

RESULTS = Path(__file__).parent / "results"


def _best_shift(t: np.ndarray, ned: np.ndarray, tt: np.ndarray, tn: np.ndarray) -> tuple[float, float]:
    """The time shift ``s`` (s) minimising the RMS of ``track(t) - truth(t - s)``, and that RMS (m)."""
    sel = (t > tt[0] + 5.0) & (t < tt[-1] - 5.0)
    best = (math.nan, math.inf)
    for s in np.arange(-0.5, 0.501, 0.02):
        ref = np.column_stack([np.interp(t[sel] - s, tt, tn[:, k]) for k in range(2)])
        r = math.sqrt(float(np.mean(np.sum((ned[sel, :2] - ref) ** 2, axis=1))))
        if r < best[1]:
            best = (float(s), r)
    return best


def _speed(tt: np.ndarray, tn: np.ndarray, t: float) -> float:
    """Truth horizontal speed at ``t`` (m/s), from the positions 0.1 s either side."""
    p0 = [np.interp(t - 0.1, tt, tn[:, k]) for k in range(2)]
    p1 = [np.interp(t + 0.1, tt, tn[:, k]) for k in range(2)]
    return math.hypot(p1[0] - p0[0], p1[1] - p0[1]) / 0.2


def main() -> None:
    res = sim.build("scooter-laps", seed=1, overrides={"duration_s": 240.0})
    d = Path(tempfile.mkdtemp()) / "sim"
    sim.write(res, d)
    slog = ingest([d])
    truth = pd.read_csv(d / "truth.csv")
    raw = slog.gnss.loc[slog.gnss["valid"]].rename(
        columns={"lat_deg": "lat", "lon_deg": "lon", "height_m": "height"}
    )
    er = track_errors(raw, truth)
    tt = truth.t.to_numpy(float)
    fr = LocalFrame(float(truth.lat.iloc[0]), float(truth.lon.iloc[0]), float(truth.height.iloc[0]))
    tn = fr.to_ned(truth.lat.to_numpy(), truth.lon.to_numpy(), truth.height.to_numpy())
    gn = fr.to_ned(raw.lat.to_numpy(), raw.lon.to_numpy(), raw.height.to_numpy())

    def rms(x: np.ndarray) -> float:
        return math.sqrt(float(np.mean(x * x)))

    md = [
        "# The demo's fused track against its raw fixes",
        "",
        "`python benchmarks/bench_eskf_demo.py` (scooter-laps, seed 1, 240 s: the inputs of `iotnav demo`).",
        "",
        "| solution | RMS every row (m) | max (m) | RMS at fix epochs (m) | corr. with GNSS error | "
        "RMS (engine - GNSS error) (m) | best truth shift (s) | RMS after 30 s (m) | max after 30 s (m) | "
        "largest error at (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    s_g, _ = _best_shift(raw.t.to_numpy(float), gn, tt, tn)
    late_g = er.t > 30.0
    md.append(
        f"| raw fixes | {rms(er.h_err):.2f} | {er.h_err.max():.2f} | {rms(er.h_err):.2f} | 1 | 0 | {s_g:+.2f} | "
        f"{rms(er.h_err[late_g]):.2f} | {er.h_err[late_g].max():.2f} | {er.t[int(np.argmax(er.h_err))]:.1f} |"
    )
    notes: list[str] = []
    for name in ("pipeline", "eskf"):
        fused = run_batch(make_engine(name), slog)
        fused = fused[fused.source != "none"]
        ef = track_errors(fused, truth)
        n_at, e_at = np.interp(er.t, ef.t, ef.n_err), np.interp(er.t, ef.t, ef.e_err)
        corr = float(
            (n_at * er.n_err + e_at * er.e_err).sum()
            / math.sqrt(float((n_at**2 + e_at**2).sum() * (er.n_err**2 + er.e_err**2).sum()))
        )
        diff = np.hypot(n_at - er.n_err, e_at - er.e_err)
        fn = fr.to_ned(fused.lat.to_numpy(), fused.lon.to_numpy(), fused.height.to_numpy())
        s_f, _ = _best_shift(fused.t.to_numpy(float), fn, tt, tn)
        late = ef.t > 30.0
        k = int(np.argmax(ef.h_err))
        g = slog.gnss[slog.gnss.t < ef.t[k]].iloc[-1]
        notes.append(
            f"{name}: largest error {ef.h_err[k]:.2f} m at {ef.t[k]:.2f} s; the last fix before it "
            f"({g.t:.1f} s, {er.h_err[np.searchsorted(er.t, g.t)]:.2f} m off) has speed {g.speed_mps:.2f} m/s, "
            f"course valid: {bool(g.course_valid)}, vn/ve given: {bool(np.isfinite(g.vn))}; the engine's "
            f"output speed there {math.hypot(fused.vn.iloc[np.searchsorted(fused.t, ef.t[k])], fused.ve.iloc[np.searchsorted(fused.t, ef.t[k])]):.2f} m/s, "
            f"the truth's {_speed(tt, tn, ef.t[k]):.2f} m/s."
        )
        md.append(
            f"| {name} | {rms(ef.h_err):.2f} | {ef.h_err.max():.2f} | {rms(np.hypot(n_at, e_at)):.2f} | {corr:.2f} | "
            f"{rms(diff):.2f} | {s_f:+.2f} | {rms(ef.h_err[late]):.2f} | {ef.h_err[late].max():.2f} | "
            f"{ef.t[int(np.argmax(ef.h_err))]:.1f} |"
        )
    ac = []
    for lag in (1, 10, 30, 60):
        a = (er.n_err[:-lag] * er.n_err[lag:] + er.e_err[:-lag] * er.e_err[lag:]).sum() / (
            er.n_err**2 + er.e_err**2
        ).sum()
        ac.append(f"{lag} s: {a:.2f}")
    md += ["", f"GNSS error autocorrelation (1 Hz fixes): {', '.join(ac)}.", "", *notes, ""]
    text = "\n".join(md)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (RESULTS / "eskf_demo.md").write_text(text)


if __name__ == "__main__":
    main()
