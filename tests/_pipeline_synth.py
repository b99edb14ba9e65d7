"""Small closed-form synthetic inputs for the Forno pipeline tests (no dependency on iotnav.sim).

A planar vehicle (level, x forward, y right, z down) follows segments of constant
longitudinal acceleration and yaw rate; the sensor sits level on it, rotated by ``mount_yaw``
about the vertical (sensor yaw = vehicle yaw + mount). IMU samples are the exact specific
force and rate plus seeded white noise and a constant gyro bias; GNSS epochs at 1 Hz carry
the true position plus noise, the true speed and course plus noise, and a PDOP.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, coerce

LAT0, LON0, H0 = 45.0625, 7.6625, 240.0
G = 9.806  # gravity used by the synthetic IMU (the pipeline is told the same value)
K_N = 111_132.0  # metres per degree latitude (approximate, test-side only)


@dataclass
class Truth:
    t: np.ndarray
    pos_n: np.ndarray  # (N, 3)
    vel_n: np.ndarray
    yaw_v: np.ndarray
    speed: np.ndarray
    static: np.ndarray


def trajectory(
    segments: list[tuple[float, float, float]], rate_hz: float, yaw0: float = 0.0, v0: float = 0.0
):
    """Integrate ``(duration_s, long_acc_mps2, yaw_rate_rad_s)`` segments at ``rate_hz``."""
    dt = 1.0 / rate_hz
    rows = []
    p = np.zeros(2)
    v, psi = v0, yaw0
    t = 0.0
    for dur, a, r in segments:
        for _ in range(round(dur * rate_hz)):
            an = a * np.array([math.cos(psi), math.sin(psi)]) + v * r * np.array(
                [-math.sin(psi), math.cos(psi)]
            )
            rows.append((t, p[0], p[1], v, psi, an[0], an[1], r, a))
            p = p + v * np.array([math.cos(psi), math.sin(psi)]) * dt + 0.5 * an * dt * dt
            v = max(v + a * dt, 0.0)
            psi += r * dt
            t += dt
    return np.array(rows)


def make_log(
    segments: list[tuple[float, float, float]],
    *,
    mount_yaw: float = 0.0,
    imu_hz: float = 20.0,
    seed: int = 0,
    acc_noise: float = 0.02,
    gyro_noise: float = 0.002,
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
    pos_noise: float = 1.0,
    speed_noise: float = 0.05,
    course_noise: float = 0.01,
    pdop: float = 1.5,
    yaw0: float = 0.0,
    gnss_gap: tuple[float, float] | None = None,
) -> tuple[Log, Truth]:
    """IMU and 1 Hz GNSS tables for the given vehicle segments."""
    rng = np.random.default_rng(seed)
    tr = trajectory(segments, imu_hz, yaw0)
    t, pn, pe, v, psi, an_n, an_e, r, _a = tr.T
    n = t.size
    yaw_b = psi + mount_yaw
    # specific force in n: a_n - g_n, rotate into b (level sensor: rotation about z only)
    fn = np.column_stack([an_n, an_e, np.full(n, -G)])
    c, s = np.cos(yaw_b), np.sin(yaw_b)
    f_b = np.column_stack([c * fn[:, 0] + s * fn[:, 1], -s * fn[:, 0] + c * fn[:, 1], fn[:, 2]])
    f_b += rng.normal(0.0, acc_noise, f_b.shape)
    w_b = np.column_stack([np.zeros(n), np.zeros(n), r]) + np.asarray(gyro_bias)
    w_b += rng.normal(0.0, gyro_noise, w_b.shape)
    imu = pd.DataFrame(
        {
            "t": t,
            "acc_x": f_b[:, 0],
            "acc_y": f_b[:, 1],
            "acc_z": f_b[:, 2],
            "gyro_x": w_b[:, 0],
            "gyro_y": w_b[:, 1],
            "gyro_z": w_b[:, 2],
        }
    )
    step = round(imu_hz)
    gi = np.arange(0, n, step)
    if gnss_gap is not None:
        gi = gi[(t[gi] < gnss_gap[0]) | (t[gi] >= gnss_gap[1])]
    m = gi.size
    noisy_n = pn[gi] + rng.normal(0.0, pos_noise, m)
    noisy_e = pe[gi] + rng.normal(0.0, pos_noise, m)
    k_e = K_N * math.cos(math.radians(LAT0))
    spd = np.abs(v[gi] + rng.normal(0.0, speed_noise, m))
    gnss = pd.DataFrame(
        {
            "t": t[gi],
            "lat_deg": LAT0 + noisy_n / K_N,
            "lon_deg": LON0 + noisy_e / k_e,
            "height_m": H0 + rng.normal(0.0, pos_noise, m),
            "pdop": np.full(m, pdop),
            "hdop": np.full(m, pdop / 1.5),
            "num_sv": np.full(m, 9),
            "speed_mps": spd,
            "course_rad": np.mod(psi[gi] + rng.normal(0.0, course_noise, m), 2 * math.pi),
            "course_valid": v[gi] > 0.5,
            "valid": np.ones(m, bool),
            "quality": np.ones(m, int),
            "source": ["sim"] * m,
        }
    )
    log = Log(gnss=coerce(gnss, GNSS_COLUMNS), imu=coerce(imu, IMU_COLUMNS))
    truth = Truth(
        t,
        np.column_stack([pn, pe, np.zeros(n)]),
        np.column_stack([v * np.cos(psi), v * np.sin(psi), np.zeros(n)]),
        psi,
        v,
        v < 1e-6,
    )
    return log, truth


def laps(
    n_laps: int = 2, speed: float = 5.0, straight_s: float = 16.0, turn_s: float = 8.0, rest_s: float = 10.0
):
    """Rest, accelerate, then constant-speed straights joined by left U-turns; brake; rest."""
    acc_s = 4.0
    seg = [(rest_s, 0.0, 0.0), (acc_s, speed / acc_s, 0.0)]
    for _ in range(n_laps * 2):
        seg += [(straight_s, 0.0, 0.0), (turn_s, 0.0, -math.pi / turn_s)]
    seg += [(straight_s, 0.0, 0.0), (acc_s, -speed / acc_s, 0.0), (rest_s, 0.0, 0.0)]
    return seg
