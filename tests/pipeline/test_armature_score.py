"""Scores of a rig against true joints and parts (pipeline.armature_score): exact small cases and loops."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.armature_score import articulation_bends, articulation_scores, bending_parts, segment_agreement


def test_bends_of_a_chain_that_folds():
    # root 0 -> 1 -> 2: joint 1 folds from straight to 90 degrees; the root and the tip bend 0
    T = 5
    ang = np.radians(np.linspace(0, 90, T))
    J = np.zeros((T, 3, 3))
    J[:, 1] = [1.0, 0, 0]
    J[:, 2] = np.c_[1 + np.cos(ang), np.sin(ang), np.zeros(T)]
    np.testing.assert_allclose(articulation_bends(J, [-1, 0, 1]), [0.0, 90.0, 0.0], atol=1e-9)


def test_scores_against_a_loop():
    rng = np.random.default_rng(0)
    T, K, Fn, size = 6, 5, 4, 100.0
    true = rng.normal(scale=50, size=(T, K, 3))
    found = true[:, [0, 1, 2, 0]] + rng.normal(scale=1.0, size=(T, Fn, 3))
    found[:, 3] += 30.0  # far from everything
    art = np.array([True, True, True, True, False])
    bend = np.array([True, True, False, True, False])
    s = articulation_scores(found, true, size=size, articulates=art, bending=bend)
    # the slow reference: a loop over pairs
    D = np.zeros((Fn, K))
    for i in range(Fn):
        for k in range(K):
            D[i, k] = np.median([np.linalg.norm(found[t, i] - true[t, k]) for t in range(T)]) / size
    np.testing.assert_allclose(s["distances"], D, rtol=1e-12)
    rec = np.mean([D[:, k].min() < 0.05 for k in np.flatnonzero(bend)])
    prec = np.mean([D[i, art].min() < 0.05 for i in range(Fn)])
    assert s["recall"] == pytest.approx(rec) and s["precision"] == pytest.approx(prec)
    assert s["recall"] == pytest.approx(2 / 3) and s["precision"] == pytest.approx(3 / 4)
    assert articulation_scores(found[:, :0], true, size=size)["recall"] == 0.0


def test_agreement_of_fused_and_cut_parts():
    truth = np.repeat([0, 1, 2], 10)
    assert segment_agreement(truth, truth) == (1.0, 1.0)
    fused = np.repeat([0, 0, 1], 10)  # parts 0 and 1 in one segment
    assert segment_agreement(fused, truth) == (pytest.approx(20 / 30), 1.0)
    cut = np.repeat([0, 1, 2, 3], [10, 10, 5, 5])  # part 2 cut in two
    assert segment_agreement(cut, truth) == (1.0, pytest.approx(25 / 30))


def test_bending_parts_join_across_still_joints():
    # body 0; limb 1 -> 2 -> 3 from the body; the joint above 2 does not bend
    pv = np.array([0, 0, 1, 1, 2, 2, 3, 3])
    out = bending_parts(pv, [-1, 0, 1, 2], [False, True, False, True])
    assert len(np.unique(out)) == 3 and out[2] == out[4] and out[0] != out[2] != out[6]


def test_invalid_input():
    J = np.zeros((2, 3, 3))
    with pytest.raises(ValueError, match="joints"):
        articulation_bends(J[0], [-1, 0, 1])
    with pytest.raises(ValueError, match="parents"):
        articulation_bends(J, [-1, 0])
    with pytest.raises(ValueError, match="size"):
        articulation_scores(J, J, size=0.0)
    with pytest.raises(ValueError, match="same frames"):
        articulation_scores(J[:1], J, size=1.0)
    with pytest.raises(ValueError, match="entries"):
        articulation_scores(J, J, size=1.0, articulates=[True])
    with pytest.raises(ValueError, match="same length"):
        segment_agreement([0, 1], [0])
    with pytest.raises(ValueError, match="integers"):
        segment_agreement([0.5, 1], [0, 1])
    with pytest.raises(ValueError, match="part_of_vertex"):
        bending_parts([0, 5], [-1, 0], [False, True])
