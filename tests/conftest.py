"""Shared fixtures: paths to ../shared/data (tests using it skip when absent)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# the paper-reproduction experiments live in benchmarks/ (research code, not the library)
sys.path.insert(0, str(REPO / "benchmarks"))
# gait2392's muscles add ~25 s to each pipeline run: off unless a test asks for them (muscles="gait2392")
os.environ.setdefault("PERSONALIZE_MUSCLES", "none")
SHARED_DATA = Path(os.environ.get("PERSONALIZE_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder of the real data set; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def opensim():
    """The opensim module; skips the test when it cannot be imported."""
    return pytest.importorskip("opensim")
