"""Output resolution of GNSS fixes (NMEA decimals) found from the fixes, and its use by eskf."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from conftest import datasets_dir
from iotnav.engines.anchor import gnss_position_noise_source
from iotnav.engines.base import GnssSample
from iotnav.engines.gnss_resolution import (
    AccuracyScaling,
    FigureDecimals,
    PositionResolution,
    accuracy_relative_steps,
    decimal_places,
    relative_step,
)
from iotnav.io import read_file
from iotnav.io.errors import IngestError

GPSD_LOGS = datasets_dir() / "gpsd_nmea_corpus" / "logs"

#: Latitude / longitude fields of GGA, RMC and GLL sentences (independent of the reader).
_POS_SENTENCE = re.compile(rb"\$[A-Z]{2}(?:GGA|RMC|GLL),[^*\r\n]*")
_LAT_LON = re.compile(rb",\d{4}\.(\d+),[NS],\d{5}\.(\d+),[EW]")


def test_decimal_places() -> None:
    assert decimal_places(3235.1758, 6, 1e-8) == 4
    assert decimal_places(3235.17580, 6, 1e-8) == 4  # trailing zeros do not count
    assert decimal_places(12.0, 6, 1e-8) == 0
    assert decimal_places(1.0 / 3.0, 6, 1e-8) is None
    assert decimal_places(math.nan, 6, 1e-8) is None


def test_sigma_is_the_uniform_rounding_of_one_step() -> None:
    """4 decimals of a minute: a step of 1852e-4 m of latitude, cos(lat) of it in longitude;
    one decimal of a metre in height; sigma = step / sqrt(12)."""
    r = PositionResolution()
    r.update(60.0 + 12.3456 / 60.0, 10.0 + 1.2345 / 60.0, 123.4)
    n, e, d = r.sigma_ned_m(60.0)
    assert n == pytest.approx(0.1852 / math.sqrt(12.0))
    assert e == pytest.approx(0.5 * 0.1852 / math.sqrt(12.0))
    assert d == pytest.approx(0.1 / math.sqrt(12.0))
    # a later fix needing a finer grid refines it; a continuous one ends the detection
    r.update(60.0 + 12.34567 / 60.0, 10.0 + 1.2345 / 60.0, 123.45)
    assert (r.minute_decimals, r.altitude_decimals) == (5, 2)
    r.update(math.nan, 10.0, 123.4)  # no position: not taken (would read as continuous)
    assert not r.continuous and r.n_fixes == 2
    r.update(60.0 + math.pi / 60.0, 10.0, 123.4)
    assert r.continuous and r.sigma_ned_m(60.0)[:2] == (0.0, 0.0)


def test_coarse_grid_needs_distinct_fixes() -> None:
    """A fix repeated on whole minutes (a hand-made log, a receiver holding its last position)
    reads as 0 decimals, a 1852 m grid: not trusted until three different positions show it
    (before, 50 such fixes gave a 535 m white sigma and the filter ignored the GNSS)."""
    r = PositionResolution()
    for _ in range(50):
        r.update(48.0, 11.0, 500.0)
    assert r.minute_decimals is None and r.altitude_decimals is None
    assert r.sigma_ned_m(48.0) == (0.0, 0.0, 0.0)
    r.update(48.0 + 1.0 / 60.0, 11.0, 501.0)
    r.update(48.0 + 2.0 / 60.0, 11.0, 502.0)
    assert (r.minute_decimals, r.altitude_decimals) == (0, 0)
    # 3 decimals and finer are taken at once
    r3 = PositionResolution()
    r3.update(48.0 + 7.038 / 60.0, 11.0 + 31.0 / 60.0, 545.4)
    assert (r3.minute_decimals, r3.altitude_decimals) == (3, 1)


def _text_decimals(data: bytes) -> int | None:
    """Most decimals (trailing zeros stripped) of any latitude or longitude minute field."""
    best: int | None = None
    for m in _POS_SENTENCE.finditer(data):
        for mm in _LAT_LON.finditer(m.group(0)):
            d = max(len(mm.group(1).rstrip(b"0")), len(mm.group(2).rstrip(b"0")))
            best = d if best is None else max(best, d)
    return best


def test_gpsd_corpus_decimals_match_the_sentences() -> None:
    """Every NMEA-only log of the gpsd corpus (real receivers: 2 to 8 decimals) read through
    ``read_file``: the decimals found from the fixes are those of the sentences' text (with
    trailing zeros stripped: ``saab-r4`` pads 4 decimals to 6); above 6, continuous."""
    assert GPSD_LOGS.is_dir(), f"gpsd corpus not found at {GPSD_LOGS}"  # real data: fail, not skip
    checked: dict[int | str, int] = {}
    for path in sorted(GPSD_LOGS.glob("*.log")):
        data = path.read_bytes()
        if b"\xb5\x62" in data:  # UBX frames carry their own (1e-7 degree) positions
            continue
        try:
            gnss = read_file(path).gnss
        except IngestError:
            continue
        if gnss is None or not np.isfinite(gnss.lat_deg.to_numpy()).any():
            continue
        expected = _text_decimals(data)
        assert expected is not None, path.name
        r = PositionResolution()
        for la, lo, h in zip(gnss.lat_deg, gnss.lon_deg, gnss.height_m, strict=True):
            if math.isfinite(la) and math.isfinite(lo):
                r.update(la, lo, h)
        if expected > 6:
            assert r.continuous, (path.name, expected, r.to_dict())
            checked["continuous"] = checked.get("continuous", 0) + 1
        else:
            assert r.minute_decimals == expected, (path.name, expected, r.to_dict())
            checked[expected] = checked.get(expected, 0) + 1
    # the corpus spans the formats that matter: 3, 4, 5 and 6 decimals and finer
    assert {3, 4, 5, 6, "continuous"} <= set(checked), checked
    assert sum(checked.values()) >= 80, checked


@pytest.mark.parametrize("decimals", [3, 4])
def test_eskf_takes_the_rounding_of_nmea_fixes_as_white_noise(decimals: int) -> None:
    """car-tunnel seed 0, 150 s, fixes rounded as a receiver writing ``decimals`` decimals of a
    minute (and 0.1 m of height) would: the engine finds the rounding and its GNSS position
    NIS per dof stays near 1 with no fix rejected (observed 0.92 for both); without it the
    rounding (5.3 cm per axis at 4 decimals, 0.53 m at 3) meets a filter whose 1 s prediction
    of the smoothed receiver error is good to a few cm: NIS/dof 3.8 and 34, 16 and 92 fixes
    of 150 rejected."""
    from iotnav import sim
    from iotnav.engines.base import run_batch
    from iotnav.engines.eskf import EskfConfig, EskfEngine
    from iotnav.io.log import Log

    res = sim.build("car-tunnel", seed=0, overrides={"duration_s": 150.0, "gnss.outages_s": ()})
    g = res.gnss.copy()
    g["lat_deg"] = np.round(g.lat_deg * 60.0, decimals) / 60.0
    g["lon_deg"] = np.round(g.lon_deg * 60.0, decimals) / 60.0
    g["height_m"] = np.round(g.height_m, 1)
    out = {}
    for detect in (True, False):
        eng = EskfEngine(EskfConfig(gnss_white_from_resolution=detect))
        run_batch(eng, Log(gnss=g, imu=res.imu))
        nis = [r[1] / r[2] for r in eng.nis_log["gnss_position"]][10:]
        rejected = sum(1 for e in eng.events if e["type"] == "fix_rejected")
        out[detect] = (float(np.mean(nis)), rejected, eng.summary()["gnss_resolution"])
    nis_on, rej_on, found = out[True]
    assert found["minute_decimals"] == decimals and found["altitude_decimals"] == 1
    assert 0.6 < nis_on < 1.4 and rej_on == 0, out
    nis_off, rej_off, _ = out[False]
    assert nis_off > 2.5 and rej_off >= 10, out


def test_relative_step_of_reported_figures() -> None:
    """The rounding step of a figure from its decimals, over the figure; DOPs with HDOP and
    PDOP give ``VDOP``'s as ``(p a + h b) / (p^2 - h^2)``; hAcc / vAcc take precedence."""
    assert relative_step(1.1) == pytest.approx(0.1 / 1.1)
    assert relative_step(1.07) == pytest.approx(0.01 / 1.07)
    assert relative_step(1.0734) == 0.0  # 4 decimals: continuous for the filters
    assert relative_step(math.nan) == 0.0 and relative_step(-1.0) == 0.0 and relative_step(0.0) == 0.0
    rh, re_, rv = accuracy_relative_steps(math.nan, math.nan, 1.1, 2.1, ("hdop", "pdop"))
    assert rh == re_ == pytest.approx(0.1 / 1.1)
    assert rv == pytest.approx((2.1 * 0.1 + 1.1 * 0.1) / (2.1**2 - 1.21))
    # a PDOP of 2.0 alone reads as a whole number; the stream's decimals correct it
    fd = FigureDecimals()
    fd.relative_steps(math.nan, math.nan, 1.1, 2.1, ("hdop", "pdop"))
    rv2 = fd.relative_steps(math.nan, math.nan, 1.1, 2.0, ("hdop", "pdop"))[2]
    assert rv2 == pytest.approx((2.0 * 0.1 + 1.1 * 0.1) / (4.0 - 1.21))
    assert accuracy_relative_steps(math.nan, math.nan, 1.1, 2.0, ("hdop", "pdop"))[2] > 0.5
    fd.relative_steps(
        math.nan, math.nan, 1.0734, 2.0, ("hdop", "pdop")
    )  # a value on no grid: continuous for good
    assert fd.relative_steps(math.nan, math.nan, 1.1, 2.0, ("hdop", "pdop"))[0] == 0.0
    assert accuracy_relative_steps(1.62, 2.5, 1.1, 2.0, ("h_acc", "v_acc")) == pytest.approx(
        (0.01 / 1.62, 0.01 / 1.62, 0.1 / 2.5)
    )
    # eskf's vertical without vAcc is 1.6 hAcc: its source says so
    assert accuracy_relative_steps(1.62, math.nan, 1.1, 2.0, ("h_acc", "h_acc"))[2] == pytest.approx(
        0.01 / 1.62
    )


