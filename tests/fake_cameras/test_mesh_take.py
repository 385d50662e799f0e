"""Multi-view takes of mesh sequences (fake_cameras.mesh_take), on a small moving ellipsoid."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fake_cameras.mesh_take import closest_on_triangles, simulate_mesh_take, snap_to_mesh, stand_in_volume
from fake_cameras.record import record_take
from fake_cameras.take import load_ground_truth
from stage.rig import Volume


def _blob(frames: int = 3):
    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    V0 = m.vertices * [2.0, 1.0, 0.7]  # y up: 0.7 tall, 2 long
    V = np.stack([V0 + [0.1 * k, 0.0, 0.0] for k in range(frames)])
    return V, np.asarray(m.faces)


def test_stand_in_volume_turns_y_up_and_fills_the_volume():
    V, _ = _blob()
    vol = Volume()
    W, scale = stand_in_volume(V, volume=vol, up_axis=1, fill=0.8)
    lo, hi = W.reshape(-1, 3).min(0), W.reshape(-1, 3).max(0)
    assert scale == pytest.approx(0.8 * 750 / 4.2)  # the sequence's longest side: 2 * 2 + 0.2 along x
    assert lo[2] == pytest.approx(0.0) and np.ptp(W[..., 2]) == pytest.approx(2.0 * scale)  # y became z
    assert (hi - lo)[1] == pytest.approx(4.2 * scale) and (lo + hi)[:2] / 2 == pytest.approx([0.0, 0.0])  # x -> y
    # a proper rotation: the input's (x, y, z) -> (z, x, y), no mirror
    assert np.allclose((W[0] - W[0].mean(0)) / scale, (V[0] - V[0].mean(0))[:, [2, 0, 1]])


def test_mesh_take_renders_every_frame_and_records_its_ground_truth(tmp_path):
    V, F = _blob()
    W, _ = stand_in_volume(V, fill=0.6)
    tk = simulate_mesh_take(W, F, name="blob", n_cameras=4, size=(96, 72), seed=1, cache=False,
                            tip_vertices={"nose": int(W[0, :, 0].argmax())})
    assert tk.images.shape == (3, 4, 72, 96, 3) and tk.masks.shape == (3, 4, 72, 96)
    assert tk.masks.any(axis=(2, 3)).all()  # every camera sees the blob on every frame
    assert set(np.unique(tk.labels)) == {-2, -1} and np.array_equal(tk.labels == -1, tk.masks)
    assert tk.tip_array().shape == (3, 1, 3) and np.allclose(tk.tip_array()[:, 0], W[:, W[0, :, 0].argmax()])
    # the mask is the mesh: its centre pixel ray hits it (the projected centroid is inside the silhouette)
    cam = tk.calibration[0]
    u, v = np.round(cam.project(W[0].mean(0)[None])[0]).astype(int)
    assert tk.masks[0, 0, v, u]
    path = record_take(tk, tmp_path / "blob.h5")
    gt = load_ground_truth(path)
    assert np.array_equal(gt["mesh_vertices"], W) and np.array_equal(gt["mesh_faces"], F)
    assert gt["limb_names"] == ["nose"] and gt["axes"] == {}
    assert np.array_equal(gt["masks"], tk.masks)


def test_snap_to_mesh_against_dense_sampling():
    rng = np.random.default_rng(0)
    V, F = _blob(1)
    V = V[0] + rng.normal(0, 0.03, V[0].shape)
    P = rng.normal(0, 1.5, (200, 3))
    tri, bary, d = snap_to_mesh(V, F, P)
    assert np.allclose(np.linalg.norm(np.einsum("nj,njc->nc", bary, V[F[tri]]) - P, axis=1), d)
    assert (bary >= -1e-12).all() and np.allclose(bary.sum(1), 1)
    # slow reference: every triangle sampled on a 40-step barycentric grid (an upper bound, 1/40 of an edge fine)
    u, w = np.meshgrid(np.linspace(0, 1, 41), np.linspace(0, 1, 41))
    keep = u + w <= 1
    u, w = u[keep], w[keep]
    best = np.full(len(P), np.inf)
    for f in F:
        a, b, c = V[f]
        S = a + np.outer(u, b - a) + np.outer(w, c - a)
        best = np.minimum(best, np.linalg.norm(P[:, None] - S[None], axis=2).min(1))
    edge = np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).max()
    assert (d <= best + 1e-12).all() and (best - d).max() <= edge / 40
    # points on the surface snap to themselves
    t0 = rng.integers(0, len(F), 50)
    b0 = rng.dirichlet([1, 1, 1], 50)
    on = np.einsum("nj,njc->nc", b0, V[F[t0]])
    assert snap_to_mesh(V, F, on)[2].max() < 1e-9


def test_closest_on_triangles_regions():
    a, b, c = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    for p, want in [([0.2, 0.2, 5.0], [0.6, 0.2, 0.2]), ([-1.0, -1, 0], [1, 0, 0]), ([2.0, -0.5, 0], [0, 1, 0]),
                    ([0.5, -1.0, 0], [0.5, 0.5, 0]), ([1.0, 1.0, 0], [0, 0.5, 0.5]), ([-1.0, 0.5, 0], [0.5, 0, 0.5])]:
        assert np.allclose(closest_on_triangles(np.array([p]), a, b, c)[0], want), p


def test_invalid_input():
    V, F = _blob()
    W, _ = stand_in_volume(V, fill=0.6)
    with pytest.raises(ValueError, match="vertices"):
        simulate_mesh_take(W[..., :2], F, cache=False)
    with pytest.raises(ValueError, match="faces"):
        simulate_mesh_take(W, F + 1000, cache=False)
    with pytest.raises(ValueError, match="capture volume"):
        simulate_mesh_take(W + [0, 0, 1000.0], F, cache=False)
    with pytest.raises(ValueError, match="tip_vertices"):
        simulate_mesh_take(W, F, tip_vertices={"nose": 10**6}, cache=False)
    with pytest.raises(ValueError, match="texture_points"):
        simulate_mesh_take(W, F, texture_points=W[0, :5], cache=False)
    with pytest.raises(ValueError, match="n_cameras"):
        simulate_mesh_take(W, F, n_cameras=2, cache=False)
    with pytest.raises(ValueError, match="fps"):
        simulate_mesh_take(W, F, fps=0, cache=False)
    with pytest.raises(ValueError, match="up_axis"):
        stand_in_volume(V, up_axis=3)
    with pytest.raises(ValueError, match="fill"):
        stand_in_volume(V, fill=1.5)
    with pytest.raises(ValueError, match="points"):
        snap_to_mesh(V[0], F, np.zeros((3, 2)))
    p3 = np.zeros((4, 3))
    tri = (np.zeros((4, 3)), np.tile([1.0, 0, 0], (4, 1)), np.tile([0, 1.0, 0], (4, 1)))
    with pytest.raises(ValueError, match="points must be finite with shape"):
        closest_on_triangles(np.zeros((4, 2)), *tri)
    with pytest.raises(ValueError, match="points must be finite"):
        closest_on_triangles(np.full((4, 3), np.nan), *tri)
    with pytest.raises(ValueError, match="points must be a numeric"):
        closest_on_triangles([["x", "y", "z"]], *tri)
    with pytest.raises(ValueError, match="b must have one triangle corner per point"):
        closest_on_triangles(p3, tri[0], tri[1][:3], tri[2])
    with pytest.raises(ValueError, match="c must be finite with shape"):
        closest_on_triangles(p3, tri[0], tri[1], tri[2][:, :2])
    np.testing.assert_allclose(closest_on_triangles(p3, *tri), np.tile([1.0, 0, 0], (4, 1)))  # the corner a
