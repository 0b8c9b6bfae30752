"""A scenario value of the wrong type, out of its physical range, naming a vehicle that does not
exist, or a --set path with an empty part: one UserError naming the field as the user writes it
with --set, and a fix that says what is allowed. Never a silent coercion or a silent fix-up."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from v2v.config.scenario import load_scenario
from v2v.errors import UserError

REPO = Path(__file__).resolve().parents[1]

SCENARIOS = REPO / "scenarios"


def _error(*overrides: str) -> UserError:
    with pytest.raises(UserError) as e:
        load_scenario(None, list(overrides))
    return e.value


@pytest.mark.parametrize(("override", "fix"), [
    ("duration_s=true", "give a number"),
    ("duration_s=nan", "give a number (a value <= 86400.0)"),  # (NaN fails every bound: not "use a value <= ...")
    ("duration_s='60'", "give a number (no quotes)"),
    ("clusters.0.vehicles='3'", "give a whole number"),
    ("clusters.0.vehicles=3.0", "give a whole number"),
    ("clusters.0.lanes=[true]", "give a whole number"),
    ('seed="7"', "give a whole number"),
    ("sensors.gnss.errors.noise=0", "give true or false"),
    ("sensors.gnss.errors.ionosphere='off'", "give true or false"),
    ("sensors.uwb.enabled='no'", "give true or false"),
    ("sensors.uwb.enabled=no", "give true or false"),  # not TOML: a plain string
    ("solutions.0.carrier_phase=1", "give true or false"),
    ("exchange.filter_lag_s=true", "give a number"),
    ("vehicle_types.passenger.antenna_lever_arm_m=[-2.0, 0.0, true]", "give a number"),
    ('faults=[{kind="clock_jump", start_s=true}]', "give a number"),
    ('faults=[{kind="cycle_slip", start_s=1.0, size_cycles="2"}]', "give a whole number"),
])
def test_a_value_of_the_wrong_type_is_refused_not_coerced(override, fix):
    """true is no 1.0, "3" no 3, 0 no false, "off" no false: each is an error whose fix names the type."""
    err = _error(override)
    field = override.split("=")[0]
    if field == "faults":
        field = "faults.0." + ("start_s" if "start_s=true" in override else "size_cycles")
    if field.endswith("antenna_lever_arm_m"):
        field += ".2"
    if field.endswith("lanes"):
        field += ".0"
    assert err.field == field and err.fix.startswith(fix), err.one_line()


def test_what_toml_gives_legitimately_is_still_accepted():
    """An integer for a float field, arrays for tuple fields, strings for enums, ISO times."""
    sc = load_scenario(None, ["duration_s=60", "step_length_s=1", "sensors.gnss.rate_hz=1", "network.origin_h_m=1100",
                              "vehicle_types.passenger.antenna_lever_arm_m=[-2, 0, 1]", "exchange.filter_lag_s=1",
                              "solutions=[{name='p', sensors=['gnss'], uwb_bias_bounds_m=[-1, 1]}]",
                              "sensors.gnss.oscillator='OCXO'", "start_utc=2021-04-28T19:00:00Z",
                              "sensors.uwb.pairs=[['c1.0', 'c1.1']]", 'faults=[{kind="clock_jump", start_s=2}]'])
    assert sc.duration_s == 60.0 and isinstance(sc.duration_s, float)
    assert sc.vehicle_types["passenger"].antenna_lever_arm_m == (-2.0, 0.0, 1.0)
    assert sc.solutions[0].uwb_bias_bounds_m == (-1.0, 1.0) and sc.exchange.filter_lag_s == 1.0
    assert sc.faults[0].start_s == 2.0 and sc.sensors.uwb.pairs == [("c1.0", "c1.1")]


@pytest.mark.parametrize("path", sorted(SCENARIOS.glob("*.toml")), ids=lambda p: p.name)
def test_shipped_scenarios_load_and_their_resolved_form_reloads(tmp_path, path):
    sc = load_scenario(path)
    resolved = tmp_path / "scenario.resolved.toml"
    resolved.write_text(sc.to_toml())
    assert load_scenario(resolved) == sc


@pytest.mark.parametrize(("override", "fix"), [
    ("clusters.0.depart_s=1e9", "use a value <= 3600"),  # it would step SUMO through the warm-up for hours
    ("clusters.0.depart_s=nan", "give a number (a value <= 3600"),
    ("network.origin_h_m=1e12", "use a value <= 9000"),
    ("network.origin_h_m=-1000", "use a value >= -500"),
])
def test_physical_quantities_are_bounded(override, fix):
    err = _error(override)
    assert err.field == override.split("=")[0] and err.fix.startswith(fix), err.one_line()


def test_bounds_admit_their_limits():
    sc = load_scenario(None, ["clusters.0.depart_s=3600", "network.origin_h_m=-500"])
    assert sc.clusters[0].depart_s == 3600.0
    assert load_scenario(None, ["network.origin_h_m=9000"]).network.origin_h_m == 9000.0


@pytest.mark.parametrize(("overrides", "field"), [
    (['faults=[{kind="clock_jump", start_s=2.0, vehicles=["c1.9"]}]'], "faults.0.vehicles"),
    (['faults=[{kind="clock_jump", start_s=1.0}, {kind="clock_jump", start_s=2.0, vehicles=["c1.0", "c2.0"]}]'],
     "faults.1.vehicles"),
    (['sensors.bearing.measuring=["c1.7"]'], "sensors.bearing.measuring"),
    (['sensors.uwb.pairs=[["c1.0", "c1.5"]]'], "sensors.uwb.pairs"),
    (['sensors.uwb.vehicle_profiles={"c1.5"="tdc"}'], "sensors.uwb.vehicle_profiles"),
])
def test_an_unknown_vehicle_is_blamed_on_the_field_that_names_it(overrides, field):
    """The default scenario's one cluster c1 has vehicles c1.0 .. c1.2: the fix lists them."""
    err = _error(*overrides)
    assert err.field == field, err.one_line()
    assert "c1.0 .. c1.2" in err.fix and "unknown vehicle" in err.message


