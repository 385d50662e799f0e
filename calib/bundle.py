"""Bundle adjustment of a camera rig observing a planar board in many poses.

Unknowns: every camera's pose (world -> camera; the reference camera's is fixed,
it defines the world), optionally every camera's intrinsics (fx, fy, cx, cy,
k1, k2, p1, p2, k3), and every board pose (board -> world). Residuals: the
reprojection errors of the observed board corners. Solved with
``scipy.optimize.least_squares`` (trust-region reflective) with a sparse
Jacobian pattern, a robust loss and ``x_scale='jac'``.

The projection is the camera model of :mod:`calib.camera` evaluated for many
cameras at once (verified against :func:`calib.camera.project_points` in the
tests).

Reference: Triggs, McLauchlan, Hartley, Fitzgibbon, "Bundle adjustment — a
modern synthesis", 2000.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

__all__ = ["BundleResult", "bundle_adjust", "rodrigues_batch", "project_batch", "INTRINSIC_NAMES",
           "reduced_intrinsics_jacobian"]

log = logging.getLogger(__name__)

N_INTR = 9  # fx, fy, cx, cy, k1, k2, p1, p2, k3
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_VERBOSE = 0


def rodrigues_batch(r: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors -> (N, 3, 3) rotation matrices (``scipy.spatial.transform.Rotation``)."""
    return Rotation.from_rotvec(np.asarray(r, dtype=np.float64).reshape(-1, 3)).as_matrix()


def project_batch(Xc: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """Project camera-frame points with per-point intrinsics.

    Parameters
    ----------
    Xc : (M, 3) float ndarray
        Points in their camera's frame.
    intr : (M, 9) float ndarray
        ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` of each point's camera.

    Returns
    -------
    (M, 2) float ndarray
        Pixels (as :func:`calib.camera.project_points`, zero skew).
    """
    z = Xc[:, 2]
    z = np.where(np.abs(z) < 1e-9, 1e-9, z)
    x = Xc[:, 0] / z
    y = Xc[:, 1] / z
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr.T
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


def _rho(z: np.ndarray, loss: str) -> tuple[np.ndarray, np.ndarray]:
    """Robust loss of ``z = (r / f_scale)**2`` and its derivative (as in ``least_squares``)."""
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "soft_l1":
        s = np.sqrt(1.0 + z)
        return 2.0 * (s - 1.0), 1.0 / s
    if loss == "huber":
        big = z > 1.0
        sz = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2.0 * sz - 1.0, z), np.where(big, 1.0 / sz, 1.0)
    if loss == "cauchy":
        return np.log1p(z), 1.0 / (1.0 + z)
    return np.arctan(z), 1.0 / (1.0 + z * z)  # arctan


class _Result:
    def __init__(self, x, fun, success, message, nfev, cost):
        self.x, self.fun, self.success, self.message, self.nfev, self.cost = x, fun, success, message, nfev, cost


def _robust_weights(r: np.ndarray, loss: str, f2: float, n_robust: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-residual cost ``f2 * rho(r**2 / f2)`` and IRLS weight; rows past ``n_robust`` (priors) are plain squares."""
    rho, w = _rho(r[:n_robust] * r[:n_robust] / f2, loss)
    cost = np.concatenate([f2 * rho, r[n_robust:] ** 2])
    return cost, np.concatenate([w, np.ones(r.size - n_robust)])


def _robust_lm(fun, jac, x0, *, loss: str, f_scale: float, max_nfev: int, ftol: float, xtol: float = 1e-12,
               n_robust: int | None = None):
    """Levenberg-Marquardt with iteratively reweighted robust loss, sparse normal equations solved directly.

    Minimizes ``0.5 * f_scale**2 * sum(rho((r / f_scale)**2))`` like ``least_squares``; residuals past
    ``n_robust`` (prior rows) enter as plain squares.
    """
    from scipy.sparse import diags
    from scipy.sparse.linalg import spsolve

    f2 = f_scale * f_scale
    x = np.asarray(x0, dtype=np.float64).copy()
    r = fun(x)
    nfev = 1

    nr = r.size if n_robust is None else int(n_robust)

    def cost_of(res):
        return 0.5 * float(np.sum(_robust_weights(res, loss, f2, nr)[0]))

    cost = cost_of(r)
    lam = 1e-4
    message, success = "maximum number of function evaluations reached", False
    while nfev < max_nfev:
        J = jac(x)
        w = _robust_weights(r, loss, f2, nr)[1]
        Jw = J.multiply(w[:, None]).tocsr() if hasattr(J, "multiply") else J * w[:, None]
        A = (J.T @ Jw).tocsc()
        g = np.asarray(J.T @ (w * r)).ravel()
        d = A.diagonal().copy()
        d[d <= 0] = 1.0
        if np.max(np.abs(g) / np.sqrt(d)) < 1e-12 * max(1.0, np.sqrt(cost)):
            message, success = "gradient below tolerance", True
            break
        improved = False
        while nfev < max_nfev:
            try:
                dx = -spsolve(A + diags(lam * d, format="csc"), g)
                if not np.all(np.isfinite(dx)):
                    raise ValueError("singular normal equations")
            except (RuntimeError, ValueError):
                lam *= 10.0
                if lam > 1e16:
                    break
                continue
            xn = x + dx
            rn = fun(xn)
            nfev += 1
            cn = cost_of(rn)
            if np.isfinite(cn) and cn < cost:
                improved = True
                lam = max(lam / 5.0, 1e-12)
                break
            lam *= 5.0
            if lam > 1e16:
                break
        if not improved:
            message, success = "no further decrease of the cost", True
            break
        dc = cost - cn
        step = float(np.linalg.norm(dx))
        x, r, cost = xn, rn, cn
        if dc < ftol * cost:
            message, success = "relative cost decrease below ftol", True
            break
        if step < xtol * (float(np.linalg.norm(x)) + xtol):
            message, success = "step below xtol", True
            break
    return _Result(x, r, success, message, nfev, cost)


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    S = np.zeros((v.shape[0], 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def _left_jacobian(r: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors -> (N, 3, 3) left Jacobians of SO(3).

    ``d(R(r) p)/dr = -[R(r) p]_x J_l(r)``.
    """
    theta = np.linalg.norm(r, axis=1)
    S = _skew(r)
    S2 = S @ S
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - np.sin(th)) / th**3)
    return np.eye(3)[None] + a[:, None, None] * S + b[:, None, None] * S2


