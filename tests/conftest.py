"""Shared fixtures: the real data in ../shared/data and the simulated rig."""

from __future__ import annotations

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


#: Test files that use another file's module-level cache (its processed takes) run in that file's
#: worker process under pytest-xdist (``--dist loadgroup``; every other file is a group of its own).
SAME_WORKER = {"test_tracking_multiview.py": "test_spine_pipeline.py"}


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook, which reads the groups
def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist: every test in its file's group, and the groups with the most ``slow``
    tests first (with ``--no-loadscope-reorder`` the workers take the groups in this order: the
    longest are not left to the end, when one worker would run them alone)."""
    if not config.pluginmanager.hasplugin("xdist"):
        return
    groups = {}
    for item in items:
        path = Path(item.path)
        groups[item] = str(path.with_name(SAME_WORKER.get(path.name, path.name)).relative_to(config.rootpath))
        item.add_marker(pytest.mark.xdist_group(groups[item]))
    slow = Counter(groups[item] for item in items if item.get_closest_marker("slow"))
    items.sort(key=lambda item: -slow[groups[item]])  # stable: the collection's order otherwise
