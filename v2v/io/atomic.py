"""Atomic file and folder writes: write to a temporary name in the same directory, then rename.

A reader (or a crashed run) never sees a half-written file that looks whole.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


def umask() -> int:
    """The process's file-mode creation mask, read without changing it where Linux tells it
    (``/proc/self/status``); elsewhere set and restored at once."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def publish(tmp_path: Path, path: Path) -> None:
    """Rename the finished temporary file ``tmp_path`` to ``path``, with the mode a plain
    ``open`` would have given it (``0o666`` less the umask: ``mkstemp`` makes its files private)."""
    os.chmod(tmp_path, 0o666 & ~umask())
    os.replace(tmp_path, path)


def atomic_write(path: Path, writer: Callable[[Path], None]) -> None:
    """Call ``writer(tmp_path)`` on a temporary file beside ``path`` and :func:`publish` it as
    ``path``; on any error the temporary file is removed and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_all([(path, writer)])


def atomic_write_all(writes: list[tuple[Path, Callable[[Path], object]]]) -> None:
    """:func:`atomic_write` of several files as one set: every ``writer(tmp_path)`` runs on
    a temporary file beside its path first, and only when all have succeeded are they
    renamed into place, so a failed writer (or a path that is a folder) leaves every path
    as it was, not some files new beside old ones. (Each rename is atomic; the set's renames
    follow each other.)"""
    for path, _ in writes:  # (a rename cannot replace a folder: found before any file is replaced)
        if Path(path).is_dir():
            raise IsADirectoryError(errno.EISDIR, "Is a directory", str(path))
    done: list[tuple[Path, Path]] = []
    try:
        for path, writer in writes:
            path = Path(path)
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
            os.close(fd)
            done.append((Path(tmp), path))
            writer(Path(tmp))
        while done:
            tmp_path, path = done[0]
            publish(tmp_path, path)
            done.pop(0)
    except BaseException:
        for tmp_path, _ in done:
            tmp_path.unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    def write(p: Path) -> None:
        p.write_text(text, encoding="utf-8")

    atomic_write(path, write)


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n")


def atomic_write_parquet(path: Path, table: Any) -> None:
    """Write a pandas DataFrame or pyarrow Table with pyarrow (zstd, :func:`v2v.io.tables.write_options`),
    atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from v2v.io.tables import write_options

    if not isinstance(table, pa.Table):
        table = pa.Table.from_pandas(table, preserve_index=False)
    options = write_options(table.schema)
    atomic_write(path, lambda p: pq.write_table(table, p, **options))


# the topmost folder each :func:`make_folder` call of this process created (for
# :func:`discard_empty_made_folders`)
_MADE_FOLDERS: list[Path] = []


def make_folder(out: Path, *, what: str = "--out") -> None:
    """``out`` and its parents (a folder that is there is fine), or a one-line
    :class:`~v2v.errors.UserError` naming ``what`` (the option that gave the path). The
    topmost folder it creates is remembered, so that a script stopped by a user's mistake
    can take it away again while it holds no file (:func:`discard_empty_made_folders`)."""
    from v2v.errors import UserError

    out = Path(out)
    first_new = first_missing(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the folder {out} ({exc.strerror or exc})", field=what,
                        fix="give a folder (not a file) that can be written") from None
    if first_new is not None:
        _MADE_FOLDERS.append(first_new)


def discard_empty_made_folders() -> None:
    """Remove each folder :func:`make_folder` created in this process that holds no file
    (only empty folders, such as an experiment's ``runs/`` made before a scenario was
    refused), so a failed script leaves nothing that looks like a result; a folder with
    any file (or link) in it is kept as it is."""
    while _MADE_FOLDERS:
        _remove_if_no_files(_MADE_FOLDERS.pop())


def first_missing(path: Path) -> Path | None:
    """The topmost of ``path`` and its parents that does not exist (what ``mkdir(parents=True)``
    of ``path`` would create first), or None if ``path`` exists."""
    return next((p for p in reversed([path, *path.parents]) if not p.exists() and not p.is_symlink()), None)


def _remove_if_no_files(top: Path) -> None:
    """Remove the folder ``top`` if it holds nothing but folders (no file, no link); else keep it."""
    if not top.is_dir() or top.is_symlink():
        return
    try:
        if all(not files and all(not (Path(root) / d).is_symlink() for d in dirs) for root, dirs, files in os.walk(top)):
            shutil.rmtree(top)
    except OSError:
        pass


