"""Motion segmentation (Tzionas & Gall 2016, section 4.1): formulas against slow references, bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh
from threadpoolctl import threadpool_limits

from pipeline.motion_segmentation import (
    _max_min,
    check_sequence,
    interval_length,
    motion_segmentation,
    spectral_clusters,
)
from pipeline.rigid_parts import _consensus_motion, _core_motion, _gaps, rigid_motions, rigid_residual
from pipeline.trajectory_distances import trajectory_distances
from tests.pipeline.shapes import two_bars


def test_interval_length_literal_eq7_is_twice_the_largest_step():
    v = np.zeros((5, 4, 3))
    v[3, 2, 0] = 4.0  # one vertex steps 4 then back 4
    assert interval_length(v, motion=None) == 4  # 2 * 4 = 8, capped at T - 1 = 4
    assert interval_length(v, to_reference=0.25, motion=None) == 2


def test_interval_length_follows_the_motion():
    """The frames the fastest vertex needs to travel ``motion`` at its top speed: 5x the rate, 5x the frames."""
    t = np.arange(200, dtype=np.float64)
    v = np.zeros((200, 3, 3))
    v[:, 0, 0] = 30.0 * np.sin(t / 20.0)  # top speed 1.5 a frame
    v[:, 1, 1] = 0.2 * t  # slower
    slow = np.linspace(0.0, 199.0, 996)  # the same motion at 5x the frame rate (0.2 frames apart)
    v5 = np.zeros((996, 3, 3))
    v5[:, 0, 0] = 30.0 * np.sin(slow / 20.0)
    v5[:, 1, 1] = 0.2 * slow
    speed = np.abs(np.diff(v[:, 0, 0])).max()
    assert interval_length(v, motion=30.0) == round(30.0 / speed)  # 20 frames
    assert interval_length(v, to_reference=2.0, motion=30.0) == round(15.0 / speed)
    assert abs(interval_length(v5, motion=30.0) - 5 * interval_length(v, motion=30.0)) <= 1
    assert interval_length(v, motion=1e6) == 199  # capped at T - 1
    assert interval_length(np.zeros((6, 3, 3)), motion=30.0) == 5  # nothing moves: the whole sequence
    with pytest.raises(ValueError, match="motion"):
        interval_length(v, motion=0.0)


def _agreement(a, b):
    """Fraction of vertices with the same segment under the best one-to-one matching of the labels."""
    from scipy.optimize import linear_sum_assignment

    C = np.zeros((a.max() + 1, b.max() + 1))
    np.add.at(C, (a, b), 1)
    r, c = linear_sum_assignment(-C)
    return C[r, c].sum() / len(a)


def test_five_times_the_frame_rate_gives_the_same_segments():
    """The simulated quadruped's stride at 20 and at 100 frames: the interval spans the same motion."""
    from fake_cameras.mesh_motion import mesh_sequence

    segs = []
    for frames in (20, 100):
        ms = mesh_sequence("quadruped", frames=frames, voxel=10.0, dtype=np.float32)
        # without the peel (its own tests are below): the interval is what this test is about
        segs.append(motion_segmentation(ms.vertices, ms.faces, lambda_thr=0.98, n_samples=600, peel_parts=False))
    a, b = segs
    # measured: 10 and 49 frames
    assert abs(b.interval - 5 * a.interval) <= 2
    # measured: 11 and 11 segments (with the peel 11 and 12: one patch of a leg sits at its threshold, 1 % of
    # the size, in the coarser sampling of the stride)
    assert abs(a.n_segments - b.n_segments) <= 1
    # measured: 0.97 of the vertices carry the same segment (boundaries move by about a sample spacing)
    assert _agreement(a.labels, b.labels) >= 0.9
    # eq. 7 as written: the interval is a fifth of the stride's (2 x the largest step, in frames)
    lit = interval_length(ms.vertices, to_reference=300.0 / np.linalg.norm(np.ptp(ms.vertices[0], axis=0)),
                          motion=None)
    assert lit < b.interval / 3


