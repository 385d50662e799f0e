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
    _import_anyio_now()
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    import cv2
    from threadpoolctl import threadpool_limits

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    threadpool_limits(1)
    cv2.setNumThreads(1)


def _import_anyio_now() -> None:
    """anyio (under FastAPI's test client and the API's file responses) imports most of its modules on first
    use, parsing their source into an AST as it does (its lazy importer, and pytest's assertion rewriting, which
    covers anyio as a pytest plugin). In Python 3.11 two threads parsing at once can fail with "SystemError: AST
    constructor recursion depth mismatch": the test client's event-loop thread importing ``anyio.open_file``'s
    module while a job's thread parses too. Every such import is done here, in the main thread, before any test
    starts a thread."""
    import importlib

    import anyio

    for name in dir(anyio):
        getattr(anyio, name)
    for module in ("anyio.from_thread", "anyio._backends._asyncio", "anyio.streams.buffered", "anyio.streams.text",
                   "anyio.streams.file"):
        importlib.import_module(module)


#: Test files whose groups take the longest, the longest first (CPU seconds of the group measured
#: with ``pytest -n 1 FILE`` on a 2-core machine; the browser tests by their wall time): under
#: pytest-xdist they start before any other, so that no worker is left running one alone at the end.
#: A file missing from the list is only scheduled later, after these.
FIRST = (
    "test_armature.py",  # about 60 s
    "test_rig_sim.py",  # about 52 s
    "test_spine_pipeline.py",  # the spine_takes group: two 30-frame takes processed (34 s), one tracked
    "test_process.py",  # about 45 s
    "test_control_browser.py",  # about 40 s of wall time
    "test_track_real_pipe.py",  # about 37 s
    "test_importer.py",  # about 28 s
    "test_store_diskfull.py",  # about 26 s
    "test_tracking_carved.py",  # about 24 s
    "test_caliscope.py",  # about 23 s
    "test_cli.py",  # tests/calib: about 23 s
    "test_handheld.py",  # about 22 s
    "test_spine.py",  # about 22 s
    "test_armature_track.py",  # about 21 s
    "test_browser_served.py",  # about 21 s of wall time
    "test_horse_take.py",  # about 20 s
    "test_photo_refine.py",  # about 17 s
)


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook, which reads the groups
def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist: every test file one group, run in one worker (its module-level caches are
    built once), unless the file names its own group (``pytestmark = pytest.mark.xdist_group(NAME)``:
    files that share a fixture module's cache, e.g. :mod:`tests.pipeline.spine_takes`); the groups of
    :data:`FIRST` first, then those with the most ``slow`` tests (with ``--no-loadscope-reorder`` the
    workers take the groups in this order)."""
    if not config.pluginmanager.hasplugin("xdist"):
        return
    groups = {}
    for item in items:
        own = item.get_closest_marker("xdist_group")
        groups[item] = own.args[0] if own and own.args else own.kwargs.get("name") if own else None
        if groups[item] is None:
            groups[item] = str(Path(item.path).relative_to(config.rootpath))
            item.add_marker(pytest.mark.xdist_group(groups[item]))
    slow = Counter(groups[item] for item in items if item.get_closest_marker("slow"))
    rank: dict = {}  # a group's place in FIRST, and where it first appears in the collection
    for i, item in enumerate(items):
        name = Path(item.path).name
        rank.setdefault(groups[item], [len(FIRST), i])
        if name in FIRST:
            rank[groups[item]][0] = min(rank[groups[item]][0], FIRST.index(name))
    items.sort(key=lambda item: (rank[groups[item]][0], -slow[groups[item]], rank[groups[item]][1]))
