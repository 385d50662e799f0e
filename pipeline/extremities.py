"""Extremities ``E_t`` of a surface: protruding local maxima of the average geodesic distance.

Brostow et al. 2004, section 4.1: vertices are labelled with their average
geodesic distance (AGD) to all other points, approximated from a handful of
well-spread base points (Hilaga et al. 2001); local maxima of the AGD are
protrusions, and "knowledge of the expected size of interesting protrusions"
thresholds which local maxima are limb tips.

Here the size test is made exact and scale-free: a local maximum ``m`` is a tip
when it *protrudes* by at least ``h``, i.e. when the AGD must fall by ``h``
before ``m`` can be joined to any higher point of the surface (the
topological persistence of ``m`` in the AGD). ``h`` defaults to
``0.1 * sqrt(surface area)``, which is pose-invariant (isometric bending keeps
the area) and unit-free. On the Sumner & Popovic horse and cat, genuine limbs
protrude by 0.15-0.6 sqrt(area) and ears, hooves and mesh noise by < 0.035.

Two tests, cheapest first:

1. *Geodesic neighbourhood*: the AGD is 1-Lipschitz in geodesic distance, so
   every vertex within geodesic distance ``h`` of a tip lies in its
   ``h``-superlevel component: a tip is the maximum of its geodesic
   ``h``-ball. Candidates (1-ring maxima) failing this are dropped.
2. *Persistence*: the connected component of ``{AGD >= AGD(m) - h}`` holding
   ``m`` contains no higher vertex. The global maximum protrudes when the
   AGD range is at least ``h`` (a sphere has no tips).

Ties are broken by vertex index (simulation of simplicity), so flat regions
give one maximum, not none.

*Clear tips*: a tip that protrudes by at least ``CLEAR * h`` (the same
persistence test at 1.5 times the threshold: ``0.15 sqrt(area)`` by default, the
least that the horse's and the cat's genuine limbs protrude) is *clear*: a limb
for sure, where a tip that barely passes ``h`` may be a bump, a fold of a carved
hull or a ragged hand split in two. The take-level count of limbs uses it
(:mod:`pipeline.correspond`: a limb fused with the body in some frames is hidden
there, not absent).

*Near-equal maxima*: a candidate that passes test 1 (the maximum of its own
geodesic ``h``-ball, so at least ``h`` from any other such maximum) but fails
test 2 is a sub-protrusion of a limb that ends in several near-equal maxima (a
horse's nose and ears). It is kept as an *alternate* of the tip whose
``h``-superlevel component holds it (the lowest such tip): which of them a
noisy surface ranks highest changes from frame to frame, so the choice of the
limb's tip among them is left to the take (:mod:`pipeline.spine`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from pipeline.geodesic import (
    average_geodesic_distance,
    edge_graph,
    mesh_edges,
    proxy_average_geodesic_distance,
    validate_mesh,
    vertex_areas,
)
from pipeline.mesh_primitives import edge_components

__all__ = ["CLEAR", "Extremities", "find_extremities", "local_maxima", "protrudes"]

#: A tip that protrudes by at least this many times the threshold ``h`` is clear (module docstring).
CLEAR = 1.5


@dataclass(frozen=True)
class Extremities:
    """Limb tips of one surface.

    Attributes
    ----------
    vertices : (n,) int ndarray
        Tip vertex ids, by decreasing AGD.
    points : (n, 3) float ndarray
        Tip positions.
    agd : (V,) float ndarray
        Average geodesic distance of every vertex.
    base : (B,) int ndarray
        Base points used for the AGD.
    threshold : float
        Protrusion threshold ``h`` used (mesh units).
    alternates : tuple of (a_i,) int ndarray
        Per tip, the near-equal maxima of its limb (the maxima of their own
        ``h``-ball inside the tip's ``h``-superlevel component), by decreasing
        AGD; empty arrays when the limb ends in one maximum.
    clear : (n,) bool ndarray
        Tips that protrude by at least ``CLEAR * threshold`` (module docstring).
    """

    vertices: np.ndarray
    points: np.ndarray
    agd: np.ndarray
    base: np.ndarray
    threshold: float
    alternates: tuple = ()
    clear: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.vertices)


def _ranks(values: np.ndarray) -> np.ndarray:
    order = np.lexsort((np.arange(len(values)), values))
    rank = np.empty(len(values), dtype=np.int64)
    rank[order] = np.arange(len(values))
    return rank


def local_maxima(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Vertices greater than all their edge neighbours (ties broken by index).

    Parameters
    ----------
    values : (V,) float ndarray
    edges : (E, 2) int ndarray

    Returns
    -------
    (M,) int ndarray
        By decreasing value.
    """
    values = np.asarray(values, dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    rank = _ranks(values)
    nb = np.full(len(values), -1, dtype=np.int64)
    np.maximum.at(nb, e[:, 0], rank[e[:, 1]])
    np.maximum.at(nb, e[:, 1], rank[e[:, 0]])
    m = np.flatnonzero(rank > nb)
    return m[np.argsort(-rank[m])]


def protrudes(values: np.ndarray, edges: np.ndarray, vertex: int, height: float) -> bool:
    """Whether ``vertex`` is a maximum of persistence >= ``height`` (slow exact test).

    True when the connected component of ``{values >= values[vertex] - height}``
    (over ``edges``) containing ``vertex`` holds no higher vertex (ties broken
    by index); for the global maximum, when the value range is >= ``height``.
    """
    values = np.asarray(values, dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    rank = _ranks(values)
    if rank[vertex] == len(values) - 1:
        return bool(values.max() - values.min() >= height)
    keep = values >= values[vertex] - height
    ee = e[keep[e[:, 0]] & keep[e[:, 1]]]
    lab = edge_components(ee, len(values))
    comp = lab == lab[vertex]
    return not bool(np.any(rank[comp] > rank[vertex]))


def find_extremities(
    vertices,
    faces,
    *,
    n_base: int = 24,
    min_protrusion: float = 0.1,
    protrusion: float | None = None,
    agd_proxy: int | None = None,
    graph: sp.csr_matrix | None = None,
    edges: np.ndarray | None = None,
) -> Extremities:
    """Find the limb tips ``E_t`` of one surface (Brostow et al. 2004, section 4.1).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
        One connected mesh (see :func:`pipeline.geodesic.largest_component`).
    n_base : int
        Base points for the AGD (geodesic farthest-point sampling).
    min_protrusion : float
        Protrusion threshold as a fraction of ``sqrt(surface area)``.
    protrusion : float, optional
        Absolute threshold in mesh units; overrides ``min_protrusion``.
    agd_proxy : int, optional
        On meshes of more than ``3 * agd_proxy`` vertices, compute the AGD on a
        proxy of about ``agd_proxy`` surface patches
        (:func:`pipeline.geodesic.proxy_average_geodesic_distance`; tips then
        move by about one patch size). Default: always exact.
    graph, edges : optional
        Precomputed :func:`pipeline.geodesic.edge_graph` / ``mesh_edges``.

    Returns
    -------
    Extremities
        Possibly empty (a sphere-like blob has no protrusion).
    """
    v, f = validate_mesh(vertices, faces)
    if int(n_base) < 2:
        raise ValueError(f"n_base must be >= 2, got {n_base}")
    h = _protrusion_height(v, f, min_protrusion=min_protrusion, protrusion=protrusion)
    if agd_proxy is not None and int(agd_proxy) < 1:
        raise ValueError(f"agd_proxy must be >= 1, got {agd_proxy}")
    if edges is None:
        edges = mesh_edges(f)
    if graph is None:
        graph = edge_graph(v, edges)
    if agd_proxy is not None and len(v) > 3 * int(agd_proxy):
        agd, base = proxy_average_geodesic_distance(v, edges, n_base=n_base, n_proxy=int(agd_proxy))
    else:
        agd, base = average_geodesic_distance(graph, n_base=n_base, vertices=v)
    finite = np.isfinite(agd)
    if not finite.all():  # disconnected input: only the reached part counts
        agd = np.where(finite, agd, -np.inf)
    rank = _ranks(agd)
    cand = local_maxima(agd, edges)
    cand = cand[np.isfinite(agd[cand])]
    cand = _hop_prefilter(graph, rank, cand, h)
    survivors = _ball_maxima(graph, rank, cand, h)
    top = int(np.argmax(rank))  # the global maximum persists when the whole field spans h
    tips = np.asarray([m for m in survivors
                       if (bool(agd[finite].max() - agd[finite].min() >= h) if m == top
                           else _persists(agd, rank, edges, m, h))], dtype=np.int64)
    rejected = np.asarray([m for m in survivors if m not in set(tips.tolist())], dtype=np.int64)
    alternates = _alternates(agd, edges, tips, rejected, h)
    spread = float(agd[finite].max() - agd[finite].min())
    clear = np.array([spread >= CLEAR * h if m == top else _persists(agd, rank, edges, int(m), CLEAR * h)
                      for m in tips], dtype=bool)
    return Extremities(vertices=tips, points=v[tips], agd=agd, base=base, threshold=h, alternates=alternates,
                       clear=clear)


# --------------------------------------------------------------------------- find_extremities, step by step


def _protrusion_height(v: np.ndarray, f: np.ndarray, *, min_protrusion: float, protrusion: float | None) -> float:
    """The threshold ``h`` in mesh units: absolute, or ``min_protrusion * sqrt(area)``."""
    if protrusion is not None:
        if not (protrusion > 0):
            raise ValueError(f"protrusion must be > 0, got {protrusion}")
        return float(protrusion)
    if not (min_protrusion > 0):
        raise ValueError(f"min_protrusion must be > 0, got {min_protrusion}")
    area = float(vertex_areas(v, f).sum())
    return float(min_protrusion) * np.sqrt(area)


def _hop_prefilter(graph: sp.csr_matrix, rank: np.ndarray, cand: np.ndarray, h: float) -> np.ndarray:
    """Exact pre-filter: a tip is the maximum of every k-hop neighbourhood that fits in its geodesic
    h-ball (k * longest edge <= h); vectorised max-dilations over the CSR rows drop the small bumps
    before any Dijkstra."""
    if not (len(cand) > 8 and graph.nnz):
        return cand
    g = graph.tocsr()
    longest = float(np.max(g.data))
    max_hops = int(h // longest) if longest > 0 else 0
    rows = np.flatnonzero(np.diff(g.indptr) > 0)
    starts = g.indptr[rows]
    nb = rank.copy()
    for _ in range(min(max_hops, 64)):
        grown = nb.copy()
        grown[rows] = np.maximum(nb[rows], np.maximum.reduceat(nb[g.indices], starts))
        nb = grown
        cand = cand[nb[cand] == rank[cand]]
        if len(cand) <= 8:
            break
    return cand


def _ball_maxima(graph: sp.csr_matrix, rank: np.ndarray, cand: np.ndarray, h: float) -> list[int]:
    """Candidates that are the maximum of their geodesic h-ball (Dijkstra in chunks of sources)."""
    survivors = []
    chunk = max(1, int(4_000_000 // max(graph.shape[0], 1)))
    for i in range(0, len(cand), chunk):
        c = cand[i : i + chunk]
        d = dijkstra(graph, directed=True, indices=c, limit=h)
        for j, m in enumerate(c):
            ball = np.isfinite(d[j])
            if not np.any(rank[ball] > rank[m]):
                survivors.append(int(m))
    return survivors


def _superlevel_labels(agd: np.ndarray, edges: np.ndarray, level: float) -> np.ndarray:
    """Connected-component label of every vertex in the super-level set ``agd >= level`` (edges
    with both ends in it); a vertex outside the set is a component of its own."""
    n = len(agd)
    keep = agd >= level
    ee = edges[keep[edges[:, 0]] & keep[edges[:, 1]]]
    return edge_components(ee, n)


def _persists(agd: np.ndarray, rank: np.ndarray, edges: np.ndarray, m: int, h: float) -> bool:
    """Persistence test: no higher vertex in ``m``'s component of the super-level set ``agd >= agd[m] - h``."""
    lab = _superlevel_labels(agd, edges, agd[m] - h)
    return not bool(np.any(rank[lab == lab[m]] > rank[m]))


def _alternates(agd: np.ndarray, edges: np.ndarray, tips: np.ndarray, rejected: np.ndarray, h: float) -> tuple:
    """Each rejected ball maximum as an alternate of the lowest tip whose ``h``-superlevel component holds it."""
    owner = np.full(len(rejected), -1, dtype=np.int64)
    for i in np.argsort(agd[tips], kind="stable") if len(rejected) else []:  # lowest tip first
        free = owner < 0
        if not free.any():
            break
        m = int(tips[i])
        lab = _superlevel_labels(agd, edges, agd[m] - h)
        owner[free & (lab[rejected] == lab[m])] = i
    return tuple(rejected[owner == i] for i in range(len(tips)))