def test_spectral_clusters_do_not_depend_on_the_order_of_the_samples():
    """Overlapping clusters give k-means local minima of nearly equal cost; the starts are chosen from the
    embedding alone (no random draw), so the samples in another order give the same partition (seeded
    k-means++ draws, 8 runs of 10 Lloyd steps, gave another one)."""
    rng = np.random.default_rng(4)
    centres = rng.normal(size=(5, 2)) * 3
    P = centres[rng.integers(5, size=300)] + rng.normal(size=(300, 2))
    A = np.exp(-((P[:, None] - P[None]) ** 2).sum(2) / 4.0)
    with threadpool_limits(1, "blas"):  # small products: threads only contend
        first = spectral_clusters(A, k=5)[0]
        orders = [np.random.default_rng(10 + i).permutation(len(A)) for i in range(3)]
        labels = [np.empty_like(first) for _ in orders]
        for lab, o in zip(labels, orders):
            lab[o] = spectral_clusters(A[np.ix_(o, o)], k=5)[0]
    for lab in labels:
        pairs = set(zip(first.tolist(), lab.tolist()))
        assert len(pairs) == len(set(first.tolist())) == len(set(lab.tolist())) == 5  # the same up to names


def test_max_min_rows_are_farthest_from_those_chosen():
    F = np.random.default_rng(2).normal(size=(40, 3))
    got = _max_min(F, 6, 7)
    chosen = [7]
    for _ in range(5):
        d = np.min([[np.linalg.norm(F[i] - F[j]) for j in chosen] for i in range(40)], axis=1)
        chosen.append(int(np.argmax(d)))
    assert got.tolist() == chosen


def test_spectral_clusters_find_blocks():
    lab = np.repeat([0, 1, 2], [30, 20, 10])
    A = np.where(lab[:, None] == lab[None, :], 1.0, 0.02)
    got, eig, k = spectral_clusters(A)
    assert k == 3
    assert eig[:3].max() < 0.7 < eig[3]
    # same partition up to renaming
    assert len({(a, b) for a, b in zip(lab, got)}) == 3


def test_rigid_residual_is_zero_for_a_rigid_motion():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    X = rng.normal(size=(50, 3))
    R = Rotation.random(6, random_state=2).as_matrix()
    Y = np.einsum("tij,nj->tni", R, X) + rng.normal(size=(6, 1, 3))
    assert rigid_residual(Y) < 1e-9
    Y[3, :25] *= 1.5
    assert rigid_residual(Y) > 0.1


def test_two_hinged_parts_are_two_segments():
    V, F, right = two_bars()
    seg = motion_segmentation(V, F, n_samples=300)
    assert seg.n_segments == 2
    # every vertex away from the hinge carries its part's label
    far = np.abs(V[0][:, 0]) > 10
    lab_r = np.bincount(seg.labels[far & right]).argmax()
    assert (seg.labels[far & right] == lab_r).all() and (seg.labels[far & ~right] != lab_r).all()


def test_a_segment_that_does_not_move_rigidly_is_cut_at_its_joint():
    """The hinged bar as one label: the normalised cut of its samples splits it at the hinge; a rigid bar stays."""
    from pipeline.motion_segmentation import _sample_normals, sample_vertices
    from pipeline.rigid_parts import _split_nonrigid

    V, F, right = two_bars()
    size = float(np.linalg.norm(np.ptp(V[0], axis=0)))
    samples = np.sort(sample_vertices(V[0], 200))
    dv, dn = trajectory_distances(V[:, samples], _sample_normals(V, F, samples), interval=len(V) - 1)
    A = np.exp(-0.1 * (300.0 / size) * dv * (dn + 1.0))
    lab = _split_nonrigid(np.zeros(len(V[0]), dtype=np.int64), V, samples, A, 0.005 * size, min_size=10)
    far = np.abs(V[0][:, 0]) > 15  # more than one mesh edge (12.5 mm) from the hinge; measured: cut at 12.5 mm
    assert len(np.unique(lab)) == 2
    assert len(np.unique(lab[far & right])) == 1 and len(np.unique(lab[far & ~right])) == 1
    assert lab[far & right][0] != lab[far & ~right][0]
    rigid = np.repeat(V[:1], len(V), axis=0)
    same = _split_nonrigid(np.zeros(len(V[0]), dtype=np.int64), rigid, samples, A, 0.005 * size, min_size=10)
    assert (same == 0).all()


