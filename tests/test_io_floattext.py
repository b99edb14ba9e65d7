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


def test_write_fixed_csv_equals_pandas_to_csv(tmp_path) -> None:
    import pandas as pd

    from iotnav.io.export import write_fixed_csv

    rng = np.random.default_rng(5)
    n = 3000
    df = pd.DataFrame(
        {
            "t": np.arange(n) * 0.01 + 0.000258,
            "a": rng.standard_normal(n) * 9.8,
            "b": rng.standard_normal(n) * 1e-7,
            "c": np.where(rng.random(n) < 0.1, np.nan, rng.standard_normal(n) * 1e6),
            "i": rng.integers(-5, 5, n),
            "f": rng.random(n) < 0.5,
        }
    )
    # infinities, signed zeros, ties at 6 and 9 decimals, a value beyond 2**52
    df.loc[0:7, "a"] = [np.inf, -np.inf, -0.0, 0.0, 0.0000005, 2.5e-6, 0.1234565, 2.0**60]
    for d in (6, 9):
        want, got = tmp_path / f"pandas{d}.csv", tmp_path / f"fast{d}.csv"
        df.to_csv(want, index=False, float_format=f"%.{d}f", na_rep="", lineterminator="\n")
        write_fixed_csv(df, got, d)
        assert got.read_bytes() == want.read_bytes()
