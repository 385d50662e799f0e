"""Topology matching of per-tip skeletons (Fig. 3B) and limb selection."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.merge import Topology, consensus_topology, merge_skeletons, skeleton_splits, tree_median, tree_path
from pipeline.skeleton import TipSkeleton


def make_skel(seed, nodes, parent, tip_nodes, cost=None):
    nodes = np.asarray(nodes, dtype=float)
    n = len(nodes)
    return TipSkeleton(
        seed=seed,
        nodes=nodes,
        parent=np.asarray(parent),
        cost=np.ones(n) if cost is None else np.asarray(cost, dtype=float),
        frame=np.tile(np.eye(3), (n, 1, 1)),
        count=np.ones(n, dtype=int),
        level=np.arange(n),
        tip_nodes=np.asarray(tip_nodes),
    )


# Fig. 3B: four tips A, B, C, D around one junction; the red skeleton pairs
# (A, B) | (C, D) through two 3-way junctions, the green one (A, C) | (B, D).
TIPS = np.array([[-1, 1, 0], [1, 1, 0], [-1, -1, 0], [1, -1, 0]], dtype=float)


def red():
    # rooted at A(0): A -> j1 -> B ; j1 -> j2 -> C, D
    nodes = [TIPS[0], [-0.1, 0.1, 0], TIPS[1], [0.1, -0.1, 0], TIPS[2], TIPS[3]]
    return make_skel(0, nodes, [-1, 0, 1, 1, 3, 3], [0, 2, 4, 5])


def green():
    # rooted at B(1): B -> k1 -> D ; k1 -> k2 -> A, C
    nodes = [TIPS[1], [0.1, 0.1, 0], TIPS[3], [-0.1, 0.0, 0], TIPS[0], TIPS[2]]
    return make_skel(1, nodes, [-1, 0, 1, 1, 3, 3], [4, 0, 5, 2])


def test_fig3b_two_three_way_junctions_become_one_four_way_metanode():
    r, g = red(), green()
    assert skeleton_splits(r) == {0b1100}
    assert skeleton_splits(g) == {0b1010}
    top = consensus_topology([skeleton_splits(r), skeleton_splits(g)], 4)
    assert top.splits == () and top.n_junctions == 1
    assert sorted(top.groups(0)) == [1, 2, 4, 8]
    m = merge_skeletons([r, g], TIPS)
    assert len(m.junctions) == 1
    assert np.all(np.abs(m.junctions[0]) <= 0.1)
    for i, ax in enumerate(m.tip_axes):
        np.testing.assert_allclose(ax[0], m.junctions[0])
        np.testing.assert_allclose(ax[-1], TIPS[i])


def test_majority_keeps_agreed_split_and_best_limb():
    r = red()
    r2 = make_skel(2, r.nodes, r.parent, r.tip_nodes, cost=[0.5] * 6)
    top = consensus_topology([skeleton_splits(s) for s in (r, r2, green())], 4)
    assert top.splits == (0b1100,) and top.n_junctions == 2
    # the limb from the cheaper skeleton (r2) wins: Q = N - sum C / max C
    m = merge_skeletons([r, r2], TIPS)
    assert m.tip_quality[1] == pytest.approx(1 - 0.5 / 1.0)


def test_topology_functions():
    t = Topology.from_splits(6, [0b000110, 0b111000])
    assert t.n_junctions == 3
    assert Topology.from_dict(t.to_dict()) == t
    assert t.restricted([0, 1, 2, 3, 4]).splits == (0b00110, 0b11000)
    assert t.restricted([0, 1, 2, 3]).splits == (0b0110,)
    with pytest.raises(ValueError, match="incompatible"):
        Topology.from_splits(4, [0b0110, 0b1100])
    with pytest.raises(ValueError, match="trivial"):
        Topology.from_splits(4, [0b0010])
    parent = np.array([-1, 0, 1, 1, 0])
    assert tree_path(parent, 2, 4) == [2, 1, 0, 4]
    assert tree_median(parent, 2, 3, 4) == 1


def test_invalid_input():
    with pytest.raises(ValueError, match="n_tips"):
        Topology.from_splits(0, [])
    with pytest.raises(ValueError, match="threshold"):
        consensus_topology([], 3, threshold=0.2)
    with pytest.raises(ValueError, match="tips"):
        merge_skeletons([red()], TIPS, tips=[0, 1, 9])
    with pytest.raises(ValueError, match="topology"):
        merge_skeletons([red()], TIPS, topology=Topology.from_splits(3, []))