def test_a_segment_with_parts_on_both_sides_of_its_cut_is_cut_deeper(monkeypatch):
    """Four blobs in two columns, each turning its own way, as one label, cut across the widest extent (the
    left column from the right, then each column top from bottom): neither column is within half the whole's
    residual, so one cut is not made; looking three cuts deep, every blob is a piece of its own. With the
    right column rigid the halves are a rigid part and the rest (the peel's case): no deeper cut. Turning by
    a fifth as much, the whole is barely past the tolerance (1.12 times) and the left column within it
    (0.90): no parts on both sides, no deeper cut (measured: without that rule, four pieces)."""
    import pipeline.rigid_parts as rp

    def blobs(turning, angle=0.8):
        rng = np.random.default_rng(5)
        centres = np.array([[0.0, 0, 0], [0, 40, 0], [100, 0, 0], [100, 40, 0]])
        X0 = np.concatenate([c + rng.normal(size=(30, 3)) * 4 for c in centres])
        blob = np.repeat(np.arange(4), 30)
        frames = []
        for t in np.linspace(0.0, 1.0, 12):
            x = X0.copy()
            for g, axis in turning:
                k = np.eye(3)[axis]
                K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
                R = np.eye(3) + np.sin(angle * t) * K + (1 - np.cos(angle * t)) * K @ K
                x[blob == g] = (X0[blob == g] - centres[g]) @ R.T + centres[g]
            frames.append(x)
        return np.stack(frames), blob

    def widest(A, near, ids, residual, min_size, cuts=19):  # the median cut across the widest extent
        p = X[0, ids]
        axis = int(np.argmax(np.ptp(p, axis=0)))
        return (p[:, axis] > np.median(p[:, axis])).astype(np.int64)

    monkeypatch.setattr(rp, "_best_cut", widest)
    for turning, angle, parts in ((((1, 2), (2, 0), (3, 1)), 0.8, 4), (((0, 2), (1, 0)), 0.8, 1),
                                  (((1, 2), (2, 0), (3, 1)), 0.15, 1)):
        X, blob = blobs(turning, angle)
        tol = 0.005 * float(np.linalg.norm(np.ptp(X[0], axis=0)))
        one = np.zeros(len(blob), dtype=np.int64)
        args = (X, np.arange(len(blob)), np.ones((len(blob), len(blob))), tol)
        assert (rp._split_nonrigid(one, *args, min_size=10) == 0).all()  # one cut: not made
        lab = rp._split_nonrigid(one, *args, min_size=10, ahead=3)
        assert len(np.unique(lab)) == parts
        assert all(len(np.unique(blob[lab == s])) == 1 for s in np.unique(lab)) or parts == 1


