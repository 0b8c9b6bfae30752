"""Scenario files: TOML, validated by pydantic, layered over the built-in default.

Layering: ``v2v/config/default.toml`` < the user's scenario file < ``--set key=value``
overrides. Tables merge key by key; lists and scalars replace. Unknown keys are
errors (a misspelt key never silently falls back to a default). The fully resolved
scenario is saved beside every result as ``scenario.resolved.toml``.

``--set`` paths are dotted; list items are addressed by index
(``clusters.0.vehicles=20``); values are parsed as TOML (``lanes=[0,1]``,
``network.name="urban_canyon"``) and fall back to a plain string.
"""

from __future__ import annotations

import difflib
import itertools
import math
import re
import tomllib
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import tomli_w
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from v2v.config.sections import (
    MAX_NAME_BYTES,
    NOMINAL_SATELLITES,
    ExchangeSection,
    SensorsSection,
    SolutionSection,
    a_path,
    has_control_chars,
    paper_solutions,
)
from v2v.errors import UserError, not_a_file
from v2v.faults import FaultSection

DEFAULT_SCENARIO_PATH = Path(__file__).with_name("default.toml")
BACKGROUND_PREFIX = "bg"  # background vehicles are bg.0, bg.1, ...: no cluster may be called that


class _Model(BaseModel):
    # Field types are strict (StrictInt, StrictFloat; v2v.config.sections' too): a wrong TOML
    # type is an error, not coerced (true is no 1.0, "3" no 3); a float field takes an integer
    # (duration_s = 60), a tuple field a TOML array.
    model_config = ConfigDict(extra="forbid", frozen=True)


class NetworkConfig(_Model):
    name: str = ""
    net_file: str = ""
    polygon_files: list[str] = Field(default_factory=list)
    route: str = "default"
    route_edges: list[str] = Field(default_factory=list)
    # ellipsoidal height of the net's z = 0, a road's: -500..9000 m holds every road on Earth, from
    # the Dead Sea's shore (~-430 m) to the highest passes (~5800 m), geoid (+-110 m) included
    origin_h_m: StrictFloat = Field(default=0.0, ge=-500.0, le=9000.0)
    georef_lat_deg: StrictFloat = Field(default=51.0775, ge=-90.0, le=90.0)
    georef_lon_deg: StrictFloat = Field(default=-114.1295, ge=-180.0, le=180.0)

    @field_validator("net_file")
    @classmethod
    def _net_file_is_a_path(cls, v: str) -> str:
        return a_path(v)

    @field_validator("polygon_files")
    @classmethod
    def _polygon_files_are_paths(cls, v: list[str]) -> list[str]:
        for i, f in enumerate(v):
            try:
                a_path(f)
            except ValueError as exc:
                raise ValueError(f"@{i}: {exc}") from None
        return v

    @model_validator(mode="after")
    def _one_source(self) -> NetworkConfig:
        if not self.name and not self.net_file:
            raise ValueError("@name: no network given (network.name and network.net_file are both empty) -- fix: give"
                             ' network.name (a sumo_nets/ name, e.g. "hospital_loop") or network.net_file')
        if self.route_edges and self.route != "default":  # (the listed edges would silently win)
            raise ValueError(f"@route: a named route ({self.route!r}) and route_edges are both given -- fix: give one: "
                             'route = "<name>" or route_edges = [...] (with route left at "default")')
        return self


class VehicleTypeConfig(_Model):
    length_m: StrictFloat = Field(gt=0.5, le=30.0)
    width_m: StrictFloat = Field(gt=0.5, le=4.0)
    height_m: StrictFloat = Field(gt=0.5, le=6.0)
    max_speed_mps: StrictFloat = Field(gt=0.0, le=70.0)
    accel_mps2: StrictFloat = Field(gt=0.0, le=10.0)
    decel_mps2: StrictFloat = Field(gt=0.0, le=12.0)
    driver_imperfection: StrictFloat = Field(default=0.5, ge=0.0, le=1.0)
    antenna_lever_arm_m: tuple[StrictFloat, StrictFloat, StrictFloat] = (-2.0, 0.0, 1.55)

    @model_validator(mode="after")
    def _antenna_on_the_vehicle(self) -> VehicleTypeConfig:
        """The antenna (x forward from the front-bumper centre, y left, z up from the road) must
        be on the body: -length <= x <= 0, |y| <= width / 2, 0 < z <= height + 0.5 m (a mast)."""
        x, y, z = self.antenna_lever_arm_m
        if not (-self.length_m <= x <= 0.0 and abs(y) <= self.width_m / 2 and 0.0 < z <= self.height_m + 0.5):
            raise ValueError(
                f"@antenna_lever_arm_m: ({x:g}, {y:g}, {z:g}) m is off the {self.length_m:g} x {self.width_m:g} x "
                f"{self.height_m:g} m body (x forward from the front-bumper centre, y left, z up from the road) -- fix: "
                f"give -{self.length_m:g} <= x <= 0, |y| <= {self.width_m / 2:g}, 0 < z <= {self.height_m + 0.5:g}")
        return self


