"""The tracker's vocabulary for any engine's track: trips, stops, odometer, geofences, events.

Pure functions, no I/O (``iotnav run`` writes ``trips.csv`` and the events,
:mod:`iotnav.runs`). Not a paper technique: the hysteresis follows Traccar's documented trip
rules (:mod:`iotnav.tracker.motion`), the rest is stated in each module.
"""

from iotnav.tracker.geofence import Zone, border_step, geofence_events, zones_from_geojson
from iotnav.tracker.motion import (
    KNOT_MPS,
    Segment,
    Switch,
    TripHysteresis,
    TripRules,
    motion_evidence,
    segments,
)
from iotnav.tracker.odometer import gated_increments, velocity_increments
from iotnav.tracker.vocabulary import (
    TRIP_COLUMNS,
    TrackerConfig,
    TrackerResult,
    describe,
    segment_table,
    track_from_fixes,
)

__all__ = [
    "KNOT_MPS",
    "TRIP_COLUMNS",
    "Segment",
    "Switch",
    "TrackerConfig",
    "TrackerResult",
    "TripHysteresis",
    "TripRules",
    "Zone",
    "border_step",
    "describe",
    "gated_increments",
    "geofence_events",
    "motion_evidence",
    "segment_table",
    "segments",
    "track_from_fixes",
    "velocity_increments",
    "zones_from_geojson",
]
