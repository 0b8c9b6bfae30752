"""Atomic writes give their files and run folders the modes a plain ``open`` / ``mkdir`` would
(0o666 / 0o777 less the umask): ``mkstemp`` / ``mkdtemp`` make theirs private (0600 / 0700),
which would leave a run's tables unreadable to the rest of a team sharing a machine."""

from __future__ import annotations

import os
import stat

import pytest

from v2v.io.atomic import (
    RunFolder,
    atomic_write_json,
    atomic_write_parquet,
    discard_empty_made_folders,
    make_folder,
    umask,
)


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    try:
        yield
    finally:
        os.umask(old)


def _mode(p) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def test_umask_is_read_without_changing_it(umask_027):
    assert umask() == 0o027
    assert umask() == 0o027  # (still in force)


def test_files_and_run_folders_get_the_umask_modes(tmp_path, umask_027):
    import pandas as pd

    with RunFolder(tmp_path / "run") as staging:
        atomic_write_json(staging / "summary.json", {"a": 1})
        atomic_write_parquet(staging / "epochs.parquet", pd.DataFrame({"t_s": [0.1]}))
        with open(staging / "plain.txt", "w") as f:  # what a plain open gives, for comparison
            f.write("x")
    run = tmp_path / "run"
    assert _mode(run) == 0o750
    assert _mode(run / "summary.json") == _mode(run / "epochs.parquet") == _mode(run / "plain.txt") == 0o640


def test_parquet_tables_round_trip_bit_for_bit_with_float_columns_plain(tmp_path):
    """Both writers (:func:`atomic_write_parquet`, :class:`ParquetStream`) read back every value
    bit for bit (NaN, -0.0, subnormals, infinities, missing strings); the float columns are not
    dictionary-encoded and the others but booleans are (``write_options``: the dictionaries pyarrow would
    build for floats are dropped or compress worse)."""
    import numpy as np
    import pandas as pd
    import pyarrow.parquet as pq

    from v2v.io.tables import ParquetStream

    rng = np.random.default_rng(1)
    x = rng.normal(size=3000)
    x[:6] = [np.nan, -0.0, 0.0, 5e-324, np.inf, -np.inf]
    columns = {"t_s": (np.arange(3000) * 0.1).tolist(), "err_m": x.tolist(), "vehicle": [f"c1.{k % 4}" for k in range(3000)],
               "sats": [k % 9 for k in range(3000)], "los": [k % 3 == 0 for k in range(3000)],
               "edge": [None if k % 7 == 0 else "e1" for k in range(3000)]}
    frame = pd.DataFrame(columns)
    atomic_write_parquet(tmp_path / "a.parquet", frame)
    stream = ParquetStream(tmp_path / "b.parquet", batch_rows=1000)
    stream.extend(columns)
    stream.close()
    for name in ("a.parquet", "b.parquet"):
        back = pd.read_parquet(tmp_path / name)
        assert list(back.columns) == list(frame.columns)
        for c in ("t_s", "err_m"):
            assert np.array_equal(back[c].to_numpy().view(np.uint64), frame[c].to_numpy().view(np.uint64))
        for c in ("vehicle", "sats", "los"):
            assert back[c].tolist() == columns[c]
        assert back["edge"].isna().tolist() == [v is None for v in columns["edge"]]
        assert (back["edge"][back["edge"].notna()] == "e1").all()
        meta = pq.ParquetFile(tmp_path / name).metadata
        for g in range(meta.num_row_groups):
            for i in range(meta.num_columns):
                col = meta.row_group(g).column(i)
                dictionary = any("DICTIONARY" in e for e in col.encodings)
                if col.physical_type != "BOOLEAN":  # (Parquet bit-packs booleans: never a dictionary)
                    assert dictionary == (col.path_in_schema not in ("t_s", "err_m")), (name, col.path_in_schema)


