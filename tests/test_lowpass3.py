"""The 3-level low-pass (Forno et al. 2020, block 4): the compiled form equals the numpy one, and
the ``fixes`` engine's parked track is that compiled form's output."""

from __future__ import annotations

import numpy as np
import pandas as pd

from iotnav.engines.base import TangentPlane, run_batch
from iotnav.engines.fixes import FixesConfig, FixesEngine
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, coerce
from iotnav.techniques.lowpass3 import (
    LP_HAVE,
    LP_N,
    LP_SIZE,
    Lowpass3,
    Lowpass3Config,
    lowpass3_n_fixes,
    lowpass3_push,
    lowpass3_reset,
)


def test_compiled_equals_numpy_form() -> None:
    rng = np.random.default_rng(8)
    cfg = Lowpass3Config(n1=3, n2=2, n3=4)
    ref = Lowpass3(cfg)
    s = np.zeros(LP_SIZE)
    b = (np.zeros((3, 3)), np.zeros((2, 3)), np.zeros((4, 3)))
    changes = 0
    for k in range(120):
        if k == 70:  # a static period ends and another starts
            ref.reset()
            lowpass3_reset(s)
        r = rng.normal(0, 3, 3)
        want = ref.push(r)
        got = lowpass3_push(s, *b, 3, 2, 4, *r)
        assert got == (want is not None)
        if want is not None:
            changes += 1
            assert np.array_equal(s[LP_N : LP_N + 3], want)
        assert lowpass3_n_fixes(s, 3, 2, 4) == ref.n_fixes
        assert (s[LP_HAVE] != 0.0) == (ref.output() is not None)
    assert changes > 20 and ref.level == 3


def test_fixes_engine_parked_track_is_the_lowpass_output() -> None:
    # ignition off: static from the second fix; every later fix goes into the low-pass, and a
    # row's position is its output (the first fix's filter state until a level is full)
    rng = np.random.default_rng(3)
    f = TangentPlane(45.0, 7.0, 100.0)
    n_fix = 200
    ne = rng.normal(0, 2.0, (n_fix, 2))
    t = np.arange(n_fix, dtype=float)
    g = coerce(
        pd.DataFrame(
            {
                "t": t,
                "utc": 1.7e9 + t,
                "lat_deg": f.lat0_deg + ne[:, 0] / f.k_n,
                "lon_deg": f.lon0_deg + ne[:, 1] / f.k_e,
                "height_m": 100.0,
                "h_acc_m": 4.0,
                "v_acc_m": 6.0,
                "pdop": 1.5,
                "num_sv": 10,
                "valid": True,
                "ignition": False,
            }
        ),
        GNSS_COLUMNS,
    )
    cfg = FixesConfig()
    out = run_batch(FixesEngine(cfg), Log(gnss=g))
    assert out["static"].iloc[1:].all()
    lat0 = out["lat"].to_numpy()
    on = (lat0 - f.lat0_deg) * f.k_n
    oe = (out["lon"].to_numpy() - f.lon0_deg) * f.k_e
    ref = Lowpass3(cfg.lowpass3)
    last = None
    seen = 0
    for k in range(1, n_fix):
        o = ref.push(np.array([ne[k, 0], ne[k, 1], 0.0]))
        last = o if o is not None else last
        if last is not None:
            seen += 1
            assert abs(on[k] - last[0]) < 1e-6 and abs(oe[k] - last[1]) < 1e-6
    assert seen > 150