RUN_FOLDER_MARKERS = ("summary.json", "scenario.resolved.toml")
# everything a run writes into its folder (README, Outputs)
RUN_FILES = frozenset({*RUN_FOLDER_MARKERS, "truth.parquet", "epochs.parquet", "measurements.parquet", "replay.rrd"})


def check_run_target(final: Path, *, what: str = "--out") -> None:
    """A run may go to ``final`` only if it does not exist, is an empty folder, or is a
    previous run's folder (it holds ``summary.json`` or ``scenario.resolved.toml`` and nothing
    but the files a run writes, :data:`RUN_FILES`), which the new run replaces; anything else
    (a file, a folder of other things, a run folder with files added to it) is the user's and
    is refused before any work is done."""
    from v2v.errors import UserError

    final = Path(final)
    here, target = Path.cwd().resolve(), final.resolve()
    if target == here or target in here.parents:
        raise UserError(f"{final} is the current folder{'' if target == here else ' or holds it'} (a run replaces "
                        f"its folder)", field=what, fix="give a subfolder, e.g. --out runs/NAME")
    if not final.exists() and not final.is_symlink():
        return
    if not final.is_dir():
        raise UserError(f"{final} exists and is not a folder", field=what, fix="give a new folder or a previous run's folder")
    try:
        entries = sorted(e.name for e in final.iterdir())
    except OSError as exc:
        raise UserError(f"cannot read {final} ({exc.strerror or exc})", field=what, fix="give a readable folder") from None
    if not entries:
        return
    if not any((final / m).is_file() for m in RUN_FOLDER_MARKERS):
        raise UserError(f"{final} exists and is not a v2v run folder (it would be replaced)", field=what,
                        fix="give a new folder, an empty one, or a previous run's folder")
    foreign = [e for e in entries if e not in RUN_FILES or not (final / e).is_file()]
    if foreign:
        listed = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise UserError(f"{final} is a run folder that also holds {listed}, which replacing it would delete",
                        field=what, fix="give a new folder, or move those out of it first")


# the run folders this process has completed (so that an interrupt that comes after a run's
# folder is whole is not reported as a run lost)
PUBLISHED: list[Path] = []


class RunFolder:
    """A run's output folder, built under a hidden temporary name and renamed when complete.

    ``with RunFolder(out) as tmp:`` gives a staging directory; on success it becomes ``out``
    (an existing run folder ``out`` is replaced; anything else there is refused up front,
    :func:`check_run_target`); on any error the staging directory is removed, so no folder
    that looks complete is left behind. A folder that cannot be created is a
    :class:`~v2v.errors.UserError` naming ``what`` (the option that gave the path).
    """

    def __init__(self, final: Path, *, what: str = "--out"):
        self.final = Path(final).resolve()
        self.what = what
        self.staging: Path | None = None
        self.made_parent: Path | None = None  # the topmost parent folder __enter__ created

    def __enter__(self) -> Path:
        from v2v.errors import UserError

        check_run_target(self.final, what=self.what)
        self.made_parent = first_missing(self.final.parent)
        try:
            self.final.parent.mkdir(parents=True, exist_ok=True)
            self.staging = Path(tempfile.mkdtemp(prefix=f".{self.final.name}.", suffix=".partial", dir=self.final.parent))
        except OSError as exc:
            raise UserError(f"cannot create {self.final} ({exc.strerror or exc})", field=self.what,
                            fix="give a writable folder whose parents are folders") from None
        return self.staging

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self.staging is not None
        if exc_type is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            if self.made_parent is not None:  # the parents made for this run go too while they hold no file
                _remove_if_no_files(self.made_parent)
            return
        os.chmod(self.staging, 0o777 & ~umask())  # the mode mkdir would give (mkdtemp's is private)
        if self.final.exists():
            old = self.final.with_name(f".{self.final.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            with _signals_held():  # (an interrupt between the renames would leave no folder at final)
                os.replace(self.final, old)
                os.replace(self.staging, self.final)
                PUBLISHED.append(self.final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(self.staging, self.final)
            PUBLISHED.append(self.final)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held inside: a handler that only records them stands in for the
    process's own, which gets each recorded signal again (``signal.raise_signal``) once the
    block is done and the handlers are back. (Blocking them with ``pthread_sigmask`` is not
    enough: it blocks the main thread only, and the kernel then hands a process-directed signal
    to another thread, such as OpenBLAS's, whose delivery Python acts on in the main thread at
    once.) Off the main thread, where handlers cannot be set, it holds nothing."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    old = {sig: signal.signal(sig, lambda signum, _frame: held.append(signum)) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        for signum in dict.fromkeys(held):  # (each once, in order of arrival)
            signal.raise_signal(signum)
