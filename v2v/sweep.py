"""Monte Carlo studies: a grid of scenario variants x seeds, run in parallel on Dask.

A *study file* is TOML, data only::

    base = "../hospital_loop.toml"      # relative to the study file; omit for the built-in default
    seeds = {start = 1, count = 100}    # or seeds = [1, 2, 3]
    replay = false                      # write replay.rrd in every run folder (default false)
    save_measurements = false           # write measurements.parquet too (default false)

    [set]                               # fixed overrides for every run (same paths as --set)
    duration_s = 30.0

    [grid]                              # every combination of these values is run for every seed
    "network.name" = ["hospital_loop", "residential"]
    solutions = [[{name = "GPS", sensors = ["gnss"]}], []]

Keys in ``[grid]`` and ``[set]`` are the dotted ``--set`` paths of
:func:`v2v.config.scenario.apply_override` (quoted, or written as nested TOML tables);
values replace, as ``--set`` does. Every combination is validated with
:func:`~v2v.config.scenario.load_scenario`, and each distinct one's set-up (network, sky, faults' PRNs)
with :func:`v2v.run.check_scenario`, before any run starts.

Execution: each run is one :func:`v2v.run.run_scenario` call in a Dask worker *process*
(libsumo allows one simulation per process and is not thread-safe; a process-wide lock
serializes runs even on a worker started with several threads). The default is a
``LocalCluster`` on 127.0.0.1 with one single-threaded worker process per core;
``--scheduler tcp://HOST:PORT`` sends the same tasks to an existing cluster, whose
workers must see the output folder (a shared file system) and have the same v2v.

Output folder::

    DIR/sweep.json          the study (grid columns, seeds, source) for ``v2v sweep report``
    DIR/runs/<run_id>/      each run's folder (written atomically by run_scenario)
    DIR/runs.parquet        one row per run: run_id, grid columns, seed, status, error,
                            wall_s, note (summary.json's, "" if none), then the run's
                            summary.json flattened to numbers

``run_id`` is ``<readable grid values>-s<seed>-<hash>``, the hash taken over the run's inputs
(the base file's bytes, ``[set]``, its grid values, its seed): editing the study gives new ids
and never reuses a stale run, while a v2v update does not invalidate finished runs (use a new
``--out`` to redo them). Rerunning a study skips runs whose folder holds a readable
``summary.json``; ``runs.parquet`` is rewritten atomically as runs complete (Ctrl-C leaves it
consistent: finished runs are in it, unfinished ones are not). ``--out`` is new, empty, or this
study's sweep folder: another study's sweep folder or a single run's folder is refused before
anything is written (:func:`_check_out_folder`).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import hashlib
import itertools
import json
import math
import os
import re
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from v2v.errors import Terminated, UserError
from v2v.io.atomic import make_folder

STUDY_KEYS = ("base", "seeds", "replay", "save_measurements", "set", "grid")
META_COLUMNS = ("run_id", "seed", "status", "error", "note", "wall_s")
RUNS_FILE = "runs.parquet"
SWEEP_FILE = "sweep.json"
PROGRESS_EVERY_S = 30.0  # wall seconds between progress lines when stderr is not a terminal
MAX_SEED = 2**31 - 1
# summary.json entries that are not per-run results (or not numbers worth a column)
_SUMMARY_SKIP = frozenset({
    "v2v_version", "scenario", "seed", "network", "wall_s", "real_time_factor", "timing_s", "vehicles",
    "leads", "solutions", "events", "table", "note", "statistics",
})


# --------------------------------------------------------------------------- the study


@dataclass(frozen=True, kw_only=True)
class RunSpec:
    """One run of a study: a grid combination and a seed."""

    run_id: str
    labels: dict[str, Any]  # grid column -> value as written to runs.parquet
    seed: int
    scenario: Any  # v2v.config.scenario.Scenario (validated)


@dataclass(frozen=True, kw_only=True)
class Study:
    source: Path
    base: Path | None
    fixed: dict[str, Any]
    grid: dict[str, list[Any]]
    seeds: tuple[int, ...]
    replay: bool = False
    save_measurements: bool = False
    runs: tuple[RunSpec, ...] = field(default=())
    # Scenario.sparse_sensor_warnings of the grid combinations, each line once (with the
    # combinations it holds for when not all of them): printed as the sweep starts
    warnings: tuple[str, ...] = field(default=())

    @property
    def grid_columns(self) -> list[str]:
        return list(self.grid)

    @property
    def base_dir(self) -> Path | None:
        return self.base.parent if self.base is not None else None


def toml_inline(value: Any) -> str:
    """A Python value read from TOML, written back as an inline TOML value (for ``--set``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, _dt.datetime | _dt.date | _dt.time):
        return value.isoformat()
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_inline(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_inline(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"cannot write {type(value).__name__} as TOML")


def _flatten_table(table: dict[str, Any], prefix: str, where: str, *, leaf_lists: bool) -> dict[str, Any]:
    """Nested TOML tables -> dotted paths. With ``leaf_lists`` every leaf must be a list (a grid)."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        path = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten_table(v, path, where, leaf_lists=leaf_lists))
        elif leaf_lists and not isinstance(v, list):
            raise UserError(f"grid values must be a list of values (got {v!r})", field=f"{where}.{path}",
                            fix=f'write e.g. "{path}" = [{toml_inline(v)}, ...], or move it to [set]')
        else:
            out[path] = v
    return out


def _label(value: Any) -> Any:
    if isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list) and value and all(isinstance(v, dict) and "name" in v for v in value):
        return ", ".join(str(v["name"]) for v in value)  # e.g. a solutions list -> its names
    return json.dumps(value, separators=(",", ":"), default=str)


def _column_labels(values: list[Any]) -> list[Any]:
    """Labels for one grid column, with one parquet type per column."""
    labels = [_label(v) for v in values]
    if len({json.dumps(x) for x in labels}) < len(labels):  # (e.g. two solutions lists of the same names)
        labels = [json.dumps(v, separators=(",", ":"), default=str) for v in values]
    if all(isinstance(x, bool) for x in labels):
        return labels
    if all(isinstance(x, int | float) and not isinstance(x, bool) for x in labels):
        return labels
    return [str(x) for x in labels]


def _slug(value: Any) -> str:
    s = re.sub(r"[^A-Za-z0-9.+-]+", "-", str(value)).strip("-.")
    return s[:24] or "x"


def _read_seeds(raw: Any, where: str) -> tuple[int, ...]:
    if isinstance(raw, list):
        seeds = raw
    elif isinstance(raw, dict):
        extra = set(raw) - {"start", "count"}
        if extra or "count" not in raw:
            raise UserError(f"seeds table needs 'count' (and optionally 'start'), got keys {sorted(raw)}",
                            field="seeds", fix="write seeds = {start = 1, count = 100} or seeds = [1, 2, 3]")
        start, count = raw.get("start", 1), raw["count"]
        if not all(isinstance(x, int) and not isinstance(x, bool) for x in (start, count)) or count < 1:
            raise UserError("seeds.start and seeds.count must be integers, count >= 1", field="seeds",
                            fix="write seeds = {start = 1, count = 100}")
        if not 0 <= start <= start + count - 1 <= MAX_SEED:  # (checked before the list is built)
            raise UserError(f"seeds {start}..{start + count - 1} leave [0, {MAX_SEED}]", field="seeds",
                            fix="use a non-negative start and a smaller count")
        seeds = list(range(start, start + count))
    else:
        raise UserError(f"seeds must be a list or a table in {where}", field="seeds",
                        fix="write seeds = [1, 2, 3] or seeds = {start = 1, count = 100}")
    if not seeds:
        raise UserError("no seeds given", field="seeds", fix="list at least one seed")
    for s in seeds:
        if not isinstance(s, int) or isinstance(s, bool) or not 0 <= s <= MAX_SEED:
            raise UserError(f"seed {s!r} is not an integer in [0, {MAX_SEED}]", field="seeds",
                            fix="use non-negative integers")
    if len(set(seeds)) != len(seeds):
        raise UserError("a seed is listed twice", field="seeds", fix="list each seed once")
    return tuple(seeds)


def load_study(path: str | Path) -> Study:
    """Read a study file and validate every run's scenario, including what a run checks
    before SUMO starts (:func:`v2v.run.check_scenario`: network, sky, faults' PRNs); raises
    :class:`UserError`."""

    from v2v.config.scenario import key_parts, load_scenario, read_toml
    from v2v.run import check_scenario

    p = Path(path)
    data = read_toml(p, field="STUDY", what="study file")
    unknown = sorted(set(data) - set(STUDY_KEYS))
    if unknown:
        import difflib

        close = difflib.get_close_matches(unknown[0], STUDY_KEYS, n=1)
        raise UserError(f"unknown key in study {p}", field=unknown[0],
                        fix=f"did you mean {close[0]!r}?" if close else f"allowed: {', '.join(STUDY_KEYS)}")
    base: Path | None = None
    if "base" in data:
        if not isinstance(data["base"], str) or not data["base"]:
            raise UserError("base must be a path string", field="base", fix='write base = "../scenario.toml"')
        base = (p.parent / data["base"]).resolve()
        if not base.is_file():
            raise UserError(f"base scenario {str(base)!r} {'is a folder' if base.is_dir() else 'does not exist'}",
                            field="base",
                            fix="give a scenario path relative to the study file, or omit base for the default")
    for flag in ("replay", "save_measurements"):
        if not isinstance(data.get(flag, False), bool):
            raise UserError(f"{flag} must be true or false", field=flag, fix=f"write {flag} = false")
    for table in ("set", "grid"):
        if not isinstance(data.get(table, {}), dict):
            raise UserError(f"{table} must be a table", field=table, fix=f"write [{table}] followed by key = value lines")
    fixed = _flatten_table(data.get("set", {}), "", "set", leaf_lists=False)
    grid = _flatten_table(data.get("grid", {}), "", "grid", leaf_lists=True)
    if "seed" in fixed:  # (each run's seed comes from `seeds`: a [set] seed would be overridden)
        example = toml_inline(fixed["seed"]) if isinstance(fixed["seed"], int) else "1"
        raise UserError("seeds are not a [set] value (each run's seed comes from seeds)", field="set.seed",
                        fix=f"use seeds = [{example}] at the top level")
    for key, values in grid.items():
        if key == "seed":
            raise UserError("seeds are not a grid parameter", field="grid.seed", fix="use seeds = [...] at the top level")
        if key in fixed:
            raise UserError(f"{key} is both in [set] and in [grid]", field=f"grid.{key}", fix="keep it in one place")
        if key in META_COLUMNS:
            raise UserError(f"{key} is a reserved column name", field=f"grid.{key}", fix="choose another field")
        if not values:
            raise UserError("empty list of grid values", field=f"grid.{key}", fix="give at least one value")
        texts = [toml_inline(v) for v in values]
        if len(set(texts)) != len(texts):
            raise UserError("a value is listed twice", field=f"grid.{key}", fix="list each value once")
    def where(k: str) -> str:
        return "grid" if k in grid else "set"

    for b in [*fixed, *grid]:  # (what apply_override would refuse naming --set, named here as the study's key)
        if not all(key_parts(b)):
            raise UserError(f"key {b!r} has an empty part" if b.strip() else "an empty key", field=f"{where(b)}.{b}",
                            fix='one "." between the parts of a quoted dotted key, e.g. "clusters.0.vehicles"')
    for b in [*fixed, *grid]:  # a path inside another: one value would silently override the other
        parts = key_parts(b)
        for a in (".".join(parts[:i]) for i in range(1, len(parts))):
            if a in fixed or a in grid:
                raise UserError(f"{b} ([{where(b)}]) is inside {a} ([{where(a)}]): one would silently override "
                                "the other", field=f"{where(b)}.{b}",
                                fix=f"give it inside {a}'s value, or split {a} into its fields")
    seeds = _read_seeds(data.get("seeds", [1]), str(p))
    study = Study(source=p.resolve(), base=base, fixed=fixed, grid=grid, seeds=seeds,
                  replay=data.get("replay", False), save_measurements=data.get("save_measurements", False))

    keys = list(grid)
    base_digest = hashlib.sha1(base.read_bytes()).hexdigest() if base is not None else "default"
    labels_by_key = {k: _column_labels(grid[k]) for k in keys}
    fixed_ov = [f"{k}={toml_inline(v)}" for k, v in fixed.items()]
    runs: list[RunSpec] = []
    seen: dict[str, str] = {}
    checked: set[str] = set()
    warned: dict[str, list[str]] = {}  # warning line -> the combinations it holds for
    for combo in itertools.product(*(range(len(grid[k])) for k in keys)):
        labels = {k: labels_by_key[k][i] for k, i in zip(keys, combo, strict=True)}
        grid_ov = [f"{k}={toml_inline(grid[k][i])}" for k, i in zip(keys, combo, strict=True)]
        desc = ", ".join(f"{k}={v}" for k, v in labels.items()) or "the base scenario"
        try:
            first = load_scenario(base, [*fixed_ov, *grid_ov, f"seed={seeds[0]}"],
                                  overrides_from="the study's [set] / [grid]")
            # what the run's set-up checks (network, sky, faults' PRNs), once per distinct input
            key = first.model_dump_json(include={"network", "sensors", "start_utc", "duration_s", "faults"})
            if key not in checked:
                check_scenario(first, study.base_dir)
                checked.add(key)
        except UserError as exc:
            field = exc.field
            if field and field.startswith("--set "):  # a key path the scenario has no place for (apply_override)
                path = field.removeprefix("--set ")
                field = f"{where(path)}.{path}"
            raise UserError(f"{exc.message} (study {p.name}, run {desc})", field=field, fix=exc.fix) from None
        for line in first.sparse_sensor_warnings():
            warned.setdefault(line, []).append(desc)
        readable = "_".join(_slug(v) for v in labels.values()) or "run"
        params = {k: toml_inline(grid[k][i]) for k, i in zip(keys, combo, strict=True)}
        for seed in seeds:  # the seed changes nothing else, and was range-checked above
            sc = first if seed == seeds[0] else first.model_copy(update={"seed": seed})
            digest = _run_digest(base_digest, fixed, params, seed)
            resolved = hashlib.sha1(sc.model_dump_json().encode()).hexdigest()
            if resolved in seen:
                raise UserError(f"runs {seen[resolved]} and {desc} resolve to the same scenario", field="grid",
                                fix="remove the duplicate grid value")
            seen[resolved] = desc
            runs.append(RunSpec(run_id=f"{readable}-s{seed}-{digest}", labels=labels, seed=seed, scenario=sc))
    n_combos = math.prod(len(grid[k]) for k in keys)
    warnings = tuple(line if len(descs) == n_combos else f"{line} (grid: {'; '.join(descs)})"
                     for line, descs in warned.items())
    return dataclasses.replace(study, runs=tuple(runs), warnings=warnings)


def _run_digest(base_digest: str, fixed: dict[str, Any], params: dict[str, str], seed: int) -> str:
    """Stable id of a run's inputs: the base file's content, [set], the grid values, the seed."""
    key = {"base": base_digest, "set": {k: toml_inline(v) for k, v in sorted(fixed.items())},
           "grid": dict(sorted(params.items())), "seed": seed}
    return hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:10]


# --------------------------------------------------------------------------- one run (in a worker)


@dataclass(frozen=True, kw_only=True)
class RunTask:
    run_id: str
    scenario: Any
    out_dir: str
    replay: bool
    save_measurements: bool
    base_dir: str | None


_SUMO_LOCK = threading.Lock()  # libsumo: one simulation per process, never two threads at once


def one_line_error(exc: BaseException) -> str:
    if isinstance(exc, UserError):
        return exc.one_line()
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def read_summary(run_dir: Path) -> dict[str, Any] | None:
    """The run's summary.json, or None if the run is not complete."""
    try:
        with (Path(run_dir) / "summary.json").open(encoding="utf-8") as f:
            s = json.load(f)
    except (OSError, ValueError):
        return None
    return s if isinstance(s, dict) else None


def _flatten_numbers(prefix: str, value: Any, out: dict[str, float]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten_numbers(f"{prefix}.{k}", v, out)
    elif isinstance(value, bool):
        out[prefix] = float(value)
    elif isinstance(value, int | float):
        out[prefix] = float(value)
    elif value is None:
        out[prefix] = float("nan")  # json_safe wrote NaN as null


def flatten_summary(summary: dict[str, Any]) -> dict[str, float]:
    """summary.json -> ``{column: number}``: ``simulated_s``, ``gnss.epochs``, ...,
    ``<solution>.<vehicle>.along.std``, ``<solution>.measurements.<kind>.<field>``."""
    out: dict[str, float] = {}
    for k, v in summary.items():
        if k not in _SUMMARY_SKIP:
            _flatten_numbers(k, v, out)
    for sol, s in (summary.get("statistics") or {}).items():
        for veh, entry in (s.get("vehicles") or {}).items():
            _flatten_numbers(f"{sol}.{veh}", entry, out)
        for k, v in s.items():
            if k != "vehicles":
                _flatten_numbers(f"{sol}.{k}", v, out)
    return out


def execute_run(task: RunTask) -> dict[str, Any]:
    """Run one scenario; never raises (libsumo's exceptions do not pickle): returns a plain dict."""
    t0 = time.perf_counter()
    try:
        from v2v.run import run_scenario

        with _SUMO_LOCK:
            run_scenario(task.scenario, Path(task.out_dir), quiet=True, replay=task.replay,
                         save_measurements=task.save_measurements,
                         base_dir=Path(task.base_dir) if task.base_dir else None)
        summary = read_summary(Path(task.out_dir))
        if summary is None:
            raise RuntimeError(f"the run finished but {task.out_dir}/summary.json is not readable")
        return {"run_id": task.run_id, "status": "ok", "error": "", "wall_s": float(summary.get("wall_s", math.nan)),
                "metrics": flatten_summary(summary), "note": str(summary.get("note", "")), "pid": os.getpid()}
    except Exception as exc:  # noqa: BLE001 - every failure becomes a row, the study goes on
        return {"run_id": task.run_id, "status": "failed", "error": one_line_error(exc),
                "wall_s": round(time.perf_counter() - t0, 3), "metrics": {}, "note": "", "pid": os.getpid()}


# --------------------------------------------------------------------------- the sweep


@dataclass(frozen=True, kw_only=True)
class SweepResult:
    out_dir: Path
    total: int
    executed: int  # runs started by this call
    skipped: int  # runs already complete in the output folder
    failed: int
    wall_s: float
    table: Any  # the runs.parquet DataFrame


def _row(spec: RunSpec, status: str, error: str, wall_s: float, metrics: dict[str, float], note: str = "") -> dict[str, Any]:
    return {"run_id": spec.run_id, **spec.labels, "seed": spec.seed, "status": status, "error": error,
            "wall_s": wall_s, "note": note, **metrics}


def _runs_table(study: Study, rows: dict[str, dict[str, Any]]):
    import pandas as pd

    ordered = [rows[s.run_id] for s in study.runs if s.run_id in rows]
    head = ["run_id", *study.grid_columns, "seed", "status", "error", "wall_s", "note"]
    empty = not ordered and bool(study.runs)
    if empty:  # the dtypes of a table with rows (a first run as a prototype, then no rows)
        ordered = [_row(study.runs[0], "ok", "", math.nan, {})]
    metrics: dict[str, None] = {}
    for r in ordered:
        metrics.update(dict.fromkeys(k for k in r if k not in head))
    df = pd.DataFrame(ordered, columns=[*head, *metrics])
    df["seed"] = df["seed"].astype("int64")
    df["wall_s"] = df["wall_s"].astype(float)
    for c in metrics:
        df[c] = df[c].astype(float)
    return df.iloc[:0].copy() if empty else df


def _import_table_modules() -> None:
    """Import pandas and pyarrow's Parquet writer on a thread of their own (started as the
    study starts; joined by the first table write's own imports, which wait for it). A signal
    interrupts only the main thread: a Ctrl-C in the ~0.3 s of pandas' first import left it
    partially initialized, and every later write of the table, the one after the interrupt
    included, then failed ("partially initialized module 'pandas'")."""
    def load() -> None:
        import pandas  # noqa: F401
        import pyarrow.parquet  # noqa: F401

    threading.Thread(target=load, name="v2v-sweep-imports", daemon=True).start()


def _write_runs(out: Path, study: Study, rows: dict[str, dict[str, Any]]):
    from v2v.io.atomic import atomic_write_parquet

    df = _runs_table(study, rows)
    atomic_write_parquet(out / RUNS_FILE, df)
    return df


def _write_sweep_json(out: Path, study: Study) -> None:
    from v2v.io.atomic import atomic_write_json

    atomic_write_json(out / SWEEP_FILE, {
        "study": str(study.source),
        "base": str(study.base) if study.base else None,
        "set": {k: toml_inline(v) for k, v in study.fixed.items()},
        "grid": {k: [toml_inline(v) for v in vals] for k, vals in study.grid.items()},
        "grid_columns": study.grid_columns,
        "seeds": list(study.seeds),
        "runs": len(study.runs),
    })


class _FolderLock:
    """An exclusive lock on a sweep's output folder (``.sweep.lock``, ``fcntl.flock``) held
    while a study runs: a second ``v2v sweep`` on the same folder (e.g. started while the
    first is still finishing after Ctrl-C) would clear the first one's staging folders and
    race it for the same runs. The operating system releases it when the process ends.

    The lock file is removed (while still locked) when the lock is released, on success and
    on every error: so a sweep that stopped leaves no ``.sweep.lock`` behind. A process that
    opened the file before its holder removed it then holds a lock on a removed file, so a
    lock counts only once the locked file is still the one at ``.sweep.lock``."""

    def __init__(self, out: Path) -> None:
        self.path = out / ".sweep.lock"
        self._f: Any = None

    def __enter__(self) -> _FolderLock:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            return self
        while True:
            self._f = open(self.path, "a+")  # noqa: SIM115 - held until __exit__
            try:
                fcntl.flock(self._f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                self._f.seek(0)
                owner = self._f.read().strip() or "another process"
                self._f.close()
                self._f = None
                raise UserError(f"another sweep is writing to {self.path.parent} ({owner})", field="--out",
                                fix="wait for it to finish (or stop it), or give another --out") from None
            try:
                st = os.stat(self.path)
                mine = os.fstat(self._f.fileno())
                if (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino):
                    break
            except OSError:  # removed by the holder that just released it: lock the next file
                pass
            self._f.close()
        self._f.seek(0)
        self._f.truncate()
        self._f.write(f"pid {os.getpid()}\n")
        self._f.flush()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._f is not None:
            try:
                self.path.unlink()  # while still holding it (see the class's docstring)
            except OSError:
                pass
            self._f.close()  # releases the lock
            self._f = None


def _remove_staging(runs_dir: Path) -> None:
    """Remove the hidden staging folders (``.<run_id>.*.partial``) of runs that never completed."""
    for d in runs_dir.glob(".*.partial"):
        shutil.rmtree(d, ignore_errors=True)


_SCHEDULER_RE = re.compile(r"^(?:tcp://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+):(?P<port>\d{1,5})$")


SCHEDULER_CONNECT_S = 30.0  # the Dask handshake with a --scheduler, in all


async def _identity(address: str, timeout_s: float) -> Any:
    """The ``identity`` reply of the Dask server at ``address`` (one message each way)."""
    from distributed.comm import connect

    comm = await connect(address, timeout=timeout_s)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


def _check_scheduler_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail fast, in one line, on a malformed or unreachable ``tcp://HOST:PORT``, or one that
    answers but is not a Dask scheduler.

    Dask's own timeout does not bound the handshake (a port that accepts TCP but speaks
    something else can hang it, or make it read a garbage frame length, and a half-built
    Client then blocks the interpreter's exit for a minute). So the address is asked for its
    identity, in a throw-away event loop on a daemon thread given ``SCHEDULER_CONNECT_S`` in
    all; only a server that answers as a Dask ``Scheduler`` passes."""
    import asyncio
    import socket

    m = _SCHEDULER_RE.match(address.strip())
    if m is None:
        raise UserError(f"{address!r} is not a scheduler address", field="--scheduler",
                        fix="give tcp://HOST:PORT, as printed by `dask scheduler`")
    host, port = m["host"].strip("[]"), int(m["port"])
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        raise UserError(f"no scheduler answers at {address} ({one_line_error(exc)})", field="--scheduler",
                        fix="start one (`dask scheduler`) or check the host and port") from None
    wait_s = SCHEDULER_CONNECT_S
    box: dict[str, Any] = {}

    def ask() -> None:
        try:
            box["reply"] = asyncio.run(asyncio.wait_for(_identity(address, wait_s), wait_s))
        except TimeoutError:
            box["error"] = f"no Dask handshake within {wait_s:.0f} s"
        except BaseException as exc:  # noqa: BLE001 - reported below, in one line
            box["error"] = one_line_error(exc) or type(exc).__name__

    t = threading.Thread(target=ask, name="v2v-scheduler-probe", daemon=True)
    t.start()
    t.join(wait_s + 5.0)
    reply = box.get("reply")
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        why = (f"no Dask handshake within {wait_s:.0f} s" if t.is_alive() else box.get("error")
               or f"it answered as {kind or 'something else'}")
        raise UserError(f"{address} answered but is not a usable Dask scheduler ({why})", field="--scheduler",
                        fix="give the scheduler's own address, as printed by `dask scheduler` (default port 8786)")


HOST_FIX = "give an address of this machine for the local cluster, e.g. --host 127.0.0.1 (the default)"


def _check_host(host: str) -> None:
    """Fail fast, in one line, on a ``--host`` the local cluster could not listen on (a name
    that does not resolve, an address of another machine): resolve it and bind a TCP socket
    to it on a free port, as the cluster's scheduler will."""
    import socket

    name = host.split("://", 1)[-1].strip()
    if name.startswith("[") and name.endswith("]"):
        name = name[1:-1]
    try:
        infos = socket.getaddrinfo(name or None, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError) as exc:
        raise UserError(f"{host!r} does not resolve to an address ({one_line_error(exc)})", field="--host",
                        fix=HOST_FIX) from None
    why = "no address"
    for family, kind, proto, _, addr in infos:
        try:
            with socket.socket(family, kind, proto) as s:
                s.bind(addr)
            return
        except OSError as exc:
            why = one_line_error(exc)
    raise UserError(f"cannot listen on {host!r} ({why})", field="--host", fix=HOST_FIX)


# Settings of the local cluster (the nannies pass them on to their workers). There is no
# dashboard, so no use for the workers' statistical profiler, which otherwise takes every
# thread's stack each 10 ms (a py-spy profile of a sweep worker: ~2.5 % of the time the worker
# holds the GIL), nor for system metrics twice a second. Memory is checked once a second, not
# ten times (a run is one task of ~0.5-20 s), and the event loops' tick (a blocked-loop
# watchdog) runs once a second, not every 20 ms. Measured on 60 runs of 60 s at N = 3 on two
# workers, three interleaved pairs: this process (scheduler, nannies, client) used 1.1-1.4 s of
# CPU against 2.1-2.2 s with Dask's defaults.
# The worker processes are forked from a fork server (started once per process, with this
# process's environment after the nannies' pre-spawn settings: one BLAS / OpenMP thread, the
# hash seed, SIGINT ignored) instead of spawned: a spawned worker ends with a full interpreter
# shutdown, which after v2v's runs took 0.45 s in a plain process and made the cluster's close
# 0.56-0.71 s of a 100-run study; a forked one leaves with os._exit once it has closed, and the
# close took 0.04-0.06 s. The workers' environment, SIGINT disposition and hash seed are the
# same either way (checked with Client.run).
# Dask's nannies also set MALLOC_TRIM_THRESHOLD_=65536 for their workers (to give freed memory
# back to the system sooner); setting it turns off glibc's dynamic mmap threshold, so every
# array over 128 kB (a 20-car covariance is 195 kB) is mapped and unmapped anew. Without it a
# warm N = 20 run took 1.97-2.09 s against 2.12-2.22 s with it (two interleaved pairs of three
# runs), N = 3 runs ~1 % less; a worker runs one study run at a time and reuses what it freed.
_LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.multiprocessing-method": "forkserver",
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.tick.interval": "1s",
}


def _open_client(scheduler: str | None, workers: int | None, host: str, n_pending: int):
    """(client, cluster or None). The local cluster: one single-threaded worker process per core."""
    import logging
    import multiprocessing
    import warnings

    import dask
    from dask.distributed import Client, LocalCluster

    if scheduler:  # (checked by _check_scheduler_reachable before anything was written)
        try:
            return Client(scheduler, timeout=f"{SCHEDULER_CONNECT_S}s", set_as_default=False), None
        except Exception as exc:  # noqa: BLE001 - a scheduler that went away since the check
            raise UserError(f"cannot connect to the scheduler {scheduler}: {one_line_error(exc)}", field="--scheduler",
                            fix="start one (dask scheduler) or give its tcp://HOST:PORT") from None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    n = max(1, min(workers or cores, n_pending))
    # Worker processes inherit an ignored SIGINT: Ctrl-C in the terminal reaches only this process,
    # which then cancels the study and closes the cluster (instead of every worker dying mid-write).
    # They are forked from the fork server and take its SIGINT disposition at its start, so SIGINT
    # is ignored only while the fork server starts (a few ms, once per process). A SIGINT or
    # SIGTERM during the cluster's start (~1 s) is held and acted on once the cluster is up and
    # closed again: ignoring SIGINT for the whole start dropped a Ctrl-C there (the study then ran
    # to its end), and raising in the middle of the start left a half-started cluster whose close
    # at exit printed tracebacks.
    config = _LOCAL_CLUSTER_CONFIG
    if "forkserver" not in multiprocessing.get_all_start_methods():  # (Windows: Dask's default, spawn)
        config = {k: v for k, v in config.items() if k != "distributed.worker.multiprocessing-method"}
    in_main = threading.current_thread() is threading.main_thread()
    with dask.config.set(config):
        from distributed.utils import get_mp_context

        forked = get_mp_context().get_start_method() == "forkserver"  # (also sets the fork server's preloads)
    held: list[int] = []
    old: dict[int, Any] = {}  # signal number -> the handler to put back
    if in_main:
        old[signal.SIGINT] = signal.signal(signal.SIGINT, signal.SIG_IGN)
        if forked:
            from multiprocessing import forkserver

            try:
                forkserver.ensure_running()
            finally:
                signal.signal(signal.SIGINT, old[signal.SIGINT])
            for signum in (signal.SIGINT, signal.SIGTERM):  # held until the cluster is up
                old[signum] = signal.signal(signum, lambda sn, _frame: held.append(sn))
    try:
        with warnings.catch_warnings(), dask.config.set(config):
            warnings.filterwarnings("ignore", message="Port .* is already in use")  # the scheduler's HTTP endpoint
            try:
                # (Dask's own logs off below CRITICAL: a run's failure is its row's one-line error, and
                # a worker whose heartbeat meets the scheduler's close after Ctrl-C logged a traceback)
                cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host=host,
                                       dashboard_address=None, silence_logs=logging.CRITICAL)
            except Exception as exc:  # noqa: BLE001 - (checked by _check_host; e.g. a port gone since)
                raise UserError(f"the local cluster did not start on {host!r} ({one_line_error(exc)})",
                                field="--host", fix=HOST_FIX) from None
    finally:
        for num, h in old.items():
            signal.signal(num, h)
    if held:  # as the handler would have, now that the cluster can be closed
        cluster.close()
        first = old.get(held[0])
        if callable(first):
            first(held[0], None)
        raise KeyboardInterrupt
    try:
        return Client(cluster, set_as_default=False), cluster
    except BaseException:
        cluster.close()
        raise


def run_study(
    study: Study | str | Path,
    out_dir: str | Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    host: str = "127.0.0.1",
    quiet: bool = True,
    flush_every_s: float = 5.0,
) -> SweepResult:
    """Run every not-yet-complete run of a study; write ``runs.parquet``. Returns counts and the table.

    While the runs complete, ``runs.parquet`` is rewritten at most every ``flush_every_s``
    seconds, and never more often than every 20 times the last rewrite took (the table grows
    with the study, and this process shares the machine with the workers: its rewrites are
    kept to <= 5 % of the wall time); it is complete when the call returns, also after Ctrl-C.

    The output folder is locked while the study runs (:class:`_FolderLock`): a second sweep
    on the same folder stops with a one-line error instead of racing the first."""
    if not isinstance(study, Study):
        study = load_study(study)
    if workers is not None and workers < 1:
        raise UserError(f"--workers must be >= 1 (got {workers})", field="--workers", fix="give a positive count")
    if workers is not None and scheduler:
        raise UserError("--workers sizes the local cluster only", field="--workers",
                        fix="drop --workers when you give --scheduler (that cluster's workers run the study)")
    wall0 = time.perf_counter()
    out = Path(out_dir).resolve()
    runs_dir = out / "runs"
    # before anything is written: the folder is this study's (or new), the cluster can be had
    _check_out_folder(study, out)
    if _scan(study, runs_dir)[1]:
        if scheduler:
            _check_scheduler_reachable(scheduler)
        else:
            _check_host(host)
    created = not out.exists()
    make_folder(out)
    try:
        with _FolderLock(out):
            _check_out_folder(study, out)  # again, locked: another sweep may have written to it meanwhile
            return _run_study_locked(study, out, scheduler, workers, host, quiet, flush_every_s, wall0)
    except BaseException:
        if created:  # a folder this call made and left empty (it failed before writing) goes too
            try:
                out.rmdir()
            except OSError:
                pass
        raise


def _run_keys_on_worker(keys: list[str], dask_worker: Any = None) -> list[tuple[str, bool]]:
    """(On a worker, through ``Client.run``.) Which of ``keys`` this worker still holds as work,
    each with whether it is running now: a cancelled task whose function had started stays
    (state ``cancelled``, in the executing set) until the function returns, and a task it was
    given but had not started stays until the scheduler's release reaches it (it may start
    meanwhile). Finished results (``memory``) are not work."""
    st = dask_worker.state
    running = st.executing | st.long_running
    return [(ts.key, ts in running) for k in keys
            if (ts := st.tasks.get(k)) is not None and ts.state not in ("memory", "error", "released", "forgotten")]


def _await_started_runs(client: Any, futures: list[Any], stopped_by: BaseException | None) -> list[str]:
    """After a remote cluster's sweep stopped early (its futures cancelled): wait until its
    workers hold none of the study's runs, so that the table written next lists every run
    that completes. Dask cannot stop a task once its function runs: such a run completes and
    publishes its folder. A second Ctrl-C, or a SIGTERM, stops the waiting. Returns the run keys
    still running when it stopped waiting (empty when none is)."""
    if stopped_by is None or not futures:
        return []
    keys = [f.key for f in futures]

    def held() -> tuple[list[str], list[str]]:  # (held by a worker, of which running)
        try:
            per = client.run(_run_keys_on_worker, keys)
        except Exception:  # noqa: BLE001 - a worker or the scheduler gone: nothing left to wait for there
            return [], []
        pairs = [p for ps in per.values() for p in ps]
        return sorted({k for k, _ in pairs}), sorted({k for k, r in pairs if r})

    waiting, running = held()
    said = False
    try:
        while waiting and not isinstance(stopped_by, Terminated):
            if running and not said:
                print(f"sweep: waiting for the {len(running)} run(s) the cluster's workers had started (Dask cannot "
                      "stop a running task); Ctrl-C again to leave them running", file=sys.stderr, flush=True)
                said = True
            time.sleep(0.1)
            waiting, running = held()
    except KeyboardInterrupt:
        running = running or held()[1]
    if running:
        print(f"sweep: {len(running)} run(s) still running on the cluster's workers are not in runs.parquet: "
              "rerun the study once they are done to list them", file=sys.stderr, flush=True)
    return running


def _check_out_folder(study: Study, out: Path) -> None:
    """Refuse, in one line naming --out, a folder a sweep of ``study`` must not write to: a
    single run's folder, or another study's sweep (whose runs.parquet and sweep.json this one
    would replace, leaving that study's run folders listed nowhere).

    A sweep folder is this study's if its sweep.json names this study file (the same file,
    perhaps edited, resumes: what is done is decided by run id), or if every run its table
    lists is a run of this study (a copy or a moved study file, or one extended by seeds or
    grid values: nothing of the folder is dropped)."""
    if not out.is_dir():
        return  # new (or not a folder: make_folder says so)
    sweep_json, runs_file = out / SWEEP_FILE, out / RUNS_FILE
    if not sweep_json.exists() and not runs_file.exists():
        from v2v.io.atomic import RUN_FOLDER_MARKERS

        marker = next((n for n in RUN_FOLDER_MARKERS if (out / n).exists()), None)
        if marker is not None:
            raise UserError(f"{out} is a run's folder (it holds {marker}), not a sweep's", field="--out",
                            fix="give a new or empty folder for the sweep (or this study's previous sweep folder)")
        other_files = sorted(n.name for n in out.iterdir() if n.name not in ("runs", ".sweep.lock"))
        if other_files:  # (runs/ alone: a sweep stopped before its sweep.json was written)
            raise UserError(f"{out} is not empty and not a sweep's folder (it holds {other_files[0]!r})",
                            field="--out", fix="give a new or empty folder for the sweep (or this study's previous "
                            "sweep folder)")
        return
    recorded: str | None = None
    try:
        with sweep_json.open(encoding="utf-8") as f:
            data = json.load(f)
        recorded = str(data["study"]) if isinstance(data, dict) and data.get("study") else None
    except (OSError, ValueError):
        pass
    if recorded == str(study.source):
        return
    dropped = _listed_run_ids(out) - {s.run_id for s in study.runs}
    if not dropped:
        return
    other = f"study {recorded}" if recorded else "another study"
    raise UserError(f"{out} holds the sweep of {other}, with {len(dropped)} run(s) that {study.source.name} does "
                    f"not have (its runs.parquet and sweep.json would be replaced)", field="--out",
                    fix=f"give a new folder for {study.source.name}, or rerun the same study into {out}")


def _listed_run_ids(out: Path) -> set[str]:
    """The run ids a sweep folder's runs.parquet lists (if it cannot be read: its run folders)."""
    try:
        import pyarrow.parquet as pq

        return {str(x) for x in pq.read_table(out / RUNS_FILE, columns=["run_id"]).column("run_id").to_pylist()}
    except Exception:  # noqa: BLE001 - missing, unreadable or not a runs table: look at the folders
        runs_dir = out / "runs"
        if not runs_dir.is_dir():
            return set()
        return {d.name for d in runs_dir.iterdir() if d.is_dir() and not d.name.startswith(".")}


def _scan(study: Study, runs_dir: Path) -> tuple[dict[str, dict[str, Any]], list[RunSpec]]:
    """(rows of the runs already complete in ``runs_dir``, the specs still to run)."""
    rows: dict[str, dict[str, Any]] = {}
    pending: list[RunSpec] = []
    for spec in study.runs:
        folder = runs_dir / spec.run_id
        summary = read_summary(folder)
        missing = (study.replay and not (folder / "replay.rrd").is_file()) or \
            (study.save_measurements and not (folder / "measurements.parquet").is_file())
        if summary is None or missing:  # (a run made before replay / save_measurements was turned on)
            pending.append(spec)
        else:
            rows[spec.run_id] = _row(spec, "ok", "", float(summary.get("wall_s", math.nan)), flatten_summary(summary),
                                     str(summary.get("note", "")))
    return rows, pending


def _run_study_locked(study: Study, out: Path, scheduler: str | None, workers: int | None, host: str, quiet: bool,
                      flush_every_s: float, wall0: float) -> SweepResult:
    """:func:`run_study` while holding the output folder's lock."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    _import_table_modules()  # (meanwhile the cluster starts)
    runs_dir = out / "runs"
    rows, pending = _scan(study, runs_dir)
    skipped = len(rows)
    failed = 0
    if not quiet:
        print(f"sweep: {len(study.runs)} runs ({skipped} already complete, {len(pending)} to run) -> {out}",
              file=sys.stderr, flush=True)
    # connect first: a scheduler that fails the handshake leaves no sweep.json / runs.parquet behind
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    n_local = min(workers or cores, len(pending))  # the local cluster's worker processes (_open_client)
    if not quiet and not scheduler and n_local > cores:
        print(f"sweep: note: {n_local} worker processes on {cores} core(s): the runs share the cores (each "
              "worker is one single-threaded process of a few hundred MB)", file=sys.stderr, flush=True)
    client, cluster = _open_client(scheduler, workers, host, len(pending)) if pending else (None, None)
    try:
        runs_dir.mkdir(parents=True, exist_ok=True)
        _remove_staging(runs_dir)  # left by a run killed mid-write
        _write_sweep_json(out, study)
        if not pending:
            df = _write_runs(out, study, rows)
    except BaseException:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
        raise
    if pending:
        assert client is not None
        by_id = {s.run_id: s for s in pending}
        futures = []
        stopped_by: BaseException | None = None  # what ended the loop early (Ctrl-C, SIGTERM, an error)
        try:
            for spec in pending:
                task = RunTask(run_id=spec.run_id, scenario=spec.scenario, out_dir=str(runs_dir / spec.run_id),
                               replay=study.replay, save_measurements=study.save_measurements,
                               base_dir=str(study.base_dir) if study.base_dir else None)
                futures.append(client.submit(execute_run, task, key=f"v2v-run-{spec.run_id}", pure=False))
            # the table of the runs already complete, written while the workers start on the others
            # (its first write may wait for pandas' import, _import_table_modules: ~0.2 s that the
            # workers no longer wait for)
            _write_runs(out, study, rows)
            next_flush = time.monotonic() + flush_every_s
            lines = not quiet and not sys.stderr.isatty()  # (no tqdm bar there: a log, CI, nohup)
            t_start = next_line = time.monotonic()
            done = 0
            with tqdm(total=len(pending), unit="run", desc="sweep", disable=True if quiet else None,
                      file=sys.stderr) as bar:
                for fut in as_completed(futures, loop=client.loop):
                    spec = by_id[fut.key.removeprefix("v2v-run-")]
                    try:
                        res = fut.result()
                    except BaseException as exc:  # noqa: BLE001 - a killed worker, a cancelled task
                        if isinstance(exc, KeyboardInterrupt):
                            raise
                        res = {"status": "failed", "error": f"dask: {one_line_error(exc)}",
                               "wall_s": math.nan, "metrics": {}}
                    failed += res["status"] != "ok"
                    rows[spec.run_id] = _row(spec, res["status"], res["error"], res["wall_s"], res["metrics"],
                                             res.get("note", ""))
                    bar.update(1)
                    bar.set_postfix(failed=failed)
                    done += 1
                    if lines and time.monotonic() >= next_line and done < len(pending):
                        el = time.monotonic() - t_start
                        next_line = time.monotonic() + PROGRESS_EVERY_S
                        print(f"sweep: {done} of {len(pending)} runs ({failed} failed), {el:.0f} s, "
                              f"~{el / done * (len(pending) - done):.0f} s to go", file=sys.stderr, flush=True)
                    if time.monotonic() >= next_flush:
                        t_w = time.monotonic()
                        _write_runs(out, study, rows)
                        now = time.monotonic()
                        next_flush = now + max(flush_every_s, 20.0 * (now - t_w))
        except BaseException as exc:
            stopped_by = exc
            raise
        finally:
            left: list[str] = []
            try:
                df = _write_runs(out, study, rows)
            finally:  # (the runs cancelled and the cluster closed even if the table could not be written)
                client.cancel([f for f in futures if not f.done()])
                # A task a remote cluster's worker is executing is not stopped by the cancel: wait
                # for those runs (Ctrl-C) so that the table lists them; the local cluster's
                # workers are closed instead, and what they were writing is removed.
                if cluster is None:
                    left = _await_started_runs(client, futures, stopped_by)  # (said also with --quiet: why it waits)
                client.close()
                if cluster is not None:
                    cluster.close()
            if not left:
                _remove_staging(runs_dir)  # its workers are gone or idle: nothing is being written any more
                # runs that completed while the cluster shut down (after Ctrl-C) are complete too;
                # the table is written again only if there are any (it holds every other row)
                n_rows = len(rows)
                for run_id, row in _scan(study, runs_dir)[0].items():
                    rows.setdefault(run_id, row)
                if len(rows) > n_rows:
                    df = _write_runs(out, study, rows)
    wall = time.perf_counter() - wall0
    return SweepResult(out_dir=out, total=len(study.runs), executed=len(pending), skipped=skipped, failed=failed,
                       wall_s=wall, table=df)


# --------------------------------------------------------------------------- the report

_STD_RE = re.compile(r"^(?P<sol>.+?)\.(?P<veh>[^.]+\.\d+)\.(?P<comp>along|across|up)\.std$")


#: the fix of a study folder whose tables cannot be used
RERUN_FIX = "rerun the sweep into DIR (finished runs are kept and re-listed)"


def t_interval_half_width(values, confidence: float = 0.95) -> tuple[int, float, float, float]:
    """(n, mean, sample std, half-width of the two-sided Student-t confidence interval of the mean)."""
    import numpy as np
    from scipy import stats

    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return 0, math.nan, math.nan, math.nan
    mean = float(x.mean())
    if n < 2:
        return 1, mean, math.nan, math.nan
    std = float(x.std(ddof=1))
    half = float(stats.t.ppf(0.5 + confidence / 2.0, n - 1) * std / math.sqrt(n))
    return n, mean, std, half


def _grid_columns(runs_dir: Path, df) -> list[str]:
    """The grid columns of ``runs.parquet``: those ``sweep.json`` lists, or (without a readable
    ``sweep.json``) the columns between ``run_id`` and ``seed``. A listed column the table
    lacks is refused: grouping without it would pool the runs of different grid values."""
    try:
        with (runs_dir / SWEEP_FILE).open(encoding="utf-8") as f:
            cols = json.load(f)["grid_columns"]
        if not isinstance(cols, list) or not all(isinstance(c, str) for c in cols):
            raise ValueError("grid_columns is not a list of names")
    except (OSError, ValueError, KeyError, TypeError):
        cols = list(df.columns)
        return cols[cols.index("run_id") + 1: cols.index("seed")] if "run_id" in cols and "seed" in cols else []
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise UserError(f"{runs_dir / RUNS_FILE} has no column {missing[0]!r}, a grid column of {SWEEP_FILE}: "
                        "its runs cannot be told apart", field="DIR",
                        fix=RERUN_FIX)
    return cols


def _with_vehicle_means(df):
    """Add ``<solution>.vehicles_mean.<comp>.std``: the run's mean over its non-lead vehicles.

    NaN for a run in which one of its vehicles (one with ``<solution>.<vehicle>.epochs``) has no
    std (never initialized, or one sample): a mean over the others would average a different set
    of vehicles in different seeds. A vehicle absent from the run (e.g. a grid point with a
    smaller cluster) has no epochs and is not one of its vehicles."""
    import pandas as pd

    groups: dict[tuple[str, str], list[tuple[str, str]]] = {}
    for c in df.columns:
        m = _STD_RE.match(c)
        if m:
            groups.setdefault((m["sol"], m["comp"]), []).append((c, f"{m['sol']}.{m['veh']}.epochs"))
    extra = {}
    for (sol, comp), cols in groups.items():
        std = df[[c for c, _ in cols]]
        present = pd.DataFrame({c: df[e].notna() if e in df else std[c].notna() for c, e in cols}, index=df.index)
        incomplete = (present & std.isna()).any(axis=1)
        extra[f"{sol}.vehicles_mean.{comp}.std"] = std.mean(axis=1, skipna=True).mask(incomplete)
    return pd.concat([df, pd.DataFrame(extra, index=df.index)], axis=1), sorted({s for s, _ in groups})


def aggregate_runs(df, grid_cols: list[str]):
    """Long table: grid values, metric, n, mean, std, ci95_half, ci95_low, ci95_high (ok runs only)."""
    import pandas as pd

    ok = df[df["status"] == "ok"]
    metrics = [c for c in ok.columns if c not in grid_cols and c not in META_COLUMNS[:-1]
               and pd.api.types.is_numeric_dtype(ok[c])]
    records = []
    groups = ok.groupby(grid_cols, sort=False, dropna=False) if grid_cols else [((), ok)]
    for key, g in groups:
        key = key if isinstance(key, tuple) else (key,)
        for m in metrics:
            n, mean, std, half = t_interval_half_width(g[m].to_numpy())
            if n == 0:
                continue
            records.append({**dict(zip(grid_cols, key, strict=True)), "metric": m, "n": n, "mean": mean, "std": std,
                            "ci95_half": half, "ci95_low": mean - half, "ci95_high": mean + half})
    return pd.DataFrame(records, columns=[*grid_cols, "metric", "n", "mean", "std", "ci95_half", "ci95_low", "ci95_high"])


def _fmt(mean: float, half: float, n: int = 0, n_ok: int = 0) -> str:
    """``mean ± half``; with ``(n = k)`` when fewer of the cell's ``n_ok`` finished runs have a value."""
    if not math.isfinite(mean):
        return "-"
    text = f"{mean:.3f} ± {half:.3f}" if math.isfinite(half) else f"{mean:.3f}"
    return f"{text} (n = {n})" if n < n_ok else text


def _md_table(header: list[str], rows: list[list[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(x) for x in r) + " |" for r in rows]
    return lines


@dataclass(frozen=True, kw_only=True)
class ReportResult:
    markdown: Path
    csv: Path
    figure: Path
    table: Any


def write_report(sweep_dir: str | Path, out_dir: str | Path | None = None) -> ReportResult:
    """Aggregate ``runs.parquet`` by grid values: mean and 95 % t-interval across seeds of every metric."""
    import pandas as pd

    src = Path(sweep_dir)
    runs_file = src / RUNS_FILE
    if not runs_file.is_file():
        raise UserError(f"no {RUNS_FILE} in {src}", field="DIR", fix="give the --out folder of a `v2v sweep` run")
    try:
        df = pd.read_parquet(runs_file)
    except (OSError, ValueError) as exc:  # (pyarrow's ArrowInvalid is a ValueError)
        raise UserError(f"{runs_file} is not readable Parquet ({one_line_error(exc)})", field="DIR",
                        fix=RERUN_FIX) from None
    lacking = [c for c in ("run_id", "status") if c not in df.columns]
    if lacking:
        raise UserError(f"{runs_file} has no column {lacking[0]!r}: it is not a `v2v sweep` table", field="DIR",
                        fix=RERUN_FIX)
    if df.empty or not (df["status"] == "ok").any():
        n = len(df)
        errors = df["error"].astype(str) if "error" in df else pd.Series([], dtype=str)
        first = next((e for e in errors if e), "")
        raise UserError(f"{runs_file} lists {n} run(s), none finished" + (f" (first error: {first})" if first else ""),
                        field="DIR",
                        fix="run the study (again) first; failed runs have their one-line error in the `error` column")
    out = Path(out_dir) if out_dir is not None else src
    make_folder(out)
    grid_cols = _grid_columns(src, df)
    df, solutions = _with_vehicle_means(df)
    agg = aggregate_runs(df, grid_cols)

    from v2v.io.atomic import atomic_write_all

    csv_path, md_path, png_path = out / "report.csv", out / "report.md", out / "report.png"
    labels = _figure_labels(df, agg, grid_cols, solutions)
    markdown = _report_markdown(src, df, agg, grid_cols, solutions, labels)
    try:  # the three as one set: a failed write leaves the folder's earlier report whole
        atomic_write_all([(csv_path, lambda p: agg.to_csv(p, index=False)),
                          (md_path, lambda p: p.write_text(markdown, encoding="utf-8")),
                          (png_path, lambda p: _report_figure(agg, labels, p))])
    except OSError as exc:
        raise UserError(f"cannot write the report into {out} ({exc.strerror or one_line_error(exc)})",
                        field="--out" if out_dir is not None else "DIR",
                        fix="give --out a folder that can be written (report.csv, report.md and report.png "
                            "must not be folders)") from None
    return ReportResult(markdown=md_path, csv=csv_path, figure=png_path, table=agg)


def _lookup(agg, grid_cols: list[str], key: tuple, metric: str) -> tuple[float, float, int]:
    sel = agg["metric"] == metric
    for c, v in zip(grid_cols, key, strict=True):
        sel &= agg[c].isna() if _isnan(v) else agg[c] == v
    hit = agg[sel]
    if hit.empty:
        return math.nan, math.nan, 0
    return float(hit["mean"].iloc[0]), float(hit["ci95_half"].iloc[0]), int(hit["n"].iloc[0])


def _isnan(v: Any) -> bool:
    return isinstance(v, float) and math.isnan(v)


def _report_markdown(src: Path, df, agg, grid_cols: list[str], solutions: list[str], labels: _FigureLabels) -> str:
    n_ok = int((df["status"] == "ok").sum())
    n_failed = int((df["status"] != "ok").sum())
    lines = [f"# Sweep report: {src}", "",
             f"{len(df)} runs: {n_ok} ok, {n_failed} failed. Each cell: mean ± half-width of the 95 % "
             "Student-t confidence interval of the mean across seeds (no interval with one seed); "
             "(n = k): only k of the combination's finished runs have a value (failed runs never count).", ""]
    groups = df.groupby(grid_cols, sort=False, dropna=False) if grid_cols else [((), df)]
    keys, n_oks, runs_rows = [], [], []
    for key, g in groups:
        key = key if isinstance(key, tuple) else (key,)
        keys.append(key)
        ok = g[g["status"] == "ok"]
        n_oks.append(len(ok))
        runs_rows.append([*key, len(ok), len(g) - len(ok), _fmt(*_lookup(agg, grid_cols, key, "simulated_s"), len(ok)),
                          f"{ok['wall_s'].mean():.2f}" if len(ok) and "wall_s" in ok else "-"])
    lines += ["## Runs", ""]
    lines += _md_table([*grid_cols, "ok", "failed", "simulated_s", "mean wall_s"], runs_rows)
    lines.append("")
    if solutions:
        lines += ["## Relative position error std per solution and vehicle (m)", ""]
        rows = []
        for key, n_ok in zip(keys, n_oks, strict=True):
            for sol in solutions:
                vehicles = sorted({m["veh"] for c in agg["metric"].unique() if (m := _STD_RE.match(c)) and m["sol"] == sol})
                for veh in [*vehicles, "vehicles_mean"]:
                    along = _lookup(agg, grid_cols, key, f"{sol}.{veh}.along.std")
                    if not math.isfinite(along[0]):
                        continue
                    across = _lookup(agg, grid_cols, key, f"{sol}.{veh}.across.std")
                    avail = _lookup(agg, grid_cols, key, f"{sol}.{veh}.availability")
                    rows.append([*key, sol, veh, *(_fmt(*x, n_ok) for x in (along, across, avail))])
        lines += _md_table([*grid_cols, "solution", "vehicle", "along std", "across std", "availability"], rows)
    else:
        lines += ["## GNSS (no solutions were run)", ""]
        rows = [[*key, *(_fmt(*_lookup(agg, grid_cols, key, m), n_ok) for m in _FALLBACK_METRICS)]
                for key, n_ok in zip(keys, n_oks, strict=True)]
        lines += _md_table([*grid_cols, *_FALLBACK_METRICS], rows)
    failed = df[df["status"] != "ok"]
    if len(failed):
        lines += ["", "## Failed runs", ""]
        lines += _md_table(["run_id", "error"], [[r.run_id, str(getattr(r, "error", "")).replace("|", "/")]
                                                  for r in failed.head(50).itertuples()])
        if len(failed) > 50:
            lines.append(f"... and {len(failed) - 50} more (see runs.parquet)")
    noted = df[(df["status"] == "ok") & (df["note"].fillna("") != "")] if "note" in df else df.iloc[:0]
    if len(noted):  # (a run that ended early, estimated nothing, or lost most messages to lateness)
        lines += ["", "## Runs with a note", ""]
        lines += _md_table(["run_id", "note"], [[r.run_id, str(r.note).replace("|", "/")] for r in noted.head(50).itertuples()])
        if len(noted) > 50:
            lines.append(f"... and {len(noted) - 50} more (see runs.parquet)")
    lines += ["", "All metrics, per grid combination: report.csv. Figure: report.png.", ""]
    shown = [c for c in labels.columns if labels.explain[c]]
    if shown:
        lines += ["## Labels in report.png", "",
                  f"A grid value whose label in report.png is not its whole value: cut to {_LABEL_CHARS} characters "
                  "(…), a solutions list named by its solutions, and [#] after a label (or a solution's name in "
                  "the legend) where two would otherwise be the same, # the value's place in its grid column.", ""]
        rows = [[c, i + 1, _md_cell(lab), _md_cell(v)] for c in shown
                for i, (v, lab) in enumerate(zip(labels.columns[c], labels.texts[c], strict=True))]
        lines += _md_table(["grid column", "#", "label in report.png", "value"], rows)
        lines.append("")
    return "\n".join(lines)


def _md_cell(value: Any) -> str:
    """A value as one markdown table cell (its | and line breaks escaped)."""
    return str(value).replace("\\", "\\\\").replace("|", "\\|").replace("\n", "\\n")


_FALLBACK_METRICS = ("gnss.satellites_tracked_mean", "gnss.nlos_fraction")


_LABEL_CHARS = 40  # a grid value's label in report.png at most (cut with "…"; report.md has the whole value)
_TICK_CHARS = 18  # characters per line of an x tick label (wrapped)


@dataclass(frozen=True, kw_only=True)
class _FigureLabels:
    """What report.png draws, with labels that are distinct and short.

    ``columns``: each grid column's values in the order of runs.parquet, ``texts`` their labels
    (:func:`_value_texts`), ``explain`` whether report.md lists them (a label that is not the
    whole value, or a solutions value the legend numbers). ``xkeys``: the x positions, one per
    combination of the grid columns but ``solutions`` (as indices into ``columns``), ``xticks``
    their tick labels (wrapped). ``series``: one bar series per (index of the ``solutions`` grid
    value or None, solution name), ``legend`` their names, numbered ``[#]`` where one name belongs
    to several grid values (else their bars would be drawn over each other as one series).
    """

    solutions: bool  # the bars are solutions (else the GNSS fallback metrics, one series)
    panels: list[tuple[str, str]]  # (panel, y label)
    columns: dict[str, list[Any]]
    texts: dict[str, list[str]]
    explain: dict[str, bool]
    x_cols: list[str]
    xkeys: list[tuple[int, ...]]
    xticks: list[str]
    series: list[tuple[int | None, str]]
    legend: list[str]

    def index(self, col: str, value: Any) -> int:
        """The place of ``value`` in grid column ``col``."""
        return _place(self.columns[col], value)

    def metric(self, panel: str, name: str) -> str:
        return f"{name}.vehicles_mean.{panel}.std" if self.solutions else panel


def _short_text(value: Any) -> str:
    """A grid value as report.png labels it: a solutions list that runs.parquet holds whole (as
    JSON: two lists had the same names) by its solutions' names, white space as single spaces,
    at most :data:`_LABEL_CHARS` characters."""
    text = str(value)
    if isinstance(value, str) and value[:1] == "[":
        try:
            parsed = json.loads(value)
        except ValueError:
            parsed = None
        if isinstance(parsed, list) and parsed and all(isinstance(v, dict) and "name" in v for v in parsed):
            text = str(_label(parsed))
    text = " ".join(text.split()) or '""'  # (an empty or blank string: a visible label)
    return text if len(text) <= _LABEL_CHARS else text[:_LABEL_CHARS - 1] + "…"


def _distinct(texts: list[str]) -> list[str]:
    """``texts`` with every text that several share numbered by its place, ``"text [#]"``; if a
    numbered text is then another one's own, every text numbered (distinct: the last numbers
    differ)."""
    counts: dict[str, int] = {}
    for t in texts:
        counts[t] = counts.get(t, 0) + 1
    out = [f"{t} [{i + 1}]" if counts[t] > 1 else t for i, t in enumerate(texts)]
    if len(set(out)) < len(out):
        out = [f"{t} [{i + 1}]" for i, t in enumerate(texts)]
    return out


def _value_texts(values: list[Any]) -> list[str]:
    """Distinct short labels of one grid column's (distinct) values."""
    return _distinct([_short_text(v) for v in values])


def _wrap(text: str, width: int) -> str:
    """``text`` in lines of at most ``width`` characters, broken after a comma or a space where
    it can be (compact JSON has no spaces), inside a longer piece where it cannot."""
    lines = [""]
    for piece in re.findall(r"[^,\s]*[,\s]*", text):
        if lines[-1] and len(lines[-1].rstrip()) + len(piece.rstrip()) > width:
            lines.append("")
        lines[-1] += piece
        while len(lines[-1].rstrip()) > width:
            lines[-1:] = [lines[-1][:width], lines[-1][width:]]
    return "\n".join(line.strip() for line in lines if line.strip())


def _place(values: list[Any], value: Any) -> int:
    """The index of ``value`` in ``values`` (NaN matches NaN)."""
    return next(i for i, v in enumerate(values) if v == value or (_isnan(v) and _isnan(value)))


def _figure_labels(df, agg, grid_cols: list[str], solutions: list[str]) -> _FigureLabels:
    import pandas as pd

    columns = {c: list(pd.unique(df[c])) for c in grid_cols}
    texts = {c: _value_texts(v) for c, v in columns.items()}
    explain = {c: any(t != str(v) for v, t in zip(columns[c], texts[c], strict=True)) for c in grid_cols}
    x_cols = [c for c in grid_cols if c != "solutions"]
    if solutions:
        panels = [("along", "along-track error std (m)"), ("across", "across-track error std (m)")]
    else:
        panels = [(m, m) for m in _FALLBACK_METRICS]
    records = agg.to_dict("records")
    xkeys: list[tuple[int, ...]] = []
    for r in records:
        k = tuple(_place(columns[c], r[c]) for c in x_cols)
        if k not in xkeys:
            xkeys.append(k)
    ticks = _distinct([", ".join(texts[c][i] for c, i in zip(x_cols, k, strict=True)) or "all runs" for k in xkeys])
    series: list[tuple[int | None, str]]
    if not solutions:
        series, legend = [(None, "")], [""]
    elif "solutions" not in grid_cols:
        series, legend = [(None, name) for name in solutions], list(solutions)
    else:  # per solutions value, the names it has a panel metric of
        have = {(_place(columns["solutions"], r["solutions"]), r["metric"]) for r in records}
        pairs = [(i, name) for name in solutions for i in range(len(columns["solutions"]))
                 if any((i, f"{name}.vehicles_mean.{p}.std") in have for p, _ in panels)]
        shared = {n for n in solutions if sum(1 for _, m in pairs if m == n) > 1}
        series = list(pairs)
        legend = _distinct([f"{n} [{i + 1}]" if n in shared else n for i, n in pairs])
        explain["solutions"] = explain["solutions"] or bool(shared)
    return _FigureLabels(solutions=bool(solutions), panels=panels, columns=columns, texts=texts, explain=explain,
                         x_cols=x_cols, xkeys=xkeys,
                         xticks=[_wrap(t, _TICK_CHARS) for t in ticks],
                         series=series, legend=legend)


def _report_figure(agg, lab: _FigureLabels, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    n_x = len(lab.xkeys)
    # wide enough for the wrapped tick labels side by side (~1.6 in at 8 pt), up to 26 in a panel
    panel_w = min(max(6.0, 1.0 + 1.6 * n_x), 26.0)
    fig, axes = plt.subplots(1, len(lab.panels), figsize=(panel_w * len(lab.panels), 4.6), squeeze=False)
    width = 0.8 / max(len(lab.series), 1)
    for ax, (panel, ylabel) in zip(axes[0], lab.panels, strict=True):
        for j, ((sv, name), legend) in enumerate(zip(lab.series, lab.legend, strict=True)):
            sub = agg[agg["metric"] == lab.metric(panel, name)]
            if sv is not None:
                sub = sub[[lab.index("solutions", v) == sv for v in sub["solutions"]]]
            if sub.empty:
                continue
            xs, ys, es = [], [], []
            for r in sub.to_dict("records"):
                k = tuple(lab.index(c, r[c]) for c in lab.x_cols)
                xs.append(lab.xkeys.index(k) + (j - (len(lab.series) - 1) / 2) * width)
                ys.append(r["mean"])
                es.append(r["ci95_half"])  # NaN (one seed): no error bar, rather than one of zero width
            ax.bar(xs, ys, width=width * 0.95, yerr=es, capsize=4, label=legend or None)
        if n_x <= 15:
            ax.set_xticks(np.arange(n_x), lab.xticks, fontsize=8)
        else:  # (the panel's width is capped: upright labels)
            ax.set_xticks(np.arange(n_x), lab.xticks, fontsize=8, rotation=90)
        ax.set_ylabel(ylabel)
        ax.set_xlabel(", ".join(lab.x_cols))
        ax.grid(axis="y", alpha=0.3)
        if lab.solutions:
            ax.set_title(f"{panel}: mean over vehicles\n95 % CI across seeds (none: one seed)", fontsize=10)
            if ax.get_legend_handles_labels()[0]:  # (a panel of a metric no run has: no bars)
                ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=120)
    plt.close(fig)


# --------------------------------------------------------------------------- command line


class _DefaultRunParser:
    """Mixin: ``v2v sweep STUDY.toml`` means ``v2v sweep run STUDY.toml``."""

    def parse_known_args(self, args=None, namespace=None):
        args = list(sys.argv[1:] if args is None else args)
        if args and args[0] not in ("run", "report", "-h", "--help"):
            args = ["run", *args]
        return super().parse_known_args(args, namespace)  # type: ignore[misc]


def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``sweep`` (sub-commands ``run``, the default, and ``report``) to the ``v2v`` sub-commands."""
    s = subparsers.add_parser(
        "sweep", help="Monte Carlo studies: a grid of scenario variants x seeds on a Dask cluster",
        description="v2v sweep [run] STUDY.toml [--out DIR] ... | v2v sweep report DIR [--out DIR2]",
    )
    parser_class = type(s)  # the CLI's parser class (one-line errors)
    s.__class__ = type("SweepParser", (_DefaultRunParser, parser_class), {})
    ssub = s.add_subparsers(dest="sweep_cmd", required=True, parser_class=parser_class,
                            metavar="STUDY.toml | report DIR")
    r = ssub.add_parser("run", help="run a study (the default sub-command)",
                        description="Run every run of a study that is not yet complete in --out.")
    r.add_argument("study", type=Path, help="study .toml: base scenario, [grid], seeds")
    r.add_argument("--out", type=Path, default=None, help="output folder (default: sweeps/<study file stem>)")
    r.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run on an existing Dask scheduler (its workers must see --out) instead of a local cluster")
    r.add_argument("--workers", type=int, default=None, help="local worker processes (default: one per core)")
    r.add_argument("--host", default="127.0.0.1", help="address the local cluster binds to (default 127.0.0.1)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    p = ssub.add_parser("report", help="aggregate a sweep's runs.parquet: means and 95 %% CIs, table and figure")
    p.add_argument("sweep_dir", type=Path, metavar="DIR", help="the --out folder of a sweep")
    p.add_argument("--out", type=Path, default=None, help="where to write report.md/.csv/.png (default: DIR)")
    return s


def cmd_sweep(args) -> int:
    if args.sweep_cmd == "report":
        rep = write_report(args.sweep_dir, args.out)
        print(f"report: {rep.markdown}, {rep.csv}, {rep.figure}")
        return 0
    out = args.out or Path("sweeps") / Path(args.study).stem
    study = load_study(args.study)
    for line in study.warnings:  # (also with --quiet, as `v2v run`: they say what the results rest on)
        print(f"v2v: warning: {line}", file=sys.stderr, flush=True)
    res = run_study(study, out, scheduler=args.scheduler, workers=args.workers, host=args.host, quiet=args.quiet)
    if not args.quiet:
        print(f"{res.total} runs: {res.executed} executed ({res.failed} failed), {res.skipped} already complete; "
              f"wall {res.wall_s:.1f} s; table {res.out_dir / RUNS_FILE}")
    if res.failed:
        first = res.table.loc[res.table["status"] != "ok", "error"].iloc[0] if res.table is not None else ""
        print(f"v2v: error: {res.failed} of {res.executed} runs failed (first: {first}) -- fix: see the `error` "
              f"column of {res.out_dir / RUNS_FILE}; rerunning the study retries only those", file=sys.stderr)
        return 1
    return 0
