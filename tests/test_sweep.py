"""`v2v sweep`: Monte Carlo studies on Dask.

What must hold: a study file is validated whole before any run starts; each run happens in a
worker process and lands in its own run folder; runs.parquet has one row per run whose
numbers are the run's summary.json; a rerun executes only the missing runs; a run SUMO rejects
is a row with a one-line error while the others succeed; an external scheduler gives the
same numbers as the built-in local cluster (same seeds -> bit-identical runs); the report's
intervals are Student-t intervals of the mean across seeds.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from v2v.errors import UserError
from v2v.sweep import (
    META_COLUMNS,
    RunTask,
    execute_run,
    flatten_summary,
    load_study,
    run_study,
    t_interval_half_width,
    toml_inline,
)

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "scenarios" / "sweeps" / "example_sweep.toml"

TINY = """\
seeds = [1, 2]
[set]
duration_s = 5.0
solutions = [{name = "GPS", sensors = ["gnss"]}]
[grid]
"network.name" = ["hospital_loop", "residential"]
"""


def _cli(argv: list[str]) -> int:
    """`v2v sweep ...` through the real CLI (whose parser must have the sweep command)."""
    from v2v import cli

    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert "sweep" in sub.choices
    return cli.main(argv)


def _metric_columns(df: pd.DataFrame) -> list[str]:
    return [c for c in df.columns if c not in META_COLUMNS]


# --------------------------------------------------------------------------- the study file (no runs)


@pytest.mark.parametrize("value", [
    3, -2.5, 1e-7, float("inf"), True, "urban \"canyon\"\n", [0, 1], [],
    [{"name": "GPS+UWB", "sensors": ["gnss", "uwb"], "uwb_sigma_m": 0.25}],
    {"profile": "tdc", "pairs": "all"}, datetime(2021, 4, 28, 19, tzinfo=UTC),
])
def test_grid_values_round_trip_through_set_syntax(value):
    # grid values reach load_scenario as `--set key=<inline TOML>`: the text must parse back to the value
    assert tomllib.loads(f"v = {toml_inline(value)}")["v"] == value


@pytest.mark.parametrize("text, field", [
    ('[grid]\n"network.nme" = ["residential"]\n', "network.nme"),  # typo in a grid path
    ('[grid]\n"clusters.0.vehicles" = [3, 1]\n', "clusters.0.vehicles"),  # second value invalid (>= 2)
    ('[set]\n"duration_s" = -1.0\n', "duration_s"),
    ('[grid]\n"network.name" = "residential"\n', "grid.network.name"),  # not a list
    ('seed = [1, 2]\n', "seed"),  # unknown study key
    ('seeds = {start = 1, count = 0}\n', "seeds"),
    ('seeds = [1, 1]\n', "seeds"),
    ('base = "nowhere.toml"\n', "base"),
    ('[grid]\n"seed" = [1, 2]\n', "grid.seed"),
    ('[set]\nseed = 99\n', "set.seed"),  # (it would be silently replaced by each run's seed from seeds)
    ('seeds = {start = true, count = 2}\n', "seeds"),  # true is not a number (as in the list form)
    ('seeds = {start = 1, count = true}\n', "seeds"),
    # one path inside another: the grid's whole cluster would override (or be overridden by) the field
    ('[grid]\n"clusters.0" = [{name = "c1", vehicles = 2}]\n"clusters.0.vehicles" = [3]\n', "grid.clusters.0.vehicles"),
    ('[set]\n"clusters.0.vehicles" = 5\n[grid]\n"clusters.0" = [{name = "c1", vehicles = 2}]\n', "set.clusters.0.vehicles"),
    # key paths the scenario has no place for: named as the study's keys, not as a --set
    ('[grid]\n"clusters.5.vehicles" = [2, 3]\n', "grid.clusters.5.vehicles: no item '5'"),
    ('[set]\n"clusters.5.vehicles" = 2\n', "set.clusters.5.vehicles: no item '5'"),
    ('[grid]\n"clusters..vehicles" = [2]\n', "grid.clusters..vehicles: key 'clusters..vehicles' has an empty part"),
    ('[grid]\n"" = [2]\n', "grid.: an empty key"),
])
def test_bad_study_fails_up_front_naming_the_field(tmp_path, text, field):
    study = tmp_path / "study.toml"
    study.write_text(text)
    with pytest.raises(UserError) as err:
        run_study(study, tmp_path / "out")
    assert field in err.value.one_line() and "\n" not in err.value.one_line()
    assert "--set" not in err.value.one_line()  # (a study has no command line to fix)
    assert not (tmp_path / "out").exists(), "nothing may start (or be written) before the whole study validates"


def test_a_sensor_too_slow_for_a_run_is_one_warning_naming_its_grid_points(tmp_path, monkeypatch, capsys):
    """`Scenario.sparse_sensor_warnings` for a study: a 2 s run at 0.4 Hz GNSS has one GNSS
    epoch (t_s = 0; the next is at 2.5 s), at 10 Hz 21. The line is given once, naming the grid
    points it holds for unless it holds for all of them, and `v2v sweep` prints it on stderr
    before any run (also with --quiet), as `v2v run` does; the study still runs (exit 0)."""
    import v2v.sweep as sweep_mod

    study = tmp_path / "study.toml"
    study.write_text('seeds = [1, 2]\n[set]\nduration_s = 2.0\nsolutions = [{name = "GPS", sensors = ["gnss"]}]\n'
                     '[grid]\n"sensors.gnss.rate_hz" = [10.0, 0.4]\n"clusters.0.vehicles" = [2, 3]\n')
    (w,) = load_study(study).warnings
    assert w.startswith("sensors.gnss.rate_hz: ") and "rest on 1 epoch" in w, w
    assert w.endswith("(grid: sensors.gnss.rate_hz=0.4, clusters.0.vehicles=2; "
                      "sensors.gnss.rate_hz=0.4, clusters.0.vehicles=3)"), w
    study.write_text('[set]\nduration_s = 2.0\n"sensors.gnss.rate_hz" = 0.4\n[grid]\n"clusters.0.vehicles" = [2, 3]\n')
    (w_all,) = load_study(study).warnings
    assert w_all.startswith("sensors.gnss.rate_hz: ") and "(grid:" not in w_all, w_all
    study.write_text('[set]\nduration_s = 2.0\n')
    assert load_study(study).warnings == ()

    calls = []

    def fake_run_study(st, out, **kw):  # (the runs are not what this test is about)
        calls.append(st)
        return sweep_mod.SweepResult(out_dir=Path(out), total=0, executed=0, skipped=0, failed=0, wall_s=0.0,
                                     table=None)

    monkeypatch.setattr(sweep_mod, "run_study", fake_run_study)
    study.write_text('[set]\nduration_s = 2.0\n"sensors.gnss.rate_hz" = 0.4\n')
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert err == [f"v2v: warning: {w_all}"], err
    assert len(calls) == 1 and calls[0].warnings == (w_all,)  # the study loaded once, handed on


def test_nested_grid_tables_equal_dotted_keys_and_ids_are_stable(tmp_path):
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text('seeds = [4, 5]\n[grid]\n"clusters.0.vehicles" = [2, 4]\n')
    b.write_text('seeds = [4, 5]\n[grid.clusters]\n"0" = {vehicles = [2, 4]}\n')  # the same, as nested tables
    sa, sb = load_study(a), load_study(b)
    assert [r.run_id for r in sa.runs] == [r.run_id for r in sb.runs] == [r.run_id for r in load_study(a).runs]
    assert [(r.labels["clusters.0.vehicles"], r.seed, r.scenario.clusters[0].vehicles) for r in sa.runs] == [
        (2, 4, 2), (2, 5, 2), (4, 4, 4), (4, 5, 4)]
    assert all(r.scenario.seed == r.seed for r in sa.runs)
    a.write_text('seeds = [4, 5]\n[set]\nduration_s = 9.0\n[grid]\n"clusters.0.vehicles" = [2, 4]\n')
    assert not {r.run_id for r in load_study(a).runs} & {r.run_id for r in sa.runs}, "an edited study never reuses runs"


def test_grid_values_whose_short_labels_collide_keep_distinct_labels(tmp_path):
    """A solutions list is labelled by its names; two lists with the same names but different
    fields would be one label, and the report would pool the two grid points as if they were
    seeds: the column's labels are then the full values."""
    study = _write(tmp_path / "s.toml", 'seeds = [1]\n[grid]\nsolutions = [[{name = "GPS+UWB", sensors = ["gnss", "uwb"]}], '
                   '[{name = "GPS+UWB", sensors = ["gnss", "uwb"], uwb_error_states = true}]]\n')
    labels = [r.labels["solutions"] for r in load_study(study).runs]
    assert len(set(labels)) == 2 and all("uwb" in lab for lab in labels)
    distinct = _write(tmp_path / "d.toml", 'seeds = [1]\n[grid]\nsolutions = [[{name = "GPS", sensors = ["gnss"]}], '
                      '[{name = "GPS+UWB", sensors = ["gnss", "uwb"]}]]\n')
    assert [r.labels["solutions"] for r in load_study(distinct).runs] == ["GPS", "GPS+UWB"]  # short when distinct


