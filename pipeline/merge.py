"""Merging the per-tip skeletons of one surface (Brostow et al. 2004, section 4.1, Fig. 3B).

Every tip of a frame seeds its own skeleton (:mod:`pipeline.skeleton`); they
describe the same creature but their junctions fall in different places, and
near a junction of high degree they can even disagree about which limbs meet
first (Fig. 3B: two pairs of three-way junctions that are one four-way
junction). The paper's leaf-seeking topology matching:

1. the limb tips are *supernodes*: the same tips in every skeleton;
2. walking inward from each supernode, the next branch node of every skeleton
   corresponds to that of the others; branch nodes reached from the same
   tips are grouped, and groups that share a node are merged into a
   *metanode* (the circle and square of Fig. 3B become one four-way junction).

We implement it through the tip *splits* that the junctions induce: every
skeleton edge between two branch nodes separates the tips into two sides. A
junction of the merged skeleton is defined by the splits that a majority of
the skeletons agree on (their sides are the "walk inward from the tips"
groups); splits only some skeletons make are the perturbed three-way pairs of
Fig. 3B, and dropping them merges those junctions into one metanode. Majority
splits are always mutually compatible, so the result is a tree whose leaves
are exactly the tips. In each constituent skeleton a metanode is realised by
the *median* node of tips lying on three of its sides (the branch point the
inward walks from those tips reach first).

Then every limb (chain between two metanodes, or a metanode and a tip) is
taken from the skeleton where its quality ``Q_L = N - sum C_i / max C`` (eq. 5)
is best, ``max C`` over all nodes of all the frame's skeletons.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from pipeline.skeleton import TipSkeleton, limb_quality

__all__ = [
    "Topology",
    "skeleton_splits",
    "consensus_topology",
    "tree_path",
    "tree_lca",
    "tree_median",
    "realize_junctions",
    "MergedSkeleton",
    "merge_skeletons",
]


def _bits(mask: int) -> list[int]:
    out, i = [], 0
    while mask:
        if mask & 1:
            out.append(i)
        mask >>= 1
        i += 1
    return out


@dataclass(frozen=True)
class Topology:
    """Tree topology over ``n`` tips, defined by its nontrivial splits.

    A split is a bitmask of tips (bit ``i`` = tip ``i``) on the side *not*
    holding tip 0. Junction 0 is the junction next to tip 0 (mask = all tips
    but 0); junction ``j >= 1`` is the top of the clade ``junction_masks[j]``
    when the tree is hung from tip 0.

    Attributes
    ----------
    n_tips : int
    splits : tuple of int
        Sorted canonical split masks (the identity of the topology).
    junction_masks : tuple of int
    junction_parent : tuple of int
        Parent junction (``-1`` for junction 0).
    tip_parent : tuple of int
        Junction each tip hangs from.
    """

    n_tips: int
    splits: tuple[int, ...]
    junction_masks: tuple[int, ...]
    junction_parent: tuple[int, ...]
    tip_parent: tuple[int, ...]

    @classmethod
    def from_splits(cls, n_tips: int, splits) -> "Topology":
        n = int(n_tips)
        if n < 1:
            raise ValueError(f"n_tips must be >= 1, got {n_tips}")
        full = (1 << n) - 1
        canon = sorted({canonical_split(int(s), n) for s in splits} - {0})
        for s in canon:
            k = bin(s).count("1")
            if k < 2 or k > n - 2:
                raise ValueError(f"split {s:b} is trivial for {n} tips")
        for a, b in combinations(canon, 2):
            if (a & b) and not ((a & b) == a or (a & b) == b):
                raise ValueError(f"splits {a:b} and {b:b} are incompatible")
        masks = [full & ~1] + sorted(canon, key=lambda m: (-bin(m).count("1"), m))

        def smallest_containing(bitmask: int, exclude: int | None) -> int:
            best, best_size = 0, None
            for j, m in enumerate(masks):
                if j == exclude or (m & bitmask) != bitmask:
                    continue
                size = bin(m).count("1")
                if best_size is None or size < best_size:
                    best, best_size = j, size
            return best

        jpar = [-1] + [smallest_containing(m, j) for j, m in enumerate(masks) if j > 0]
        tpar = [0] + [smallest_containing(1 << i, None) for i in range(1, n)]
        return cls(n, tuple(canon), tuple(masks), tuple(jpar), tuple(tpar))

    @property
    def n_junctions(self) -> int:
        return len(self.junction_masks)

    def groups(self, j: int) -> list[int]:
        """Tip masks of the sides around junction ``j`` (one per incident edge)."""
        n = self.n_tips
        full = (1 << n) - 1
        own = self.junction_masks[j]
        g = [self.junction_masks[c] for c in range(self.n_junctions) if self.junction_parent[c] == j]
        g += [1 << i for i in range(n) if self.tip_parent[i] == j and (i > 0 or j != 0)]
        g.append(full & ~own)  # the side of the parent (holds tip 0)
        return [m for m in g if m]

    def restricted(self, keep) -> "Topology":
        """Topology over the tips ``keep`` (renumbered 0..len-1 in that order)."""
        keep = [int(i) for i in keep]
        new = []
        for s in self.splits:
            m = 0
            for k, i in enumerate(keep):
                if s >> i & 1:
                    m |= 1 << k
            new.append(m)
        n = len(keep)
        ok = [canonical_split(m, n) for m in new]
        ok = [m for m in ok if 2 <= bin(m).count("1") <= n - 2]
        return Topology.from_splits(n, ok)

    def to_dict(self) -> dict:
        return {"n_tips": self.n_tips, "splits": list(self.splits)}

    @classmethod
    def from_dict(cls, d: dict) -> "Topology":
        return cls.from_splits(int(d["n_tips"]), [int(s) for s in d["splits"]])


def canonical_split(mask: int, n: int) -> int:
    """The side of a split that does not hold tip 0."""
    full = (1 << n) - 1
    mask &= full
    return (full ^ mask) if mask & 1 else mask


class _Tree:
    """A parent array whose ancestor chains are computed once per node (the junction
    search asks for the same few chains thousands of times)."""

    def __init__(self, parent) -> None:
        self.parent = np.asarray(parent).tolist()
        self._cache: dict[int, list[int]] = {}

    def ancestors(self, node: int) -> list[int]:
        node = int(node)
        out = self._cache.get(node)
        if out is None:
            out = self._cache[node] = _ancestors(self.parent, node)
        return out


def _ancestors(parent, node: int) -> list[int]:
    if isinstance(parent, _Tree):
        return parent.ancestors(node)
    out = []
    while node >= 0:
        out.append(int(node))
        node = int(parent[node])
    return out


def tree_path(parent: np.ndarray, a: int, b: int) -> list[int]:
    """Nodes on the tree path from ``a`` to ``b`` (both included)."""
    pa = _ancestors(parent, a)
    pb = _ancestors(parent, b)
    sb = {x: i for i, x in enumerate(pb)}
    for i, x in enumerate(pa):
        if x in sb:
            return pa[: i + 1] + pb[: sb[x]][::-1]
    raise ValueError(f"nodes {a} and {b} are not in the same tree")


def tree_lca(parent: np.ndarray, a: int, b: int) -> int:
    """Lowest common ancestor of ``a`` and ``b`` in a rooted tree (``-1`` if none)."""
    return _lca(parent, a, b)


def _lca(parent, a, b):
    sa = set(_ancestors(parent, a))
    for x in _ancestors(parent, b):
        if x in sa:
            return x
    return -1


def tree_median(parent: np.ndarray, a: int, b: int, c: int) -> int:
    """The node on all three pairwise paths between ``a``, ``b``, ``c`` in a rooted tree."""
    cands = [_lca(parent, a, b), _lca(parent, a, c), _lca(parent, b, c)]
    depth = [len(_ancestors(parent, x)) for x in cands]
    return cands[int(np.argmax(depth))]


def skeleton_splits(skeleton: TipSkeleton, tips=None) -> set[int]:
    """Canonical tip splits induced by the branch nodes of one skeleton.

    Parameters
    ----------
    skeleton : TipSkeleton
    tips : sequence of int, optional
        Frame tips to consider (default all); bit ``k`` of a split is ``tips[k]``.

    Returns
    -------
    set of int
    """
    tn = skeleton.tip_nodes
    tips = list(range(len(tn))) if tips is None else [int(t) for t in tips]
    n = len(tips)
    mask: dict[int, int] = {}
    for k, t in enumerate(tips):
        if tn[t] < 0:
            continue
        for x in _ancestors(skeleton.parent, int(tn[t])):
            mask[x] = mask.get(x, 0) | (1 << k)
    out = set()
    for m in set(mask.values()):
        m = canonical_split(m, n)
        if 2 <= bin(m).count("1") <= n - 2:
            out.add(m)
    return out


def consensus_topology(split_sets, n_tips: int, *, threshold: float = 0.5) -> Topology:
    """Majority-rule topology: the splits found in more than ``threshold`` of the skeletons.

    Parameters
    ----------
    split_sets : sequence of set of int
        :func:`skeleton_splits` of each skeleton.
    n_tips : int
    threshold : float
        In ``[0.5, 1)``; 0.5 is the strict majority (always a tree).
    """
    if not 0.5 <= threshold < 1:
        raise ValueError(f"threshold must be in [0.5, 1), got {threshold}")
    sets = list(split_sets)
    if not sets:
        return Topology.from_splits(n_tips, [])
    c = Counter(s for ss in sets for s in ss)
    keep = [s for s, k in c.items() if k > threshold * len(sets)]
    return Topology.from_splits(n_tips, keep)


def realize_junctions(skeleton: TipSkeleton, topology: Topology, tips) -> list[int | None]:
    """Node of ``skeleton`` standing for each junction of ``topology`` (``None`` if not possible).

    For each junction the tips around it fall in groups (one per incident
    edge); the junction is the tree median of one tip from each of three
    groups (the tip nearest the junction in each group); with more than three
    groups, the medoid of the medians of all group triples. Junctions with
    fewer than three groups holding a reached tip are ``None``; with
    ``n_tips <= 2`` the single junction is the middle of the path between the
    tips (or the ring farthest from a lone tip).
    """
    tips = [int(t) for t in tips]
    tn = skeleton.tip_nodes
    par = _Tree(skeleton.parent)
    node_of = [int(tn[t]) if t >= 0 else -1 for t in tips]
    n = topology.n_tips
    if n <= 2:
        present = [x for x in node_of if x >= 0]
        if len(present) == 2:
            p = tree_path(par, present[0], present[1])
            return [p[len(p) // 2]]
        if len(present) == 1:
            return [int(np.argmax(skeleton.level))]
        return [None]
    out: list[int | None] = []
    for j in range(topology.n_junctions):
        reps = []
        for g in topology.groups(j):
            members = [i for i in _bits(g) if node_of[i] >= 0]
            if not members:
                continue
            # the member hanging closest (in hops) to junction j
            members.sort(key=lambda i: _hops(topology, i, j))
            reps.append(node_of[members[0]])
        if len(reps) < 3:
            out.append(None)
            continue
        meds = [tree_median(par, a, b, c) for a, b, c in combinations(reps, 3)]
        if len(set(meds)) == 1:
            out.append(meds[0])
        else:
            cost = [sum(len(tree_path(par, m, o)) for o in meds) for m in meds]
            out.append(meds[int(np.argmin(cost))])
    return out


def _hops(topology: Topology, tip: int, j: int) -> int:
    """Number of junctions between tip and junction j in the topology tree."""
    path = []
    x = topology.tip_parent[tip]
    while x >= 0:
        path.append(x)
        x = topology.junction_parent[x]
    if j in path:
        return path.index(j)
    # j is below: walk from j up
    y, h = j, 0
    while y >= 0 and y not in path:
        y = topology.junction_parent[y]
        h += 1
    return h + (path.index(y) if y in path else 0)


@dataclass(frozen=True)
class MergedSkeleton:
    """One skeleton for one frame: a topology realised with the best limbs.

    Attributes
    ----------
    topology : Topology
        Over the frame's (selected) tips; tip ``i`` is ``tips[i]``.
    tips : (n, 3) float ndarray
        Tip positions (nan when absent).
    junctions : (J, 3) float ndarray
        Junction positions (nan when not realised).
    tip_axes : list of (m, 3) ndarray or None
        Polyline from the parent junction to each tip.
    junction_axes : list of (m, 3) ndarray or None
        Polyline from the parent junction to each junction (``None`` for junction 0).
    tip_quality, junction_quality : (n,), (J,) float ndarray
        ``Q_L`` of the chosen version of each limb (nan when absent).
    """

    topology: Topology
    tips: np.ndarray
    junctions: np.ndarray
    tip_axes: list
    junction_axes: list
    tip_quality: np.ndarray
    junction_quality: np.ndarray


def merge_skeletons(
    skeletons,
    tip_points: np.ndarray,
    *,
    tips=None,
    topology: Topology | None = None,
    junction_hints: np.ndarray | None = None,
    cost_norm: float | None = None,
) -> MergedSkeleton:
    """Merge per-tip skeletons into one, keeping the best version of each limb.

    Parameters
    ----------
    skeletons : sequence of TipSkeleton
        Skeletons of one frame, all carrying ``tip_nodes`` for the same tips.
    tip_points : (T, 3) float ndarray
        Positions of the frame's tips.
    tips : sequence of int, optional
        The tips to keep, in output order; ``-1`` = an absent tip (its limb is
        empty). Default: all tips.
    topology : Topology, optional
        Impose this topology over ``tips`` (section 4.3); default: the
        majority consensus of the skeletons (section 4.1).
    junction_hints : (J, 3) float ndarray, optional
        Where to place junctions that cannot be realised (fewer than three
        sides with a tip): the node nearest the hint on the path between the
        present sides. Rows of nan = no hint.
    cost_norm : float, optional
        ``max C_i`` to normalise by (default: over all nodes of ``skeletons``).

    Returns
    -------
    MergedSkeleton
    """
    skeletons = list(skeletons)
    P = np.asarray(tip_points, dtype=np.float64).reshape(-1, 3)
    tips = list(range(len(P))) if tips is None else [int(t) for t in tips]
    if any(t >= len(P) for t in tips):
        raise ValueError("tips index beyond tip_points")
    n = len(tips)
    present = [t for t in tips if t >= 0]
    # only the skeletons seeded at kept tips take part
    kept = [s for s in skeletons if s.seed in present] or skeletons
    if topology is None:
        topology = _consensus_over(kept, tips)
    elif topology.n_tips != n:
        raise ValueError(f"topology has {topology.n_tips} tips, tips has {n}")
    if cost_norm is None:
        allc = np.concatenate([s.cost for s in skeletons]) if skeletons else np.zeros(1)
        cost_norm = float(allc.max()) if allc.size and allc.max() > 0 else 1.0
    J = topology.n_junctions
    tips_xyz = np.full((n, 3), np.nan)
    for i, t in enumerate(tips):
        if t >= 0:
            tips_xyz[i] = P[t]
    real = _realized_junctions(kept, topology, tips, junction_hints)
    jpos = np.full((J, 3), np.nan)
    for j in range(J):
        pts = [kept[si].nodes[real[si][j]] for si in range(len(kept)) if real[si][j] is not None]
        if pts:
            jpos[j] = np.median(np.asarray(pts), axis=0)
    chains = _ChainPicker(kept, real, jpos, cost_norm)
    tip_axes, tq = [], np.full(n, np.nan)
    for i, t in enumerate(tips):
        if t < 0:
            tip_axes.append(None)
            continue
        poly, q = chains.best(lambda si, s, t=t: int(s.tip_nodes[t]), topology.tip_parent[i], True, tips_xyz[i])
        tip_axes.append(poly)
        tq[i] = q
    junction_axes, jq = [None], np.full(J, np.nan)
    for j in range(1, J):
        poly, q = chains.best(lambda si, s, j=j: real[si][j], topology.junction_parent[j], False, jpos[j])
        junction_axes.append(poly)
        jq[j] = q
    return MergedSkeleton(topology, tips_xyz, jpos, tip_axes, junction_axes, tq, jq)


def _consensus_over(kept, tips: list[int]) -> Topology:
    """Majority topology of the skeletons over the present tips, in the numbering of ``tips``."""
    n = len(tips)
    sub = [i for i, t in enumerate(tips) if t >= 0]
    split_sets = [skeleton_splits(s, [tips[i] for i in sub]) for s in kept]
    topology = consensus_topology(split_sets, len(sub)) if sub else Topology.from_splits(max(n, 1), [])
    if len(sub) == n:
        return topology
    lifted = []  # lift back to the full tip numbering
    for s in topology.splits:
        m = 0
        for k, i in enumerate(sub):
            if s >> k & 1:
                m |= 1 << i
        lifted.append(m)
    return Topology.from_splits(n, lifted)


def _realized_junctions(kept, topology: Topology, tips, junction_hints) -> list[list]:
    """Per skeleton, the node of every junction (None when it cannot be realised nor hinted)."""
    real = [realize_junctions(s, topology, tips) for s in kept]
    if junction_hints is None:
        return real
    hints = np.asarray(junction_hints, dtype=np.float64).reshape(topology.n_junctions, 3)
    for si, s in enumerate(kept):
        for j in range(topology.n_junctions):
            if real[si][j] is None and np.all(np.isfinite(hints[j])):
                real[si][j] = _node_near_hint(s, topology, tips, j, hints[j])
    return real


@dataclass
class _ChainPicker:
    """Picks, among the skeletons, the best-quality chain from a junction to a tip or junction."""

    kept: list
    real: list
    jpos: np.ndarray
    cost_norm: float

    def best(self, end_node_of, j_parent: int, end_is_tip: bool, end_xyz: np.ndarray):
        """``(polyline from the junction's median position to end_xyz, quality)`` or ``(None, nan)``."""
        best_q, best_poly = -np.inf, None
        for si, s in enumerate(self.kept):
            a = self.real[si][j_parent]
            b = end_node_of(si, s)
            if a is None or b is None or b < 0:
                continue
            path = tree_path(s.parent, a, b)
            inner = path[1:] if end_is_tip else path[1:-1]
            q = limb_quality(s.cost[inner], self.cost_norm) if inner else 0.0
            if q > best_q:
                best_q = q
                best_poly = s.nodes[path]
        if best_poly is None or not np.all(np.isfinite(self.jpos[j_parent])):
            return None, np.nan
        poly = best_poly.copy()
        poly[0] = self.jpos[j_parent]
        if end_is_tip:
            poly = np.vstack([poly, end_xyz[None]])
        else:
            poly[-1] = end_xyz
        if not np.all(np.isfinite(poly[-1])):
            return None, np.nan
        return _dedupe(poly), best_q


def _node_near_hint(s: TipSkeleton, topology: Topology, tips, j: int, hint: np.ndarray):
    reps = []
    for g in topology.groups(j):
        for i in _bits(g):
            if tips[i] >= 0 and s.tip_nodes[tips[i]] >= 0:
                reps.append(int(s.tip_nodes[tips[i]]))
                break
    if len(reps) < 2:
        return None
    best, bd = None, np.inf
    for a, b in combinations(reps, 2):
        path = tree_path(s.parent, a, b)
        d = np.linalg.norm(s.nodes[path] - hint, axis=1)
        k = int(np.argmin(d))
        if d[k] < bd:
            best, bd = path[k], d[k]
    return best


def _dedupe(poly: np.ndarray) -> np.ndarray:
    keep = np.ones(len(poly), dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(poly, axis=0)) > 0, axis=1)
    return poly[keep]
