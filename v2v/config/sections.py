"""Scenario sections for the sensors, the V2V exchange and the solutions.

These are the *user-facing* fields (units in names, degrees at this edge). The builders
in :mod:`v2v.pipeline` turn them into the sensor and filter parameter objects.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    ValidationInfo,
    field_validator,
    model_validator,
)

from v2v.errors import sigma_problem, sigma_range, tau_problem
from v2v.sensors.gnss.constellation import SLOT_TABLES

# v2v tracks GPS L1 C/A only, whose PRNs are 1-32 (IS-GPS-200 Table 3-Ia): no sky, a RINEX file's
# or the nominal one, has more GPS satellites, let alone more in common with the lead.
GPS_MAX_PRN = 32
# the built-in nominal sky (sensors.gnss.ephemeris = "nominal"): the slots of the table a run's
# NominalConstellation uses (its default, the expandable-24 constellation's 27)
NOMINAL_SATELLITES = len(SLOT_TABLES["expandable27"])


def a_path(v: str, fix: str = "give the file's path") -> str:
    """A file path field's value, checked: a NUL byte cannot be in a path (Python's file calls
    raise ValueError on it)."""
    if "\x00" in v:
        raise ValueError(f"contains a NUL character (\\u0000), which no file path can -- fix: {fix}")
    return v


class _Model(BaseModel):
    # Field types are strict (StrictBool, StrictInt, StrictFloat), as v2v.config.scenario's: a
    # wrong TOML type is an error, not coerced (true is no 1.0, "3" no 3, 0 no false); a float
    # field takes an integer (rate_hz = 10), a tuple field a TOML array.
    model_config = ConfigDict(extra="forbid", frozen=True)


class GnssErrorsSection(_Model):
    """Each GNSS error model, switchable on its own (all on by default)."""

    receiver_clock: StrictBool = True
    ionosphere: StrictBool = True
    troposphere: StrictBool = True
    satellite_orbit: StrictBool = True
    satellite_clock: StrictBool = True
    multipath: StrictBool = True
    noise: StrictBool = True
    foliage: StrictBool = True
    nlos: StrictBool = True


class GnssSection(_Model):
    enabled: StrictBool = True
    rate_hz: StrictFloat = Field(default=10.0, gt=0.0, le=100.0)
    elevation_mask_deg: StrictFloat = Field(default=10.0, ge=0.0, lt=90.0)
    # "nominal" = the built-in SPS PS 27-slot (expandable 24) constellation at start_utc
    # (v2v.sensors.gnss.constellation), or a RINEX 2/3 nav file path for a real sky.
    ephemeris: str = "nominal"
    oscillator: Literal["TCXO", "OCXO"] = "TCXO"
    errors: GnssErrorsSection = GnssErrorsSection()

    @field_validator("ephemeris")
    @classmethod
    def _ephemeris_is_a_path(cls, v: str) -> str:
        return a_path(v, fix='give the RINEX file\'s path, or "nominal"')


# the built-in UWB radio profiles (v2v.sensors.uwb.PROFILES; names matched case-insensitively)
UWB_PROFILE_NAMES = ("ideal", "mssi", "tdc")


def _unknown_profile(name: str) -> str | None:
    if str(name).lower() in UWB_PROFILE_NAMES:
        return None
    return f"unknown UWB radio profile {name!r} -- fix: use one of {', '.join(UWB_PROFILE_NAMES)}"


class UwbSection(_Model):
    enabled: StrictBool = True
    profile: str = "mssi"  # mssi | tdc | ideal
    vehicle_profiles: dict[str, str] = Field(default_factory=dict)  # per vehicle id
    pairs: Literal["all"] | list[tuple[str, str]] = "all"

    @field_validator("profile")
    @classmethod
    def _known_profile(cls, v: str) -> str:
        bad = _unknown_profile(v)
        if bad:
            raise ValueError(bad)
        return v

    @field_validator("pairs", mode="before")
    @classmethod
    def _pairs_of_two_ids(cls, v: Any) -> Any:
        fix = 'give "all" or a list of [id, id] pairs, e.g. [["c1.0", "c1.1"]]'
        if isinstance(v, list | tuple):
            for i, pair in enumerate(v):
                if not (isinstance(pair, list | tuple) and len(pair) == 2 and all(isinstance(x, str) for x in pair)):
                    raise ValueError(f"@{i}: each pair is two vehicle ids, got {pair!r} -- fix: {fix}")
        elif v != "all":
            raise ValueError(f'is "all" or a list of vehicle-id pairs -- fix: {fix}')
        return v

    @field_validator("vehicle_profiles")
    @classmethod
    def _known_vehicle_profiles(cls, v: dict[str, str]) -> dict[str, str]:
        for vid, name in v.items():
            bad = _unknown_profile(name)
            if bad:
                raise ValueError(f'@"{vid}": {bad}')
        return v


class BearingSection(_Model):
    enabled: StrictBool = True
    sigma_deg: StrictFloat = Field(default=0.5, gt=0.0, le=30.0)
    field_of_view_deg: StrictFloat = Field(default=360.0, gt=0.0, le=360.0)
    max_range_m: StrictFloat = Field(default=150.0, gt=0.0, le=10000.0)  # (a camera or radar: 10 km is beyond any)
    rate_hz: StrictFloat = Field(default=10.0, gt=0.0, le=100.0)
    azimuth_sigma_deg: StrictFloat = Field(default=0.1, ge=0.0, le=30.0)
    measuring: Literal["all"] | list[str] = "all"


class SensorsSection(_Model):
    gnss: GnssSection = GnssSection()
    uwb: UwbSection = UwbSection()
    bearing: BearingSection = BearingSection()


SENSOR_NAMES = ("gnss", "uwb", "bearing")
# a scenario's name names its run folder (and, with 18 more, the hidden staging folder); a
# solution's labels rows and columns: both at most this many UTF-8 bytes
MAX_NAME_BYTES = 100


def has_control_chars(v: str) -> bool:
    return any(ord(ch) < 32 or ord(ch) == 127 for ch in v)


class ExchangeSection(_Model):
    """V2V message exchange to the lead's filter (see :mod:`v2v.exchange`)."""

    latency_s: StrictFloat = Field(default=0.0, ge=0.0, le=10.0)
    loss_probability: StrictFloat = Field(default=0.0, ge=0.0, le=1.0)
    filter_lag_s: StrictFloat | None = Field(default=None, ge=0.0, le=10.0)

    @property
    def lag_s(self) -> float:
        return self.latency_s if self.filter_lag_s is None else self.filter_lag_s


