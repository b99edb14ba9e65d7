"""Benchmark of the ``eskf`` engine: outage drift on ``car-tunnel``, attitude on
``car-magnetometer``, Monte Carlo NEES / NIS, and IMU samples per second.

Run: ``.venv/bin/python benchmarks/bench_eskf.py [n_seeds]``; with ``IOTNAV_WRITE_RESULTS=1``
the markdown is written to ``benchmarks/results/eskf.md``.
"""

from __future__ import annotations

import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from iotnav import sim
from iotnav.engines.base import GnssSample, iter_samples, run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.engines.eskf_models import dcm_to_rotvec
from iotnav.eval.metrics import outage_drift, track_errors
from iotnav.geo import dcm_to_rpy, euler_to_dcm
from iotnav.io.log import Log


def tunnel(seeds: list[int]) -> tuple[list[str], float]:
    lines = [
        "| seed | outage (s) | length (s) | distance (m) | end error (m) | drift (%) |",
        "|---|---|---|---|---|---|",
    ]
    long: list[float] = []
    rate = []
    for seed in seeds:
        res = sim.build("car-tunnel", seed=seed)
        eng = EskfEngine(EskfConfig())
        t0 = time.perf_counter()
        df = run_batch(eng, Log(gnss=res.gnss, imu=res.imu, mag=res.mag))
        rate.append(len(df) / (time.perf_counter() - t0))
        err = track_errors(df, res.truth)
        for d in outage_drift(err, res.truth, list(res.config.gnss.outages_s)):
            lines.append(
                f"| {seed} | {d['start']:.0f}-{d['end']:.0f} | {d['length_s']:.0f} | {d['distance_m']:.0f} | "
                f"{d['end_error_m']:.2f} | {d['drift_pct']:.2f} |"
            )
            if 30.0 <= d["length_s"] <= 60.0:
                long.append(d["drift_pct"])
    lines.append("")
    lines.append(
        f"Median drift over the {len(long)} outages of 30-60 s: **{np.median(long):.2f} %** "
        f"(max {np.max(long):.2f} %; target <= 2 %; u-blox NEO-M8U typ. 10 %, ZED-F9R 2 % with wheel ticks)."
    )
    return lines, float(np.median(rate))


def magnetometer(seeds: list[int]) -> list[str]:
    lines = [
        "| seed | roll RMS (deg) | pitch RMS (deg) | yaw RMS (deg) | max error in the 4 s gap (m) |",
        "|---|---|---|---|---|",
    ]
    for seed in seeds:
        res = sim.build("car-magnetometer", seed=seed)
        hard, soft = res.mag_calibration()
        cfg = EskfConfig(
            mag_hard_iron_ut=hard,
            mag_soft_iron=soft,
            mag_declination_rad=math.radians(res.config.mag.declination_deg),
        )
        df = run_batch(EskfEngine(cfg), Log(gnss=res.gnss, imu=res.imu, mag=res.mag))
        tr = res.truth
        t = df.t.to_numpy()
        ok = t > 2.0
        rms = []
        for c in ("roll", "pitch", "yaw"):
            e = df[c].to_numpy()[ok] - np.interp(t[ok], tr.t, np.unwrap(tr[c].to_numpy()))
            e = (e + np.pi) % (2 * np.pi) - np.pi
            rms.append(math.degrees(float(np.sqrt(np.mean(e**2)))))
        err = track_errors(df, tr)
        gap = (err.t >= 170.0) & (err.t <= 175.0)
        lines.append(f"| {seed} | {rms[0]:.2f} | {rms[1]:.2f} | {rms[2]:.2f} | {err.h_err[gap].max():.2f} |")
    return lines


