"""Shared test fixtures: paths to ../shared data (skipped with a reason where absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def redwood75_dir() -> Path:
    path = SHARED / "redwood75"
    if not (path / "annotations.json").exists():
        pytest.skip(f"REDWOOD75 ground truth not found at {path} (../shared is absent)")
    return path


@pytest.fixture(scope="session")
def nocs_dir() -> Path:
    path = SHARED / "nocs_real_sample"
    if not path.exists():
        pytest.skip(f"NOCS sample not found at {path} (../shared is absent)")
    return path
