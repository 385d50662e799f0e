"""Shared fixtures: the real data in ../shared/data and the simulated rig."""

from __future__ import annotations

import os
from collections import Counter
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


def pytest_configure(config):
    """A pytest-xdist worker shares the cores with the other workers: its BLAS and OpenCV run in one
    thread, as do the worker processes its tests start (the variables), instead of as many threads
    as cores in every process, which only wait on each other."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    import cv2
    from threadpoolctl import threadpool_limits

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    threadpool_limits(1)
    cv2.setNumThreads(1)


#: Test files that take minutes, the longest first: under pytest-xdist they start before any other,
#: so that no worker is left running one alone at the end (measured on 2 cores: the quadruped's
#: accurate tracking, about 4 minutes, is the longest test of the suite).
FIRST = ("test_tracking_multiview.py",)


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook, which reads the groups
def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist: every test file one group, run in one worker (its module-level caches are
    built once), the files of :data:`FIRST` first, then those with the most ``slow`` tests (with
    ``--no-loadscope-reorder`` the workers take the groups in this order)."""
    if not config.pluginmanager.hasplugin("xdist"):
        return
    groups = {item: str(Path(item.path).relative_to(config.rootpath)) for item in items}
    for item in items:
        item.add_marker(pytest.mark.xdist_group(groups[item]))
    slow = Counter(groups[item] for item in items if item.get_closest_marker("slow"))
    rank = {name: i for i, name in enumerate(FIRST)}
    # stable: the collection's order otherwise
    items.sort(key=lambda item: (rank.get(Path(item.path).name, len(FIRST)), -slow[groups[item]]))