def nees(n_seeds: int) -> list[str]:
    modelled = {"imu.acc_misalignment_pct": 0.0, "imu.gyro_misalignment_pct": 0.0}
    out = []
    for label, extra in (
        ("MPU-6050 preset", {}),
        ("MPU-6050 without cross-axis errors (the filter still assumes them: conservative)", modelled),
    ):
        runs, nis = [], []
        for seed in range(n_seeds):
            res = sim.build(
                "car-tunnel", seed=seed, overrides={"duration_s": 90.0, "gnss.outages_s": (), **extra}
            )
            c = res.config
            C_vb = euler_to_dcm(c.mount_roll_rad, c.mount_pitch_rad, c.mount_yaw_rad)
            tt = res.truth.t.to_numpy()
            tr = res.truth
            eng = EskfEngine(EskfConfig())
            vals, t_next = [], 45.0
            for s in iter_samples(Log(gnss=res.gnss, imu=res.imu, mag=res.mag)):
                eng.step(s)
                if isinstance(s, GnssSample) or s.t < t_next:
                    continue
                t_next += 1.0
                eng._propagate_cov()
                row = tr.iloc[int(np.argmin(np.abs(tt - s.t)))]
                C_nb = euler_to_dcm(row.roll, row.pitch, row.yaw) @ C_vb
                dx = np.concatenate(
                    [
                        eng.frame.to_ned(row.lat, row.lon, row.height)  # the engine's frame
                        - eng.nom.p_n
                        - eng.nom.v_n * (row.t - s.t),
                        row[["vn", "ve", "vd"]].to_numpy(float) - eng.nom.v_n,
                        dcm_to_rotvec(C_nb @ eng.nom.C_nb.T),
                    ]
                )
                P = eng.P[:9, :9]
                vals.append(
                    [
                        float(dx[i : i + 3] @ np.linalg.solve(P[i : i + 3, i : i + 3], dx[i : i + 3]))
                        for i in (0, 3, 6)
                    ]
                    + [float(dx @ np.linalg.solve(P, dx))]
                )
            runs.append(np.array(vals))
            nis += [r[1] / r[2] for r in eng.nis_log["gnss_position"][10:]]
            nis_v = [r[1] / r[2] for r in eng.nis_log["gnss_velocity"][10:]]
        L = min(len(r) for r in runs)
        a = np.mean([r[:L] for r in runs], axis=0).mean(axis=0)
        lo, hi = chi2.ppf([0.025, 0.975], 9 * n_seeds) / n_seeds
        out.append(
            f"| {label} | {n_seeds} | {a[0]:.1f} | {a[1]:.1f} | {a[2]:.1f} | {a[3]:.1f} | [{lo:.2f}, {hi:.2f}] | "
            f"{np.mean(nis):.2f} | {np.mean(nis_v):.2f} |"
        )
    head = [
        "| IMU errors | runs | ANEES pos (3) | vel (3) | att (3) | all (9) | 95 % band (9 dof) | GNSS pos NIS/dof | GNSS vel NIS/dof |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    return head + out


DRIVE = Path("/work/shared/datasets/rtklibexplorer_gnss_imu/drive_0708")


def real_drive() -> list[str]:
    """rtklibexplorer drive_0708: 1 Hz GNSS with 2 m correlated noise in, RTK as truth (200 s)."""
    if not DRIVE.exists():
        return ["(drive_0708 not available)"]
    from iotnav.io import ingest

    log = ingest([DRIVE / "gnss_1934_sf.pos", DRIVE / "imu_1934.csv"])
    rtk = log.gnss
    imu = log.imu.copy()
    imu["t"] = imu.t - 0.125  # the author's logging delay
    t0 = float(rtk.t.iloc[0])
    rtk = rtk[rtk.t < t0 + 200.0].reset_index(drop=True)
    imu = imu[(imu.t >= t0) & (imu.t < t0 + 200.0)].reset_index(drop=True)
    rng = np.random.default_rng(5)
    g = rtk.iloc[::4].reset_index(drop=True).copy()
    n = len(g)
    e = np.zeros((n, 2))
    phi = np.exp(-1.0 / 60.0)
    for k in range(1, n):
        e[k] = phi * e[k - 1] + rng.normal(0.0, 2.0 * np.sqrt(1 - phi**2), 2)
    lat0 = np.radians(float(g.lat_deg.iloc[0]))
    g["lat_deg"] = g.lat_deg + np.degrees(e[:, 0] / 6.371e6)
    g["lon_deg"] = g.lon_deg + np.degrees(e[:, 1] / (6.371e6 * np.cos(lat0)))
    for c in ("vn", "ve", "vd"):
        g[c] = g[c] + rng.normal(0.0, 0.1, n)
    g["h_acc_m"], g["v_acc_m"], g["s_acc_mps"] = 2.0 * np.sqrt(2.0), 4.0, 0.12
    g = g[~((g.t >= t0 + 120.0) & (g.t < t0 + 130.0))].reset_index(drop=True)
    cfg = EskfConfig(
        acc_noise_density_ug_rthz=1000.0,
        gyro_noise_density_mdps_rthz=150.0,
        acc_turn_on_bias_mg=20.0,
        gyro_turn_on_bias_dps=1.0,
        acc_scale_factor_pct=0.5,
        gyro_scale_factor_pct=0.5,
    )
    eng = EskfEngine(cfg)
    df = run_batch(eng, Log(gnss=g, imu=imu))
    truth = rtk.rename(columns={"lat_deg": "lat", "lon_deg": "lon", "height_m": "height"})
    err = track_errors(df[df.source != "none"], truth[["t", "lat", "lon", "height"]])
    late = err.t > t0 + 60.0
    gap = (err.t >= t0 + 120.0) & (err.t < t0 + 130.0)
    C_author = euler_to_dcm(*np.radians([180.0, -6.79, 185.35])).T  # passive form in the author's code
    r, p, y = (math.degrees(a) for a in eng.mount_rpy_rad)
    ra, pa, ya = (math.degrees(a) for a in dcm_to_rpy(C_author))
    ang = math.degrees(float(np.linalg.norm(dcm_to_rotvec(eng.nom.C_vb @ C_author.T))))
    return [
        "| horizontal error p95 after 60 s (m) | max error in the 10 s outage (m) | RMS after 60 s (m) |",
        "|---|---|---|",
        f"| {np.percentile(err.h_err[late], 95):.2f} | {err.h_err[gap].max():.2f} | "
        f"{np.sqrt(np.mean(np.asarray(err.h_err[late]) ** 2)):.2f} |",
        "",
        f"Mount found (C_vb, roll/pitch/yaw): {r:.2f} / {p:.2f} / {y:.2f} deg; the author's "
        f"[180, 0, 180] + [0, -6.79, 5.35] deg (passive form) is {ra:.2f} / {pa:.2f} / {ya:.2f} deg: "
        f"{ang:.2f} deg apart.",
    ]


def main() -> None:
    n_seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 20
    t_lines, rate = tunnel([0, 1, 2, 3])
    m_lines = magnetometer([0, 1, 2])
    n_lines = nees(n_seeds)
    md = [
        "# eskf engine",
        "",
        f"Machine: {platform.machine()}, Python {platform.python_version()}; per-IMU step compiled (numba).",
        "",
        "## car-tunnel (MPU-6050, 100 Hz, GNSS 1 Hz): drift at the end of each outage",
        "",
        *t_lines,
        "",
        "## car-magnetometer (calibrated HMC5883L, 6 Hz): attitude RMS (t > 2 s) and the 4 s gap",
        "",
        *m_lines,
        "",
        "## Real drive (rtklibexplorer drive_0708, ICM-45686 on the roof, sensor z up): degraded GNSS",
        "",
        "1 Hz, 2 m correlated noise (60 s), 0.1 m/s velocity noise fed in; RTK as truth; first 200 s;",
        "one 10 s outage at 120 s. The engine finds the mount itself.",
        "",
        *real_drive(),
        "",
        "## Consistency: 90 s car-tunnel runs, NEES sampled at 1 Hz after t = 45 s",
        "",
        *n_lines,
        "",
        f"## Cost: {rate:,.0f} IMU samples/s (median over the car-tunnel runs, 24/30-state ESKF, one core; "
        "includes loading the compiled kernels; the speed section has the per-core figure)",
        "",
        "## Notes",
        "",
        "* Cross-axis coupling (the preset's 2/3 % per element) is not estimated as states: the",
        "  accelerometer's enters as a wider turn-on bias plus acceleration-driven bias noise",
        "  (`acc_misalignment_pct`), the gyro's as rate-driven attitude noise per sensor axis",
        "  (`gyro_misalignment_pct`), both with `cross_axis_corr_time_s` = 5 s (eskf module docstring).",
        "* GNSS error: Gauss-Markov through the receiver's smoothing filter (second order, eskf",
        "  module docstring), horizontal and vertical correlation times apart (`gnss_corr_time_s`,",
        "  `gnss_corr_time_v_s`); the white part of the position noise is the rounding of the",
        "  fixes' format, found in the fixes (`iotnav.engines.gnss_resolution`). NIS/dof in the",
        "  table above; whiteness of the innovations in `tests/test_eskf.py`.",
        "",
    ]
    text = "\n".join(md)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "eskf.md"
        out.write_text(text)


if __name__ == "__main__":
    main()
