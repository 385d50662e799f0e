import numpy as np
import pytest

from fake_cameras.creatures import BODY, CREATURES, Pose, make_creature, round_cone_sdf
from stage.rig import Volume


def _reference_sdf_outside(p, a, b, ra, rb, n=20001):
    """Distance from an outside point to the union of the swept spheres (dense sampling)."""
    s = np.linspace(0, 1, n)[:, None]
    c = a + s * (b - a)
    r = ra + s[:, 0] * (rb - ra)
    return np.min(np.linalg.norm(p - c, axis=1) - r)


def test_round_cone_sdf_matches_dense_reference():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b = rng.uniform(-50, 50, size=(2, 3))
        ra, rb = rng.uniform(3, 25, size=2)
        pts = rng.uniform(-90, 90, size=(40, 3))
        d = round_cone_sdf(pts, a[None], b[None], np.array([ra]), np.array([rb]))[:, 0]
        for p, dv in zip(pts, d):
            ref = _reference_sdf_outside(p, a, b, ra, rb)
            if ref > 0:
                assert dv == pytest.approx(ref, abs=2e-3)
            else:
                assert dv <= 1e-9


def test_degenerate_round_cone_is_the_larger_sphere():
    a = np.array([[0.0, 0, 0]])
    b = np.array([[1.0, 0, 0]])
    pts = np.array([[30.0, 0, 0], [0, 40.0, 0], [0, 0, 0]])
    d = round_cone_sdf(pts, a, b, np.array([20.0]), np.array([5.0]))[:, 0]
    assert np.allclose(d, np.linalg.norm(pts - a, axis=1) - 20.0)
    sp = Pose.spheres([[0, 0, 100]], 10.0)
    assert sp.sdf(np.array([[0, 0, 130.0]]))[0] == pytest.approx(20.0)


@pytest.mark.parametrize("name", CREATURES)
def test_creature_stays_in_volume_and_moves_smoothly(name):
    vol = Volume()
    lo, hi = (np.asarray(b) for b in vol.bounds)
    c = make_creature(name)
    times = np.linspace(0, 8, 97)
    prev = None
    spans = []
    for t in times:
        p = c.pose(t)
        plo, phi = p.bounds()
        assert np.all(plo > lo) and np.all(phi < hi), (t, plo, phi)
        assert plo[2] > 0  # above the floor
        spans.append((phi - plo).max())
        tips = p.tip_array()
        if prev is not None:
            # 1/12 s apart: tips move, but smoothly (< 60 mm)
            step = np.linalg.norm(tips - prev, axis=1)
            assert step.max() < 60
        prev = tips
    assert 300 <= max(spans) <= 560
    # the pose really changes over time
    assert np.abs(c.pose(0).tip_array() - c.pose(0.4).tip_array()).max() > 10


@pytest.mark.parametrize("name", CREATURES)
def test_tips_and_axes_are_consistent_with_the_surface(name):
    p = make_creature(name, seed=2).pose(0.7)
    assert set(p.tips) == set(p.names) == set(p.axes)
    expected = {"starfish": 5, "quadruped": 6, "biped": 5, "tailed_quadruped": 6}[name]
    assert len(p.names) == expected
    for li, n in enumerate(p.names):
        tip = p.tips[n]
        ax = p.axes[n]
        assert ax.shape[1] == 3 and ax.shape[0] >= 3
        assert np.allclose(ax[-1], tip)
        # the tip is on the surface and is the extreme point along the last segment
        assert abs(p.sdf(tip[None])[0]) < 1e-6
        u = (ax[-2] - ax[-3]) / np.linalg.norm(ax[-2] - ax[-3])
        assert np.all(p.sdf((tip + u * 0.5)[None]) > 0)
        # the junction lies inside (or on) the creature, the axis inside the limb
        assert p.sdf(ax[:1])[0] <= 1e-6
        mids = (ax[1:-1] + ax[:-2]) / 2
        assert np.all(p.sdf(mids) < 0)
        # a point just inside the tip belongs to that limb
        assert p.label_at((tip - u * 1.0)[None])[0] == li
    assert np.all(np.isin(p.limb, [BODY, *range(len(p.names))]))


def test_sdf_is_the_minimum_over_capsules():
    p = make_creature("quadruped").pose(1.1)
    rng = np.random.default_rng(0)
    pts = rng.uniform([-300, -300, 0], [300, 300, 400], size=(500, 3))
    per = p.capsule_sdf(pts)
    assert np.allclose(p.sdf(pts, chunk=77), per.min(1))
    assert np.array_equal(p.label_at(pts, chunk=33), p.limb[per.argmin(1)])


