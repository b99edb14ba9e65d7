"""RTKLIB ``.pos`` reader: real drive/walk solutions and small hand-written variants."""

from __future__ import annotations

import calendar
import math
from pathlib import Path

import numpy as np
import pymap3d
import pytest

from iotnav.io.errors import IngestError
from iotnav.io.report import SkipReason
from iotnav.io.rtklib import read_rtklib_pos

RTK = "rtklibexplorer_gnss_imu"


def _data_lines(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("%")]


@pytest.mark.parametrize(
    ("rel", "n_fix", "n_float"),
    [("drive_0708/gnss_1934_sf.pos", 2189, 8), ("walk_0827/gnss_1730_sf.pos", 349, 187)],
)
def test_real_pos_counts(datasets: Path, rel: str, n_fix: int, n_float: int) -> None:
    path = datasets / RTK / rel
    part = read_rtklib_pos(path)
    n_lines = len(_data_lines(path))
    g = part.gnss
    assert len(g) == n_lines  # independent count of solution lines
    assert part.clock == "utc"
    # Q counts from the dataset README
    assert part.report.records["Q1"] == n_fix
    assert part.report.records["Q2"] == n_float
    assert int((g["quality"] == 4).sum()) == n_fix  # Q1 fix -> GGA 4
    assert int((g["quality"] == 5).sum()) == n_float  # Q2 float -> GGA 5
    assert g["valid"].all()
    assert (np.diff(g["t"].to_numpy()) > 0).all()
    r = part.report
    assert (
        r.n_records + sum(r.ignored.values()) + r.n_skipped == r.units == len(path.read_text().splitlines())
    )
    assert any("GPST" in n for n in r.notes)


def test_drive_gpst_to_utc_and_fields(datasets: Path) -> None:
    path = datasets / RTK / "drive_0708/gnss_1934_sf.pos"
    part = read_rtklib_pos(path)
    g = part.gnss
    # first line: 2025/07/08 19:34:18.499 GPST -> 19:34:00.499 UTC (18 leap seconds)
    expected = calendar.timegm((2025, 7, 8, 19, 34, 0, 0, 0, 0)) + 0.499
    assert g["t"].iloc[0] == pytest.approx(expected, abs=1e-6)
    assert g["utc"].iloc[0] == g["t"].iloc[0]
    # Fields of one moving epoch, parsed here by hand from the text
    lines = _data_lines(path)
    k = 1000
    f = lines[k].split()
    lat, lon, h = float(f[2]), float(f[3]), float(f[4])
    sdn, sde, sdu = float(f[7]), float(f[8]), float(f[9])
    vn, ve, vu = float(f[15]), float(f[16]), float(f[17])
    row = g.iloc[k]
    assert row["lat_deg"] == lat and row["lon_deg"] == lon and row["height_m"] == h
    assert row["num_sv"] == int(float(f[6]))
    assert row["vn"] == vn and row["ve"] == ve
    assert row["vd"] == -vu  # ENU up -> NED down
    assert row["h_acc_m"] == pytest.approx(math.hypot(sdn, sde))
    assert row["v_acc_m"] == sdu
    assert row["speed_mps"] == pytest.approx(math.hypot(vn, ve))
    assert row["course_rad"] == pytest.approx(math.atan2(ve, vn) % (2 * math.pi))
    assert bool(row["course_valid"]) == (math.hypot(vn, ve) > 0.5)
    # The static start: course not valid
    assert not g["course_valid"].iloc[0]


