"""Scenario simulator: trajectories, sensor error models, files in the formats iotnav reads.

Usage::

    from iotnav import sim

    sim.list_scenarios()
    result = sim.build("scooter-laps", seed=1, overrides={"motion.laps": 3, "imu.preset": "mpu6050"})
    sim.write(result, "out/scooter")

Modules: :mod:`~iotnav.sim.trajectory` (motion primitives, truth consistent with
:mod:`iotnav.strapdown` by construction), :mod:`~iotnav.sim.imu_model`,
:mod:`~iotnav.sim.gnss_model`, :mod:`~iotnav.sim.mag_model`, :mod:`~iotnav.sim.presets`
(datasheet values), :mod:`~iotnav.sim.config` (frozen parameters, dotted overrides),
:mod:`~iotnav.sim.scenarios` (named scenarios, pipeline), :mod:`~iotnav.sim.writers`.
"""

from __future__ import annotations

from iotnav.sim.config import ScenarioConfig, apply_overrides, parameter_keys
from iotnav.sim.scenarios import SCENARIOS, SimResult, build, default_config, list_scenarios, simulate
from iotnav.sim.writers import write

__all__ = [
    "SCENARIOS",
    "ScenarioConfig",
    "SimResult",
    "apply_overrides",
    "build",
    "default_config",
    "list_scenarios",
    "parameter_keys",
    "simulate",
    "write",
]