def _bar_chain(kind, T=8):
    """A 300 mm bar along x cut at x = -40 and 40 mm into three labels, its right end turning by up to 60
    degrees: ``"skinned"`` one hinge at the origin whose skinning blends the two bones' motions across the
    middle label (linear blend skinning, weights rising smoothly from x = -40 to 40); ``"rigid"`` two hinges
    at x = -40 and 40, the middle label a rigid part turning by half as much (a uniform curl)."""
    from pipeline.geodesic import mesh_edges

    m = trimesh.creation.box(extents=(300, 20, 20))
    for _ in range(4):
        m = m.subdivide()
    x0 = np.asarray(m.vertices)
    lab = np.digitize(x0[:, 0], [-40.0, 40.0]).astype(np.int64)

    def turn(p, ang, about):
        c, s = np.cos(ang), np.sin(ang)
        return (p - about) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + about

    frames = []
    for ang in np.linspace(0, np.pi / 3, T):
        if kind == "skinned":
            u = np.clip((x0[:, :1] + 40.0) / 80.0, 0.0, 1.0)
            w = u * u * (3 - 2 * u)
            frames.append((1 - w) * x0 + w * turn(x0, ang, np.zeros(3)))
        else:
            v = x0.copy()
            a, b = np.array([-40.0, 0, 0]), np.array([40.0, 0, 0])
            v[lab == 1] = turn(x0[lab == 1], ang / 2, a)
            v[lab == 2] = turn(turn(x0[lab == 2], ang / 2, b), ang / 2, a)
            frames.append(v)
    return np.asarray(frames), mesh_edges(np.asarray(m.faces)), lab


def test_blend_gaps_match_a_search_over_the_weight():
    from pipeline.rigid_parts import _blend_gaps

    rng = np.random.default_rng(5)
    Pa, Pb = rng.normal(size=(2, 6, 40, 3))
    w = rng.uniform(-0.5, 1.5, size=40)  # some outside [0, 1]: the weight is clipped there
    Y = w[None, :, None] * Pa + (1 - w[None, :, None]) * Pb + rng.normal(scale=0.1, size=(6, 40, 3))
    grid = np.linspace(0, 1, 4001)
    slow = [np.sqrt(((grid[:, None, None] * Pa[:, i] + (1 - grid[:, None, None]) * Pb[:, i] - Y[:, i]) ** 2)
                    .sum(2).mean(1)).min() for i in range(40)]
    np.testing.assert_allclose(_blend_gaps(Y, Pa, Pb), slow, rtol=1e-5, atol=1e-6)


def test_a_joints_blend_zone_is_dissolved_a_rigid_part_between_two_is_not():
    """A skinned hinge's blend zone cut off as a segment joins the two parts, each vertex the one whose motion
    carries it closest; a rigid middle part of a uniform curl (the same labels) stays, and so does the blend
    zone when a neighbour is smaller than it (a segment that carries a smaller part is no joint's band)."""
    from pipeline.rigid_parts import _dissolve_blends

    V, E, lab = _bar_chain("skinned")
    out = _dissolve_blends(lab, V, E)
    x = V[0][:, 0]
    assert set(np.unique(out)) == {0, 2}
    assert (out[x < -40] == 0).all() and (out[x > 40] == 2).all()
    assert (out[x < -10] == 0).all() and (out[x > 10] == 2).all()  # the zone split at its middle
    small = lab.copy()
    small[x < -80] = 3  # the zone's left neighbour now two rings of the bar, smaller than the zone
    np.testing.assert_array_equal(_dissolve_blends(small, V, E), small)
    V, E, lab = _bar_chain("rigid")
    np.testing.assert_array_equal(_dissolve_blends(lab, V, E), lab)


def test_rigid_sequence_is_one_segment(caplog):
    V, F, _ = two_bars(8)
    Vr = np.repeat(V[:1], 8, axis=0) + np.linspace(0, 80, 8)[:, None, None]  # translates, nothing bends
    with caplog.at_level(logging.WARNING):
        seg = motion_segmentation(Vr, F, n_samples=200)
    assert seg.n_segments == 1 and seg.k == 1
    assert "nothing bends" in caplog.text


def test_one_frame_is_one_segment(caplog):
    V, F, _ = two_bars(3)
    with caplog.at_level(logging.WARNING):
        seg = motion_segmentation(V[:1], F)
    assert seg.n_segments == 1
    assert "one frame" in caplog.text