HEADER_LLH = (
    "% program   : RTKPOST ver.demo5\n"
    "%  GPST          latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  "
    "sdne(m)  sdeu(m)  sdun(m) age(s)  ratio    vn(m/s)    ve(m/s)    vu(m/s)\n"
)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_week_tow_utc_header_and_bad_lines(tmp_path: Path) -> None:
    # GPS week 2374, tow 243258.5 s: 1980-01-06 + 2374 weeks + 243258.5 s, on GPST
    body = (
        "2374 243258.500   40.0 -105.0 1600.0 1 20 0.01 0.02 0.03 0 0 0 0 0 1.0 2.0 -0.5\n"
        "2374 243258.750   40.0 -105.0 1600.0 2 20 0.01 0.02 0.03 0 0 0 0 0 1.0 2.0 -0.5\n"
        "2374 243258.750   40.0 -105.0 1600.0 2 20 0.01 0.02 0.03 0 0 0 0 0 1.0 2.0 -0.5\n"
        "2374 243258.600   40.0 -105.0 1600.0 2 20 0.01 0.02 0.03 0 0 0 0 0 1.0 2.0 -0.5\n"
        "2374 243259.000   40.0 -105.0 1600.0 5 20\n"
        "2374 243259.250   4x.0 -105.0 1600.0 5 20 0.01 0.02 0.03 0 0 0 0 0 1.0 2.0 -0.5\n"
        "2374 243259.500   nan -105.0 1600.0 5 20 0.01 0.02 0.03 0 0 0 0 0 1.0 2.0 -0.5\n"
        "\n"
        "2374 243259.750   40.0 -105.0 1600.0 6 20 0.01 0.02 0.03 0 0 0 0 0 0.1 0.1 0.0\n"
    )
    p = _write(tmp_path, "tow.pos", HEADER_LLH + body)
    part = read_rtklib_pos(p)
    g = part.gnss
    assert len(g) == 3
    t0 = 315964800 + 2374 * 604800 + 243258.5 - 18
    assert g["t"].iloc[0] == pytest.approx(t0, abs=1e-6)
    assert list(g["quality"]) == [4, 5, 1]  # Q1, Q2, Q6 (PPP -> 1)
    sk = part.report.skipped
    assert sk[SkipReason.DUPLICATE] == 1
    assert sk[SkipReason.NON_MONOTONIC] == 1
    assert sk[SkipReason.TRUNCATED] == 1
    assert sk[SkipReason.MALFORMED] == 1
    assert sk[SkipReason.NAN_FIELD] == 1
    r = part.report
    assert r.n_records + sum(r.ignored.values()) + r.n_skipped == len((HEADER_LLH + body).splitlines())
    # UTC header: no leap-second shift
    p2 = _write(tmp_path, "utc.pos", HEADER_LLH.replace("GPST", "UTC ") + body.splitlines()[0] + "\n")
    g2 = read_rtklib_pos(p2).gnss
    assert g2["t"].iloc[0] == pytest.approx(t0 + 18, abs=1e-6)


def test_ecef_and_dms(tmp_path: Path) -> None:
    lat, lon, h = 40.0966268, -105.1474483, 1601.474
    x, y, z = pymap3d.geodetic2ecef(lat, lon, h)
    # velocity 3 m/s north, 4 m/s east, 1 m/s up, expressed in ECEF
    vx, vy, vz = pymap3d.enu2uvw(4.0, 3.0, 1.0, lat, lon)
    text = (
        "%  GPST                  x-ecef(m)      y-ecef(m)      z-ecef(m)   Q  ns   sdx(m)   sdy(m)   "
        "sdz(m)  sdxy(m)  sdyz(m)  sdzx(m) age(s)  ratio    vx(m/s)    vy(m/s)    vz(m/s)\n"
        f"2025/07/08 19:34:18.499 {x:.4f} {y:.4f} {z:.4f} 1 21 0.02 0.02 0.02 0 0 0 0 0 {vx:.5f} {vy:.5f} {vz:.5f}\n"
    )
    g = read_rtklib_pos(_write(tmp_path, "xyz.pos", text)).gnss
    assert g["lat_deg"].iloc[0] == pytest.approx(lat, abs=1e-8)
    assert g["lon_deg"].iloc[0] == pytest.approx(lon, abs=1e-8)
    assert g["height_m"].iloc[0] == pytest.approx(h, abs=1e-3)
    assert (g["vn"].iloc[0], g["ve"].iloc[0], g["vd"].iloc[0]) == pytest.approx((3.0, 4.0, -1.0), abs=1e-4)
    # isotropic 2 cm: horizontal DRMS sqrt(2)*0.02, vertical 0.02 whatever the rotation
    assert g["h_acc_m"].iloc[0] == pytest.approx(math.sqrt(2) * 0.02)
    assert g["v_acc_m"].iloc[0] == pytest.approx(0.02)
    dms = (
        "%  GPST                  latitude(d'\")   longitude(d'\")  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  "
        "sdne(m)  sdeu(m)  sdun(m) age(s)  ratio\n"
        "2025/07/08 19:34:18.499  40 05 47.8565 -105 08 50.8139 1601.4740 1 21 0.01 0.01 0.01 0 0 0 0 0\n"
    )
    g2 = read_rtklib_pos(_write(tmp_path, "dms.pos", dms)).gnss
    assert g2["lat_deg"].iloc[0] == pytest.approx(40 + 5 / 60 + 47.8565 / 3600)
    assert g2["lon_deg"].iloc[0] == pytest.approx(-(105 + 8 / 60 + 50.8139 / 3600))
    assert np.isnan(g2["vn"].iloc[0]) and not g2["course_valid"].iloc[0]


def test_not_a_pos_file(tmp_path: Path) -> None:
    p = _write(tmp_path, "x.pos", "hello world\nthis is not RTKLIB\n")
    with pytest.raises(IngestError, match=r"x\.pos.*RTKLIB"):
        read_rtklib_pos(p)
    with pytest.raises(IngestError, match="cannot open"):
        read_rtklib_pos(tmp_path / "missing.pos")
