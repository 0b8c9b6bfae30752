"""Helpers for the experiments' smoke tests: load an experiment script as a module, check a PNG."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


def load_experiment(name: str) -> ModuleType:
    """Import ``experiments/<name>.py`` (not a package) as module ``_exp_<name>``."""
    spec = importlib.util.spec_from_file_location(f"_exp_{name}", EXPERIMENTS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def assert_png(path: Path, min_bytes: int = 10_000) -> None:
    """A real, non-trivial PNG file (signature and size)."""
    assert path.is_file() and path.stat().st_size > min_bytes, f"{path.name} missing or empty"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