def test_rigid_motions_match_one_alignment_per_frame():
    """Batched over frames against :func:`pipeline.correspond.arun_alignment` frame by frame (1e-9),
    from a reference frame in the middle; a mirrored frame still gets a rotation."""
    from scipy.spatial.transform import Rotation

    from pipeline.correspond import arun_alignment

    rng = np.random.default_rng(3)
    X = rng.normal(size=(40, 3)) * [50.0, 20.0, 10.0]
    R = Rotation.random(7, random_state=4).as_matrix()
    Y = np.einsum("tij,nj->tni", R, X) + rng.normal(size=(7, 1, 3)) * 30 + rng.normal(size=(7, 40, 3))
    Y[5] = Y[5] * [-1.0, 1.0, 1.0]  # a reflection: no rotation maps onto it exactly
    Rb, tb = rigid_motions(Y, reference=2)
    for k in range(7):
        Rk, tk, _ = arun_alignment(Y[2], Y[k])
        assert np.allclose(Rb[k], Rk, atol=1e-9) and np.allclose(tb[k], tk, atol=1e-9), k
    assert np.allclose(np.linalg.det(Rb), 1.0)
    assert np.allclose(Y[2] @ Rb[2].T + tb[2], Y[2])


def test_invalid_input():
    V, F, _ = two_bars(3)
    with pytest.raises(ValueError, match="points"):
        rigid_motions(np.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match="reference"):
        rigid_motions(np.zeros((3, 4, 3)), reference=3)
    with pytest.raises(ValueError, match="track"):
        check_sequence([V[0], V[1][:-5]], F)
    with pytest.raises(ValueError, match="vertices"):
        motion_segmentation(V[0], F)
    with pytest.raises(ValueError, match="faces"):
        motion_segmentation(V, F + len(V[0]))
    with pytest.raises(ValueError, match="lambda_thr"):
        motion_segmentation(V, F, lambda_thr=3.0)
    with pytest.raises(ValueError, match="lam"):
        motion_segmentation(V, F, lam=-1)
    with pytest.raises(ValueError, match="n_samples"):
        motion_segmentation(V, F, n_samples=1)
    bad = V.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        motion_segmentation(bad, F)


def test_a_small_bend_that_one_cluster_hides_uses_the_small_motion_threshold(caplog):
    """The hinged bar bent by only 10 degrees: lambda_thr 0.7 sees one cluster although the bar does not move
    rigidly (2.8 % of its size); the paper's threshold for small motion (0.98) is used and says so. Bent by
    3 degrees (0.4 %, under the rigidity tolerance) it stays one segment."""
    import logging

    V, F, right = two_bars(12)

    def bent(deg):
        W = np.repeat(V[:1], 12, axis=0)
        for t, a in enumerate(np.radians(np.linspace(0, deg, 12))):
            R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            W[t, right] = V[0, right] @ R.T
        return W

    with caplog.at_level(logging.WARNING):
        seg = motion_segmentation(bent(10), F, n_samples=300)
    assert seg.n_segments == 2 and seg.lambda_thr == 0.98 and "small parts with small motion" in caplog.text
    # what it means, with the figures that say how sure the segments are, in words of no caller's parameter
    from pipeline.motion_segmentation import subject_size
    from pipeline.rigid_parts import rigid_residual

    W = bent(10)
    assert "the segments are only as sure as that motion: 12 frames, the surface " in caplog.text
    assert "lambda_thr" not in caplog.text and "min_gap=" not in caplog.text
    bend = float(caplog.text.split("12 frames, the surface ")[1].split(" %")[0])
    assert abs(bend - 100 * rigid_residual(W[:, seg.samples]) / subject_size(W)) < 0.01  # its 2 decimals
    far = np.abs(V[0][:, 0]) > 10
    assert len(np.unique(seg.labels[far & right])) == 1 and len(np.unique(seg.labels[far & ~right])) == 1
    seg = motion_segmentation(bent(3), F, n_samples=300)
    assert seg.n_segments == 1 and seg.lambda_thr == 0.7


