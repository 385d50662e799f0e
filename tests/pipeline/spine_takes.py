"""The simulated multi-view takes of the spine pipeline (8 cameras, 640x480, 30 frames = one gait
cycle at 30 fps), recorded and processed by :func:`pipeline.process.process_take` once per test
process, and their spines scored against the simulator's ground truth
(:func:`fake_cameras.evaluate.evaluate_spine`).

The test files that use them (the spine pipeline, the multi-view tracking) declare
``pytestmark = pytest.mark.xdist_group(GROUP)``: under pytest-xdist they run in one worker, which
processes each take once. Rendering is cached on disk after the first run
(``fake_cameras.take.cache_dir``).
"""

from __future__ import annotations

import json

import numpy as np

from fake_cameras.evaluate import evaluate_spine
from fake_cameras.record import record_take
from fake_cameras.take import simulate_take
from pipeline.process import process_take

GROUP = "spine_takes"
N_CAMERAS = 8
N_FRAMES = 30

_RUNS: dict = {}


def run(name: str, tmp_path_factory) -> dict:
    """Simulate, record and process one take (once per test process), and score its spine ->
    ``dict(sim, res, spine, acc)``: the simulated take, ``process_take``'s result, ``spine.json``
    and :func:`evaluate_spine`'s scores."""
    if name not in _RUNS:
        sim = simulate_take(name, n_cameras=N_CAMERAS, frames=N_FRAMES, size=(640, 480), seed=3)
        root = tmp_path_factory.mktemp(f"spine_{name}")
        path = record_take(sim, root / f"{name}.h5")
        res = process_take(path, root / "results", executor=None)
        spine = json.loads((root / "results" / "spine.json").read_text())
        axes = {n: np.stack([a[n] for a in sim.axes]) for n in sim.limb_names}
        acc = evaluate_spine(spine, sim.tip_array(), axes, list(sim.limb_names), poses=sim.poses)
        _RUNS[name] = dict(sim=sim, res=res, spine=spine, acc=acc)
    return _RUNS[name]
