"""Benchmark: characterise a seeded 6-hour static IMU log (100 Hz, 6 axes) as Dabove et al. did.

Synthesises white noise + flicker (bias instability) + rate random walk per axis with known
parameters (the generator of ``tests/test_allan.py``, re-implemented here so the benchmark stands
alone), times :func:`iotnav.techniques.allan.characterize` (Allan deviation with allantools and
the fits), and prints a markdown snippet with the timing and recovered vs configured values.
With ``IOTNAV_WRITE_RESULTS=1`` the snippet goes to ``benchmarks/results/characterize.md``.

Run: ``.venv/bin/python benchmarks/bench_characterize.py [rate_hz]``
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from iotnav.techniques.allan import characterize

SEED = 20160101
F = math.sqrt(2.0 * math.log(2.0) / math.pi)
DEG = math.pi / 180.0
UG = 9.80665e-6
GYRO = ((0.004, 8.0), (0.005, 10.0), (0.006, 12.0))  # deg/s/rtHz, deg/h
ACC = ((80.0, 40.0), (100.0, 50.0), (120.0, 60.0))  # ug/rtHz, ug


def synth(rng: np.random.Generator, n: int, fs: float, N: float, B: float, K: float) -> np.ndarray:
    """White (PSD N^2) + flicker (PSD B^2 / (2 pi f)) + rate random walk (K)."""
    f = np.fft.rfftfreq(n, 1.0 / fs)
    psd = np.zeros_like(f)
    psd[1:] = B**2 / (2.0 * math.pi * f[1:])
    z = (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f))) / math.sqrt(2.0)
    flicker = np.fft.irfft(np.sqrt(psd * n * fs) * z, n)
    return (
        N * math.sqrt(fs) * rng.standard_normal(n)
        + flicker
        + np.cumsum(K * math.sqrt(1.0 / fs) * rng.standard_normal(n))
    )


def expected_b(N: float, B: float, K: float) -> float:
    """Analytic ADEV floor / 0.664 of the three-term model."""
    return math.sqrt((F * B) ** 2 + 2.0 * N * K / math.sqrt(3.0)) / F


def main(fs: float = 100.0) -> str:
    n = int(6 * 3600 * fs)
    rng = np.random.default_rng(SEED)
    cols_g, cols_a, exp = [], [], []
    t0 = time.perf_counter()
    for nd, bi in GYRO:
        N, B = nd * DEG, bi * DEG / 3600.0
        K = F * B / math.sqrt(1000.0)
        cols_g.append(synth(rng, n, fs, N, B, K))
        exp.append(("gyro", nd, expected_b(N, B, K) * 3600.0 / DEG))
    for nd, bi in ACC:
        N, B = nd * UG, bi * UG
        K = F * B / math.sqrt(1000.0)
        cols_a.append(synth(rng, n, fs, N, B, K))
        exp.append(("accel", nd, expected_b(N, B, K) / UG))
    t_gen = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = characterize(np.arange(n) / fs, np.column_stack(cols_a), np.column_stack(cols_g))
    t_char = time.perf_counter() - t0
    lines = [
        "## characterize: 6-hour static log",
        "",
        f"{n:,} samples per axis at {fs:g} Hz, 6 axes, seed {SEED}. Synthesis {t_gen:.1f} s; "
        f"`characterize` (allantools oadev + fits) {t_char:.1f} s.",
        "",
        "| axis | N configured | N recovered | B expected (floor/0.664) | B recovered |",
        "|---|---|---|---|---|",
    ]
    params = list(res.gyro_params) + list(res.acc_params)
    for (kind, nd, b_exp), p, ax in zip(exp, params, "xyzxyz", strict=True):
        if kind == "gyro":
            n_rec, b_rec, un, ub = (
                p.noise_density / DEG,
                p.bias_instability * 3600 / DEG,
                "deg/s/rtHz",
                "deg/h",
            )
        else:
            n_rec, b_rec, un, ub = p.noise_density / UG, p.bias_instability / UG, "ug/rtHz", "ug"
        lines.append(f"| {kind} {ax} | {nd:.4g} {un} | {n_rec:.4g} | {b_exp:.4g} {ub} | {b_rec:.4g} |")
    text = "\n".join(lines) + "\n"
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        dest = Path(__file__).resolve().parent / "results" / "characterize.md"
        dest.write_text(text)
    return text


if __name__ == "__main__":
    print(main(float(sys.argv[1]) if len(sys.argv) > 1 else 100.0))
