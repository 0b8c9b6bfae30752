"""Errors common to nearby receivers: ionosphere, troposphere, satellite orbit and clock.

Every model here is a smooth function of *where the signal passes* (ionospheric pierce
point, receiver height, satellite), never an independent draw per receiver, so that the
between-receiver single difference of two vehicles tens of metres apart cancels what
really cancels, by physics:

* **Ionosphere** (group delay on code, advance on phase). True slant delay =
  ``scale * Klobuchar(IS-GPS-200 20.3.3.5.2.5) + M(E) * V(IPP, t)``, where ``V`` is a
  spatially smooth vertical residual: a sum of ``K`` travelling plane waves in the
  pierce-point plane (wavelengths 500-3000 km, log-uniform, drifting at ~100 m/s like
  travelling ionospheric disturbances), with RMS ``residual_vertical_sigma_m``. Its RMS
  vertical gradient per horizontal axis is ``sigma sqrt(mean(k^2) / 2)`` = 2.3 mm/km with
  the defaults (:meth:`IonosphereField.rms_gradient_m_per_m`), within the nominal
  mid-latitude 1-4 mm/km of Lee et al. (2007), so two receivers 30 m apart (pierce
  points ~30 m apart) differ by ~0.1 mm vertical, ~0.3 mm slant at low elevation.
* **Troposphere**: Saastamoinen zenith hydrostatic + wet delay from a standard
  atmosphere at the receiver's height (as in RTKLIB ``tropmodel``), times the bounded
  mapping ``m(E) = 1.001 / sqrt(0.002001 + sin^2 E)`` (Black & Eisner 1984, RTCA DO-229
  A.4.2.4), plus a zenith residual common to the area with a small horizontal gradient.
* **Orbit**: the broadcast position differs from the true one by a per-satellite,
  per-pass constant (radial, along, cross) vector ``dr``; the pseudorange error is the
  exact range difference ``|x_true - x_rx| - |x_bc - x_rx| ~ -e . dr`` (``e`` receiver to
  satellite unit vector), which differs between receivers 30 m apart by ~|dr| * 1.5e-6.
* **Satellite clock**: the broadcast clock correction differs from the true satellite
  clock by a per-satellite, per-pass constant, identical for all receivers.

References
----------
IS-GPS-200 (Rev. N) 20.3.3.5.2.5 (Klobuchar single-frequency ionospheric model).
Saastamoinen, J. (1972), Atmospheric correction for the troposphere and stratosphere in
radio ranging of satellites, AGU Geophys. Monogr. 15.
Lee, J., Pullen, S., Datta-Barua, S. & Enge, P. (2007), Assessment of ionosphere spatial
decorrelation for GPS-based aircraft landing systems, J. Aircraft 44(5) (nominal vertical
gradient sigma ~ 4 mm/km at mid latitudes).
Misra, P. & Enge, P. (2011), *Global Positioning System*, 2nd ed., §5.3 (ionosphere:
thin-shell obliquity factor; troposphere), §5.2 (ephemeris/clock errors: radial ~ 0.5 m,
along/cross ~ 1-2 m class).
MacGougan (2009) eq. 5.1 (P and Phi error terms: d rho, dt, I, T; phase has -I).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from v2v.errors import UserError
from v2v.sensors.measurements import SPEED_OF_LIGHT_MPS

F64 = NDArray[np.float64]

EARTH_RADIUS_M = 6_371_000.0  # mean radius for the thin-shell ionosphere
# Klobuchar coefficients broadcast on 2021-04-28 (brdc1180.21n header, ION ALPHA/BETA).
KLOBUCHAR_ALPHA_2021_04_28 = (0.9313e-08, 0.1490e-07, -0.5960e-07, -0.1192e-06)
KLOBUCHAR_BETA_2021_04_28 = (0.8806e05, 0.4915e05, -0.1311e06, -0.3277e06)


@dataclass(frozen=True, kw_only=True)
class IonosphereConfig:
    """Ionosphere truth model (see module docstring).

    Parameters
    ----------
    enabled : bool
    klobuchar_alpha : 4 floats, s, s/semicircle, s/semicircle^2, s/semicircle^3.
    klobuchar_beta : 4 floats, s, s/semicircle, ...
    klobuchar_scale : float
        Truth = scale * Klobuchar + residual. 1.0 by default.
    residual_vertical_sigma_m : float
        RMS of the smooth vertical residual field ``V`` (L1), metres. Klobuchar removes
        ~50 % of the delay (IS-GPS-200); 0.5 m vertical is a mid-latitude daytime value.
    residual_wavelength_min_m, residual_wavelength_max_m : float
        Wavelength range of the plane waves (log-uniform), metres. Sets the gradient:
        ``sigma 2 pi sqrt(mean(1/lambda^2) / 2)`` per axis.
    residual_speed_mps : float
        Drift speed of the plane waves (TID-like), m/s.
    residual_components : int
        Number of plane waves ``K``.
    shell_height_m : float
        Thin-shell height for the pierce point and obliquity factor.
    """

    enabled: bool = True
    klobuchar_alpha: tuple[float, float, float, float] = KLOBUCHAR_ALPHA_2021_04_28
    klobuchar_beta: tuple[float, float, float, float] = KLOBUCHAR_BETA_2021_04_28
    klobuchar_scale: float = 1.0
    residual_vertical_sigma_m: float = 0.5
    residual_wavelength_min_m: float = 500e3
    residual_wavelength_max_m: float = 3000e3
    residual_speed_mps: float = 100.0
    residual_components: int = 8
    shell_height_m: float = 350e3

    def __post_init__(self) -> None:
        if self.residual_vertical_sigma_m < 0 or self.klobuchar_scale < 0:
            raise UserError("ionosphere scale and residual sigma must be >= 0", field="gnss.iono",
                            fix="use klobuchar_scale ~1 and residual_vertical_sigma_m ~0.5")
        if not 0 < self.residual_wavelength_min_m <= self.residual_wavelength_max_m:
            raise UserError("need 0 < residual_wavelength_min_m <= residual_wavelength_max_m",
                            field="gnss.iono.residual_wavelength_min_m", fix="e.g. 150e3 and 1500e3")
        if self.residual_components < 1:
            raise UserError("residual_components must be >= 1", field="gnss.iono.residual_components",
                            fix="use 8")


@dataclass(frozen=True, kw_only=True)
class TroposphereConfig:
    """Troposphere truth model.

    Parameters
    ----------
    enabled : bool
    temperature_sea_level_c : float, standard atmosphere surface temperature, deg C.
    relative_humidity : float in [0, 1].
    zenith_residual_sigma_m : float
        1-sigma of the area-wide zenith delay the standard atmosphere misses (constant per
        run), metres. 5 cm is typical of Saastamoinen with a standard atmosphere.
    zenith_gradient_sigma_m_per_m : float
        1-sigma of each horizontal component of the zenith-delay gradient, m/m
        (1e-6 = 1 mm/km).
    """

    enabled: bool = True
    temperature_sea_level_c: float = 15.0
    relative_humidity: float = 0.5
    zenith_residual_sigma_m: float = 0.05
    zenith_gradient_sigma_m_per_m: float = 1e-6

    def __post_init__(self) -> None:
        if not 0.0 <= self.relative_humidity <= 1.0:
            raise UserError("relative_humidity must be in [0, 1]", field="gnss.tropo.relative_humidity",
                            fix="use e.g. 0.5")


@dataclass(frozen=True, kw_only=True)
class SatelliteErrorConfig:
    """Broadcast orbit and clock errors (per satellite, per pass; common to all receivers).

    Defaults: GPS broadcast signal-in-space URE of ~0.5-1 m (Misra & Enge 2011 §5.2;
    radial small, along-track largest).
    """

    orbit_enabled: bool = True
    clock_enabled: bool = True
    orbit_sigma_radial_m: float = 0.3
    orbit_sigma_along_m: float = 1.0
    orbit_sigma_cross_m: float = 0.6
    clock_sigma_m: float = 0.6

    def __post_init__(self) -> None:
        if min(self.orbit_sigma_radial_m, self.orbit_sigma_along_m, self.orbit_sigma_cross_m,
               self.clock_sigma_m) < 0:
            raise UserError("satellite error sigmas must be >= 0", field="gnss.satellite",
                            fix="use values of ~0.3-1 m")


# --------------------------------------------------------------------------- ionosphere


def klobuchar_delay_s(
    lat_rad: ArrayLike,
    lon_rad: ArrayLike,
    el_rad: ArrayLike,
    az_rad: ArrayLike,
    t_gps_s: ArrayLike,
    alpha: tuple[float, ...],
    beta: tuple[float, ...],
) -> F64:
    """L1 ionospheric group delay (s) of the Klobuchar model, IS-GPS-200 20.3.3.5.2.5.

    With angles in semicircles (E elevation, phi_u/lambda_u user latitude/longitude)::

        psi = 0.0137 / (E + 0.11) - 0.022
        phi_i = clip(phi_u + psi cos A, -0.416, 0.416)
        lambda_i = lambda_u + psi sin A / cos(phi_i pi)
        phi_m = phi_i + 0.064 cos((lambda_i - 1.617) pi)
        t = (4.32e4 lambda_i + t_gps) mod 86400
        F = 1 + 16 (0.53 - E)^3
        PER = max(sum beta_n phi_m^n, 72000), AMP = max(sum alpha_n phi_m^n, 0)
        x = 2 pi (t - 50400) / PER
        T = F (5e-9 + AMP (1 - x^2/2 + x^4/24)) if |x| < 1.57 else F 5e-9
    """
    sc = np.pi
    e_sc = np.asarray(el_rad, dtype=float) / sc
    phi_u = np.asarray(lat_rad, dtype=float) / sc
    lam_u = np.asarray(lon_rad, dtype=float) / sc
    a = np.asarray(az_rad, dtype=float)
    psi = 0.0137 / (e_sc + 0.11) - 0.022
    phi_i = np.clip(phi_u + psi * np.cos(a), -0.416, 0.416)
    lam_i = lam_u + psi * np.sin(a) / np.cos(phi_i * sc)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * sc)
    t = np.mod(4.32e4 * lam_i + np.asarray(t_gps_s, dtype=float), 86400.0)
    f = 1.0 + 16.0 * (0.53 - e_sc) ** 3
    per = sum(b * phi_m**n for n, b in enumerate(beta))
    per = np.maximum(per, 72000.0)
    amp = sum(al * phi_m**n for n, al in enumerate(alpha))
    amp = np.maximum(amp, 0.0)
    x = 2.0 * np.pi * (t - 50400.0) / per
    day = 5e-9 + amp * (1.0 - x**2 / 2.0 + x**4 / 24.0)
    return f * np.where(np.abs(x) < 1.57, day, 5e-9)


def thin_shell_obliquity(el_rad: ArrayLike, shell_height_m: float) -> F64:
    """Slant/vertical factor ``M = 1 / sqrt(1 - (R cos E / (R + h))^2)`` (Misra & Enge §5.3.2)."""
    c = EARTH_RADIUS_M * np.cos(np.asarray(el_rad, dtype=float)) / (EARTH_RADIUS_M + shell_height_m)
    return 1.0 / np.sqrt(1.0 - c**2)


def pierce_point(
    lat_rad: ArrayLike, lon_rad: ArrayLike, el_rad: ArrayLike, az_rad: ArrayLike, shell_height_m: float
) -> tuple[F64, F64]:
    """Thin-shell ionospheric pierce point (lat, lon), radians (spherical Earth).

    Earth-central angle ``psi = pi/2 - E - asin(R cos E / (R + h))``;
    ``lat_i = asin(sin lat cos psi + cos lat sin psi cos A)``;
    ``lon_i = lon + asin(sin psi sin A / cos lat_i)``.
    """
    lat = np.asarray(lat_rad, dtype=float)
    e = np.asarray(el_rad, dtype=float)
    a = np.asarray(az_rad, dtype=float)
    psi = np.pi / 2 - e - np.arcsin(EARTH_RADIUS_M * np.cos(e) / (EARTH_RADIUS_M + shell_height_m))
    lat_i = np.arcsin(np.sin(lat) * np.cos(psi) + np.cos(lat) * np.sin(psi) * np.cos(a))
    lon_i = np.asarray(lon_rad, dtype=float) + np.arcsin(np.sin(psi) * np.sin(a) / np.cos(lat_i))
    return lat_i, lon_i


class IonosphereField:
    """Truth ionosphere: ``I = scale * Klobuchar + M(E) * V(IPP, t)`` (metres of L1 group delay).

    ``V(e, n, t) = sum_k a_k cos(k_e e + k_n n - w_k t + phi_k)`` with ``a_k = sigma sqrt(2/K)``
    (so RMS(V) = sigma), ``|k| = 2 pi / wavelength`` (log-uniform wavelength), random
    direction, ``w_k = |k| v`` and ``(e, n)`` the pierce point in a local tangent plane at
    ``(ref_lat, ref_lon)``. RMS gradient = ``sigma sqrt(mean |k|^2 / 2)`` per axis.
    """

    def __init__(self, config: IonosphereConfig, rng: np.random.Generator, ref_lat_rad: float, ref_lon_rad: float):
        self.config = config
        self.ref_lat_rad = float(ref_lat_rad)
        self.ref_lon_rad = float(ref_lon_rad)
        k_n = config.residual_components
        lam = np.exp(rng.uniform(np.log(config.residual_wavelength_min_m),
                                 np.log(config.residual_wavelength_max_m), k_n))
        direction = rng.uniform(0.0, 2.0 * np.pi, k_n)
        kmag = 2.0 * np.pi / lam
        self.k_en = np.stack([kmag * np.sin(direction), kmag * np.cos(direction)], axis=-1)
        self.omega_radps = kmag * config.residual_speed_mps
        self.phase_rad = rng.uniform(0.0, 2.0 * np.pi, k_n)
        self.amp_m = config.residual_vertical_sigma_m * np.sqrt(2.0 / k_n) * np.ones(k_n)

    def rms_gradient_m_per_m(self) -> float:
        """RMS of one horizontal component of ``grad V`` (m/m): ``sqrt(sum a_k^2 k_x^2 / 2)``."""
        return float(np.sqrt(np.sum(self.amp_m**2 * self.k_en[:, 0] ** 2) / 2.0))

    def vertical_residual_m(self, ipp_lat_rad: ArrayLike, ipp_lon_rad: ArrayLike, t_gps_s: float) -> F64:
        """Smooth vertical residual ``V`` at pierce points, metres."""
        e = EARTH_RADIUS_M * (np.asarray(ipp_lon_rad) - self.ref_lon_rad) * np.cos(self.ref_lat_rad)
        n = EARTH_RADIUS_M * (np.asarray(ipp_lat_rad) - self.ref_lat_rad)
        arg = (
            np.multiply.outer(e, self.k_en[:, 0])
            + np.multiply.outer(n, self.k_en[:, 1])
            - self.omega_radps * t_gps_s
            + self.phase_rad
        )
        return np.cos(arg) @ self.amp_m

    def slant_delay_m(
        self, lat_rad: ArrayLike, lon_rad: ArrayLike, el_rad: ArrayLike, az_rad: ArrayLike, t_gps_s: float
    ) -> F64:
        """True L1 slant group delay, metres (0 when disabled)."""
        el = np.asarray(el_rad, dtype=float)
        if not self.config.enabled:
            return np.zeros(el.shape)
        c = self.config
        klob = SPEED_OF_LIGHT_MPS * klobuchar_delay_s(lat_rad, lon_rad, el, az_rad, t_gps_s,
                                                      c.klobuchar_alpha, c.klobuchar_beta)
        ipp_lat, ipp_lon = pierce_point(lat_rad, lon_rad, el, az_rad, c.shell_height_m)
        resid = self.vertical_residual_m(ipp_lat, ipp_lon, t_gps_s)
        # A group delay cannot be negative: clip where a deep residual trough exceeds the
        # (night-time) Klobuchar floor.
        return np.maximum(c.klobuchar_scale * klob + thin_shell_obliquity(el, c.shell_height_m) * resid, 0.0)


# --------------------------------------------------------------------------- troposphere


def saastamoinen_zenith_delay_m(
    lat_rad: ArrayLike, h_m: ArrayLike, *, temperature_sea_level_c: float = 15.0, relative_humidity: float = 0.5
) -> F64:
    """Zenith tropospheric delay (hydrostatic + wet), metres, standard atmosphere at height ``h``.

    As RTKLIB ``tropmodel`` (Saastamoinen 1972): ``P = 1013.25 (1 - 2.2557e-5 h)^5.2568`` hPa,
    ``T = T0 - 6.5e-3 h + 273.16`` K, ``e = 6.108 RH exp((17.15 T - 4684) / (T - 38.45))`` hPa,
    ``ZHD = 0.0022768 P / (1 - 0.00266 cos 2 lat - 0.00028 h_km)``,
    ``ZWD = 0.002277 (1255 / T + 0.05) e``. Heights are clipped to [0, 10 km].
    """
    h = np.clip(np.asarray(h_m, dtype=float), 0.0, 1e4)
    pres = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temp = temperature_sea_level_c - 6.5e-3 * h + 273.16
    e = 6.108 * relative_humidity * np.exp((17.15 * temp - 4684.0) / (temp - 38.45))
    zhd = 0.0022768 * pres / (1.0 - 0.00266 * np.cos(2.0 * np.asarray(lat_rad, dtype=float)) - 0.00028 * h / 1e3)
    zwd = 0.002277 * (1255.0 / temp + 0.05) * e
    return zhd + zwd


def tropo_mapping(el_rad: ArrayLike) -> F64:
    """Bounded ``1/sin(E)``-like mapping ``1.001 / sqrt(0.002001 + sin^2 E)`` (RTCA DO-229 A.4.2.4)."""
    s = np.sin(np.asarray(el_rad, dtype=float))
    return 1.001 / np.sqrt(0.002001 + s**2)


class TroposphereField:
    """Truth troposphere: ``T = m(E) (ZTD_saast(h) + dz + g . (e, n))`` metres.

    ``dz`` (area residual) and ``g`` (horizontal gradient, m/m) are drawn once per run.
    """

    def __init__(self, config: TroposphereConfig, rng: np.random.Generator, ref_lat_rad: float, ref_lon_rad: float):
        self.config = config
        self.ref_lat_rad = float(ref_lat_rad)
        self.ref_lon_rad = float(ref_lon_rad)
        self.zenith_residual_m = float(rng.standard_normal() * config.zenith_residual_sigma_m)
        self.gradient_en = rng.standard_normal(2) * config.zenith_gradient_sigma_m_per_m

    def slant_delay_m(self, lat_rad: ArrayLike, lon_rad: ArrayLike, h_m: ArrayLike, el_rad: ArrayLike) -> F64:
        el = np.asarray(el_rad, dtype=float)
        if not self.config.enabled:
            return np.zeros(el.shape)
        c = self.config
        zenith = saastamoinen_zenith_delay_m(lat_rad, h_m, temperature_sea_level_c=c.temperature_sea_level_c,
                                             relative_humidity=c.relative_humidity)
        e = EARTH_RADIUS_M * (np.asarray(lon_rad) - self.ref_lon_rad) * np.cos(self.ref_lat_rad)
        n = EARTH_RADIUS_M * (np.asarray(lat_rad) - self.ref_lat_rad)
        zenith = zenith + self.zenith_residual_m + self.gradient_en[0] * e + self.gradient_en[1] * n
        return tropo_mapping(el) * zenith


# --------------------------------------------------------------------------- satellites


class SatelliteErrors:
    """Per-satellite, per-pass broadcast orbit and clock errors, identical for all receivers.

    Each (prn, pass) draws from its own stream ``SeedSequence(entropy, spawn_key + (prn, pass))``,
    so the values do not depend on the order in which satellites are first seen.
    """

    def __init__(self, config: SatelliteErrorConfig, seed: np.random.SeedSequence):
        self.config = config
        self._seed = seed
        self._cache: dict[tuple[int, int], tuple[F64, float]] = {}

    def _draw(self, prn: int, pass_index: int) -> tuple[F64, float]:
        key = (int(prn), int(pass_index))
        if key not in self._cache:
            ss = np.random.SeedSequence(self._seed.entropy, spawn_key=(*self._seed.spawn_key, *key))
            rng = np.random.default_rng(ss)
            c = self.config
            rac = rng.standard_normal(3) * np.array([c.orbit_sigma_radial_m, c.orbit_sigma_along_m,
                                                     c.orbit_sigma_cross_m])
            clk = float(rng.standard_normal() * c.clock_sigma_m)
            self._cache[key] = (rac if c.orbit_enabled else np.zeros(3), clk if c.clock_enabled else 0.0)
        return self._cache[key]

    def orbit_error_ecef_m(self, prn: ArrayLike, pass_index: ArrayLike, pos_ecef_m: F64, vel_ecef_mps: F64) -> F64:
        """Broadcast-minus-true position ``dr`` (n, 3) in ECEF from (radial, along, cross) constants.

        radial = r/|r|, cross = (r x v)/|r x v|, along = cross x radial.
        """
        rac = self.orbit_error_rac_m(prn, pass_index)
        r = np.asarray(pos_ecef_m, dtype=float).reshape(-1, 3)
        v = np.asarray(vel_ecef_mps, dtype=float).reshape(-1, 3)
        return rac_to_ecef(rac, r, v)

    def orbit_error_rac_m(self, prn: ArrayLike, pass_index: ArrayLike) -> F64:
        """The (radial, along, cross) orbit error constants (n, 3) of each (prn, pass), metres."""
        prn_a = np.atleast_1d(prn)
        pas = np.broadcast_to(np.asarray(pass_index), prn_a.shape)
        return np.array([self._draw(p, k)[0] for p, k in zip(prn_a, pas, strict=True)]).reshape(-1, 3)

    def clock_error_m(self, prn: ArrayLike, pass_index: ArrayLike) -> F64:
        """True-minus-broadcast satellite clock, metres (``c (dt_true - dt_broadcast)``)."""
        prn_a = np.atleast_1d(prn)
        pas = np.broadcast_to(np.asarray(pass_index), prn_a.shape)
        return np.array([self._draw(p, k)[1] for p, k in zip(prn_a, pas, strict=True)], dtype=float)


def rac_to_ecef(rac_m: F64, pos_ecef_m: F64, vel_ecef_mps: F64) -> F64:
    """(radial, along, cross) components (..., 3) to ECEF at satellite states (..., 3).

    radial = r/|r|, cross = (r x v)/|r x v|, along = cross x radial.
    """
    r = np.asarray(pos_ecef_m, dtype=float)
    v = np.asarray(vel_ecef_mps, dtype=float)
    rac = np.asarray(rac_m, dtype=float)
    u_r = r / np.linalg.norm(r, axis=-1, keepdims=True)
    h = _cross3(r, v)
    u_c = h / np.linalg.norm(h, axis=-1, keepdims=True)
    u_a = _cross3(u_c, u_r)
    return rac[..., :1] * u_r + rac[..., 1:2] * u_a + rac[..., 2:3] * u_c


def _cross3(a: F64, b: F64) -> F64:
    """``a x b`` along the last axis (what ``np.cross`` computes, without its overhead)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


