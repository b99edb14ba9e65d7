"""The tracker's odometer from an engine's speed: sparse curves, engine-held halts, parked noise."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from iotnav.geo import LocalFrame
from iotnav.tracker import TrackerConfig, describe, gated_increments, velocity_increments

FRAME = LocalFrame(45.0, 7.0, 0.0)


def _track(
    t: np.ndarray,
    n: np.ndarray,
    e: np.ndarray,
    sigma: float,
    vn: np.ndarray,
    ve: np.ndarray,
    static: np.ndarray | None = None,
) -> pd.DataFrame:
    lat, lon, _ = FRAME.from_ned(np.column_stack([n, e, np.zeros_like(t)]))
    return pd.DataFrame(
        {
            "t": t,
            "lat": lat,
            "lon": lon,
            "vn": vn,
            "ve": ve,
            "static": np.zeros(t.size, bool) if static is None else static,
            "std_north": sigma,
            "std_east": sigma,
        }
    )


def _trip_distance(track: pd.DataFrame, config: TrackerConfig | None = None) -> float:
    trips = describe(track, config=config).trips
    assert (trips["kind"] == "trip").sum() == 1
    return float(trips.loc[trips["kind"] == "trip", "distance_m"].iloc[0])


def test_sparse_circle_distance_is_the_arc() -> None:
    """A circle of 150 m radius at 10 m/s, one fix every 20 s (200 m of arc, 76 degrees):
    10 min parked, 30 min on the circle (18 km), 10 min parked. The chords between fixes are
    7.3 % short of the arc (sin(0.67) / 0.67); the speed's trapezoid is the arc."""
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 3001.0, 20.0)
    r, v = 150.0, 10.0
    s = np.clip(t - 600.0, 0.0, 1800.0) * v  # arc length travelled, m
    ang = s / r
    moving = (t >= 600.0) & (t < 2400.0)
    n = r * np.sin(ang) + rng.normal(0, 2.0, t.size)
    e = r * (1.0 - np.cos(ang)) + rng.normal(0, 2.0, t.size)
    vn = np.where(moving, v * np.cos(ang), 0.0) + rng.normal(0, 0.1, t.size)
    ve = np.where(moving, v * np.sin(ang), 0.0) + rng.normal(0, 0.1, t.size)
    track = _track(t, n, e, 2.0, vn, ve, static=~moving)
    truth = 1800.0 * v
    d = _trip_distance(track)
    assert d == pytest.approx(truth, rel=0.02)
    # the chords (the odometer before) are 7 % short
    chords = _trip_distance(track, TrackerConfig(odometer="chords"))
    assert chords < 0.95 * truth


def _stop_and_go(rng: np.random.Generator) -> tuple[pd.DataFrame, float]:
    """An engine's track of stop-and-go traffic in a canyon: runs of 1-5 m/s for 20-90 s and
    halts of 10-60 s (turns of up to 90 degrees between runs) between 10 min parked at each end;
    the engine flags the halts static and holds its position there. Its positions are smooth
    (1 m of slowly varying error), its reported sigma the fix's (7.6 m per axis, absolute: the
    errors are time-correlated), its speed within 0.1 m/s."""
    v: list[float] = [0.0] * 600
    psi: list[float] = [0.0] * 600
    held: list[bool] = [True] * 600
    heading = 0.3
    while len(v) < 2400:
        run = int(rng.uniform(20, 90))
        v += [float(rng.uniform(1.0, 5.0))] * run
        psi += [heading] * run
        held += [False] * run
        halt = int(rng.uniform(10, 60))
        v += [0.0] * halt
        psi += [heading] * halt
        held += [True] * halt
        heading += rng.uniform(-np.pi / 2, np.pi / 2)
    v += [0.0] * 600
    psi += [psi[-1]] * 600
    held += [True] * 600
    speed, hd, st = np.asarray(v), np.asarray(psi), np.asarray(held)
    t = np.arange(speed.size, dtype=float)
    tn, te = (
        np.cumsum(speed * np.cos(hd)) - speed * np.cos(hd),
        np.cumsum(speed * np.sin(hd)) - speed * np.sin(hd),
    )
    err_n = np.convolve(rng.normal(0, 1.0, t.size), np.ones(30) / np.sqrt(30), "same")
    err_e = np.convolve(rng.normal(0, 1.0, t.size), np.ones(30) / np.sqrt(30), "same")
    n, e = tn + err_n, te + err_e
    # held rows keep the position of the last row the engine did not hold
    last = 0
    for i in range(t.size):
        if st[i] and i > 0:
            n[i], e[i] = n[last], e[last]
        else:
            last = i
    vn = np.where(st, 0.0, speed * np.cos(hd) + rng.normal(0, 0.1, t.size))
    ve = np.where(st, 0.0, speed * np.sin(hd) + rng.normal(0, 0.1, t.size))
    return _track(t, n, e, 7.6, vn, ve, static=st), float(speed.sum())


def test_engine_held_stop_and_go_distance() -> None:
    """The distance of an engine's stop-and-go track is within 2 % of the truth; the chords,
    gated at 4 sqrt(2) x the absolute sigma (43 m) and debiased with it, are far short."""
    track, truth = _stop_and_go(np.random.default_rng(5))
    assert _trip_distance(track) == pytest.approx(truth, rel=0.02)
    assert _trip_distance(track, TrackerConfig(odometer="chords")) < 0.96 * truth