class ClusterConfig(_Model):
    name: str
    vehicles: StrictInt = Field(ge=2, le=200)
    vehicle_type: str | list[str] = "passenger"
    lanes: list[StrictInt] = Field(default_factory=lambda: [0], min_length=1)
    time_gap_s: StrictFloat = Field(default=2.0, gt=0.0, le=60.0)
    lead: StrictInt = Field(default=0, ge=0)
    # SUMO time of the cluster's first departure. The warm-up steps SUMO (background traffic
    # and all) until every cluster vehicle has departed, and t_s = 0 is then: a later departure
    # only lengthens the warm-up. At most an hour (3600 s).
    depart_s: StrictFloat = Field(default=0.0, ge=0.0, le=3600.0)
    max_separation_m: StrictFloat = Field(default=300.0, gt=0.0)

    @field_validator("name")
    @classmethod
    def _name_is_a_vehicle_id_prefix(cls, v: str) -> str:
        # its vehicles are <name>.0, <name>.1, ... in SUMO, the outputs and the replay's entity paths;
        # a multi-cluster run keys its solutions <cluster>/<solution>
        if not v.strip() or "/" in v or has_control_chars(v):
            raise ValueError("must be a non-empty name without '/' or control characters (it prefixes its vehicle ids)"
                             ' -- fix: give a name such as "c1"')
        if v == BACKGROUND_PREFIX:
            raise ValueError(f"{v!r} is reserved: background vehicles are {v}.0, {v}.1, ... (SUMO refused them, or"
                             ' they took the cluster\'s ids) -- fix: give the cluster another name, e.g. "c1"')
        return v

    @field_validator("lanes")
    @classmethod
    def _lanes_nonneg(cls, v: list[int]) -> list[int]:
        for i, lane in enumerate(v):
            if lane < 0:
                raise ValueError(f"@{i}: lane indices are >= 0 (0 = rightmost lane) -- fix: give lanes such as [0] or [0, 1]")
        return v

    @model_validator(mode="after")
    def _lead_in_range(self) -> ClusterConfig:
        if self.lead >= self.vehicles:
            raise ValueError(f"@lead: lead={self.lead} but the cluster has only {self.vehicles} vehicles (0-based index)"
                             f" -- fix: give 0 .. {self.vehicles - 1}")
        if isinstance(self.vehicle_type, list) and len(self.vehicle_type) != self.vehicles:
            raise ValueError(f"@vehicle_type: a list of {len(self.vehicle_type)} type(s) for {self.vehicles} vehicles"
                             f" -- fix: give one entry per vehicle ({self.vehicles}), or one type for all")
        return self

    def type_of(self, i: int) -> str:
        return self.vehicle_type[i] if isinstance(self.vehicle_type, list) else self.vehicle_type


class BackgroundConfig(_Model):
    vehicles_per_hour: StrictFloat = Field(default=0.0, ge=0.0, le=20000.0)
    truck_fraction: StrictFloat = Field(default=0.2, ge=0.0, le=1.0)


