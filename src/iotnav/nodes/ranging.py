"""Log-distance path-loss ranging model, radio presets and robust calibration.

The anchor-node mechanism of Zorkany et al. (2022, "Real time IoT mobile anchor nodes outdoor
localization mechanism", Int. J. Smart Sensing and Intelligent Systems 15(1), section 4 and
Fig. 3) locates non-GNSS IoT nodes "referencing anchor nodes" through the wireless link they
share (LoRaWAN, BLE). The paper leaves the ranging model to "known methods" and cites RSSI
ranging with noisy anchor positions (Kumar and Arablouei 2022); iotnav uses the standard
log-distance path-loss model with log-normal shadowing:

.. math::

    \\mathrm{RSSI}(d) = P_0 - 10\\,n\\,\\log_{10}(d / d_0) + X_\\sigma,
    \\qquad X_\\sigma \\sim \\mathcal{N}(0, \\sigma^2)                              \\quad (R1)

with ``P0`` the mean received power (dBm) at the reference distance ``d0`` (m), ``n`` the
path-loss exponent and ``sigma`` the shadowing standard deviation (dB). Inverting (R1) gives
the median distance estimate and, to first order, its spread:

.. math::

    \\hat d = d_0\\,10^{(P_0 - \\mathrm{RSSI}) / (10 n)},
    \\qquad \\sigma_d \\approx d\\,\\frac{\\ln 10\\,\\sigma}{10\\,n}                 \\quad (R2)

so ranging error grows in proportion to distance: with ``n = 2.7`` and ``sigma = 6 dB`` one
report ranges to about +-51 % of the distance. Calibration fits ``P0`` and ``n`` by robust
(Huber, IRLS) linear regression of RSSI on ``x = -10 log10(d / d0)``:

.. math::

    \\mathrm{RSSI}_k = P_0 + n\\,x_k + e_k, \\qquad
    \\min_{P_0, n} \\sum_k \\rho_c\\!\\left(\\frac{e_k}{s}\\right)                 \\quad (R3)

with the Huber function ``rho_c`` (``c = 1.345``, 95 % efficiency under Gaussian noise) and the
scale ``s`` re-estimated from the median absolute deviation at every iteration, so that NLOS
reports (strongly attenuated) do not bend the fit.

Everything here is pure: arrays in, arrays out, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: ``10 / ln(10)``: d(10 log10 d)/d(ln d), dB per neper of distance.
DB_PER_LN: float = 10.0 / math.log(10.0)

#: Physical range of a received signal strength, dBm. Below the thermal noise floor of a
#: 125 kHz LoRa channel at the lowest usable SNR (about -149 dBm) nothing is decodable; above
#: +30 dBm (1 W, beyond every ISM-band transmit limit) the value is not a reception.
RSSI_MIN_DBM: float = -150.0
RSSI_MAX_DBM: float = 30.0

#: SX127x receiver sensitivity at 125 kHz bandwidth per spreading factor, dBm (datasheet).
LORA_SENSITIVITY_DBM: dict[int, float] = {7: -123.0, 8: -126.0, 9: -129.0, 10: -132.0, 11: -134.5, 12: -137.0}


@dataclass(frozen=True)
class PathLossModel:
    """Log-distance path-loss parameters of one radio (equation R1).

    Attributes
    ----------
    name : str
        Preset name (``lora-sf7`` ... ``lora-sf12``, ``ble``, ``wifi``) or ``custom``.
    p0_dbm : float
        Mean RSSI at the reference distance ``d0_m``, dBm.
    n : float
        Path-loss exponent (2 in free space, 2.5-3.5 outdoors with obstacles).
    shadowing_db : float
        Shadowing standard deviation ``sigma``, dB.
    d0_m : float
        Reference distance, m.
    sensitivity_dbm : float
        Weakest decodable RSSI, dBm; weaker packets are lost (simulation) and cannot be reported.
    frequency_hz : float
        Carrier frequency, Hz (documentation; P0 already holds the free-space loss at ``d0``).
    spreading_factor : int
        LoRa spreading factor, 0 for other radios.
    """

    name: str = "lora-sf7"
    p0_dbm: float = -17.2
    n: float = 2.7
    shadowing_db: float = 6.0
    d0_m: float = 1.0
    sensitivity_dbm: float = -123.0
    frequency_hz: float = 868.1e6
    spreading_factor: int = 7

    def with_shadowing(self, shadowing_db: float) -> PathLossModel:
        """A copy with another shadowing sigma, dB."""
        return replace(self, shadowing_db=float(shadowing_db))


def free_space_loss_db(distance_m: float, frequency_hz: float) -> float:
    """Free-space path loss ``20 log10(4 pi d / lambda)``, dB."""
    wavelength = 299_792_458.0 / frequency_hz
    return 20.0 * math.log10(4.0 * math.pi * distance_m / wavelength)


def _lora(sf: int) -> PathLossModel:
    # EU868, 14 dBm transmit power, 0 dBi antennas: P0 at 1 m = 14 dBm - FSPL(1 m) = -17.2 dBm;
    # suburban exponent 2.7 and 6 dB shadowing (typical LoRaWAN measurement campaigns).
    return PathLossModel(
        name=f"lora-sf{sf}",
        p0_dbm=round(14.0 - free_space_loss_db(1.0, 868.1e6), 1),
        n=2.7,
        shadowing_db=6.0,
        sensitivity_dbm=LORA_SENSITIVITY_DBM[sf],
        frequency_hz=868.1e6,
        spreading_factor=sf,
    )


#: Radio presets. LoRa presets differ by sensitivity and (through
#: :func:`lora_time_on_air_s`) by the duty-cycle-limited report rate.
RADIOS: dict[str, PathLossModel] = {
    **{f"lora-sf{sf}": _lora(sf) for sf in range(7, 13)},
    # BLE advertising at 0 dBm: iBeacon-style "measured power" -59 dBm at 1 m, exponent 2.2.
    "ble": PathLossModel(
        name="ble",
        p0_dbm=-59.0,
        n=2.2,
        shadowing_db=4.0,
        sensitivity_dbm=-97.0,
        frequency_hz=2.44e9,
        spreading_factor=0,
    ),
    # 2.4 GHz Wi-Fi at 20 dBm: P0 = 20 - FSPL(1 m) = -20 dBm, exponent 3.0.
    "wifi": PathLossModel(
        name="wifi",
        p0_dbm=-20.0,
        n=3.0,
        shadowing_db=6.0,
        sensitivity_dbm=-92.0,
        frequency_hz=2.437e9,
        spreading_factor=0,
    ),
}


def radio(name: str) -> PathLossModel:
    """The preset called ``name`` (see :data:`RADIOS`); ``ValueError`` names the choices."""
    try:
        return RADIOS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown radio {name!r}; expected one of {', '.join(RADIOS)}") from None


def lora_time_on_air_s(
    spreading_factor: int,
    payload_bytes: int = 12,
    bandwidth_hz: float = 125e3,
    coding_rate: int = 1,
    preamble_symbols: int = 8,
    explicit_header: bool = True,
    crc: bool = True,
) -> float:
    """Time on air of one LoRa packet, s (Semtech SX127x datasheet formula).

    Parameters
    ----------
    spreading_factor : int
        7 to 12.
    payload_bytes : int
        Application payload length, bytes.
    bandwidth_hz : float
        Channel bandwidth, Hz.
    coding_rate : int
        1 to 4 for 4/5 to 4/8.
    preamble_symbols : int
        Programmed preamble length, symbols.
    explicit_header, crc : bool
        Header mode and payload CRC.

    Returns
    -------
    float
        Packet duration, s. With a duty-cycle limit ``D`` a transmitter may send at most every
        ``time_on_air / D`` seconds.
    """
    sf = int(spreading_factor)
    t_sym = 2.0**sf / bandwidth_hz
    low_dr = 1 if t_sym > 16e-3 else 0
    num = 8 * payload_bytes - 4 * sf + 28 + (16 if crc else 0) - (0 if explicit_header else 20)
    n_payload = 8 + max(math.ceil(num / (4 * (sf - 2 * low_dr))) * (coding_rate + 4), 0)
    return (preamble_symbols + 4.25 + n_payload) * t_sym


def rssi_from_distance(distance_m: npt.ArrayLike, model: PathLossModel) -> FloatArray:
    """Mean RSSI at a distance (equation R1 without shadowing), dBm.

    Parameters
    ----------
    distance_m : array_like
        Transmitter-receiver distance, m (> 0).
    model : PathLossModel
        Radio parameters.

    Returns
    -------
    numpy.ndarray
        Mean RSSI, dBm.
    """
    d = np.asarray(distance_m, dtype=float)
    return model.p0_dbm - 10.0 * model.n * np.log10(d / model.d0_m)


def distance_from_rssi(rssi_dbm: npt.ArrayLike, model: PathLossModel) -> FloatArray:
    """Median distance for an RSSI (equation R2), m."""
    r = np.asarray(rssi_dbm, dtype=float)
    return model.d0_m * 10.0 ** ((model.p0_dbm - r) / (10.0 * model.n))


def range_std_m(distance_m: npt.ArrayLike, model: PathLossModel) -> FloatArray:
    """First-order standard deviation of an RSSI range at a distance (equation R2), m."""
    d = np.asarray(distance_m, dtype=float)
    return d * model.shadowing_db / (DB_PER_LN * model.n)


@dataclass(frozen=True)
class PathLossFit:
    """Result of :func:`fit_path_loss`.

    Attributes
    ----------
    p0_dbm, n : float
        Fitted reference RSSI (dBm at ``d0_m``) and exponent.
    shadowing_db : float
        Robust (MAD-based) standard deviation of the residuals, dB.
    cov : numpy.ndarray
        ``(2, 2)`` covariance of ``[p0_dbm, n]`` (dB^2, dB, 1).
    inliers : numpy.ndarray
        Boolean mask of pairs whose final Huber weight is 1 (residual within ``c`` scales).
    d0_m : float
        Reference distance used, m.
    iterations : int
        IRLS iterations run.
    """

    p0_dbm: float
    n: float
    shadowing_db: float
    cov: FloatArray
    inliers: npt.NDArray[np.bool_]
    d0_m: float
    iterations: int

    def model(self, base: PathLossModel | None = None) -> PathLossModel:
        """A :class:`PathLossModel` carrying the fitted parameters (other fields from ``base``)."""
        b = base if base is not None else PathLossModel(name="custom")
        return replace(b, p0_dbm=self.p0_dbm, n=self.n, shadowing_db=self.shadowing_db, d0_m=self.d0_m)


def fit_path_loss(
    distance_m: npt.ArrayLike,
    rssi_dbm: npt.ArrayLike,
    d0_m: float = 1.0,
    huber_c: float = 1.345,
    max_iter: int = 50,
    tol_db: float = 1e-6,
) -> PathLossFit:
    """Fit ``P0`` and ``n`` of equation R1 to (known distance, RSSI) pairs, robustly (R3).

    Parameters
    ----------
    distance_m : array_like
        Known distances, m (> 0), at least three distinct values.
    rssi_dbm : array_like
        Measured RSSI at those distances, dBm.
    d0_m : float
        Reference distance, m.
    huber_c : float
        Huber threshold in robust scales; ``inf`` gives ordinary least squares.
    max_iter : int
        IRLS iteration limit.
    tol_db : float
        Stop when the parameters change less than this (dB, and dB/decade for ``n``).

    Returns
    -------
    PathLossFit
        Parameters, covariance, robust shadowing sigma and inlier mask.

    Raises
    ------
    ValueError
        On non-finite inputs, non-positive distances or fewer than three distinct distances.
    """
    d = np.asarray(distance_m, dtype=float).ravel()
    r = np.asarray(rssi_dbm, dtype=float).ravel()
    if d.shape != r.shape:
        raise ValueError(f"distance and RSSI differ in length ({d.size} vs {r.size})")
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(r))):
        raise ValueError("calibration pairs contain NaN or infinite values")
    if np.any(d <= 0.0):
        raise ValueError("calibration distances must be positive")
    if np.unique(np.round(d, 6)).size < 3:
        raise ValueError("calibration needs at least three distinct distances")
    x = -10.0 * np.log10(d / d0_m)
    A = np.column_stack([np.ones_like(x), x])
    w = np.ones_like(x)
    theta = np.zeros(2)
    s = 1.0
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        sw = np.sqrt(w)
        new, *_ = np.linalg.lstsq(A * sw[:, None], r * sw, rcond=None)
        e = r - A @ new
        s = max(1.4826 * float(np.median(np.abs(e - np.median(e)))), 1e-9)
        u = np.abs(e) / s
        w = np.where(u <= huber_c, 1.0, huber_c / np.maximum(u, 1e-300))
        done = bool(np.max(np.abs(new - theta)) < tol_db)
        theta = new
        if done:
            break
    e = r - A @ theta
    # Sandwich covariance of the Huber M-estimator: s^2 (sum psi'^2 ... ) approximated by
    # the weighted least-squares form with the robust scale.
    AtWA = A.T @ (A * w[:, None])
    cov = s**2 * np.linalg.inv(AtWA) @ (A.T @ (A * (w**2)[:, None])) @ np.linalg.inv(AtWA)
    inl = np.abs(e) <= huber_c * s
    return PathLossFit(
        p0_dbm=float(theta[0]),
        n=float(theta[1]),
        shadowing_db=s,
        cov=0.5 * (cov + cov.T),
        inliers=inl,
        d0_m=float(d0_m),
        iterations=it,
    )