# The solution fields the filter squares into variances: field -> (factor to the filter's unit, unit).
# Each must give a positive normal float64 variance (v2v.errors.sigma_problem); those in _ZERO_IS_OFF
# may also be 0 (the term is off).
_DEG = math.pi / 180.0  # (= numpy.radians' factor, which the pipeline converts with)
_FILTER_SIGMAS = {"pseudorange_sigma_m": (1.0, "m"), "doppler_sigma_mps": (1.0, "m/s"), "uwb_sigma_m": (1.0, "m"),
                  "bearing_sigma_deg": (_DEG, "deg"), "velocity_sigma_horizontal_mps": (1.0, "m/s"),
                  "velocity_sigma_vertical_mps": (1.0, "m/s"), "clock_drift_sigma_mps": (1.0, "m/s"),
                  "height_aiding_sigma_m": (1.0, "m"), "azimuth_rw_deg_per_sqrt_s": (_DEG, "deg/sqrt(s)"),
                  "yaw_rate_sigma_deg_s": (_DEG, "deg/s"), "phase_sigma_m": (1.0, "m")}
_ZERO_IS_OFF = ("azimuth_rw_deg_per_sqrt_s", "yaw_rate_sigma_deg_s")


class SolutionSection(_Model):
    """One filter configuration. Every solution processes the same measurements.

    ``*_sigma_*`` are the *filter's* assumed noises (paper Table 1 defaults), not the
    world's: where the filter deliberately differs from the simulated errors (the paper
    ignored UWB bias and scale factor), that is set here.
    """

    name: str
    sensors: list[str] = Field(min_length=1)
    azimuth: Literal["known", "estimated"] = "known"
    uwb_error_states: StrictBool = False
    # MacGougan (2009) eq. 3.19-3.22: after each UWB update a bias or scale state beyond its
    # known range is pulled onto the bound by a pseudo-measurement (uwb_error_states only).
    # Bias: +-1.23 m, the worst case of 20 ppm oscillators (IEEE 802.15.4a; thesis section 3.4.2, eq. 3.19-3.22);
    # scale: 0-5000 ppm covers both built-in radios' line-of-sight walk (2300-4700 ppm, 2.11.1).
    uwb_constraints: StrictBool = False
    uwb_bias_bounds_m: tuple[StrictFloat, StrictFloat] = (-1.23, 1.23)
    uwb_scale_bounds: tuple[StrictFloat, StrictFloat] = (0.0, 0.005)
    pseudorange_sigma_m: StrictFloat = Field(default=5.0, gt=0.0)
    doppler_sigma_mps: StrictFloat = Field(default=0.1, gt=0.0)
    uwb_sigma_m: StrictFloat = Field(default=0.5, gt=0.0)
    bearing_sigma_deg: StrictFloat = Field(default=0.5, gt=0.0)
    significance: StrictFloat = Field(default=0.001, gt=0.0, lt=1.0)
    velocity_sigma_horizontal_mps: StrictFloat = Field(default=10.0, gt=0.0)
    velocity_sigma_vertical_mps: StrictFloat = Field(default=1.0, gt=0.0)
    velocity_tau_s: StrictFloat = Field(default=2.0, gt=0.0)
    clock_drift_sigma_mps: StrictFloat = Field(default=1000.0, gt=0.0)
    clock_drift_tau_s: StrictFloat = Field(default=10.0, gt=0.0)
    # "relative up = h_v - h_lead +- sigma" (antenna heights above the road, from the vehicle
    # types' antenna_lever_arm_m) in epochs without GNSS (cars on one locally flat road): UWB and
    # bearings carry no height, and without it their geometry degrades within seconds of an outage.
    # height_aiding = false turns it off (TOML has no null; height_aiding_sigma_m = None given from
    # Python means the same and is stored as height_aiding = false).
    height_aiding: StrictBool = True
    height_aiding_sigma_m: StrictFloat = Field(default=1.0, gt=0.0)
    # A vehicle with fewer satellites in common with the lead than this leaves its GNSS out of
    # the epoch (as in an outage: height aiding, UWB and bearings carry it). 0: use every SD
    # (the paper's filter). 4 in a deep canyon: see the README's carrier-phase section.
    # At most GPS_MAX_PRN (32): a larger count can never be met and would leave every epoch's GNSS
    # out (with the nominal sky at most its 27: Scenario checks that, as it knows the sky).
    gnss_min_satellites: StrictInt = 0
    # SNR mask of the SD pseudoranges and Dopplers: only signals with C/N0 >= this (dB-Hz) at
    # both receivers. Echoes arrive echo_loss_db (8 dB) weaker than their direct signal, so 41
    # (zenith 49 - 8) leaves none. 0: no mask (the paper's filter). See FilterConfig.
    gnss_cn0_mask_dbhz: StrictFloat = Field(default=0.0, ge=0.0, le=60.0)
    # Estimated-azimuth process model (azimuth = "estimated" only): azimuth = integral of a
    # first-order Gauss-Markov yaw rate (sigma, tau) plus a random walk. yaw_rate_sigma_deg_s = 0
    # drops the yaw-rate state (pure random walk). See v2v.estimation.process.
    azimuth_rw_deg_per_sqrt_s: StrictFloat = Field(default=2.0, ge=0.0)
    yaw_rate_sigma_deg_s: StrictFloat = Field(default=30.0, ge=0.0)
    yaw_rate_tau_s: StrictFloat = Field(default=1.0, gt=0.0)
    # Carrier phase (MacGougan (2009) sections 3.4-3.7; v2v.estimation.phase): SD phase with SD
    # ambiguity states, LAMBDA partial fixing validated by the bootstrapped success rate and the
    # ratio test, fix-and-hold. The phase solutions use a realistic code sigma (open-sky code
    # error ~0.5 m), not the paper's 5 m: with 5 m the float ambiguities need many minutes.
    carrier_phase: StrictBool = False
    phase_sigma_m: StrictFloat = Field(default=0.005, gt=0.0)
    phase_elevation_mask_deg: StrictFloat = Field(default=15.0, ge=0.0, lt=90.0)
    ambiguity_resolution: StrictBool = True
    ar_min_success: StrictFloat = Field(default=0.999, gt=0.0, lt=1.0)
    ar_ratio: StrictFloat = Field(default=3.0, ge=1.0)

    @field_validator(*_FILTER_SIGMAS)
    @classmethod
    def _usable_sigma(cls, v: float, info: ValidationInfo) -> float:
        name = str(info.field_name)
        to_filter, unit = _FILTER_SIGMAS[name]
        off = name in _ZERO_IS_OFF
        why = sigma_problem(v, to_filter=to_filter, zero_is_off=off)
        if why:
            raise ValueError(f"{why} -- fix: give {name} in {sigma_range(to_filter=to_filter)} {unit}"
                             + (", or 0 (off)" if off else ""))
        return v

    @field_validator("velocity_tau_s", "clock_drift_tau_s", "yaw_rate_tau_s")
    @classmethod
    def _usable_tau(cls, v: float, info: ValidationInfo) -> float:
        why = tau_problem(v)
        if why:
            raise ValueError(f"{why} -- fix: give {info.field_name} as a positive number of seconds, e.g. "
                             f"{cls.model_fields[str(info.field_name)].default}")
        return v

    @field_validator("gnss_min_satellites")
    @classmethod
    def _satellites_that_can_be_met(cls, v: int) -> int:
        fix = f"give 0 .. {GPS_MAX_PRN} (0: every SD is used; e.g. 4 in a deep canyon)"
        if v < 0:
            raise ValueError(f"is a number of satellites, not {v} -- fix: {fix}")
        if v > GPS_MAX_PRN:
            raise ValueError(f"{v} satellites in common can never be met: GPS has PRNs 1-{GPS_MAX_PRN} (the nominal sky"
                             f" {NOMINAL_SATELLITES}), so every epoch's GNSS would be left out -- fix: {fix}")
        return v

    @model_validator(mode="before")
    @classmethod
    def _no_sigma_means_off(cls, data: object) -> object:
        if isinstance(data, dict) and "height_aiding_sigma_m" in data and data["height_aiding_sigma_m"] is None:
            data = {k: v for k, v in data.items() if k != "height_aiding_sigma_m"}
            data["height_aiding"] = False
        return data

    @property
    def height_aiding_sigma(self) -> float | None:
        """The height-aiding sigma in metres, or None when ``height_aiding`` is off."""
        return self.height_aiding_sigma_m if self.height_aiding else None

    @field_validator("name")
    @classmethod
    def _name_is_a_label(cls, v: str) -> str:
        # the name labels the table's rows, summary.json's statistics and runs.parquet's columns
        if not v.strip() or has_control_chars(v):
            raise ValueError('must be a non-empty name without control characters (it labels the table\'s rows and the '
                             'statistics) -- fix: e.g. name = "GPS+UWB"')
        if len(v.encode()) > MAX_NAME_BYTES:
            raise ValueError(f"is {len(v.encode())} bytes long -- fix: give a name of at most {MAX_NAME_BYTES} "
                             "characters (UTF-8 bytes)")
        return v

    @field_validator("sensors")
    @classmethod
    def _known_sensors(cls, v: list[str]) -> list[str]:
        bad = [s for s in v if s not in SENSOR_NAMES]
        if bad:
            raise ValueError(f"unknown sensor(s) {bad} -- fix: use {', '.join(map(repr, SENSOR_NAMES))}")
        if "gnss" not in v:
            raise ValueError("every solution needs 'gnss' (the relative DGPS backbone) -- fix: add \"gnss\" to sensors")
        return v

    @model_validator(mode="after")
    def _azimuth_needs_bearing(self) -> SolutionSection:
        if self.azimuth == "estimated" and "bearing" not in self.sensors:
            raise ValueError("@azimuth: azimuth = 'estimated' needs the 'bearing' sensor in this solution -- fix: add"
                             ' "bearing" to its sensors, or azimuth = "known"')
        if self.uwb_error_states and "uwb" not in self.sensors:
            raise ValueError("@uwb_error_states: uwb_error_states needs the 'uwb' sensor in this solution -- fix: add"
                             ' "uwb" to its sensors, or uwb_error_states = false')
        if self.uwb_constraints and not self.uwb_error_states:
            raise ValueError("@uwb_constraints: uwb_constraints bound the UWB bias / scale states -- fix: set"
                             " uwb_error_states = true too, or uwb_constraints = false")
        for name in ("uwb_bias_bounds_m", "uwb_scale_bounds"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ValueError(f"@{name}: needs [min, max] with min < max, got [{lo}, {hi}] -- fix: give e.g."
                                 f" {list(type(self).model_fields[name].default)}")
        return self


def paper_solutions() -> list[SolutionSection]:
    """The paper's comparisons (Petovello et al. sec. 5): four sensor sets, azimuth known,
    plus the two azimuth-estimated bearing variants (sec. 5.3)."""
    return [
        SolutionSection(name="GPS", sensors=["gnss"]),
        SolutionSection(name="GPS+UWB", sensors=["gnss", "uwb"]),
        SolutionSection(name="GPS+Bearing", sensors=["gnss", "bearing"]),
        SolutionSection(name="GPS+UWB+Bearing", sensors=["gnss", "uwb", "bearing"]),
        SolutionSection(name="GPS+Bearing az-est", sensors=["gnss", "bearing"], azimuth="estimated"),
        SolutionSection(name="GPS+UWB+Bearing az-est", sensors=["gnss", "uwb", "bearing"], azimuth="estimated"),
    ]


def phase_solutions() -> list[SolutionSection]:
    """The carrier-phase solutions (issue 9; MacGougan (2009) ch. 4: GPS vs tightly-coupled
    GPS+UWB RTK). Code sigma 1 m; UWB with bias and scale states (thesis ch. 4: observable
    with a range of motion, needed below 10 cm, paper section 5.4)."""
    common: dict[str, Any] = {"carrier_phase": True, "pseudorange_sigma_m": 1.0}
    return [
        SolutionSection(name="GPS-phase", sensors=["gnss"], **common),
        SolutionSection(name="GPS-phase+UWB", sensors=["gnss", "uwb"], uwb_error_states=True, **common),
        SolutionSection(name="GPS-phase+UWB+Bearing", sensors=["gnss", "uwb", "bearing"], uwb_error_states=True,
                        **common),
    ]