# --------------------------------------------------------------------------- compiled scalar forms
# The receiver's per-(vehicle, satellite) kernel (v2v.sensors.gnss.receiver) evaluates the
# same formulas as the array functions above, one pair at a time inside a numba loop; the
# tests (tests/test_gnss_kernels.py) check that the two agree to float rounding.

_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def klobuchar_delay_scalar_s(lat_rad, lon_rad, el_rad, az_rad, t_gps_s, alpha, beta):  # pragma: no cover
    """:func:`klobuchar_delay_s` for one signal (compiled); ``alpha``/``beta``: (4,) arrays."""
    return _klobuchar_core_s(lat_rad, lon_rad, el_rad, np.cos(az_rad), np.sin(az_rad), t_gps_s, alpha, beta)


@njit(**_JIT)
def _klobuchar_core_s(lat_rad, lon_rad, el_rad, cos_az, sin_az, t_gps_s, alpha, beta):  # pragma: no cover
    sc = np.pi
    e_sc = el_rad / sc
    psi = 0.0137 / (e_sc + 0.11) - 0.022
    phi_i = min(max(lat_rad / sc + psi * cos_az, -0.416), 0.416)
    lam_i = lon_rad / sc + psi * sin_az / np.cos(phi_i * sc)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * sc)
    t = np.mod(4.32e4 * lam_i + t_gps_s, 86400.0)
    f = 1.0 + 16.0 * (0.53 - e_sc) ** 3
    per = 0.0
    amp = 0.0
    p = 1.0
    for n in range(beta.shape[0]):
        per += beta[n] * p
        amp += alpha[n] * p
        p *= phi_m
    per = max(per, 72000.0)
    amp = max(amp, 0.0)
    x = 2.0 * np.pi * (t - 50400.0) / per
    if abs(x) < 1.57:
        return f * (5e-9 + amp * (1.0 - x**2 / 2.0 + x**4 / 24.0))
    return f * 5e-9