def test_runs_table_without_rows_has_the_dtypes_of_one_with_rows(tmp_path):
    """An interrupted sweep's runs.parquet before any run finished: no rows, the same column
    dtypes as a table with rows (seed int64, a grid column of ints int64, texts as text)."""
    from v2v.sweep import _row, _runs_table

    study = load_study(_write(tmp_path / "s.toml", 'seeds = [1, 2]\n[grid]\n"clusters.0.vehicles" = [2, 3]\n'))
    spec = study.runs[0]
    full = _runs_table(study, {spec.run_id: _row(spec, "ok", "", 1.0, {})})
    empty = _runs_table(study, {})
    assert len(empty) == 0 and list(empty.columns) == list(full.columns)
    assert dict(empty.dtypes) == dict(full.dtypes)
    assert empty["seed"].dtype == np.int64 and empty["clusters.0.vehicles"].dtype == np.int64


def test_example_study_is_2_networks_x_2_solutions_x_5_seeds_of_30_s():
    st = load_study(EXAMPLE)
    assert len(st.runs) == 20 and len({r.run_id for r in st.runs}) == 20
    combos = {(r.scenario.network.name, tuple(s.name for s in r.scenario.solutions)) for r in st.runs}
    assert combos == {(n, (s,)) for n in ("hospital_loop", "residential") for s in ("GPS", "GPS+UWB+Bearing")}
    assert {r.seed for r in st.runs} == {1, 2, 3, 4, 5}
    assert all(r.scenario.duration_s == 30.0 for r in st.runs)
    assert not st.replay


def test_t_interval_matches_student_t_tables():
    # t_{0.975, 1} = 12.7062, t_{0.975, 4} = 2.7764 (any statistics table)
    n, mean, std, half = t_interval_half_width([1.0, 2.0])
    assert (n, mean) == (2, 1.5) and std == pytest.approx(math.sqrt(0.5))
    assert half == pytest.approx(12.7062 * math.sqrt(0.5) / math.sqrt(2), rel=1e-4)
    x = [0.1, 0.2, 0.15, 0.3, 0.25]
    assert t_interval_half_width(x)[3] == pytest.approx(2.7764 * np.std(x, ddof=1) / math.sqrt(5), rel=1e-4)
    assert math.isnan(t_interval_half_width([3.0, float("nan")])[3])  # one finite value: no interval


def _synthetic_runs() -> pd.DataFrame:
    """runs.parquet as a sweep writes it: grid x seeds, one failed run (a number it must not
    count), a vehicle never initialized in one run (std NaN, epochs 50), a vehicle absent from
    the runs of one grid point (no epochs), a grid point with one finished seed."""
    nan = math.nan
    rows = [  # (n_vehicles, seed, status, c1.1 std, c1.2 std, c1.2 epochs, c1.3 std, c1.3 epochs)
        (3, 1, "ok", 0.10, 0.20, 50, 0.30, 50),
        (3, 2, "ok", 0.12, nan, 50, 0.35, 50),
        (3, 3, "ok", 0.16, 0.26, 50, 0.28, 50),
        (3, 4, "failed", 9.0, 9.0, 50, 9.0, 50),
        (2, 1, "ok", 0.11, 0.21, 50, nan, nan),
        (2, 2, "ok", 0.14, 0.19, 50, nan, nan),
        (1, 1, "ok", 0.50, nan, nan, nan, nan),
        (1, 2, "failed", nan, nan, nan, nan, nan),
    ]
    return pd.DataFrame([{"run_id": f"n{v}-s{s}", "n_vehicles": v, "seed": s, "status": st,
                          "error": "" if st == "ok" else "RuntimeError: x", "wall_s": 1.0 + s, "note": "",
                          "GPS.c1.1.epochs": 50.0, "GPS.c1.1.along.std": a, "GPS.c1.2.epochs": float(e2),
                          "GPS.c1.2.along.std": b, "GPS.c1.3.epochs": float(e3), "GPS.c1.3.along.std": c}
                         for v, s, st, a, b, e2, c, e3 in rows])


