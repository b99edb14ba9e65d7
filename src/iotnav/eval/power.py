"""Energy model of a tracker that sleeps its GNSS receiver between fixes (issue 20).

The anchor-node paper (Real time IoT mobile anchor nodes outdoor localization mechanism, Int.
J. on Smart Sensing and Intelligent Systems 15, 2022) puts its unit at 134.76 mW: GPS module
79.2 mW, IMU (MPU6050) 10.56 mW, ATmega128 45 mW (section "Hardware implementation of IoT
anchor node", the note on power consumption, repeated with Table 1 of the results; the
journal's HTML edition has no page numbers: in ``papers/iot-mobile-anchor-node-localization.txt``
lines 328 and 411), and proposes that the microcontroller "place the GPS in sleep mode and wake
it only at certain time intervals". Dabove et al. (the image-positioning paper) choose their fix
interval with the battery in mind. This module computes what such a duty cycle buys.

Model (every power in mW, every time in s, energy in mWh; all pure functions)
------------------------------------------------------------------------------
One GNSS cycle of period ``T``: the receiver wakes, acquires for the time to fix after waking
``t_fix`` (a hot start: ephemeris still valid, the receiver kept its backup domain) at the
acquisition power ``P_acq``, stays on ``t_on`` more (default 0: the fix is read, the receiver
goes back to backup) at the tracking power ``P_trk``, and sleeps the rest of the period at the
backup power ``P_bak``::

    P_gnss(T) = (t_fix P_acq + t_on P_trk + (T - t_fix - t_on) P_bak) / T     (T > t_fix + t_on)
    P_gnss(always on) = P_trk

A period no longer than ``t_fix + t_on`` cannot sleep: the receiver stays on (``P_trk``).

The IMU and the microcontroller depend on the engine. An inertial engine (``pipeline``,
``anchor``, ``qekf``, ``eskf``) integrates every IMU sample, so the IMU is always on and the
microcontroller busy a fraction ``mcu_busy`` of the time (1.0 by default: the paper's 10 ms
frame takes 10.223 ms, the CPU never sleeps), asleep otherwise. A GNSS-only engine
(``fixes``) needs no IMU (asleep) and the microcontroller only while the receiver is on::

    P_imu  = P_imu,on                                 (inertial)  | P_imu,sleep        (GNSS only)
    P_mcu  = b P_mcu,on + (1 - b) P_mcu,sleep        (inertial)  | a P_mcu,on + (1 - a) P_mcu,sleep
    a = (t_fix + t_on) / T  (1 when always on),   b = mcu_busy

Battery life, hours, from the capacity ``C`` (mAh) at the nominal voltage ``V`` (V) and the
usable fraction ``u`` (1.0: no derating; regulators, self-discharge and temperature are left to
the user's ``u``)::

    E = u C V  (mWh),     life = E / (P_gnss + P_imu + P_mcu)  (h)

Check by hand (the paper's unit always on, a 2000 mAh 3.7 V cell): 7400 mWh / 134.76 mW =
54.9 h.

Defaults and presets (datasheet values; the source is in each preset's ``source``)
-----------------------------------------------------------------------------------
* ``paper`` GNSS: 79.2 mW acquiring and tracking (the paper gives one figure); backup 15 uA
  at 3.0 V = 0.045 mW, the u-blox M8 hardware-backup current (ZOE-M8Q, RAK12500 datasheet
  "I_BCKP 15 uA"): the paper gives no sleep figure; time to fix after waking 1 s (u-blox
  hot start, SAM-M10Q datasheet as tabled by SparkFun: hot start 1 s).
* ``sam-m8q`` GNSS: u-blox SAM-M8Q data sheet UBX-16012619 R04, Table 8 p. 17, GPS only at
  3.0 V: acquisition 25 mA (75 mW, the average from start-up to the first fix), continuous
  tracking 23 mA (69 mW); backup and hot start as above.
* ``paper`` IMU: 10.56 mW on; asleep 5 uA at 3.3 V = 0.0165 mW (MPU-6000/6050 product
  specification PS-MPU-6000A-00 rev. 3.4, section 6.3 p. 14, full-chip idle 5 uA; the paper's
  MPU6050 at 3.3 V).
* ``mpu6050`` IMU: the same specification, gyroscope + accelerometer with the DMP disabled
  3.8 mA at 3.3 V = 12.54 mW; idle 0.0165 mW.
* ``paper`` MCU: 45 mW on; asleep: ATmega128 power-down with the watchdog running (the wake-up
  timer) 15 uA typical at 3 V = 0.045 mW (ATmega128 datasheet 2467X-AVR-06/11, DC
  characteristics p. 319).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = [
    "GNSS_ONLY_ENGINES",
    "GNSS_PRESETS",
    "IMU_PRESETS",
    "MCU_PRESETS",
    "PAPER_TOTAL_MW",
    "Battery",
    "ComponentPower",
    "DevicePower",
    "GnssPower",
    "PowerBudget",
    "battery_life_h",
    "budget",
    "budgets",
    "gnss_average_mw",
    "uses_imu",
]

#: The paper's unit: GPS 79.2 + IMU 10.56 + MCU 45 mW.
PAPER_TOTAL_MW = 134.76

#: Engines that run on GNSS fixes alone (no IMU): the IMU sleeps, the MCU wakes with the receiver.
GNSS_ONLY_ENGINES = frozenset({"fixes", "hold"})


@dataclass(frozen=True)
class GnssPower:
    """A GNSS receiver's powers and its time to fix after waking.

    Attributes
    ----------
    name : str
        Preset name.
    acquisition_mw : float
        Average power from waking to the fix, mW.
    tracking_mw : float
        Continuous tracking, mW.
    backup_mw : float
        Asleep between fixes with the backup domain kept (hot start on waking), mW.
    time_to_fix_s : float
        Time to fix after waking (hot start), s.
    source : str
        Where the figures come from.
    """

    name: str
    acquisition_mw: float
    tracking_mw: float
    backup_mw: float
    time_to_fix_s: float
    source: str = ""

    def __post_init__(self) -> None:
        for f in ("acquisition_mw", "tracking_mw", "backup_mw", "time_to_fix_s"):
            v = getattr(self, f)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"GNSS {self.name}: {f} must be a finite number >= 0, got {v}")


@dataclass(frozen=True)
class ComponentPower:
    """A component that is either on or asleep (IMU, microcontroller).

    Attributes
    ----------
    name : str
        Preset name.
    active_mw, sleep_mw : float
        Power on and asleep, mW.
    source : str
        Where the figures come from.
    """

    name: str
    active_mw: float
    sleep_mw: float
    source: str = ""

    def __post_init__(self) -> None:
        for f in ("active_mw", "sleep_mw"):
            v = getattr(self, f)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{self.name}: {f} must be a finite number >= 0, got {v}")


_PAPER = "anchor-node paper (IJSSIS 15, 2022), hardware section note and Table 1"
_M8_BACKUP = "u-blox M8 hardware backup 15 uA at 3.0 V (ZOE-M8Q, RAK12500 datasheet)"
_HOT = "hot start 1 s (u-blox SAM-M10Q datasheet, as tabled in SparkFun's SAM-M10Q guide)"
_MPU = "MPU-6000/6050 spec PS-MPU-6000A-00 rev 3.4 sec. 6.3 p. 14 at 3.3 V"

#: GNSS receivers by preset name.
GNSS_PRESETS: dict[str, GnssPower] = {
    "paper": GnssPower("paper", 79.2, 79.2, 0.015 * 3.0, 1.0, f"on: {_PAPER}; backup: {_M8_BACKUP}; {_HOT}"),
    "sam-m8q": GnssPower(
        "sam-m8q",
        25.0 * 3.0,
        23.0 * 3.0,
        0.015 * 3.0,
        1.0,
        f"SAM-M8Q data sheet UBX-16012619 R04 Table 8 p. 17 (GPS, 3.0 V): acquisition 25 mA, "
        f"tracking 23 mA; backup: {_M8_BACKUP}; {_HOT}",
    ),
}

#: IMUs by preset name.
IMU_PRESETS: dict[str, ComponentPower] = {
    "paper": ComponentPower("paper", 10.56, 0.005 * 3.3, f"on: {_PAPER}; idle 5 uA: {_MPU}"),
    "mpu6050": ComponentPower(
        "mpu6050", 3.8 * 3.3, 0.005 * 3.3, f"gyro + accel (DMP off) 3.8 mA, idle 5 uA: {_MPU}"
    ),
}

#: Microcontrollers by preset name.
MCU_PRESETS: dict[str, ComponentPower] = {
    "paper": ComponentPower(
        "paper",
        45.0,
        0.015 * 3.0,
        f"on: {_PAPER}; power-down with watchdog 15 uA at 3 V: ATmega128 datasheet 2467X "
        "DC characteristics p. 319",
    ),
}


@dataclass(frozen=True)
class DevicePower:
    """The three powered parts of a tracker.

    Attributes
    ----------
    gnss : GnssPower
    imu, mcu : ComponentPower
    on_after_fix_s : float
        Time the receiver stays on (tracking) after its fix before going back to backup, s.
    mcu_busy : float
        Fraction of the time the microcontroller runs an inertial engine (0..1).
    """

    gnss: GnssPower = GNSS_PRESETS["paper"]
    imu: ComponentPower = IMU_PRESETS["paper"]
    mcu: ComponentPower = MCU_PRESETS["paper"]
    on_after_fix_s: float = 0.0
    mcu_busy: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.on_after_fix_s) and self.on_after_fix_s >= 0.0):
            raise ValueError(f"on_after_fix_s must be >= 0, got {self.on_after_fix_s}")
        if not (0.0 <= self.mcu_busy <= 1.0):
            raise ValueError(f"mcu_busy must be within 0..1, got {self.mcu_busy}")


@dataclass(frozen=True)
class Battery:
    """A battery: capacity at its nominal voltage.

    Attributes
    ----------
    capacity_mah : float
        Capacity, mAh.
    voltage_v : float
        Nominal voltage, V.
    usable_fraction : float
        Fraction of the energy the device can use (1.0: no derating).
    """

    capacity_mah: float = 2000.0
    voltage_v: float = 3.7
    usable_fraction: float = 1.0

    def __post_init__(self) -> None:
        if not (self.capacity_mah > 0.0 and math.isfinite(self.capacity_mah)):
            raise ValueError(f"battery capacity must be > 0 mAh, got {self.capacity_mah}")
        if not (self.voltage_v > 0.0 and math.isfinite(self.voltage_v)):
            raise ValueError(f"battery voltage must be > 0 V, got {self.voltage_v}")
        if not (0.0 < self.usable_fraction <= 1.0):
            raise ValueError(f"usable fraction must be within (0, 1], got {self.usable_fraction}")

    @property
    def energy_mwh(self) -> float:
        """Usable energy, mWh (``u C V``)."""
        return self.usable_fraction * self.capacity_mah * self.voltage_v


@dataclass(frozen=True)
class PowerBudget:
    """Average powers (mW) and battery life (h) of one duty cycle.

    ``period_s`` is None for the receiver always on; ``gnss_on_fraction`` is the fraction of
    the time the receiver is awake.
    """

    period_s: float | None
    gnss_mw: float
    imu_mw: float
    mcu_mw: float
    gnss_on_fraction: float
    life_h: float

    @property
    def total_mw(self) -> float:
        """Sum of the three, mW."""
        return self.gnss_mw + self.imu_mw + self.mcu_mw

    @property
    def label(self) -> str:
        """``always on`` or ``every N s``."""
        return "always on" if self.period_s is None else f"every {self.period_s:g} s"


def uses_imu(engine: str) -> bool:
    """Whether an engine needs the IMU (and the MCU at its ``mcu_busy``); see the module docstring."""
    return engine not in GNSS_ONLY_ENGINES


def _check_period(period_s: float | None) -> None:
    if period_s is not None and not (math.isfinite(period_s) and period_s > 0.0):
        raise ValueError(f"fix period must be a positive number of seconds, got {period_s}")


def _awake_s(gnss: GnssPower, on_after_fix_s: float) -> float:
    return gnss.time_to_fix_s + on_after_fix_s


def gnss_on_fraction(gnss: GnssPower, period_s: float | None, on_after_fix_s: float = 0.0) -> float:
    """Fraction of the time the receiver is awake (1 when always on or when it cannot sleep)."""
    _check_period(period_s)
    awake = _awake_s(gnss, on_after_fix_s)
    if period_s is None or period_s <= awake:
        return 1.0
    return awake / period_s


def gnss_average_mw(gnss: GnssPower, period_s: float | None, on_after_fix_s: float = 0.0) -> float:
    """Average receiver power over a duty cycle, mW (module docstring).

    Parameters
    ----------
    gnss : GnssPower
        The receiver.
    period_s : float or None
        Time between fixes, s; None: always on.
    on_after_fix_s : float
        Tracking time after the fix before going back to backup, s.
    """
    _check_period(period_s)
    awake = _awake_s(gnss, on_after_fix_s)
    if period_s is None or period_s <= awake:
        return gnss.tracking_mw
    energy = (
        gnss.time_to_fix_s * gnss.acquisition_mw
        + on_after_fix_s * gnss.tracking_mw
        + (period_s - awake) * gnss.backup_mw
    )
    return energy / period_s


def battery_life_h(battery: Battery, average_mw: float) -> float:
    """Hours a battery lasts at an average power (``E / P``); ``inf`` at 0 mW."""
    if not (average_mw >= 0.0 and math.isfinite(average_mw)):
        raise ValueError(f"average power must be a finite number >= 0 mW, got {average_mw}")
    return math.inf if average_mw == 0.0 else battery.energy_mwh / average_mw


def budget(device: DevicePower, battery: Battery, period_s: float | None, engine: str) -> PowerBudget:
    """Average powers and battery life of one duty cycle for one engine.

    Parameters
    ----------
    device : DevicePower
        Receiver, IMU, MCU.
    battery : Battery
        The battery.
    period_s : float or None
        Time between fixes, s (None: always on).
    engine : str
        Engine name: :data:`GNSS_ONLY_ENGINES` sleep the IMU and wake the MCU with the receiver.

    Returns
    -------
    PowerBudget
    """
    gnss_mw = gnss_average_mw(device.gnss, period_s, device.on_after_fix_s)
    a = gnss_on_fraction(device.gnss, period_s, device.on_after_fix_s)
    if uses_imu(engine):
        imu_mw = device.imu.active_mw
        b = device.mcu_busy
    else:
        imu_mw = device.imu.sleep_mw
        b = a
    mcu_mw = b * device.mcu.active_mw + (1.0 - b) * device.mcu.sleep_mw
    total = gnss_mw + imu_mw + mcu_mw
    return PowerBudget(period_s, gnss_mw, imu_mw, mcu_mw, a, battery_life_h(battery, total))


def budgets(
    device: DevicePower, battery: Battery, periods_s: Sequence[float | None], engine: str
) -> list[PowerBudget]:
    """:func:`budget` for each duty cycle, in the given order."""
    return [budget(device, battery, p, engine) for p in periods_s]
