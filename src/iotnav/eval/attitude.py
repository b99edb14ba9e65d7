"""Attitude benchmark on BROAD: metrics, frame conversion, filter adapters and the runner.

Metric (Laidig et al. 2021, "BROAD -- A Benchmark for Robust Inertial Orientation Estimation",
Data 6(7):72, and its ``example_code/broad_utils.py``), for estimated and reference
orientations ``q_est``, ``q_ref`` (sensor -> ENU, scalar first):

    q_err = q_est (x) q_ref^-1                 (error expressed in the earth frame)
    total       = 2 acos(|w|)
    heading     = 2 atan(|z / w|)              (rotation about the vertical)
    inclination = 2 acos(sqrt(w^2 + z^2))      (the remaining, tilt part)

each reduced to an RMSE in degrees over the samples flagged ``movement``, ignoring NaN
reference rows. Evaluation protocol (BROAD's own example code): 9-axis estimates are scored
raw, with no alignment of any kind; 6-axis estimates have no absolute heading, so their
inclination is scored raw and their total/heading errors after removing **one constant heading
offset per trial and filter** (the circular mean of the per-sample heading error over the scored
samples) -- upstream never scores 6-axis filters, this is the README's stated option.

Frames. BROAD's ``opt_quat`` maps sensor vectors into ENU; iotnav's ``q_nb`` maps them into
NED. The conversion is stated once here: ``q_enu_b = Q_ENU_NED (x) q_nb`` with
``Q_ENU_NED = [0, 1/sqrt(2), 1/sqrt(2), 0]`` (a half turn about the bisector of North and
East, which swaps x and y and flips z; it is its own inverse up to sign), see
:func:`ned_to_enu_quat` and :func:`enu_to_ned_quat`.

Filters are adapters with one signature, ``fn(trial) -> q_enu_b (N, 4)``, collected as
:class:`FilterSpec`. Peer packages (``vqf``, ``imufusion``, ``ahrs``) are imported lazily, so
this module imports without them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from iotnav.techniques.ahrs_eskf import (
    AhrsEskfConfig,
    dcm_to_quat,
    default_config,
    quat_conjugate,
    quat_multiply,
    run_ahrs_eskf,
)

FloatArray = npt.NDArray[np.float64]

#: ``q_enu_ned``: rotation taking NED vectors to ENU (and, up to sign, back).
Q_ENU_NED = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])
#: ``q_enu_nwu``: rotation taking North-West-Up vectors to ENU (+90 deg about Up).
Q_ENU_NWU = np.array([math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)])


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------


def ned_to_enu_quat(q_nb: FloatArray) -> FloatArray:
    """``q_nb`` (b -> NED) to ``q_enu_b`` (b -> ENU), ``(..., 4)`` scalar first."""
    return quat_multiply(Q_ENU_NED, q_nb)


def enu_to_ned_quat(q_enu_b: FloatArray) -> FloatArray:
    """``q_enu_b`` (b -> ENU) to ``q_nb`` (b -> NED), ``(..., 4)`` scalar first."""
    return quat_multiply(quat_conjugate(Q_ENU_NED), q_enu_b)


def quat_to_euler_ned(q_nb: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Roll, pitch, yaw (rad, ZYX; yaw from North towards East) of ``q_nb`` ``(N, 4)``."""
    q = np.asarray(q_nb, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


# --------------------------------------------------------------------------------------------
# Metric
# --------------------------------------------------------------------------------------------


def error_quat(q_est: FloatArray, q_ref: FloatArray) -> FloatArray:
    """``q_err = q_est (x) q_ref^-1`` (earth-frame error), both normalised, ``(N, 4)``."""
    a = np.asarray(q_est, dtype=float)
    b = np.asarray(q_ref, dtype=float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    e = quat_multiply(a, quat_conjugate(b))
    return e / np.linalg.norm(e, axis=-1, keepdims=True)


def total_error(q_err: FloatArray) -> FloatArray:
    """Total rotation angle of an error quaternion, rad: ``2 acos(|w|)``."""
    return 2.0 * np.arccos(np.clip(np.abs(q_err[..., 0]), 0.0, 1.0))


def heading_error(q_err: FloatArray) -> FloatArray:
    """Heading (vertical-axis) error, rad: ``2 atan(|z / w|)``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return 2.0 * np.arctan(np.abs(q_err[..., 3] / q_err[..., 0]))


def inclination_error(q_err: FloatArray) -> FloatArray:
    """Inclination (tilt) error, rad: ``2 acos(sqrt(w^2 + z^2))``."""
    return 2.0 * np.arccos(np.clip(np.sqrt(q_err[..., 0] ** 2 + q_err[..., 3] ** 2), 0.0, 1.0))


def _rmse_deg(e: FloatArray) -> float:
    return float(np.degrees(np.sqrt(np.nanmean(e**2))))


@dataclass(frozen=True)
class AttitudeRmse:
    """BROAD's RMSE triple, degrees, plus the heading offset removed (6-axis), degrees."""

    total_deg: float
    heading_deg: float
    inclination_deg: float
    heading_offset_deg: float = 0.0


def remove_heading_offset(
    q_est: FloatArray, q_ref: FloatArray, mask: npt.NDArray[np.bool_]
) -> tuple[FloatArray, float]:
    """Rotate ``q_est`` about the earth vertical by the constant that best matches ``q_ref``.

    The offset is the circular mean of the signed heading error ``2 atan2(z, w)`` (``w >= 0``)
    of ``q_err`` over ``mask`` and the finite reference rows.

    Returns
    -------
    q_aligned : numpy.ndarray
        ``Rz(-offset) (x) q_est``, ``(N, 4)``.
    offset_rad : float
        The removed offset, rad.
    """
    e = error_quat(q_est, q_ref)
    e = e * np.where(e[:, :1] < 0, -1.0, 1.0)
    psi = 2.0 * np.arctan2(e[:, 3], e[:, 0])
    sel = mask & np.isfinite(psi)
    off = float(np.arctan2(np.mean(np.sin(psi[sel])), np.mean(np.cos(psi[sel]))))
    rz = np.array([math.cos(-off / 2), 0.0, 0.0, math.sin(-off / 2)])
    return quat_multiply(rz, q_est), off


def attitude_rmse(
    q_est: FloatArray, q_ref: FloatArray, movement: npt.NDArray[np.bool_], remove_heading: bool = False
) -> AttitudeRmse:
    """BROAD's total, heading and inclination RMSE (degrees) over the ``movement`` samples.

    Parameters
    ----------
    q_est, q_ref : numpy.ndarray
        ``(N, 4)`` estimated and reference orientations in the same earth frame, scalar
        first; NaN reference rows are ignored.
    movement : numpy.ndarray
        ``(N,)`` bool, the samples to score.
    remove_heading : bool
        Remove one constant heading offset first (6-axis filters).

    Returns
    -------
    AttitudeRmse
        RMSEs in degrees.
    """
    mask = np.asarray(movement, dtype=bool)
    off = 0.0
    if remove_heading:
        q_est, off = remove_heading_offset(q_est, q_ref, mask)
    e = error_quat(q_est, q_ref)[mask]
    return AttitudeRmse(
        _rmse_deg(total_error(e)),
        _rmse_deg(heading_error(e)),
        _rmse_deg(inclination_error(e)),
        math.degrees(off),
    )


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuRecording:
    """A 9-axis IMU recording, with BROAD's truth when present.

    Attributes
    ----------
    name : str
        Trial name (file stem).
    fs_hz : float
        Sampling rate, Hz.
    gyr_b, acc_b, mag_b : numpy.ndarray
        ``(N, 3)`` rad/s, m/s^2, µT in the sensor frame.
    q_ref_enu : numpy.ndarray or None
        ``(N, 4)`` truth, sensor -> ENU, scalar first (NaN rows where tracking was lost).
    movement : numpy.ndarray or None
        ``(N,)`` bool, samples to score.
    """

    name: str
    fs_hz: float
    gyr_b: FloatArray
    acc_b: FloatArray
    mag_b: FloatArray | None
    q_ref_enu: FloatArray | None = None
    movement: npt.NDArray[np.bool_] | None = None

    def segment(self, start: int, stop: int) -> ImuRecording:
        """The samples ``start:stop`` as a new recording."""
        s = slice(start, stop)
        return ImuRecording(
            self.name,
            self.fs_hz,
            self.gyr_b[s],
            self.acc_b[s],
            None if self.mag_b is None else self.mag_b[s],
            None if self.q_ref_enu is None else self.q_ref_enu[s],
            None if self.movement is None else self.movement[s],
        )


def load_broad(path: str | Path) -> ImuRecording:
    """Load one BROAD trial converted to ``.npz`` (keys ``imu_gyr``, ``imu_acc``, ``imu_mag``,
    ``opt_quat``, ``movement``, ``sampling_rate``)."""
    p = Path(path)
    with np.load(p) as d:
        missing = {"imu_gyr", "imu_acc", "sampling_rate"} - set(d.files)
        if missing:
            raise ValueError(f"{p}: not a BROAD .npz, missing keys {sorted(missing)}")
        return ImuRecording(
            name=p.stem,
            fs_hz=float(d["sampling_rate"]),
            gyr_b=np.ascontiguousarray(d["imu_gyr"], dtype=float),
            acc_b=np.ascontiguousarray(d["imu_acc"], dtype=float),
            mag_b=np.ascontiguousarray(d["imu_mag"], dtype=float) if "imu_mag" in d.files else None,
            q_ref_enu=np.asarray(d["opt_quat"], dtype=float) if "opt_quat" in d.files else None,
            movement=np.asarray(d["movement"], dtype=bool) if "movement" in d.files else None,
        )


# --------------------------------------------------------------------------------------------
# Filters
# --------------------------------------------------------------------------------------------

FilterFn = Callable[[ImuRecording], FloatArray]


@dataclass(frozen=True)
class FilterSpec:
    """A filter to benchmark.

    Attributes
    ----------
    name : str
        Row label.
    fn : callable
        ``fn(recording) -> q_enu_b (N, 4)``.
    nine_axis : bool
        True when the filter uses the magnetometer (scored raw); False for 6-axis (heading
        offset removed for total/heading).
    params : dict
        Parameters used, echoed in the results.
    """

    name: str
    fn: FilterFn
    nine_axis: bool
    params: Mapping[str, object] = field(default_factory=dict)


def initial_quat_enu(acc_b: FloatArray, mag_b: FloatArray | None) -> FloatArray:
    """``q_enu_b`` from one accelerometer and (optionally) magnetometer sample (TRIAD)."""
    up_b = np.asarray(acc_b, dtype=float) / np.linalg.norm(acc_b)
    ref = np.array([0.0, 1.0, 0.0]) if mag_b is None else np.asarray(mag_b, dtype=float)
    east_b = np.cross(ref, up_b)
    east_b /= np.linalg.norm(east_b)
    north_b = np.cross(up_b, east_b)
    return dcm_to_quat(np.vstack([east_b, north_b, up_b]))


def _nwu_from_enu(q_enu_b: FloatArray) -> FloatArray:
    return quat_multiply(quat_conjugate(Q_ENU_NWU), q_enu_b)


def run_eskf(rec: ImuRecording, config: AhrsEskfConfig | None = None, nine_axis: bool = True) -> FloatArray:
    """iotnav's :mod:`~iotnav.techniques.ahrs_eskf`; returns ``q_enu_b``."""
    c = replace(config or default_config(nine_axis), use_mag=nine_axis)
    res = run_ahrs_eskf(rec.gyr_b, rec.acc_b, rec.mag_b if nine_axis else None, rec.fs_hz, c)
    return ned_to_enu_quat(res.q_nb)


def run_vqf(rec: ImuRecording, nine_axis: bool = True, **params: float) -> FloatArray:
    """VQF (Laidig and Seel 2023, PyPI ``vqf``), online (causal) class; returns ``q_enu_b``.

    VQF's 9-axis output is sensor -> ENU; its 6-axis output has an arbitrary heading.
    """
    from vqf import VQF

    v = VQF(1.0 / rec.fs_hz, **params) if params else VQF(1.0 / rec.fs_hz)
    mag = rec.mag_b if nine_axis and rec.mag_b is not None else None
    out = v.updateBatch(np.ascontiguousarray(rec.gyr_b), np.ascontiguousarray(rec.acc_b), mag)
    return np.asarray(out["quat9D" if mag is not None else "quat6D"], dtype=float)


def run_imufusion(
    rec: ImuRecording,
    nine_axis: bool = True,
    gain: float | None = None,
    acceleration_rejection_deg: float | None = None,
    magnetic_rejection_deg: float | None = None,
    rejection_timeout_s: float | None = None,
    gyroscope_range_deg_s: float | None = None,
    bias_correction: bool = False,
) -> FloatArray:
    """x-io Fusion AHRS (PyPI ``imufusion``); returns ``q_enu_b``.

    Fusion takes deg/s and g; ``None`` keeps the library default of a setting.
    ``bias_correction`` runs Fusion's gyroscope offset (``Bias``) object before the AHRS, as
    in Fusion's advanced example. imufusion 1.3.3 outputs North-West-Up whatever
    ``convention`` is set to (checked on BROAD: asking for ENU still gives NWU), so the
    default NWU is requested and rotated into ENU here.
    """
    import imufusion

    s = imufusion.AhrsSettings(sample_rate=rec.fs_hz, convention=imufusion.CONVENTION_NWU)
    if gain is not None:
        s.gain = gain
    if acceleration_rejection_deg is not None:
        s.acceleration_rejection = acceleration_rejection_deg
    if magnetic_rejection_deg is not None:
        s.magnetic_rejection = magnetic_rejection_deg
    if rejection_timeout_s is not None:
        s.rejection_timeout = rejection_timeout_s
    if gyroscope_range_deg_s is not None:
        s.gyroscope_range = gyroscope_range_deg_s
    ahrs = imufusion.Ahrs()
    ahrs.set_settings(s)
    bias = None
    if bias_correction:
        bias = imufusion.Bias()
        bias.set_settings(imufusion.BiasSettings(sample_rate=rec.fs_hz))
    gyr = np.degrees(rec.gyr_b)
    acc = rec.acc_b / 9.80665
    mag = rec.mag_b
    n = len(gyr)
    q = np.empty((n, 4))
    use_mag = nine_axis and mag is not None
    for k in range(n):
        g = bias.update(gyr[k]) if bias is not None else gyr[k]
        if use_mag and mag is not None:
            ahrs.update(g, acc[k], mag[k])
        else:
            ahrs.update_no_magnetometer(g, acc[k])
        q[k] = ahrs.get_quaternion()
    return quat_multiply(Q_ENU_NWU, q)


def run_ahrs_madgwick(rec: ImuRecording, nine_axis: bool = True, gain: float | None = None) -> FloatArray:
    """Madgwick's filter from PyPI ``ahrs`` (NWU earth frame), started like BROAD's example code
    from the accelerometer/magnetometer orientation of the first sample; returns ``q_enu_b``.

    ``gain=None`` keeps the package defaults (0.041 9-axis, 0.033 6-axis).
    """
    from ahrs.filters import Madgwick

    mag = rec.mag_b if nine_axis else None
    q0 = _nwu_from_enu(initial_quat_enu(rec.acc_b[0], mag[0] if mag is not None else None))
    kw: dict[str, object] = {"frequency": rec.fs_hz, "q0": q0}
    if gain is not None:
        kw["gain"] = gain
    f = Madgwick(gyr=rec.gyr_b, acc=rec.acc_b, mag=mag, **kw)
    return quat_multiply(Q_ENU_NWU, np.asarray(f.Q, dtype=float))


def run_ahrs_mahony(
    rec: ImuRecording, nine_axis: bool = True, k_p: float | None = None, k_i: float | None = None
) -> FloatArray:
    """Mahony's filter from PyPI ``ahrs``; returns ``q_enu_b``.

    ``ahrs`` 0.4's Mahony uses an earth frame with gravity on +z and magnetic North on +y
    (i.e. ENU) for its magnetometer reference, unlike its Madgwick (NWU); both are started from
    the first sample's accelerometer/magnetometer orientation. ``None`` keeps the package
    defaults (k_P = 1, k_I = 0.3).
    """
    from ahrs.filters import Mahony

    mag = rec.mag_b if nine_axis else None
    q0 = initial_quat_enu(rec.acc_b[0], mag[0] if mag is not None else None)
    kw: dict[str, object] = {"frequency": rec.fs_hz, "q0": q0}
    if k_p is not None:
        kw["k_P"] = k_p
    if k_i is not None:
        kw["k_I"] = k_i
    f = Mahony(gyr=rec.gyr_b, acc=rec.acc_b, mag=mag, **kw)
    return np.asarray(f.Q, dtype=float)


def run_cascade(rec: ImuRecording, nine_axis: bool = False, rest: bool = True) -> FloatArray:
    """Adapter for the Forno/Zihajehzadeh cascaded KF (:mod:`iotnav.techniques.cascade`).

    The cascade gives ``C_nb`` (NED) per sample (:func:`~iotnav.techniques.cascade.run_cascade_imu`,
    the same compiled step as ``CascadeKF.step``); it is 6-axis here (its yaw KF is aided by GPS
    course, not used on BROAD). Its static flag, which enables the gyro-bias filter, is
    ``ahrs_eskf``'s rest detector (:func:`~iotnav.techniques.ahrs_eskf.detect_rest`: gyro and
    accelerometer quiet over a window) when ``rest`` is True, else never static.
    """
    from scipy.spatial.transform import Rotation

    from iotnav.techniques.ahrs_eskf import detect_rest
    from iotnav.techniques.cascade import run_cascade_imu

    static = detect_rest(rec.gyr_b, rec.acc_b, rec.fs_hz) if rest else np.zeros(len(rec.gyr_b), bool)
    C = run_cascade_imu(rec.acc_b, rec.gyr_b, rec.fs_hz, static, 9.81)
    xyzw = Rotation.from_matrix(C).as_quat()
    return ned_to_enu_quat(np.column_stack([xyzw[:, 3], xyzw[:, :3]]))


def cascade_available() -> bool:
    """True when :mod:`iotnav.techniques.cascade` imports and exposes ``CascadeKF``."""
    try:
        from iotnav.techniques.cascade import CascadeKF  # noqa: F401
    except Exception:
        return False
    return True


#: BROAD-tuned parameters of the upstream baselines (README of the dataset).
BROAD_MADGWICK_BETA = 0.12
BROAD_MAHONY_KP = 0.74
BROAD_MAHONY_KI = 0.0012


def peer_filters(nine_axis: bool = True) -> list[FilterSpec]:
    """The published filters at documented defaults and, where BROAD gives them, tuned values."""
    ax = "9D" if nine_axis else "6D"
    out = [
        FilterSpec(f"vqf {ax}", lambda r: run_vqf(r, nine_axis), nine_axis, {"defaults": True}),
        FilterSpec(f"imufusion {ax}", lambda r: run_imufusion(r, nine_axis), nine_axis, {"defaults": True}),
        FilterSpec(
            f"imufusion {ax} (example settings)",
            lambda r: run_imufusion(r, nine_axis, 0.5, 10.0, 10.0, 5.0, 2000.0, True),
            nine_axis,
            {
                "gain": 0.5,
                "acc_rej_deg": 10,
                "mag_rej_deg": 10,
                "timeout_s": 5,
                "gyr_range_dps": 2000,
                "bias": True,
            },
        ),
        FilterSpec(
            f"ahrs Madgwick {ax}", lambda r: run_ahrs_madgwick(r, nine_axis), nine_axis, {"defaults": True}
        ),
        FilterSpec(
            f"ahrs Mahony {ax}", lambda r: run_ahrs_mahony(r, nine_axis), nine_axis, {"defaults": True}
        ),
    ]
    if nine_axis:
        out += [
            FilterSpec(
                f"ahrs Madgwick {ax} (BROAD β=0.12)",
                lambda r: run_ahrs_madgwick(r, nine_axis, BROAD_MADGWICK_BETA),
                nine_axis,
                {"beta": BROAD_MADGWICK_BETA},
            ),
            FilterSpec(
                f"ahrs Mahony {ax} (BROAD Kp=0.74 Ki=0.0012)",
                lambda r: run_ahrs_mahony(r, nine_axis, BROAD_MAHONY_KP, BROAD_MAHONY_KI),
                nine_axis,
                {"k_p": BROAD_MAHONY_KP, "k_i": BROAD_MAHONY_KI},
            ),
        ]
    return out


def iotnav_filters(nine_axis: bool = True, config: AhrsEskfConfig | None = None) -> list[FilterSpec]:
    """iotnav's attitude filters (the ESKF; the cascade once it is importable, 6-axis)."""
    c = replace(config or default_config(nine_axis), use_mag=nine_axis)
    ax = "9D" if nine_axis else "6D"
    out = [FilterSpec(f"iotnav ahrs_eskf {ax}", lambda r: run_eskf(r, c, nine_axis), nine_axis, c.as_dict())]
    if not nine_axis and cascade_available():
        out.append(
            FilterSpec("iotnav cascade 6D (rest detector)", run_cascade, False, {"static": "detect_rest"})
        )
        out.append(
            FilterSpec(
                "iotnav cascade 6D (never static)",
                lambda r: run_cascade(r, rest=False),
                False,
                {"static": False},
            )
        )
    return out


def available_filters() -> dict[str, FilterSpec]:
    """Every filter by a short CLI name (``eskf``, ``eskf6``, ``vqf``, ``madgwick``, ...)."""
    return {
        "eskf": iotnav_filters(True)[0],
        "eskf6": iotnav_filters(False)[0],
        "vqf": peer_filters(True)[0],
        "vqf6": peer_filters(False)[0],
        "imufusion": peer_filters(True)[1],
        "madgwick": peer_filters(True)[5],
        "mahony": peer_filters(True)[6],
        "cascade": FilterSpec(
            "iotnav cascade 6D (rest detector)", run_cascade, False, {"static": "detect_rest"}
        ),
    }


def score(rec: ImuRecording, q_enu_b: FloatArray, nine_axis: bool) -> AttitudeRmse:
    """BROAD metrics of an estimate of ``rec`` (raw for 9-axis, heading offset removed for 6-axis)."""
    if rec.q_ref_enu is None or rec.movement is None:
        raise ValueError(f"{rec.name}: no reference orientation to score against")
    return attitude_rmse(q_enu_b, rec.q_ref_enu, rec.movement, remove_heading=not nine_axis)


def evaluate(rec: ImuRecording, spec: FilterSpec) -> AttitudeRmse:
    """Run ``spec`` on ``rec`` and score it."""
    return score(rec, spec.fn(rec), spec.nine_axis)


# --------------------------------------------------------------------------------------------
# Synthetic sustained linear acceleration (robustness case built on a real trial)
# --------------------------------------------------------------------------------------------


def translation_strokes(
    active: npt.NDArray[np.bool_],
    fs_hz: float,
    seed: int = 0,
    accel_m_s2: tuple[float, float] = (2.0, 5.0),
    half_s: tuple[float, float] = (0.4, 1.5),
    pause_s: tuple[float, float] = (0.2, 1.0),
) -> FloatArray:
    """Linear acceleration (ENU, m/s^2) of fast translation strokes while ``active``.

    Each stroke is bang-bang along a random direction (uniform on the sphere): ``+A`` for
    ``T`` seconds then ``-A`` for ``T`` seconds, so the velocity returns to zero and the
    displacement is ``A T^2``; ``A`` and ``T`` are drawn uniformly from ``accel_m_s2`` and
    ``half_s``, and a pause drawn from ``pause_s`` follows. A stroke that would run past the end
    of an active stretch is not started.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` linear acceleration in ENU, m/s^2.
    """
    act = np.asarray(active, dtype=bool)
    n = len(act)
    rng = np.random.default_rng(seed)
    a = np.zeros((n, 3))
    k = 0
    while k < n:
        if not act[k]:
            k += 1
            continue
        amp = rng.uniform(*accel_m_s2)
        m = max(1, round(rng.uniform(*half_s) * fs_hz))
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        if k + 2 * m <= n and act[k : k + 2 * m].all():
            a[k : k + m] = amp * u
            a[k + m : k + 2 * m] = -amp * u
            k += 2 * m
        else:
            k += m
        k += round(rng.uniform(*pause_s) * fs_hz)
    return a


def slow_translation(
    active: npt.NDArray[np.bool_], fs_hz: float, amp_m_s2: float = 0.3, period_s: float = 4.0
) -> FloatArray:
    """Linear acceleration (ENU, m/s^2) of a slow back-and-forth translation along East while
    ``active``: ``amp sin(2 pi t / period)`` over each active stretch (a whole number of periods
    fits, so the velocity starts and ends at zero; any remainder is left still)."""
    act = np.asarray(active, dtype=bool)
    a = np.zeros((len(act), 3))
    edges = np.flatnonzero(np.diff(np.concatenate([[0], act.astype(np.int8), [0]])))
    per = round(period_s * fs_hz)
    for start, stop in zip(edges[0::2], edges[1::2], strict=True):
        m = (stop - start) // per * per
        t = np.arange(m) / fs_hz
        a[start : start + m, 0] = amp_m_s2 * np.sin(2.0 * np.pi * t / period_s)
    return a


def _nearest_finite_dcm(q_enu_b: FloatArray, name: str) -> FloatArray:
    """``C_Eb`` per row of a reference with NaN rows (each NaN row takes the nearest finite one)."""
    from iotnav.techniques.ahrs_eskf import quat_to_dcm

    q = np.asarray(q_enu_b, dtype=float)
    ok = np.flatnonzero(np.isfinite(q).all(axis=1))
    if len(ok) == 0:
        raise ValueError(f"{name}: no finite reference orientation")
    idx = np.arange(len(q))
    if len(ok) > 1:
        pos = np.clip(np.searchsorted(ok, idx), 1, len(ok) - 1)
        left, right = ok[pos - 1], ok[pos]
        nearest = np.where(idx - left <= right - idx, left, right)
    else:
        nearest = np.full(len(q), ok[0])
    return quat_to_dcm(q[nearest])


def add_vertical_rotation(rec: ImuRecording, rate_rad_s: FloatArray) -> ImuRecording:
    """A copy of ``rec`` turned on top of its own motion about the ENU vertical at ``rate_rad_s``.

    With ``theta_k`` the integrated rate and ``R_k = Rz(theta_k)`` (ENU), the new truth is
    ``q' = R (x) q``; a rotation about the vertical leaves the earth-frame specific force and
    field unchanged, so ``f_b' = C_b'E C_Eb f_b`` and ``m_b' = C_b'E C_Eb m_b``, and the gyro
    gains the body-frame rate of ``R``: ``omega_b' = omega_b + C_b'E [0, 0, rate]``. NaN
    reference rows stay NaN in the truth; the sensor rotation uses the nearest finite row.
    """
    if rec.q_ref_enu is None:
        raise ValueError(f"{rec.name}: a reference orientation is needed to rotate the recording")
    from iotnav.techniques.ahrs_eskf import quat_to_dcm

    rate = np.asarray(rate_rad_s, dtype=float)
    theta = np.cumsum(rate) / rec.fs_hz
    rz = np.stack([np.cos(theta / 2), np.zeros_like(theta), np.zeros_like(theta), np.sin(theta / 2)], axis=1)
    C_Eb = _nearest_finite_dcm(rec.q_ref_enu, rec.name)
    C_new = np.einsum("kij,kjl->kil", quat_to_dcm(rz), C_Eb)  # C_E'b = R C_Eb
    M = np.einsum("kji,kjl->kil", C_new, C_Eb)  # C_b'E C_Eb

    def turn(v: FloatArray) -> FloatArray:
        return np.einsum("kij,kj->ki", M, v)

    w_E = np.zeros((len(rate), 3))
    w_E[:, 2] = rate
    return ImuRecording(
        rec.name + "+turn",
        rec.fs_hz,
        rec.gyr_b + np.einsum("kji,kj->ki", C_new, w_E),
        turn(rec.acc_b),
        None if rec.mag_b is None else turn(rec.mag_b),
        quat_multiply(rz, rec.q_ref_enu),
        rec.movement,
    )


def add_linear_acceleration(rec: ImuRecording, a_enu: FloatArray) -> ImuRecording:
    """A copy of ``rec`` whose accelerometer also senses the linear acceleration ``a_enu``.

    The specific force gains ``C_bE a_E`` (``a_E`` in ENU, m/s^2), rotated into the sensor frame
    with the recording's reference orientation (rows where the reference is NaN use the
    nearest finite one); gyro, magnetometer and truth are unchanged (a pure translation).
    """
    if rec.q_ref_enu is None:
        raise ValueError(f"{rec.name}: a reference orientation is needed to rotate the acceleration")
    C_Eb = _nearest_finite_dcm(rec.q_ref_enu, rec.name)
    extra_b = np.einsum("kji,kj->ki", C_Eb, np.asarray(a_enu, dtype=float))
    return ImuRecording(
        rec.name + "+translation",
        rec.fs_hz,
        rec.gyr_b,
        rec.acc_b + extra_b,
        rec.mag_b,
        rec.q_ref_enu,
        rec.movement,
    )


def rest_breaks(rec: ImuRecording) -> npt.NDArray[np.bool_]:
    """The samples not flagged ``movement`` between the first and the last that are (the rest
    breaks of a trial, without its initial and final rest)."""
    if rec.movement is None:
        raise ValueError(f"{rec.name}: no movement flags")
    mov = np.asarray(rec.movement, dtype=bool)
    idx = np.flatnonzero(mov)
    out = np.zeros(len(mov), dtype=bool)
    if len(idx):
        out[idx[0] : idx[-1]] = ~mov[idx[0] : idx[-1]]
    return out


def fast_translation_with_rest(
    rec: ImuRecording, seed: int = 1, turn_rad_s: float = math.radians(3.0), slow_amp_m_s2: float = 0.3
) -> ImuRecording:
    """The robustness case: fast translation strokes during ``rec``'s motion, fooled rest in its breaks.

    :func:`translation_strokes` (defaults, ``seed``) while ``movement``; in the
    :func:`rest_breaks`, :func:`slow_translation` (``slow_amp_m_s2``, 4 s period) and a turn about
    the vertical at ``turn_rad_s`` (:func:`add_vertical_rotation`): slow enough that the gyro
    stays within 2 deg/s of its own low-pass, which a gyro-only rest test takes for rest.
    """
    brk = rest_breaks(rec)
    turned = add_vertical_rotation(rec, np.where(brk, turn_rad_s, 0.0))
    a = translation_strokes(rec.movement if rec.movement is not None else brk, rec.fs_hz, seed)
    a += slow_translation(brk, rec.fs_hz, slow_amp_m_s2)
    out = add_linear_acceleration(turned, a)
    return replace(out, name=rec.name + "+fast_translation_with_rest")
