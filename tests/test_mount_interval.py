"""The compiled interval step of block 5 (:mod:`iotnav.techniques.mount_interval`) against a reference.

The reference below is the aligner's per-interval step as it was written in numpy before it was
compiled (``MountAligner._close_body``, ``_smooth`` and ``add_gnss`` of main at 9ca3d3f, kept
here as the oracle): the same buffers, the same rows, the same gravity reference, the same
scalar state after every epoch, on random interval streams with body-frame and levelled input,
gaps, invalid speeds, static epochs, both methods and several smoothing lengths.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav.techniques.mount import (
    AS_SQ,
    AS_X,
    AS_Y,
    AV_Y,
    COURSE,
    DT,
    DV,
    IMU_FB,
    IMU_N,
    IMU_R,
    IMU_SQ,
    IMU_SX,
    IMU_SY,
    N_COLS,
    N_IMU,
    R_MEAN,
    V_MEAN,
    MountAligner,
    MountConfig,
    accumulate_body,
    accumulate_levelled,
    levelled,
)


class _Reference:
    """The numpy step of main at 9ca3d3f, on its own copy of the aligner's state."""

    def __init__(self, al: MountAligner) -> None:
        self.c = al.config
        self.sums = al.imu_sums.copy()
        self.ring = al.ring.copy()
        self.ring_ok = al.ring_ok.copy()
        self.f_ref_b = al.f_ref_b.copy()
        self.t_ref = al.t_ref
        self.k_ring = al.k_ring
        self.sm = al.sm.copy()
        self.smooth_w = al.smooth_w
        self.k_sm = al.k_sm
        self.buf = al.buf.copy()
        self.k = al.k
        self.t_prev = al._t_prev
        self.v_prev = al._v_prev
        self.v_start = al._v_start

    def close_body(self, t: float, speed_mps: float, dt: float) -> bool:
        c, s = self.c, self.sums
        n = int(s[IMU_N])
        f_mean = s[IMU_FB : IMU_FB + 3] / n if n > 0 else np.full(3, np.nan)
        ok = (
            n > 0 and math.isfinite(speed_mps) and math.isfinite(self.v_prev) and 0.0 < dt <= c.max_interval_s
        )
        have = False
        if ok and np.all(np.isfinite(self.f_ref_b)) and t - self.t_ref <= c.ref_max_age_s:
            d = f_mean - self.f_ref_b
            u = -self.f_ref_b / float(np.linalg.norm(self.f_ref_b))
            a_s = levelled(d, u)
            s[0] = a_s[0] * n
            s[1] = a_s[1] * n
            s[3] = float(a_s @ a_s) * n
            have = True
        w = self.ring.shape[0]
        i = self.k_ring % w
        if ok:
            self.ring[i, 0:3] = f_mean
            self.ring[i, 3] = n
            self.ring[i, 4] = speed_mps - self.v_prev
            self.ring[i, 5] = dt
            self.ring[i, 6] = 0.5 * (speed_mps + self.v_prev) * s[2] / n
        self.ring_ok[i] = ok
        self.k_ring += 1
        if self.k_ring >= w and bool(self.ring_ok.all()):
            T = float(self.ring[:, 5].sum())
            a_long = float(self.ring[:, 4].sum()) / T
            a_lat = float((self.ring[:, 6] * self.ring[:, 5]).sum()) / T
            wts = self.ring[:, 3]
            f_bar = (self.ring[:, 0:3] * wts[:, None]).sum(axis=0) / wts.sum()
            spread = float(np.sqrt(((self.ring[:, 0:3] - f_bar) ** 2).sum(axis=1).max()))
            if math.hypot(a_long, a_lat) < c.ref_max_accel_mps2 and spread < c.ref_max_spread_mps2:
                self.f_ref_b = f_bar
                self.t_ref = t
        s[IMU_FB : IMU_FB + 3] = 0.0
        return have

    def smooth(self, raw: np.ndarray) -> np.ndarray | None:
        w = self.smooth_w
        if w.size == 1:
            return raw
        self.sm[:-1] = self.sm[1:]
        self.sm[-1] = raw
        self.k_sm += 1
        if self.k_sm < w.size:
            return None
        sw = float(w.sum())
        row = (w[:, None] * self.sm).sum(axis=0) / sw
        row[DV] = float(w @ self.sm[:, DV]) / sw
        row[DT] = float(w @ self.sm[:, DT]) / sw
        row[COURSE] = raw[COURSE]
        row[N_IMU] = float(self.sm[:, N_IMU].sum())
        row[AS_SQ] = float(row[AS_X] ** 2 + row[AS_Y] ** 2) * row[N_IMU]
        return row

    def add_gnss(
        self, t: float, speed_mps: float, course_rad: float, course_valid: bool, static: bool
    ) -> bool:
        """One epoch; True when the buffer became full (the aligner evaluates it then)."""
        c, s = self.c, self.sums
        ok_prev = math.isfinite(self.v_prev)
        dt = t - self.t_prev
        have_acc = self.close_body(t, speed_mps, dt) if s[5] != 0.0 else True
        n = int(s[IMU_N])
        good = (
            have_acc
            and ok_prev
            and math.isfinite(speed_mps)
            and (course_valid or not (c.require_course or c.method == "paper"))
            and not static
            and n > 0
            and 0.0 < dt <= c.max_interval_s
            and min(speed_mps, self.v_prev) >= c.min_speed_mps
        )
        full = False
        if good:
            if self.k == 0:
                self.v_start = self.v_prev
            raw = np.empty(N_COLS)
            raw[AS_X] = s[0] / n
            raw[AS_Y] = s[1] / n
            raw[DV] = speed_mps - self.v_prev
            raw[DT] = dt
            raw[V_MEAN] = 0.5 * (speed_mps + self.v_prev)
            raw[R_MEAN] = s[2] / n
            raw[COURSE] = course_rad
            raw[N_IMU] = n
            raw[AS_SQ] = s[3]
            raw[AV_Y] = raw[V_MEAN] * raw[R_MEAN]
            row = raw if c.method == "paper" else self.smooth(raw)
            if row is not None:
                self.buf[self.k] = row
                self.k += 1
                if self.k == self.buf.shape[0]:
                    full = True
                    self.k = 0
        else:
            self.k_sm = 0
            if c.method == "paper":
                self.k = 0
        s[0:4] = 0.0
        s[IMU_N] = 0.0
        self.t_prev = t
        self.v_prev = speed_mps if math.isfinite(speed_mps) else math.nan
        return full


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.allclose(a, b, rtol=1e-12, atol=1e-12, equal_nan=True))