@njit(**_JIT)
def iono_slant_delay_scalar_m(
    lat_rad, lon_rad, el_rad, az_rad, t_gps_s, scale, alpha, beta, shell_height_m, ref_lat_rad, ref_lon_rad,
    k_en, omega_radps, phase_rad, amp_m,
):  # pragma: no cover
    """:meth:`IonosphereField.slant_delay_m` for one signal (compiled; field passed as arrays)."""
    return iono_slant_delay_core_m(lat_rad, lon_rad, np.sin(lat_rad), np.cos(lat_rad), el_rad, np.cos(az_rad),
                                   np.sin(az_rad), t_gps_s, scale, alpha, beta, shell_height_m, ref_lat_rad,
                                   np.cos(ref_lat_rad), ref_lon_rad, k_en, omega_radps, phase_rad, amp_m)


@njit(**_JIT)
def iono_slant_delay_core_m(
    lat_rad, lon_rad, sin_lat, cos_lat, el_rad, cos_az, sin_az, t_gps_s, scale, alpha, beta, shell_height_m,
    ref_lat_rad, cos_ref_lat, ref_lon_rad, k_en, omega_radps, phase_rad, amp_m,
):  # pragma: no cover
    """:func:`iono_slant_delay_scalar_m` with the sines/cosines of latitude and azimuth given
    (the receiver kernel shares them between pairs and models)."""
    klob = SPEED_OF_LIGHT_MPS * _klobuchar_core_s(lat_rad, lon_rad, el_rad, cos_az, sin_az, t_gps_s, alpha, beta)
    ce = EARTH_RADIUS_M * np.cos(el_rad) / (EARTH_RADIUS_M + shell_height_m)
    psi = np.pi / 2 - el_rad - np.arcsin(ce)
    s_psi = np.sin(psi)
    lat_i = np.arcsin(sin_lat * np.cos(psi) + cos_lat * s_psi * cos_az)
    lon_i = lon_rad + np.arcsin(s_psi * sin_az / np.cos(lat_i))
    e = EARTH_RADIUS_M * (lon_i - ref_lon_rad) * cos_ref_lat
    n = EARTH_RADIUS_M * (lat_i - ref_lat_rad)
    resid = 0.0
    for j in range(amp_m.shape[0]):
        resid += np.cos(e * k_en[j, 0] + n * k_en[j, 1] - omega_radps[j] * t_gps_s + phase_rad[j]) * amp_m[j]
    obliq = 1.0 / np.sqrt(1.0 - ce**2)
    return max(scale * klob + obliq * resid, 0.0)


