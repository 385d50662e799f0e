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

    (L^T L + gamma D + eps I) V = L^T L V_{t-1} + gamma B + eps V_0

share one matrix for x, y and z; only the diagonal ``D`` (how many pairs each vertex has)
changes between rounds and frames. A tiny ``eps`` (1e-4 gamma) towards the round's start
``V_0`` keeps components without any data (several components, unseen parts) well posed.
The system is solved by sparse Cholesky (LDL^T): the fill-reducing ordering and elimination
tree are computed once per take, each round only refactors numerically
(:class:`CholeskySystem`; QDLDL when installed, else scipy's SuperLU). 15 rounds per frame,
each frame started from the previous one (or from a caller's guess such as a skinned pose).

What is hand-written and why: the cotangent Laplacian and the pair gating are a few lines
of numpy on top of scipy's KD-tree; no maintained package offers the paper's energy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

__all__ = [
    "TrackingError",
    "cotangent_laplacian",
    "vertex_normals",
    "mean_triangle_area",
    "choose_gamma",
    "default_gate",
    "closest_pairs",
    "CholeskySystem",
    "FrameFit",
    "TemplateTracker",
    "mesh_volume",
]

COS_45 = math.cos(math.radians(45.0))
PAPER_GATE_MM = 10.0
PAPER_OBJECT_MM = 300.0  # size of the paper's objects (pipe, lamp) the 10 mm gate was set for
ROUNDS = 15


class TrackingError(RuntimeError):
    """The data cannot be explained by the template (e.g. too few pairs to place it)."""


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 4:
        raise ValueError(f"vertices must have shape (V >= 4, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices must be finite")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape (F >= 1, 3), got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError("faces index vertices that do not exist")
    return v, f.astype(np.int64)


def _triangle_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def mean_triangle_area(vertices, faces) -> float:
    """Mean triangle area of a mesh (mm^2 when the mesh is in mm)."""
    v, f = _check_mesh(vertices, faces)
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


def cotangent_laplacian(vertices, faces, *, max_cot: float = 1e3) -> sp.csr_matrix:
    """Cotangent Laplacian of eq. 5 (Tzionas & Gall 2016; Sorkine 2005).

    ``(L V)_i = 1 / (2 |A_i|) sum_{j in N1(i)} (cot a_ij + cot b_ij) (V_j - V_i)``
    with ``|A_i|`` half the sum of the areas of the triangles around vertex ``i``.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    max_cot : float, optional
        Cotangents are clipped to ``[-max_cot, max_cot]`` (degenerate slivers of marching cubes).

    Returns
    -------
    (V, V) scipy.sparse.csr_matrix
        Rows of isolated vertices are zero.
    """
    v, f = _check_mesh(vertices, faces)
    n = v.shape[0]
    rows, cols, w = [], [], []
    for k in range(3):
        i, j, o = f[:, (k + 1) % 3], f[:, (k + 2) % 3], f[:, k]  # edge (i, j), opposite corner o
        a, b = v[i] - v[o], v[j] - v[o]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        dot = np.einsum("ij,ij->i", a, b)
        cot = np.clip(dot / np.maximum(cross, 1e-12 * np.maximum(dot, 1.0)), -max_cot, max_cot)
        rows += [i, j]
        cols += [j, i]
        w += [cot, cot]
    rows, cols, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(w)
    W = sp.coo_matrix((w, (rows, cols)), shape=(n, n)).tocsr()  # sums cot a + cot b per edge
    area = np.zeros(n)
    np.add.at(area, f.ravel(), np.repeat(_triangle_areas(v, f), 3))
    area *= 0.5
    scale = np.where(area > 0, 1.0 / (2.0 * np.maximum(area, 1e-300)), 0.0)
    deg = np.asarray(W.sum(axis=1)).ravel()
    L = sp.diags(scale) @ (W - sp.diags(deg))
    return sp.csr_matrix(L)


def vertex_normals(vertices, faces) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals (zero for isolated vertices)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(nn > 0, nn, 1.0)


def mesh_volume(vertices, faces) -> float:
    """Enclosed volume (divergence theorem; exact for closed, consistently oriented meshes)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    return float(abs(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum()) / 6.0)


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


class CholeskySystem:
    """``(K + diag(d)) x = b`` for a fixed sparse SPD ``K`` and a changing diagonal ``d``.

    The symbolic analysis (fill-reducing ordering, elimination tree) is done once; each
    :meth:`solve` refactors numerically. Backend ``"qdldl"`` (QDLDL's LDL^T, which keeps
    its AMD ordering and elimination tree between ``update`` calls) when the package is
    installed, else ``"splu"`` (scipy's SuperLU with a symmetric-mode ordering; it redoes
    the ordering every time, scipy offering no way to keep it).

    Parameters
    ----------
    K : (N, N) scipy.sparse matrix, symmetric positive semi-definite
    backend : {"auto", "qdldl", "splu"}
    """

    def __init__(self, K: sp.spmatrix, *, backend: str = "auto"):
        if backend not in ("auto", "qdldl", "splu"):
            raise ValueError(f"backend must be 'auto', 'qdldl' or 'splu', got {backend!r}")
        if backend == "auto":
            try:
                import qdldl  # noqa: F401

                backend = "qdldl"
            except ImportError:
                backend = "splu"
        self.backend = backend
        n = K.shape[0]
        # pattern: the upper triangle of K + I (K is PSD, so no diagonal entry cancels), CSC
        base = sp.triu(sp.csc_matrix(K) + sp.eye(n, format="csc"), format="csc")
        base.sort_indices()
        self._U = base
        self._kdiag = base.diagonal() - 1.0
        # position of each diagonal entry in the CSC data: the last entry of every column
        self._diag_pos = base.indptr[1:] - 1
        if not np.array_equal(base.indices[self._diag_pos], np.arange(n)):
            raise AssertionError("upper-triangular CSC without its diagonal last")
        self._solver = None
        self.n = n
        self.factorizations = 0

    def _matrix(self, d: np.ndarray) -> sp.csc_matrix:
        A = self._U.copy()
        A.data[self._diag_pos] = self._kdiag + d
        return A

    def factor(self, d: np.ndarray) -> None:
        """Numerically factor ``K + diag(d)`` (``d`` > 0 somewhere on every component)."""
        A = self._matrix(np.asarray(d, dtype=np.float64))
        if self.backend == "qdldl":
            import qdldl

            if self._solver is None:
                self._solver = qdldl.Solver(A, upper=True)
            else:
                self._solver.update(A, upper=True)
        else:
            from scipy.sparse.linalg import splu

            full = A + sp.triu(A, k=1, format="csc").T
            self._solver = splu(sp.csc_matrix(full), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                options={"SymmetricMode": True})
        self.factorizations += 1

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve for a (N,) or (N, k) right-hand side with the last factorisation."""
        if self._solver is None:
            raise RuntimeError("factor() first")
        b = np.asarray(b, dtype=np.float64)
        if self.backend == "qdldl":
            if b.ndim == 1:
                return self._solver.solve(b)
            return np.stack([self._solver.solve(np.ascontiguousarray(b[:, k])) for k in range(b.shape[1])], axis=1)
        return self._solver.solve(b)


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

    Notes
    -----
    Reused between the rounds and frames of a take: the Laplacian ``L``, ``L^T L`` and its
    upper-triangular pattern, the fill-reducing ordering and elimination tree of the
    Cholesky factorisation, and the frame's KD-tree over the data; per round only the
    KD-tree over the moved vertices, the pairs and the numeric factorisation are redone.
    """

    def __init__(self, vertices, faces, *, gamma: float | None = None, gate: float | None = None,
                 rounds: int = ROUNDS, backend: str = "auto", tangential: float = 0.25, hold: float = 0.1):
        v, f = _check_mesh(vertices, faces)
        self.tangential = float(tangential)
        self.hold = float(hold)
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

    def _target(self, v, n, x):
        d = x - v
        dn = n * np.einsum("ij,ij->i", d, n)[:, None]
        return v + dn + self.tangential * (d - dn)

    @property
    def n_vertices(self) -> int:
        return int(self.template.shape[0])

    def fit(self, points, normals, *, previous, init=None, visible=None) -> FrameFit:
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
        for _ in range(self.rounds):
            vn = vertex_normals(V, self.faces)
            if visible is None:
                vis = np.ones(n, bool)
            elif callable(visible):
                vis = np.asarray(visible(V, vn), bool)
            else:
                vis = np.asarray(visible, bool)
            counts = np.zeros(n)
            target = np.zeros((n, 3))
            if tree_x is not None:
                vi = np.flatnonzero(vis)
                i, j = closest_pairs(V[vi], vn[vi], tree_x, N, gate=self.gate)
                i = vi[i]
                np.add.at(counts, i, 1.0)
                np.add.at(target, i, self._target(V[i], vn[i], X[j]))
                n_md = len(i)
                tree_v = cKDTree(V)
                jd, iv = closest_pairs(X, N, tree_v, vn, gate=self.gate)
                np.add.at(counts, iv, 1.0)
                np.add.at(target, iv, self._target(V[iv], vn[iv], X[jd]))
                n_dm = len(jd)
                d2 = np.concatenate([((V[i] - X[j]) ** 2).sum(1), ((V[iv] - X[jd]) ** 2).sum(1)])
                res = float(np.sqrt(d2.mean())) if len(d2) else float("nan")
            history.append((n_md, n_dm, res))
            if n_md + n_dm == 0:
                break
            hold = self.hold * (counts == 0)  # vertices without a pair keep their start weakly
            self.system.factor(self.gamma * (counts + hold) + self.eps)
            rhs = smooth_rhs + self.gamma * (target + hold[:, None] * start) + self.eps * V
            V = self.system.solve(rhs)
        return FrameFit(vertices=V, model_pairs=n_md, data_pairs=n_dm, residual=res,
                        rounds=len(history), history=history)