class Scenario(_Model):
    name: str
    seed: StrictInt = Field(ge=0, le=2**31 - 1)
    duration_s: StrictFloat = Field(gt=0.0, le=86400.0)
    step_length_s: StrictFloat = Field(gt=0.0, le=1.0)
    start_utc: datetime
    network: NetworkConfig
    clusters: list[ClusterConfig] = Field(min_length=1)
    vehicle_types: dict[str, VehicleTypeConfig]
    background: BackgroundConfig = BackgroundConfig()
    sensors: SensorsSection = SensorsSection()
    exchange: ExchangeSection = ExchangeSection()
    solutions: list[SolutionSection] = Field(default_factory=paper_solutions)
    faults: list[FaultSection] = Field(default_factory=list)

    @field_validator("start_utc")
    @classmethod
    def _utc(cls, v: datetime) -> datetime:
        if v.tzinfo is None:
            v = v.replace(tzinfo=UTC)
        v = v.astimezone(UTC)
        if v < datetime(1980, 1, 6, tzinfo=UTC):
            raise ValueError("is before the GPS epoch 1980-01-06T00:00:00Z -- fix: give a later UTC time")
        return v

    @field_validator("name")
    @classmethod
    def _name_is_a_folder_name(cls, v: str) -> str:
        # the default run folder is runs/<name>: "", ".", ".." or a path would put it elsewhere
        if not v.strip() or v in (".", "..") or "/" in v or "\\" in v or has_control_chars(v):
            raise ValueError("must be a non-empty name without '/' or control characters (it names the run folder"
                             ' runs/<name>) -- fix: e.g. name = "urban_canyon"')
        if len(v.encode()) > MAX_NAME_BYTES:
            raise ValueError(f"is {len(v.encode())} bytes long: a run folder's name is at most {MAX_NAME_BYTES} -- fix:"
                             f" give a name of at most {MAX_NAME_BYTES} characters (UTF-8 bytes)")
        return v

    @model_validator(mode="after")
    def _steps_fit(self) -> Scenario:
        # output epochs are the GNSS epochs, and each needs a SUMO step at its time (the truth)
        dt = self.step_length_s
        if self.duration_s < dt:
            raise ValueError(f"@duration_s: {self.duration_s} s is shorter than one step_length_s ({dt} s)"
                             f" -- fix: give at least {dt} s")
        gi = 1.0 / self.sensors.gnss.rate_hz
        if abs(gi / dt - round(gi / dt)) > 1e-6:
            raise ValueError(f"@step_length_s: {dt} s does not divide the GNSS interval {gi:g} s (1 / sensors.gnss.rate_hz;"
                             f" GNSS epochs, the output epochs, must fall on SUMO steps) -- fix: use a step that divides"
                             f" it (e.g. 0.1 or 0.05 s at 10 Hz) or a GNSS rate of 1 / (a multiple of {dt} s)")
        return self

    @model_validator(mode="after")
    def _check_refs(self) -> Scenario:
        names = [c.name for c in self.clusters]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"@clusters: cluster name(s) {dup} appear more than once -- fix: give each cluster its own name")
        for ci, c in enumerate(self.clusters):
            for i in range(c.vehicles):
                t = c.type_of(i)
                if t not in self.vehicle_types:
                    at = f"clusters.{ci}.vehicle_type" + (f".{i}" if isinstance(c.vehicle_type, list) else "")
                    known = ", ".join(map(repr, sorted(self.vehicle_types)))
                    raise ValueError(f"@{at}: vehicle type {t!r} is not defined in [vehicle_types] -- fix: "
                                     + (f"use one of {known} or define [vehicle_types.{t}]" if known else
                                        f"define [vehicle_types.{t}] (none is defined)"))
        sol_names = [s.name for s in self.solutions]
        if len(set(sol_names)) != len(sol_names):
            dup = sorted({n for n in sol_names if sol_names.count(n) > 1})
            raise ValueError(f"@solutions: solution name(s) {dup} appear more than once -- fix: give each solution its own name")
        for si, s in enumerate(self.solutions):
            if self.sensors.gnss.ephemeris == "nominal" and s.gnss_min_satellites > NOMINAL_SATELLITES:
                raise ValueError(
                    f"@solutions.{si}.gnss_min_satellites: {s.gnss_min_satellites} satellites in common can never be met:"
                    f" the nominal sky (sensors.gnss.ephemeris) has {NOMINAL_SATELLITES}, so every epoch's GNSS would be"
                    f" left out -- fix: give 0 .. {NOMINAL_SATELLITES} (0: every SD is used), or a RINEX ephemeris")
            for sensor in s.sensors:
                if not getattr(self.sensors, sensor).enabled:
                    raise ValueError(
                        f"@solutions.{si}.sensors: solution {s.name!r} uses {sensor!r} but sensors.{sensor}.enabled = false"
                        f" -- fix: enable the sensor (sensors.{sensor}.enabled = true) or drop it from the solution"
                    )
        ids = set(self.vehicle_ids())
        uwb, bearing = self.sensors.uwb, self.sensors.bearing
        named = [("sensors.uwb.vehicle_profiles", list(uwb.vehicle_profiles)),
                 ("sensors.uwb.pairs", [v for pair in (uwb.pairs if uwb.pairs != "all" else []) for v in pair]),
                 ("sensors.bearing.measuring", list(bearing.measuring) if bearing.measuring != "all" else []),
                 *((f"faults.{i}.vehicles", list(f.vehicles)) for i, f in enumerate(self.faults) if f.vehicles != "all")]
        for at, listed in named:
            unknown = [v for v in dict.fromkeys(listed) if v not in ids]
            if unknown:
                have = ", ".join(f"{c.name}.0 .. {c.name}.{c.vehicles - 1}" for c in self.clusters)
                raise ValueError(f"@{at}: unknown vehicle id(s) {unknown} -- fix: use the clusters' vehicle ids"
                                 f" (<cluster>.<index>): {have}")
        self._check_uwb_pairs()
        return self

    def _check_uwb_pairs(self) -> None:
        """What the UWB network refuses (v2v.sensors.uwb.UwbNetwork), here so that a scenario
        check needs no sensor module: a radio ranging to itself, and two radio types ranging
        to each other (two-way ranging needs one type: turnaround and timing)."""
        uwb = self.sensors.uwb
        if uwb.pairs != "all":
            for a, b in uwb.pairs:
                if a == b:
                    raise ValueError(f"@sensors.uwb.pairs: pair ({a!r}, {b!r}) ranges a radio to itself -- fix: use two vehicles")
        if not uwb.vehicle_profiles:
            return
        ids = self.vehicle_ids()
        kind = {v: uwb.vehicle_profiles.get(v, uwb.profile).lower() for v in ids}
        for a, b in itertools.combinations(ids, 2) if uwb.pairs == "all" else uwb.pairs:  # (as the network pairs them)
            if kind[a] != kind[b]:
                raise ValueError(f"@sensors.uwb.pairs: vehicles {a!r} ({kind[a]}) and {b!r} ({kind[b]}) carry radios of "
                                 "different types -- fix: range only between radios of one type (list the pairs explicitly)")

    def sparse_sensor_warnings(self) -> list[str]:
        """One line per sensor so slow that the run has fewer than 2 of its epochs (its period
        exceeds duration_s): the GNSS (whose epochs are the output epochs: every statistic then
        rests on one epoch, and a std on none) and a bearing sensor a solution uses. Not an error:
        a user may want it; the command line prints them as the run starts."""
        out = []
        sensors = [("gnss", "GNSS epoch", "its statistics rest on {n} epoch (a std on none)")]
        if any("bearing" in s.sensors for s in self.solutions):
            sensors.append(("bearing", "bearing epoch", "the solutions with bearings get them at {n} epoch"))
        for name, what, result in sensors:
            rate = getattr(self.sensors, name).rate_hz
            # epochs at k / rate_hz from t_s = 0 to duration_s (both ends are SUMO steps)
            n = math.floor(self.duration_s * rate + 1e-6) + 1
            if n < 2:
                out.append(f"sensors.{name}.rate_hz: one {what} every {1.0 / rate:g} s ({rate:g} Hz) in a "
                           f"{self.duration_s:g} s run (duration_s): {result.format(n=n)} -- fix: raise sensors.{name}."
                           f"rate_hz to 1 / duration_s or more (e.g. the default 10 Hz), or duration_s to "
                           f"{1.0 / rate:g} s or more")
        return out

    def vehicle_ids(self) -> list[str]:
        """Cluster vehicle ids, ``<cluster>.<index>`` in departure order."""
        return [f"{c.name}.{i}" for c in self.clusters for i in range(c.vehicles)]

    def to_toml(self) -> str:
        data = self.model_dump(mode="json")
        return tomli_w.dumps(_drop_none(data))