@pytest.mark.parametrize(("override", "field"), [
    ('clusters.0.vehicle_type="bus"', "clusters.0.vehicle_type"),
    ('clusters.0.vehicle_type=["passenger", "bus", "truck"]', "clusters.0.vehicle_type.1"),
])
def test_an_undefined_vehicle_type_names_the_cluster_field_and_the_defined_types(override, field):
    err = _error(override)
    assert err.field == field and "'bus'" in err.message, err.one_line()
    assert "'passenger'" in err.fix and "'truck'" in err.fix


@pytest.mark.parametrize("pairs", ['[["c1.0"]]', '[["c1.0", "c1.1", "c1.2"]]', '[["c1.0", 3]]', '["c1.0"]'])
def test_a_uwb_pair_that_is_not_two_ids_names_the_pair(pairs):
    err = _error(f"sensors.uwb.pairs={pairs}")
    assert err.field == "sensors.uwb.pairs.0" and "two vehicle ids" in err.message, err.one_line()
    assert err.fix.startswith('give "all" or a list of [id, id] pairs')
    assert "literal" not in err.one_line()


@pytest.mark.parametrize(("override", "field"), [
    ("sensors.uwb.pairs='some'", "sensors.uwb.pairs"),
    ("sensors.bearing.measuring=3", "sensors.bearing.measuring"),
    ("sensors.bearing.measuring=[1]", "sensors.bearing.measuring.0"),
    ('faults=[{kind="clock_jump", start_s=2.0, vehicles="c1.0"}]', "faults.0.vehicles"),
    ("clusters.0.vehicle_type=3", "clusters.0.vehicle_type"),
])
def test_a_union_field_error_names_the_field_not_pydantic_internals(override, field):
    """'all'-or-a-list and type-or-list fields: no pydantic member tag (literal['all'], str) in
    the path, and a fix that is not "use one of 'all'" alone."""
    err = _error(override)
    assert err.field == field, err.one_line()
    assert "literal" not in err.one_line() and ("list" in err.fix or "string" in err.fix), err.one_line()


@pytest.mark.parametrize("key", ["network..name", ".seed", "seed.", "clusters..0.vehicles"])
def test_a_set_path_with_an_empty_part_is_refused(key):
    err = _error(f"{key}=1")
    assert err.field == "--set" and repr(f"{key}=1") in err.message, err.one_line()


