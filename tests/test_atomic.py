"""Atomic writes give their files and run folders the modes a plain ``open`` / ``mkdir`` would
(0o666 / 0o777 less the umask): ``mkstemp`` / ``mkdtemp`` make theirs private (0600 / 0700),
which would leave a run's tables unreadable to the rest of a team sharing a machine."""

from __future__ import annotations

import os
import stat

import pytest

from v2v.io.atomic import RunFolder, atomic_write_json, atomic_write_parquet, umask


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
