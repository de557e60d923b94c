"""Shared fixtures. Real data lives in ../shared/data beside the repository; tests skip without it."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from tests.support.paths import REPO

SHARED_DATA = Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))


def data_path(*parts: str) -> Path:
    """Path inside ../shared/data; skips the calling test with a clear reason when absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not found: {p} (set ROBOTD_SHARED_DATA or place ../shared/data)")
    return p


@pytest.fixture
def shared_data():
    """Callable fixture: shared_data('kitti-seq1') -> Path, skipping when absent."""
    return data_path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