def test_the_cli_says_each_mistake_in_one_line_exit_2(tmp_path):
    for kv, field in [("duration_s=true", "duration_s"), ('sensors.bearing.measuring=["c1.77"]', "sensors.bearing.measuring"),
                      ("network..name=1", "--set"), ("clusters.0.depart_s=1e9", "clusters.0.depart_s")]:
        p = subprocess.run([sys.executable, "-m", "v2v", "scenario", "check", str(SCENARIOS / "open_highway.toml"),
                            "--set", kv], cwd=tmp_path, capture_output=True, text=True, timeout=300)
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
        assert lines[0].startswith(f"v2v: error: {field}: ") and " -- fix: " in lines[0], lines[0]
        assert p.stdout == ""


@pytest.mark.parametrize(("fault", "field", "fix"), [
    # a field the kind does not act on is not silently ignored (prns on a pr_blunder blundered every satellite)
    ('{kind="pr_blunder", start_s=1.0, duration_s=2.0, size_m=30.0, prns=[5]}', "faults.0.prns", "remove prns"),
    ('{kind="clock_jump", start_s=1.0, probability=0.5}', "faults.0.probability", "remove probability"),
    ('{kind="gnss_outage", start_s=1.0, duration_s=1.0, sensor="uwb"}', "faults.0.sensor", "remove sensor"),
    ('{kind="satellites_lost", start_s=1.0, duration_s=1.0, prns=[3], size_cycles=2}', "faults.0.size_cycles",
     "remove size_cycles"),
    # non-finite sizes: NaN/Inf measurements are the nonfinite kind's (its size_m: inf for +Inf, else NaN)
    ('{kind="pr_blunder", start_s=1.0, duration_s=2.0, size_m=nan}', "faults.0.size_m", "give a finite size_m"),
    ('{kind="clock_jump", start_s=1.0, size_m=inf}', "faults.0.size_m", "give a finite size_m"),
    ('{kind="uwb_scale_drift", start_s=1.0, scale_ppm=nan}', "faults.0.scale_ppm", "give a finite scale_ppm"),
    # finite but absurd: squares of such errors overflowed (numpy RuntimeWarnings in the run)
    ('{kind="uwb_replace", start_s=1.0, vehicles=["c1.1"], size_m=1e300}', "faults.0.size_m", "give |size_m| <= 3e+08"),
    ('{kind="uwb_scale_drift", start_s=1.0, scale_ppm=1e300}', "faults.0.scale_ppm", "give |scale_ppm| <= 1e+06"),
    ('{kind="nonfinite", start_s=1.0, duration_s=1.0, size_m=-inf}', "faults.0.size_m", "give size_m = inf"),
    ('{kind="nonfinite", start_s=1.0, duration_s=1.0, size_m=5.0}', "faults.0.size_m", "give size_m = inf"),
    # a slip beyond int64 was an OverflowError traceback in the run
    ('{kind="cycle_slip", start_s=1.0, size_cycles=100000000000000000000}', "faults.0.size_cycles", "use a value <="),
    ('{kind="satellites_lost", start_s=1.0, duration_s=1.0, prns=[5, -3]}', "faults.0.prns.1", "use a value >= 1"),
    ('{kind="satellites_lost", start_s=1.0, duration_s=1.0, prns=[5, 99]}', "faults.0.prns.1", "use a value <= 32"),
    # what a kind needs names the field it needs, with a fix
    ('{kind="satellites_lost", start_s=1.0, duration_s=1.0}', "faults.0.prns", "give prns"),
    ('{kind="satellites_lost", start_s=1.0, prns=[3]}', "faults.0.duration_s", "give duration_s"),
    ('{kind="cycle_slip", start_s=1.0}', "faults.0.size_cycles", "give size_cycles"),
    ('{kind="uwb_replace", start_s=1.0}', "faults.0.vehicles", "give e.g. vehicles"),
])
def test_a_fault_field_its_kind_ignores_or_cannot_use_is_refused(fault, field, fix):
    err = _error(f"faults=[{fault}]")
    assert err.field == field and err.fix.startswith(fix), err.one_line()


