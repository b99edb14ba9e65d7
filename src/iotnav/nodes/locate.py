"""Locate every node of an RSSI log from the anchors' tracks (tables in, tables out).

The fleet-level step of the anchor-node mechanism (Zorkany et al. 2022, Fig. 3): each RSSI
report ``t, anchor_id, node_id, rssi_dbm`` is paired with the reporting anchor's position at
``t`` (linear interpolation of its fused track, covariance from ``std_north``/``std_east``),
then each node is solved on its own with :func:`iotnav.nodes.multilateration.solve_position`
(static nodes) or :func:`iotnav.nodes.tracking.track_node` (slowly moving nodes).

Nothing is dropped silently: every report that cannot be used is counted by reason in
:attr:`LocateResult.skipped`, and every node seen in the log gets a row, with status
``no_data`` when none of its reports was usable. Pure: no files are read or written here.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.nodes.multilateration import Method, SolverConfig, Status, solve_position
from iotnav.nodes.ranging import PathLossModel
from iotnav.nodes.tracking import POS, TrackerConfig, track_node

FloatArray = npt.NDArray[np.float64]

#: Skip reasons counted by :func:`pair_reports`.
UNKNOWN_ANCHOR = "unknown anchor id"
NO_ANCHOR_POSITION = "no anchor position at report time"

POSITION_COLUMNS = [
    "node_id",
    "t_first",
    "t_last",
    "north",
    "east",
    "std_north",
    "std_east",
    "cov_ne",
    "drms_m",
    "n_reports",
    "n_used",
    "n_anchors",
    "status",
    "mirror_north",
    "mirror_east",
]


@dataclass(frozen=True)
class LocateConfig:
    """Settings of :func:`locate_nodes`.

    Attributes
    ----------
    method : str
        ``wls``, ``huber`` (default: robust to NLOS at 5 % efficiency cost), ``ransac`` or
        ``track`` (EKF for moving nodes).
    max_anchor_gap_s : float
        A report is paired with an anchor position only if the anchor's track has epochs
        within this many seconds on both sides (or at the same time), s.
    solver : SolverConfig
        Batch solver tunables.
    tracker : TrackerConfig
        Tracking-filter tunables.
    """

    method: str = "huber"
    max_anchor_gap_s: float = 30.0
    solver: SolverConfig = field(default_factory=SolverConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    def to_dict(self) -> dict[str, Any]:
        """Plain dictionary (for ``summary.json``)."""
        return asdict(self)


@dataclass(frozen=True)
class LocateResult:
    """Output of :func:`locate_nodes`.

    Attributes
    ----------
    positions : pandas.DataFrame
        One row per node (:data:`POSITION_COLUMNS`; north/east in m in the local frame).
    track : pandas.DataFrame or None
        With ``method="track"``: ``t, node_id, north, east, v_north, v_east, std_north,
        std_east, cov_ne, accepted`` after every report.
    skipped : collections.Counter
        Unusable reports by reason.
    status_counts : collections.Counter
        Nodes by status.
    """

    positions: pd.DataFrame
    track: pd.DataFrame | None
    skipped: Counter[str]
    status_counts: Counter[str]


def pair_reports(
    tracks: pd.DataFrame, rssi: pd.DataFrame, max_gap_s: float, skipped: Counter[str]
) -> pd.DataFrame:
    """Attach the reporting anchor's interpolated position to every report.

    Parameters
    ----------
    tracks : pandas.DataFrame
        Anchor tracks, NED form ``t, anchor_id, north, east, down, std_north, std_east``.
    rssi : pandas.DataFrame
        Reports ``t, anchor_id, node_id, rssi_dbm``.
    max_gap_s : float
        Largest allowed distance in time to the bracketing track epochs, s.
    skipped : collections.Counter
        Incremented with :data:`UNKNOWN_ANCHOR` and :data:`NO_ANCHOR_POSITION`.

    Returns
    -------
    pandas.DataFrame
        The usable reports with ``a_north, a_east, a_down, a_std_north, a_std_east`` added.
    """
    out = []
    known = set(tracks["anchor_id"].astype(str))
    ids = rssi["anchor_id"].astype(str)
    n_unknown = int((~ids.isin(known)).sum())
    if n_unknown:
        skipped[UNKNOWN_ANCHOR] += n_unknown
    for aid, tr in tracks.groupby("anchor_id", sort=True):
        sel = rssi.loc[ids == str(aid)]
        if sel.empty:
            continue
        tr = tr.sort_values("t")
        tt = tr["t"].to_numpy(float)
        t = sel["t"].to_numpy(float)
        j = np.searchsorted(tt, t)
        lo = np.clip(j - 1, 0, tt.size - 1)
        hi = np.clip(j, 0, tt.size - 1)
        exact = tt[hi] == t
        ok = exact | ((j > 0) & (j < tt.size) & (t - tt[lo] <= max_gap_s) & (tt[hi] - t <= max_gap_s))
        if (~ok).any():
            skipped[NO_ANCHOR_POSITION] += int((~ok).sum())
        s = sel.loc[ok].copy()
        for c in ("north", "east", "down", "std_north", "std_east"):
            s[f"a_{c}"] = np.interp(s["t"].to_numpy(float), tt, tr[c].to_numpy(float))
        out.append(s)
    if not out:
        cols = [*rssi.columns, "a_north", "a_east", "a_down", "a_std_north", "a_std_east"]
        return pd.DataFrame(columns=cols)
    return pd.concat(out).sort_index()


def _cov(df: pd.DataFrame) -> FloatArray:
    C = np.zeros((len(df), 2, 2))
    C[:, 0, 0] = df["a_std_north"].to_numpy(float) ** 2
    C[:, 1, 1] = df["a_std_east"].to_numpy(float) ** 2
    return C


def locate_nodes(
    tracks: pd.DataFrame,
    rssi: pd.DataFrame,
    model: PathLossModel,
    config: LocateConfig | None = None,
    node_down_m: float | None = None,
) -> LocateResult:
    """Position every node of an RSSI log.

    Parameters
    ----------
    tracks : pandas.DataFrame
        Anchor tracks in the local NED frame (see :func:`pair_reports`), m.
    rssi : pandas.DataFrame
        Reports ``t, anchor_id, node_id, rssi_dbm`` (validated: finite, physical range).
    model : PathLossModel
        Radio.
    config : LocateConfig, optional
        Settings.
    node_down_m : float, optional
        Down coordinate of the nodes, m; the median anchor down coordinate when omitted.

    Returns
    -------
    LocateResult
        Positions (north/east, m), optional tracks, skip and status counts.
    """
    cfg = config if config is not None else LocateConfig()
    skipped: Counter[str] = Counter()
    nodes = list(dict.fromkeys(rssi["node_id"].astype(str)))
    paired = pair_reports(tracks, rssi, cfg.max_anchor_gap_s, skipped)
    z_node = float(np.median(tracks["down"])) if node_down_m is None else float(node_down_m)
    rows: list[dict[str, Any]] = []
    track_parts: list[pd.DataFrame] = []
    status_counts: Counter[str] = Counter()
    groups = {str(k): g for k, g in paired.groupby(paired["node_id"].astype(str), sort=False)}
    for nid in nodes:
        g = groups.get(nid)
        row: dict[str, Any] = dict.fromkeys(POSITION_COLUMNS, np.nan)
        row["node_id"] = nid
        if g is None or g.empty:
            row.update(n_reports=0, n_used=0, n_anchors=0, status=str(Status.NO_DATA))
            rows.append(row)
            status_counts[str(Status.NO_DATA)] += 1
            continue
        g = g.sort_values("t", kind="stable")
        A = g[["a_north", "a_east", "a_down"]].to_numpy(float)
        C = _cov(g)
        r = g["rssi_dbm"].to_numpy(float)
        row.update(
            t_first=float(g["t"].iloc[0]),
            t_last=float(g["t"].iloc[-1]),
            n_reports=len(g),
            n_anchors=int(g["anchor_id"].nunique()),
        )
        if cfg.method == "track":
            tr = track_node(g["t"].to_numpy(float), A, C, r, model, z_node, cfg.tracker)
            ok = ~np.isnan(tr.x[:, 0])
            if ok.any():
                k = int(np.flatnonzero(ok)[-1])
                P = tr.P[k][POS, POS]
                row.update(
                    north=tr.x[k, 0],
                    east=tr.x[k, 1],
                    std_north=float(np.sqrt(P[0, 0])),
                    std_east=float(np.sqrt(P[1, 1])),
                    cov_ne=float(P[0, 1]),
                    drms_m=float(np.sqrt(np.trace(P))),
                    n_used=int(tr.accepted.sum()),
                    status=str(Status.OK),
                )
                track_parts.append(
                    pd.DataFrame(
                        {
                            "t": tr.t[ok],
                            "node_id": nid,
                            "north": tr.x[ok, 0],
                            "east": tr.x[ok, 1],
                            "v_north": tr.x[ok, 2],
                            "v_east": tr.x[ok, 3],
                            "std_north": np.sqrt(tr.P[ok, 0, 0]),
                            "std_east": np.sqrt(tr.P[ok, 1, 1]),
                            "cov_ne": tr.P[ok, 0, 1],
                            "accepted": tr.accepted[ok],
                        }
                    )
                )
            else:
                row.update(n_used=0, status=str(Status.UNDETERMINED))
        else:
            est = solve_position(A, r, model, C, z_node, Method(cfg.method), cfg.solver)
            row.update(
                north=est.p_ne[0],
                east=est.p_ne[1],
                std_north=float(np.sqrt(est.P[0, 0])),
                std_east=float(np.sqrt(est.P[1, 1])),
                cov_ne=float(est.P[0, 1]),
                drms_m=est.drms_m,
                n_used=est.n_used,
                status=str(est.status),
                mirror_north=est.mirror_ne[0],
                mirror_east=est.mirror_ne[1],
            )
        status_counts[str(row["status"])] += 1
        rows.append(row)
    positions = pd.DataFrame(rows, columns=POSITION_COLUMNS)
    track = pd.concat(track_parts, ignore_index=True) if track_parts else None
    return LocateResult(positions, track, skipped, status_counts)
