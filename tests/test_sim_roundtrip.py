"""Simulated files read back by the iotnav readers equal the simulated measurements."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pynmeagps import VALCKSUM, NMEAReader
from pyubx2 import UBXReader

from iotnav import sim
from iotnav.io import imu_csv as imu_mod
from iotnav.io import nmea as nmea_mod


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[sim.SimResult, Path]:
    out = tmp_path_factory.mktemp("carmag")
    r = sim.build("car-magnetometer", seed=9, overrides={"gnss.write_ubx": True})
    sim.write(r, out)
    return r, out


def test_nmea_checksums_valid_by_reference_parser(written: tuple[sim.SimResult, Path]) -> None:
    _, out = written
    lines = (out / "gnss.nmea").read_text().splitlines()
    assert len(lines) == 4 * 256
    for ln in lines:
        stamp, _, sentence = ln.partition(",")
        assert len(stamp.split(".")[1]) == 3
        msg = NMEAReader.parse(sentence, validate=VALCKSUM)
        assert msg.msgID in ("GGA", "RMC", "GSA", "VTG")


def test_nmea_round_trip(written: tuple[sim.SimResult, Path]) -> None:
    r, out = written
    part = nmea_mod.read_nmea(out / "gnss.nmea")
    g, s = part.gnss, r.gnss
    assert len(g) == len(s)
    np.testing.assert_allclose(g["t"], s["t"], atol=5e-4)
    np.testing.assert_allclose(g["utc"], s["utc"], atol=5e-3)
    assert (g["valid"].to_numpy() == s["valid"].to_numpy()).all()
    assert (g["quality"].to_numpy() == s["quality"].to_numpy()).all()
    v = s["valid"].to_numpy()
    assert (g["num_sv"].to_numpy()[v] == s["num_sv"].to_numpy()[v]).all()
    # ddmm.mmmmmmm: 1e-7 minute = 1.7e-9 deg
    np.testing.assert_allclose(g["lat_deg"][v], s["lat_deg"][v], atol=1e-9, rtol=0)
    np.testing.assert_allclose(g["lon_deg"][v], s["lon_deg"][v], atol=1e-9, rtol=0)
    np.testing.assert_allclose(g["height_m"][v], s["height_m"][v], atol=1.1e-3, rtol=0)
    np.testing.assert_allclose(g["speed_mps"][v], s["speed_mps"][v], atol=0.0006 * 1852 / 3600, rtol=0)
    for c in ("hdop", "pdop", "vdop"):
        np.testing.assert_allclose(g[c][v], s[c][v], atol=0.0051, rtol=0)
    cv = s["course_valid"].to_numpy()
    assert (g["course_valid"].to_numpy() == cv).all()
    np.testing.assert_allclose(g["course_rad"][cv], s["course_rad"][cv], atol=np.radians(0.0051), rtol=0)


def test_imu_csv_round_trip(written: tuple[sim.SimResult, Path]) -> None:
    r, out = written
    part = imu_mod.read_imu_csv(out / "imu.csv")
    assert len(part.imu) == len(r.imu) and len(part.mag) == len(r.mag) > 1000
    for c in ("t", "acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z"):
        np.testing.assert_allclose(part.imu[c], r.imu[c], atol=5.1e-7, rtol=0)
    for c in ("t", "mag_x_ut", "mag_y_ut", "mag_z_ut"):
        np.testing.assert_allclose(part.mag[c], r.mag[c], atol=5.1e-7, rtol=0)


def test_ubx_nav_pvt_round_trip(written: tuple[sim.SimResult, Path]) -> None:
    r, out = written
    msgs = []
    with open(out / "gnss.ubx", "rb") as fh:
        for _raw, parsed in UBXReader(fh, protfilter=2):
            msgs.append(parsed)
    assert len(msgs) == len(r.gnss)
    s = r.gnss
    v = s["valid"].to_numpy()
    lat = np.array([m.lat for m in msgs])
    h = np.array([m.height for m in msgs]) / 1000.0
    vn = np.array([m.velN for m in msgs]) / 1000.0
    np.testing.assert_allclose(lat[v], s["lat_deg"][v], atol=5.1e-8, rtol=0)
    np.testing.assert_allclose(h[v], s["height_m"][v], atol=5.1e-4, rtol=0)
    np.testing.assert_allclose(vn[v], s["vn"][v], atol=5.1e-4, rtol=0)
    assert [m.fixType for m in msgs] == [3 if x else 0 for x in v]


def test_fixes_round_trip(tmp_path: Path) -> None:
    from iotnav.io import fixes as fixes_mod

    r = sim.build("pedestrian-fixes", seed=3, overrides={"motion.laps": 1, "gnss.enabled": False})
    sim.write(r, tmp_path)
    got = fixes_mod.read_fixes(tmp_path / "fixes.csv").table
    assert r.fixes is not None and len(got) == len(r.fixes)
    for a, b in (
        ("t_valid", "t_valid"),
        ("lat_deg", "lat"),
        ("lon_deg", "lon"),
        ("roll", "roll"),
        ("yaw", "yaw"),
    ):
        np.testing.assert_allclose(got[a], r.fixes[b], atol=5.1e-10, rtol=0)
