"""Regenerate the stored qekf reference runs (``qekf_reference.npz``) of ``tests/test_qekf_kernel.py``.

Made with main's per-sample Python engine (commit 7f3bbd5, before the compiled kernel of
issue 21) and kept so that the compiled engine can be checked against the behaviour it
replaced. Re-running this script with a later engine overwrites the reference with that
engine's own output (which then proves nothing): do it only after a deliberate change of the
filter's numerics, and say so in the commit.

Each case stores its input (the ingested log's IMU, GNSS and magnetometer tables, so the test
does not depend on the simulator staying the same), the configuration overrides, and what
the engine produced through ``step()``, sample by sample:

* every 4th output row (the float columns of :data:`iotnav.engines.base.FLOAT_COLUMNS` and
  the source code);
* ``x`` and ``P`` after every 3rd GNSS sample (at most 24), and at the end;
* the NIS list (time and value) and the event counts;
* with smoothing, the record times and the sum over the records of each recorded array.

Usage (from a checkout of the engine to record, e.g. ``git worktree add /tmp/ref 7f3bbd5``)::

    cd /tmp/ref && PYTHONPATH=src python tests/data/qekf_reference/make_reference.py
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from iotnav import sim
from iotnav.engines.base import FLOAT_COLUMNS, SOURCES, GnssSample, ImuSample, iter_samples
from iotnav.engines.qekf import QekfConfig, QekfEngine
from iotnav.io import ingest
from iotnav.io.log import Log

OUT = Path(__file__).resolve().parent / "qekf_reference.npz"

#: name -> (scenario, seed, simulator overrides, config form, config overrides)
CASES: dict[str, tuple[str, int, dict[str, Any], str, dict[str, Any]]] = {
    # the paper's form: TRIAD observations, GNSS velocity, smoothing records
    "paper": (
        "car-magnetometer",
        0,
        {"duration_s": 24.0},
        "paper",
        {"init_duration_s": 5.0, "smoothing": True},
    ),
    # the consistent form: direction observations, 28 states, cross-axis noise, positions only
    "consistent": (
        "car-magnetometer",
        3,
        {"duration_s": 24.0},
        "consistent",
        {"init_duration_s": 5.0, "use_gnss_velocity": False},
    ),
    # no magnetometer: the fallback (mount aligner, horizontal re-initialisations)
    "fallback": ("car-tunnel", 0, {"duration_s": 24.0}, "paper", {"init_duration_s": 5.0, "smoothing": True}),
}


def config(scenario: sim.SimResult, form: str, overrides: dict[str, Any]) -> QekfConfig:
    """The case's configuration (the simulated magnetometer's calibration, WMM 2020.45)."""
    kw: dict[str, Any] = {"wmm_year": 2020.45, **overrides}
    if scenario.config.mag.enabled:
        hard, soft = scenario.mag_calibration()
        kw.update(mag_hard_iron_ut=hard, mag_soft_iron=soft)
    return (QekfConfig.consistent if form == "consistent" else QekfConfig)(**kw)


def record(eng: QekfEngine, log: Log) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Run ``log`` through ``eng.step()`` and keep what the reference stores (module docstring).

    Returns every 4th output row (IMU sample index, :data:`FLOAT_COLUMNS`, source code), ``x``
    (with the IMU sample index in front) and ``P`` after every 3rd GNSS sample once initialised
    (at most 24), and the number of IMU output rows. ``tests/test_qekf_kernel.py`` records the
    compiled engine with this same function.
    """
    eng.utc_offset_s = log.utc_offset_s
    rows, xs, Ps, n_imu, n_gnss = [], [], [], 0, 0
    for s in iter_samples(log):
        o = eng.step(s)
        if isinstance(s, ImuSample) and o is not None:
            if n_imu % 4 == 0:
                d = o._asdict()
                rows.append([n_imu] + [d[c] for c in FLOAT_COLUMNS] + [SOURCES.index(o.source)])
            n_imu += 1
        elif isinstance(s, GnssSample):
            if n_gnss % 3 == 0 and eng.initialised and len(xs) < 24:
                xs.append(np.r_[n_imu, eng.x])
                Ps.append(eng.P.copy())
            n_gnss += 1
    return np.array(rows), np.array(xs), np.array(Ps), n_imu


def main() -> None:
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {}
    for name, (scen, seed, sim_over, form, cfg_over) in CASES.items():
        with tempfile.TemporaryDirectory() as tmp:
            r = sim.build(scen, seed=seed, overrides=sim_over)
            sim.write(r, Path(tmp))
            log = ingest([Path(tmp)])
        cfg = config(r, form, cfg_over)
        meta[name] = {
            "form": form,
            "config": cfg_over,
            "utc_offset_s": log.utc_offset_s,
            "scenario": scen,
            "seed": seed,
            "sim": sim_over,
        }
        if cfg.mag_soft_iron is not None:
            meta[name]["mag_soft_iron"] = list(cfg.mag_soft_iron)
            meta[name]["mag_hard_iron_ut"] = list(cfg.mag_hard_iron_ut)
        for table in ("imu", "gnss", "mag"):
            df = getattr(log, table)
            meta[name][table + "_columns"] = list(df.columns)
            meta[name][table + "_dtypes"] = [str(d) for d in df.dtypes]
            for col in df.columns:
                values = df[col].to_numpy()
                # text columns (the GNSS source) as fixed-width strings: loadable without pickle
                arrays[f"{name}/{table}/{col}"] = values.astype(str) if values.dtype == object else values
        eng = QekfEngine(cfg)
        rows, xs, Ps, n_imu = record(eng, log)
        arrays[f"{name}/rows"] = rows
        arrays[f"{name}/x"] = xs
        arrays[f"{name}/P"] = Ps
        arrays[f"{name}/x_end"] = eng.x.copy()
        arrays[f"{name}/P_end"] = eng.P.copy()
        arrays[f"{name}/nis"] = np.array([(t, v) for t, _, v, _ in eng.nis])
        counts: dict[str, int] = {}
        for e in eng.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        meta[name]["event_counts"] = counts
        meta[name]["n_imu"] = n_imu
        log_s = eng.smoothing_log
        meta[name]["smoothing_records"] = 0 if log_s is None else len(log_s)
        if log_s is not None:
            arrays[f"{name}/smooth_t"] = np.array(log_s.t)
            for part in ("x_prior", "P_prior", "Phi", "x_post", "P_post"):
                arrays[f"{name}/smooth_{part}_sum"] = np.sum(getattr(log_s, part), axis=0)
        print(name, n_imu, "imu rows;", len(xs), "snapshots;", counts)
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez_compressed(OUT, **arrays)
    print(OUT, OUT.stat().st_size, "bytes")


if __name__ == "__main__":
    main()
