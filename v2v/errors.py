"""User-facing errors.

Every mistake a user can make (bad scenario field, missing file, unreadable RINEX...)
is raised as :class:`UserError`. The CLI prints it as a single line and exits with
status 2; it never shows a traceback for these.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any


class UserError(Exception):
    """A user's input is wrong. ``field`` names what is wrong, ``fix`` says what to do; ``where``
    (optional) where the value came from, added to the message as `` in <where>`` (``detail`` is
    the message without it)."""

    def __init__(self, message: str, *, field: str | None = None, fix: str | None = None, where: str | None = None):
        self.field = field
        self.fix = fix
        self.detail = message
        self.where = where
        self.message = message if where is None else f"{message} in {where}"
        super().__init__(self.one_line())

    def one_line(self) -> str:
        parts = []
        if self.field:
            parts.append(f"{self.field}: {self.message}")
        else:
            parts.append(self.message)
        if self.fix:
            parts.append(f"fix: {self.fix}")
        return " -- ".join(parts).replace("\n", " ")


EXIT_USER_ERROR = 2


def not_a_file(path: str | Path) -> str | None:
    """Why ``path`` cannot be read as a file ("not found", "is a folder", "is not a regular
    file": /dev/null, a pipe), or None if it can: for the one-line errors of file options."""
    p = Path(path)
    if p.is_file():
        return None
    if p.is_dir():
        return "is a folder"
    return "is not a regular file" if p.exists() else "not found"


def check_positive(value: float, option: str) -> None:
    """A script option that must be a positive, finite number: else the one-line
    :class:`UserError` naming it (``--keep 0``, ``--trials -5``, an alert limit of -1 m)."""
    if not (value > 0 and math.isfinite(value)):
        raise UserError(f"{value!r} is not a positive number", field=option, fix=f"give {option} > 0")


# A filter's sigma (a measurement's, a process noise's, a prior's) becomes a variance: sigma^2,
# or 2 sigma^2 for a single difference (and q = 2 sigma^2 / tau for a Gauss-Markov process), which
# a scalar update divides by (S = h P h^T + r, K = P h^T / S). For those variances to be positive
# normal float64 numbers (IEEE 754 binary64: smallest normal 2^-1022 = 2.2250738585072014e-308,
# largest 1.7976931348623157e308 = sys.float_info.min / max):
#   sigma^2 >= 2^-1022        <=>  sigma >= 2^-511 = 1.4916681462400413e-154 (exact: 2^-1022 is an
#                                  even power; one ulp less and sigma^2 is subnormal or 0);
#   2 sigma^2 <= float max    <=>  sigma <= sqrt(max / 2) = 9.480751908109176e153 (the largest
#                                  float64 whose 2 sigma^2 stays finite; sqrt(max) = 1.34e154 would
#                                  make an SD's 2 sigma^2 inf).
# Outside, a "1e-300 m" sigma is a zero-variance update (division by ~0) and "1e200 m" an inf one.
SIGMA_MIN = 2.0 ** -511
SIGMA_MAX = math.sqrt(sys.float_info.max / 2.0)


def sigma_problem(value: float, *, to_filter: float = 1.0, zero_is_off: bool = False) -> str | None:
    """Why ``value``, a filter sigma / noise strength given in its field's unit (``to_filter``
    times it is the filter's: pi / 180 for a ``*_deg`` field), cannot be used, or None: it must be
    finite and > 0 (``zero_is_off``: or exactly 0, which turns the term off) with
    :data:`SIGMA_MIN` <= sigma <= :data:`SIGMA_MAX` in the filter's unit, so that sigma^2 and
    2 sigma^2 are positive normal float64 numbers. One rule for every such field: the scenario's
    solution fields and the filter's own configuration objects use it."""
    if zero_is_off and value == 0.0:
        return None
    if not (math.isfinite(value) and value > 0.0):
        return "is not a finite number " + (">= 0" if zero_is_off else "> 0")
    x = value * to_filter
    if x < SIGMA_MIN:
        return "is too small: its square, the filter's variance, is below float64's smallest normal 2.2e-308 (zero)"
    if x > SIGMA_MAX:
        return "is too large: the filter's variance 2 sigma^2 overflows float64 to inf"
    return None


def check_sigmas(config: object, prefix: str, names: tuple[str, ...], *, zero_is_off: bool = False) -> None:
    """:func:`sigma_problem` of each of ``config``'s fields ``names`` (in the filter's units): the
    first that fails is a :class:`UserError` naming ``<prefix>.<name>`` (the filter's configuration
    objects, built from Python; a scenario's fields are checked with their own names first)."""
    for name in names:
        value = getattr(config, name)
        why = sigma_problem(value, zero_is_off=zero_is_off)
        if why:
            raise UserError(f"{value!r} {why}", field=f"{prefix}.{name}",
                            fix=f"give a value in {sigma_range()}" + (", or 0 (off)" if zero_is_off else ""))


def sigma_range(*, to_filter: float = 1.0) -> str:
    """The accepted range of :func:`sigma_problem` (besides a 0 that means off), in the field's
    unit, for a fix: ``[1.5e-154, 9.4e+153]``, both printed ends inside it."""
    lo = _two_digits(SIGMA_MIN / to_filter, up=True)
    hi = _two_digits(SIGMA_MAX / to_filter, up=False)
    return f"[{lo:.2g}, {hi:.2g}]"


def _two_digits(x: float, *, up: bool) -> float:
    """``x`` to two significant digits, rounded up or down (inward: both printed ends of a range
    are then inside it)."""
    mant, exp = f"{x:.1e}".split("e")
    m = float(mant)
    while (float(f"{m:.1f}e{exp}") < x) if up else (float(f"{m:.1f}e{exp}") > x):
        m += 0.1 if up else -0.1
    return float(f"{m:.1f}e{exp}")


def tau_problem(value: float) -> str | None:
    """Why ``value``, a Gauss-Markov correlation time in seconds, cannot be used, or None: it
    must be finite and at least float64's smallest normal number (2.2e-308 s), so that the
    process's rate 1 / tau (its transition is exp(-dt / tau)) is finite."""
    if not (math.isfinite(value) and value >= sys.float_info.min):
        return "is not a finite time > 0 s (at least 2.2e-308 s, so that the rate 1 / tau is finite)"
    return None


def interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C (or SIGTERM raised as one) that ``exc`` was raised while handling, if any.

    A signal that arrives while a numba kernel runs surfaces as its dispatcher's
    ``SystemError(... returned a result with an exception set)`` whose context is the
    :class:`KeyboardInterrupt`: the command lines treat that as the interrupt it is."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a batch system's end of job), handled as Ctrl-C is: a run
    removes its staging folder, a sweep cancels its pending runs and keeps its table consistent."""


_PENDING: list[KeyboardInterrupt] = []  # the interrupt a signal raised, until a command line handles it


def _raise_on_signal(signum: int, frame: object) -> None:
    import signal

    exc: KeyboardInterrupt = Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()
    _PENDING.append(exc)
    raise exc


def check_interrupt() -> None:
    """Raise again the interrupt a signal raised where it was swallowed: Python only prints
    ("Exception ignored on calling ctypes callback function") what a handler raises inside a
    ctypes callback, such as llvmlite's while numba compiles or caches a kernel, and goes on.
    The run loop calls this once a step, so the signal still ends the run."""
    if _PENDING:
        raise _PENDING[-1]


@contextmanager
def signals_as_interrupts() -> Iterator[None]:
    """Inside: SIGINT raises :class:`KeyboardInterrupt` and SIGTERM :class:`Terminated`, each
    also recorded for :func:`check_interrupt` (and, if swallowed, not printed as an "Exception
    ignored" traceback); outside, the handlers and hook before and no record.
    (Off the main thread, where handlers cannot be set, it changes nothing.)"""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.signal(sig, _raise_on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    old_hook = sys.unraisablehook

    def quiet_hook(unraisable: Any) -> None:  # our swallowed interrupt: check_interrupt raises it
        if not any(unraisable.exc_value is e for e in _PENDING):
            old_hook(unraisable)

    _PENDING.clear()
    sys.unraisablehook = quiet_hook
    try:
        yield
    finally:
        sys.unraisablehook = old_hook
        for sig, handler in old.items():
            signal.signal(sig, handler)
        _PENDING.clear()


@contextmanager
def interrupts_unwrapped() -> Iterator[None]:
    """Re-raise an exception that :func:`interrupt_behind` finds a Ctrl-C (or SIGTERM) behind
    as that interrupt, so the command lines' ``except KeyboardInterrupt`` sees it."""
    try:
        yield
    except Exception as exc:
        interrupt = interrupt_behind(exc)
        if interrupt is None:
            raise
        raise interrupt from None


class ScriptArgumentParser(argparse.ArgumentParser):
    """An experiment script's argument parser: a bad option (an int that is not one, a missing
    value, an unknown choice) is one line on stderr and exit status 2, as ``v2v``'s are
    (``<prog>: error: <what> -- fix: see `<prog> --help```), not argparse's usage block."""

    def error(self, message: str):  # (exits: argparse's NoReturn)
        self.exit(EXIT_USER_ERROR, f"{self.prog}: error: {message} -- fix: see `{self.prog} --help`\n")


def _option_for(field: str | None, options: Mapping[str, str]) -> str | None:
    """The option of ``options`` (scenario field path -> option) that set ``field``: the longest
    path that is ``field`` or a path above it (``clusters.0.lanes`` for ``clusters.0.lanes.1``),
    a ``*`` part matching any one part (``solutions.*.uwb_sigma_m``)."""
    if not field:
        return None
    parts = field.split(".")
    best: tuple[int, str] | None = None
    for path, option in options.items():
        want = path.split(".")
        if len(want) <= len(parts) and all(w in ("*", p) for w, p in zip(want, parts, strict=False)):
            if best is None or len(want) > best[0]:
                best = (len(want), option)
    return best[1] if best else None


@contextmanager
def script_options(options: Mapping[str, str]) -> Iterator[None]:
    """Inside, an error naming a scenario field that a script's option set names the option
    the user typed instead, the field after the message: ``--vehicles: Input should be greater
    than or equal to 2 (got 1) (clusters.0.vehicles) -- fix: use a value >= 2``. ``options`` maps
    scenario field paths to the options that set them (see :func:`_option_for`). Around the
    loading *and* the running of an experiment's scenario: the run's set-up refuses what only it
    can check (a lane the net lacks, a RINEX file that does not span the start). Errors naming
    no mapped field pass unchanged."""
    try:
        yield
    except UserError as exc:
        option = _option_for(exc.field, options)
        if option is None:
            raise
        # (without where the scenario's values came from: "the command line's --set", in a script)
        raise UserError(f"{exc.detail} ({exc.field})", field=option, fix=exc.fix) from None


def script_main(main: Callable[[], int | None], prog: str) -> int:
    """Run a script's ``main()`` as ``v2v`` runs a command (the experiments' ``__main__``): a
    :class:`UserError` is one line on stderr, ``<prog>: error: <field>: ... -- fix: ...``, and
    exit status 2; Ctrl-C is one line and 130; anything else propagates (a bug: its traceback).
    After a user's error or Ctrl-C, the folders the script made that hold no file (its ``--out``
    and ``runs/`` made before a scenario was refused) are taken away again."""
    from v2v.io.atomic import discard_empty_made_folders

    try:
        with signals_as_interrupts(), interrupts_unwrapped():
            return int(main() or 0)
    except UserError as exc:
        discard_empty_made_folders()
        print(f"{prog}: error: {exc.one_line()}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        discard_empty_made_folders()
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
