"""Motion segmentation of vertex trajectories by spectral clustering (Tzionas & Gall 2016, section 4.1).

A mesh sequence with shared connectivity gives every vertex ``i`` a trajectory
``T_i = (V_i,1 .. V_i,T)``. Vertices of one rigid part keep their distances
(and the angles between their normals) over time; vertices of two parts that
turn against each other do not. The paper's steps:

1. sample ``n`` (1000) vertices uniformly over the surface;
2. an interval length ``dt`` (eq. 7 sets ``dt = 2 max_i,t ||V_i,t - V_i,t-1||``,
   millimetres taken as frames; here it spans a stretch of motion, see
   :func:`interval_length` and below);
3. ``d^v_ij``: the largest change of ``||V_i - V_j||`` within any interval of
   ``dt`` frames (eq. 8); ``d^n_ij``: the same for the angle between the
   normals (eq. 9, radians); ``d_ij = d^v_ij (d^n_ij + 1)`` (eq. 10: "adding 1
   to ``d^n`` was necessary since ``d^n`` can be close to zero despite large
   displacement changes");
4. affinity ``Phi_ij = exp(-lambda d_ij)`` (eq. 6, ``lambda = 0.1`` per mm);
5. normalised graph Laplacian ``L = I - D^-1/2 Phi D^-1/2`` (Ng, Jordan &
   Weiss 2002); ``k`` = number of eigenvalues below ``lambda_thr``;
6. k-means on the rows of the first ``k`` eigenvectors (rows normalised to
   unit length, as Ng et al.; started from centres as orthogonal as possible, their
   initialisation, from 32 deterministic starts, the least distortion kept);
7. every other vertex takes the label of its nearest sample along the surface.

Units and size. The paper's constants are for millimetres and objects of
0.2-0.4 m (spray, donkey, lamp, pipe). So that the defaults follow the subject
and not its units, distances are expressed in *reference millimetres*: the
subject's rest-frame bounding-box diagonal is mapped to ``reference_size``
(300 mm). ``lambda = 0.1`` is then applied as written (and eq. 7, when asked
for). For a 0.3 m subject in millimetres this is the paper's setting (the
interval aside, see below).

``lambda_thr``: 0.7 (default) when reasonably sized parts undergo a pronounced
movement; 0.98 for small parts with a small motion compared to the size of the
subject (the paper's "spray" handle, the rope) -- it over-segments, which adds
joints that can be ignored.

The interval (a decision): eq. 7 taken literally ties ``dt`` to the frame
rate -- the same motion at 5x the rate has 5x smaller steps, so a 5x shorter
interval in frames and 25x shorter in time -- and on slow, dense sequences
the distances cannot change within it. ``dt`` is therefore the number of
frames the fastest vertex takes to travel the reference size (300 reference
mm) at its top speed, ``dt = 300 / max ||V_i,t - V_i,t-1||``: resampling the
motion multiplies it by the same factor, and the segments stay
(``interval_motion=None`` restores eq. 7 as written). When ``dt`` exceeds
``2 x WINDOW_FRAMES`` (32), eqs. 8-9 run on every ``dt // 32``-th frame (the
trajectories are smooth, as the paper notes for eq. 7; at least 32 frames
per interval).

Three steps are ours (the paper is silent): a motion segment must be connected
on the surface, so a label whose vertices form several surface patches (two
legs that happen to move in step) is split, and patches smaller than
``min_segment`` of the vertices are merged into the neighbour they share the
longest boundary with; adjacent segments whose union still moves as one rigid
body (median residual of each of the two after the best rigid motion of both,
below ``rigid_tol`` of the size in every frame) are merged, so that over-segmentation (``lambda_thr = 0.98``, or
k-means splitting a rigid part) adds no joint that never bends; and a segment
that does not move rigidly is cut in two by the normalised cut of its own
samples when both halves are then at most half as far from rigid (the
eigenvalue count spends clusters on large parts and can leave a small part,
a tail, fused to its neighbour), recursively, before the merge runs again.
With the peel (below), what it leaves of several parts -- a segment whose best cut leaves
parts on both sides, neither half rigid nor half as far from rigid, as when the count
falls one short on an eigenvalue at ``lambda_thr`` -- is cut deeper (its halves cut
again, up to ``DEEPER_CUTS`` cuts) when every piece is then at most half as far from
rigid, and the pieces are peeled.
Last (with the peel), a skinned joint's blend zone cut off as a segment is
dissolved into its neighbours (``_dissolve_blends`` of :mod:`pipeline.rigid_parts`).
Labels are renumbered by decreasing size.

Hand-written because no library computes trajectory distances
(:mod:`pipeline.trajectory_distances`, eqs. 8-9); the eigen-decomposition (``numpy.linalg.eigh``),
k-means (``scipy.cluster.vq``) and the surface distances (``scipy.sparse.csgraph``) are library calls.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.cluster.vq import kmeans, vq
from scipy.sparse.csgraph import dijkstra

from pipeline.geodesic import edge_graph, mesh_edges
from pipeline.mesh_primitives import edge_components
from pipeline.rigid_parts import (
    _dissolve_blends,
    _max_min,
    _merge_rigid,
    _peel_nonrigid,
    _some_frames,
    _split_nonrigid,
    rigid_residual,
)
from pipeline.trajectory_distances import trajectory_distances

__all__ = [
    "REFERENCE_SIZE",
    "SMALL_MOTION_THR",
    "MIN_GAP",
    "Segmentation",
    "check_sequence",
    "subject_size",
    "sample_vertices",
    "interval_length",
    "spectral_clusters",
    "propagate_labels",
    "motion_segmentation",
]

log = logging.getLogger(__name__)

REFERENCE_SIZE = 300.0  # mm: the size of the paper's objects, where lambda = 0.1 / mm holds
INTERVAL_MOTION = REFERENCE_SIZE  # reference mm the fastest vertex travels within the interval
WINDOW_FRAMES = 32  # frames per interval at least, when a long interval lets eqs. 8-9 skip frames
#: the paper's eigenvalue threshold for small parts undergoing a small motion (section 5), used when the
#: one asked for finds a single cluster in a subject that does not move as one rigid body
SMALL_MOTION_THR = 0.98
#: the gap between the eigenvalues either side of ``lambda_thr`` below which the spectrum is read as having no
#: cluster structure there (``min_gap`` of :func:`motion_segmentation`, on for tracked templates)
MIN_GAP = 0.2
#: cuts deep the split looks, after the peel, into a segment of several parts (``_split_nonrigid``'s ``ahead``)
DEEPER_CUTS = 3


@dataclass(frozen=True, eq=False)
class Segmentation:
    """A motion segmentation of a mesh sequence.

    Attributes
    ----------
    labels : (V,) int ndarray
        Segment of every vertex, ``0 .. k-1`` by decreasing size.
    samples : (n,) int ndarray
        The sampled vertices.
    sample_labels : (n,) int ndarray
        Their spectral cluster (before propagation and the connectivity split).
    eigenvalues : (m,) float ndarray
        The smallest eigenvalues of the normalised Laplacian (ascending).
    k : int
        Number of spectral clusters (eigenvalues below ``lambda_thr``).
    interval : int
        ``dt`` in frames.
    lam : float
        ``lambda`` in the sequence's own units (per unit).
    lambda_thr : float
        The eigenvalue threshold used (``SMALL_MOTION_THR`` when the one asked for found one cluster
        in a subject that does not move rigidly; nan when not recorded).
    source : str
        ``"motion"`` (this module's spectral segmentation) or where given segments came from (``"limbs"``:
        :func:`pipeline.limb_segments.limb_segments`, :func:`pipeline.armature_files.limb_parts`); given
        segments have no samples, eigenvalues, ``interval`` or ``lam`` (0, nan).
    """

    labels: np.ndarray
    samples: np.ndarray
    sample_labels: np.ndarray
    eigenvalues: np.ndarray
    k: int
    interval: int
    lam: float
    lambda_thr: float = float("nan")
    source: str = "motion"

    @property
    def n_segments(self) -> int:
        return int(self.labels.max()) + 1 if len(self.labels) else 0


# --------------------------------------------------------------------------- validation


def check_sequence(vertices, faces, *, name: str = "vertices") -> tuple[np.ndarray, np.ndarray]:
    """Validate a mesh sequence with shared connectivity.

    Parameters
    ----------
    vertices : (T, V, 3) float ndarray
    faces : (F, 3) int ndarray

    Returns
    -------
    vertices : (T, V, 3) float ndarray
        float32 input stays float32 (long sequences), anything else becomes float64.
    faces : (F, 3) int64 ndarray
    """
    if isinstance(vertices, (list, tuple)) and vertices and len({np.shape(x) for x in vertices}) > 1:
        counts = sorted({len(x) for x in vertices})
        raise ValueError(
            f"{name}: the frames have different vertex counts ({', '.join(map(str, counts[:4]))}): "
            "a sequence without shared connectivity needs its template tracked first (stage track)"
        )
    v = np.asarray(vertices)
    if v.dtype not in (np.float32, np.float64):
        v = v.astype(np.float64)
    if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 1 or v.shape[1] < 4:
        raise ValueError(f"{name} must have shape (T, V, 3) with T >= 1 and V >= 4, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an (F, 3) integer array with F > 0, got {f.shape} {f.dtype}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= v.shape[1]:
        raise ValueError("faces reference vertices that do not exist")
    return v, f


def subject_size(vertices) -> float:
    """Bounding-box diagonal of the first frame (the subject's size)."""
    v = np.asarray(vertices)
    v0 = np.asarray(v[0] if v.ndim == 3 else v, dtype=np.float64)  # the first frame only (long sequences)
    return float(np.linalg.norm(v0.max(0) - v0.min(0)))


# --------------------------------------------------------------------------- geometry


def sample_vertices(points, n: int, *, start: int | None = None) -> np.ndarray:
    """``n`` vertices spread uniformly over a surface (Euclidean farthest-point sampling).

    Parameters
    ----------
    points : (V, 3) float ndarray
        Vertex positions (the rest frame).
    n : int
        Number of samples (capped at ``V``).
    start : int, optional
        First sample (default: the vertex farthest from the centroid).

    Returns
    -------
    (n,) int ndarray
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"points must have shape (V, 3) with V > 0, got {p.shape}")
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    n = min(int(n), len(p))
    first = int(np.argmax(((p - p.mean(0)) ** 2).sum(1))) if start is None else int(start)
    out = np.empty(n, dtype=np.int64)
    out[0] = first
    dmin = ((p - p[first]) ** 2).sum(1)
    x, y, z = (np.ascontiguousarray(p[:, k]) for k in range(3))  # one coordinate at a time: no (V, 3) temporaries
    d, w = np.empty(len(p)), np.empty(len(p))
    for i in range(1, n):
        nxt = int(np.argmax(dmin))
        out[i] = nxt
        np.subtract(x, x[nxt], out=d)
        np.multiply(d, d, out=d)
        for c in (y, z):  # summed in the order of ``((p - q) ** 2).sum(1)``: the same distances
            np.subtract(c, c[nxt], out=w)
            np.multiply(w, w, out=w)
            np.add(d, w, out=d)
        np.minimum(dmin, d, out=dmin)
    return out


def _sample_normals(v: np.ndarray, f: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """(T, n, 3) unit normals of the sampled vertices only (their incident faces); zero for a sample
    in no face, as :func:`pipeline.mesh_primitives.vertex_normals`."""
    pos = np.full(v.shape[1], -1, dtype=np.int64)
    pos[samples] = np.arange(len(samples))
    hit = pos[f] >= 0
    fi = np.flatnonzero(hit.any(1))
    fs = f[fi]
    out = np.zeros((v.shape[0], len(samples), 3))
    for t in range(v.shape[0]):
        fn = np.cross(v[t, fs[:, 1]] - v[t, fs[:, 0]], v[t, fs[:, 2]] - v[t, fs[:, 0]])
        for c in range(3):
            m = hit[fi, c]
            np.add.at(out[t], pos[fs[m, c]], fn[m])
    ln = np.linalg.norm(out, axis=2, keepdims=True)
    return out / np.where(ln > 0, ln, 1.0)


def interval_length(vertices, *, to_reference: float = 1.0, motion: float | None = INTERVAL_MOTION) -> int:
    """The interval of eqs. 8-9 in frames: a span of motion, not of frames.

    ``motion`` given (the default): the frames the fastest vertex takes to
    travel ``motion`` reference millimetres at its top speed,
    ``dt = motion / max_i,t ||V_i,t - V_i,t-1||``. The interval then covers
    the same stretch of motion whatever the frame rate: resampling a
    sequence at 5x the rate divides every step by 5 and multiplies ``dt``
    by 5 (see the module docstring).

    ``motion=None``: eq. 7 of Tzionas & Gall as written,
    ``dt = 2 max_i,t ||V_i,t - V_i,t-1||``, millimetres taken as frames.

    Parameters
    ----------
    vertices : (T, V, 3) float ndarray
        Trajectories (all vertices or a sample of them).
    to_reference : float
        Factor from the sequence's units to reference millimetres.
    motion : float or None
        Reference millimetres.

    Returns
    -------
    int
        Within ``1 .. max(T - 1, 1)``.
    """
    v = np.asarray(vertices)
    T = v.shape[0]
    if motion is not None and not (motion > 0 and np.isfinite(motion)):
        raise ValueError(f"motion must be > 0 or None, got {motion}")
    if T < 2:
        return 1
    chunk = max(1, 4_000_000 // max(v.shape[1] * 3, 1))  # frames at a time
    step = float(to_reference) * max(
        float(np.sqrt((np.diff(v[t : min(t + chunk, T - 1) + 1].astype(np.float64), axis=0) ** 2).sum(2)).max())
        for t in range(0, T - 1, chunk)
    )
    if motion is None:
        return int(np.clip(round(2.0 * step), 1, T - 1))
    if step <= 0:
        return T - 1
    return int(np.clip(round(float(motion) / step), 1, T - 1))


def spectral_clusters(
    affinity, *, lambda_thr: float = 0.7, max_clusters: int = 64, restarts: int = 32,
    k: int | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Spectral clustering with the number of clusters from the eigenvalues (Ng et al. 2002).

    Parameters
    ----------
    affinity : (n, n) float ndarray
        Symmetric, non-negative.
    lambda_thr : float
        ``k`` = number of eigenvalues of ``I - D^-1/2 A D^-1/2`` below it.
    max_clusters : int
        Upper bound of ``k``.
    restarts : int
        k-means runs, each from its own deterministic start (Ng et al.'s initialisation: centres
        as orthogonal as possible, here the rows farthest apart, :func:`_max_min`, begun at each
        of the first ``restarts`` rows in farthest-point order), Lloyd's steps until the distortion
        stops falling; the one with the smallest within-cluster distortion wins. No random draw:
        the same affinities give the same clusters.
    k : int, optional
        The number of clusters, in place of the eigenvalue count.

    Returns
    -------
    labels : (n,) int ndarray
    eigenvalues : (m,) float ndarray
        The ``m = min(n, max_clusters + 1)`` smallest eigenvalues.
    k : int
    """
    A = np.asarray(affinity, dtype=np.float64)
    if A.ndim != 2 or A.shape[0] != A.shape[1] or len(A) == 0:
        raise ValueError(f"affinity must be a square (n, n) matrix, got {A.shape}")
    if not (0 < lambda_thr < 2):
        raise ValueError(f"lambda_thr must be within (0, 2), got {lambda_thr}")
    n = len(A)
    d = A.sum(1)
    s = 1.0 / np.sqrt(np.maximum(d, 1e-300))
    L = np.eye(n) - s[:, None] * A * s[None, :]
    w, U = np.linalg.eigh(L)
    m = min(n, int(max_clusters) + 1)
    k = int(np.clip((w < lambda_thr).sum() if k is None else k, 1, min(int(max_clusters), n)))
    if k == 1:
        return np.zeros(n, dtype=np.int64), w[:m], 1
    F = U[:, :k]
    F = F / np.maximum(np.linalg.norm(F, axis=1, keepdims=True), 1e-12)
    best, best_cost = None, np.inf
    for first in _max_min(F, min(max(1, int(restarts)), n)):
        cent, _ = kmeans(F, F[_max_min(F, k, first)], thresh=1e-9)  # Lloyd until the distortion stops falling
        lab, _ = vq(F, cent)
        cost = float(((F - cent[lab]) ** 2).sum())
        if cost < best_cost:
            best, best_cost = lab, cost
    _, best = np.unique(best, return_inverse=True)
    return best.astype(np.int64), w[:m], k


def propagate_labels(points, faces, samples, sample_labels) -> np.ndarray:
    """Every vertex takes the label of its nearest sample along the surface.

    Distances are shortest paths on the edge graph; a vertex in a part of the
    mesh that holds no sample takes the label of the Euclidean-nearest one.

    Returns
    -------
    (V,) int ndarray
    """
    p = np.asarray(points, dtype=np.float64)
    samples = np.asarray(samples, dtype=np.int64)
    sample_labels = np.asarray(sample_labels, dtype=np.int64)
    g = edge_graph(p, mesh_edges(faces))
    dist, _, src = dijkstra(g, directed=False, indices=samples, min_only=True, return_predecessors=True)
    out = np.full(len(p), -1, dtype=np.int64)
    ok = np.isfinite(dist) & (src >= 0)
    lut = np.full(len(p), -1, dtype=np.int64)
    lut[samples] = sample_labels
    out[ok] = lut[src[ok]]
    if np.any(~ok):
        from scipy.spatial import cKDTree

        _, j = cKDTree(p[samples]).query(p[~ok])
        out[~ok] = sample_labels[j]
    return out


def _connected_segments(labels: np.ndarray, edges: np.ndarray, n_vertices: int, min_size: int) -> np.ndarray:
    """Split labels into surface-connected patches, merge tiny patches, renumber by size."""
    same = labels[edges[:, 0]] == labels[edges[:, 1]]
    comp = edge_components(edges[same], n_vertices)
    for _ in range(50):
        sizes = np.bincount(comp)
        small = np.flatnonzero((sizes > 0) & (sizes < min_size))
        if len(small) == 0 or (sizes > 0).sum() <= 1:
            break
        # shared boundary lengths between patches
        ca, cb = comp[edges[:, 0]], comp[edges[:, 1]]
        cross = ca != cb
        pairs = np.r_[np.c_[ca[cross], cb[cross]], np.c_[cb[cross], ca[cross]]]
        changed = False
        for c in small[np.argsort(sizes[small])]:
            nb = pairs[pairs[:, 0] == c, 1]
            nb = nb[sizes[nb] > 0]
            if len(nb) == 0:
                continue  # an isolated part of the mesh: keep it
            tgt = int(np.bincount(nb).argmax())
            comp[comp == c] = tgt
            sizes[tgt] += sizes[c]
            sizes[c] = 0
            changed = True
        if not changed:
            break
    uniq, inv = np.unique(comp, return_inverse=True)
    order = np.argsort(-np.bincount(inv), kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[inv].astype(np.int64)


def _small_motion(v, samples, size, eig, k, thr, rigid_tol, min_gap) -> str | None:
    """Why the paper's small-motion threshold should replace ``thr`` (None: it should not).

    One cluster while the subject does not move as one rigid body; or (``min_gap`` given) the
    eigenvalues crossing ``thr`` without a gap: the spectrum has no cluster structure at that scale
    (von Luxburg 2007, the eigengap), so the count below ``thr`` is no count of parts.
    """
    if thr >= SMALL_MOTION_THR or rigid_tol is None:
        return None
    if k == 1:
        res = rigid_residual(v[_some_frames(len(v))][:, samples])
        if res > float(rigid_tol) * size:
            return (f"one eigenvalue below the threshold {thr:g}, yet the subject does not move rigidly "
                    f"({100 * res / size:.2f} % of its size)")
        return None
    if min_gap is not None and k < len(eig) and eig[k] - eig[k - 1] < float(min_gap):
        return (f"the eigenvalues cross the threshold {thr:g} without a gap ({eig[k - 1]:.3f} -> {eig[k]:.3f}, "
                f"a gap under {float(min_gap):g})")
    return None


def motion_segmentation(
    vertices,
    faces,
    *,
    n_samples: int = 1000,
    lam: float = 0.1,
    lambda_thr: float = 0.7,
    reference_size: float = REFERENCE_SIZE,
    use_normals: bool = True,
    min_segment: float = 0.005,
    rigid_tol: float | None = 0.005,
    interval_motion: float | None = INTERVAL_MOTION,
    max_clusters: int = 64,
    peel_parts: bool = True,
    min_gap: float | None = None,
) -> Segmentation:
    """Segment a mesh sequence into rigidly moving parts (Tzionas & Gall 2016, section 4.1).

    Parameters
    ----------
    vertices : (T, V, 3) float ndarray
        Vertex trajectories: vertex ``i`` is the same surface point in every
        frame (shared connectivity).
    faces : (F, 3) int ndarray
    n_samples : int
        Sampled vertices for the affinity matrix (paper: 1000).
    lam : float
        ``lambda`` of ``exp(-lambda d)`` per reference millimetre (paper: 0.1).
    lambda_thr : float
        Eigenvalue threshold (paper: 0.7; 0.98 for small parts with small motion).
    reference_size : float
        The subject's size in reference millimetres (see the module docstring).
    use_normals : bool
        Include ``d^n`` (the paper's default); ``False`` uses ``d^v`` alone.
    min_segment : float
        Surface patches below this fraction of the vertices are merged into a neighbour.
    rigid_tol : float or None
        Adjacent segments whose union moves rigidly within this fraction of
        the subject's size (median residual of each, worst frame) are merged: a joint that never
        bends is no joint. ``None`` keeps the spectral segments.
    interval_motion : float or None
        The interval of eqs. 8-9 spans the frames in which some vertex moves
        this many reference millimetres (:func:`interval_length`); ``None``:
        eq. 7 as written (twice the largest step, millimetres as frames).
    max_clusters : int
    peel_parts : bool
        Peel parts fused to a segment off it (vertices its trimmed core motion leaves twice
        ``rigid_tol`` away, surface patches with a motion of their own), and dissolve skinned joints'
        blend zones cut off as segments. On for animated and scanned sequences; off for a tracked
        template, whose tracking noise both read as parts (docs/armature-format.md).
    min_gap : float or None
        When the eigenvalues cross ``lambda_thr`` with a smaller gap than this (``lambda_{k+1} -
        lambda_k``), the spectrum has no cluster structure at that threshold and the paper's
        small-motion threshold (``SMALL_MOTION_THR``) is used, with a warning. ``None`` (the default):
        only the one-cluster case does that. :data:`MIN_GAP` for a tracked template
        (:func:`pipeline.armature_files.armature_results`; docs/armature-format.md, "The eigengap").

    Returns
    -------
    Segmentation
        ``k == 1`` (one segment, a warning logged) when nothing bends or the
        sequence has a single frame.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, "blas"):  # many small products: threads only contend on a busy machine
        return _motion_segmentation(vertices, faces, n_samples, lam, lambda_thr, reference_size, use_normals,
                                    min_segment, rigid_tol, interval_motion, max_clusters, bool(peel_parts),
                                    min_gap)


def _motion_segmentation(vertices, faces, n_samples, lam, lambda_thr, reference_size, use_normals, min_segment,
                         rigid_tol, interval_motion, max_clusters, peel_parts, min_gap) -> Segmentation:
    v, f = check_sequence(vertices, faces)
    if not (lam > 0 and np.isfinite(lam)):
        raise ValueError(f"lam must be > 0, got {lam}")
    if not (reference_size > 0 and np.isfinite(reference_size)):
        raise ValueError(f"reference_size must be > 0, got {reference_size}")
    if int(n_samples) < 2:
        raise ValueError(f"n_samples must be >= 2, got {n_samples}")
    if not 0 <= min_segment < 0.5:
        raise ValueError(f"min_segment must be within [0, 0.5), got {min_segment}")
    if min_gap is not None and not 0 < min_gap < 2:
        raise ValueError(f"min_gap must be within (0, 2) or None, got {min_gap}")
    T, V, _ = v.shape
    size = subject_size(v)
    if not size > 0:
        raise ValueError("vertices: the subject has zero size")
    to_ref = float(reference_size) / size
    samples = sample_vertices(v[0], n_samples)
    dt = interval_length(v[:, samples], to_reference=to_ref, motion=interval_motion)
    lam_units = float(lam) * to_ref
    if T < 2:
        log.warning("one frame: no motion to segment, the whole mesh is one segment")
        return Segmentation(np.zeros(V, dtype=np.int64), samples, np.zeros(len(samples), dtype=np.int64),
                            np.zeros(1), 1, dt, lam_units)
    # a long interval on smooth trajectories: every ``stride``-th frame holds its extremes (at least
    # WINDOW_FRAMES frames per interval), for a fraction of the work
    stride = max(1, dt // WINDOW_FRAMES)
    frames = np.arange(0, T, stride)
    normals = _sample_normals(v[frames], f, samples) if use_normals else None
    dv, dn = trajectory_distances(v[frames][:, samples], normals, interval=max(1, int(round(dt / stride))))
    d = dv * (dn + 1.0) if use_normals else dv
    A = np.exp(-lam_units * d.astype(np.float64))
    sample_labels, eig, k = spectral_clusters(A, lambda_thr=lambda_thr, max_clusters=max_clusters)
    thr = float(lambda_thr)
    reason = _small_motion(v, samples, size, eig, k, thr, rigid_tol, min_gap)
    if reason:
        # the paper's threshold for small parts with a small motion (its spray handle; a starfish curling
        # its arms); the merge then folds what moves as one rigid body
        bend = rigid_residual(v[_some_frames(T)][:, samples]) / size
        log.warning("the motion shows no parts at the eigenvalue threshold %g (%s): the threshold for small parts "
                    "with small motion, %g, used instead; it finds parts in whatever little the surface bends, so the "
                    "segments are only as sure as that motion: %d frames, the surface %.2f %% of its size from one "
                    "rigid motion (median); more frames and more bending make them surer", thr, reason,
                    SMALL_MOTION_THR, T, 100 * bend)
        thr = SMALL_MOTION_THR
        sample_labels, eig, k = spectral_clusters(A, lambda_thr=thr, max_clusters=max_clusters)
    if k == 1:
        log.warning("nothing bends in this sequence (one eigenvalue below the threshold %g): one segment", thr)
        return Segmentation(np.zeros(V, dtype=np.int64), samples, sample_labels, eig, 1, dt, lam_units, thr)
    labels = propagate_labels(v[0], f, samples, sample_labels)
    edges = mesh_edges(f)
    labels = _connected_segments(labels, edges, V, max(1, int(round(min_segment * V))))
    if rigid_tol is not None:
        tol = float(rigid_tol) * size
        min_size = max(1, int(round(min_segment * V)))
        labels = _merge_rigid(labels, v, edges, tol)
        memo: dict = {}  # the split's cuts and residuals, for its second look below
        labels = _split_nonrigid(labels, v, samples, A, tol, min_size=min_size, memo=memo)
        labels = _connected_segments(labels, edges, V, min_size)
        if peel_parts:
            labels = _connected_segments(_peel_nonrigid(labels, v, edges, 2.0 * tol, min_size=min_size), edges, V,
                                         min_size)
            # what the peel left of several parts with no core (parts on both sides of every cut) cut deeper,
            # and the pieces peeled
            deeper = _split_nonrigid(labels, v, samples, A, tol, min_size=min_size, ahead=DEEPER_CUTS, memo=memo)
            if np.any(deeper != labels):
                cut = np.isin(labels, labels[deeper != labels])  # the vertices of the segments cut
                deeper = _connected_segments(deeper, edges, V, min_size)
                settled = set(np.unique(deeper[~cut]).tolist()) - set(np.unique(deeper[cut]).tolist())
                labels = _connected_segments(_peel_nonrigid(deeper, v, edges, 2.0 * tol, min_size=min_size,
                                                            settled=settled), edges, V, min_size)
        labels = _merge_rigid(labels, v, edges, tol)
        if peel_parts:
            labels = _dissolve_blends(_connected_segments(labels, edges, V, 1), v, edges)
            labels = _merge_rigid(_connected_segments(labels, edges, V, min_size), v, edges, tol)
        labels = _connected_segments(labels, edges, V, 1)
    if labels.max() == 0:
        log.warning("nothing bends in this sequence (the segments move rigidly together): one segment")
    return Segmentation(labels, samples, sample_labels, eig, k, dt, lam_units, thr)
