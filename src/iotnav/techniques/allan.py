"""IMU noise characterisation from static logs: Allan deviation and residual RMS.

Dabove et al. (2016) characterise the inertial platforms of two smartphones with a 6-hour static
recording and report the RMS of the static residuals per axis (their Table 2: acceleration in g,
angular rate in rad/s). This module computes that table and, from the same static log, the
Allan deviation and the three IEEE Std 952-1997 noise terms that Kalman filters and simulators
need: the white-noise density, the bias instability and the rate random walk.

Overlapping Allan variance (IEEE Std 952-1997 Annex C; El-Sheimy, Hou and Niu, "Analysis and
modeling of inertial sensors using Allan variance", IEEE TIM 57(1), 2008). For a rate signal
``y_k`` (rad/s or m/s^2) sampled every ``tau_0`` seconds, ``M`` samples, cluster time
``tau = m tau_0``, with the integrated signal ``theta_k = tau_0 * sum_{i<k} y_i``::

    sigma^2(tau) = 1 / (2 tau^2 (M - 2m)) * sum_{k=0}^{M-2m-1} (theta_{k+2m} - 2 theta_{k+m} + theta_k)^2

computed here by ``allantools.oadev`` (frequency-type data). Its link to the two-sided power
spectral density ``S(f)`` of the rate signal is::

    sigma^2(tau) = 4 * integral_0^inf S(f) sin^4(pi f tau) / (pi f tau)^2 df

and the three terms identified here are (IEEE Std 952 Table C.1):

=====================  ========================  ===========================  ==============
term                   PSD ``S(f)``              Allan deviation              log-log slope
=====================  ========================  ===========================  ==============
white noise (ARW/VRW)  ``N^2``                   ``N / sqrt(tau)``            -1/2
bias instability       ``B^2 / (2 pi f)``        ``B sqrt(2 ln 2 / pi)``      0
                                                 ``= 0.664 B``
rate random walk       ``K^2 / (2 pi f)^2``      ``K sqrt(tau / 3)``          +1/2
=====================  ========================  ===========================  ==============

Reading the terms off the curve (the graphical method of IEEE Std 952, made mechanical):

* ``N`` is the value at ``tau = 1 s`` of the slope -1/2 line through the points where the local
  slope is -1/2 (within 0.05; 0.15 if none), i.e. the median of ``sigma(tau) sqrt(tau)`` there.
  For a white sequence of per-sample standard deviation ``s`` at ``f_s`` Hz, ``N = s / sqrt(f_s)``.
* ``B`` is the flat minimum of the curve divided by 0.664. The lowest point is searched among
  the averaging times followed by at least half a decade of curve; the minimum is the vertex of
  a parabola fitted in log-log to the points within one decade of the lowest point (this
  removes the downward bias of taking the single lowest of many noisy points; on a 6-hour log
  the estimate scatters by about 5 % (1 sigma) per axis, the statistical limit of the ADEV at
  tau ~ 100 s). It is only *identified* when the curve after the lowest point has stopped falling (slope of a log-log
  line fit above -0.15; the lowest point itself is used when the parabola is not convex) and
  the curve does not fall faster than slope -3/4 between the white-noise region and the minimum
  (a periodic component such as vibration, IEEE Std 952 "sinusoidal noise"); otherwise the
  lowest value / 0.664 is returned as an upper bound and ``B`` is NaN.
* ``K`` is the value at ``tau = 3 s`` of the slope +1/2 line through the points after the minimum
  whose local slope is +1/2 (within 0.15), NaN when there are fewer than two.

Averaging times run from ``tau_0`` to a tenth of the record (``max_tau_fraction``): beyond that
fewer than ten independent clusters remain. The record length therefore bounds which terms can
be identified: a 30 s static segment gives ``N`` (and only an upper bound on ``B``); the 6-hour
log of Dabove et al. gives ``N`` and ``B``; ``K`` usually needs many hours more.

Units: everything in this module is SI (rad/s, m/s^2, s). :class:`NoiseModel` converts to the
datasheet units its field names carry (deg/s/sqrt(Hz), deg/h, ug/sqrt(Hz), ug, ...) and back.

References
----------
P. Dabove, G. Ghinamo, A. M. Lingua, "Inertial sensors for smartphones navigation",
SpringerPlus 4:834, 2015 (the paper shipped as ``ins-with-image-based-positioning.txt``; cited
in this project as Dabove et al. 2016), section "Data acquired through smartphones and wavelet
filtering", Table 2.
IEEE Std 952-1997, "IEEE Standard Specification Format Guide and Test Procedure for Single-Axis
Interferometric Fiber Optic Gyros", Annex C (Allan variance method).
D. W. Allan, "Statistics of atomic frequency standards", Proc. IEEE 54(2), 1966.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields
from typing import Any

import allantools
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Standard gravity, m/s^2 (the "g" of accelerometer datasheets).
G0_MPS2 = 9.80665
#: ``sigma_floor = BI_FACTOR * B`` for bias instability (sqrt(2 ln 2 / pi)).
BI_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)
#: Averaging time at which the white-noise line is read, s.
N_TAU_S = 1.0
#: Averaging time at which the rate-random-walk line is read, s.
K_TAU_S = 3.0

_DEG = math.pi / 180.0
_UG = 1e-6 * G0_MPS2


@dataclass(frozen=True)
class AllanCurve:
    """An overlapping Allan deviation curve of one axis.

    Attributes
    ----------
    tau_s : ndarray
        Averaging times, s (integer multiples of the sample interval).
    adev : ndarray
        Allan deviation, in the unit of the signal (rad/s or m/s^2).
    adev_err : ndarray
        1-sigma uncertainty of ``adev`` as allantools gives it (``adev / sqrt(n)``).
    n_terms : ndarray
        Number of overlapping second differences averaged at each ``tau_s``.
    """

    tau_s: FloatArray
    adev: FloatArray
    adev_err: FloatArray
    n_terms: FloatArray

    @property
    def slope(self) -> FloatArray:
        """Local log-log slope ``d ln sigma / d ln tau`` (NaN for fewer than 2 points)."""
        if len(self.tau_s) < 2:
            return np.full(len(self.tau_s), np.nan)
        return np.gradient(np.log(self.adev), np.log(self.tau_s))


@dataclass(frozen=True)
class AllanParams:
    """The IEEE Std 952 noise terms of one axis, SI.

    Attributes
    ----------
    noise_density : float
        ``N``: white-noise coefficient, unit/sqrt(Hz) (rad/s/sqrt(Hz) = rad/sqrt(s) for a gyro,
        m/s^2/sqrt(Hz) = m/s/sqrt(s) for an accelerometer). ``sigma(tau) = N / sqrt(tau)``.
    noise_density_identified : bool
        A slope -1/2 region was found (otherwise ``N`` is read at the point whose slope is
        closest to -1/2 and is only indicative).
    bias_instability : float
        ``B`` = ADEV floor / 0.664, unit (rad/s or m/s^2); NaN when the floor was not reached.
    bias_instability_tau_s : float
        Averaging time of the floor, s (NaN when not identified).
    bias_instability_upper_bound : float
        Lowest ADEV / 0.664: an upper bound on ``B`` whether or not it was identified.
    rate_random_walk : float
        ``K``: ``sigma(tau) = K sqrt(tau / 3)``, unit/sqrt(s) (rad/s/sqrt(s), m/s^2/sqrt(s));
        NaN when no slope +1/2 region was found.
    notes : tuple of str
        Why a term is missing or only indicative.
    """

    noise_density: float
    noise_density_identified: bool
    bias_instability: float
    bias_instability_tau_s: float
    bias_instability_upper_bound: float
    rate_random_walk: float
    notes: tuple[str, ...] = ()


def averaging_times(
    n_samples: int, rate_hz: float, per_decade: int = 10, max_tau_fraction: float = 0.1
) -> FloatArray:
    """Log-spaced averaging times, integer multiples of the sample interval.

    Parameters
    ----------
    n_samples : int
        Record length in samples.
    rate_hz : float
        Sample rate, Hz.
    per_decade : int
        Points per decade of ``tau``.
    max_tau_fraction : float
        Longest ``tau`` as a fraction of the record duration.

    Returns
    -------
    ndarray
        Unique averaging times, s, from ``1 / rate_hz`` upwards.
    """
    m_max = max(1, math.floor(max_tau_fraction * n_samples))
    n_pts = max(2, math.ceil(per_decade * math.log10(max(m_max, 1))) + 1)
    m = np.unique(np.round(np.logspace(0.0, math.log10(m_max), n_pts)).astype(np.int64))
    return m.astype(np.float64) / rate_hz


def allan_deviation(
    y: npt.ArrayLike, rate_hz: float, per_decade: int = 10, max_tau_fraction: float = 0.1
) -> AllanCurve:
    """Overlapping Allan deviation of a rate signal (allantools ``oadev``, frequency data).

    Parameters
    ----------
    y : array_like, shape (n,)
        Evenly sampled rate signal (rad/s or m/s^2) of a static sensor.
    rate_hz : float
        Sample rate, Hz.
    per_decade : int
        Averaging times per decade.
    max_tau_fraction : float
        Longest averaging time as a fraction of the record (default a tenth).

    Returns
    -------
    AllanCurve
        Averaging times (s) and Allan deviation (unit of ``y``).
    """
    x = np.asarray(y, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"expected a 1-D signal, got shape {x.shape}")
    if len(x) < 20:
        raise ValueError(f"{len(x)} samples are too few for an Allan deviation (need at least 20)")
    if not np.all(np.isfinite(x)):
        raise ValueError("the signal holds NaN or infinite samples")
    taus = averaging_times(len(x), rate_hz, per_decade, max_tau_fraction)
    tau_out, ad, ade, ns = allantools.oadev(x, rate=rate_hz, data_type="freq", taus=taus)
    return AllanCurve(
        tau_s=np.asarray(tau_out, dtype=np.float64),
        adev=np.asarray(ad, dtype=np.float64),
        adev_err=np.asarray(ade, dtype=np.float64),
        n_terms=np.asarray(ns, dtype=np.float64),
    )


def _first_run(mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.intp]:
    """Indices of the first contiguous run of True in ``mask`` (empty if none)."""
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return idx
    breaks = np.flatnonzero(np.diff(idx) > 1)
    end = breaks[0] + 1 if len(breaks) else len(idx)
    return idx[:end]


def fit_allan(curve: AllanCurve) -> AllanParams:
    """Read ``N``, ``B`` and ``K`` off an Allan deviation curve (see the module docstring).

    Parameters
    ----------
    curve : AllanCurve
        The Allan deviation of one axis, SI.

    Returns
    -------
    AllanParams
        The terms, SI, with NaN and a note for the ones the record cannot identify.
    """
    tau, sig = curve.tau_s, curve.adev
    ltau, lsig = np.log(tau), np.log(sig)
    slope = curve.slope
    notes: list[str] = []

    # --- white noise: slope -1/2, read at tau = 1 s --------------------------------------
    n_ident = True
    run = _first_run(np.abs(slope + 0.5) <= 0.05)
    if len(run) == 0:
        run = _first_run(np.abs(slope + 0.5) <= 0.15)
    if len(run) == 0:
        n_ident = False
        run = np.array([int(np.nanargmin(np.abs(slope + 0.5)))])
        notes.append(
            f"no slope -1/2 region (closest slope {slope[run[0]]:.2f} at tau={tau[run[0]]:.3g} s): "
            "N is indicative only"
        )
    noise_density = float(np.exp(np.median(lsig[run] + 0.5 * (ltau[run] - math.log(N_TAU_S)))))

    # --- bias instability: flat minimum / 0.664 ------------------------------------------
    # The lowest point is searched among averaging times followed by at least half a decade of
    # curve (at the longest ones a noisy dip would pass for a floor); the floor counts as reached
    # when the curve after it has stopped falling (log-log slope of a line fit > -0.15).
    upper = float(np.min(sig) / BI_FACTOR)
    bias, bias_tau = math.nan, math.nan
    cand = np.flatnonzero(tau <= tau[-1] / math.sqrt(10.0))
    i_min = int(cand[np.argmin(sig[cand])]) if len(cand) else len(tau) - 1
    turned_up = False
    if len(tau) - 1 - i_min >= 2:
        trend = np.polyfit(ltau[i_min:], lsig[i_min:], 1)[0]
        turned_up = bool(trend > -0.15)
    between = slope[run[-1] + 1 : i_min]
    periodic = bool(len(between) and np.min(between) < -0.75)
    rejected = turned_up and periodic
    if rejected:
        turned_up = False
        notes.append(
            "ADEV falls faster than white noise (slope < -3/4) before its minimum: a periodic "
            f"(vibration) component, not a bias-instability floor; only B <= {upper:.3g} (SI unit of the signal)"
        )
    if turned_up:
        near = np.abs(ltau - ltau[i_min]) <= math.log(10.0)
        u_lo, u_hi = ltau[near].min() - ltau[i_min], ltau[near].max() - ltau[i_min]
        a, b, c = np.polyfit(ltau[near] - ltau[i_min], lsig[near], 2)
        if a > 0.0:
            u = float(np.clip(-b / (2.0 * a), u_lo, u_hi))
            bias = float(np.exp(a * u * u + b * u + c)) / BI_FACTOR
            bias_tau = float(np.exp(ltau[i_min] + u))
        else:  # flat or bent down around the minimum: the lowest point is the floor
            bias = float(sig[i_min] / BI_FACTOR)
            bias_tau = float(tau[i_min])
    elif not rejected:
        notes.append(
            f"ADEV still falling at the longest tau ({tau[-1]:.3g} s): bias instability not "
            f"identifiable from this record, only B <= {upper:.3g} (SI unit of the signal)"
        )

    # Structure check on the well-estimated part (at least half a decade below the longest tau).
    before = slope[: i_min if turned_up else len(cand)]
    if len(before) and (np.min(before) < -0.75 or np.max(before) > 0.25):
        notes.append(
            "ADEV has slopes below -3/4 or rising parts before its minimum: periodic components "
            "(e.g. vibration) are present and N may include them"
        )

    # --- rate random walk: slope +1/2 after the minimum, read at tau = 3 s ----------------
    rrw = math.nan
    after = np.zeros(len(tau), dtype=bool)
    after[i_min + 1 :] = True
    krun = np.flatnonzero(after & (np.abs(slope - 0.5) <= 0.15))
    if len(krun) >= 2:
        rrw = float(np.exp(np.median(lsig[krun] - 0.5 * (ltau[krun] - math.log(K_TAU_S)))))
    else:
        notes.append("no slope +1/2 region: rate random walk not identifiable from this record")

    return AllanParams(
        noise_density=noise_density,
        noise_density_identified=n_ident,
        bias_instability=bias,
        bias_instability_tau_s=bias_tau,
        bias_instability_upper_bound=upper,
        rate_random_walk=rrw,
        notes=tuple(notes),
    )


def residual_rms(samples: npt.ArrayLike) -> FloatArray:
    """RMS of the static residuals about the mean, per column (Dabove et al. Table 2).

    Parameters
    ----------
    samples : array_like, shape (n,) or (n, k)
        Static samples of one or more axes, any unit.

    Returns
    -------
    ndarray, shape (k,)
        ``sqrt(mean((y - mean(y))^2))`` per column, same unit as the input.
    """
    y = np.asarray(samples, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    return np.sqrt(np.mean((y - y.mean(axis=0)) ** 2, axis=0))


# ------------------------------------------------------------------------------------------
# Noise model file
# ------------------------------------------------------------------------------------------

_FIELD_DOCS: dict[str, str] = {
    "gyro_noise_density_dps_rthz": "gyro white noise N (angle random walk), deg/s/sqrt(Hz) = deg/sqrt(s); "
    "ADEV(1 s) of the white part; per-sample std at f_s Hz = N*sqrt(f_s)",
    "gyro_bias_instability_dph": "gyro bias instability B = ADEV floor / 0.664, deg/h",
    "gyro_bias_instability_tau_s": "averaging time of the gyro ADEV floor, s",
    "gyro_rate_random_walk_dps_per_rts": "gyro rate random walk K, ADEV = K*sqrt(tau/3), "
    "deg/s/sqrt(s) = deg/s^2/sqrt(Hz)",
    "accel_noise_density_ug_rthz": "accel white noise N (velocity random walk), ug/sqrt(Hz); "
    "ADEV(1 s) of the white part; per-sample std at f_s Hz = N*sqrt(f_s)",
    "accel_bias_instability_ug": "accel bias instability B = ADEV floor / 0.664, ug",
    "accel_bias_instability_tau_s": "averaging time of the accel ADEV floor, s",
    "accel_rate_random_walk_ug_per_rts": "accel rate random walk K, ADEV = K*sqrt(tau/3), "
    "ug/sqrt(s) = ug/s/sqrt(Hz)",
    "sample_rate_hz": "sample rate of the characterised log, Hz",
    "duration_s": "length of the static record used, s",
    "source": "where the figures come from",
}


@dataclass(frozen=True)
class NoiseModel:
    """IMU noise parameters in datasheet units, as the Kalman engines and the simulator take them.

    One scalar per sensor (the largest over the three axes that identified the term, i.e. the
    conservative choice for filter tuning). NaN means *not identified from the data* (record too
    short): a consumer must then fall back to a datasheet value, never to zero. ``ug`` is
    micro-g with g = 9.80665 m/s^2. The SI properties (``gyro_noise_density`` ...) give the same
    numbers in rad and m/s^2.

    Attributes
    ----------
    gyro_noise_density_dps_rthz : float
        Gyro white-noise coefficient ``N`` (angle random walk), deg/s/sqrt(Hz), which equals
        deg/sqrt(s) (multiply by 60 for deg/sqrt(h)). It is the Allan deviation at
        ``tau = 1 s`` of the white part; a white sequence sampled at ``f_s`` has per-sample
        standard deviation ``N sqrt(f_s)``.
    gyro_bias_instability_dph : float
        Gyro bias instability ``B``, deg/h: the flat floor of the Allan deviation divided by
        ``sqrt(2 ln 2 / pi) = 0.664`` (IEEE Std 952); the PSD is ``B^2 / (2 pi f)``.
    gyro_bias_instability_tau_s : float
        Averaging time at which the gyro floor occurs, s. A first-order Gauss-Markov bias with
        correlation time ``T_c ~ tau / 1.89`` peaks there.
    gyro_rate_random_walk_dps_per_rts : float
        Gyro rate random walk ``K``, deg/s/sqrt(s) (= deg/s^2/sqrt(Hz)): the bias is a random
        walk whose increment over ``dt`` has standard deviation ``K sqrt(dt)``;
        ``ADEV(tau) = K sqrt(tau / 3)``.
    accel_noise_density_ug_rthz : float
        Accelerometer white-noise coefficient ``N`` (velocity random walk), ug/sqrt(Hz); per-sample
        standard deviation at ``f_s`` is ``N sqrt(f_s)``.
    accel_bias_instability_ug : float
        Accelerometer bias instability ``B`` = ADEV floor / 0.664, ug.
    accel_bias_instability_tau_s : float
        Averaging time at which the accelerometer floor occurs, s.
    accel_rate_random_walk_ug_per_rts : float
        Accelerometer rate random walk ``K``, ug/sqrt(s) (= ug/s/sqrt(Hz)).
    sample_rate_hz : float
        Sample rate of the log the model was estimated from, Hz (NaN if given by hand).
    duration_s : float
        Length of the static record used, s (NaN if given by hand).
    source : str
        Free text: file, time window, or "datasheet".
    """

    gyro_noise_density_dps_rthz: float
    gyro_bias_instability_dph: float
    gyro_rate_random_walk_dps_per_rts: float
    accel_noise_density_ug_rthz: float
    accel_bias_instability_ug: float
    accel_rate_random_walk_ug_per_rts: float
    gyro_bias_instability_tau_s: float = math.nan
    accel_bias_instability_tau_s: float = math.nan
    sample_rate_hz: float = math.nan
    duration_s: float = math.nan
    source: str = ""

    # --- SI views --------------------------------------------------------------------------
    @property
    def gyro_noise_density(self) -> float:
        """Gyro ``N``, rad/s/sqrt(Hz)."""
        return self.gyro_noise_density_dps_rthz * _DEG

    @property
    def gyro_bias_instability(self) -> float:
        """Gyro ``B``, rad/s."""
        return self.gyro_bias_instability_dph * _DEG / 3600.0

    @property
    def gyro_rate_random_walk(self) -> float:
        """Gyro ``K``, rad/s/sqrt(s)."""
        return self.gyro_rate_random_walk_dps_per_rts * _DEG

    @property
    def accel_noise_density(self) -> float:
        """Accelerometer ``N``, m/s^2/sqrt(Hz)."""
        return self.accel_noise_density_ug_rthz * _UG

    @property
    def accel_bias_instability(self) -> float:
        """Accelerometer ``B``, m/s^2."""
        return self.accel_bias_instability_ug * _UG

    @property
    def accel_rate_random_walk(self) -> float:
        """Accelerometer ``K``, m/s^2/sqrt(s)."""
        return self.accel_rate_random_walk_ug_per_rts * _UG

    @classmethod
    def from_si(
        cls,
        gyro: AllanParams | None,
        accel: AllanParams | None,
        sample_rate_hz: float = math.nan,
        duration_s: float = math.nan,
        source: str = "",
    ) -> NoiseModel:
        """Build a model from one gyro and one accelerometer :class:`AllanParams` (SI).

        Parameters
        ----------
        gyro, accel : AllanParams or None
            Terms of one axis each (e.g. the worst axis); None gives NaN fields.
        sample_rate_hz, duration_s : float
            Record facts, Hz and s.
        source : str
            Free text.

        Returns
        -------
        NoiseModel
        """
        nan = math.nan
        g = gyro
        a = accel
        return cls(
            gyro_noise_density_dps_rthz=g.noise_density / _DEG if g else nan,
            gyro_bias_instability_dph=g.bias_instability * 3600.0 / _DEG if g else nan,
            gyro_rate_random_walk_dps_per_rts=g.rate_random_walk / _DEG if g else nan,
            accel_noise_density_ug_rthz=a.noise_density / _UG if a else nan,
            accel_bias_instability_ug=a.bias_instability / _UG if a else nan,
            accel_rate_random_walk_ug_per_rts=a.rate_random_walk / _UG if a else nan,
            gyro_bias_instability_tau_s=g.bias_instability_tau_s if g else nan,
            accel_bias_instability_tau_s=a.bias_instability_tau_s if a else nan,
            sample_rate_hz=float(sample_rate_hz),
            duration_s=float(duration_s),
            source=source,
        )

    def to_toml(self) -> str:
        """The model as a TOML document (table ``[imu_noise]``, units in comments).

        NaN values are written as TOML ``nan``.
        """
        lines = [
            "# iotnav IMU noise model (Allan variance, IEEE Std 952). nan = not identified from the data.",
            "# ug = micro-g, g = 9.80665 m/s^2. Per-sample white-noise std at f_s Hz = N * sqrt(f_s).",
            "[imu_noise]",
        ]
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, str):
                text = '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'
            elif math.isnan(value):
                text = "nan"
            elif math.isinf(value):
                text = "inf" if value > 0 else "-inf"
            else:
                text = repr(float(value))
            lines.append(f"{f.name} = {text}  # {_FIELD_DOCS[f.name]}")
        return "\n".join(lines) + "\n"

    @classmethod
    def from_toml(cls, text: str) -> NoiseModel:
        """Parse a TOML document written by :meth:`to_toml` (or by hand).

        The keys may sit in an ``[imu_noise]`` table or at the top level. Missing optional keys
        take their defaults; unknown keys are an error (a misspelt key must not pass silently).

        Parameters
        ----------
        text : str
            TOML text.

        Returns
        -------
        NoiseModel

        Raises
        ------
        ValueError
            On unknown or missing required keys, or non-numeric values.
        """
        doc: dict[str, Any] = tomllib.loads(text)
        table = doc.get("imu_noise", doc)
        if not isinstance(table, dict):
            raise ValueError("[imu_noise] must be a table")
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise ValueError(f"unknown noise-model key(s): {', '.join(unknown)}; expected {', '.join(known)}")
        kwargs: dict[str, Any] = {}
        for name, value in table.items():
            if name == "source":
                kwargs[name] = str(value)
            elif isinstance(value, (int, float)) and not isinstance(value, bool):
                kwargs[name] = float(value)
            else:
                raise ValueError(f"noise-model key {name} must be a number, got {value!r}")
        try:
            return cls(**kwargs)
        except TypeError as exc:
            raise ValueError(f"incomplete noise model: {exc}") from None


# ------------------------------------------------------------------------------------------
# Whole-IMU characterisation
# ------------------------------------------------------------------------------------------

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Characterization:
    """Everything :func:`characterize` finds in a static IMU record (SI).

    Attributes
    ----------
    rate_hz : float
        Sample rate used, Hz.
    duration_s : float
        Record length, s.
    acc_rms : ndarray, shape (3,)
        RMS of the accelerometer static residuals per axis, m/s^2 (Table 2 form).
    gyro_rms : ndarray, shape (3,)
        RMS of the gyro static residuals per axis, rad/s.
    acc_curves, gyro_curves : tuple of AllanCurve
        Allan deviation per axis (m/s^2, rad/s).
    acc_params, gyro_params : tuple of AllanParams
        Noise terms per axis.
    model : NoiseModel
        Worst-axis summary in datasheet units.
    notes : tuple of str
        Remarks on the record (irregular sampling, short length).
    """

    rate_hz: float
    duration_s: float
    acc_rms: FloatArray
    gyro_rms: FloatArray
    acc_curves: tuple[AllanCurve, ...]
    gyro_curves: tuple[AllanCurve, ...]
    acc_params: tuple[AllanParams, ...]
    gyro_params: tuple[AllanParams, ...]
    model: NoiseModel
    notes: tuple[str, ...]


def _worst(params: tuple[AllanParams, ...]) -> AllanParams:
    """Per term, the largest identified value over the axes (NaN if none)."""

    def top(values: list[float]) -> float:
        finite = [v for v in values if math.isfinite(v)]
        return max(finite) if finite else math.nan

    nd = [p.noise_density for p in params if p.noise_density_identified]
    bi = [(p.bias_instability, p.bias_instability_tau_s) for p in params if math.isfinite(p.bias_instability)]
    b, b_tau = max(bi) if bi else (math.nan, math.nan)
    return AllanParams(
        noise_density=top(nd),
        noise_density_identified=bool(nd),
        bias_instability=b,
        bias_instability_tau_s=b_tau,
        bias_instability_upper_bound=top([p.bias_instability_upper_bound for p in params]),
        rate_random_walk=top([p.rate_random_walk for p in params]),
    )


def characterize(
    t: npt.ArrayLike,
    acc: npt.ArrayLike,
    gyro: npt.ArrayLike,
    source: str = "",
    per_decade: int = 10,
    max_tau_fraction: float = 0.1,
) -> Characterization:
    """Residual RMS, Allan deviation and noise terms of a static IMU record.

    Parameters
    ----------
    t : array_like, shape (n,)
        Sample times, s (the rate is ``(n - 1) / (t[-1] - t[0])``; samples are assumed evenly
        spaced, and a note says when they are not).
    acc : array_like, shape (n, 3)
        Specific force, m/s^2.
    gyro : array_like, shape (n, 3)
        Angular rate, rad/s.
    source : str
        Free text for :attr:`NoiseModel.source`.
    per_decade, max_tau_fraction :
        See :func:`allan_deviation`.

    Returns
    -------
    Characterization
    """
    tt = np.asarray(t, dtype=np.float64)
    a = np.asarray(acc, dtype=np.float64)
    w = np.asarray(gyro, dtype=np.float64)
    if a.shape != (len(tt), 3) or w.shape != (len(tt), 3):
        raise ValueError(f"expected t (n,), acc (n, 3), gyro (n, 3); got {tt.shape}, {a.shape}, {w.shape}")
    if len(tt) < 20:
        raise ValueError(f"only {len(tt)} IMU samples in the window; need at least 20")
    duration = float(tt[-1] - tt[0])
    if not duration > 0:
        raise ValueError("the IMU time stamps do not increase")
    rate = (len(tt) - 1) / duration
    notes: list[str] = []
    dt = np.diff(tt)
    irregular = np.abs(dt - 1.0 / rate) > 0.5 / rate
    if np.any(irregular):
        notes.append(
            f"{np.count_nonzero(irregular)} of {len(dt)} sample intervals differ from 1/rate by more "
            "than half an interval (duplicates or gaps); the Allan deviation assumes even sampling"
        )
    if duration < 3600.0:
        notes.append(
            f"record is {duration:.1f} s long: ADEV reaches tau = {max_tau_fraction * duration:.3g} s, so "
            "the noise density is identified but bias instability and rate random walk need hours"
        )
    acc_curves = tuple(allan_deviation(a[:, i], rate, per_decade, max_tau_fraction) for i in range(3))
    gyro_curves = tuple(allan_deviation(w[:, i], rate, per_decade, max_tau_fraction) for i in range(3))
    acc_params = tuple(fit_allan(c) for c in acc_curves)
    gyro_params = tuple(fit_allan(c) for c in gyro_curves)
    model = NoiseModel.from_si(
        _worst(gyro_params), _worst(acc_params), sample_rate_hz=rate, duration_s=duration, source=source
    )
    return Characterization(
        rate_hz=rate,
        duration_s=duration,
        acc_rms=residual_rms(a),
        gyro_rms=residual_rms(w),
        acc_curves=acc_curves,
        gyro_curves=gyro_curves,
        acc_params=acc_params,
        gyro_params=gyro_params,
        model=model,
        notes=tuple(notes),
    )