@njit(**_JIT)
def tropo_slant_delay_scalar_m(
    lat_rad, lon_rad, h_m, el_rad, temperature_sea_level_c, relative_humidity, zenith_residual_m, gradient_e,
    gradient_n, ref_lat_rad, ref_lon_rad,
):  # pragma: no cover
    """:meth:`TroposphereField.slant_delay_m` for one signal (compiled)."""
    zenith = tropo_zenith_scalar_m(lat_rad, lon_rad, h_m, temperature_sea_level_c, relative_humidity,
                                   zenith_residual_m, gradient_e, gradient_n, ref_lat_rad, ref_lon_rad)
    s = np.sin(el_rad)
    return 1.001 / np.sqrt(0.002001 + s**2) * zenith


@njit(**_JIT)
def tropo_zenith_scalar_m(
    lat_rad, lon_rad, h_m, temperature_sea_level_c, relative_humidity, zenith_residual_m, gradient_e, gradient_n,
    ref_lat_rad, ref_lon_rad,
):  # pragma: no cover
    """Zenith delay of :meth:`TroposphereField.slant_delay_m` at one receiver (compiled)."""
    h = min(max(h_m, 0.0), 1e4)
    pres = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temp = temperature_sea_level_c - 6.5e-3 * h + 273.16
    e = 6.108 * relative_humidity * np.exp((17.15 * temp - 4684.0) / (temp - 38.45))
    zhd = 0.0022768 * pres / (1.0 - 0.00266 * np.cos(2.0 * lat_rad) - 0.00028 * h / 1e3)
    zwd = 0.002277 * (1255.0 / temp + 0.05) * e
    de = EARTH_RADIUS_M * (lon_rad - ref_lon_rad) * np.cos(ref_lat_rad)
    dn = EARTH_RADIUS_M * (lat_rad - ref_lat_rad)
    return zhd + zwd + zenith_residual_m + gradient_e * de + gradient_n * dn
