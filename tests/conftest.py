"""Shared test set-up: paths, the shared-data marker, and small fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("O3DRBF_NO_PROGRESS", "1")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_data_or_skip() -> Path:
    """The ../shared/data folder, or skip the test with the reason."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"needs the shared data folder {SHARED_DATA} (not present: a clone without ../shared)")
    return SHARED_DATA


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
