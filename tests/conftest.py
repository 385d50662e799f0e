"""Shared fixtures: the real data in ../shared/data and the simulated rig."""

from __future__ import annotations

from pathlib import Path

import pytest

from stage.benchmarks._data import SHARED_DATA

__all__ = ["SHARED_DATA", "shared_data", "shared_dataset"]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` next to the project; skips with a reason when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (only present in the project's CI and dev machines)")
    return SHARED_DATA


def shared_dataset(name: str) -> Path:
    """Path of one dataset in ``../shared/data``; skips when absent."""
    p = SHARED_DATA / name
    if not p.is_dir():
        pytest.skip(f"real test data {name!r} not found at {p} (only present in the project's CI and dev machines)")
    return p
