"""Single RGB-D tracking on real tracked motion: the pipe Tzionas & Gall (2016, section 5) rig.

``../shared/data/tzionas_pipe/pipe.npz`` (60 of the sequence's 400 frames, 6359 vertices, mm in
the original RGB-D sensor's camera frame) is rendered by the OAK-like camera at that sensor's
pose (:func:`fake_cameras.rgbd.simulate_sensor_rgbd_take`), tracked by ``stage track TAKE.h5
--template TAKE.template.ply --out DIR`` and rigged by ``stage armature``'s
:func:`pipeline.armature_files.armature_results`; every vertex is its own ground truth.

The subsample's frames are 6.7 original frames apart: the true motion is up to 19.6 mm a frame
on average over the vertices (28 mm at most; frames 15..27 and 41..46) against the 12 mm gate,
about 3 mm a frame at the original sensor's 30 fps. The test takes the first 30 of the 60
frames (:data:`FRAMES`): the fast stretch of frames 15..27 and the sharpest bend (frame 29,
120 degrees), at half the cost; the whole 60 frames are ``stage bench track --accuracy``'s
(figures in docs/tracking.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import SHARED_DATA

PIPE = SHARED_DATA / "tzionas_pipe" / "pipe.npz"
FRAMES = 30  # the first 30 of the file's 60: the fast frames 15..27 and the sharpest bend, frame 29


@pytest.fixture(scope="module")
def real_pipe(tmp_path_factory):
    """The take recorded and tracked once: (the simulated take with its ground truth, the output directory)."""
    if not PIPE.is_file():
        pytest.skip(f"real data not found: {PIPE} (../shared/data is absent)")
    from fake_cameras.rgbd import record_rgbd_take, simulate_sensor_rgbd_take, template_path
    from stage.cli import main

    d = np.load(PIPE)
    J = d["joints"].astype(np.float64)
    length = float(np.linalg.norm(np.diff(J[0], axis=0), axis=1).sum())  # the two bones: 349 mm
    tk = simulate_sensor_rgbd_take(d["vertices"][:FRAMES], d["faces"], joint_positions=J[:FRAMES, 1:2],
                                   vertex_segment=d["bone_of_vertex"], length=length, name="tzionas_pipe")
    root = tmp_path_factory.mktemp("real_pipe")
    take = record_rgbd_take(tk, root / "pipe.h5")
    out = root / "out"
    assert main(["-q", "track", str(take), "--template", str(template_path(take)), "--out", str(out)]) == 0
    return tk, out


def _tracked(out, frames):
    from pipeline.meshio import load_mesh

    return np.stack([load_mesh(out / "tracked" / f"{k:06d}.ply", largest=False)[0] for k in range(frames)])


@pytest.mark.slow
def test_real_pipe_is_in_view_at_the_sensors_distance(real_pipe):
    tk, _ = real_pipe
    cam = tk.calibration[0]
    uv, z = cam.project(tk.truth.reshape(-1, 3), return_depth=True)
    # measured: u 204..503 of 640, v 144..322 of 400, 496..623 mm from the camera
    assert cam.in_image(uv, margin=20).all()
    assert 300 <= z.min() and z.max() <= 1500  # within an OAK-D's depth range
    on_object = (tk.depth > 0) & (tk.depth < 1000)
    assert on_object.sum(axis=(1, 2)).min() > 5000  # measured: 9400..11200 depth pixels a frame on the pipe


@pytest.mark.slow
def test_real_pipe_tracked_to_one_percent_without_thinning(real_pipe):
    from pipeline.mesh_primitives import mesh_volume

    tk, out = real_pipe
    V = _tracked(out, tk.n_frames)
    F = tk.template_faces
    err = np.linalg.norm(V - tk.truth, axis=2).mean(axis=1)
    # within 1 % of the length on average (the figures: docs/tracking.md, the RGB-D rows)
    assert err.mean() <= 0.01 * tk.size, err.mean() / tk.size
    v0 = mesh_volume(tk.template_vertices, F)
    vol = np.array([mesh_volume(v, F) for v in V]) / v0
    true_vol = np.array([mesh_volume(v, F) for v in tk.truth]) / v0
    # The given surface itself is not volume-preserving: posed by linear blend skinning, it
    # collapses at the bend, so its own volume falls to 0.949 of the template's at the sharpest
    # bend (frame 29, 120 degrees; its self-overlap is only about 0.6 % of it, docs/tracking.md).
    # No thinning is then measured against the true surface of the same frame, within 5 %.
    assert true_vol.min() < 0.96  # what makes the template the wrong reference here
    assert np.abs(vol / true_vol - 1).max() <= 0.05


@pytest.mark.slow
def test_real_pipe_rigged_with_one_articulation_at_the_true_joint(real_pipe):
    from pipeline.armature_files import armature_results

    tk, out = real_pipe
    rig = armature_results(out)
    sk = rig.skeleton
    assert int(sk.articulation.sum()) == 1
    true_joint = tk.joint_positions[:, 0]  # pipe.npz's joint 1, half way along the pipe
    # the rest pose is the rig's reference frame (choose_reference), not necessarily frame 0
    ref = int(rig.frame_indices[rig.reference])
    # within 5 % of the size (17.5 mm) of the true joint at the reference frame
    assert np.linalg.norm(sk.rest[sk.articulation][0] - true_joint[ref]) <= 0.05 * tk.size
    found = rig.fit.joints[:, sk.articulation][:, 0]
    # the tolerance, 5 % of the size over the frames (the figure: docs/tracking.md, "Accuracy")
    assert np.median(np.linalg.norm(found - true_joint, axis=1)) <= 0.05 * tk.size
