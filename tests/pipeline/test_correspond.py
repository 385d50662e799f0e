"""Correspondence tracking (section 4.2): Arun alignment, K, references, assignments."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.correspond import (
    NoLimbsError,
    alignment_errors,
    arun_alignment,
    correspond_tips,
    limb_count,
    reference_frames,
)

RNG = np.random.default_rng(7)
BASE = np.array([[0, 0, 0], [4, 0, 0], [0, 2, 0], [0, 0, 1], [3, 3, 1], [-2, 1, 2]], dtype=float) * 50


def test_arun_recovers_exact_rotation():
    R = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    T = np.array([10.0, -5.0, 3.0])
    A = RNG.normal(size=(7, 3))
    B = A @ R.T + T
    R2, T2, e = arun_alignment(A, B)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(T2, T, atol=1e-10)
    assert e < 1e-18
    # a reflection is not a rotation: det stays +1
    R3, _, e3 = arun_alignment(A, A * [1, 1, -1])
    assert np.linalg.det(R3) == pytest.approx(1.0)
    assert e3 > 0


def test_batched_errors_match_arun():
    A = RNG.normal(size=(5, 3))
    B = RNG.normal(size=(20, 5, 3))
    batch = alignment_errors(A, B)
    ref = [arun_alignment(A, b)[2] for b in B]
    np.testing.assert_allclose(batch, ref, rtol=1e-9, atol=1e-12)


def test_limb_count_and_references():
    assert limb_count([5, 5, 4, 6, 5]) == 5
    assert limb_count([4, 4, 6, 6, 6, 4, 4]) == 4
    assert limb_count([3, 3, 4, 4, 4]) == 4
    assert limb_count([4, 3, 3, 3, 4, 4]) == 3  # a 3:3 tie -> the count with the longest run
    assert reference_frames([5, 5, 5, 4, 5, 5, 5, 5, 5], 5) == [6]
    refs = reference_frames([5] * 400, 5, span=150)
    assert refs[0] == 199 and len(refs) >= 3


def take(T=30, perm_seed=0):
    """A rigid-ish moving set of 6 tips, shuffled in each frame; returns tips and true order."""
    rng = np.random.default_rng(perm_seed)
    tips, truth = [], []
    for t in range(T):
        R = Rotation.from_rotvec([0, 0, 0.05 * t]).as_matrix()
        X = BASE @ R.T + [3.0 * t, 0, 0] + rng.normal(scale=1.0, size=BASE.shape)
        p = rng.permutation(6)
        tips.append(X[p])
        truth.append(np.argsort(p))  # limb k is at index truth[k]
    return tips, truth


def test_permutations_are_undone():
    tips, truth = take()
    c = correspond_tips(tips)
    assert c.K == 6
    r = c.references[0]
    # limb k of the result = limb (truth-order) at reference: consistent in every frame
    lab = [np.argsort(truth[t])[c.assignment[t]] for t in range(len(tips))]
    for t in range(len(tips)):
        np.testing.assert_array_equal(lab[t], lab[r])


def test_spurious_tip_culled_and_missing_limb_null():
    tips, truth = take(T=12)
    extra = tips[4].copy()
    tips[4] = np.vstack([extra, [[500.0, 500.0, 500.0]]])  # spurious protrusion
    gone = truth[7][2]
    tips[7] = np.delete(tips[7], gone, axis=0)  # limb 2 hidden
    c = correspond_tips(tips)
    assert c.K == 6
    r = c.references[0]
    ref_lab = np.argsort(truth[r])[c.assignment[r]]
    assert 6 not in c.assignment[4]  # the spurious tip (index 6) is culled
    np.testing.assert_array_equal(np.argsort(truth[4])[c.assignment[4]], ref_lab)
    k_missing = int(np.flatnonzero(ref_lab == 2)[0])
    assert c.assignment[7, k_missing] == -1
    seen = c.assignment[7] >= 0
    idx = np.arange(6)[np.arange(6) != gone]  # frame-7 index -> original index
    np.testing.assert_array_equal(np.argsort(truth[7])[idx[c.assignment[7][seen]]], ref_lab[seen])


def _hidden_take(T=30):
    """The 6-tip take with limbs 1 and 4 hidden (fused with the body) in the first and last 11
    frames, the others clear; frames 11-18 show all six clear, and a weak bump (not clear) beside
    limb 0 in 6 of them; frame 15 adds a clear phantom. -> tips, clear flags, and per frame the
    index of each limb's tip (-1 hidden)."""
    tips, truth = take(T=T)
    clear, where = [], []
    for t in range(T):
        keep = np.ones(6, dtype=bool)
        if t < 11 or t >= 19:
            keep[truth[t][[1, 4]]] = False
        new = np.cumsum(keep) - 1  # old tip index -> new
        where.append(np.where(keep[truth[t]], new[truth[t]], -1))
        X, c = tips[t][keep], np.ones(int(keep.sum()), dtype=bool)
        if 11 <= t < 17:
            X, c = np.vstack([X, tips[t][truth[t][0]] + [0.0, 30.0, 0.0]]), np.append(c, False)
        if t == 15:
            X, c = np.vstack([X, [[400.0, -300.0, 200.0]]]), np.append(c, True)
        tips[t] = X
        clear.append(c)
    return tips, clear, where