def test_a_failed_script_takes_away_only_the_folders_it_made_that_hold_no_file(tmp_path):
    """make_folder remembers the topmost folder it created; discard_empty_made_folders removes
    it while it holds only folders, keeps it once a file is in it, and never touches a folder
    that was there before (the user's)."""
    mine = tmp_path / "mine"
    mine.mkdir()
    make_folder(mine / "out")             # new: made here
    (mine / "out" / "runs" / "a").mkdir(parents=True)
    make_folder(tmp_path / "new" / "deep")  # new, two levels
    make_folder(mine)                     # there before: nothing to remember
    kept = tmp_path / "kept"
    make_folder(kept / "runs")
    (kept / "runs" / "result.csv").write_text("x")
    discard_empty_made_folders()
    assert mine.is_dir() and not (mine / "out").exists() and not (tmp_path / "new").exists()
    assert (kept / "runs" / "result.csv").is_file()
    discard_empty_made_folders()  # nothing left to do
    assert mine.is_dir()


def test_a_failed_run_removes_the_parent_folders_it_made_but_not_the_users(tmp_path):
    """RunFolder makes the parents of its target; a run that fails takes the new ones away again
    (while they hold no file) and leaves a parent that was there before."""
    with pytest.raises(RuntimeError):
        with RunFolder(tmp_path / "a" / "b" / "run"):
            raise RuntimeError("the run failed")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "notes.txt").write_text("mine")
    with pytest.raises(RuntimeError):
        with RunFolder(tmp_path / "a" / "b" / "run"):
            raise RuntimeError("the run failed")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["notes.txt"]


def test_an_interrupt_while_a_run_replaces_the_previous_one_leaves_a_whole_folder(tmp_path, monkeypatch):
    """README (The command line): a run replaces a previous run's folder at --out, and a Ctrl-C
    or SIGTERM that lands after the new folder is complete keeps it. One that lands between
    moving the previous folder aside and moving the new one in waits for the second move: the
    folder at --out is whole (the new run's) and the interrupt is raised after it, never a
    missing folder with the two runs in hidden ones."""
    import signal

    import v2v.io.atomic as atomic
    from v2v.errors import signals_as_interrupts

    final = tmp_path / "run"
    final.mkdir()
    (final / "summary.json").write_text('"previous"')
    real_replace, calls = os.replace, []

    def replace_then_interrupt(src, dst):
        real_replace(src, dst)
        calls.append(dst)
        if len(calls) == 1:  # the previous folder is aside: Ctrl-C now
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(atomic.os, "replace", replace_then_interrupt)
    # another thread that does not block signals (a run has OpenBLAS's and rerun's): the kernel may
    # hand it the process-directed SIGINT, so blocking the signal in the main thread does not hold it
    import threading

    done = threading.Event()
    other = threading.Thread(target=done.wait)
    other.start()
    try:
        with signals_as_interrupts(), pytest.raises(KeyboardInterrupt):
            with RunFolder(final) as tmp:
                (tmp / "summary.json").write_text('"new"')
    finally:
        done.set()
        other.join()
    assert len(calls) == 2 and (final / "summary.json").read_text() == '"new"'
    assert final.resolve() in atomic.PUBLISHED  # what the command line reports as a complete run


def test_a_set_of_files_is_replaced_whole_or_not_at_all(tmp_path):
    """atomic_write_all: a writer that fails (here the second of three) leaves the earlier
    versions of all three files, and no temporary file; when all succeed all are new."""
    from v2v.io.atomic import atomic_write_all

    paths = [tmp_path / n for n in ("a.csv", "b.md", "c.png")]
    for p in paths:
        p.write_text("old")

    def fail(p):
        p.write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        atomic_write_all([(paths[0], lambda p: p.write_text("new")), (paths[1], fail),
                          (paths[2], lambda p: p.write_text("new"))])
    assert [p.read_text() for p in paths] == ["old"] * 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.md", "c.png"]
    atomic_write_all([(p, lambda q: q.write_text("new")) for p in paths])
    assert [p.read_text() for p in paths] == ["new"] * 3