@pytest.mark.parametrize("name, voxel, coarse", [("quadruped", 6.0, 4), ("starfish", 9.0, 3), ("biped", 7.5, 5)])
def test_grid_sdf_gives_the_mesh_of_every_point(name, voxel, coarse):
    """Exact within two steps of the surface, the right sign elsewhere: marching cubes gives the
    same mesh as from the distance at every grid point."""
    from skimage.measure import marching_cubes

    p = make_creature(name).pose(0.7)
    lo, hi = p.bounds()
    axes = [np.arange(lo[k] - 2 * voxel, hi[k] + 3 * voxel, voxel) for k in range(3)]
    full = p.sdf(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)).reshape([len(a) for a in axes])
    fast = p.grid_sdf(axes, coarse=coarse)
    near = np.abs(full) <= 2 * voxel
    assert np.array_equal(fast[near], full[near]) and np.array_equal(np.sign(fast), np.sign(full))
    assert (np.abs(full) > 4 * voxel).mean() > 0.5  # most of the grid is far from the surface
    for a, b in zip(marching_cubes(full, 0.0)[:2], marching_cubes(fast, 0.0)[:2]):
        assert np.array_equal(a, b)


def test_tuck_presses_two_limbs_together_and_spur_adds_a_protrusion():
    plain = make_creature("quadruped")
    hard = make_creature("quadruped", tuck=(0.5, 1.0), spur=(0.2, 0.2 + 1 / 30))
    a, b = hard.tuck_pair
    ia, ib = hard.names.index(a), hard.names.index(b)
    inside = hard.pose(0.75)
    outside = hard.pose(1.5)
    d_in = np.linalg.norm(inside.tips[a] - inside.tips[b])
    d_out = np.linalg.norm(outside.tips[a] - outside.tips[b])
    assert d_in < 60 < d_out
    # outside the interval (and its ramp) the pose is the plain one
    assert np.allclose(outside.tip_array(), plain.pose(1.5).tip_array())
    # limb segments keep their lengths while tucked
    la = np.linalg.norm(np.diff(inside.axes[a][:-1], axis=0), axis=1)
    lp = np.linalg.norm(np.diff(plain.pose(0.75).axes[a][:-1], axis=0), axis=1)
    assert np.allclose(la, lp)
    assert ia != ib
    n_plain = plain.pose(0.21).n_capsules
    assert hard.pose(0.21).n_capsules == n_plain + 1
    assert hard.pose(0.19).n_capsules == n_plain
    assert hard.pose(0.2 + 1 / 30 + 1e-6).n_capsules == n_plain
    assert set(hard.pose(0.21).tips) == set(plain.names)


def test_invalid_input():
    with pytest.raises(ValueError, match="name"):
        make_creature("dragon")
    with pytest.raises(ValueError, match="scale"):
        make_creature("starfish", scale=0)
    with pytest.raises(ValueError, match="scale"):
        make_creature("starfish", scale="x")
    with pytest.raises(ValueError, match="tuck"):
        make_creature("starfish", tuck=(1.0, 0.5))
    with pytest.raises(ValueError, match="spur"):
        make_creature("starfish", spur=3)
    c = make_creature("biped")
    with pytest.raises(ValueError, match="time_s"):
        c.pose(float("nan"))
    p = c.pose(0)
    with pytest.raises(ValueError, match="points"):
        p.sdf(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="axes"):
        p.grid_sdf([np.arange(3.0), np.arange(3.0)])
    with pytest.raises(ValueError, match="axes"):
        p.grid_sdf([np.arange(3.0), np.zeros(0), np.arange(3.0)])
    with pytest.raises(ValueError, match="coarse"):
        p.grid_sdf([np.arange(3.0)] * 3, coarse=0)
    with pytest.raises(ValueError, match="points"):
        p.label_at(np.zeros(3))
    with pytest.raises(ValueError, match="radii"):
        Pose(p0=[[0, 0, 0]], p1=[[1, 0, 0]], r0=[0.0], r1=[1.0], limb=[-1])
    with pytest.raises(ValueError):
        Pose(p0=[[0, 0, 0]], p1=[[1, 0, 0]], r0=[1.0, 2.0], r1=[1.0], limb=[-1])


def test_tailed_quadruped_keeps_its_thin_tail_at_any_scale():
    """``scale`` grows the animal (body and other limbs exactly by the factor), not its tail."""
    small, big = make_creature("tailed_quadruped"), make_creature("tailed_quadruped", scale=1.6)
    a, b = (next(lb for lb in c.limbs if lb.name == "tail") for c in (small, big))
    assert a.radii == b.radii == (18.0, 15.0, 12.0, 8.0) and a.lengths == b.lengths
    np.testing.assert_allclose(np.asarray(b.attach), 1.6 * np.asarray(a.attach))
    for la, lb in zip(small.limbs, big.limbs):
        if la.name != "tail":
            np.testing.assert_allclose(lb.radii, 1.6 * np.asarray(la.radii))


