"""The compiled pdr engine against runs stored from the per-sample Python engine it replaced.

``tests/data/pdr_reference/pdr_reference.npz`` was made by its ``make_reference.py`` at main
3ec104d (before the kernel) on the real walk_0827 (the ``datasets`` fixture: fails when the
shared datasets are absent), as recorded and edited (GNSS outages, an IMU gap, a 60 m jump),
and the first 55 s of the edited one.
Both paths of the compiled engine are checked: ``step()`` sample by sample (the reference's
own recording function) and :func:`~iotnav.engines.base.run_batch` (the block kernel over
the IMU samples between GNSS epochs): outputs, final state and summary to 1e-9, events the
same.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from iotnav.engines.base import FLOAT_COLUMNS, SOURCES, run_batch
from iotnav.engines.pdr import PdrEngine

REFERENCE = Path(__file__).resolve().parent / "data" / "pdr_reference" / "pdr_reference.npz"


def _make_reference() -> ModuleType:
    """The script that made the reference (its case builder and recording function)."""
    path = REFERENCE.with_name("make_reference.py")
    spec = importlib.util.spec_from_file_location("pdr_make_reference", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _close(a: Any, b: Any, path: str = "") -> None:
    """Nested JSON-like values equal, floats to 1e-9 (relative and absolute), NaN equal to NaN."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for k in a:
            _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), path
        for i, (u, v) in enumerate(zip(a, b, strict=True)):
            _close(u, v, f"{path}[{i}]")
    elif isinstance(a, float) or isinstance(b, float):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9, err_msg=path)
    else:
        assert a == b, path


@pytest.fixture(scope="module")
def cases(datasets: Path) -> dict[str, Any]:
    mr = _make_reference()
    return {"module": mr, "logs": mr.cases(mr.walk_log(datasets))}


@pytest.mark.parametrize("name", ["short"])
def test_step_matches_python_engine(cases: dict[str, Any], name: str) -> None:
    """``step()`` of the compiled engine reproduces the stored run of the Python engine (the
    first 55 s of the edited walk: an outage and the IMU gap; the whole walks through batch)."""
    ref = np.load(REFERENCE)
    meta = json.loads(str(ref["meta"]))[name]
    eng = PdrEngine()
    got = cases["module"].record(eng, cases["logs"][name])
    assert got["n"] == meta["n"]
    np.testing.assert_allclose(got["rows"], ref[f"{name}/rows"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["sums"], ref[f"{name}/sums"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["x"], ref[f"{name}/x"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["P"], ref[f"{name}/P"], rtol=1e-9, atol=1e-12)
    _close(meta["events"], got["events"], "events")
    _close(meta["summary"], got["summary"], "summary")


@pytest.mark.parametrize("name", ["walk", "edited"])
def test_batch_matches_python_engine(cases: dict[str, Any], name: str) -> None:
    """:func:`run_batch` (the block kernel) gives the same rows, events and summary."""
    ref = np.load(REFERENCE)
    meta = json.loads(str(ref["meta"]))[name]
    eng = PdrEngine()
    df = run_batch(eng, cases["logs"][name])
    assert len(df) == meta["n"]
    vals = np.column_stack(
        [df[c].to_numpy(float) for c in FLOAT_COLUMNS]
        + [df.source.map(SOURCES.index).to_numpy(float), df.static.to_numpy(float)]
    )
    rows = ref[f"{name}/rows"]
    np.testing.assert_allclose(vals[rows[:, 0].astype(int)], rows[:, 1:], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.nan_to_num(vals).sum(axis=0), ref[f"{name}/sums"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(eng.x, ref[f"{name}/x"], rtol=1e-9, atol=1e-9)
    # run_batch counts the IMU gaps before the blocks (one event, at the gap's time): in time order
    events = sorted(json.loads(json.dumps(df.attrs["events"])), key=lambda e: e["t"])
    _close(sorted(meta["events"], key=lambda e: e["t"]), events, "events")
    _close(meta["summary"], json.loads(json.dumps(df.attrs["summary"])), "summary")