def test_fault_fields_a_kind_uses_and_nonfinite_sizes_are_accepted(tmp_path):
    faults = ('faults=[{kind="nonfinite", start_s=1.0, duration_s=1.0, sensor="uwb", size_m=inf, probability=0.5}, '
              '{kind="nonfinite", start_s=1.0, duration_s=1.0, size_m=nan}, '
              '{kind="cycle_slip", start_s=1.0, size_cycles=-2, prns=[4]}, '
              '{kind="uwb_replace", start_s=1.0, vehicles=["c1.1"], size_m=0.4, scale_ppm=3000.0}, '
              '{kind="satellites_lost", start_s=1.0, duration_s=1.0, prns=[1, 32]}]')
    sc = load_scenario(None, [faults])
    assert [f.kind for f in sc.faults] == ["nonfinite", "nonfinite", "cycle_slip", "uwb_replace", "satellites_lost"]
    resolved = tmp_path / "scenario.resolved.toml"  # (every field written, its defaults included)
    resolved.write_text(sc.to_toml())
    again = load_scenario(resolved).faults
    assert again[0] == sc.faults[0] and again[2:] == sc.faults[2:] and math.isnan(again[1].size_m)  # (nan != nan)


@pytest.mark.parametrize(("override", "field", "fix"), [
    # a NUL in a name or a path was a ValueError traceback (embedded null byte) when the run made its folder
    ('name="a\\u0000b"', "name", "e.g. name ="),
    ('name="a\\nb"', "name", "e.g. name ="),
    ('name="' + "x" * 101 + '"', "name", "give a name of at most 100"),  # (was "--out: cannot create ..." without --out)
    ('network.net_file="a\\u0000b"', "network.net_file", "give the file's path"),
    ('network.polygon_files=["x.poly.xml", "a\\u0000b"]', "network.polygon_files.1", "give the file's path"),
    ('sensors.gnss.ephemeris="a\\u0000b"', "sensors.gnss.ephemeris", "give the RINEX file's path"),
    # cluster names prefix vehicle ids: "bg" took the background vehicles' ids (SUMO refused those, and the
    # refusals were logged as teleports of the cluster's own vehicles); "" gave ids ".0", ".1"
    ('clusters.0.name="bg"', "clusters.0.name", "give the cluster another name"),
    ('clusters.0.name=""', "clusters.0.name", "give a name such as"),
    ('clusters.0.name="a/b"', "clusters.0.name", "give a name such as"),
    ('clusters.0.name="a\\tb"', "clusters.0.name", "give a name such as"),
    # a solution's name labels the table's rows and the statistics: "" left them blank, "a\nb" split a row
    ('solutions=[{name="", sensors=["gnss"]}]', "solutions.0.name", "e.g. name ="),
    ('solutions=[{name=" ", sensors=["gnss"]}]', "solutions.0.name", "e.g. name ="),
    ('solutions=[{name="a\\nb", sensors=["gnss"]}]', "solutions.0.name", "e.g. name ="),
    ('solutions=[{name="' + "x" * 101 + '", sensors=["gnss"]}]', "solutions.0.name", "give a name of at most 100"),
])
def test_names_and_paths_that_cannot_be_folders_ids_or_files_are_refused(override, field, fix):
    err = _error(override)
    assert err.field == field and err.fix.startswith(fix), err.one_line()