def test_pose_rest_motions_carry_the_painted_texture_with_every_capsule():
    """``Pose.rest`` takes every capsule from its place at time 0 to the pose: a point fixed in a
    capsule (fake_cameras.surface_motion's frames, the tracking ground truth) maps back to where it
    was at time 0 (exact formula); at time 0 every motion is the identity; a tucked limb's segments
    and the spur get motions too, and their capsules' end spheres map back onto the rest chain."""
    from fake_cameras.render import _rest_points
    from fake_cameras.surface_motion import capsule_frames

    rng = np.random.default_rng(0)
    for name in ("quadruped", "starfish", "biped"):
        c = make_creature(name, seed=3)
        R0, o0 = capsule_frames(c, 0.0)
        R, o = capsule_frames(c, 0.37)
        q = rng.normal(size=(len(R), 3)) * 10  # one point per capsule, in its own frame
        at0 = np.einsum("mij,mj->mi", R0, q) + o0
        now = np.einsum("mij,mj->mi", R, q) + o
        assert np.allclose(_rest_points(c.pose(0.37).rest, now), at0, atol=1e-9)
        rest0 = c.pose(0.0).rest
        assert np.allclose(rest0[:, :, :3], np.eye(3), atol=1e-12) and np.allclose(rest0[:, :, 3], 0, atol=1e-9)
    c = make_creature("quadruped", seed=3, tuck=(0.2, 0.5), spur=(0.3, 0.34))
    p, p0 = c.pose(0.31), c.pose(0.0)
    assert p.rest.shape == (p.n_capsules, 3, 4) and p.n_capsules == p0.n_capsules + 1
    n = p0.n_capsules
    assert np.allclose(_rest_points(p.rest[:n], p.p0[:n]), p0.p0, atol=1e-6)
    assert np.allclose(_rest_points(p.rest[:n], p.p1[:n]), p0.p1, atol=1e-6)


def test_true_surface_lies_on_the_creature():
    """fake_cameras.surface_motion.true_surface: the vertices lie on the exact surface (|sdf|,
    the round-cone formula) within 0.05 voxel on average and 0.3 at most (measured 0.018 / 0.22:
    the Taubin smoothing rounds the creases where capsules meet), a closed mesh whose volume is
    the creature's (voxel centres inside, 2 %; measured 0.995)."""
    from fake_cameras.surface_motion import true_surface
    from pipeline.volume import Grid

    c = make_creature("starfish", seed=3)
    pose = c.pose(0.2)
    grid = Grid(np.array([-180.0, -200.0, 10.0]), (80, 80, 36), 5.0)
    mesh = true_surface(c, 0.2, grid)
    assert mesh.is_watertight
    off = np.abs(pose.sdf(mesh.vertices)) / grid.voxel
    assert off.mean() <= 0.05 and off.max() <= 0.3
    inside = (pose.sdf(grid.centers()) < 0).sum() * grid.voxel ** 3
    assert abs(mesh.volume / inside - 1) <= 0.02


def test_true_surface_invalid_input():
    from fake_cameras.surface_motion import true_surface
    from pipeline.volume import Grid

    c = make_creature("starfish", seed=3)
    grid = Grid(np.zeros(3), (4, 4, 4), 1.0)
    with pytest.raises(ValueError, match="creature"):
        true_surface("starfish", 0.0, grid)
    with pytest.raises(ValueError, match="grid"):
        true_surface(c, 0.0, {"lo": [0, 0, 0]})
    with pytest.raises(ValueError, match="time_s"):
        true_surface(c, float("nan"), grid)


def _tracked_results(tmp_path, shifts):
    """A results directory whose template is the starfish's true surface at its frame 1 and whose
    tracked frames are the true tracks shifted along x by ``shifts`` voxels."""
    import json

    from fake_cameras.surface_motion import surface_point_tracks, true_surface
    from pipeline.results import ply_bytes
    from pipeline.volume import Grid

    c = make_creature("starfish", seed=3)
    times = np.array([0.0, 0.1, 0.2])
    grid = Grid(np.array([-180.0, -200.0, 10.0]), (80, 80, 36), 5.0)
    mesh = true_surface(c, times[1], grid)
    V0, F0 = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    (tmp_path / "tracked").mkdir()
    (tmp_path / "template.ply").write_bytes(ply_bytes(V0, F0))
    (tmp_path / "grid.json").write_text(json.dumps(grid.to_dict()))
    (tmp_path / "tracked" / "track.json").write_text(json.dumps({"template": str(tmp_path / "template.ply"),
                                                                 "reference_frame": 1}))
    truth = surface_point_tracks(c, V0, [times[1], *times])[1:]
    written = [truth[k] + [shifts[k] * grid.voxel, 0.0, 0.0] for k in range(len(times))]
    for k, v in enumerate(written):
        (tmp_path / "tracked" / f"{k:06d}.ply").write_bytes(ply_bytes(v, F0))
    return c, times, V0, F0, written


