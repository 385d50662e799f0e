"""Template tracking: one mesh deformed frame by frame onto the data (Tzionas & Gall 2016, §3.2).

The template's vertices ``V`` are moved to minimise, per frame, the paper's energy (eq. 1)

    E(V) = E_smooth(V) + gamma * (E_model->data(V) + E_data->model(V))

- ``E_model->data`` (eq. 2): every *visible* vertex ``V_i`` and its closest data point ``X_i``,
  ``sum ||V_i - X_i||^2``;
- ``E_data->model``: every data point ``X_j`` and its closest vertex ``V_i``, ``sum ||V_i - X_j||^2``;
  both kinds of pair are dropped when the normals differ by more than 45 degrees or the points
  are further apart than a distance gate (the paper's 10 mm for objects of about 30 cm, here
  scaled with the template's size, :func:`default_gate`);
- ``E_smooth`` (eq. 4): ``sum_i ||L(V_i) - L(V_i,t-1)||^2`` with the cotangent Laplacian of
  eq. 5, ``L(V_i) = 1 / (2 |A_i|) sum_j (cot a_ij + cot b_ij) (V_j - V_i)``, ``|A_i|`` half the
  sum of the areas of the triangles around ``V_i`` (the paper's approximation of the Voronoi
  cell), computed once on the template;
- ``gamma`` from the template's triangles (the paper's finding, §5): 0.05 when their mean area
  is above 10 mm^2, 0.005 below (:func:`choose_gamma`).

Every round of correspondences gives a linear least-squares problem whose normal equations

    (L^T L + gamma (D + rho I) + eps I) V = L^T L V_{t-1} + gamma (B + rho P) + eps V_0

share one matrix for x, y and z; only the diagonal (how many pairs each vertex has) changes
between rounds and frames. A tiny ``eps`` (1e-4 gamma) towards the round's start ``V_0``
keeps components without any data well posed. The system is solved by sparse Cholesky
(LDL^T): the fill-reducing ordering and elimination tree are computed once per take
(:class:`~pipeline.cholesky.CholeskySystem`; QDLDL when installed, else scipy's SuperLU, which cannot keep
them); the first round of a frame refactors numerically, the later rounds (whose pairs, so
diagonal, change little) solve by conjugate gradients preconditioned with that factor,
refactoring only when CG does not reach 1e-5 in 6 steps. 15 rounds per frame, each frame started from the previous one (or from
a caller's guess such as a skinned pose).

Where this departs from the letter of the paper, and why (the measurements behind each point:
docs/tracking.md, "Where the tracker departs from the paper"; the patch functions named here are
:mod:`pipeline.tracking_patches`'s):

- *Point-to-plane through rigid patches.* Point-to-point pairs carry only the normal part of a
  displacement, so the unseen half of an object was extrapolated wrongly and a static object
  thinned. The template is cut into patches (:func:`surface_patches`); each round every patch
  gets the rigid motion that best fits its pairs point-to-plane (:func:`patch_rigid_motion`),
  ``P`` is every vertex moved with its patch, a pair's target is ``P_i`` moved along the data
  normal onto the data point (``B``), and every vertex is drawn to ``P_i`` with weight ``rho``
  (``rigidity``, 0.5 of a pair).
- *Only the motions the pairs see.* A patch's rigid motion is solved in the directions its
  point-to-plane pairs constrain (``cutoff``): a cylinder's twist about its own axis is invisible
  to them and, left free, depth noise twisted it.
- *The previous frame's shape, for a single view* (``prior="previous"``): the prior's shape is the
  previous frame's, placed patch by patch onto the round's start (:func:`patch_align`) and moved
  with the patch's motion, so a shape error made in one round is not kept by the next. The
  patches overlap and are blended (:func:`blended_patches`, :func:`blended_align`): with a
  partition every patch boundary is a free hinge. On whole surfaces (multi-view) it is opt-in
  (:func:`pipeline.track.track_results`, ``shape_memory``).
- *A prediction of every frame* (:func:`predict_motion`): every patch repeats the rigid motion
  of the two frames before, restricted to the motions the data constrained on the previous
  frame (:func:`patch_constraints`), since along unseen directions an error would repeat and grow.
- *A second start where the prediction is out of reach* (:func:`choose_start`, multi-view with a
  spine): patches with many vertices out of the gate's reach take, when the frame's data explain
  it better (:func:`start_residuals`), the previous frame moved by the spine's skinned step, the
  previous frame itself or half the predicted step (a swinging limb slows and turns back where
  constant velocity carries it on; :func:`pipeline.track_frames.slowed_starts`).
- *Vertices the data sees.* Model->data pairs only for vertices that project onto a pixel with
  data (:func:`pipeline.rgbd_preprocess.visible_vertices`): near the silhouette a depth camera
  returns nothing usable.
- The contour term (eq. 3) enters as a pair whose "plane" contains the depth edge's ray
  (``contour=``; optional, as in the paper).
- *Colour feature tracks* (``tracks=``, beyond the paper): where the colour image says a vertex
  went (:func:`pipeline.colour_tracks.colour_tracks`), as two pairs across the viewing ray;
  point-to-plane pairs cannot see a round part turn about its own axis.

What is hand-written and why: the cotangent Laplacian and the pair gating are a few lines
of numpy on top of scipy's KD-tree; no maintained package offers the paper's energy.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from pipeline.cholesky import CholeskySystem
from pipeline.mesh_primitives import check_mesh, vertex_normals
from pipeline.mesh_primitives import scatter_add as _scatter_add
from pipeline.mesh_primitives import summing_matrix as _summing
from pipeline.mesh_primitives import triangle_areas as _triangle_areas
from pipeline.skinning import cotangent_laplacian as stiffness_laplacian
from pipeline.tracking_patches import (
    _blended_align,
    _blended_patches,
    _check_labels,
    _cover_sums,
    _patch_align,
    _patch_rigid_motion,
    _shape_of,
    _umbrella,
    patch_constraints,
    predict_motion,
    surface_patches,
)

__all__ = [
    "TrackingError",
    "cotangent_laplacian",
    "mean_triangle_area",
    "choose_gamma",
    "default_gate",
    "closest_pairs",
    "FrameFit",
    "TemplateTracker",
    "start_residuals",
    "choose_start",
]

COS_45 = math.cos(math.radians(45.0))
PAPER_GATE_MM = 10.0
PAPER_OBJECT_MM = 300.0  # size of the paper's objects (pipe, lamp) the 10 mm gate was set for
ROUNDS = 15


class TrackingError(RuntimeError):
    """The data cannot be explained by the template (e.g. too few pairs to place it)."""


def mean_triangle_area(vertices, faces) -> float:
    """Mean triangle area of a mesh (mm^2 when the mesh is in mm)."""
    v, f = check_mesh(vertices, faces, min_vertices=4, min_faces=1)
    return float(_triangle_areas(v, f).mean())


def choose_gamma(vertices, faces) -> float:
    """The data weight ``gamma_def`` the paper found best for a template (Tzionas & Gall 2016, §5).

    0.05 for templates whose triangles are larger than 10 mm^2 on average ("donkey", "lamp"),
    0.005 for smaller ones ("spray", "pipe"). Vertices in millimetres.
    """
    return 0.05 if mean_triangle_area(vertices, faces) > 10.0 else 0.005


def default_gate(vertices) -> float:
    """Distance gate of the pairs: the paper's 10 mm, scaled by the template's size / 300 mm.

    The size is the diagonal of the template's bounding box; the gate never drops below 10 mm.
    """
    v = np.asarray(vertices, dtype=np.float64)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    return max(PAPER_GATE_MM, PAPER_GATE_MM * diag / PAPER_OBJECT_MM)


def cotangent_laplacian(vertices, faces) -> sp.csr_matrix:
    """Cotangent Laplacian of eq. 5 (Tzionas & Gall 2016; Sorkine 2005).

    ``(L V)_i = 1 / (2 |A_i|) sum_{j in N1(i)} (cot a_ij + cot b_ij) (V_j - V_i)``
    with ``|A_i|`` half the sum of the areas of the triangles around vertex ``i``: the
    cotangent stiffness of :func:`pipeline.skinning.cotangent_laplacian` (cotangents clipped
    to ``[-1e3, 1e3]`` for the slivers of marching cubes), scaled per vertex by that area.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray

    Returns
    -------
    (V, V) scipy.sparse.csr_matrix
        Rows of isolated vertices are zero.
    """
    v, f = check_mesh(vertices, faces, min_vertices=4, min_faces=1)
    n = v.shape[0]
    stiffness = stiffness_laplacian(v, f)  # -(cot a + cot b) / 2 off the diagonal
    area = 0.5 * _scatter_add(f.ravel(), np.repeat(_triangle_areas(v, f), 3), n)
    scale = np.where(area > 0, 1.0 / (2.0 * np.maximum(area, 1e-300)), 0.0)
    return sp.csr_matrix(sp.diags(scale) @ (-2.0 * stiffness))


def closest_pairs(
    src: np.ndarray,
    src_normals: np.ndarray,
    dst_tree: cKDTree,
    dst_normals: np.ndarray,
    *,
    gate: float,
    cos_angle: float = COS_45,
) -> tuple[np.ndarray, np.ndarray]:
    """Closest-point pairs from ``src`` to the points of ``dst_tree``, gated.

    A pair is kept when the points are closer than ``gate`` and their normals differ by at
    most ``arccos(cos_angle)`` (45 degrees in the paper).

    Returns
    -------
    src_index, dst_index : (P,) int ndarray
    """
    if len(src) == 0 or dst_tree.n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d, j = dst_tree.query(src, distance_upper_bound=gate)
    ok = np.isfinite(d)
    i = np.flatnonzero(ok)
    j = j[ok]
    agree = np.einsum("ij,ij->i", src_normals[i], dst_normals[j]) >= cos_angle
    return i[agree], j[agree]


def _check_tracks(tracks, n: int):
    if tracks is None:
        return None
    if len(tracks) not in (2, 3):
        raise ValueError("tracks must be (index, targets) or (index, targets, rays)")
    ti, tx = np.asarray(tracks[0]), np.asarray(tracks[1], dtype=np.float64)
    if ti.ndim != 1 or not np.issubdtype(ti.dtype, np.integer) or tx.shape != (len(ti), 3):
        raise ValueError(f"tracks must be ((T,) int, (T, 3) float), got {ti.shape} {ti.dtype} and {tx.shape}")
    if len(ti) and (ti.min() < 0 or ti.max() >= n):
        raise ValueError("tracks index vertices that do not exist")
    rays = None if len(tracks) == 2 else np.asarray(tracks[2], dtype=np.float64)
    if rays is not None and rays.shape != tx.shape:
        raise ValueError(f"tracks' rays must have shape {tx.shape}, got {rays.shape}")
    return ti.astype(np.int64), tx, rays


def _tangent_pairs(V, vn, ti, tx, rays, *, gate: float):
    """Feature tracks as pairs along two directions: across their viewing ray when given (what
    the image measures), else the vertex's tangent plane. Kept: those within the gate and within
    3 times the tracks' median distance (a track that jumped to another part is not a pair)."""
    dist = np.linalg.norm(tx - V[ti], axis=1)
    near = dist < min(gate, 3.0 * float(np.median(dist))) if len(dist) else dist < gate
    ti, tx = ti[near], tx[near]
    n = vn[ti] if rays is None else rays[near]
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    t2 = np.cross(n, t1)
    return np.concatenate([ti, ti]), np.concatenate([tx, tx]), np.concatenate([t1, t2])


