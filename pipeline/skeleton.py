"""A skeleton grown from one limb tip through level-set rings (Brostow et al. 2004, section 4.1).

From a seed tip the geodesic distance of every vertex is quantised into a fixed
number of bins (default 100). Each connected component of a bin is a *ring*;
its centroid is a skeleton node. Rings are linked along the progression of the
distance: a ring's parent is the ring holding the shortest-path predecessor
of its nearest vertex, so the nodes form a tree rooted at the seed that
branches where a ring splits (Fig. 2C-E, Fig. 3A). Every node carries the cost
``C_i`` of eq. 4 and the local frame ``(v1, v2, v1 x v2)`` of its ring.

Bins thinner than the mesh edges would cut rings into fragments; the bin width
is therefore never below ``min_bin_width`` (the caller passes about one mean
edge length), which keeps the default 100 bins on dense meshes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from pipeline.mesh_primitives import edge_components

__all__ = ["TipSkeleton", "level_set_rings", "ring_statistics", "grow_skeleton", "limb_quality", "limb_end", "limb_points"]


@dataclass(frozen=True)
class TipSkeleton:
    """Tree of ring nodes grown from one seed tip.

    Attributes
    ----------
    seed : int
        Index (into the frame's tips) of the seed tip.
    nodes : (R, 3) float ndarray
        Ring centroids.
    parent : (R,) int ndarray
        Parent ring, ``-1`` for the root (the seed's ring).
    cost : (R,) float ndarray
        ``C_i`` of eq. 4 (mean squared distance of the ring's points to its centroid).
    frame : (R, 3, 3) float ndarray
        Rows ``v1, v2, v1 x v2``: major, minor and central axis of each ring.
    count : (R,) int ndarray
        Vertices per ring.
    level : (R,) int ndarray
        Bin of each ring.
    tip_nodes : (n_tips,) int ndarray
        Ring holding each tip of the frame (``-1`` if unreached).
    """

    seed: int
    nodes: np.ndarray
    parent: np.ndarray
    cost: np.ndarray
    frame: np.ndarray
    count: np.ndarray
    level: np.ndarray
    tip_nodes: np.ndarray

    def to_dict(self) -> dict:
        return {
            "seed": int(self.seed),
            "nodes": self.nodes.tolist(),
            "parent": self.parent.tolist(),
            "cost": self.cost.tolist(),
            "frame": self.frame.reshape(-1, 9).tolist(),
            "count": self.count.tolist(),
            "level": self.level.tolist(),
            "tip_nodes": self.tip_nodes.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "TipSkeleton":
        return cls(
            seed=int(d["seed"]),
            nodes=np.asarray(d["nodes"], dtype=np.float64).reshape(-1, 3),
            parent=np.asarray(d["parent"], dtype=np.int64),
            cost=np.asarray(d["cost"], dtype=np.float64),
            frame=np.asarray(d["frame"], dtype=np.float64).reshape(-1, 3, 3),
            count=np.asarray(d["count"], dtype=np.int64),
            level=np.asarray(d["level"], dtype=np.int64),
            tip_nodes=np.asarray(d["tip_nodes"], dtype=np.int64),
        )


def level_set_rings(distance: np.ndarray, edges: np.ndarray, *, n_bins: int = 100, min_bin_width: float = 0.0):
    """Quantise a distance field into bins and split each bin into connected rings.

    Parameters
    ----------
    distance : (V,) float ndarray
        Geodesic distance from the seed (``inf`` = unreached, gets ring -1).
    edges : (E, 2) int ndarray
    n_bins : int
        Bins over ``[0, max distance]`` (fewer if they would be thinner than ``min_bin_width``).
    min_bin_width : float

    Returns
    -------
    ring : (V,) int ndarray
        Ring of each vertex (``-1`` unreached), rings numbered by increasing bin.
    ring_level : (R,) int ndarray
        Bin of each ring.
    width : float
        Bin width used.
    """
    if int(n_bins) < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    d = np.asarray(distance, dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ok = np.isfinite(d)
    n = len(d)
    dmax = float(d[ok].max()) if ok.any() else 0.0
    nb = int(n_bins)
    if min_bin_width > 0 and dmax > 0:
        nb = max(1, min(nb, int(dmax / min_bin_width)))
    width = dmax / nb if dmax > 0 else 1.0
    b = np.full(n, -1, dtype=np.int64)
    b[ok] = np.minimum((d[ok] / width).astype(np.int64), nb - 1)
    e = e[(b[e[:, 0]] >= 0) & (b[e[:, 1]] >= 0)]
    # an edge belongs to every band its distance interval crosses: links
    # (u, k) - (v, k) for each such band k
    lo = np.minimum(b[e[:, 0]], b[e[:, 1]])
    span = np.abs(b[e[:, 0]] - b[e[:, 1]]) + 1
    rep = np.repeat(np.arange(len(e)), span)
    k = lo[rep] + (np.arange(len(rep)) - np.repeat(np.cumsum(span) - span, span))
    valid = np.flatnonzero(ok)
    # node (v, k) -> id v + n * (k - b[v] + S): the vertex's own band is block S
    S = int(span.max()) - 1 if len(span) else 0
    if S <= 8:
        iu = e[rep, 0] + n * (k - b[e[rep, 0]] + S)
        iv = e[rep, 1] + n * (k - b[e[rep, 1]] + S)
        m = n * (2 * S + 1)
        own_id = valid + n * S
    else:  # very long edges: compact the ids
        own = valid * nb + b[valid]
        keys, inv = np.unique(np.concatenate([own, e[rep, 0] * nb + k, e[rep, 1] * nb + k]), return_inverse=True)
        m = len(keys)
        own_id = inv[: len(own)]
        iu = inv[len(own) : len(own) + len(rep)]
        iv = inv[len(own) + len(rep) :]
    lab = edge_components(np.stack([iu, iv], axis=1), m)
    lab_own = lab[own_id]
    # rings: components holding at least one vertex of their own bin, numbered by (bin, component)
    comp_ids, first = np.unique(lab_own, return_index=True)
    comp_bin = b[valid[first]]
    order = np.lexsort((comp_ids, comp_bin))
    new = np.empty(len(comp_ids), dtype=np.int64)
    new[order] = np.arange(len(comp_ids))
    ring = np.full(n, -1, dtype=np.int64)
    ring[valid] = new[np.searchsorted(comp_ids, lab_own)]
    return ring, comp_bin[order], width


def ring_statistics(points: np.ndarray, ring: np.ndarray, n_rings: int, *, weights=None):
    """Centroid, cost ``C_i`` (eq. 4) and frame of every ring, vectorised.

    ``C_i = (s1^2 + s2^2 + s3^2) / n`` with ``s`` the singular values of the
    ring's centred points: the mean squared distance to the centroid. The
    right singular vectors give ``v1, v2`` and the frame is completed with
    ``v1 x v2``. With ``weights`` (vertex areas) all sums are weighted, which
    is the same formula for a uniformly sampled surface.

    Parameters
    ----------
    points : (V, 3) float ndarray
    ring : (V,) int ndarray
        Ring of each point, ``-1`` = ignored.
    n_rings : int
    weights : (V,) float ndarray, optional

    Returns
    -------
    centroid : (R, 3) float ndarray
    cost : (R,) float ndarray
    frame : (R, 3, 3) float ndarray
    count : (R,) int ndarray
    """
    p = np.asarray(points, dtype=np.float64)
    r = np.asarray(ring, dtype=np.int64)
    sel = r >= 0
    p, r = p[sel], r[sel]
    w = np.ones(len(r)) if weights is None else np.asarray(weights, dtype=np.float64)[sel]
    w = np.maximum(w, 1e-300)
    count = np.bincount(r, minlength=n_rings)
    W = np.bincount(r, weights=w, minlength=n_rings)
    Wsafe = np.where(W > 0, W, 1.0)
    c = np.stack([np.bincount(r, weights=w * p[:, k], minlength=n_rings) for k in range(3)], axis=1) / Wsafe[:, None]
    q = p - c[r]
    cov = np.empty((n_rings, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            s = np.bincount(r, weights=w * q[:, i] * q[:, j], minlength=n_rings) / Wsafe
            cov[:, i, j] = s
            cov[:, j, i] = s
    evals, evecs = np.linalg.eigh(cov)  # ascending
    v1 = evecs[:, :, 2]
    v2 = evecs[:, :, 1]
    frame = np.stack([v1, v2, np.cross(v1, v2)], axis=1)
    cost = np.maximum(evals.sum(axis=1), 0.0)
    return c, cost, frame, count


def grow_skeleton(
    vertices: np.ndarray,
    edges: np.ndarray,
    graph: sp.csr_matrix,
    seed_vertex: int,
    *,
    tips=None,
    seed: int = 0,
    n_bins: int = 100,
    min_bin_width: float = 0.0,
    weights=None,
) -> TipSkeleton:
    """Grow the skeleton of one surface from one tip (Brostow et al. 2004, 4.1, Fig. 2C-E).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    edges : (E, 2) int ndarray
    graph : (V, V) sparse matrix
        :func:`pipeline.geodesic.edge_graph` of the same mesh.
    seed_vertex : int
        Vertex the skeleton grows from.
    tips : (n,) int ndarray, optional
        All tip vertices of the frame; their rings are recorded.
    seed : int
        Index of the seed among ``tips`` (stored as :attr:`TipSkeleton.seed`).
    n_bins, min_bin_width :
        See :func:`level_set_rings`.
    weights : (V,) float ndarray, optional
        Vertex areas for the ring statistics.

    Returns
    -------
    TipSkeleton
    """
    v = np.asarray(vertices, dtype=np.float64)
    n = len(v)
    if not (0 <= int(seed_vertex) < n):
        raise ValueError(f"seed_vertex must index a vertex 0..{n - 1}, got {seed_vertex}")
    d, pred = dijkstra(graph, directed=True, indices=int(seed_vertex), return_predecessors=True)
    ring, level, _ = level_set_rings(d, edges, n_bins=n_bins, min_bin_width=min_bin_width)
    R = len(level)
    nodes, cost, frame, count = ring_statistics(v, ring, R, weights=weights)
    # parent ring: ring of the predecessor of each ring's nearest vertex
    valid = np.flatnonzero(ring >= 0)
    order = valid[np.lexsort((d[valid], ring[valid]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = ring[order[1:]] != ring[order[:-1]]
    nearest = order[first]  # one vertex per ring, in ring order
    parent = np.full(R, -1, dtype=np.int64)
    pv = pred[nearest]
    has = pv >= 0
    parent[ring[nearest[has]]] = ring[pv[has]]
    tips_arr = np.asarray([] if tips is None else tips, dtype=np.int64)
    tip_nodes = ring[tips_arr] if len(tips_arr) else np.zeros(0, dtype=np.int64)
    return TipSkeleton(
        seed=int(seed),
        nodes=nodes,
        parent=parent,
        cost=cost,
        frame=frame,
        count=count,
        level=np.asarray(level, dtype=np.int64),
        tip_nodes=tip_nodes,
    )


def limb_quality(costs, norm: float) -> float:
    """Limb quality ``Q_L = N - sum_i C_i / norm`` (eq. 5).

    Parameters
    ----------
    costs : (N,) float array-like
        ``C_i`` of the limb's nodes.
    norm : float
        ``max(C_i)`` over all candidate skeletons of the frame (> 0).
    """
    c = np.asarray(costs, dtype=np.float64)
    if not norm > 0:
        raise ValueError(f"norm must be > 0, got {norm}")
    return float(len(c) - c.sum() / norm)


def limb_end(skeleton: TipSkeleton) -> int:
    """The ring where the seed's own limb ends: the first ring where the paths to the other
    tips part (their lowest common ancestor, the limb's junction with the body); with no other
    tip, the farthest ring.

    Parameters
    ----------
    skeleton : TipSkeleton

    Returns
    -------
    int
        Index into ``skeleton.nodes``.
    """
    par = skeleton.parent
    others = [int(x) for i, x in enumerate(skeleton.tip_nodes) if i != skeleton.seed and x >= 0]
    if not others:
        return int(np.argmax(skeleton.level))
    anc = None
    for o in others:
        chain = []
        x = o
        while x >= 0:
            chain.append(x)
            x = int(par[x])
        anc = chain[::-1] if anc is None else [a for a, c in zip(anc, chain[::-1]) if a == c]
    return int(anc[-1]) if anc else 0


def limb_points(skeleton: TipSkeleton, tip_point, fractions=(0.25, 0.5, 0.75)) -> np.ndarray:
    """Points along the seed's own limb, at fractions of its length from the tip.

    The limb is the chain from the seed's ring to :func:`limb_end`. Used to align whole skeletons, not only
    tips, when tracking correspondence.

    Parameters
    ----------
    skeleton : TipSkeleton
    tip_point : (3,) float array-like
        The seed tip (replaces the first ring centroid).
    fractions : sequence of float in [0, 1]

    Returns
    -------
    (len(fractions), 3) float ndarray
    """
    par = skeleton.parent
    end = limb_end(skeleton)
    path = []
    x = end
    while x >= 0:
        path.append(x)
        x = int(par[x])
    path = path[::-1]  # root .. end
    P = skeleton.nodes[path].copy()
    P[0] = np.asarray(tip_point, dtype=np.float64)
    seg = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    q = np.asarray(fractions, dtype=np.float64) * seg[-1]
    return np.stack([np.interp(q, seg, P[:, k]) for k in range(3)], axis=1)