def _drop_none(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _drop_none(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list):
        return [_drop_none(v) for v in obj]
    return obj


# --------------------------------------------------------------------------- layering


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Tables merge recursively; everything else (lists too) is replaced by ``over``."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _split_assignment(assignment: str) -> tuple[str, str]:
    """(key path, value text) of ``key=value``: the first '=' outside a quoted key part."""
    quoted = False
    for i, ch in enumerate(assignment):
        if ch == '"':
            quoted = not quoted
        elif ch == "=" and not quoted:
            return assignment[:i], assignment[i + 1:]
    path, _, text = assignment.partition("=")
    return path, text


def key_parts(path: str) -> list[str]:
    """A dotted key path's parts; a part in double quotes may hold dots, as in TOML
    (``sensors.uwb.vehicle_profiles."c1.2"``, the way errors name such a field)."""
    parts: list[str] = []
    cur: list[str] = []
    quoted = False
    for ch in path.strip():
        if ch == '"':
            quoted = not quoted
        elif ch == "." and not quoted:
            parts.append("".join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    parts.append("".join(cur).strip())
    return parts


def apply_override(data: dict[str, Any], assignment: str) -> dict[str, Any]:
    """Apply one ``a.b.0.c=value`` override to a nested dict (returns a new dict)."""
    if "=" not in assignment:
        raise UserError(f"override {assignment!r} is not key=value", field="--set", fix="write e.g. --set seed=3")
    path, text = _split_assignment(assignment)
    keys = key_parts(path)
    if keys == [""]:
        raise UserError(f"override {assignment!r} has an empty key", field="--set", fix="write e.g. --set seed=3")
    if not all(k.strip() for k in keys):  # "network..name": not silently network.name
        parts = ".".join(k.strip() for k in keys if k.strip())
        raise UserError(f"override {assignment!r} has an empty part in its key {path.strip()!r}", field="--set",
                        fix=f"one '.' between the parts: --set {parts}={text.strip()}" if parts else "write e.g. --set seed=3")
    value = _parse_value(text.strip())
    import copy

    root = copy.deepcopy(data)
    node: Any = root
    for i, k in enumerate(keys):
        last = i == len(keys) - 1
        if isinstance(node, list):
            if not k.isdigit() or int(k) >= len(node):
                raise UserError(
                    f"no item {k!r} in list {'.'.join(keys[:i])!r} (length {len(node)})",
                    field=f"--set {path}",
                    fix="use a 0-based index that exists",
                )
            idx = int(k)
            if last:
                node[idx] = value
            else:
                node = node[idx]
        elif isinstance(node, dict):
            if last:
                node[k] = value
            else:
                if k not in node:
                    if keys[i + 1].isdigit():  # an index into a list the scenario does not have (faults = [])
                        raise UserError(f"no item {keys[i + 1]!r} in list {'.'.join(keys[:i + 1])!r} (it has none)",
                                        field=f"--set {path}", fix=f"give the whole list: --set {k}=[...]")
                    node[k] = {}
                node = node[k]
        else:
            raise UserError(
                f"{'.'.join(keys[:i])!r} is a value, not a table", field=f"--set {path}", fix="check the key path"
            )
    return root


_STUDY_ONLY_KEYS = frozenset({"base", "seeds", "grid", "set"})  # top-level keys of a sweep study (v2v.sweep)


def _format_validation_error(err: ValidationError, data: dict[str, Any], source: str) -> UserError:
    e = _union_member_error(err.errors())
    loc = ".".join(str(p) for p in e["loc"])
    if e["type"] == "extra_forbidden":
        name = str(e["loc"][-1])
        allowed = _allowed_keys_at(e["loc"][:-1])
        close = difflib.get_close_matches(name, allowed, n=1)
        fix = f"did you mean {close[0]!r}?" if close else f"allowed keys here: {', '.join(sorted(allowed))}"
        if len(e["loc"]) == 1 and name in _STUDY_ONLY_KEYS:  # (a study file given to `v2v run`)
            study = "a sweep study file runs with `v2v sweep FILE`"
            fix = f"{fix} ({study})" if close else study
        return UserError(f"unknown key in {source}", field=loc, fix=fix)
    if e["type"] == "missing":
        return UserError(f"required key missing in {source}", field=loc, fix="add it (see the README scenario reference)")
    msg = e["msg"].removeprefix("Value error, ")
    if e["type"] in ("model_type", "dict_type"):
        msg = "is a table of fields, not a single value"
    # a validator may name the field and the fix itself: "@field: message -- fix: what to do"
    fix = _constraint_fix(e)
    if " -- fix: " in msg:
        msg, fix = msg.split(" -- fix: ", 1)
    if msg.startswith("@") and ": " in msg:
        own, msg = msg[1:].split(": ", 1)
        loc = f"{loc}.{own}" if loc else own
    got = e.get("input")
    if isinstance(got, float) and math.isnan(got) and e["type"] in _BOUND_WORDS:  # (NaN fails every bound: the
        return UserError("is nan, not a number", field=loc or "scenario",  # first one said "should be <= ...")
                         fix=f"give a number ({_constraint_fix(e).removeprefix('use ')})", where=source)
    got_s = f" (got {got!r})" if not isinstance(got, dict | list) and got is not None and _quotes_not(msg, got) else ""
    return UserError(f"{msg}{got_s}", field=loc or "scenario", fix=fix, where=source)


# pydantic's tag of a union's member in an error's loc: ("faults", 0, "vehicles", "literal['all']")
_UNION_TAG = re.compile(r"str|int|float|bool|(literal|list|tuple|dict)\[.*\]")
_UNION_WORDS = {"str": "a quoted string", "list[str]": "a list of quoted strings"}


def _union_member_error(errors: list[Any]) -> Any:
    """The first error, where it is a union field's (``Literal["all"] | list[str]``) as the user
    means it: pydantic reports every member's error, each loc tagged with the member. Keep the
    list member's if the value is a list, else the first member's; drop the tag from the loc;
    a value that is none of the members says what the members are."""
    e = errors[0]
    j = next((k for k, p in enumerate(e["loc"]) if isinstance(p, str) and _UNION_TAG.fullmatch(p)), None)
    if j is None:
        return e
    at = e["loc"][:j]
    members = [x for x in errors if x["loc"][:j] == at and len(x["loc"]) > j and isinstance(x["loc"][j], str)
               and _UNION_TAG.fullmatch(x["loc"][j])]
    tags = list(dict.fromkeys(x["loc"][j] for x in members))
    if len(tags) < 2:
        return e
    whole = next((x for x in members if len(x["loc"]) == j + 1), e)["input"]
    chosen = next((x for x in members if isinstance(whole, list) and x["loc"][j].startswith("list[")), e)
    out = {**chosen, "loc": (*at, *chosen["loc"][j + 1:])}
    if len(chosen["loc"]) == j + 1:  # the value is none of the members
        alts = " or ".join(t[len("literal["):-1] if t.startswith("literal[") else _UNION_WORDS.get(t, f"a {t}")
                           for t in tags)
        out.update(type="union_member", msg=f"Input should be {alts}", ctx={"fix": f"give {alts}"})
    return out


_BOUND_WORDS = {"greater_than": ("gt", "> {}"), "greater_than_equal": ("ge", ">= {}"),
                "less_than": ("lt", "< {}"), "less_than_equal": ("le", "<= {}")}
_TYPE_FIXES = {"int_parsing": "give a whole number", "int_from_float": "give a whole number",
               "int_type": "give a whole number{hint}",
               "float_parsing": "give a number (no quotes)", "float_type": "give a number{hint}",
               "bool_parsing": "give true or false", "bool_type": "give true or false{hint}",
               "union_member": "{fix}",
               "string_type": 'give a quoted string, e.g. "name"', "list_type": "give a list, e.g. [0, 1]",
               "too_short": "give at least {min_length} item(s)", "too_long": "give at most {max_length} item(s)",
               "literal_error": "use one of {expected}", "datetime_parsing": 'give an ISO 8601 time, e.g. "2021-04-28T19:00:00Z"',
               "datetime_from_date_parsing": 'give an ISO 8601 time, e.g. "2021-04-28T19:00:00Z"',
               "datetime_type": 'give a date and time, e.g. 2021-04-28T19:00:00Z',
               "model_type": "give a table {{key = value, ...}}, or set one of its keys (e.g. --set {loc}.KEY=VALUE)",
               "dict_type": "give a table {{key = value, ...}}, or set one of its keys (e.g. --set {loc}.KEY=VALUE)"}


# lists of tables: "give a list, e.g. [0, 1]" would mislead there
_TABLE_LIST_FIXES = {
    "clusters": 'give [[clusters]] tables, e.g. clusters = [{name = "c1", vehicles = 3}]',
    "solutions": 'give [[solutions]] tables, e.g. solutions = [{name = "GPS", sensors = ["gnss"]}]',
    "faults": 'give [[faults]] tables, e.g. faults = [{kind = "gnss_outage", start_s = 10.0, duration_s = 5.0}]',
}


def _constraint_fix(e: Any) -> str:
    """The fix part of a pydantic error: the bound or the expected type, when pydantic says it."""
    ctx = e.get("ctx") or {}
    kind = e.get("type", "")
    if kind == "list_type" and len(e.get("loc", ())) == 1 and e["loc"][0] in _TABLE_LIST_FIXES:
        return _TABLE_LIST_FIXES[e["loc"][0]]
    if kind in _BOUND_WORDS:
        key, fmt = _BOUND_WORDS[kind]
        if key in ctx:
            return "use a value " + fmt.format(ctx[key])
    if kind in _TYPE_FIXES:
        got = e.get("input")
        hint = (" (no quotes)" if isinstance(got, str) else " (not true or false)" if isinstance(got, bool)
                else f", not {got!r}" if isinstance(got, int | float) else "")
        try:
            return _TYPE_FIXES[kind].format(hint=hint, loc=".".join(str(p) for p in e["loc"]) or "KEY", **ctx)
        except (KeyError, IndexError):
            return _TYPE_FIXES[kind].split(" {")[0]
    return "correct the value"


def _quotes_not(msg: str, got: Any) -> bool:
    """Show the offending value unless the message already quotes it."""
    return repr(got) not in msg


def _allowed_keys_at(loc: tuple[Any, ...]) -> list[str]:
    """Field names allowed at a validation-error location (for 'did you mean')."""
    model: Any = Scenario
    skip_key = False
    for part in loc:
        if isinstance(part, int):
            continue
        if skip_key:  # the key of a dict[str, Model]
            skip_key = False
            continue
        field = model.model_fields.get(part)
        if field is None:
            return []
        ann = field.annotation
        origin = getattr(ann, "__origin__", None)
        candidates = [c for c in (ann, *getattr(ann, "__args__", ())) if isinstance(c, type) and issubclass(c, BaseModel)]
        if not candidates:
            return []
        model = candidates[0]
        skip_key = origin is dict
    return list(model.model_fields)


def read_toml(path: Path, *, field: str, what: str) -> dict[str, Any]:
    """Read a TOML file (data only); a missing file or bad syntax is a one-line UserError."""
    p = Path(path)
    why = not_a_file(p)
    if why:
        raise UserError(f"{what} {str(p)!r} {why.replace('not found', 'does not exist')}", field=field,
                        fix="give the path to a .toml file")
    try:
        with p.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{p}: not valid TOML ({exc})", field=field, fix="fix the TOML syntax") from None
    except UnicodeDecodeError:
        raise UserError(f"{p}: not UTF-8 text", field=field, fix="save it as UTF-8 TOML") from None
    except OSError as exc:
        raise UserError(f"cannot read {p} ({exc.strerror or exc})", field=field, fix="give a readable file") from None


def load_default_dict() -> dict[str, Any]:
    with DEFAULT_SCENARIO_PATH.open("rb") as f:
        return tomllib.load(f)


def _filled_clusters(data: dict[str, Any], base_cluster: dict[str, Any]) -> dict[str, Any]:
    """``data`` with each cluster filled from the default cluster's values: a cluster list (a
    file's or a --set's) replaces the default list whole, and a user writes just `name` and
    `vehicles`."""
    if isinstance(data.get("clusters"), list):
        data["clusters"] = [deep_merge(base_cluster, c) if isinstance(c, dict) else c for c in data["clusters"]]
    return data


def load_scenario(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (), *,
                  overrides_from: str = "the command line's --set / --seed") -> Scenario:
    """Load, layer and validate a scenario. ``path=None`` gives the built-in default.
    ``overrides`` are ``key=value`` paths; ``overrides_from`` says where they came from in the
    errors (a study passes "the study's [set] / [grid]").

    Raises :class:`UserError` (one line, naming the field) for every user mistake.
    """
    data = load_default_dict()
    base_cluster = data["clusters"][0]
    source = "the default scenario"
    if path is not None:
        p = Path(path)
        user = read_toml(p, field="SCENARIO", what="scenario file")
        data = _filled_clusters(deep_merge(data, user), base_cluster)  # (so that --set can reach their fields)
        source = str(p)
    if "solutions" not in data:
        data["solutions"] = [sol.model_dump(mode="json") for sol in paper_solutions()]
    for ov in overrides:
        data = apply_override(data, ov)
    if overrides:
        data = _filled_clusters(data, base_cluster)  # (a --set clusters=[...] list)
        source += f" with {overrides_from}"
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise _format_validation_error(err, data, source) from None


def save_resolved(scenario: Scenario, path: Path) -> None:
    from v2v.io.atomic import atomic_write_text

    atomic_write_text(path, scenario.to_toml())

