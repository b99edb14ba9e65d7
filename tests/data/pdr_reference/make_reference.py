"""Regenerate the stored pdr reference runs (``pdr_reference.npz``) of ``tests/test_pdr_kernel.py``.

Made with main's per-sample Python engine (commit 3ec104d, before the compiled kernel of
issue 21) and kept so that the compiled engine can be checked against the behaviour it
replaced. Re-running this script with a later engine overwrites the reference with that
engine's own output (which then proves nothing): do it only after a deliberate change of the
filter's numerics, and say so in the commit.

Input: the real hand-held walk ``rtklibexplorer_gnss_imu/walk_0827`` (135 s, 166 Hz IMU,
4 Hz RTK; read from ``$IOTNAV_DATASETS``, not stored), in two cases (:func:`cases`):

* ``walk``: the recording as it is;
* ``edited``: GNSS removed over 30-45 s and 70-100 s (pure PDR), IMU removed over
  50.0-51.0 s (a gap not integrated), and the fixes over 110-112 s moved 60 m North (gated
  out, then a position reset);
* ``short``: the first 55 s of ``edited`` (an outage and the gap; for a quick ``step()`` test).

Stored per case, from ``eng.step()`` sample by sample: every 211th output row (IMU index,
:data:`~iotnav.engines.base.FLOAT_COLUMNS`, source code, static), the sum over all rows of
each float column (NaN as 0) and of the source codes and static flags, the final ``x`` and
``P``; the events and the summary as JSON.

Usage (from a checkout of the engine to record, e.g. ``git worktree add /tmp/ref 3ec104d``)::

    cd /tmp/ref && IOTNAV_DATASETS=/path/to/datasets PYTHONPATH=src \
        python tests/data/pdr_reference/make_reference.py
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from iotnav.engines.base import FLOAT_COLUMNS, SOURCES, ImuSample, iter_samples
from iotnav.engines.pdr import PdrEngine
from iotnav.io import ingest
from iotnav.io.log import Log

OUT = Path(__file__).resolve().parent / "pdr_reference.npz"
EVERY = 211


def walk_log(datasets: Path) -> Log:
    """The walk_0827 recording (RTK ``.pos`` and the raw IMU csv with its ``.tag``)."""
    folder = datasets / "rtklibexplorer_gnss_imu" / "walk_0827"
    return ingest([folder / "gnss_1730_sf.pos", folder / "imu_1730.csv"])


def cases(log: Log) -> dict[str, Log]:
    """The two input cases (module docstring) built from the walk."""
    t0 = float(log.imu.t.iloc[0])
    g, imu = log.gnss.copy(), log.imu.copy()
    rel = g.t - t0
    g = g[~(((rel >= 30.0) & (rel < 45.0)) | ((rel >= 70.0) & (rel < 100.0)))].copy()
    jump = (g.t - t0 >= 110.0) & (g.t - t0 < 112.0)
    g.loc[jump, "lat_deg"] += 60.0 / 111_132.0
    r_imu = imu.t - t0
    imu = imu[~((r_imu >= 50.0) & (r_imu < 51.0))]
    edited = Log(
        gnss=g.reset_index(drop=True),
        imu=imu.reset_index(drop=True),
        mag=log.mag,
        utc_offset_s=log.utc_offset_s,
    )
    t_end = t0 + 55.0
    short = Log(
        gnss=edited.gnss[edited.gnss.t < t_end].reset_index(drop=True),
        imu=edited.imu[edited.imu.t < t_end].reset_index(drop=True),
        mag=log.mag,
        utc_offset_s=log.utc_offset_s,
    )
    return {"walk": log, "edited": edited, "short": short}


def record(eng: Any, log: Log) -> dict[str, Any]:
    """Run ``log`` through ``eng.step()``; what the reference stores (module docstring).

    ``tests/test_pdr_kernel.py`` records the compiled engine with this same function.
    """
    rows, sums, n = [], np.zeros(len(FLOAT_COLUMNS) + 2), 0
    for s in iter_samples(log):
        o = eng.step(s)
        if not isinstance(s, ImuSample) or o is None:
            continue
        d = o._asdict()
        vals = [d[c] for c in FLOAT_COLUMNS] + [SOURCES.index(o.source), float(o.static)]
        if n % EVERY == 0:
            rows.append([n, *vals])
        sums += np.nan_to_num(np.array(vals, dtype=float))
        n += 1
    return {
        "rows": np.array(rows),
        "sums": sums,
        "x": eng.x.copy(),
        "P": eng.P.copy(),
        "n": n,
        "events": json.loads(json.dumps(eng.events)),
        "summary": json.loads(json.dumps(eng.summary())),
    }


def main() -> None:
    log = walk_log(Path(os.environ["IOTNAV_DATASETS"]))
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {}
    for name, case in cases(log).items():
        r = record(PdrEngine(), case)
        for key in ("rows", "sums", "x", "P"):
            arrays[f"{name}/{key}"] = r[key]
        meta[name] = {"n": r["n"], "events": r["events"], "summary": r["summary"]}
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez_compressed(OUT, **arrays)  # type: ignore[arg-type]
    print(f"{OUT}: {OUT.stat().st_size} bytes")


if __name__ == "__main__":
    main()