def test_accuracy_scaling_follows_jumps_and_low_passes_rounding() -> None:
    """Continuous figures are followed at every fix; a change within 4 rounding steps moves the
    level by ``dt / tau`` of the log difference; beyond, at once; another kind of figures
    makes a new level without a ratio."""
    sc = AccuracyScaling(tau_s=5.0)
    assert sc.ratio(0.0, [1.0, 1.0, 2.0], "dop", [0.0] * 3) is None  # the first: the level
    k = sc.ratio(1.0, [1.05, 1.0, 2.0], "dop", [0.0] * 3)
    assert k == pytest.approx((1.05, 1.0, 1.0))
    k = sc.ratio(2.0, [1.06, 1.03, 2.0], "dop", [0.01] * 3)  # within 4 % of 1.05 / 1.0: low-passed
    a = 1.0 - math.exp(-1.0 / 5.0)  # 1 s of the 5 s first-order low-pass
    assert k == pytest.approx(((1.06 / 1.05) ** a, 1.03**a, 1.0))
    assert sc.level[0] == pytest.approx(1.05 * (1.06 / 1.05) ** a)
    lev = list(sc.level)
    k = sc.ratio(3.0, [3.0, lev[1], 2.0], "dop", [0.01] * 3)  # a jump (re-acquisition)
    assert k is not None and k[0] == pytest.approx(3.0 / lev[0]) and sc.level[0] == pytest.approx(3.0)
    assert sc.ratio(4.0, [1.0, 1.0, 1.0], "hacc", [0.0] * 3) is None
    assert sc.level == [1.0, 1.0, 1.0]
    assert sc.ratio(5.0, [1.0, 1.0, 1.0], "hacc", [0.0] * 3) is None  # nothing changed
    # time going backwards: no low-pass step, the clock stays; a NaN time changes nothing
    assert sc.ratio(4.0, [1.01, 1.0, 1.0], "hacc", [0.01] * 3) is None and sc.t == 5.0
    assert sc.ratio(math.nan, [3.0, 3.0, 3.0], "hacc", [0.0] * 3) is None and sc.level == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match="time constant"):
        AccuracyScaling(tau_s=0.0)