@pytest.mark.parametrize(("override", "field", "fix"), [
    ('network.name=""', "network.name", "give network.name"),
    ("clusters.0.lanes=[0, -1]", "clusters.0.lanes.1", "give lanes such as"),
    ('solutions=[{name="a", sensors=["gnss", "lidar"]}]', "solutions.0.sensors", "use 'gnss', 'uwb', 'bearing'"),
    ('solutions=[{name="a", sensors=["uwb"]}]', "solutions.0.sensors", 'add "gnss"'),
    ('solutions=[{name="a", sensors=["gnss"], azimuth="estimated"}]', "solutions.0.azimuth", 'add "bearing"'),
    ('solutions=[{name="a", sensors=["gnss"], uwb_error_states=true}]', "solutions.0.uwb_error_states", 'add "uwb"'),
    ('solutions=[{name="a", sensors=["gnss", "uwb"], uwb_constraints=true}]', "solutions.0.uwb_constraints",
     "set uwb_error_states = true"),
    ('solutions=[{name="a", sensors=["gnss", "uwb"], uwb_scale_bounds=[1, 0]}]', "solutions.0.uwb_scale_bounds",
     "give e.g. [0.0, 0.005]"),
    ("clusters.0=5", "clusters.0", "give a table"),
    ("sensors=1", "sensors", "give a table"),
    ("start_utc=19:00:00", "start_utc", "give a date and time"),
])
def test_a_rule_s_error_names_the_field_and_a_fix_not_correct_the_value(override, field, fix):
    err = _error(override)
    assert err.field == field and err.fix.startswith(fix), err.one_line()
    assert "ClusterConfig" not in err.message and "SensorsSection" not in err.message


def test_a_polygon_file_that_is_a_folder_or_empty_says_so(tmp_path):
    from v2v.run import check_scenario

    for given, why in ((str(tmp_path), "is a folder"), ("", "is empty"), (str(tmp_path / "no.poly.xml"), "not found")):
        with pytest.raises(UserError) as e:
            check_scenario(load_scenario(None, [f"network.polygon_files=[{given!r}]"]))
        assert e.value.field == "network.polygon_files.0" and e.value.message.endswith(why), e.value.one_line()


# ------------------------------------------------------------------ what the filter can use


def _solution_error(**fields: object) -> UserError:
    items = ", ".join(f"{k}={v}" for k, v in fields.items())
    return _error(f'solutions=[{{name="s", sensors=["gnss", "uwb", "bearing"], {items}}}]')


def _one_line_naming(err: UserError, field: str) -> None:
    line = err.one_line()
    assert err.field == f"solutions.0.{field}" and "\n" not in line and " -- fix: " in line, line


def test_gnss_min_satellites_is_at_most_what_a_sky_can_hold():
    """A count of satellites in common with the lead that no sky can give left every epoch's
    GNSS out, silently. v2v tracks GPS only (PRNs 1-32): 32 is the most any sky can hold, the
    nominal one's 27 slots the most it holds; one more is refused, naming the field and its range."""
    from v2v.config.sections import GPS_MAX_PRN, NOMINAL_SATELLITES

    assert (GPS_MAX_PRN, NOMINAL_SATELLITES) == (32, 27)
    sol = 'solutions=[{{name="s", sensors=["gnss"], gnss_min_satellites={}}}]'
    assert load_scenario(None, [sol.format(27)]).solutions[0].gnss_min_satellites == 27
    err = _error(sol.format(28))
    _one_line_naming(err, "gnss_min_satellites")
    assert "nominal sky" in err.message and err.fix.startswith("give 0 .. 27"), err.one_line()
    rinex = 'sensors.gnss.ephemeris="brdc1180.21n"'  # (a file's existence is the set-up's check)
    assert load_scenario(None, [rinex, sol.format(32)]).solutions[0].gnss_min_satellites == 32
    for n in (33, 1000):
        err = _error(rinex, sol.format(n))
        _one_line_naming(err, "gnss_min_satellites")
        assert "PRNs 1-32" in err.message and err.fix.startswith("give 0 .. 32"), err.one_line()
    err = _error(sol.format(-1))
    _one_line_naming(err, "gnss_min_satellites")
    assert err.fix.startswith("give 0 .. 32"), err.one_line()


def test_gnss_min_satellites_is_at_most_what_the_rinex_sky_holds(tmp_path):
    """With a RINEX sky the bound is the file's satellites, known once the file is read: the
    repository's excerpt of brdc1180.21n holds PRNs 1, 8 and 14, so 3 is accepted and 4 is
    refused by `v2v scenario check`'s check and by the run, before a run folder is written."""
    from v2v.run import check_scenario, run_scenario

    shutil.copy(REPO / "tests" / "data" / "gnss_2021-04-28" / "brdc1180.21n.excerpt", tmp_path / "brdc.21n")
    base = [f'sensors.gnss.ephemeris="{tmp_path / "brdc.21n"}"', "start_utc=2021-04-28T19:00:00Z", "duration_s=2.0"]
    sol = 'solutions=[{{name="s", sensors=["gnss"], gnss_min_satellites={}}}]'
    check_scenario(load_scenario(None, [*base, sol.format(3)]))
    bad = load_scenario(None, [*base, sol.format(4)])
    for check in (lambda: check_scenario(bad), lambda: run_scenario(bad, tmp_path / "r", quiet=True, replay=False)):
        with pytest.raises(UserError) as ei:
            check()
        _one_line_naming(ei.value, "gnss_min_satellites")
        assert "has 3" in ei.value.message and ei.value.fix.startswith("give 0 .. 3"), ei.value.one_line()
    assert not (tmp_path / "r").exists()


