"""The pipeline with its heading unresolved (:mod:`iotnav.engines.pipeline`, "Heading unresolved").

Before the yaw filter has a heading, or while block 5 has no mount angle, the horizontal
specific force cannot be placed in ``n``: the pipeline must not integrate it in the direction it
happens to assume (the cause of the 3.6 m spike at the start of ``make run``'s scooter-laps,
where the mount is 88 deg), and must use it again once the heading is known.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from _pipeline_synth import H0, LAT0, LON0, G
from iotnav.engines import GnssSample, ImuSample, Pipeline, PipelineConfig
from iotnav.engines.base import MagSample
from iotnav.engines.config import EngineConfig

CFG = PipelineConfig(pipeline=EngineConfig(gravity_mps2=G))
FORCE = 2.0  # m/s^2 along sensor x for the last second: 1 m of travel, direction unknown to the filter


def _run(cfg: PipelineConfig, mag: bool) -> tuple[float, float, float]:
    """A fix at rest, 2 s at rest, then 1 s of FORCE (100 Hz IMU); final north, east, std_north (m)."""
    p = Pipeline(cfg)
    p.step(GnssSample(0.0, LAT0, LON0, H0, 1.0, 0.8, 12, 0.0, math.nan, False, True))
    o = None
    for k in range(1, 301):
        t = k * 0.01
        if mag:  # a field along sensor x, level: the heading is known (sensor x to magnetic north)
            p.step(MagSample(t, np.array([20.0, 0.0, 40.0])))
        o = p.step(ImuSample(t, np.array([FORCE if t > 2.0 else 0.0, 0.0, -G]), np.zeros(3)))
    assert o is not None and not o.static and o.source == "dr"
    return o.north, o.east, o.std_north


RESOLVED = CFG.replace(pipeline=dataclasses.replace(CFG.pipeline, use_mount=False))


def test_an_unresolved_heading_does_not_place_the_horizontal_force() -> None:
    # no course (at rest), no magnetometer, no mount: the old pipeline moved 1.0 m north (yaw 0)
    north, east, std = _run(CFG, mag=False)
    assert math.hypot(north, east) < 0.01
    # the force it could not place is process noise instead: less sure than with the heading known
    assert std > _run(RESOLVED, mag=True)[2]


def test_a_resolved_heading_places_it() -> None:
    # heading from the magnetometer and a mount declared aligned (block 5 off): the force is used
    north, east, _ = _run(RESOLVED, mag=True)
    assert 0.8 < math.hypot(north, east) < 1.2
