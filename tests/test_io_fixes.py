"""Absolute-fix reader (iotnav.io.fixes): schema, defaults, bad rows counted by reason."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from iotnav.io.errors import IngestError
from iotnav.io.fixes import (
    ARRIVAL_BEFORE_VALID,
    DEFAULT_SIGMA_ATT_RAD,
    DEFAULT_SIGMA_POS_M,
    FIX_COLUMNS,
    UNKNOWN_COLUMN,
    read_fixes,
)
from iotnav.io.report import SkipReason


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_csv_geodetic_with_attitude_and_defaults(tmp_path: Path) -> None:
    p = _write(
        tmp_path,
        "fixes.csv",
        "# image-based fixes\n"
        "t_valid,t_arrival,lat,lon,height,roll,pitch,yaw,sigma_pos_m\n"
        "10.0,10.8,45.06,7.66,250.0,0.01,-0.02,1.5,0.25\n"
        "11.0,11.9,45.0601,7.6601,250.1,,,,\n"
        "\n"
        "12.0,12.7,45.0602,7.6602,250.2,0.0,0.0,6.0,\n",
    )
    fx = read_fixes(p)
    t = fx.table
    assert list(t.columns) == list(FIX_COLUMNS)
    assert [str(t[c].dtype) for c in t.columns] == list(FIX_COLUMNS.values())
    assert fx.position_frame == "geodetic"
    assert len(t) == 3
    assert t["lat_deg"].tolist() == [45.06, 45.0601, 45.0602]
    assert t["has_attitude"].tolist() == [True, False, True]
    assert t["sigma_pos_m"].tolist() == [0.25, DEFAULT_SIGMA_POS_M, DEFAULT_SIGMA_POS_M]
    assert DEFAULT_SIGMA_POS_M == 0.30  # the ~30 cm of Dabove et al.
    assert t["sigma_att_rad"].iloc[0] == DEFAULT_SIGMA_ATT_RAD
    assert math.isnan(t["sigma_att_rad"].iloc[1]) and math.isnan(t["yaw"].iloc[1])
    assert t["north_m"].isna().all()
    assert fx.report.records["fix"] == 3
    assert fx.report.ignored["comment"] == 1 and fx.report.ignored["header"] == 1
    assert fx.report.n_skipped == 0


def test_csv_ned_and_degree_aliases(tmp_path: Path) -> None:
    p = _write(
        tmp_path,
        "ned.csv",
        "t_valid,t_arrival,north,east,down,roll_deg,pitch_deg,yaw_deg,sigma_att_deg\n1,1.5,3.0,-4.0,0.5,0,10,270,2\n",
    )
    fx = read_fixes(p)
    row = fx.table.iloc[0]
    assert fx.position_frame == "ned"
    assert (row["north_m"], row["east_m"], row["down_m"]) == (3.0, -4.0, 0.5)
    assert row["pitch"] == pytest.approx(math.radians(10.0))
    assert row["yaw"] == pytest.approx(math.radians(270.0))
    assert row["sigma_att_rad"] == pytest.approx(math.radians(2.0))
    assert math.isnan(row["lat_deg"])


def test_csv_bad_rows_counted_by_reason(tmp_path: Path) -> None:
    header = "t_valid,t_arrival,lat,lon,height,roll,pitch,yaw,sigma_pos_m,sigma_att_rad\n"
    rows = [
        "1,1.5,45,7,100,0,0,0,0.3,0.01",  # good
        "2,1.5,45,7,100,0,0,0,0.3,0.01",  # arrival before validity
        "3,3.5,nan,7,100,0,0,0,0.3,0.01",  # NaN required field
        "4,4.5,45,7,100,0,2.0,0,0.3,0.01",  # pitch > pi/2
        "5,5.5,45,7,100,0,0,7.0,0.3,0.01",  # yaw > 2 pi
        "6,6.5,95,7,100,0,0,0,0.3,0.01",  # latitude out of range
        "7,7.5,45,7,100,0,0,0,-1,0.01",  # negative sigma
        "8,8.5,45,7,100,0,0",  # truncated line
        "9,9.5,45,7,100,0,0,0,0.3,0.01,99",  # extra field
        "10,10.5,45,seven,100,0,0,0,0.3,0.01",  # not a number
        "11,11.5,45,7,100,0.1,,0.2,0.3,0.01",  # partial attitude
        "12,12.5,45,7,100,0,0,0,0.3,0.01",  # good
    ]
    fx = read_fixes(_write(tmp_path, "bad.csv", header + "\n".join(rows) + "\n"))
    assert fx.table["t_valid"].tolist() == [1.0, 12.0]
    sk = fx.report.skipped
    assert sk[ARRIVAL_BEFORE_VALID] == 1
    assert sk[str(SkipReason.NAN_FIELD)] == 2
    assert sk[str(SkipReason.OUT_OF_RANGE)] == 4
    assert sk[str(SkipReason.TRUNCATED)] == 1
    assert sk[str(SkipReason.MALFORMED)] == 2
    assert fx.report.n_records + fx.report.n_skipped == len(rows)
    # examples keep the line numbers (header is line 1)
    assert fx.report.examples[ARRIVAL_BEFORE_VALID][0][0] == 3


def test_jsonl_rows_unknown_keys_and_truncation(tmp_path: Path) -> None:
    lines = [
        json.dumps({"t_valid": 1.0, "t_arrival": 1.2, "lat": 45.0, "lon": 7.0, "height": 200.0}),
        json.dumps({"t_valid": 2.0, "t_arrival": 2.2, "lat": 45.0, "lon": 7.0, "height": 200.0, "speed": 3}),
        '{"t_valid": 3.0, "t_arrival": 3.2, "lat": 45.0, "lon"',
        json.dumps({"t_valid": 4.0, "t_arrival": 4.2, "north": 1.0, "east": 2.0, "down": 0.0}),
        json.dumps({"t_valid": 5.0, "t_arrival": 5.2, "lat": 45.0, "lon": 7.0, "height": None}),
        json.dumps([1, 2, 3]),
        json.dumps(
            {
                "t_valid": 6.0,
                "t_arrival": 6.1,
                "lat": 45.0,
                "lon": 7.0,
                "height": 1.0,
                "roll": 0,
                "pitch": 0,
                "yaw": 3,
            }
        ),
    ]
    fx = read_fixes(_write(tmp_path, "fixes.jsonl", "\n".join(lines) + "\n"))
    assert fx.report.format == "fixes-jsonl"
    assert fx.table["t_valid"].tolist() == [1.0, 6.0]
    assert fx.table["has_attitude"].tolist() == [False, True]
    sk = fx.report.skipped
    assert sk[UNKNOWN_COLUMN] == 1
    assert sk[str(SkipReason.TRUNCATED)] == 1
    assert sk[str(SkipReason.MALFORMED)] == 2  # NED row in a geodetic file, a JSON array
    assert sk[str(SkipReason.NAN_FIELD)] == 1


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "empty"),
        ("$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\n", "not an absolute-fix header"),
        ("t_valid,t_arrival,lat,lon,height,sigma_pos\n1,2,3,4,5,6\n", "unknown column"),
        ("t_valid,t_arrival,lat,lon,height,north,east,down\n", "either"),
        ("t_valid,t_arrival,lat,lon\n", "missing column"),
        ("t_valid,t_arrival,lat,lon,height,roll\n", "roll, pitch, yaw"),
        ('{"a": 1}\n{"b": 2}\n', "no JSON object"),
        ("# only a comment\n", "no header"),
    ],
)
def test_not_a_fixes_file_raises(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(IngestError, match=match):
        read_fixes(_write(tmp_path, "x.csv", text))


def test_binary_and_missing_file(tmp_path: Path) -> None:
    p = tmp_path / "x.bin"
    p.write_bytes(b"\xb5\x62\x01\x07\x00\x00" * 10)
    with pytest.raises(IngestError, match=r"binary|UTF-8"):
        read_fixes(p)
    with pytest.raises(FileNotFoundError):
        read_fixes(tmp_path / "nope.csv")


def test_round_trip_of_generated_fixes(tmp_path: Path) -> None:
    """Seeded fixes written as CSV come back exactly (13 significant digits written)."""
    rng = np.random.default_rng(7)
    n = 50
    tv = np.cumsum(rng.uniform(0.5, 1.5, n))
    ta = tv + rng.uniform(0.1, 2.0, n)
    north, east, down = rng.normal(0, 50, (3, n))
    yaw = rng.uniform(-math.pi, math.pi, n)
    lines = ["t_valid,t_arrival,north,east,down,roll,pitch,yaw"]
    lines += [
        f"{a:.13g},{b:.13g},{c:.13g},{d:.13g},{e:.13g},0,0,{f:.13g}"
        for a, b, c, d, e, f in zip(tv, ta, north, east, down, yaw, strict=True)
    ]
    fx = read_fixes(_write(tmp_path, "gen.csv", "\n".join(lines) + "\n"))
    np.testing.assert_allclose(fx.table["t_arrival"], ta, rtol=1e-12)
    np.testing.assert_allclose(fx.table["yaw"], yaw, rtol=1e-12)
    assert fx.table["has_attitude"].all()