@dataclass
class FrameFit:
    """One tracked frame.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        The template's vertices on this frame, in template order.
    model_pairs, data_pairs : int
        Pairs of the last round (model->data, data->model).
    residual : float
        RMS distance of the last round's pairs, mm.
    rounds : int
    """

    vertices: np.ndarray
    model_pairs: int
    data_pairs: int
    residual: float
    rounds: int = ROUNDS
    history: list = field(default_factory=list)
    constrained: np.ndarray | None = None


class TemplateTracker:
    """Tracks one template through a take: caches its Laplacian and the factorisation's analysis.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Template (rest) vertices, mm.
    faces : (F, 3) int ndarray
    gamma : float, optional
        Weight of the data terms; default :func:`choose_gamma`.
    gate : float, optional
        Distance gate of the pairs, mm; default :func:`default_gate`.
    rounds : int, optional
        Rounds of correspondences and solve per frame (the paper's 15).
    backend : {"auto", "qdldl", "splu"}
        Sparse Cholesky backend (:class:`CholeskySystem`).
    point_to_plane : bool, optional
        Pairs through patch-rigid motions (see the module docstring); False: point-to-point.
    rigidity : float, optional
        Weight of the patch-rigid prior, in pairs (0.5).
    patch_size : float, optional
        Patch diameter, mm (default a quarter of the template's bounding-box diagonal).
    prior : {"round", "previous"}
        Shape the rigid prior keeps: the round's start (whole-surface data), or the previous
        frame's, placed patch by patch (single-view data; see the module docstring).
    align_size : float, optional
        Diameter of the patches that place the previous frame's shape, mm (default 15 % of the
        template's bounding-box diagonal; only with ``prior="previous"``).
    blend : bool, optional
        Overlapping, blended patches place the previous frame's shape (:func:`blended_align`,
        default True) instead of a partition (:func:`patch_align`, False); only with
        ``prior="previous"``, and only the one chosen is built.
    patch_labels : (V,) int ndarray, optional
        The template's limb (``0, 1, ...``) or body (``-1``) of every vertex: no rigid patch spans
        two parts, the body is one patch and every limb is cut on its own grid
        (:func:`surface_patches`, ``labels``). Default: the patches follow the surface alone.

    Notes
    -----
    Reused between the rounds and frames of a take: the Laplacian ``L``, ``L^T L`` and its
    upper-triangular pattern (each factorisation only writes the new diagonal into it), the
    fill-reducing ordering and elimination tree of the Cholesky factorisation, the patches and
    the sparse summing matrices of the sums over fixed indices (vertex normals from the
    triangles, patch centroids and per-patch Kabsch: one sparse product each, the same sums
    as ``bincount``'s, bit for bit; also those of the blended patches that place the previous
    frame's shape, and their weights), the prediction's averaging matrix (:attr:`smoother`,
    :meth:`predict`), and the frame's KD-tree over the data; between the rounds
    of a frame, the numeric factor of its first round (as CG preconditioner, whose residual is
    tested before it is preconditioned, so the step that converges costs no triangular
    solve); per round only the KD-tree over the moved vertices, the pairs and the patch
    motions are redone.
    """

    #: How the rigid patches are cut (:func:`pipeline.tracking_patches.surface_patches`): recorded in
    #: ``track.json``, so that frames tracked with an earlier rule (``"grid"``: one seed per cell of a
    #: grid from the template's lowest corner) are tracked again rather than resumed or reused.
    patch_rule = "surface"

    def __init__(self, vertices, faces, *, gamma: float | None = None, gate: float | None = None,
                 rounds: int = ROUNDS, backend: str = "auto", point_to_plane: bool = True, rigidity: float = 0.5,
                 patch_size: float | None = None, prior: str = "round", align_size: float | None = None,
                 blend: bool = True, patch_labels=None):
        v, f = check_mesh(vertices, faces, min_vertices=4, min_faces=1)
        if prior not in ("round", "previous"):
            raise ValueError(f"prior must be 'round' or 'previous', got {prior!r}")
        for name, value in (("patch_size", patch_size), ("align_size", align_size)):
            if value is not None and (isinstance(value, bool) or not (isinstance(value, (int, float, np.integer,
                                      np.floating)) and math.isfinite(value) and value > 0)):
                raise ValueError(f"{name} must be a positive number (mm), got {value!r}")
        if not isinstance(blend, (bool, np.bool_)):
            raise ValueError(f"blend must be True or False, got {blend!r}")
        self.prior = prior
        self.blend = bool(blend)
        self.point_to_plane = bool(point_to_plane)
        if not (isinstance(rigidity, (int, float)) and rigidity >= 0):
            raise ValueError(f"rigidity must be a number >= 0, got {rigidity!r}")
        self.rigidity = float(rigidity)
        if gamma is not None and not (isinstance(gamma, (int, float)) and math.isfinite(gamma) and gamma > 0):
            raise ValueError(f"gamma must be a positive number, got {gamma!r}")
        if gate is not None and not (isinstance(gate, (int, float)) and math.isfinite(gate) and gate > 0):
            raise ValueError(f"gate must be a positive number (mm), got {gate!r}")
        if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 1:
            raise ValueError(f"rounds must be a positive integer, got {rounds!r}")
        self.template = v
        self.faces = f
        self.gamma = float(choose_gamma(v, f) if gamma is None else gamma)
        self.gate = float(default_gate(v) if gate is None else gate)
        self.rounds = int(rounds)
        self.L = cotangent_laplacian(v, f)
        self.LtL = sp.csr_matrix(self.L.T @ self.L)
        self.eps = 1e-4 * self.gamma
        self.system = CholeskySystem(self.LtL, backend=backend)
        size = float(np.linalg.norm(np.ptp(v, axis=0)))
        self.patch_size = float(patch_size) if patch_size is not None else 0.25 * size
        self.patch_labels = None if patch_labels is None else _check_labels(patch_labels, len(v), "patch_labels")
        self.patches, self.patch_component = surface_patches(v, f, self.patch_size, labels=self.patch_labels)
        self.align_size = float(align_size) if align_size is not None else 0.15 * size
        # the previous shape's placement: blended patches, or a partition (only what is used is built)
        self.align_cover = _blended_patches(v, f, self.align_size) if prior == "previous" and self.blend else None
        self.align_patches = surface_patches(v, f, self.align_size)[0] if prior == "previous" and not self.blend else None
        # summing matrices of the per-round sums over fixed indices (the same sums as bincount's, in one product)
        self._corner_sum = _summing(f.ravel(), len(v))
        self._patch_sum = _summing(self.patches, int(self.patches.max()) + 1)
        self._align_sum = None if self.align_patches is None else _summing(self.align_patches, int(self.align_patches.max()) + 1)
        self._smoother = None  # the prediction's averaging: built on first use
        self._cover_sums = None if self.align_cover is None else _cover_sums(self.align_cover, len(v))

    def _solve_round(self, V, pv, px, pn, smooth_rhs, start, first, prev=None, anchor=None):
        """One linear solve of the energy for fixed pairs (see the module docstring); ``anchor``:
        (positions (V, 3), weight in pairs) every vertex is also drawn to."""
        n = self.n_vertices
        if self.point_to_plane:
            # the prior's shape: the round's start, or the previous frame's shape placed patch by patch onto it
            if self.align_cover is not None:
                base = _blended_align(prev, V, self.align_cover, self._cover_sums)
            else:
                base = V if self.align_patches is None else _patch_align(prev, V, self.align_patches, self._align_sum)
            P = _patch_rigid_motion(base, pv, px, pn, self.patches, self._patch_sum, fallback=start,
                                    component=self.patch_component)
            # the data fix each paired vertex along the data normal; tangentially it follows its patch
            tx = P[pv] + pn * np.einsum("ij,ij->i", px - P[pv], pn)[:, None]
        else:
            P, tx = V, px
        counts = np.bincount(pv, minlength=n).astype(np.float64)
        target = _scatter_add(pv, tx, n)
        rw = self.rigidity if self.point_to_plane else 0.0
        d = self.gamma * (counts + rw) + self.eps
        rhs = smooth_rhs + self.gamma * (target + rw * P) + self.eps * V
        if anchor is not None:
            d = d + self.gamma * anchor[1]
            rhs = rhs + self.gamma * anchor[1] * anchor[0]
        if first:
            self.system.factor(d)
            return self.system.solve(rhs)
        return self.system.solve_near(d, rhs, V)

    def _check_anchor(self, anchor):
        if anchor is None:
            return None
        try:
            pos, w = anchor
        except (TypeError, ValueError):
            raise ValueError("anchor must be (positions (V, 3), weight)") from None
        pos = np.asarray(pos, dtype=np.float64)
        if pos.shape != self.template.shape or not np.all(np.isfinite(pos)):
            raise ValueError(f"anchor positions must be finite with shape {self.template.shape}, got {pos.shape}")
        if isinstance(w, bool) or not isinstance(w, numbers.Real) or not (math.isfinite(w) and w >= 0):
            raise ValueError(f"anchor weight must be a number >= 0, got {w!r}")
        return pos, float(w)

    @property
    def n_vertices(self) -> int:
        return int(self.template.shape[0])

    @property
    def corner_sum(self) -> sp.csr_matrix:
        """(V, 3F) summing matrix of the template's face corners, built once:
        ``vertex_normals(V, faces, corners=tracker.corner_sum)``."""
        return self._corner_sum

    @property
    def patch_sum(self) -> sp.csr_matrix:
        """(n_patches, V) summing matrix of :attr:`patches`, built once."""
        return self._patch_sum

    @property
    def smoother(self) -> sp.csr_matrix:
        """(V, V) one ring of :func:`predict_motion`'s averaging over the template's faces,
        built once (on first use)."""
        if self._smoother is None:
            self._smoother = _umbrella(self.faces, self.n_vertices)
        return self._smoother

    def predict(self, previous, before, *, constrained=None) -> np.ndarray:
        """:func:`predict_motion` on this template's faces and patches, with the matrices built
        once per take (:attr:`smoother`, :attr:`patch_sum`): the next frame's start."""
        return predict_motion(previous, before, self.faces, self.patches, constrained=constrained,
                              smoother=self.smoother, patch_sum=self._patch_sum)

    def fit(self, points, normals, *, previous, init=None, visible=None, contour=None, tracks=None,
            anchor=None) -> FrameFit:
        """Deform the template onto one frame's data.

        Parameters
        ----------
        points : (P, 3) float ndarray
            The frame's data points (mm).
        normals : (P, 3) float ndarray
            Their unit normals (pointing out of the surface, towards the sensor for depth).
        previous : (V, 3) float ndarray
            The template on the previous frame (smoothness term's ``V_t-1``).
        init : (V, 3) float ndarray, optional
            Start of the rounds (default ``previous``).
        visible : callable or (V,) bool ndarray, optional
            Vertices that get model->data pairs: a mask, or ``visible(vertices, normals) -> mask``
            evaluated every round (a z-buffer render for a depth camera). Default: all.
        contour : callable, optional
            ``contour(vertices, normals) -> (vertex_index, targets)``: the contour term's pairs
            (vertex, nearest point of a depth edge's projection ray), weighted like data pairs.
        tracks : ((T,) int, (T, 3) float[, (T, 3) float]) ndarrays, optional
            Feature tracks: template vertices, where the colour image says they went and,
            optionally, the unit viewing rays of those points
            (:func:`pipeline.colour_tracks.colour_tracks`). Each enters, while within the gate, as
            two pairs across its ray (else along the vertex's tangent plane): they see what
            point-to-plane pairs cannot, a round part's twist about its own axis.
        anchor : ((V, 3) float ndarray, float), optional
            Positions every vertex is also drawn to and the pull's weight, in pairs (>= 0): an
            articulated prior's skinned pose (:class:`pipeline.armature_track.ArmatureTracker`).

        Returns
        -------
        FrameFit
        """
        X = np.asarray(points, dtype=np.float64)
        N = np.asarray(normals, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 3 or N.shape != X.shape:
            raise ValueError(f"points and normals must both have shape (P, 3), got {X.shape} and {N.shape}")
        prev = np.asarray(previous, dtype=np.float64)
        if prev.shape != self.template.shape:
            raise ValueError(f"previous must have shape {self.template.shape}, got {prev.shape}")
        V = prev.copy() if init is None else np.array(init, dtype=np.float64)
        if V.shape != self.template.shape:
            raise ValueError(f"init must have shape {self.template.shape}, got {V.shape}")
        n = self.n_vertices
        tree_x = cKDTree(X) if len(X) else None
        smooth_rhs = self.LtL @ prev
        start = V.copy()
        history = []
        n_md = n_dm = 0
        res = float("nan")
        gate = self.gate
        tracks = _check_tracks(tracks, n)
        anchor = self._check_anchor(anchor)
        for _ in range(self.rounds):
            vn = vertex_normals(V, self.faces, corners=self._corner_sum)
            if visible is None:
                vis = np.ones(n, bool)
            elif callable(visible):
                vis = np.asarray(visible(V, vn), bool)
            else:
                vis = np.asarray(visible, bool)
            pv = np.zeros(0, np.int64)
            px = np.zeros((0, 3))
            pn = np.zeros((0, 3))
            if tree_x is not None:
                vi = np.flatnonzero(vis)
                i, j = closest_pairs(V[vi], vn[vi], tree_x, N, gate=gate)
                jd, iv = closest_pairs(X, N, cKDTree(V), vn, gate=gate)
                n_md, n_dm = len(i), len(jd)
                pv = np.concatenate([vi[i], iv])
                px = np.concatenate([X[j], X[jd]])
                pn = np.concatenate([N[j], N[jd]])
                res = float(np.sqrt(((V[pv] - px) ** 2).sum(1).mean())) if len(pv) else float("nan")
            if contour is not None:  # vertex -> nearest point of an edge's ray: a plane through the ray
                cv, cx = contour(V, vn)
                off = cx - V[cv]
                dist = np.linalg.norm(off, axis=1)
                near = dist < gate
                cv, cx, off, dist = cv[near], cx[near], off[near], dist[near]
                cn = off / np.maximum(dist, 1e-12)[:, None]
                pv, px, pn = np.concatenate([pv, cv]), np.concatenate([px, cx]), np.concatenate([pn, cn])
            if tracks is not None:
                tv, tx, tn = _tangent_pairs(V, vn, *tracks, gate=gate)
                pv, px, pn = np.concatenate([pv, tv]), np.concatenate([px, tx]), np.concatenate([pn, tn])
            history.append((n_md, n_dm, res))
            if len(pv) == 0:
                break
            V = self._solve_round(V, pv, px, pn, smooth_rhs, start, first=len(history) == 1, prev=prev, anchor=anchor)
        seen = patch_constraints(V, pv, pn, self.patches) if len(pv) else None
        return FrameFit(vertices=V, model_pairs=n_md, data_pairs=n_dm, residual=res,
                        rounds=len(history), history=history, constrained=seen)


def _check_start_inputs(V, X, N, faces, patches, gate, corners) -> None:
    """The inputs :func:`start_residuals` and :func:`choose_start` share; ValueError naming the first wrong one."""
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"the start must have shape (V, 3), got {V.shape}")
    if X.ndim != 2 or X.shape[1] != 3 or N.shape != X.shape:
        raise ValueError(f"points and normals must both have shape (P, 3), got {X.shape} and {N.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer) \
            or (faces.size and (faces.min() < 0 or faces.max() >= len(V))):
        raise ValueError(f"faces must be (F, 3) integer indices of the {len(V)} vertices, got {faces.shape} {faces.dtype}")
    if patches.shape != (len(V),) or not np.issubdtype(patches.dtype, np.integer) or (patches.size and patches.min() < 0):
        raise ValueError(f"patches must be one non-negative integer per vertex, shape ({len(V)},), got {patches.shape}")
    if isinstance(gate, bool) or not isinstance(gate, numbers.Real) or not (math.isfinite(gate) and gate > 0):
        raise ValueError(f"gate must be a positive number (mm), got {gate!r}")
    if corners is not None and (not sp.issparse(corners) or corners.shape != (len(V), faces.size)):
        raise ValueError(f"corners must be a sparse matrix of shape {(len(V), faces.size)} (the faces' corner sums), "
                         f"got {_shape_of(corners)}")


def start_residuals(V, points, normals, faces, patches, *, gate: float, tree=None, corners=None) -> np.ndarray:
    """Per patch, how far one start of a frame's rounds is from that frame's data, both ways.

    The gated closest-point distance of every vertex to the data (model->data) and of every
    data point to the start's vertices (data->model, charged to the patch of its closest
    vertex), each at most ``gate``: a pair the gate or the 45-degree normal test would drop
    counts as ``gate``. Their mean per patch: 0 where the start lies on the data, ``gate``
    where nothing of the data is within reach of the fit's first round.

    Parameters
    ----------
    V : (V, 3) float ndarray
        The start.
    points, normals : (P, 3) float ndarray
        The frame's data.
    faces : (F, 3) int ndarray
    patches : (V,) int ndarray
    gate : float
    tree : cKDTree, optional
        Over ``points`` (built here by default).
    corners : sparse matrix, optional
        :attr:`TemplateTracker.corner_sum`.

    Returns
    -------
    (n_patches,) float ndarray
    """
    V = np.asarray(V, float)
    X, N = np.asarray(points, float), np.asarray(normals, float)
    patches, f = np.asarray(patches), np.asarray(faces)
    _check_start_inputs(V, X, N, f, patches, gate, corners)
    n_p = int(patches.max()) + 1
    if len(X) == 0:
        return np.full(n_p, float(gate))
    f = f.astype(np.int64, copy=False)
    vn = vertex_normals(V, f, corners=corners)
    tree = cKDTree(X) if tree is None else tree

    def gated(d, j, a, b):
        ok = np.isfinite(d) & (d < gate)
        ok[ok] &= np.einsum("ij,ij->i", a[ok], b[j[ok]]) >= COS_45
        return np.where(ok, d, gate)

    d, j = tree.query(V, distance_upper_bound=gate)
    j = np.minimum(j, len(X) - 1)
    md = gated(d, j, vn, N)
    d2, i2 = cKDTree(V).query(X)
    dm = gated(d2, i2, N, vn)
    lab = patches[i2]
    total = np.bincount(patches, weights=md, minlength=n_p) + np.bincount(lab, weights=dm, minlength=n_p)
    count = np.bincount(patches, minlength=n_p) + np.bincount(lab, minlength=n_p)
    return total / np.maximum(count, 1)


def choose_start(candidates, points, normals, faces, patches, *, gate: float, out_of_reach: float = 0.1, smoother=None,
                 smoothing: int = 10, corners=None) -> tuple[np.ndarray, np.ndarray]:
    """Per patch, the start the frame's data explain best (:func:`start_residuals`), blended.

    The first candidate (the constant-velocity prediction) is kept by every patch the data
    are within its reach of: where fewer than ``out_of_reach`` of the patch's vertices have
    no data point within the gate, the fit's first round pairs the patch anyway, and a
    closest-point residual cannot see what another start does along the surface (a start
    that is off mostly along the surface scores as well as the right one: docs/tracking.md,
    "Where the tracker departs from the paper"). A patch out of reach (a galloping leg whose step is longer than the
    gate) takes the candidate with the smallest gated residual. The choice (one weight per
    candidate and vertex) is averaged over ``smoothing`` rings of neighbours, so that patches
    taken from different candidates meet without a tear: the vertices of a patch within
    ``smoothing`` rings of a patch that took another candidate take a blend of both.

    Parameters
    ----------
    candidates : sequence of (V, 3) float ndarray
        Starts of the same frame (e.g. the constant-velocity prediction and the spine's skinned pose).
    points, normals : (P, 3) float ndarray
    faces : (F, 3) int ndarray
    patches : (V,) int ndarray
    gate : float
    out_of_reach : float
        Share of a patch's vertices without a data point within ``gate`` (first candidate)
        from which the patch may take another candidate.
    smoother : (V, V) sparse matrix, optional
        One ring of averaging (:attr:`TemplateTracker.smoother`).

    Returns
    -------
    start : (V, 3) float ndarray
    chosen : (n_patches,) int ndarray
        The candidate of every patch.
    """
    C = [np.asarray(c, float) for c in candidates]
    if not C or any(c.shape != C[0].shape for c in C):
        raise ValueError("candidates must be one or more arrays of the same shape (V, 3)")
    if isinstance(out_of_reach, bool) or not isinstance(out_of_reach, numbers.Real) or not 0 <= out_of_reach <= 1:
        raise ValueError(f"out_of_reach must be a share in [0, 1], got {out_of_reach!r}")
    if isinstance(smoothing, bool) or not isinstance(smoothing, (int, np.integer)) or smoothing < 0:
        raise ValueError(f"smoothing must be an integer >= 0, got {smoothing!r}")
    patches = np.asarray(patches)
    _check_start_inputs(C[0], np.asarray(points, float), np.asarray(normals, float), np.asarray(faces), patches, gate,
                        corners)
    n = len(C[0])
    if smoother is not None and (not sp.issparse(smoother) or smoother.shape != (n, n)):
        raise ValueError(f"smoother must be a sparse matrix of shape {(n, n)}, got {_shape_of(smoother)}")
    if len(C) == 1:
        return C[0].copy(), np.zeros(int(np.max(patches)) + 1, np.int64)
    tree = cKDTree(np.asarray(points, float)) if len(points) else None
    n_p = int(np.max(patches)) + 1
    if tree is not None:  # the first candidate stays wherever the data are within the gate's reach of it
        d, _ = tree.query(C[0], distance_upper_bound=gate)
        out = np.bincount(patches, weights=~np.isfinite(d), minlength=n_p) / np.maximum(np.bincount(patches, minlength=n_p), 1)
        if not np.any(out >= out_of_reach):  # nothing to choose: the residuals are not computed
            return C[0].copy(), np.zeros(n_p, np.int64)
    R = np.stack([start_residuals(c, points, normals, faces, patches, gate=gate, tree=tree, corners=corners) for c in C])
    chosen = np.argmin(R, axis=0)
    if tree is not None:
        chosen[out < out_of_reach] = 0
    if np.all(chosen == chosen[0]):  # one start for all: itself, to the bit
        return C[int(chosen[0])].copy(), chosen
    W = (chosen[patches][:, None] == np.arange(len(C))[None]).astype(float)
    S = _umbrella(faces, len(C[0])) if smoother is None else smoother
    for _ in range(int(smoothing)):
        W = S @ W
    return np.einsum("vc,cvk->vk", W, np.stack(C)), chosen