def _independent_cell(x) -> dict[str, float]:
    from scipy import stats

    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    n, mean = len(x), x.mean()
    std = x.std(ddof=1) if n > 1 else math.nan
    half = stats.t.ppf(0.975, n - 1) * std / math.sqrt(n) if n > 1 else math.nan
    return {"n": n, "mean": mean, "std": std, "ci95_half": half, "ci95_low": mean - half, "ci95_high": mean + half}


def test_aggregate_matches_an_independent_t_interval_per_grid_point():
    from v2v.sweep import _with_vehicle_means, aggregate_runs

    runs = _synthetic_runs()
    df, solutions = _with_vehicle_means(runs)
    assert solutions == ["GPS"]
    agg = aggregate_runs(df, ["n_vehicles"])
    ok = runs[runs["status"] == "ok"]
    # the mean over a run's vehicles: NaN when one of its vehicles has no std (n = 2 seeds),
    # over the vehicles it has when the grid point has fewer (c1.3 absent at n_vehicles = 2)
    vm = df.set_index("run_id")["GPS.vehicles_mean.along.std"]
    assert math.isnan(vm["n3-s2"]) and vm["n3-s1"] == pytest.approx(0.2) and vm["n2-s1"] == pytest.approx(0.16)
    assert vm["n1-s1"] == 0.5
    expected = {
        (3, "GPS.c1.1.along.std"): [0.10, 0.12, 0.16],
        (3, "GPS.c1.2.along.std"): [0.20, 0.26],
        (3, "GPS.vehicles_mean.along.std"): [0.20, np.mean([0.16, 0.26, 0.28])],
        (2, "GPS.c1.1.along.std"): [0.11, 0.14],
        (2, "GPS.vehicles_mean.along.std"): [0.16, 0.165],
        (1, "GPS.c1.1.along.std"): [0.50],
        (3, "wall_s"): [2.0, 3.0, 4.0],
    }
    for (v, metric), x in expected.items():
        if "vehicles_mean" not in metric:  # (the expected values are the finished runs' own)
            assert x == pytest.approx(list(ok.loc[ok["n_vehicles"] == v, metric].dropna()))
        row = agg[(agg["n_vehicles"] == v) & (agg["metric"] == metric)]
        assert len(row) == 1, (v, metric)  # grid points never pooled, seeds always
        got = row.iloc[0]
        for k, want in _independent_cell(x).items():
            if math.isnan(want):
                assert math.isnan(got[k]), (v, metric, k)  # one seed: no std, no interval
            else:
                assert got[k] == pytest.approx(want, rel=1e-12), (v, metric, k)
    # a metric with no value in any finished run of a grid point has no row there
    assert agg[(agg["n_vehicles"] == 2) & (agg["metric"] == "GPS.c1.3.along.std")].empty
    assert not agg["metric"].isin(["seed", "run_id", "status", "error", "note", "n_vehicles"]).any()


def test_report_says_how_many_seeds_a_value_has_and_draws_no_zero_interval(tmp_path, monkeypatch):
    import matplotlib.axes

    runs = _synthetic_runs()
    runs.to_parquet(tmp_path / "runs.parquet")
    (tmp_path / "sweep.json").write_text(json.dumps({"grid_columns": ["n_vehicles"]}))
    bars: list[dict] = []
    orig_bar = matplotlib.axes.Axes.bar

    def bar(self, x, height, *args, **kwargs):
        bars.append({"x": list(x), "mean": list(height), "yerr": list(kwargs.get("yerr")), "ax": self})
        return orig_bar(self, x, height, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "bar", bar)
    assert _cli(["sweep", "report", str(tmp_path)]) == 0
    md = (tmp_path / "report.md").read_text()
    # 3 finished seeds at n_vehicles = 3, c1.2 has a std in 2 of them
    assert "| 3 | GPS | c1.2 | 0.230 ± 0.381 (n = 2) |" in md
    assert "| 3 | GPS | c1.1 | 0.127 ± 0.076 |" in md
    assert "| 1 | GPS | c1.1 | 0.500 |" in md
    along = bars[0]
    assert along["mean"][2] == 0.5 and math.isnan(along["yerr"][2])  # one seed: no error bar (not one of zero)
    assert along["ax"].get_xlabel() == "n_vehicles" and along["ax"].get_ylabel() == "along-track error std (m)"


