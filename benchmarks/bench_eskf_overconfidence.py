"""Where eskf claims too little after its heading is known (issue 16, left item (a)): per window.

For every 30 s outage window of the drive_0708 cuts of :mod:`iotnav.eval.cases` (one run per
window, the window's fixes masked, as in :mod:`iotnav.eval.outages`), the horizontal error at
the last output before the window ends, split along and across the true velocity, against the
claimed horizontal 1-sigma ``hypot(std_n, std_e)``; the window's time since the heading was set.
A ratio above 2.15 (the 2-D 99 % radius) is a window the covariance does not cover.

Run: ``.venv/bin/python benchmarks/bench_eskf_overconfidence.py ['{"knob": value}']``: the
optional JSON changes the profile's eskf settings (a what-if); with ``IOTNAV_WRITE_RESULTS=1``
and no change the markdown is written to ``benchmarks/results/eskf_overconfidence.md``.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from iotnav.engines.base import TangentPlane, run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.eval.cases import CASES, load_case
from iotnav.eval.outages_feed import mask_windows, moving_part, outage_windows
from iotnav.io.log import Log


def windows(changes: dict[str, Any]) -> list[str]:
    md = [
        "| case | window start (s) | since heading (s) | end error (m) | along (m) | across (m) "
        "| claimed sigma (m) | error / sigma |",
        "|---|---|---|---|---|---|---|---|",
    ]
    ratios = []
    for case in (k for k in CASES if k.startswith("drive_0708")):
        lc = load_case(case)
        oc, g, tr = lc.config, lc.fed.gnss, lc.truth
        m0, m1 = moving_part(tr, oc.moving_speed_mps)
        t0 = float(tr.t.iloc[0])
        fr = TangentPlane(float(tr.lat.iloc[0]), float(tr.lon.iloc[0]), float(tr.height.iloc[0]))
        tt = tr.t.to_numpy(float)
        for st, L in outage_windows(m0, m1, [30.0], oc.spacing_s, oc.first_offset_s, g["t"].to_numpy(float)):
            eng = EskfEngine(EskfConfig(**{**dict(lc.profile.eskf), **changes}))
            imu = lc.fed.imu[lc.fed.imu.t < st + L + 1.0]
            df = run_batch(eng, Log(gnss=mask_windows(g, [(st, L)]), imu=imu, mag=lc.fed.mag))
            row = df[df.t < st + L].iloc[-1]
            k = int(np.searchsorted(tt, row.t))
            p = fr.to_ned(row.lat, row.lon, row.height)
            q = fr.to_ned(tr.lat.iloc[k], tr.lon.iloc[k], tr.height.iloc[k])
            e = (p - q)[:2]
            v = np.array([tr.vn.iloc[k], tr.ve.iloc[k]])
            u = v / max(float(np.linalg.norm(v)), 0.1)
            sig = math.hypot(row.std_north, row.std_east)
            th = next(ev["t"] for ev in eng.events if ev["type"] == "heading_initialised")
            r = float(np.linalg.norm(e)) / sig
            ratios.append(r)
            md.append(
                f"| {case} | {st - t0:.0f} | {st - th:.0f} | {np.linalg.norm(e):.1f} | {float(e @ u):.1f} "
                f"| {float(u[0] * e[1] - u[1] * e[0]):.1f} | {sig:.1f} | {r:.1f} |"
            )
            print(md[-1], flush=True)
    a = np.array(ratios)
    md += [
        "",
        f"Median error / sigma {np.median(a):.2f}; above 2.15 in {int((a > 2.15).sum())} of {a.size} windows.",
    ]
    return md


def main(changes: dict[str, Any]) -> None:
    md = [
        "# eskf after its heading: error against the claimed sigma at the end of 30 s outages",
        "",
        "Regenerate: `IOTNAV_WRITE_RESULTS=1 .venv/bin/python benchmarks/bench_eskf_overconfidence.py`.",
        "Along / across: the end error along and across the true velocity there (negative along:",
        "behind the truth).",
        "",
        *windows(changes),
    ]
    text = "\n".join(md) + "\n"
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1" and not changes:
        (Path(__file__).parent / "results" / "eskf_overconfidence.md").write_text(text)


if __name__ == "__main__":
    main(json.loads(sys.argv[1]) if len(sys.argv) > 1 else {})
