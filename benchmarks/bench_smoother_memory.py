"""RTS smoother (``iotnav run --smooth``): peak memory and time per hour of 100 Hz data (issue 21).

Prints markdown; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/smoother_memory.md``. ``--before SRC`` runs another checkout's ``src``
folder (e.g. main's before the bounded-memory records) beside this one and compares their
smoothed tracks.

Scenario ``car-tunnel`` (seed 1, ``--duration`` s, one hour by default) written once to a
temporary folder; each figure comes from a fresh Python process that loads it and runs the
``eskf`` engine with :func:`iotnav.engines.base.run_batch`: once without smoothing (the
forward run's own peak) and once with ``smoothing=True`` followed by
:func:`iotnav.engines.smoother.smooth_output`. Peak memory is the process's maximum resident
set size after a short warm run in the same process (which compiles or loads the kernels; the
mark is reset through ``/proc/self/clear_refs`` and read as ``VmHWM``, Linux); each run's growth
is that peak less the resident size when the measured run starts, and the smoothing's share is
the growth with smoothing less the growth without. Times are CPU seconds (``time.process_time``) after
that warm run, measured on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

SCENARIO = "car-tunnel"
SEED = 1
COLUMNS = ("north", "east", "down", "vn", "ve", "vd", "roll", "pitch", "yaw", "std_north", "std_east")

_CHILD = """
import json, pickle, resource, sys, time
import numpy as np
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.io.log import Log
data, mode, out = sys.argv[1], sys.argv[2], sys.argv[3]
with open(data, "rb") as f:
    gnss, imu, mag = pickle.load(f)
log = Log(gnss=gnss, imu=imu, mag=mag)
warm = Log(gnss=gnss.iloc[:200], imu=imu.iloc[:20000], mag=mag.iloc[:2000])
smoothing = mode == "smooth"
from iotnav.engines.smoother import smooth_output
e = make_engine("eskf", smoothing=smoothing)
f = run_batch(e, warm)
if smoothing:
    smooth_output(e, f)
del e, f
import gc
gc.collect()
try:  # reset the peak-RSS mark (Linux): the compile and warm run are not counted
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    reset = True
except OSError:
    reset = False
def _rss(key):
    with open("/proc/self/status") as fh:
        return next(int(l.split()[1]) for l in fh if l.startswith(key))
start_kb = _rss("VmRSS:") if reset else 0
eng = make_engine("eskf", smoothing=smoothing)
t0 = time.process_time()
fwd = run_batch(eng, log)
res = {"forward_s": time.process_time() - t0, "rows": len(fwd)}
if smoothing:
    t0 = time.process_time()
    sm = smooth_output(eng, fwd)
    res["smooth_s"] = time.process_time() - t0
    sl = eng.smoothing_log
    res["records"] = len(sl)
    stored = getattr(sl, "stored_bytes", None)
    if stored is not None:
        res["ram_bytes"], res["file_bytes"] = stored
    cols = sys.argv[4].split(",")
    np.save(out, sm[list(cols)].to_numpy(float))
res["peak_rss_kb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
if reset:
    res["peak_rss_kb"] = _rss("VmHWM:")
res["start_rss_kb"] = start_kb
res["reset"] = reset
print(json.dumps(res))
"""


def _child(src: Path, data: Path, mode: str, out: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(src)}
    cmd = [sys.executable, "-c", _CHILD, str(data), mode, str(out), ",".join(COLUMNS)]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return dict(json.loads(res.stdout.strip().splitlines()[-1]))


def main(duration_s: float, before: Path | None, label: str) -> str:
    from iotnav import sim

    here = Path(__file__).resolve().parents[1] / "src"
    runs = [("this checkout", here)]
    if before is not None:
        runs.insert(0, (f"before: {label or before}", before))
    hours = duration_s / 3600.0
    with tempfile.TemporaryDirectory(prefix="iotnav-smoother-bench-") as tmp:
        r = sim.build(SCENARIO, seed=SEED, overrides={"duration_s": duration_s})
        data = Path(tmp) / "log.pkl"
        with open(data, "wb") as f:
            pickle.dump((r.gnss, r.imu, r.mag), f)
        n_imu = len(r.imu)
        del r
        rows = []
        tracks = []
        for name, src in runs:
            out = Path(tmp) / f"track{len(tracks)}.npy"
            fw = _child(src, data, "forward", out)
            sm = _child(src, data, "smooth", out)
            tracks.append(np.load(out))
            rows.append((name, fw, sm))
    lines = [
        "# RTS smoother memory (eskf, `iotnav run --smooth`)",
        "",
        (__doc__ or "").split("\n\n", 2)[2].strip(),
        "",
        f"Run: {duration_s:g} s ({n_imu} IMU samples, 100 Hz), `{SCENARIO}` seed {SEED}.",
        "",
        "| code | records | peak RSS, forward only (growth) | peak RSS with smoothing (growth) "
        "| smoothing's share, per hour | records in RAM / on disk, per hour | forward CPU s "
        "| smoothing CPU s (smooth_output) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, fw, sm in rows:
        g_fw = fw["peak_rss_kb"] - fw["start_rss_kb"]
        g_sm = sm["peak_rss_kb"] - sm["start_rss_kb"]
        share = (g_sm - g_fw) / 1024.0 / hours
        if "ram_bytes" in sm:
            st = f"{sm['ram_bytes'] / 2**20 / hours:.0f} MB / {sm['file_bytes'] / 2**20 / hours:.0f} MB"
        else:
            st = f"{sm['records'] * 8 * (1 + 2 * 30 + 3 * 900) / 2**20 / hours:.0f} MB / 0 (lists of arrays)"
        lines.append(
            f"| {name} | {sm['records']} | {fw['peak_rss_kb'] / 1024:.0f} MB ({g_fw / 1024:.0f} MB) "
            f"| {sm['peak_rss_kb'] / 1024:.0f} MB ({g_sm / 1024:.0f} MB) "
            f"| {share:.0f} MB | {st} | {sm['forward_s']:.1f} | {sm['smooth_s']:.2f} |"
        )
    if len(tracks) == 2:
        a, b = tracks
        same_nan = bool(np.array_equal(np.isnan(a), np.isnan(b)))
        d = np.nanmax(np.abs(a - b), axis=0)
        lines += [
            "",
            "Smoothed track, this checkout against the one before: NaN pattern "
            + ("identical" if same_nan else "DIFFERENT")
            + "; largest difference per column: "
            + ", ".join(f"{c} {v:.1e}" for c, v in zip(COLUMNS, d, strict=True))
            + " (m, m/s, rad).",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--duration", type=float, default=3600.0, help="simulated seconds (default 3600)")
    ap.add_argument("--before", type=Path, help="src folder of another checkout to run beside this one")
    ap.add_argument("--before-label", default="", help="name of --before in the table")
    args = ap.parse_args()
    text = main(args.duration, args.before, args.before_label)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        p = Path(__file__).parent / "results" / "smoother_memory.md"
        p.write_text(text)
        print(f"written {p}")