def test_tracking_errors_are_the_distances_to_the_true_tracks(tmp_path):
    """fake_cameras.surface_motion.tracking_errors: tracked frames that are the true tracks shifted
    by 0, 1 and 2.5 voxels score exactly that (the PLY round trip is exact: 1e-9), and the volumes
    are the frames' own over the template's."""
    from fake_cameras.surface_motion import tracking_errors
    from pipeline.mesh_primitives import mesh_volume

    c, times, V0, F0, written = _tracked_results(tmp_path, [0.0, 1.0, 2.5])
    err, vols, rep = tracking_errors(c, times, tmp_path)
    assert err.shape == (3, len(V0)) and rep["reference_frame"] == 1
    for k, shift in enumerate([0.0, 1.0, 2.5]):
        np.testing.assert_allclose(err[k], shift, atol=1e-9)
        assert vols[k] == pytest.approx(mesh_volume(written[k], F0) / mesh_volume(V0, F0), rel=1e-12)
    err2, vols2, _ = tracking_errors(c, times, tmp_path, frames=2)
    assert np.array_equal(err2, err[:2]) and np.array_equal(vols2, vols[:2])


def test_tracking_errors_invalid_input(tmp_path):
    from fake_cameras.surface_motion import tracking_errors
    from pipeline.results import ply_bytes

    c, times, V0, F0, written = _tracked_results(tmp_path, [0.0, 0.0, 0.0])
    for bad in (0, 4, True, 1.5):
        with pytest.raises(ValueError, match="frames"):
            tracking_errors(c, times, tmp_path, frames=bad)
    with pytest.raises(ValueError, match="results_dir"):
        tracking_errors(c, times, tmp_path / "nowhere")
    with pytest.raises(ValueError, match="creature"):
        tracking_errors("starfish", times, tmp_path)
    (tmp_path / "tracked" / "000002.ply").write_bytes(ply_bytes(written[2], F0[:-1]))
    with pytest.raises(ValueError, match="not the template's mesh"):
        tracking_errors(c, times, tmp_path)


def test_invented_motion_is_zero_for_rigid_parts_and_sees_noise(tmp_path):
    """fake_cameras.surface_motion.invented_motion: the true tracks, shifted rigidly, invent nothing
    but the template's own distance from the true surface they were snapped to (measured 0.018
    voxels; at most 0.05); a frame with independent noise of 0.5 voxels per coordinate on every vertex
    invents what a rigid fit cannot take out, close to the noise's mean length (0.8 voxels)."""
    from fake_cameras.surface_motion import invented_motion
    from pipeline.results import ply_bytes

    c, times, V0, F0, written = _tracked_results(tmp_path, [0.0, 1.0, 2.5])
    # the reference frame's tracked file is the template itself
    (tmp_path / "tracked" / "000001.ply").write_bytes(ply_bytes(V0, F0))
    inv = invented_motion(c, times, tmp_path)
    assert inv.shape == (3,) and inv[1] < 1e-9 and np.all(inv < 0.05), inv
    assert invented_motion(c, times, tmp_path, frames=1).shape == (1,)
    rng = np.random.default_rng(0)
    noisy = written[2] + rng.normal(0.0, 0.5 * 5.0, written[2].shape)
    (tmp_path / "tracked" / "000002.ply").write_bytes(ply_bytes(noisy, F0))
    noise = invented_motion(c, times, tmp_path)[2]
    assert 0.5 <= noise <= 0.9, noise


def test_invented_motion_invalid_input(tmp_path):
    from fake_cameras.surface_motion import invented_motion

    c, times, V0, F0, written = _tracked_results(tmp_path, [0.0, 0.0, 0.0])
    for bad in (0, 4, True):
        with pytest.raises(ValueError, match="frames"):
            invented_motion(c, times, tmp_path, frames=bad)
    with pytest.raises(ValueError, match="min_vertices"):
        invented_motion(c, times, tmp_path, min_vertices=2)
    with pytest.raises(ValueError, match="results_dir"):
        invented_motion(c, times, tmp_path / "nowhere")
    with pytest.raises(ValueError, match="creature"):
        invented_motion("starfish", times, tmp_path)
