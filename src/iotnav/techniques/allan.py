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

Fitting the terms to the whole curve (IEEE Std 952 Annex C model, fitted instead of read off
graphically). The Allan variance of independent noises adds, so per axis::

    sigma^2(tau) = N^2 / tau + (0.664 B)^2 + K^2 tau / 3

is linear in ``(N^2, (0.664 B)^2, K^2)``, and these are found by non-negative weighted least
squares (``scipy.optimize.nnls``) on the overlapping Allan variance at every averaging time:

* The weight of each point is ``1 / var(sigma^2)``, ``var(sigma^2) = 2 sigma^4 / edf``, with the
  equivalent degrees of freedom ``edf`` of NIST SP 1065 Table 5 (allantools ``edf_simple``) for
  the noise type the model's local slope says dominates there (interpolated between white,
  flicker and random-walk FM), and ``sigma^2`` the *model* value, refitted ``FIT_ITERATIONS``
  times (weights from the noisy data would favour the low points and bias ``B`` down).
  allantools' own ``adev_err = adev / sqrt(n)`` counts overlapping clusters as independent and
  is ~20 times too small at ``tau = T / 10``, so it is not used.
* The uncertainty of each term is the fit covariance ``(A^T W A)^-1`` (delta method for the
  square roots), widened by ``sqrt(chi^2 / dof)`` when the model fits badly and by the
  correlation of neighbouring overlapping ADEVs (``INDEPENDENT_PER_DECADE``).
* A term is *identified* when its relative 1-sigma uncertainty is below
  ``IDENTIFIED_REL_SIGMA`` (10 %); otherwise it is reported as NaN with a note, and ``B`` keeps
  the bound ``B <= min(ADEV) / 0.664``. ``N`` also needs a slope -1/2 region (within 0.15). If
  the curve falls faster than slope -3/4 or rises (without a random walk) in its well-estimated
  part (tau up to ``T / 10 / sqrt(10)``), it holds periodic components (vibration, IEEE Std 952
  "sinusoidal noise") that the model lacks: ``B`` and ``K`` are then not identified.
* ``B`` is the flicker level itself, not the ADEV minimum / 0.664: white noise and rate random
  walk lift the minimum above ``0.664 B`` (by ~5 % in the six-hour test of tests/test_allan.py)
  and the fit separates them. The fit also uses the part of the curve where white noise still
  dominates, so ``B`` is identified even when the ADEV has not yet turned flat at the longest
  ``tau`` (the simulator's 3DM-GX3-35 gyro: ``N`` falls to the floor only near 80 s). On a
  6-hour log the fitted ``B`` scatters by ~6 % (gyro) and ~2 % (accelerometer) per axis, which
  the reported uncertainty matches (``benchmarks/bench_characterize_sim.py``).
* ``bias_instability_tau_s`` is the averaging time of the fitted curve's minimum,
  ``sqrt(3) N / K`` (clipped to the curve), or the longest ``tau`` when ``K = 0``.
* Quantisation noise (slope -1) and the exact finite-band flicker shape are not modelled: for
  records sampled at >= 10 Hz and the averaging times used here their effect on ``N`` and ``B``
  is within the statistical scatter.

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

Modules: the Allan deviation, its fit and the residual RMS are in
:mod:`iotnav.techniques.allan_fit`; this module turns them into the :class:`NoiseModel` file and
the :func:`characterize` summary (public names re-exported here).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.techniques.allan_fit import (  # re-exported
    BI_FACTOR as BI_FACTOR,
)
from iotnav.techniques.allan_fit import (
    FIT_ITERATIONS as FIT_ITERATIONS,
)
from iotnav.techniques.allan_fit import (
    G0_MPS2,
    AllanCurve,
    AllanParams,
    allan_deviation,
    fit_allan,
    residual_rms,
)
from iotnav.techniques.allan_fit import (
    IDENTIFIED_REL_SIGMA as IDENTIFIED_REL_SIGMA,
)
from iotnav.techniques.allan_fit import (
    INDEPENDENT_PER_DECADE as INDEPENDENT_PER_DECADE,
)
from iotnav.techniques.allan_fit import (
    K_TAU_S as K_TAU_S,
)
from iotnav.techniques.allan_fit import (
    N_TAU_S as N_TAU_S,
)
from iotnav.techniques.allan_fit import (
    averaging_times as averaging_times,
)

FloatArray = npt.NDArray[np.float64]

_DEG = math.pi / 180.0
_UG = 1e-6 * G0_MPS2


# ------------------------------------------------------------------------------------------
# Noise model file
# ------------------------------------------------------------------------------------------

_FIELD_DOCS: dict[str, str] = {
    "gyro_noise_density_dps_rthz": "gyro white noise N (angle random walk), deg/s/sqrt(Hz) = deg/sqrt(s); "
    "ADEV(1 s) of the white part; per-sample std at f_s Hz = N*sqrt(f_s)",
    "gyro_bias_instability_dph": "gyro bias instability B (ADEV floor 0.664 B, whole-curve fit), deg/h",
    "gyro_bias_instability_tau_s": "averaging time of the fitted gyro ADEV minimum, s",
    "gyro_rate_random_walk_dps_per_rts": "gyro rate random walk K, ADEV = K*sqrt(tau/3), "
    "deg/s/sqrt(s) = deg/s^2/sqrt(Hz)",
    "accel_noise_density_ug_rthz": "accel white noise N (velocity random walk), ug/sqrt(Hz); "
    "ADEV(1 s) of the white part; per-sample std at f_s Hz = N*sqrt(f_s)",
    "accel_bias_instability_ug": "accel bias instability B (ADEV floor 0.664 B, whole-curve fit), ug",
    "accel_bias_instability_tau_s": "averaging time of the fitted accel ADEV minimum, s",
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