def _source(h_acc: float, v_acc: float, hdop: float, pdop: float) -> tuple[str, str]:
    """The figures behind anchor's / qekf's GNSS noise (``gnss_position_noise_source``)."""
    s = GnssSample(0.0, 0.0, 0.0, 0.0, pdop=pdop, hdop=hdop, h_acc_m=h_acc, v_acc_m=v_acc)
    return gnss_position_noise_source(s, 2.0, 2.0)[1]


def test_accuracy_source_names_the_figures_behind_the_sigma() -> None:
    """The order of :func:`iotnav.gnss_accuracy.position_sigmas`: hAcc, HDOP, PDOP, default
    horizontally; vAcc, 1.5 hAcc, VDOP from PDOP and HDOP, 1.5 HDOP vertically. Each sigma
    takes the rounding of the figure it comes from (a review finding: a vertical sigma from the
    DOPs once took hAcc's 1 mm step, which made every DOP step an exact scaling)."""
    nan = math.nan
    assert _source(1.6, 2.5, 1.1, 2.1) == ("h_acc", "v_acc")
    assert _source(1.6, nan, 1.1, 2.1) == ("h_acc", "h_acc")
    assert _source(nan, nan, 1.1, 2.1) == ("hdop", "pdop")
    assert _source(nan, nan, 1.1, nan) == ("hdop", "hdop")
    assert _source(nan, nan, nan, 2.0) == ("pdop", "pdop")
    assert _source(nan, nan, 1.0, 0.9) == ("hdop", "hdop")
    assert _source(nan, nan, nan, nan) == ("default", "default")
    rh, _, rv = accuracy_relative_steps(1.623, nan, 1.1, 2.1, _source(1.623, nan, 1.1, 2.1))
    assert rh == rv == pytest.approx(0.001 / 1.623)
    rh, _, rv = accuracy_relative_steps(nan, nan, 1.1, 2.1, _source(nan, nan, 1.1, 2.1))
    assert rh == pytest.approx(0.1 / 1.1)
    assert rv == pytest.approx((2.1 * 0.1 + 1.1 * 0.1) / (2.1**2 - 1.21))
    assert accuracy_relative_steps(nan, nan, nan, nan, _source(nan, nan, nan, nan)) == (0.0, 0.0, 0.0)