def test_a_run_past_the_ephemeris_end_blames_its_duration_and_one_before_it_its_start(tmp_path):
    """A run that starts inside a navigation file's span and runs past its end is too long
    (duration_s, with the longest that fits), not badly started; one that starts outside it
    names start_utc. Both messages give the span's ends with their dates."""
    from v2v.sensors.gnss.rinex import read_rinex_nav
    from v2v.sensors.gnss.source import ephemeris_source
    from v2v.sensors.gnss.time import gps_s_to_utc

    nav = REPO / "tests" / "data" / "gnss_2021-04-28" / "brdc1180.21n.excerpt"
    lo, hi = read_rinex_nav(nav).validity()
    start = hi - 600.0  # 10 min before the span's end
    with pytest.raises(UserError) as ei:
        ephemeris_source(str(nav), start, 1200.0)
    assert ei.value.field == "duration_s" and ei.value.fix.startswith("give duration_s <= 600 s"), ei.value.one_line()
    assert f"{gps_s_to_utc(hi):%Y-%m-%d %H:%M}" in ei.value.message
    ephemeris_source(str(nav), start, 600.0)  # (exactly to the end: inside)
    with pytest.raises(UserError) as ei:
        ephemeris_source(str(nav), lo - 60.0, 10.0)
    assert ei.value.field == "start_utc" and "starts outside" in ei.value.message, ei.value.one_line()


def test_the_nominal_sky_has_the_satellites_the_bound_says():
    from v2v.config.sections import NOMINAL_SATELLITES
    from v2v.sensors.gnss.source import ephemeris_source

    sky = ephemeris_source("nominal", 1_300_000_000.0, 60.0)
    assert len(set(int(p) for p in sky.prns())) == NOMINAL_SATELLITES


# every solution field the filter squares into a variance: (field, factor to the filter's unit, 0 = off)
_DEG = math.pi / 180.0
FILTER_SIGMAS = [("pseudorange_sigma_m", 1.0, False), ("doppler_sigma_mps", 1.0, False), ("uwb_sigma_m", 1.0, False),
                 ("bearing_sigma_deg", _DEG, False), ("velocity_sigma_horizontal_mps", 1.0, False),
                 ("velocity_sigma_vertical_mps", 1.0, False), ("clock_drift_sigma_mps", 1.0, False),
                 ("height_aiding_sigma_m", 1.0, False), ("phase_sigma_m", 1.0, False),
                 ("azimuth_rw_deg_per_sqrt_s", _DEG, True), ("yaw_rate_sigma_deg_s", _DEG, True)]


def test_the_list_of_filter_sigmas_is_every_sigma_field_of_a_solution():
    from v2v.config.sections import _FILTER_SIGMAS, SolutionSection

    names = {f for f in SolutionSection.model_fields if "sigma" in f or "_rw_" in f}
    assert names == {f for f, _, _ in FILTER_SIGMAS} == set(_FILTER_SIGMAS)


def _edge(x: float, ok, toward: float) -> tuple[float, float]:
    """(last accepted, first refused) float64 stepping from ``x``, within a few ulps of the edge,
    toward ``toward``."""
    for _ in range(8):  # (x refused: step back inside first)
        if ok(x):
            break
        x = math.nextafter(x, -toward if toward else math.inf)
    for _ in range(8):
        if not ok(math.nextafter(x, toward)):
            break
        x = math.nextafter(x, toward)
    assert ok(x) and not ok(math.nextafter(x, toward))
    return x, math.nextafter(x, toward)


