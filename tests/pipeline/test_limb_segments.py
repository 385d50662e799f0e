"""pipeline.limb_segments: a synthetic limb chain with known cuts, the interval costs against Kabsch per interval."""

import numpy as np
import pytest

from pipeline.limb_segments import LIMB_FACTOR, _interval_costs, chain_cuts, limb_noise, limb_segments, seam_positions

BODY = 400
AXIS = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])


def _rot(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _chain(cuts, *, seed=0, frames=20, n=300, noise=0.05, off=None):
    """A box body and one limb along x whose parts turn about joints at ``cuts``; every frame adds a small rigid
    jitter to every unit patch (a tracking's noise) and per-vertex noise. With ``off`` (one offset a joint) the
    joints turn about ``cuts`` moved by it, and frame 0 is the rest pose (unturned)."""
    rng = np.random.default_rng(seed)
    body = rng.uniform([-4, -2, -2], [0, 2, 2], (BODY, 3))
    s = rng.uniform(0, 10, n)
    X = np.r_[body, np.c_[s, rng.normal(0, 0.4, (n, 2))]]
    part = np.r_[np.full(BODY, -1), np.searchsorted(cuts, s)]
    V = np.repeat(X[None], frames, axis=0)
    for t in range(frames):
        for k in range(len(cuts) - 1, -1, -1):  # distal joints first, about their rest positions
            m = part >= k + 1
            j = np.array([cuts[k], 0.0, 0.0]) + (0.0 if off is None else np.asarray(off[k], float))
            angle = 0.6 * np.sin(t / 3 + k) - (0.0 if off is None else 0.6 * np.sin(k))
            V[t, m] = (V[t, m] - j) @ _rot([0, k % 2, 1 - k % 2], angle).T + j
    patch = np.floor(X[:, 0]).astype(int) * 7 + np.floor(X[:, 1]).astype(int)
    _, patch = np.unique(patch, return_inverse=True)
    V += rng.normal(0, noise, (frames, patch.max() + 1, 3))[:, patch] + rng.normal(0, noise, V.shape)
    return V, np.r_[np.full(BODY, -1), np.zeros(n, int)], part


@pytest.mark.parametrize(("cuts", "rho"), [((4.0, 7.0), None), ((2.0, 4.0, 6.0, 8.0), None), ((5.0,), "limb"),
                                         ((4.0, 7.0), "limb"), ((2.0, 4.0, 6.0, 8.0), "limb")])
def test_a_limb_chain_is_cut_where_it_bends(cuts, rho):
    V, labels, part = _chain(cuts)
    seg = limb_segments(V, labels, [AXIS], reference=0, rho=rho)
    assert (seg[:BODY] == 0).all()
    limb, true = seg[BODY:], part[BODY:]
    assert len(np.unique(limb)) == len(cuts) + 1
    # every found interval lies on one true part (a vertex within noise of a joint may fall either side)
    agree = sum(np.bincount(true[limb == p]).max() for p in np.unique(limb)) / len(limb)
    assert agree > 0.9


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_a_cut_whose_centre_lies_off_the_limb_is_dropped(seed):
    # joints at 4 and 7; the second turns about a point 1.5 (about 3 of the limb's radii, 0.44-0.46) off the axis,
    # across its hinge (about y: off in z), so its parts' relative motion has its centre outside the limb. (With
    # seed 2 the cuts there hold a sliver of 12 vertices whose centre is ill-determined, and are kept: the rule
    # drops only centres determined to lie off the limb.)
    V, labels, _ = _chain((4.0, 7.0), seed=seed, off=[(0.0, 0.0, 0.0), (0.0, 0.0, 1.5)])
    x = V[0, :, 0]
    plain = _cuts(limb_segments(V, labels, [AXIS], rho="limb"), x)
    assert np.abs(plain - 7.0).min() < 0.4 and np.abs(plain - 4.0).min() < 0.4  # cut there without the rule
    kept = _cuts(limb_segments(V, labels, [AXIS], rho="limb", centres=True), x)
    assert len(kept) == 1 and abs(kept[0] - 4.0) < 0.4
    # on the axis, or half a radius off it, both joints are kept
    for o in (0.0, 0.25):
        V, labels, _ = _chain((4.0, 7.0), seed=seed, off=[(0.0, 0.0, 0.0), (0.0, 0.0, o)])
        near = _cuts(limb_segments(V, labels, [AXIS], rho="limb", centres=True), V[0, :, 0])
        assert len(near) == 2 and np.abs(near - 4.0).min() < 0.4 and np.abs(near - 7.0).min() < 0.4


def test_interval_costs_are_the_rigid_residual_of_the_interval():
    V, _, _ = _chain((4.0, 7.0), frames=5, n=60)
    X = V[:, BODY:][:, np.argsort(V[2, BODY:, 0])]
    starts = np.array([0, 10, 25, 40, 60])
    C = _interval_costs(X, starts, 2)
    for i in range(4):
        for j in range(i + 1, 5):
            P = X[2, starts[i]:starts[j]]
            ref = 0.0
            for Q in X[:, starts[i]:starts[j]]:
                U, _, Wt = np.linalg.svd((P - P.mean(0)).T @ (Q - Q.mean(0)))
                D = np.diag([1, 1, np.sign(np.linalg.det(U @ Wt))])
                R = (U @ D @ Wt).T
                ref += ((Q - Q.mean(0) - (P - P.mean(0)) @ R.T) ** 2).sum()
            assert C[i, j] == pytest.approx(ref, rel=1e-6, abs=1e-9)


def test_the_limbs_noise_is_the_mean_fraction_its_far_cuts_remove():
    r = np.r_[0.5, 0.3, 0.2, 0.1, 0.05, 0.04, np.full(10, 0.01), np.full(5, 0.5)]  # cuts 7-16 remove 1 % each
    E = np.cumprod(np.r_[1.0, 1.0 - r])
    assert limb_noise(E) == pytest.approx(LIMB_FACTOR * 0.01)
    short = np.cumprod(np.r_[1.0, 1.0 - np.array([0.5, 0.1, 0.02, 0.04])])  # fewer cuts: the last half of them
    assert limb_noise(short) == pytest.approx(LIMB_FACTOR * 0.03)
    assert limb_noise([1.0]) == 0.0


def test_a_rigid_chain_needs_no_cut_without_noise():
    V, _, _ = _chain((), noise=0.0)
    s = V[0, BODY:, 0]
    assert (chain_cuts(V[:, BODY:], s, rho=0.1) == 0).all()


def _torn(seam, *, seed=0, angle=0.3):
    """``_chain`` with one joint at 7 and a tear at ``seam``: the limb beyond it turned by up to ``angle`` about it
    (a tracking's seam between two parts it moved rigidly), smoothed over a band of 0.03; and a strip of triangles
    along the limb, two parts meeting at the seam."""
    V, labels, _ = _chain((7.0,), seed=seed)
    x = V[0, :, 0]
    w = np.where(labels < 0, 0.0, 1 / (1 + np.exp(-(x - seam) / 0.03)))
    j = np.array([seam, 0.0, 0.0])
    for t in range(len(V)):
        V[t] += w[:, None] * ((V[t] - j) @ _rot([0, 0, 1], angle * np.sin(t / 2)).T + j - V[t])
    o = BODY + np.argsort(x[BODY:])
    faces = np.c_[o[:-2], o[1:-1], o[2:]]
    parts = np.where(labels < 0, 0, np.where(x < seam, 1, 2))
    return V, labels, faces, parts


def _cuts(seg, x):
    limb = seg[BODY:]
    return np.sort([x[BODY:][limb == p].min() for p in np.unique(limb)])[1:]


def test_the_cuts_keep_off_the_seams_of_the_tracking():
    seam = 10.0 * 10 / 32  # a candidate cut of the 32 lies on it
    V, labels, faces, parts = _torn(seam)
    x = V[0, :, 0]
    half = 0.5 * np.ptp(x[BODY:]) / 32
    plain = _cuts(limb_segments(V, labels, [AXIS], rho="limb"), x)
    assert np.abs(plain - seam).min() < 0.05  # the tear is cut where it is
    kept = _cuts(limb_segments(V, labels, [AXIS], rho="limb", faces=faces, seams=parts), x)
    assert len(kept) == len(plain)
    assert np.abs(kept - seam).min() >= half - 0.05  # (the cut's first vertex: within a vertex spacing)
    assert np.abs(kept - 7.0).min() < 0.4  # the joint is still found


def test_a_seam_is_the_median_position_of_the_vertices_on_its_edges():
    rng = np.random.default_rng(3)
    faces = rng.integers(0, 40, (60, 3))
    parts = rng.integers(0, 3, 40)
    position = np.where(rng.random(40) < 0.7, rng.uniform(0, 5, 40), np.nan)
    by_pair = {}
    for f in faces:
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            if a != b and parts[a] != parts[b]:
                key = tuple(sorted((parts[a], parts[b])))
                by_pair.setdefault(key, set()).update(v for v in (a, b) if np.isfinite(position[v]))
    ref = np.sort([np.median(position[sorted(v)]) for v in by_pair.values() if v])
    assert seam_positions(faces, parts, position) == pytest.approx(ref, abs=1e-12)


def test_invalid_input():
    V, labels, _ = _chain((4.0,), frames=3, n=40)
    with pytest.raises(ValueError, match="vertices"):
        limb_segments(V[:1], labels, [AXIS])
    with pytest.raises(ValueError, match="labels"):
        limb_segments(V, labels[:-1], [AXIS])
    with pytest.raises(ValueError, match="labels"):
        limb_segments(V, labels + 1, [AXIS])
    with pytest.raises(ValueError, match="axes"):
        limb_segments(V, labels, [AXIS[:1]])
    with pytest.raises(ValueError, match="reference"):
        limb_segments(V, labels, [AXIS], reference=3)
    with pytest.raises(ValueError, match="candidates"):
        limb_segments(V, labels, [AXIS], candidates=1)
    with pytest.raises(ValueError, match="rho"):
        limb_segments(V, labels, [AXIS], rho=1.0)
    with pytest.raises(ValueError, match="rho"):
        limb_segments(V, labels, [AXIS], rho="body")
    with pytest.raises(ValueError, match="faces"):
        limb_segments(V, labels, [AXIS], seams=np.zeros(len(labels), int))
    with pytest.raises(ValueError, match="seams"):
        limb_segments(V, labels, [AXIS], faces=[[0, 1, 2]], seams=np.zeros(3, int))
    with pytest.raises(ValueError, match="faces"):
        limb_segments(V, labels, [AXIS], faces=[[0, 1, len(labels)]], seams=np.zeros(len(labels), int))
    with pytest.raises(ValueError, match="centres"):
        limb_segments(V, labels, [AXIS], centres="yes")
    with pytest.raises(ValueError, match="avoid"):
        chain_cuts(V, V[0, :, 0], rho=0.1, avoid=[np.nan])
    with pytest.raises(ValueError, match="parts"):
        seam_positions([[0, 1, 2]], np.zeros(3, int), np.zeros(4))
    with pytest.raises(ValueError, match="labels: the body"):
        limb_segments(V[:, BODY:], labels[BODY:], [AXIS])
    with pytest.raises(ValueError, match="rho"):
        chain_cuts(V, V[0, :, 0], rho="body")
    with pytest.raises(ValueError, match="rho"):
        chain_cuts(V, V[0, :, 0], rho=-0.1)
    for E in (np.ones((2, 3)), [], [1.0, np.nan], [1.0, -1.0]):
        with pytest.raises(ValueError, match="E must"):
            limb_noise(E)
