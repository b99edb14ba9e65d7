"""Magnetometer model: Earth field plus disturbances, seen by a 3-axis sensor with iron errors.

::

    m_n(t) = F [cos I cos D, cos I sin D, sin I] + sum_j w_j(t) d_j
    y = sat(quant((I + S) C_nb^T m_n + h + n))

``F`` total intensity (uT), ``I`` inclination (positive down), ``D`` declination (positive
East); ``d_j`` local disturbances in ``n`` (a steel structure, a passing truck) with
raised-cosine envelopes ``w_j`` over their intervals; ``S`` symmetric soft-iron matrix and ``h``
hard-iron offset, drawn once from the preset's sigmas; ``n`` white noise.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from iotnav.sim.config import MagConfig
from iotnav.sim.presets import MagSpec

FloatArray = npt.NDArray[np.float64]

__all__ = ["earth_field_n", "simulate_mag"]


def earth_field_n(field_ut: float, inclination_deg: float, declination_deg: float) -> FloatArray:
    """Earth magnetic field in NED, uT."""
    inc, dec = np.radians(inclination_deg), np.radians(declination_deg)
    return field_ut * np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])


def disturbance_n(
    t: FloatArray, disturbances: tuple[tuple[float, float, float, float, float], ...]
) -> FloatArray:
    """Sum of the configured disturbances at times ``t``, uT in ``n``, ``(n, 3)``."""
    out = np.zeros((len(t), 3))
    for t0, t1, dn, de, dd in disturbances:
        if t1 <= t0:
            raise ValueError(f"mag.disturbances: interval ({t0}, {t1}) must have t_end > t_start")
        u = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
        w = 0.5 * (1.0 - np.cos(2.0 * np.pi * u))
        out += w[:, None] * np.array([dn, de, dd])
    return out


def simulate_mag(
    cfg: MagConfig, spec: MagSpec, t: FloatArray, q_nb: FloatArray, rng: np.random.Generator
) -> tuple[FloatArray, dict[str, FloatArray]]:
    """Magnetometer samples at times ``t`` for sensor attitudes ``q_nb`` (scipy quaternions).

    Returns
    -------
    numpy.ndarray
        Field in ``b``, uT, ``(n, 3)``.
    dict
        ``hard_iron_ut`` and ``soft_iron`` (the matrix ``I + S``) drawn.
    """
    m_n = earth_field_n(cfg.field_ut, cfg.inclination_deg, cfg.declination_deg) + disturbance_n(
        t, cfg.disturbances
    )
    m_b = Rotation.from_quat(q_nb).inv().apply(m_n)
    if not cfg.errors:
        return m_b, {"hard_iron_ut": np.zeros(3), "soft_iron": np.eye(3)}
    s = rng.normal(0.0, spec.soft_iron_pct * 1e-2, (3, 3))
    soft = np.eye(3) + 0.5 * (s + s.T)
    hard = rng.normal(0.0, spec.hard_iron_ut, 3)
    y = m_b @ soft.T + hard + rng.normal(0.0, spec.noise_ut, m_b.shape)
    if spec.lsb_ut > 0:
        y = np.round(y / spec.lsb_ut) * spec.lsb_ut
    y = np.clip(y, -spec.range_ut, spec.range_ut)
    return y, {"hard_iron_ut": hard, "soft_iron": soft}
