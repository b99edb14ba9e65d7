"""``registry.default_engine``: the engine for the inputs a log holds (issue 16, item 9)."""

from __future__ import annotations

import dataclasses

from iotnav.engines.registry import default_engine
from iotnav.eval.cases import load_case
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, empty_table


def test_default_engine_for_a_car_a_robot_and_a_walker() -> None:
    car = load_case("drive_0708-start100-bias1", max_duration_s=150.0).fed
    name, why = default_engine(car)
    assert name == "eskf" and "faster than walking" in why
    robot = load_case("husky", max_duration_s=150.0).fed
    name, why = default_engine(robot)
    assert name == "eskf" and "no walking cadence" in why  # 1 m/s but on wheels
    walk = load_case("walk_0827").fed
    name, why = default_engine(walk)
    assert name == "pdr" and "steps/s" in why


def test_default_engine_without_imu_or_gnss() -> None:
    walk = load_case("walk_0827").fed
    name, why = default_engine(dataclasses.replace(walk, gnss=empty_table(GNSS_COLUMNS)))
    assert name == "pipeline" and "no GNSS" in why
    name, why = default_engine(dataclasses.replace(walk, imu=empty_table(IMU_COLUMNS)))
    assert name in ("fixes", "pipeline") and "no IMU" in why