def test_parked_noisy_speed_adds_nothing() -> None:
    """Two hours parked, the engine not flagging static and its speed reading 0.7 m/s of noise
    (a canyon's Doppler): no trip, the odometer stays 0."""
    rng = np.random.default_rng(9)
    t = np.arange(0.0, 7200.0)
    n = np.convolve(rng.normal(0, 3.0, t.size), np.ones(60) / np.sqrt(60), "same")
    e = np.convolve(rng.normal(0, 3.0, t.size), np.ones(60) / np.sqrt(60), "same")
    track = _track(t, n, e, 8.0, rng.normal(0, 0.55, t.size), rng.normal(0, 0.55, t.size))
    assert float(np.median(np.hypot(track["vn"], track["ve"]))) > 0.6
    res = describe(track)
    assert res.trips["kind"].tolist() == ["stop"]
    assert res.odometer_m == 0.0


def test_velocity_increments_hand_worked() -> None:
    """Rows 0-1 static (0 m), 1 -> 2 leaves the static state with a 10 m jump (sigmas 2 m:
    debiased sqrt(100 - 16) = 9.17 m, more than the trapezoid 0.5 x 4 m/s x 1 s), 2 -> 3 at
    4 then 6 m/s over 2 s (10 m), 3 -> 4 enters the static state (0.5 x 6 x 1 = 3 m); the rows'
    own speeds (no median)."""
    t = np.array([0.0, 1.0, 2.0, 4.0, 5.0])
    north = np.array([0.0, 0.0, 10.0, 20.0, 21.0])
    east = np.zeros(5)
    speed = np.array([0.3, 0.2, 4.0, 6.0, 0.1])
    static = np.array([True, True, False, False, True])
    inc = velocity_increments(t, north, east, np.full(5, 2.0), speed, static, 0.0)
    assert inc == pytest.approx([0.0, 0.0, np.sqrt(84.0), 10.0, 3.0])
    # a small jump leaving the static state counts the trapezoid (the chord is within the noise)
    north[2] = 3.0
    inc = velocity_increments(t, north, east, np.full(5, 2.0), speed, static, 0.0)
    assert inc[2] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="finite speed"):
        velocity_increments(t, north, east, np.full(5, 2.0), np.array([0.0, np.nan, 1, 1, 1]), static)
    with pytest.raises(ValueError, match="different lengths"):
        velocity_increments(t, north, east, np.full(4, 2.0), speed, static)


def test_track_without_velocity_counts_chords() -> None:
    """No ``vn``/``ve``: the odometer is the gated chords (as before); a bad name is refused."""
    t = np.arange(0.0, 1500.0)
    e = np.clip(t - 300.0, 0.0, 900.0) * 2.0
    lat, lon, _ = FRAME.from_ned(np.column_stack([np.zeros_like(t), e, np.zeros_like(t)]))
    track = pd.DataFrame({"t": t, "lat": lat, "lon": lon, "static": False, "std_north": 1.0, "std_east": 1.0})
    res = describe(track)
    assert res.odometer_measure == "chords" and res.summary()["odometer_measure"] == "chords"
    inc = gated_increments(np.zeros_like(t), e, np.full(t.size, 1.0), TrackerConfig().odometer_k_sigma)
    trip = res.trips[res.trips["kind"] == "trip"].iloc[0]
    i0, i1 = int(np.searchsorted(t, trip["t_start"])), int(np.searchsorted(t, trip["t_end"]))
    assert trip["distance_m"] == pytest.approx(inc[i0 + 1 : i1 + 1].sum())
    with pytest.raises(ValueError, match="odometer"):
        TrackerConfig(odometer="gps")


def test_speed_spike_of_a_smoothed_jump_is_not_distance() -> None:
    """A smoother spreads an accepted 40 m jump over two rejected fixes (27 m/s for 2 s in
    traffic at 2 m/s, 25 m/s from the 5 s median): the spikes take the median, the trapezoid
    is the 2 m/s; a real change of speed (2 -> 8 m/s, 6 m/s in a second) is kept."""
    t = np.arange(0.0, 20.0)
    speed = np.full(t.size, 2.0)
    speed[9:11] = 27.0
    zeros = np.zeros(t.size)
    inc = velocity_increments(t, zeros, 2.0 * t, np.full(t.size, 3.0), speed, np.zeros(t.size, bool))
    assert inc.sum() == pytest.approx(2.0 * 19.0)
    raw = velocity_increments(t, zeros, 2.0 * t, np.full(t.size, 3.0), speed, np.zeros(t.size, bool), 0.0)
    assert raw.sum() == pytest.approx(2.0 * 19.0 + 25.0 * 2.0)
    speed[9:] = 8.0
    inc = velocity_increments(t, zeros, 2.0 * t, np.full(t.size, 3.0), speed, np.zeros(t.size, bool))
    assert inc.sum() == pytest.approx(2.0 * 8.0 + 5.0 + 8.0 * 10.0)


def test_trip_starts_at_the_held_row_before_a_departure_jump() -> None:
    """Parked 10 min (static, held), then 10 min at 3 m/s east; the engine holds for the first
    5 s of motion and re-initialises 15 m on (sigmas 2 m). The trip includes that jump: its
    distance is the 1800 m driven, not 1785 m."""
    t = np.arange(0.0, 1500.0)
    e_true = np.clip(t - 600.0, 0.0, 600.0) * 3.0
    static = (t < 605.0) | (t >= 1200.0)
    e = np.where(t < 605.0, 0.0, e_true)
    ve = np.where(static, 0.0, 3.0)
    track = _track(t, np.zeros_like(t), e, 2.0, np.zeros_like(t), ve, static=static)
    res = describe(track)
    assert res.odometer_measure == "velocity"
    trip = res.trips[res.trips["kind"] == "trip"].iloc[0]
    assert trip["t_start"] == 604.0
    assert trip["distance_m"] == pytest.approx(1800.0, rel=0.005)
    assert (res.trips.loc[res.trips["kind"] == "stop", "distance_m"] == 0.0).all()
