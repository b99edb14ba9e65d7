"""Simulated anchor tracks and RSSI reports for non-GNSS nodes.

Scenario of Zorkany et al. (2022, section 4, Fig. 3): mobile anchor nodes (vehicles with
GNSS + IMU) periodically broadcast beacons; unknown nodes around them log what they hear. For
every beacon ``j`` of anchor ``a`` at true position ``a_j`` and every node at ``p``:

.. math::

    \\mathrm{RSSI}_{j} = P_0 - 10 n \\log_{10}(d_j / d_0) + X_j - L_j,
    \\qquad d_j = \\lVert p - a_j \\rVert                                          \\quad (S1)

* shadowing ``X_j ~ N(0, sigma^2)``; with a decorrelation distance ``D > 0`` it follows the
  Gudmundson (1991) first-order model along the link,
  ``X_j = rho X_{j-1} + sqrt(1 - rho^2) N(0, sigma^2)``, ``rho = exp(-Delta s / D)`` with
  ``Delta s`` the anchor's (plus node's) displacement since the previous beacon; ``D = 0`` means
  independent draws (moving anchors whose beacons are further apart than ``D``);
* NLOS: with probability ``nlos_probability`` an extra attenuation ``L_j`` (dB) is applied;
* a report exists only when ``RSSI_j`` is above the radio's sensitivity and the packet is not
  lost (probability ``packet_loss``);
* beacon interval ``max(beacon_interval_s, time_on_air / duty_cycle)`` (LoRa duty cycle, 1 % in
  the EU868 g1 sub-band), with a random phase per anchor;
* ``snr_db = RSSI - N_floor``, ``N_floor = -174 + 10 log10(BW) + NF`` dBm;
* the anchors' *reported* tracks are the true tracks plus a Gaussian error with the tracks'
  ``std_north``/``std_east`` (white, or first-order Gauss-Markov with ``anchor_error_tau_s``),
  as a fusion engine's output would be.

Trajectory generators (:func:`static_anchors`, :func:`line_track`, :func:`loop_track`) return
anchor track tables in the local NED frame with columns ``t, anchor_id, north, east, down,
std_north, std_east``; :func:`tracks_to_geodetic` / :func:`tracks_from_geodetic` convert to
and from ``t, anchor_id, lat, lon, height, std_north, std_east`` so any table written by
``iotnav run`` can drive the simulation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.geo import LocalFrame
from iotnav.nodes.ranging import PathLossModel, lora_time_on_air_s, rssi_from_distance

FloatArray = npt.NDArray[np.float64]

TRACK_COLUMNS = ["t", "anchor_id", "north", "east", "down", "std_north", "std_east"]
RSSI_COLUMNS = ["t", "anchor_id", "node_id", "rssi_dbm", "snr_db"]


@dataclass(frozen=True)
class RadioSimConfig:
    """Link-layer settings of the RSSI simulation.

    Attributes
    ----------
    beacon_interval_s : float
        Requested interval between an anchor's beacons, s.
    duty_cycle : float
        Transmit duty-cycle limit (0.01 = 1 %); lengthens the interval for slow LoRa SFs.
    payload_bytes : int
        Beacon payload length, bytes (for LoRa time on air).
    packet_loss : float
        Probability that a decodable beacon is lost anyway (collisions, interference).
    decorrelation_m : float
        Shadowing decorrelation distance ``D``, m; 0 draws independent shadowing per beacon.
    nlos_probability : float
        Probability that a report is NLOS.
    nlos_loss_db : float
        Extra attenuation of NLOS reports, dB.
    noise_figure_db : float
        Receiver noise figure, dB (for ``snr_db``).
    bandwidth_hz : float
        Channel bandwidth, Hz (for ``snr_db`` and LoRa time on air).
    rssi_resolution_db : float
        Quantisation step of the reported RSSI, dB (1 dB on LoRa and BLE chips); 0 keeps floats.
    anchor_error_tau_s : float
        Correlation time of the anchors' reported position error, s; 0 for white.
    """

    beacon_interval_s: float = 10.0
    duty_cycle: float = 0.01
    payload_bytes: int = 12
    packet_loss: float = 0.1
    decorrelation_m: float = 0.0
    nlos_probability: float = 0.0
    nlos_loss_db: float = 20.0
    noise_figure_db: float = 6.0
    bandwidth_hz: float = 125e3
    rssi_resolution_db: float = 1.0
    anchor_error_tau_s: float = 0.0

    def to_dict(self) -> dict[str, float | int]:
        """Plain dictionary (for ``summary.json``)."""
        return asdict(self)


def beacon_interval_s(model: PathLossModel, cfg: RadioSimConfig) -> float:
    """Effective beacon interval: the requested one, lengthened by the duty-cycle limit, s."""
    if model.spreading_factor > 0 and cfg.duty_cycle > 0:
        toa = lora_time_on_air_s(model.spreading_factor, cfg.payload_bytes, cfg.bandwidth_hz)
        return max(cfg.beacon_interval_s, toa / cfg.duty_cycle)
    return cfg.beacon_interval_s


def _table(t: FloatArray, anchor_id: str, ne: FloatArray, down: float, std_m: float) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "t": t,
            "anchor_id": anchor_id,
            "north": ne[:, 0],
            "east": ne[:, 1],
            "down": float(down),
            "std_north": float(std_m),
            "std_east": float(std_m),
        }
    )


def static_anchors(
    positions_ne: npt.ArrayLike,
    t: npt.ArrayLike,
    ids: Sequence[str] | None = None,
    down_m: float = -1.5,
    std_m: float = 3.0,
) -> pd.DataFrame:
    """Anchors standing still.

    Parameters
    ----------
    positions_ne : array_like
        ``(K, 2)`` north/east positions, m.
    t : array_like
        Epochs of the track, s.
    ids : sequence of str, optional
        Anchor ids (``A01``, ``A02``, ... when omitted).
    down_m : float
        Down coordinate of the anchors (antenna height above the node plane is ``-down_m``), m.
    std_m : float
        Reported horizontal standard deviation of each axis, m.

    Returns
    -------
    pandas.DataFrame
        Track table with :data:`TRACK_COLUMNS`.
    """
    P = np.asarray(positions_ne, dtype=float).reshape(-1, 2)
    tt = np.asarray(t, dtype=float)
    names = list(ids) if ids is not None else [f"A{k + 1:02d}" for k in range(P.shape[0])]
    parts = [
        _table(tt, names[k], np.repeat(P[k : k + 1], tt.size, axis=0), down_m, std_m)
        for k in range(P.shape[0])
    ]
    return pd.concat(parts, ignore_index=True)


def line_track(
    start_ne: npt.ArrayLike,
    end_ne: npt.ArrayLike,
    speed_mps: float,
    t: npt.ArrayLike,
    anchor_id: str = "A01",
    down_m: float = -1.5,
    std_m: float = 3.0,
) -> pd.DataFrame:
    """A vehicle driving back and forth along a straight segment at constant speed.

    Parameters
    ----------
    start_ne, end_ne : array_like
        Segment ends ``[north, east]``, m.
    speed_mps : float
        Speed, m/s.
    t : array_like
        Epochs, s (the vehicle is at ``start_ne`` at ``t[0]``).
    anchor_id : str
        Anchor id.
    down_m, std_m : float
        Down coordinate and reported horizontal standard deviation, m.

    Returns
    -------
    pandas.DataFrame
        Track table with :data:`TRACK_COLUMNS`.
    """
    a = np.asarray(start_ne, dtype=float)
    b = np.asarray(end_ne, dtype=float)
    tt = np.asarray(t, dtype=float)
    length = float(np.linalg.norm(b - a))
    s = speed_mps * (tt - tt[0])
    phase = np.mod(s, 2.0 * length) / length  # 0..2
    frac = np.where(phase <= 1.0, phase, 2.0 - phase)
    ne = a[None, :] + frac[:, None] * (b - a)[None, :]
    return _table(tt, anchor_id, ne, down_m, std_m)


def loop_track(
    center_ne: npt.ArrayLike,
    radius_m: float,
    speed_mps: float,
    t: npt.ArrayLike,
    anchor_id: str = "A01",
    phase_rad: float = 0.0,
    down_m: float = -1.5,
    std_m: float = 3.0,
) -> pd.DataFrame:
    """A vehicle driving a circle at constant speed (counter-clockwise seen from above).

    Parameters
    ----------
    center_ne : array_like
        Circle centre ``[north, east]``, m.
    radius_m, speed_mps : float
        Radius (m) and speed (m/s).
    t : array_like
        Epochs, s.
    anchor_id : str
        Anchor id.
    phase_rad : float
        Bearing of the start point from the centre, rad (from north towards east).
    down_m, std_m : float
        Down coordinate and reported horizontal standard deviation, m.

    Returns
    -------
    pandas.DataFrame
        Track table with :data:`TRACK_COLUMNS`.
    """
    c = np.asarray(center_ne, dtype=float)
    tt = np.asarray(t, dtype=float)
    ang = phase_rad - speed_mps * (tt - tt[0]) / radius_m
    ne = np.column_stack([c[0] + radius_m * np.cos(ang), c[1] + radius_m * np.sin(ang)])
    return _table(tt, anchor_id, ne, down_m, std_m)


def tracks_to_geodetic(tracks: pd.DataFrame, frame: LocalFrame) -> pd.DataFrame:
    """NED track table to ``t, anchor_id, lat, lon, height, std_north, std_east`` (degrees, m)."""
    lat, lon, h = frame.from_ned(tracks[["north", "east", "down"]].to_numpy(float))
    return pd.DataFrame(
        {
            "t": tracks["t"].to_numpy(float),
            "anchor_id": tracks["anchor_id"].astype(str).to_numpy(),
            "lat": lat,
            "lon": lon,
            "height": h,
            "std_north": tracks["std_north"].to_numpy(float),
            "std_east": tracks["std_east"].to_numpy(float),
        }
    )


def tracks_from_geodetic(tracks: pd.DataFrame, frame: LocalFrame) -> pd.DataFrame:
    """A geodetic anchor track table (``t, anchor_id, lat, lon[, height, std_north, std_east]``)
    to the NED form of :data:`TRACK_COLUMNS`; missing ``height`` is 0 m, missing standard
    deviations are 0 m (the anchor position taken as exact)."""
    h = tracks["height"].to_numpy(float) if "height" in tracks else np.zeros(len(tracks))
    ned = frame.to_ned(tracks["lat"].to_numpy(float), tracks["lon"].to_numpy(float), h)
    out = pd.DataFrame(
        {
            "t": tracks["t"].to_numpy(float),
            "anchor_id": tracks["anchor_id"].astype(str).to_numpy(),
            "north": ned[:, 0],
            "east": ned[:, 1],
            "down": ned[:, 2],
        }
    )
    for c in ("std_north", "std_east"):
        out[c] = tracks[c].to_numpy(float) if c in tracks else 0.0
    return out


def random_nodes(n_nodes: int, area_m: float, rng: np.random.Generator, down_m: float = 0.0) -> pd.DataFrame:
    """``n_nodes`` static nodes uniform over a square of side ``area_m`` centred on the origin.

    Returns
    -------
    pandas.DataFrame
        ``node_id, north, east, down`` (m).
    """
    ne = rng.uniform(-area_m / 2, area_m / 2, size=(n_nodes, 2))
    return pd.DataFrame(
        {
            "node_id": [f"N{k + 1:03d}" for k in range(n_nodes)],
            "north": ne[:, 0],
            "east": ne[:, 1],
            "down": down_m,
        }
    )


def _interp_track(track: pd.DataFrame, t: FloatArray) -> FloatArray:
    tt = track["t"].to_numpy(float)
    return np.column_stack([np.interp(t, tt, track[c].to_numpy(float)) for c in ("north", "east", "down")])


def _node_positions(nodes: pd.DataFrame, node_id: str, t: FloatArray) -> FloatArray:
    sel = nodes.loc[nodes["node_id"] == node_id]
    if "t" in sel and len(sel) > 1:
        sel = sel.sort_values("t")
        ts = sel["t"].to_numpy(float)
        return np.column_stack([np.interp(t, ts, sel[c].to_numpy(float)) for c in ("north", "east", "down")])
    row = sel.iloc[0]
    return np.tile([float(row["north"]), float(row["east"]), float(row.get("down", 0.0))], (t.size, 1))


def anchor_errors(tracks: pd.DataFrame, cfg: RadioSimConfig, rng: np.random.Generator) -> pd.DataFrame:
    """The anchors' reported tracks: truth plus Gaussian error with the tables' standard deviations.

    The error is white per epoch, or first-order Gauss-Markov with correlation time
    ``cfg.anchor_error_tau_s`` (stationary standard deviation unchanged).
    """
    out = []
    for _, tr in tracks.groupby("anchor_id", sort=True):
        tr = tr.sort_values("t").copy()
        std = tr[["std_north", "std_east"]].to_numpy(float)
        w = rng.standard_normal(std.shape)
        if cfg.anchor_error_tau_s > 0:
            dt = np.diff(tr["t"].to_numpy(float), prepend=tr["t"].iloc[0])
            e = np.empty_like(w)
            e[0] = w[0]
            for k in range(1, len(w)):
                rho = math.exp(-dt[k] / cfg.anchor_error_tau_s)
                e[k] = rho * e[k - 1] + math.sqrt(1.0 - rho * rho) * w[k]
            w = e
        tr["north"] = tr["north"].to_numpy(float) + std[:, 0] * w[:, 0]
        tr["east"] = tr["east"].to_numpy(float) + std[:, 1] * w[:, 1]
        out.append(tr)
    return pd.concat(out, ignore_index=True)[TRACK_COLUMNS]


def simulate_rssi(
    tracks: pd.DataFrame,
    nodes: pd.DataFrame,
    model: PathLossModel,
    cfg: RadioSimConfig | None = None,
    rng: np.random.Generator | None = None,
) -> pd.DataFrame:
    """RSSI reports heard by the nodes from the anchors' beacons (equation S1).

    Parameters
    ----------
    tracks : pandas.DataFrame
        True anchor tracks, NED form (:data:`TRACK_COLUMNS`; std columns unused here).
    nodes : pandas.DataFrame
        ``node_id, north, east[, down]`` (m) for static nodes; with a ``t`` column (s), several
        rows per node describe a moving node (linear interpolation).
    model : PathLossModel
        Radio (``shadowing_db`` is the simulated sigma).
    cfg : RadioSimConfig, optional
        Link-layer settings.
    rng : numpy.random.Generator, optional
        Random source (seeded by the caller for reproducibility).

    Returns
    -------
    pandas.DataFrame
        Reports ``t, anchor_id, node_id, rssi_dbm, snr_db`` sorted by time, plus
        ``true_distance_m`` and ``nlos`` for evaluation (not part of the file format).
    """
    c = cfg if cfg is not None else RadioSimConfig()
    g = rng if rng is not None else np.random.default_rng(0)
    interval = beacon_interval_s(model, c)
    noise_floor = -174.0 + 10.0 * math.log10(c.bandwidth_hz) + c.noise_figure_db
    node_ids = list(dict.fromkeys(nodes["node_id"].astype(str)))
    rows: list[pd.DataFrame] = []
    for aid, tr in tracks.groupby("anchor_id", sort=True):
        tr = tr.sort_values("t")
        t0, t1 = float(tr["t"].iloc[0]), float(tr["t"].iloc[-1])
        tb = np.arange(t0 + g.uniform(0.0, interval), t1, interval)
        if tb.size == 0:
            continue
        a = _interp_track(tr, tb)
        for nid in node_ids:
            p = _node_positions(nodes, nid, tb)
            d = np.maximum(np.linalg.norm(p - a, axis=1), 0.1)
            x = g.standard_normal(tb.size) * model.shadowing_db
            if c.decorrelation_m > 0:
                ds = np.linalg.norm(np.diff(a[:, :2], axis=0), axis=1) + np.linalg.norm(
                    np.diff(p[:, :2], axis=0), axis=1
                )
                rho = np.exp(-ds / c.decorrelation_m)
                for k in range(1, tb.size):
                    x[k] = rho[k - 1] * x[k - 1] + math.sqrt(1.0 - rho[k - 1] ** 2) * x[k]
            nlos = g.random(tb.size) < c.nlos_probability
            r = rssi_from_distance(d, model) + x - np.where(nlos, c.nlos_loss_db, 0.0)
            if c.rssi_resolution_db > 0:
                r = np.round(r / c.rssi_resolution_db) * c.rssi_resolution_db
            heard = (r >= model.sensitivity_dbm) & (g.random(tb.size) >= c.packet_loss)
            rows.append(
                pd.DataFrame(
                    {
                        "t": tb[heard],
                        "anchor_id": str(aid),
                        "node_id": nid,
                        "rssi_dbm": r[heard],
                        "snr_db": np.round((r[heard] - noise_floor) * 4.0) / 4.0,
                        "true_distance_m": d[heard],
                        "nlos": nlos[heard],
                    }
                )
            )
    if not rows:
        return pd.DataFrame(columns=[*RSSI_COLUMNS, "true_distance_m", "nlos"])
    out = pd.concat(rows, ignore_index=True)
    return out.sort_values(["t", "anchor_id", "node_id"], kind="stable").reset_index(drop=True)


@dataclass(frozen=True)
class Scenario:
    """A complete simulated fleet: true and reported anchor tracks, nodes, RSSI reports.

    Attributes
    ----------
    frame : LocalFrame
        Origin of the local NED frame.
    tracks_true, tracks_reported : pandas.DataFrame
        Anchor tracks (NED form); the reported ones carry the fusion-engine error.
    nodes : pandas.DataFrame
        True node positions ``node_id, north, east, down`` (m).
    rssi : pandas.DataFrame
        Reports (see :func:`simulate_rssi`).
    """

    frame: LocalFrame
    tracks_true: pd.DataFrame
    tracks_reported: pd.DataFrame
    nodes: pd.DataFrame
    rssi: pd.DataFrame


def fleet_scenario(
    n_anchors: int,
    n_nodes: int,
    model: PathLossModel,
    cfg: RadioSimConfig | None = None,
    seed: int = 0,
    area_m: float = 1000.0,
    duration_s: float = 600.0,
    speed_mps: float = 10.0,
    anchor_std_m: float = 3.0,
    frame: LocalFrame | None = None,
    nodes: pd.DataFrame | None = None,
) -> Scenario:
    """Vehicles driving loops over a square area, static nodes uniform over it.

    Anchor ``k`` drives a circle of radius ``area_m / 4`` around a centre uniform over the
    central half of the area, with a random start bearing, sampled at 1 Hz.

    Parameters
    ----------
    n_anchors, n_nodes : int
        Fleet sizes.
    model : PathLossModel
        Radio.
    cfg : RadioSimConfig, optional
        Link-layer settings.
    seed : int
        Seed of everything random.
    area_m : float
        Side of the square area, m.
    duration_s : float
        Simulated time, s.
    speed_mps : float
        Anchor speed, m/s.
    anchor_std_m : float
        The anchors' horizontal position error per axis, m (reported and simulated).
    frame : LocalFrame, optional
        Geodetic origin (a default one when omitted).
    nodes : pandas.DataFrame, optional
        Node positions to use instead of random ones.

    Returns
    -------
    Scenario
        The simulated fleet.
    """
    c = cfg if cfg is not None else RadioSimConfig()
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s + 1e-9, 1.0)
    parts = []
    for k in range(n_anchors):
        centre = rng.uniform(-area_m / 4, area_m / 4, size=2)
        phase = rng.uniform(0.0, 2.0 * math.pi)
        parts.append(
            loop_track(centre, area_m / 4, speed_mps, t, f"A{k + 1:02d}", phase_rad=phase, std_m=anchor_std_m)
        )
    tracks = pd.concat(parts, ignore_index=True)
    nd = nodes if nodes is not None else random_nodes(n_nodes, area_m, rng)
    rssi = simulate_rssi(tracks, nd, model, c, rng)
    reported = anchor_errors(tracks, c, rng)
    fr = frame if frame is not None else LocalFrame(47.3769, 8.5417, 408.0)
    return Scenario(fr, tracks, reported, nd, rssi)