def test_hidden_limbs_counted_from_clear_tips():
    """Limbs fused with the body in most frames are hidden there, not absent: the clear tips of
    a quarter of the take raise K from the mode (4) to 6, never to a weak bump's or a one-frame
    phantom's count; every limb keeps its identity and the hidden ones are null."""
    tips, clear, truth = _hidden_take()
    assert limb_count([len(x) for x in tips]) == 4
    assert correspond_tips(tips).K == 4  # without the clear tips: the paper's mode
    c = correspond_tips(tips, clear=clear)
    assert c.K == 6 and c.count_rule.startswith("hidden limbs: 6 clear tips in 27 %")
    r = c.references[0]
    lab = {int(np.flatnonzero(truth[r] == c.assignment[r, k])[0]) for k in range(6)}
    assert lab == set(range(6))
    for k in range(6):
        limb = int(np.flatnonzero(truth[r] == c.assignment[r, k])[0])
        for t in range(len(tips)):
            assert c.assignment[t, k] == truth[t][limb], (t, k)
    # clear tips never lower K: all flags off leaves the mode
    assert correspond_tips(tips, clear=[np.zeros(len(x), dtype=bool) for x in tips]).count_rule == "mode"


def _swing_take(*, bumps: bool, seed: int, T: int = 30):
    """Five tips moving rigidly and a sixth swinging 250 wide through +-75 degrees beside them
    (an arm by the body), hidden in frames 9-21 (6 tips in 57 % of the frames: a borderline
    count); with ``bumps`` the sixth is a bump at a random place (normal, 120) instead."""
    rng = np.random.default_rng(seed)
    five, tips = BASE[:5], []
    for t in range(T):
        R = Rotation.from_rotvec([0, 0, 0.05 * t]).as_matrix()
        a = 1.3 * np.sin(2 * np.pi * t / T)
        sixth = five.mean(0) + [0, 0, 100] + 250 * np.array([np.cos(a), np.sin(a), 0.0])
        if bumps:
            sixth = five.mean(0) + rng.normal(scale=120.0, size=3)
        X = np.vstack([five, sixth]) @ R.T + [3.0 * t, 0, 0] + rng.normal(scale=1.0, size=(6, 3))
        X = X[:5] if 9 <= t < 22 else X
        tips.append(X[rng.permutation(len(X))])
    return tips


@pytest.mark.parametrize("seed", [0, 3])
def test_borderline_limb_that_moves_continuously_is_a_limb(seed):
    """A limb that swings far (spread 0.85 of the tip radius, beyond 0.4) but a little each frame is
    the same limb throughout: K = 6. Bumps at random places in the same frames are not (their step
    0.47-0.77 of a random place's, limit 0.35): K = 5."""
    c = correspond_tips(_swing_take(bumps=False, seed=seed))
    assert c.K == 6 and "is the same limb" in c.count_rule and "spread 0.85" in c.count_rule
    c = correspond_tips(_swing_take(bumps=True, seed=seed))
    assert c.K == 5 and "is not the same limb" in c.count_rule


def test_large_K_uses_local_search():
    X = RNG.normal(size=(9, 3)) * 100
    p = RNG.permutation(9)
    c = correspond_tips([X, X[p] + 5.0], max_permutations=1000)
    np.testing.assert_array_equal(p[c.assignment[1]], c.assignment[0])


def test_invalid_input():
    with pytest.raises(ValueError, match="tips"):
        correspond_tips([])
    with pytest.raises(ValueError, match=r"tips\[0\]"):
        correspond_tips([np.zeros((3, 2))])
    with pytest.raises(NoLimbsError):
        correspond_tips([np.zeros((0, 3)), np.zeros((0, 3))])
    with pytest.raises(ValueError, match="K"):
        correspond_tips([BASE], K=3)
    with pytest.raises(ValueError, match="features"):
        correspond_tips([BASE], features=[np.zeros((2, 1, 3))])
    with pytest.raises(ValueError, match="gate"):
        correspond_tips([BASE], gate=0)
    with pytest.raises(ValueError, match="clear"):
        correspond_tips([BASE], clear=[np.ones(5, dtype=bool)])
    with pytest.raises(ValueError, match="clear"):
        correspond_tips([BASE, BASE], clear=[np.ones(6, dtype=bool)])
    with pytest.raises(ValueError, match="A and B"):
        arun_alignment(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="B"):
        alignment_errors(np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="counts"):
        limb_count([])
    with pytest.raises(ValueError, match="span"):
        reference_frames([3], 3, span=0)