@dataclass(frozen=True, eq=False)
class BundleResult:
    """Output of :func:`bundle_adjust` (arrays as in its parameters)."""

    cam_rvec: np.ndarray
    cam_tvec: np.ndarray
    intrinsics: np.ndarray
    board_rvec: np.ndarray
    board_tvec: np.ndarray
    residuals: np.ndarray  # (M, 2) px, final
    success: bool
    message: str
    nfev: int
    cost: float
    intrinsics_cov: np.ndarray | None = None  # (C, 9, 9), NaN rows/columns for intrinsics not estimated
    sigma_px: float = float("nan")  # residual scale the covariance is expressed in
    rotation_cov: np.ndarray | None = None  # (C, C, 3, 3) rad^2, camera rotations (left perturbation), reference 0


def _observations(obs_cam, obs_board, obs_points, obs_uv, intrinsics, cam_rvec, cam_tvec, board_rvec, board_tvec):
    """The inputs of :func:`bundle_adjust` as arrays of the documented shapes (ValueError otherwise)."""
    obs_cam = np.asarray(obs_cam, dtype=np.int64).ravel()
    obs_board = np.asarray(obs_board, dtype=np.int64).ravel()
    X = np.asarray(obs_points, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(obs_uv, dtype=np.float64).reshape(-1, 2)
    M = obs_cam.shape[0]
    if not (obs_board.shape[0] == X.shape[0] == uv.shape[0] == M) or M == 0:
        raise ValueError("obs_cam, obs_board, obs_points and obs_uv must be non-empty and of equal length")
    intr0 = np.asarray(intrinsics, dtype=np.float64).reshape(-1, N_INTR)
    C = intr0.shape[0]
    crv = np.asarray(cam_rvec, dtype=np.float64).reshape(C, 3)
    ctv = np.asarray(cam_tvec, dtype=np.float64).reshape(C, 3)
    brv = np.asarray(board_rvec, dtype=np.float64).reshape(-1, 3)
    btv = np.asarray(board_tvec, dtype=np.float64).reshape(-1, 3)
    B = brv.shape[0]
    if obs_cam.min() < 0 or obs_cam.max() >= C or obs_board.min() < 0 or obs_board.max() >= B:
        raise ValueError("obs_cam / obs_board index out of range")
    return obs_cam, obs_board, X, uv, intr0, crv, ctv, brv, btv


def _check_options(reference, loss, f_scale, solver, fixed_intrinsics, C: int) -> None:
    """ValueError naming the first bad option of :func:`bundle_adjust`."""
    if not 0 <= reference < C:
        raise ValueError(f"reference must be a camera index in [0, {C}), got {reference}")
    if loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
        raise ValueError(f"loss must be a least_squares loss name, got {loss!r}")
    if not f_scale > 0:
        raise ValueError(f"f_scale must be > 0, got {f_scale!r}")
    if solver not in ("lm", "scipy"):
        raise ValueError(f"solver must be 'lm' or 'scipy', got {solver!r}")
    if isinstance(fixed_intrinsics, np.ndarray):
        if fixed_intrinsics.shape != (C, N_INTR) or fixed_intrinsics.dtype != bool:
            raise ValueError(f"fixed_intrinsics as an array must be ({C}, {N_INTR}) bool, got "
                             f"{fixed_intrinsics.shape} {fixed_intrinsics.dtype}")
        return
    bad = sorted(set(fixed_intrinsics) - set(INTRINSIC_NAMES))
    if isinstance(fixed_intrinsics, str) or bad:
        raise ValueError(f"fixed_intrinsics must name intrinsics among {INTRINSIC_NAMES}, got {fixed_intrinsics!r}")


def _held_mask(fixed_intrinsics, C: int) -> np.ndarray:
    """(C, 9) bool: the intrinsics each camera keeps at its initial value."""
    if isinstance(fixed_intrinsics, np.ndarray):
        return fixed_intrinsics.copy()
    return np.tile([n in fixed_intrinsics for n in INTRINSIC_NAMES], (C, 1))


def bundle_adjust(
    obs_cam: np.ndarray,
    obs_board: np.ndarray,
    obs_points: np.ndarray,
    obs_uv: np.ndarray,
    *,
    intrinsics: np.ndarray,
    cam_rvec: np.ndarray,
    cam_tvec: np.ndarray,
    board_rvec: np.ndarray,
    board_tvec: np.ndarray,
    reference: int = 0,
    optimize_intrinsics: bool = False,
    fixed_intrinsics: tuple[str, ...] | np.ndarray = (),
    loss: str = "soft_l1",
    f_scale: float = 1.0,
    max_nfev: int | None = None,
    ftol: float = 1e-10,
    solver: str = "lm",
    prior_cov: np.ndarray | None = None,
    prior_scale: float = 1.0,
    prior_mean: np.ndarray | None = None,
    covariance: bool = False,
    prior_jacobian: np.ndarray | None = None,
) -> BundleResult:
    """Jointly refine camera poses (and intrinsics) and board poses.

    Parameters
    ----------
    obs_cam, obs_board : (M,) int ndarray
        Camera and board-pose index of every observed corner.
    obs_points : (M, 3) float ndarray
        The corner in the board frame.
    obs_uv : (M, 2) float ndarray
        Its observed pixel.
    intrinsics : (C, 9) float ndarray
        ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` per camera (initial values).
    cam_rvec, cam_tvec : (C, 3) float ndarray
        World -> camera poses (initial).
    board_rvec, board_tvec : (B, 3) float ndarray
        Board -> world poses (initial).
    reference : int
        Camera whose pose stays fixed (gauge).
    optimize_intrinsics : bool
    fixed_intrinsics : tuple of str or (C, 9) bool ndarray
        Intrinsics that stay at their initial values when ``optimize_intrinsics`` is set,
        named as in ``INTRINSIC_NAMES`` (e.g. ``("k3",)`` for a camera calibrated with
        ``fix_k3``, ``("p1", "p2")`` with ``zero_tangent``), or per camera (True: held).
    loss : str
        ``least_squares`` loss (``"linear"``, ``"soft_l1"``, ``"huber"``, ``"cauchy"``).
    f_scale : float
        Inlier scale of the robust loss, px.
    solver : {"lm", "scipy"}
        ``"lm"``: Levenberg-Marquardt on the normal equations with iteratively
        reweighted robust loss (same objective as ``least_squares``; the sparse
        normal equations, ``6 C + 9 C + 6 B`` unknowns, are solved directly by
        sparse LU, which copes with this poorly conditioned problem where
        ``least_squares``' LSMR trust-region steps crawl: docs/calibration.md). ``"scipy"``:
        ``scipy.optimize.least_squares`` (TRF, sparse analytic Jacobian,
        ``x_scale='jac'``), the reference (its robust loss also bends the prior rows).
    prior_cov : (C, 9, 9) float ndarray, optional
        Gaussian prior on the intrinsics when they are optimized: centred on
        ``intrinsics``, with this covariance (e.g. from the per-camera Zhang solve,
        :func:`calib.intrinsics.calibrate_intrinsics`). The prior rows are
        ``prior_scale * L.T @ (p - p0)`` with ``L L.T`` the inverse covariance of the
        free intrinsics, so with ``prior_scale`` the pixel noise the reprojection
        rows are the whitened negative log-likelihood up to that common factor.
        An intrinsic with an infinite variance (and zero covariances) has no prior row;
        other non-finite entries leave a camera's intrinsics without a prior.
    prior_scale : float
        Pixel noise (px) the prior is expressed in, see ``prior_cov``.
    prior_mean : (C, 9) float ndarray, optional
        Centre of the prior (default ``intrinsics``, the initial values): e.g. zero
        tangential terms for a maximum-a-posteriori solve (:mod:`calib.intrinsics`).
    covariance : bool
        Also return the marginal covariance of every camera's intrinsics at the
        solution (``(J^T W J)^-1`` with the robust weights, scaled by the
        residual variance; Triggs et al. 2000, section 10) and the joint covariance
        of the camera rotations (``rotation_cov``: block ``[a, b]`` is the
        cross-covariance of the small rotations ``d`` with ``R_a <- exp([d]_x) R_a``,
        in radians squared; the reference camera's blocks are zero, it is the gauge).
        The board poses are eliminated by their Schur complement.
    prior_jacobian : (M, 2, 9) float ndarray, optional
        With ``prior_cov`` from a solve that saw some of the same corners (each camera's own Zhang solve,
        whose views are also frame-set views here): for every observation, the Jacobian of that solve's
        reprojection error at the same corner in the intrinsics, its view's board pose projected out
        (:func:`reduced_intrinsics_jacobian`); zero where that solve did not see the corner. The covariance
        is then the sandwich ``A^-1 M A^-1`` of the estimator as it is (``A`` the normal matrix the solve
        weights with, ``M`` the covariance of its right-hand side: the prior as the posterior it is, the
        corners at the residuals' scale, and the cross terms of the corners both solves used, their noise
        taken as the prior solve's), instead of ``A^-1``, which counts those corners' information twice and
        comes out too small. The estimate does not change.

    Returns
    -------
    BundleResult
    """
    obs_cam, obs_board, X, uv, intr0, crv, ctv, brv, btv = _observations(
        obs_cam, obs_board, obs_points, obs_uv, intrinsics, cam_rvec, cam_tvec, board_rvec, board_tvec)
    C = intr0.shape[0]
    _check_options(reference, loss, f_scale, solver, fixed_intrinsics, C)
    held = _held_mask(fixed_intrinsics, C)
    free_i = ~held.all(axis=0)  # estimated for at least one camera
    held_f = held[:, free_i]  # (C, NF): entries a camera holds (zero Jacobian columns, no prior)
    prior_rows = _prior_rows(prior_cov, C, free_i, prior_scale, held_f) if optimize_intrinsics else None
    mu = intr0 if prior_mean is None else np.asarray(prior_mean, dtype=np.float64)
    if mu.shape != intr0.shape or not np.all(np.isfinite(mu)):
        raise ValueError(f"prior_mean must be finite with shape {intr0.shape}, got {mu.shape}")
    unknowns = _Unknowns(intr0, crv, ctv, brv, btv, reference=reference, optimize_intrinsics=optimize_intrinsics,
                         free_i=free_i)
    problem = _Problem(unknowns, obs_cam, obs_board, X, uv, held_f=held_f, prior_rows=prior_rows, prior_mean=mu)
    x0 = unknowns.pack()
    M = obs_cam.shape[0]
    shared = _shared_prior(prior_jacobian, M, free_i, prior_rows)
    if solver == "scipy":
        res = least_squares(
            problem.residuals, x0, jac=problem.jacobian, method="trf", loss=loss, f_scale=f_scale, x_scale="jac",
            max_nfev=max_nfev, ftol=ftol, xtol=1e-12, gtol=1e-10, tr_solver="lsmr", verbose=_VERBOSE,
        )
    else:
        res = _robust_lm(problem.residuals, problem.jacobian, x0, loss=loss, f_scale=f_scale,
                         max_nfev=200 if max_nfev is None else max_nfev, ftol=ftol, n_robust=2 * M)
    rv, tv, intr, bR, bT = unknowns.unpack(res.x)
    log.debug("bundle adjustment: %s after %d evaluations", res.message, res.nfev)
    icov, rcov, sigma = None, None, float("nan")
    if covariance:
        icov, rcov, sigma = _covariance(problem.jacobian(res.x), np.asarray(res.fun), 2 * M, loss, f_scale, C,
                                        free_i, held_f, unknowns.n_pose, unknowns.n_intr, unknowns.free_cams, rv,
                                        optimize_intrinsics, prior_scale, shared=shared, obs_cam=obs_cam,
                                        prior_rows=prior_rows)
    return BundleResult(
        cam_rvec=rv, cam_tvec=tv, intrinsics=np.array(intr, dtype=np.float64), board_rvec=bR, board_tvec=bT,
        residuals=np.asarray(res.fun)[: 2 * M].reshape(-1, 2), success=bool(res.success), message=str(res.message),
        nfev=int(res.nfev), cost=float(res.cost), intrinsics_cov=icov, sigma_px=sigma, rotation_cov=rcov,
    )


class _Unknowns:
    """The vector of unknowns: the free cameras' poses (6 each, every camera but the reference), the free
    intrinsics of every camera (when optimized) and the board poses (6 each), in that order."""

    def __init__(self, intr0, crv, ctv, brv, btv, *, reference: int, optimize_intrinsics: bool,
                 free_i: np.ndarray):
        self.intr0, self.crv, self.ctv, self.brv, self.btv = intr0, crv, ctv, brv, btv
        self.C, self.B = intr0.shape[0], brv.shape[0]
        self.optimize_intrinsics = optimize_intrinsics
        self.free_i = free_i
        self.NF = int(free_i.sum())
        self.free_cams = np.array([c for c in range(self.C) if c != reference], dtype=np.int64)
        self.cam_slot = -np.ones(self.C, dtype=np.int64)
        self.cam_slot[self.free_cams] = np.arange(self.free_cams.size)
        self.n_pose = 6 * self.free_cams.size
        self.n_intr = self.NF * self.C if optimize_intrinsics else 0

    def pack(self) -> np.ndarray:
        """The starting vector."""
        return np.concatenate(
            [np.hstack([self.crv[self.free_cams], self.ctv[self.free_cams]]).ravel(),
             self.intr0[:, self.free_i].ravel() if self.optimize_intrinsics else [],
             np.hstack([self.brv, self.btv]).ravel()]
        )

    def unpack(self, p: np.ndarray):
        """Camera rotation and translation vectors, intrinsics, board rotation and translation vectors."""
        rv, tv = self.crv.copy(), self.ctv.copy()
        n_pose, n_intr = self.n_pose, self.n_intr
        poses = p[:n_pose].reshape(-1, 6)
        rv[self.free_cams], tv[self.free_cams] = poses[:, :3], poses[:, 3:]
        if self.optimize_intrinsics:
            intr = self.intr0.copy()
            intr[:, self.free_i] = p[n_pose : n_pose + n_intr].reshape(self.C, self.NF)
        else:
            intr = self.intr0
        b = p[n_pose + n_intr :].reshape(self.B, 6)
        return rv, tv, intr, b[:, :3], b[:, 3:]


class _Problem:
    """Residuals and sparse Jacobian of the bundle adjustment over :class:`_Unknowns`.

    The Jacobian's sparsity is fixed by the observations, so its compressed-row layout is
    found once; each evaluation only fills in the values.
    """

    def __init__(self, unknowns: _Unknowns, obs_cam, obs_board, X, uv, *, held_f, prior_rows, prior_mean):
        self.u = unknowns
        self.obs_cam, self.obs_board, self.X, self.uv = obs_cam, obs_board, X, uv
        self.held_f, self.prior_rows, self.mu = held_f, prior_rows, prior_mean
        self._layout = _jacobian_layout(unknowns, obs_cam, obs_board, with_prior=prior_rows is not None)

    def forward(self, p: np.ndarray):
        """The unknowns and the chain of points from the board to the camera frame."""
        rv, tv, intr, bR, bT = self.u.unpack(p)
        Rc = rodrigues_batch(rv)
        Rb = rodrigues_batch(bR)
        RbX = np.einsum("mij,mj->mi", Rb[self.obs_board], self.X)
        Xw = RbX + bT[self.obs_board]
        RcXw = np.einsum("mij,mj->mi", Rc[self.obs_cam], Xw)
        Xc = RcXw + tv[self.obs_cam]
        return rv, bR, intr, Rc, RbX, RcXw, Xc

    def residuals(self, p: np.ndarray) -> np.ndarray:
        """(2 M,) reprojection errors, then the prior rows (when there is a prior)."""
        *_, intr, _Rc, _RbX, _RcXw, Xc = self.forward(p)
        r = (project_batch(Xc, intr[self.obs_cam]) - self.uv).ravel()
        if self.prior_rows is None:
            return r
        free_i = self.u.free_i
        d = (intr[:, free_i] - self.mu[:, free_i])  # (C, NF)
        return np.concatenate([r, np.einsum("cij,cj->ci", self.prior_rows, d).ravel()])

    def blocks(self, p: np.ndarray) -> np.ndarray:
        """(M, 2, k) every observation's Jacobian entries: camera pose (6), free intrinsics (when
        optimized), board pose (6)."""
        obs_cam, obs_board = self.obs_cam, self.obs_board
        rv, bR, intr, Rc, RbX, RcXw, Xc = self.forward(p)
        J_Xc, Ji = _projection_derivatives(Xc, intr[obs_cam])
        J_cr = -J_Xc @ _skew(RcXw) @ _left_jacobian(rv)[obs_cam]
        J_Xw = J_Xc @ Rc[obs_cam]
        J_br = -J_Xw @ _skew(RbX) @ _left_jacobian(bR)[obs_board]
        parts = [np.concatenate([J_cr, J_Xc], axis=2)]
        if self.u.optimize_intrinsics:
            parts.append(Ji[:, :, self.u.free_i] * ~self.held_f[obs_cam][:, None, :])
        parts.append(np.concatenate([J_br, J_Xw], axis=2))
        return np.concatenate(parts, axis=2)

    def jacobian(self, p: np.ndarray) -> csr_matrix:
        """The residuals' Jacobian, (2 M [+ C NF], n) sparse."""
        data = self.blocks(p).reshape(-1)  # (M, 2, k) row-major
        keep, order, indices, indptr, shape = self._layout
        values = data[keep]
        if self.prior_rows is not None:
            values = np.concatenate([values, self.prior_rows.ravel()])
        return csr_matrix((values[order], indices.copy(), indptr.copy()), shape=shape)


def _jacobian_layout(u: _Unknowns, obs_cam: np.ndarray, obs_board: np.ndarray, *, with_prior: bool):
    """The Jacobian's fixed sparsity as a compressed-row layout.

    Every observation has 2 rows x (6 camera pose + the free intrinsics + 6 board pose) entries
    (no pose entries for the reference camera), then the prior's (C NF) rows of NF entries each.
    Returns ``keep`` (which of the dense (M, 2, k) values are entries), ``order`` (an index putting
    the kept values, prior values appended, in compressed-row order), ``indices``, ``indptr`` and the shape:
    ``csr_matrix((values[order], indices, indptr))`` equals the matrix built from coordinates.
    """
    M, C, NF, n_pose, n_intr = obs_cam.shape[0], u.C, u.NF, u.n_pose, u.n_intr
    obs_cslot = u.cam_slot[obs_cam]
    has_pose = obs_cslot >= 0
    col_pose = np.where(has_pose, obs_cslot, 0)[:, None] * 6 + np.arange(6)
    col_intr = n_pose + obs_cam[:, None] * NF + np.arange(NF)
    col_board = n_pose + n_intr + obs_board[:, None] * 6 + np.arange(6)
    blocks = [col_pose]
    if u.optimize_intrinsics:
        blocks.append(col_intr)
    blocks.append(col_board)
    cols = np.concatenate(blocks, axis=1)  # (M, k)
    k = cols.shape[1]
    row_idx = np.repeat(np.arange(2 * M), k)
    col_idx = np.repeat(cols, 2, axis=0).ravel()
    keep_mask = np.ones((M, k), bool)
    keep_mask[:, :6] = has_pose[:, None]
    keep = np.repeat(keep_mask, 2, axis=0).ravel()
    rows, columns, n_rows = row_idx[keep], col_idx[keep], 2 * M
    if with_prior:
        pr = 2 * M + np.repeat(np.arange(C * NF), NF)
        pc = n_pose + (np.arange(C)[:, None, None] * NF + np.zeros((1, NF, 1), int) + np.arange(NF)).ravel()
        rows, columns, n_rows = np.concatenate([rows, pr]), np.concatenate([columns, pc]), n_rows + C * NF
    shape = (n_rows, n_pose + n_intr + 6 * u.B)
    # the position of every value, carried through the same conversion as the values themselves
    # (no two values share a row and column, so none are summed)
    where = csr_matrix((np.arange(1, rows.size + 1, dtype=np.float64), (rows, columns)), shape=shape)
    order = where.data.astype(np.int64) - 1
    if np.array_equal(order, np.arange(order.size)):
        order = slice(None)  # the observations' rows come in order, columns ascending within each
    return keep, order, where.indices, where.indptr, shape


def _projection_derivatives(Xc: np.ndarray, ip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of :func:`project_batch`: (M, 2, 3) by the camera-frame point and (M, 2, 9) by the
    intrinsics ``ip`` (M, 9)."""
    M = Xc.shape[0]
    fx, fy = ip[:, 0], ip[:, 1]
    k1, k2, p1, p2, k3 = ip[:, 4], ip[:, 5], ip[:, 6], ip[:, 7], ip[:, 8]
    z = np.where(np.abs(Xc[:, 2]) < 1e-9, 1e-9, Xc[:, 2])
    x, y = Xc[:, 0] / z, Xc[:, 1] / z
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    # d(u, v) / d(x, y)
    dxd_dx = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
    D = np.empty((M, 2, 2))
    D[:, 0, 0], D[:, 0, 1] = fx * dxd_dx, fx * dxd_dy
    D[:, 1, 0], D[:, 1, 1] = fy * dxd_dy, fy * dyd_dy
    # d(x, y) / d Xc
    P = np.zeros((M, 2, 3))
    P[:, 0, 0] = 1.0 / z
    P[:, 1, 1] = 1.0 / z
    P[:, 0, 2] = -x / z
    P[:, 1, 2] = -y / z
    Ji = np.zeros((M, 2, N_INTR))
    Ji[:, 0, 0] = xd
    Ji[:, 1, 1] = yd
    Ji[:, 0, 2] = 1.0
    Ji[:, 1, 3] = 1.0
    Ji[:, 0, 4], Ji[:, 1, 4] = fx * x * r2, fy * y * r2
    Ji[:, 0, 5], Ji[:, 1, 5] = fx * x * r2 * r2, fy * y * r2 * r2
    Ji[:, 0, 6], Ji[:, 1, 6] = fx * 2.0 * x * y, fy * (r2 + 2.0 * y * y)
    Ji[:, 0, 7], Ji[:, 1, 7] = fx * (r2 + 2.0 * x * x), fy * 2.0 * x * y
    Ji[:, 0, 8], Ji[:, 1, 8] = fx * x * r2**3, fy * y * r2**3
    return D @ P, Ji


def _prior_rows(prior_cov, C: int, free_i: np.ndarray, scale: float, held_f: np.ndarray) -> np.ndarray | None:
    """(C, NF, NF) whitening rows ``scale * L.T`` of the prior on the free intrinsics (zero: no prior),
    each camera's over the intrinsics it does not hold."""
    if prior_cov is None:
        return None
    cov = np.asarray(prior_cov, dtype=np.float64)
    if cov.shape != (C, N_INTR, N_INTR):
        raise ValueError(f"prior_cov must have shape ({C}, {N_INTR}, {N_INTR}), got {cov.shape}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"prior_scale must be > 0, got {scale!r}")
    NF = int(free_i.sum())
    rows = np.zeros((C, NF, NF))
    for c in range(C):
        var = np.diag(cov[c])[free_i]
        own = ~held_f[c] & ~np.isposinf(var)  # infinite variance: no prior on that intrinsic
        S = cov[c][np.ix_(free_i, free_i)][np.ix_(own, own)]
        if not np.all(np.isfinite(S)):
            continue
        try:
            L = np.linalg.cholesky(np.linalg.inv(0.5 * (S + S.T)))
        except np.linalg.LinAlgError:
            continue
        rows[c][np.ix_(own, own)] = scale * L.T
    return rows


def _camera_block_inverse(A, n_cam: int, rhs: np.ndarray | None = None):
    """Inverse of the camera block (first ``n_cam`` unknowns) of the normal matrix ``A``.

    The board poses (6 x 6 diagonal blocks after the camera unknowns) are eliminated by their
    Schur complement, so the cost is that of the cameras, not of the frame sets. With ``rhs``
    ((n, m) dense), also the camera rows of ``A^-1 rhs``.
    """
    A = A.tocsr()
    n = A.shape[0]
    nb = (n - n_cam) // 6
    Acc = A[:n_cam, :n_cam].toarray()
    Acb = A[:n_cam, n_cam:].toarray()
    Abb = A[n_cam:, n_cam:]
    blocks = np.stack([Abb[6 * b : 6 * b + 6, 6 * b : 6 * b + 6].toarray() for b in range(nb)]) if nb else np.zeros((0, 6, 6))
    try:
        inv_b = np.linalg.inv(blocks)
    except np.linalg.LinAlgError:
        inv_b = np.linalg.pinv(blocks)
    # S = Acc - Acb Abb^-1 Abc, with Abb^-1 block diagonal
    Acb3 = Acb.reshape(n_cam, nb, 6).transpose(1, 0, 2)  # (nb, n_cam, 6)
    S = Acc - np.einsum("bik,bkl,bjl->ij", Acb3, inv_b, Acb3)
    try:
        Sinv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        Sinv = np.linalg.pinv(S)
    if rhs is None:
        return Sinv
    # camera rows of A^-1 rhs: S^-1 (rhs_c - Acb Abb^-1 rhs_b)
    rb = rhs[n_cam:].reshape(nb, 6, -1)
    return Sinv, Sinv @ (rhs[:n_cam] - np.einsum("bik,bkl,blm->im", Acb3, inv_b, rb))


def _shared_prior(prior_jacobian, M: int, free_i, prior_rows):
    """``prior_jacobian`` of :func:`bundle_adjust` over the free intrinsics, (M, 2, NF), or None."""
    if prior_jacobian is None:
        return None
    if prior_rows is None:
        raise ValueError("prior_jacobian needs prior_cov and optimize_intrinsics")
    G = np.asarray(prior_jacobian, dtype=np.float64)
    if G.shape != (M, 2, N_INTR) or not np.all(np.isfinite(G)):
        raise ValueError(f"prior_jacobian must be finite with shape ({M}, 2, {N_INTR}), got {G.shape}")
    return G[:, :, free_i]


def _normal_matrix(Jd, w, n_obs: int, pixel_var: float, prior_scale: float, held_cols: np.ndarray):
    """``J^T D J`` with the pixel rows weighted by their robust weights over ``pixel_var`` and the prior rows by
    ``1 / prior_scale**2``; held intrinsics (empty rows and columns, exactly known) get a unit diagonal."""
    from scipy.sparse import diags

    scale = np.full(Jd.shape[0], 1.0 / prior_scale**2)
    scale[:n_obs] = w[:n_obs] / pixel_var
    A = Jd.T @ Jd.multiply(scale[:, None]).tocsr()
    if held_cols.size:
        unit = np.zeros(Jd.shape[1])
        unit[held_cols] = 1.0
        A = A + diags(unit)
    return A


def _sandwich(Jd, w, sigma2, n_obs, prior_scale, n_pose, n_cam, held_cols, shared, obs_cam, prior_rows, C, NF):
    """Camera block of ``A^-1 M A^-1`` (:func:`bundle_adjust`'s ``prior_jacobian``).

    The solve's normal equations, divided by ``prior_scale**2``: ``A dx = J^T W e / s_p^2 + P^T C_Z^-1 dtheta_Z``
    (``e`` the corners' errors, ``W`` the robust weights, ``P`` picks the intrinsics, ``C_Z`` the prior
    covariance), with the prior's own move ``C_Z^-1 dtheta_Z = G^T e_Z / s_Z^2`` (``G`` its reduced Jacobian).
    Its right-hand side's covariance, the rig's corners at ``sigma2`` and the prior solve's at ``s_Z^2``:
    ``M = k A + (1 - k) P^T C_Z^-1 P + X + X^T`` with ``k = sigma2 / s_p^2`` (the prior's part taken as the
    posterior it is, ``Cov(C_Z^-1 dtheta_Z) = C_Z^-1``, its own distortion prior included) and
    ``X = J^T W S G P / s_p^2`` over the corners both used (``S``), whose shared noise is ``s_Z^2``.
    A camera without a prior has zero prior rows and no ``G`` (its corners are the rig's alone).
    """
    from scipy.sparse import coo_matrix

    G = shared
    ps2 = prior_scale**2
    A = _normal_matrix(Jd, w, n_obs, ps2, prior_scale, held_cols)
    m = C * NF
    # S W G P / s_p^2 as a sparse (2 M, C NF): each pixel row in its camera's columns
    rows = np.repeat(np.arange(n_obs), NF)
    cols = (np.repeat(obs_cam, 2)[:, None] * NF + np.arange(NF)).ravel()
    vals = (G.reshape(n_obs, NF) * (w[:n_obs] / ps2)[:, None]).ravel()
    WG = coo_matrix((vals, (rows, cols)), shape=(n_obs, m)).tocsr()
    K = np.asarray((Jd[:n_obs].T @ WG).todense())  # (n, C NF)
    Ainv, Q = _camera_block_inverse(A, n_cam, K)
    k = sigma2 / ps2
    Y = Ainv[n_pose : n_pose + m]  # P A^-1, camera columns
    Ci = np.einsum("cji,cjk->cik", prior_rows, prior_rows) / ps2  # the prior's inverse covariance
    YC = np.einsum("cij,cjk->cik", Ci, Y.reshape(C, NF, -1)).reshape(m, -1)
    QY = Q @ Y
    return k * Ainv + (1.0 - k) * (Y.T @ YC) + QY + QY.T


def _covariance(J, r, n_obs, loss, f_scale, C, free_i, held_f, n_pose, n_intr, free_cams, cam_rvec, optimized,
                prior_scale, *, shared=None, obs_cam=None, prior_rows=None):
    """Marginal (C, 9, 9) intrinsics covariance, (C, C, 3, 3) camera rotation covariance and the
    residual scale (px) at a solution (with ``shared``, the estimator's sandwich: :func:`_sandwich`)."""
    cov = np.full((C, N_INTR, N_INTR), np.nan)
    f2 = f_scale * f_scale
    _, w = _robust_weights(r, loss, f2, n_obs)
    n = J.shape[1]
    dof = max(n_obs - n, 1)
    sigma2 = float(np.sum(w[:n_obs] * r[:n_obs] ** 2) / dof)
    Jd = J.tocsr()
    n_cam = n_pose + n_intr
    held_cols = n_pose + np.flatnonzero(held_f.ravel()) if optimized else np.zeros(0, np.int64)
    if shared is not None and optimized:
        Ainv = _sandwich(Jd, w, sigma2, n_obs, prior_scale, n_pose, n_cam, held_cols, shared, obs_cam, prior_rows,
                         C, int(free_i.sum()))
    else:
        # whitened: pixel rows by the residual scale, prior rows by the scale they were written in
        Ainv = _camera_block_inverse(_normal_matrix(Jd, w, n_obs, sigma2, prior_scale, held_cols), n_cam)
    # rotation vector -> left perturbation: d = J_l(r) dr
    Jl = _left_jacobian(cam_rvec[free_cams]) if free_cams.size else np.zeros((0, 3, 3))
    rcov = np.zeros((C, C, 3, 3))
    for a, ca in enumerate(free_cams):
        for b, cb in enumerate(free_cams):
            blk = Ainv[6 * a : 6 * a + 3, 6 * b : 6 * b + 3]
            rcov[ca, cb] = Jl[a] @ blk @ Jl[b].T
    if not optimized:
        return cov, rcov, float(np.sqrt(sigma2))
    NF = int(free_i.sum())
    idx = np.flatnonzero(free_i)
    for c in range(C):
        sl = slice(n_pose + c * NF, n_pose + (c + 1) * NF)
        cov[c][np.ix_(idx, idx)] = Ainv[sl, sl]
        gone = idx[held_f[c]]
        cov[c][gone, :] = np.nan
        cov[c][:, gone] = np.nan
    return cov, rcov, float(np.sqrt(sigma2))


def reduced_intrinsics_jacobian(
    obs_board: np.ndarray,
    obs_points: np.ndarray,
    obs_uv: np.ndarray,
    *,
    intrinsics: np.ndarray,
    board_rvec: np.ndarray,
    board_tvec: np.ndarray,
    held: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """One camera's reprojection errors at its own solution and their Jacobian in its intrinsics with
    every view's board pose projected out (its Schur complement), as :func:`bundle_adjust`'s ``prior_jacobian``
    needs for the corners of that camera's own solve.

    Parameters
    ----------
    obs_board : (M,) int ndarray
        View (board pose) index of every corner.
    obs_points : (M, 3) float ndarray
        The corner in the board frame.
    obs_uv : (M, 2) float ndarray
        Its observed pixel.
    intrinsics : (9,) float ndarray
        ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` of the camera (its solution).
    board_rvec, board_tvec : (V, 3) float ndarray
        Board -> camera pose of every view (its solution).
    held : (9,) bool ndarray, optional
        Intrinsics the solve held (zero columns).

    Returns
    -------
    residuals : (M, 2) float ndarray
        Projection minus observation, px.
    jacobian : (M, 2, 9) float ndarray
        ``(I - J_b (J_b^T J_b)^-1 J_b^T) J_i`` per view (``J_i``, ``J_b``: the view's rows in the intrinsics
        and its board pose), so that ``jacobian^T jacobian / sigma^2`` is the intrinsics' information from
        these corners.
    sigma : float
        Residual scale per coordinate, px (degrees of freedom ``2 M`` less the free intrinsics and ``6 V``).

    Raises
    ------
    ValueError
        When the arrays' shapes disagree.
    """
    held = np.zeros(N_INTR, bool) if held is None else np.asarray(held, dtype=bool).reshape(-1)
    if held.shape != (N_INTR,):
        raise ValueError(f"held must be ({N_INTR},) bool, got {held.shape}")
    intr = np.asarray(intrinsics, dtype=np.float64).reshape(-1)
    if intr.shape != (N_INTR,):
        raise ValueError(f"intrinsics must have shape ({N_INTR},), got {intr.shape}")
    obs_cam = np.zeros(np.asarray(obs_board).reshape(-1).shape[0], np.int64)
    oc, ob, X, uv, intr0, crv, ctv, brv, btv = _observations(obs_cam, obs_board, obs_points, obs_uv, intr[None],
                                                            np.zeros(3), np.zeros(3), board_rvec, board_tvec)
    free_i = ~held
    u = _Unknowns(intr0, crv, ctv, brv, btv, reference=0, optimize_intrinsics=True, free_i=free_i)
    problem = _Problem(u, oc, ob, X, uv, held_f=np.zeros((1, u.NF), bool), prior_rows=None, prior_mean=intr0)
    p = u.pack()
    D = problem.blocks(p)  # (M, 2, 6 + NF + 6); the camera pose's 6 are the reference's, not unknowns
    Ji, Jb = D[:, :, 6 : 6 + u.NF], D[:, :, 6 + u.NF :]
    V = brv.shape[0]
    BB = np.zeros((V, 6, 6))
    BI = np.zeros((V, 6, u.NF))
    np.add.at(BB, ob, np.einsum("mak,mal->mkl", Jb, Jb))
    np.add.at(BI, ob, np.einsum("mak,mal->mkl", Jb, Ji))
    coef = np.linalg.solve(BB, BI)  # (V, 6, NF)
    Jt = np.zeros((ob.shape[0], 2, N_INTR))
    Jt[:, :, free_i] = Ji - Jb @ coef[ob]
    r = problem.residuals(p).reshape(-1, 2)
    dof = max(r.size - u.NF - 6 * V, 1)
    return r, Jt, float(np.sqrt(np.sum(r**2) / dof))
