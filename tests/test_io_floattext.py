"""The compiled ten-digit float text of track.csv is byte for byte pyarrow's cast."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from iotnav.io._floattext import MIN_VALUES, ten_digit_text
from iotnav.io.export import round_significant


def _pyarrow(r: np.ndarray) -> pa.Array:
    return pc.cast(pa.array(r, from_pandas=True), pa.string())


def test_ten_digit_text_equals_pyarrow_cast() -> None:
    rng = np.random.default_rng(21)
    n = MIN_VALUES
    v = rng.standard_normal(n) * 10.0 ** rng.integers(-12, 9, n)
    edges = [
        0.0,
        -0.0,
        np.nan,
        1e-6,
        -1e-6,
        9.999999999e-7,
        1e-13,
        1.5e-10,
        999999999.0,
        0.5,
        100.0,
        45.06281221,
    ]
    v[: len(edges)] = edges
    v[len(edges) : 2000] = np.round(v[len(edges) : 2000], 3)  # short decimals: trailing zeros dropped
    r = round_significant(v, 10)
    r = r[~(np.abs(r) < 1e-13) | (r == 0)]
    r = np.concatenate([r, np.round(rng.uniform(-180, 180, n), 6)])
    text = ten_digit_text(r)
    assert text is not None
    assert text.equals(_pyarrow(r))
    assert text.null_count == 1


def test_out_of_range_or_short_columns_go_to_pyarrow() -> None:
    r = round_significant(np.linspace(1.0, 2.0, MIN_VALUES), 10)
    assert ten_digit_text(r[: MIN_VALUES - 1]) is None
    for bad in (1e9, 1e-14, np.inf, 0.1 + 0.2):  # 0.30000000000000004 is not a 10-digit decimal
        r2 = r.copy()
        r2[5] = bad
        assert ten_digit_text(r2) is None