def _hinged_chain(parts, deg, T=12, length=300.0):
    """A bar of ``parts`` parts hinged about z in a chain; hinge j turns by up to ``deg`` degrees, out of phase."""
    m = trimesh.creation.box(extents=(length, 20, 20))
    for _ in range(4):
        m = m.subdivide()
    v0 = np.asarray(m.vertices)
    hinge = np.linspace(-length / 2, length / 2, parts + 1)[1:-1]
    part = np.searchsorted(hinge, v0[:, 0])
    frames = np.repeat(v0[None], T, axis=0)
    for t in range(T):
        for j, x in enumerate(hinge):
            a = np.radians(deg) * np.sin(np.pi * t / (T - 1) + j)
            R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            out = part > j
            frames[t, out] = (frames[t, out] - [x, 0, 0]) @ R.T + [x, 0, 0]
    return frames, np.asarray(m.faces), part


def test_eigenvalues_crossing_lambda_thr_without_a_gap_use_the_small_motion_threshold(caplog):
    """A chain of six parts whose hinges turn by 10 degrees: the eigenvalues rise without a gap past 0.7 (0.63,
    0.77, ...), so their count there is no count of parts; with ``min_gap`` (a tracked template's default) the
    small-motion threshold is used, says so, and every part is one segment. The hinged bar bent by 60 degrees has
    its gap at 0.7 (0.30 -> 0.97) and keeps the paper's threshold and its two segments."""
    import logging

    from pipeline.motion_segmentation import MIN_GAP, SMALL_MOTION_THR

    V, F, part = _hinged_chain(6, 10.0)
    assert motion_segmentation(V, F, n_samples=300).lambda_thr == 0.7  # the rule is off by default
    with caplog.at_level(logging.WARNING):
        seg = motion_segmentation(V, F, n_samples=300, min_gap=MIN_GAP)
    assert seg.lambda_thr == SMALL_MOTION_THR and "without a gap" in caplog.text
    assert seg.n_segments == 6
    assert all(len(np.unique(seg.labels[part == p])) == 1 for p in range(6))  # measured: each part one segment
    V, F, right = two_bars(12)
    seg = motion_segmentation(V, F, n_samples=300, min_gap=MIN_GAP)
    assert seg.lambda_thr == 0.7 and seg.n_segments == 2
    with pytest.raises(ValueError, match="min_gap"):
        motion_segmentation(V, F, min_gap=0.0)


def test_consensus_motion_is_the_largest_rigid_group_where_the_trimmed_core_fits_none():
    """Three blobs turning apart, none half of the points: the trimmed core (the half it fits best) mixes
    them, the consensus motion is the largest blob's own (``_peel_nonrigid`` falls back to it)."""
    rng = np.random.default_rng(5)
    sizes, centres = (40, 33, 27), np.array([[0.0, 0, 0], [30, 0, 0], [0, 30, 0]])
    X0 = np.concatenate([c + rng.normal(size=(n, 3)) * 4 for n, c in zip(sizes, centres)])
    group = np.repeat(np.arange(3), sizes)
    frames = []
    for t in np.linspace(0.0, 1.0, 12):
        x = X0.copy()
        for g, axis in ((1, np.array([0.0, 0, 1])), (2, np.array([1.0, 0, 0]))):
            a = 0.8 * t * (1 if g == 1 else -1)
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
            x[group == g] = (X0[group == g] - centres[0]) @ R.T + centres[0]
        frames.append(x + [5.0 * t, 0, 0])
    Y = np.stack(frames)
    tol = 0.5
    trimmed = _gaps(_core_motion(Y), Y[0], Y).max(0) <= tol
    assert trimmed.sum() < 0.5 * sizes[0]  # the trimmed core fits no blob
    within = _gaps(_consensus_motion(Y, tol, 8), Y[0], Y).max(0) <= tol
    assert within.tolist() == (group == 0).tolist()  # exactly the largest blob