@pytest.mark.parametrize(("field", "to_filter", "zero_is_off"), FILTER_SIGMAS)
def test_a_filter_sigma_must_give_a_positive_normal_float64_variance(field, to_filter, zero_is_off):
    """inf, a sigma whose square underflows to 0 (a zero-variance scalar update divides by ~0) and
    one whose 2 sigma^2 overflows to inf are refused in one line naming the field and its range.
    Boundary: in the filter's unit (radians for a *_deg field, the pipeline's conversion) the
    smallest accepted sigma is 2^-511 (its square is float64's smallest normal, 2^-1022) and
    the largest sqrt(max / 2) (2 sigma^2 is the largest finite float64); the floats next to them
    are refused. Both ends the fix prints are accepted."""
    from v2v.errors import SIGMA_MAX, SIGMA_MIN

    def ok(v: float) -> bool:
        try:
            load_scenario(None, [f'solutions=[{{name="s", sensors=["gnss", "bearing"], {field}={v!r}}}]'])
        except UserError:
            return False
        return True

    for bad in ("inf", "-inf", "1e-300", "1e200", "-1.0") + (() if zero_is_off else ("0.0",)):
        err = _solution_error(**{field: bad})
        _one_line_naming(err, field)
        if bad not in ("-1.0", "0.0", "-inf"):
            assert err.fix.startswith(f"give {field} in ["), err.one_line()
    if zero_is_off:
        assert getattr(load_scenario(None, [f'solutions=[{{name="s", sensors=["gnss"], {field}=0.0}}]']).solutions[0],
                       field) == 0.0
    lo_ok, lo_bad = _edge(SIGMA_MIN / to_filter, ok, 0.0)
    hi_ok, hi_bad = _edge(SIGMA_MAX / to_filter, ok, math.inf)
    if to_filter == 1.0:
        assert (lo_ok, hi_ok) == (SIGMA_MIN, SIGMA_MAX) == (2.0 ** -511, 9.480751908109176e153)
    assert (lo_ok * to_filter) ** 2 >= 2.2250738585072014e-308 > (lo_bad * to_filter) ** 2
    assert math.isfinite(2.0 * (hi_ok * to_filter) ** 2) and not math.isfinite(2.0 * (hi_bad * to_filter) ** 2)
    printed = _solution_error(**{field: "inf"}).fix.split("[", 1)[1].split("]")[0]
    assert all(ok(float(x)) for x in printed.split(", ")), printed


@pytest.mark.parametrize("field", ["velocity_tau_s", "clock_drift_tau_s", "yaw_rate_tau_s"])
def test_a_gauss_markov_time_constant_must_be_finite_and_positive(field):
    """tau = inf (or one so small that the model's rate 1 / tau overflows) is refused in one line
    naming the field; the smallest normal float64 is accepted."""
    for bad in ("inf", "nan", "0.0", "-2.0", "1e-310"):
        _one_line_naming(_solution_error(**{field: bad}), field)
    sol = f'solutions=[{{name="s", sensors=["gnss"], {field}=2.2250738585072014e-308}}]'
    assert getattr(load_scenario(None, [sol]).solutions[0], field) == 2.2250738585072014e-308


def test_the_cli_refuses_an_unusable_filter_sigma_in_one_line(tmp_path):
    for kv, field in [("solutions.0.pseudorange_sigma_m=1e-300", "solutions.0.pseudorange_sigma_m"),
                      ("solutions.0.velocity_tau_s=inf", "solutions.0.velocity_tau_s"),
                      ("solutions.0.gnss_min_satellites=40", "solutions.0.gnss_min_satellites")]:
        p = subprocess.run([sys.executable, "-m", "v2v", "scenario", "check", str(SCENARIOS / "open_highway.toml"),
                            "--set", kv], cwd=tmp_path, capture_output=True, text=True, timeout=300)
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
        assert lines[0].startswith(f"v2v: error: {field}: ") and " -- fix: " in lines[0], lines[0]