def test_report_figure_labels_grid_values_whose_labels_collide_distinctly(tmp_path, monkeypatch):
    """runs.parquet of a study over two solutions lists of the same name (written whole, as
    JSON) and scenario names alike in their first 40 characters. Before, both lists' bars were
    drawn at the same place under one legend entry, and the names were drawn whole (70
    characters, over each other). Now: one series per list, numbered, bars side by side; tick
    labels cut, numbered where cut ones would be the same, wrapped; report.md lists the whole
    values beside the labels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.figure

    from v2v.sweep import _LABEL_CHARS, _TICK_CHARS, _row, _write_runs, _write_sweep_json

    common = "a scenario name long enough to be cut in the figure, "
    names = [common + "variant one", common + "variant two", "short"]
    study = load_study(_write(tmp_path / "s.toml", "seeds = [1, 2]\n[grid]\nsolutions = ["
                              '[{name = "GPS+UWB", sensors = ["gnss", "uwb"]}], '
                              '[{name = "GPS+UWB", sensors = ["gnss", "uwb"], uwb_error_states = true}]]\n'
                              f"name = {json.dumps(names)}\n"))
    sol_values = list(dict.fromkeys(r.labels["solutions"] for r in study.runs))
    assert len(sol_values) == 2 and all(v.startswith("[{") for v in sol_values)  # whole values: the names collide
    rng = np.random.default_rng(5)
    rows = {r.run_id: _row(r, "ok", "", 1.0, {f"GPS+UWB.{v}.{m}": x for v in ("c1.1", "c1.2")
                                              for m, x in (("epochs", 50.0), ("along.std", rng.uniform(0.1, 0.3)),
                                                           ("across.std", rng.uniform(0.1, 0.3)))})
            for r in study.runs}
    out = tmp_path / "sweep"
    out.mkdir()
    _write_runs(out, study, rows)
    _write_sweep_json(out, study)
    figures = []
    orig = matplotlib.figure.Figure.savefig

    def savefig(self, *args, **kwargs):
        figures.append(self)
        return orig(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    assert _cli(["sweep", "report", str(out)]) == 0
    (fig,) = figures
    assert len(fig.axes) == 2  # along, across
    for ax in fig.axes:
        ticks = [t.get_text() for t in ax.get_xticklabels()]
        assert len(ticks) == 3 and len(set(ticks)) == 3, ticks
        assert all(len(line) <= _TICK_CHARS for t in ticks for line in t.split("\n")), ticks
        # cut to _LABEL_CHARS with "…", both to the same text, so numbered; wrapped at spaces here
        cut = [names[0][:_LABEL_CHARS - 1] + "… [1]", names[1][:_LABEL_CHARS - 1] + "… [2]", "short"]
        assert [" ".join(t.split("\n")) for t in ticks] == cut
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        assert legend == ["GPS+UWB [1]", "GPS+UWB [2]"]
        xs = [round(b.get_x(), 9) for b in ax.patches]
        assert len(xs) == 6 and len(set(xs)) == 6  # 3 names x 2 lists, no bar drawn over another
    md = (out / "report.md").read_text()
    labels = md[md.index("## Labels in report.png"):]
    assert f"| solutions | 1 | GPS+UWB [1] | {sol_values[0]} |" in labels
    assert f"| solutions | 2 | GPS+UWB [2] | {sol_values[1]} |" in labels
    for i, name in enumerate(names):
        assert f"| name | {i + 1} | {cut[i]} | {name} |" in labels


@pytest.mark.parametrize(("texts", "expected"), [
    (["a", "b"], ["a", "b"]),
    (["a", "a", "b"], ["a [1]", "a [2]", "b"]),
    (["A", "A", "A [2]"], ["A [1]", "A [2]", "A [2] [3]"]),  # a numbered label is another value's own
])
def test_figure_labels_are_numbered_only_where_shared(texts, expected):
    from v2v.sweep import _distinct

    assert _distinct(texts) == expected


def test_tick_labels_wrap_after_commas_and_spaces():
    from v2v.sweep import _wrap

    assert _wrap('[["c1.0","c1.1"],["c1.0","c1.2"]] [2]', 18) == '[["c1.0","c1.1"],\n["c1.0","c1.2"]]\n[2]'
    assert _wrap("hospital_loop, 0.1", 18) == "hospital_loop, 0.1"
    assert _wrap("x" * 40, 18) == "x" * 18 + "\n" + "x" * 18 + "\n" + "x" * 4  # no place to break: cut


def test_flatten_summary_names_columns_solution_vehicle_metric():
    s = {"seed": 3, "wall_s": 1.0, "simulated_s": 5.0, "gnss": {"epochs": 51, "nlos_fraction": None},
         "events": [{"t_s": 1.0}], "table": "x",
         "statistics": {"GPS": {"vehicles": {"c1.1": {"availability": 1.0, "along": {"std": 0.1}}},
                                "measurements": {"sd_pseudorange": {"used": 600}}}}}
    flat = flatten_summary(s)
    assert math.isnan(flat.pop("gnss.nlos_fraction"))  # JSON null (json_safe wrote NaN as null)
    assert flat == {"simulated_s": 5.0, "gnss.epochs": 51.0, "GPS.c1.1.availability": 1.0,
                    "GPS.c1.1.along.std": 0.1, "GPS.measurements.sd_pseudorange.used": 600.0}


# --------------------------------------------------------------------------- one run in a process


@pytest.mark.sumo
def test_failed_run_is_a_plain_dict_and_the_process_can_run_again(tmp_path):
    """libsumo's errors don't pickle and it allows one simulation per process: a task that SUMO
    rejects returns a one-line error, and the next task in the same process runs fine."""
    bad_sc = load_study(_write(tmp_path / "bad.toml", 'seeds = [1]\n[set]\nduration_s = 2.0\nsolutions = []\n'
                                "\"network.route_edges\" = ['ap_in', 'SW-SE']\n")).runs[0].scenario
    good_sc = load_study(_write(tmp_path / "good.toml", "seeds = [1]\n[set]\nduration_s = 2.0\nsolutions = []\n")).runs[0].scenario
    bad = execute_run(RunTask(run_id="bad", scenario=bad_sc, out_dir=str(tmp_path / "bad"), replay=False,
                              save_measurements=False, base_dir=None))
    assert bad["status"] == "failed" and "network.route_edges" in bad["error"] and "\n" not in bad["error"]
    assert not (tmp_path / "bad").exists()
    good = execute_run(RunTask(run_id="good", scenario=good_sc, out_dir=str(tmp_path / "good"), replay=False,
                               save_measurements=False, base_dir=None))
    assert good["status"] == "ok", good["error"]
    assert good["metrics"]["simulated_s"] == pytest.approx(2.0)


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- whole sweeps on Dask


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory) -> Path:
    return _write(tmp_path_factory.mktemp("study") / "tiny.toml", TINY)


@pytest.fixture(scope="module")
def local_sweep(tiny_study, tmp_path_factory) -> Path:
    """The tiny study through the CLI on v2v's own LocalCluster (2 single-threaded worker processes)."""
    out = tmp_path_factory.mktemp("sweep") / "local"
    assert _cli(["sweep", str(tiny_study), "--out", str(out), "--workers", "2", "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def external_scheduler():
    """A scheduler + 2 worker processes on loopback, started outside v2v (as a user's cluster would be)."""
    from dask.distributed import LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None)
    yield cluster.scheduler_address
    cluster.close()


@pytest.mark.sumo
def test_runs_parquet_rows_are_the_runs_summaries(local_sweep):
    df = pd.read_parquet(local_sweep / "runs.parquet")
    assert len(df) == 4 and (df["status"] == "ok").all() and (df["error"] == "").all()
    assert list(df.columns[:6]) == ["run_id", "network.name", "seed", "status", "error", "wall_s"]
    assert sorted(zip(df["network.name"], df["seed"], strict=True)) == [
        ("hospital_loop", 1), ("hospital_loop", 2), ("residential", 1), ("residential", 2)]
    for row in df.to_dict("records"):
        s = json.loads((local_sweep / "runs" / row["run_id"] / "summary.json").read_text())
        assert s["seed"] == row["seed"] and s["network"].startswith(row["network.name"])
        assert row["wall_s"] == s["wall_s"] and row["simulated_s"] == s["simulated_s"] == pytest.approx(5.0, abs=0.11)
        for veh in ("c1.1", "c1.2"):
            st = s["statistics"]["GPS"]["vehicles"][veh]
            assert row[f"GPS.{veh}.along.std"] == st["along"]["std"]
            assert row[f"GPS.{veh}.across.std"] == st["across"]["std"]
            assert row[f"GPS.{veh}.availability"] == st["availability"]
        assert row["gnss.epochs"] == s["gnss"]["epochs"]
        assert row["note"] == s.get("note", "") == ""  # (these runs estimate: no note)
    # the seeds differ, so the runs differ (no accidental seed reuse across workers)
    assert df["GPS.c1.1.along.std"].nunique() == 4
    assert json.loads((local_sweep / "sweep.json").read_text())["grid_columns"] == ["network.name"]


@pytest.mark.sumo
def test_external_scheduler_gives_identical_results(tiny_study, local_sweep, external_scheduler, tmp_path):
    res = run_study(tiny_study, tmp_path / "ext", scheduler=external_scheduler)
    assert (res.executed, res.skipped, res.failed) == (4, 0, 0)
    a = pd.read_parquet(local_sweep / "runs.parquet")
    b = pd.read_parquet(tmp_path / "ext" / "runs.parquet")
    assert list(a.columns) == list(b.columns)
    cols = [c for c in a.columns if c != "wall_s"]
    pd.testing.assert_frame_equal(a[cols], b[cols])  # same seeds -> bit-identical runs, wherever they ran


@pytest.mark.sumo
def test_rerun_executes_only_missing_runs(tiny_study, local_sweep, external_scheduler, tmp_path):
    out = tmp_path / "resumed"
    shutil.copytree(local_sweep, out)
    before = pd.read_parquet(out / "runs.parquet")
    victim = before["run_id"][2]
    shutil.rmtree(out / "runs" / victim)  # as if killed before this run finished ...
    (out / "runs" / f".{victim}.abc.partial").mkdir()  # ... with its staging folder left behind
    mtimes = {r: (out / "runs" / r / "summary.json").stat().st_mtime_ns for r in before["run_id"] if r != victim}
    res = run_study(tiny_study, out, scheduler=external_scheduler)
    assert (res.executed, res.skipped, res.failed) == (1, 3, 0)
    assert {r: (out / "runs" / r / "summary.json").stat().st_mtime_ns for r in mtimes} == mtimes, "others untouched"
    assert not list((out / "runs").glob(".*")), "the dead run's staging folder is cleaned up"
    after = pd.read_parquet(out / "runs.parquet")
    cols = [c for c in before.columns if c != "wall_s"]
    pd.testing.assert_frame_equal(before[cols], after[cols])  # the re-run run reproduces its numbers
    again = run_study(tiny_study, out, scheduler=external_scheduler)
    assert (again.executed, again.skipped) == (0, 4)


@pytest.mark.sumo
def test_turning_replay_on_reruns_the_runs_without_a_replay(tiny_study, local_sweep, external_scheduler, tmp_path):
    """A run made with replay = false is not complete for the same study with replay = true
    (the study file says it "writes replay.rrd in every run folder")."""
    out = tmp_path / "with_replay"
    shutil.copytree(local_sweep, out)
    study = _write(tmp_path / "tiny_replay.toml", "replay = true\n" + tiny_study.read_text())
    study_base = load_study(study)
    assert [r.run_id for r in study_base.runs] == [r.run_id for r in load_study(tiny_study).runs]
    res = run_study(study, out, scheduler=external_scheduler)
    assert (res.executed, res.skipped) == (4, 0)
    assert all((out / "runs" / r.run_id / "replay.rrd").is_file() for r in study_base.runs)
    assert run_study(study, out, scheduler=external_scheduler).executed == 0


@pytest.mark.sumo
@pytest.mark.parametrize("remote", [True, False], ids=["scheduler", "local"])
def test_ctrl_c_midway_leaves_the_table_listing_exactly_the_complete_runs(remote, external_scheduler, tmp_path):
    """Ctrl-C once the first runs are being written. On a --scheduler cluster Dask's cancel
    does not stop a task a worker is already executing: those runs still complete and publish
    their folders, and the sweep waits for them (it used to exit at once, its table missing the
    runs that landed after it). The local cluster's workers are closed instead and their staging
    folders removed. Either way runs.parquet lists exactly the complete run folders. (The signal
    comes ~0.1-0.5 s after the runs were submitted, while the sweep's first table write may still
    be importing pandas: an interrupt there used to leave pandas half imported and the table
    unwritable.)"""
    study = tmp_path / "s.toml"
    # runs of a few seconds even on warm workers: each is still running when the signal arrives
    study.write_text(TINY.replace("seeds = [1, 2]", "seeds = [1, 2, 3, 4]").replace("duration_s = 5.0", "duration_s = 120.0")
                     .replace('sensors = ["gnss"]', 'sensors = ["gnss", "uwb", "bearing"]')
                     .replace("[grid]", '"clusters.0.vehicles" = 8\n[grid]'))
    out = tmp_path / "out"
    where = ["--scheduler", external_scheduler] if remote else ["--workers", "2"]
    proc = subprocess.Popen([sys.executable, "-m", "v2v", "sweep", str(study), "--out", str(out), "--quiet", *where],
                            stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(600):  # until a worker has started a run (its staging folder exists)
            if (out / "runs").is_dir() and any((out / "runs").glob(".*.partial")):
                break
            time.sleep(0.05)
        else:
            pytest.fail("no run started in 30 s")
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert ("sweep: waiting for the" in err) == remote and "run the same command again for the rest" in err, err
    assert "Traceback" not in err
    runs = out / "runs"
    assert not list(runs.glob(".*.partial"))
    complete = {d.name for d in runs.iterdir() if (d / "summary.json").is_file()}
    listed = set(pd.read_parquet(out / "runs.parquet")["run_id"])
    assert complete == listed and len(listed) < 8  # not the cancelled runs
    assert complete or not remote  # the runs a remote cluster had started completed (local ones may have)


@pytest.mark.sumo
def test_a_run_sumo_rejects_is_recorded_and_the_others_succeed(external_scheduler, tmp_path):
    study = _write(tmp_path / "fail.toml", 'seeds = [1, 2]\n[set]\nduration_s = 3.0\nsolutions = []\n'
                   "[grid]\n\"network.route_edges\" = [[], ['ap_in', 'SW-SE']]\n")
    res = run_study(study, tmp_path / "out", scheduler=external_scheduler)
    assert (res.executed, res.failed) == (4, 2)
    df = pd.read_parquet(tmp_path / "out" / "runs.parquet")
    ok, bad = df[df["status"] == "ok"], df[df["status"] == "failed"]
    assert len(ok) == 2 and (ok["network.route_edges"] == "[]").all()
    assert len(bad) == 2 and (bad["network.route_edges"] == '["ap_in","SW-SE"]').all()
    for err in bad["error"]:
        assert "network.route_edges" in err and "fix:" in err and "\n" not in err
    assert bad["simulated_s"].isna().all() and np.allclose(ok["simulated_s"], 3.0, atol=0.11)
    assert all((tmp_path / "out" / "runs" / r / "summary.json").is_file() for r in ok["run_id"])
    assert not any((tmp_path / "out" / "runs" / r).exists() for r in bad["run_id"])
    # failed runs are retried by the next invocation; finished ones are not
    again = run_study(study, tmp_path / "out", scheduler=external_scheduler)
    assert (again.executed, again.skipped, again.failed) == (2, 2, 2)


@pytest.mark.sumo
def test_a_runs_note_is_in_runs_parquet_and_the_report(external_scheduler, tmp_path):
    """A run that completes but estimates nothing (every V2V message lost) is "ok" with its
    summary's note in the ``note`` column, listed under "Runs with a note" in report.md."""
    study = _write(tmp_path / "lossy.toml", 'seeds = [1]\n[set]\nduration_s = 3.0\n'
                   'solutions = [{name = "GPS", sensors = ["gnss"]}]\n[grid]\n"exchange.loss_probability" = [0.0, 1.0]\n')
    res = run_study(study, tmp_path / "out", scheduler=external_scheduler, quiet=True)
    assert (res.executed, res.failed) == (2, 0)
    df = pd.read_parquet(tmp_path / "out" / "runs.parquet").set_index("exchange.loss_probability")
    lossy, clean = df.loc[1.0], df.loc[0.0]
    assert "every V2V message was lost" in lossy["note"] and clean["note"] == ""
    assert lossy["note"] == json.loads((tmp_path / "out" / "runs" / lossy["run_id"] / "summary.json").read_text())["note"]
    assert lossy["GPS.c1.1.availability"] == 0.0 < clean["GPS.c1.1.availability"]
    assert _cli(["sweep", "report", str(tmp_path / "out"), "--out", str(tmp_path / "rep")]) == 0
    md = (tmp_path / "rep" / "report.md").read_text()
    section = md.split("## Runs with a note", 1)[1]
    assert lossy["run_id"] in section and clean["run_id"] not in section


@pytest.mark.sumo
def test_report_means_and_t_intervals_across_seeds(local_sweep, tmp_path):
    assert _cli(["sweep", "report", str(local_sweep), "--out", str(tmp_path)]) == 0
    runs = pd.read_parquet(local_sweep / "runs.parquet")
    rep = pd.read_csv(tmp_path / "report.csv")
    for net, g in runs.groupby("network.name"):
        for metric in ("GPS.c1.1.along.std", "GPS.c1.2.across.std", "simulated_s"):
            x = g[metric].to_numpy()
            r = rep[(rep["network.name"] == net) & (rep["metric"] == metric)].iloc[0]
            assert r["n"] == 2 and r["mean"] == pytest.approx(x.mean())
            # two seeds: half-width = t_{0.975,1} * |x1 - x2| / 2 (t = 12.706)
            assert r["ci95_half"] == pytest.approx(12.7062 * abs(x[0] - x[1]) / 2, rel=1e-4)
            assert r["ci95_low"] <= x.min() + 1e-12 and r["ci95_high"] >= x.max() - 1e-12
        # the per-run vehicle mean is the mean of the vehicles' stds
        vm = rep[(rep["network.name"] == net) & (rep["metric"] == "GPS.vehicles_mean.along.std")].iloc[0]
        assert vm["mean"] == pytest.approx(g[["GPS.c1.1.along.std", "GPS.c1.2.along.std"]].to_numpy().mean())
    md = (tmp_path / "report.md").read_text()
    assert "| hospital_loop | GPS | c1.1 |" in md and "| residential | 2 | 0 |" in md
    png = (tmp_path / "report.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


# --------------------------------------------------------------------------- slow: real dask CLIs


@pytest.mark.slow
@pytest.mark.sumo
def test_dask_cli_scheduler_and_worker(tiny_study, local_sweep, tmp_path):
    """`dask scheduler` + `dask worker --nthreads 1` as separate programs, as on a real cluster."""
    dask_exe = str(Path(sys.executable).with_name("dask"))
    port_file = tmp_path / "scheduler.json"
    sched = subprocess.Popen([dask_exe, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                              "--scheduler-file", str(port_file)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = None
    try:
        for _ in range(300):
            if port_file.is_file() and port_file.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(port_file.read_text())["address"]
        worker = subprocess.Popen([dask_exe, "worker", address, "--nthreads", "1", "--nworkers", "2",
                                   "--no-dashboard", "--host", "127.0.0.1"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        res = run_study(tiny_study, tmp_path / "cli", scheduler=address)
        assert (res.executed, res.failed) == (4, 0)
        a = pd.read_parquet(local_sweep / "runs.parquet")
        b = pd.read_parquet(tmp_path / "cli" / "runs.parquet")
        cols = [c for c in a.columns if c != "wall_s"]
        pd.testing.assert_frame_equal(a[cols], b[cols])
    finally:
        for p in (worker, sched):
            if p is not None:
                p.terminate()
                p.wait(timeout=30)


def test_out_folder_of_other_files_is_refused_in_one_line(tiny_study, tmp_path, capsys):
    """--out is a new or empty folder or a sweep's: a folder of other files (a user's notes)
    would get runs/, sweep.json and runs.parquet written among them."""
    out = tmp_path / "notes"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    assert _cli(["sweep", str(tiny_study), "--out", str(out), "--quiet"]) == 2
    assert "notes.txt" in _one_error_line(capsys, "--out")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_second_sweep_on_a_busy_folder_stops_with_one_line(tiny_study, tmp_path, capsys):
    """While one sweep writes to a folder (its lock held; here by this process), a second one
    on that folder must stop before touching it (it would remove the first one's staging
    folders and run the same runs twice): exit 2, one line naming --out, nothing written."""
    from v2v.sweep import _FolderLock

    out = tmp_path / "busy"
    out.mkdir()
    with _FolderLock(out):
        assert _cli(["sweep", str(tiny_study), "--out", str(out), "--quiet"]) == 2
        assert sorted(p.name for p in out.iterdir()) == [".sweep.lock"]  # the holder's lock, and nothing else
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and "another sweep" in err[0] and f"pid {__import__('os').getpid()}" in err[0]
    assert list(out.iterdir()) == [], "the lock file goes with its release"


# --------------------------------------------------------------------------- bad input, one line each


def test_host_the_local_cluster_cannot_use_is_one_line_and_leaves_nothing(tiny_study, tmp_path, monkeypatch, capsys):
    """--host that does not resolve: refused before anything is written (the real command: exit
    2, one line, no traceback). Should the cluster still fail to start (here the probe is
    skipped), that is one line too, and the folder's lock is released and removed."""
    out = tmp_path / "new"
    cmd = [str(Path(sys.executable).with_name("v2v")), "sweep", str(tiny_study), "--out", str(out), "--workers", "1",
           "--host", "999.1.1.1"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("v2v: error: --host: ") and "127.0.0.1" in proc.stderr
    assert not out.exists()
    import v2v.sweep as sweep_mod

    monkeypatch.setattr(sweep_mod, "_check_host", lambda host: None)
    (tmp_path / "empty").mkdir()
    for out in (tmp_path / "empty", tmp_path / "new"):
        assert _cli(["sweep", str(tiny_study), "--out", str(out), "--workers", "1", "--host", "999.1.1.1", "--quiet"]) == 2
        assert "the local cluster did not start" in _one_error_line(capsys, "--host")
    assert list((tmp_path / "empty").iterdir()) == [] and not (tmp_path / "new").exists()


@pytest.mark.sumo
def test_out_of_another_study_or_of_a_run_is_refused_and_the_same_study_resumes(local_sweep, tmp_path, capsys):
    """A sweep never replaces another study's runs.parquet / sweep.json (orphaning its run
    folders) nor writes into a single run's folder: one line naming --out, nothing written. The
    same study (also a copy of its file elsewhere) resumes there."""
    assert not (local_sweep / ".sweep.lock").exists(), "a finished sweep leaves no lock file"
    out = tmp_path / "sw"
    shutil.copytree(local_sweep, out)
    before = {p: p.read_bytes() for p in (out / "runs.parquet", out / "sweep.json")}
    other = _write(tmp_path / "other.toml", TINY.replace("duration_s = 5.0", "duration_s = 3.0"))
    assert _cli(["sweep", str(other), "--out", str(out), "--quiet"]) == 2
    assert "holds the sweep of study" in _one_error_line(capsys, "--out")
    assert {p: p.read_bytes() for p in before} == before and sorted(p.name for p in out.iterdir()) == [
        "runs", "runs.parquet", "sweep.json"]
    run_dir = next((out / "runs").iterdir())
    listing = sorted(p.name for p in run_dir.iterdir())
    assert _cli(["sweep", str(other), "--out", str(run_dir), "--quiet"]) == 2
    assert "is a run's folder" in _one_error_line(capsys, "--out")
    assert sorted(p.name for p in run_dir.iterdir()) == listing
    copy = _write(tmp_path / "copy_of_tiny.toml", TINY)
    res = run_study(copy, out)
    assert (res.executed, res.skipped) == (0, 4)


def _one_error_line(capsys, field: str) -> str:
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("v2v: error: ") and field in err[0] and "fix:" in err[0], err
    return err[0]


@pytest.mark.sumo
def test_value_a_run_would_refuse_stops_the_study_before_any_run(tmp_path, capsys):
    """A grid value the schema accepts but every run would refuse at its set-up (an unknown UWB
    radio profile) stops the study at load, naming the run, before a cluster starts or a
    folder is written: not one failed run per seed."""
    study = _write(tmp_path / "s.toml", 'seeds = [1, 2]\n[set]\nduration_s = 2.0\n'
                   '[grid]\n"sensors.uwb.profile" = ["mssi", "decawave"]\n')
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    line = _one_error_line(capsys, "sensors.uwb.profile")
    assert "unknown UWB radio profile 'decawave'" in line and "run sensors.uwb.profile=decawave" in line


def test_bad_grid_value_says_it_came_from_the_study(tmp_path, capsys):
    """A value the schema refuses names its field and says the study's [set] / [grid] set it (not
    the command line's --set, which a study has none of)."""
    study = _write(tmp_path / "s.toml", 'seeds = [1]\n[grid]\n"clusters.0.vehicles" = [3, -2]\n')
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    line = _one_error_line(capsys, "clusters.0.vehicles")
    assert "the study's [set] / [grid]" in line and "command line" not in line and "run clusters.0.vehicles=-2" in line
    assert not (tmp_path / "o").exists()


@pytest.mark.sumo
def test_more_workers_than_cores_is_noted(tmp_path, capsys):
    """--workers above the cores this process may use still runs (a user may mean it), with a
    note that the runs share the cores; no note when the pending runs need fewer workers."""
    cores = len(os.sched_getaffinity(0))
    study = _write(tmp_path / "w.toml", f"seeds = {list(range(1, cores + 2))}\n[set]\nduration_s = 1.0\n"
                   'solutions = [{name = "GPS", sensors = ["gnss"]}]\n')
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "o"), "--workers", str(cores + 1)]) == 0
    err = capsys.readouterr().err
    assert f"sweep: note: {cores + 1} worker processes on {cores} core(s)" in err
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "o"), "--workers", str(cores + 1)]) == 0  # nothing pending
    assert "note:" not in capsys.readouterr().err


def test_local_cluster_workers_have_one_thread_ignore_ctrl_c_and_come_from_the_fork_server():
    """The local cluster's contract: each worker process runs one BLAS / OpenMP thread (one
    run per core), ignores SIGINT (Ctrl-C reaches only the sweep's process, which cancels the
    study and closes the cluster instead of every worker dying mid-write), and is forked by
    the fork server, not by this process (so a closed worker leaves with os._exit instead of
    a full interpreter shutdown)."""
    import signal

    from v2v.sweep import _open_client

    client, cluster = _open_client(None, 2, "127.0.0.1", 2)
    try:
        parents = client.run(os.getppid)
        sigint = client.run(signal.getsignal, signal.SIGINT)
        env = {k: client.run(os.environ.get, k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    finally:
        client.close()
        cluster.close()
    assert len(parents) == 2
    assert all(p != os.getpid() for p in parents.values()) and len(set(parents.values())) == 1
    assert all(h == signal.SIG_IGN for h in sigint.values())
    assert all(v == "1" for per_worker in env.values() for v in per_worker.values())


def test_a_ctrl_c_during_the_cluster_start_is_held_and_acted_on_once_the_cluster_is_closed(monkeypatch):
    """A SIGINT that arrives while the local cluster starts (~1 s) is neither dropped (the
    study used to run to its end: SIGINT was ignored for the whole start) nor raised in the
    middle of the start (a half-started cluster's close at exit printed tracebacks): the start
    completes, the cluster is closed, then the interrupt is raised, and the handler is back."""
    import signal

    import dask.distributed

    from v2v.sweep import _open_client

    events = []

    class StartedWithACtrlC:  # stands in for LocalCluster: a Ctrl-C arrives during its start
        def __init__(self, **_kw):
            os.kill(os.getpid(), signal.SIGINT)
            events.append("started")

        def close(self):
            events.append("closed")

    monkeypatch.setattr(dask.distributed, "LocalCluster", StartedWithACtrlC)
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        _open_client(None, 1, "127.0.0.1", 1)
    assert events == ["started", "closed"]
    assert signal.getsignal(signal.SIGINT) is before


def test_huge_seed_count_is_refused_before_the_list_is_built(tmp_path, capsys):
    study = _write(tmp_path / "huge.toml", "seeds = {start = 1, count = 3000000000}\n")
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "2147483647" in _one_error_line(capsys, "seeds")
    assert not (tmp_path / "o").exists()


def test_scheduler_port_that_is_not_dask_fails_in_one_line_and_writes_nothing(tiny_study, tmp_path, capsys,
                                                                              monkeypatch):
    """An HTTP server accepts the TCP connection (the reachability probe passes) but never does
    the Dask handshake: the bounded connection gives up (here after 2 s instead of 30 s) before
    anything is written, so no sweep.json / runs.parquet can pass for a sweep."""
    import http.server
    import threading

    import v2v.sweep as sweep

    class Quiet(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):  # (it answers the Dask frame with 400 Bad request)
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    monkeypatch.setattr(sweep, "SCHEDULER_CONNECT_S", 2.0)
    out = tmp_path / "o"
    try:
        code = _cli(["sweep", str(tiny_study), "--out", str(out), "--quiet",
                     "--scheduler", f"tcp://127.0.0.1:{srv.server_address[1]}"])
    finally:
        srv.shutdown()
    assert code == 2
    assert "not a usable Dask scheduler" in _one_error_line(capsys, "--scheduler")
    assert not (out / "sweep.json").exists() and not (out / "runs.parquet").exists()


def test_report_refuses_corrupt_empty_or_unwritable(tmp_path, capsys):
    d = tmp_path / "sw"
    d.mkdir()
    (d / "runs.parquet").write_bytes(b"not parquet")
    assert _cli(["sweep", "report", str(d)]) == 2
    assert "not readable Parquet" in _one_error_line(capsys, "DIR")
    pd.DataFrame({"run_id": ["a"], "status": ["failed"], "error": ["x"]}).to_parquet(d / "runs.parquet")
    assert _cli(["sweep", "report", str(d)]) == 2
    assert "none finished" in _one_error_line(capsys, "DIR")
    assert not (d / "report.md").exists()


def test_report_that_cannot_be_written_says_so_and_leaves_the_earlier_report_whole(tmp_path, capsys):
    """A report.png that is a folder (the last of the three files) made the report write
    report.csv and report.md, then end in a traceback beside the old figure. Now nothing
    is replaced and the error is one line naming --out."""
    runs = _synthetic_runs()
    runs.to_parquet(tmp_path / "runs.parquet")
    (tmp_path / "sweep.json").write_text(json.dumps({"grid_columns": ["n_vehicles"]}))
    out = tmp_path / "rep"
    out.mkdir()
    for name in ("report.csv", "report.md"):
        (out / name).write_text("earlier report\n")
    (out / "report.png").mkdir()
    assert _cli(["sweep", "report", str(tmp_path), "--out", str(out)]) == 2
    assert "cannot write the report" in _one_error_line(capsys, "--out")
    assert [(out / n).read_text() for n in ("report.csv", "report.md")] == ["earlier report\n"] * 2
    assert sorted(p.name for p in out.iterdir()) == ["report.csv", "report.md", "report.png"]  # no temporary left


def test_report_refuses_a_table_without_a_grid_column_of_sweep_json(tmp_path, capsys):
    """Grouping without one of sweep.json's grid columns would pool the runs of different grid
    values (the seeds of two grid points averaged as one): refused in one line."""
    runs = _synthetic_runs().drop(columns=["n_vehicles"])
    runs.to_parquet(tmp_path / "runs.parquet")
    (tmp_path / "sweep.json").write_text(json.dumps({"grid_columns": ["n_vehicles"]}))
    assert _cli(["sweep", "report", str(tmp_path)]) == 2
    assert "no column 'n_vehicles'" in _one_error_line(capsys, "DIR")
    assert not (tmp_path / "report.md").exists()


@pytest.mark.sumo
def test_sweep_whose_runs_fail_exits_1_naming_the_first_error(tmp_path, capsys):
    """Failed runs do not stop the study, but the command's status says so (1, with the first
    one-line error), so a script or CI running a sweep does not take it for a success."""
    study = _write(tmp_path / "bad.toml", 'seeds = [1]\n[set]\nduration_s = 2.0\nsolutions = []\n'
                   "[grid]\n\"network.route_edges\" = [['ap_in', 'SW-SE']]\n")
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "o"), "--quiet", "--workers", "1"]) == 1
    line = _one_error_line(capsys, "network.route_edges")
    assert "1 of 1 runs failed" in line
    runs = pd.read_parquet(tmp_path / "o" / "runs.parquet")
    assert runs["status"].tolist() == ["failed"]
    # nothing to aggregate: the report says so in one line, with the run's error
    assert _cli(["sweep", "report", str(tmp_path / "o")]) == 2
    assert runs["error"][0] in _one_error_line(capsys, "DIR")


@pytest.mark.sumo
def test_a_sweep_logged_to_a_file_reports_progress(tmp_path, monkeypatch, capsys):
    """With stderr not a terminal (no tqdm bar) a sweep prints progress lines: runs done of
    those to run, failures, elapsed and remaining time (here after every run but the last)."""
    import v2v.sweep as sweep_mod

    monkeypatch.setattr(sweep_mod, "PROGRESS_EVERY_S", 0.0)
    study = _write(tmp_path / "p.toml", 'seeds = [1, 2, 3]\n[set]\nduration_s = 1.0\n'
                   'solutions = [{name = "GPS", sensors = ["gnss"]}]\n')
    assert _cli(["sweep", str(study), "--out", str(tmp_path / "o"), "--workers", "1"]) == 0
    got = [re.fullmatch(r"sweep: (\d) of 3 runs \(0 failed\), \d+ s, ~\d+ s to go", ln)
           for ln in capsys.readouterr().err.splitlines()]
    assert [int(m.group(1)) for m in got if m] == [1, 2]