@pytest.mark.parametrize(
    ("method", "smooth_epochs", "body", "seed"),
    [
        ("lsq", 3, True, 0),
        ("lsq", 1, True, 1),
        ("lsq", 4, False, 2),
        ("paper", 1, True, 3),
        ("paper", 3, False, 4),
    ],
)
def test_compiled_interval_step_equals_the_numpy_reference(
    method: str, smooth_epochs: int, body: bool, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    # buffers never evaluated here (the evaluation is the same Python code before and after):
    # a buffer longer than the stream, and no one-off end
    cfg = MountConfig(method=method, smooth_epochs=smooth_epochs, buffer_epochs=10_000, ref_window_epochs=4)  # type: ignore[arg-type]
    al = MountAligner(cfg)
    if body:
        # a gravity reference to start from (sensor z down, slightly tilted), as after a static start
        al.set_gravity_reference(np.array([0.3, -0.2, -9.79]), 0.0)
    ref = _Reference(al)
    t, v = 0.0, 6.0
    n_rows = n_refreshed = 0
    for _ in range(600):
        # 3 s: a gap beyond max_interval_s; calm stretches (constant speed, no turn, no shake)
        # refresh the gravity reference
        dt = float(rng.choice([1.0] * 16 + [0.2, 3.0]))
        t += dt
        calm = (t // 40.0) % 2 == 0
        if not calm:
            v = min(max(1.0, v + float(rng.normal(0.0, 0.4))), 12.0)  # mostly above min_speed_mps
        speed = math.nan if rng.random() < 0.01 else v
        static = bool(rng.random() < 0.02)
        valid = bool(rng.random() < 0.97)
        for _ in range(int(rng.integers(0, 12)) if rng.random() < 0.05 else 10):
            r = float(rng.normal(0.0, 0.001 if calm else 0.2))
            if body:
                f = np.array([0.3, -0.2, -9.79]) + rng.normal(0.0, 0.001 if calm else 0.8, 3)
                accumulate_body(al.imu_sums, float(f[0]), float(f[1]), float(f[2]), r)
                accumulate_body(ref.sums, float(f[0]), float(f[1]), float(f[2]), r)
            else:
                a = rng.normal(0.0, 0.8, 2)
                accumulate_levelled(al.imu_sums, float(a[0]), float(a[1]), r)
                accumulate_levelled(ref.sums, float(a[0]), float(a[1]), r)
        k_before = al.k
        f_before = al.f_ref_b.copy()
        course = float(rng.uniform(-math.pi, math.pi))
        assert al.add_gnss(t, speed, course, valid, static) is None
        ref.add_gnss(t, speed, course, valid, static)
        n_rows += al.k > k_before
        n_refreshed += not _close(f_before, al.f_ref_b)
        assert (al.k, al.k_sm, al.k_ring) == (ref.k, ref.k_sm, ref.k_ring)
        assert _close(
            np.array([al._t_prev, al._v_prev, al._v_start, al.t_ref]),
            np.array([ref.t_prev, ref.v_prev, ref.v_start, ref.t_ref]),
        )
        assert _close(al.buf[: al.k], ref.buf[: ref.k])
        assert _close(al.imu_sums, ref.sums) and _close(al.f_ref_b, ref.f_ref_b)
        assert _close(al.ring, ref.ring) and bool(np.array_equal(al.ring_ok, ref.ring_ok))
        assert _close(al.sm, ref.sm)
    # the stream exercised what it is for: rows buffered, and (body input) the reference refreshed
    assert n_rows > 100, n_rows
    if body:
        assert n_refreshed > 0
    for name in (IMU_SX, IMU_SY, IMU_R, IMU_SQ):
        assert al.imu_sums[name] == 0.0
