"""Localizing non-GNSS nodes from (mobile) anchor nodes: the anchor-node mechanism.

Zorkany et al. (2022, "Real time IoT mobile anchor nodes outdoor localization mechanism",
Int. J. Smart Sensing and Intelligent Systems 15(1), section 4, Fig. 3) equip only some IoT
nodes (the anchors) with GNSS + IMU and locate the cheaper nodes from the radio signals they
exchange with the anchors. The anchors' fused tracks come from iotnav's engines; this package
does the second step.

Modules
-------
:mod:`~iotnav.nodes.ranging`
    Log-distance path loss (R1-R3), radio presets (LoRa SF7-SF12, BLE, Wi-Fi), robust
    calibration of ``P0`` and ``n``.
:mod:`~iotnav.nodes.multilateration`
    WLS / Gauss-Newton with the anchors' covariance propagated, Huber and RANSAC variants,
    Cramer-Rao bound (M1-M4), geometry flags.
:mod:`~iotnav.nodes.tracking`
    EKF for slowly moving nodes hearing moving anchors (T1).
:mod:`~iotnav.nodes.simulate`
    Anchor trajectories and RSSI reports (S1): shadowing, packet loss, LoRa duty cycle.
:mod:`~iotnav.nodes.locate`
    Fleet-level pairing of reports with anchor positions and per-node solving.
:mod:`~iotnav.nodes.io`
    Reading anchor tracks and RSSI CSV (counted skips), writing CSV and GeoJSON.

Frames and units follow :mod:`iotnav`: positions in a local NED frame ``n`` in metres, RSSI
in dBm (``rssi_dbm``), shadowing in dB, times in seconds.
"""

from iotnav.nodes.locate import LocateConfig, LocateResult, locate_nodes
from iotnav.nodes.multilateration import (
    Method,
    PositionEstimate,
    SolverConfig,
    Status,
    crb,
    solve_position,
)
from iotnav.nodes.ranging import RADIOS, PathLossFit, PathLossModel, fit_path_loss, radio
from iotnav.nodes.tracking import NodeTracker, TrackerConfig, track_node

__all__ = [
    "RADIOS",
    "LocateConfig",
    "LocateResult",
    "Method",
    "NodeTracker",
    "PathLossFit",
    "PathLossModel",
    "PositionEstimate",
    "SolverConfig",
    "Status",
    "TrackerConfig",
    "crb",
    "fit_path_loss",
    "locate_nodes",
    "radio",
    "solve_position",
    "track_node",
]