def test_script_options_blame_the_option_that_set_a_field():
    """v2v.errors.script_options: an error naming a field an option set (or a part of it: a list's
    item) names the option, the field after the message, without the "--set" source the scenario
    would name; the longest matching path wins ("*" matches one part); any other error, and an
    error outside the block, is unchanged."""
    from v2v.errors import script_options

    options = {"clusters.0.vehicles": "--vehicles", "clusters.0.lanes": "--lanes", "solutions.*": "--solution-set",
               "solutions.*.uwb_sigma_m": "--uwb-sigma-m"}
    cases = [(["clusters.0.vehicles=1"], "--vehicles", "clusters.0.vehicles"),
             (["clusters.0.lanes=[0, -1]"], "--lanes", "clusters.0.lanes.1"),
             (['solutions=[{name="a", sensors=["gnss", "uwb"], uwb_sigma_m=inf}]'], "--uwb-sigma-m",
              "solutions.0.uwb_sigma_m"),
             (['solutions=[{name="a", sensors=["gnss"], gnss_min_satellites=28}]'], "--solution-set",
              "solutions.0.gnss_min_satellites")]
    for overrides, option, field in cases:
        plain = _error(*overrides)
        with pytest.raises(UserError) as e, script_options(options):
            load_scenario(None, overrides)
        assert (plain.field, e.value.field, e.value.fix) == (field, option, plain.fix), e.value.one_line()
        assert e.value.message == f"{plain.detail} ({field})" and "--set" not in e.value.one_line()
        assert "--set" in plain.one_line()  # (outside the block: the scenario's own error)
    with pytest.raises(UserError) as e, script_options(options):
        load_scenario(None, ["duration_s=-1"])
    assert e.value.field == "duration_s"
    with pytest.raises(UserError) as e, script_options(options):
        raise UserError("lane 5 is not on the route", field="clusters.0.lanes", fix="use 0..1")  # (a run's set-up)
    assert e.value.one_line() == "--lanes: lane 5 is not on the route (clusters.0.lanes) -- fix: use 0..1"


def test_set_reaches_quoted_keys_with_dots_as_errors_name_them():
    """Vehicle ids hold a dot: an error names such a field `sensors.uwb.vehicle_profiles."c1.2"`,
    and --set takes the same quoted part (it split it at the dot into "c1 and 2")."""
    sc = load_scenario(None, ['sensors.uwb.vehicle_profiles."c1.2"="mssi"'])
    assert sc.sensors.uwb.vehicle_profiles == {"c1.2": "mssi"}
    err = _error('sensors.uwb.vehicle_profiles."c1.2"="nope"')
    assert err.field == 'sensors.uwb.vehicle_profiles."c1.2"', err.one_line()


def test_an_index_into_a_list_the_scenario_lacks_says_so():
    """faults is empty by default: faults.0.start_s has no item to set (it said "faults: Input
    should be a valid list", an index having made a table of it)."""
    err = _error("faults.0.start_s=1.0")
    assert err.field == "--set faults.0.start_s" and "no item '0' in list 'faults'" in err.message, err.one_line()
    assert err.fix == "give the whole list: --set faults=[...]"


def test_clusters_given_by_set_are_filled_from_the_default_cluster_as_a_file_s_are():
    sc = load_scenario(None, ['clusters=[{name="X"}]'])
    default = load_scenario(None).clusters[0]
    assert sc.clusters[0].name == "X" and sc.clusters[0].model_dump(exclude={"name"}) == default.model_dump(exclude={"name"})


def test_a_named_route_and_route_edges_together_are_refused():
    """Both given: the listed edges silently won."""
    err = _error('network.route_edges=["J-NW"]', 'network.route="visit"')
    assert err.field == "network.route" and err.fix.startswith("give one"), err.one_line()


@pytest.mark.parametrize("key", ["clusters", "solutions", "faults"])
def test_a_list_of_tables_given_a_value_gets_an_example_that_loads(key):
    """`clusters = 3`: the fix was "give a list, e.g. [0, 1]", itself wrong there. It now gives
    [[key]] tables with an example, and the example is a valid value."""
    err = _error(f"{key}=3")
    assert err.field == key and err.fix.startswith(f"give [[{key}]] tables, e.g. "), err.one_line()
    example = err.fix.split("e.g. ", 1)[1]
    assert len(getattr(load_scenario(None, [example]), key)) == 1
