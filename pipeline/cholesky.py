"""Sparse Cholesky of ``K + diag(d)`` with the symbolic analysis kept: the template tracker's solver.

Every round of :class:`pipeline.tracking.TemplateTracker` solves normal equations whose matrix is a
fixed sparse SPD part plus a diagonal that changes between rounds and frames. The fill-reducing
ordering and the elimination tree depend on the sparsity only, so they are computed once per take.
Hand-written glue because neither backend offers it whole: QDLDL (``qdldl``, when installed) keeps
its ordering between numeric updates; scipy's SuperLU, the fallback, cannot keep it and redoes it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["CholeskySystem"]


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
        self.cg_iterations = 0
        self._K = sp.csr_matrix(K)

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

    def solve_near(self, d: np.ndarray, b: np.ndarray, x0: np.ndarray, *, rtol: float = 1e-5,
                   max_iter: int = 6) -> np.ndarray:
        """Solve ``(K + diag(d)) x = b`` (N, k) by conjugate gradients preconditioned with the last
        factorisation (of a nearby diagonal), refactoring first when there is none or CG stalls.

        Between the rounds of one frame the pairs, hence ``d``, change little: a few CG steps
        reach ``rtol`` for a fraction of the cost of a numeric refactorisation. The default
        ``rtol`` (of the right-hand side's norm, per column) is a round's own accuracy, not the
        frame's: the next round re-pairs from it anyway (docs/tracking.md measures what 1e-4,
        1e-5 and 1e-6 move and cost).
        """
        d = np.asarray(d, dtype=np.float64)
        if self._solver is None:
            self.factor(d)
            return self.solve(b)
        K = self._K

        def matvec(x):
            return K @ x + d[:, None] * x

        x = np.array(x0, dtype=np.float64)
        r = b - matvec(x)
        bn = np.maximum(np.linalg.norm(b, axis=0), 1e-300)

        def converged(r):
            return bool(np.all(np.linalg.norm(r, axis=0) <= rtol * bn))

        if max_iter > 0 and converged(r):
            return x
        # the residual is tested before it is preconditioned: the last step's solve is not done for nothing
        z = self.solve(r)
        p = z.copy()
        rz = np.einsum("ij,ij->j", r, z)
        for step in range(1, max_iter + 1):
            Ap = matvec(p)
            alpha = rz / np.maximum(np.einsum("ij,ij->j", p, Ap), 1e-300)
            x += p * alpha
            r -= Ap * alpha
            if step == max_iter:
                break
            if converged(r):
                self.cg_iterations += step
                return x
            z = self.solve(r)
            rz_new = np.einsum("ij,ij->j", r, z)
            p = z + p * (rz_new / np.maximum(rz, 1e-300))
            rz = rz_new
        self.cg_iterations += max_iter
        self.factor(d)  # the diagonal moved too far: refactor
        return self.solve(b)

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
