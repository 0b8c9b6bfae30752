"""Shared test fixtures.

``shared_data`` points at ``../shared/data`` beside the checkout. A user's clone has
no ``../shared``: tests that need it skip cleanly.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import v2v  # noqa: F401  (sets single-threaded BLAS before numpy loads)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_gnss_day() -> Path:
    d = SHARED_DATA / "gnss_2021-04-28"
    if not all((d / f).is_file() for f in ("brdc1180.21n", "COD0MGXFIN_20211180000_01D_05M_ORB.SP3")):
        pytest.skip("../shared/data/gnss_2021-04-28 not present (only in the project's workspace)")
    return d
