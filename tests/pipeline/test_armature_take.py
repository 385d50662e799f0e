"""An armature from a simulated multi-view take through ``process``, ``track`` and ``armature``
(Tzionas & Gall 2016 section 4 on the path a lab takes): the starfish curling its arms, filmed by 6
cameras at 480x360 for 8 frames (one second of its motion), against the simulator's joints.

Its figures (recall and precision over the joints that bend by 10 degrees or more) are in
docs/armature-format.md, "Where it goes wrong", with the calls that print them. The larger takes of
``stage bench armature --accuracy`` are the figures; this is the cheap one that can fail (at 320x240
the arms are a few voxels thick and it finds 3-4 segments).
"""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_starfish_take_through_process_track_and_armature(tmp_path):
    from fake_cameras.mesh_motion import true_joints
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.armature_files import armature_results
    from pipeline.armature_score import articulation_scores
    from pipeline.process import process_take

    sim = simulate_take("starfish", n_cameras=6, frames=8, size=(480, 360), seed=3, fps=8.0)
    res = tmp_path / "results"
    process_take(record_take(sim, tmp_path / "starfish.h5"), res, executor=None)
    process_take(tmp_path / "starfish.h5", res, steps=("track",), executor=None)
    rig = armature_results(res)
    _, J, bending = true_joints(sim.creature, sim.times)
    s = articulation_scores(rig.fit.joints[:, rig.skeleton.articulation], J, size=rig.size, bending=bending)
    assert s["bending"] >= 15  # the arms curl: most of the 20 joints bend by 10 degrees or more
    assert s["recall"] >= 0.7, s
    assert s["precision"] >= 0.6, s
    assert (res / "rig" / "rig.json").is_file()
    spine = json.loads((res / "rig" / "rig.json").read_text())["spine"]  # the take's spine: its limbs were used
    assert len(spine["segment_limbs"]) == rig.segmentation.n_segments and len(spine["limbs"]) >= 5
