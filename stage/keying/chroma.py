"""Chroma keying: a shading-invariant distance to the backdrop's colour.

A backdrop pixel in shadow or under uneven light is the backdrop colour scaled by
a factor ``k``; in OpenCV's YCrCb (offset removed) its luma and chroma both scale
by ``k``. So the chroma a backdrop pixel should have *at its own luma* is
``Y * n0`` with ``n0 = c0 / Y0`` the backdrop's chroma-to-luma ratio, and the
residual ``r = c - Y * n0`` is (up to noise) zero for the lit backdrop, its
shadows and darker folds, but not for a subject of another colour. A pixel's
backdrop distance is the Mahalanobis norm of ``r`` under the residual covariance
of the backdrop (the colour-difference keys of Vlahos / Smith & Blinn 1996,
"Blue screen matting", made shading-invariant as in Horprasert et al. 1999).
Near-black pixels have no measurable chroma; they count as foreground (a dark
subject must not be carved away), through a second term that requires the pixel
to be measurably backdrop-coloured.

The model is estimated robustly: the dominant saturated hue, then concentration
steps of a minimum-covariance-determinant estimate (Rousseeuw & Van Driessen
1999) on the residuals.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from stage.keying._color import M_C, M_Y, NAMED_COLORS_BGR, chi2_cdf, chi_radius
from stage.keying.params import KeyingError

__all__ = ["estimate_chroma_model", "chroma_distance", "chroma_matrix", "backdrop_share"]

_MIN_SAT = 8.0  # chroma units: below this a colour is too grey to vote for the backdrop hue
_HUE_HALF_WIDTH = np.deg2rad(20.0)


def _hue_of(bgr: tuple[int, int, int]) -> float:
    c = M_C @ np.asarray(bgr, float)
    return float(np.arctan2(c[1], c[0]))


def estimate_chroma_model(
    samples: np.ndarray, *, backdrop_color: str | None = None, iterations: int = 8, max_components: int = 2
) -> dict[str, Any]:
    """Fit the backdrop's chroma model to pixel samples.

    Parameters
    ----------
    samples : (K, 3) float ndarray
        BGR pixel values (from a background plate or sampled from the frames);
        the backdrop must be the dominant saturated colour.
    backdrop_color : str or None
        Restrict the backdrop hue to within 60 degrees of this named colour.
    iterations : int
        Concentration steps.
    max_components : int
        Residual Gaussians fitted (a second one covers e.g. a floor painted or lit
        differently from the wall); a pixel's distance is to the nearest one.

    Returns
    -------
    dict
        ``n0`` (2,) chroma-to-luma ratio (Cr, Cb), ``cov`` (2, 2) residual covariance
        (chroma units squared), ``hue`` (radians) of the main component,
        ``components`` (list of ``{"n0", "cov"}``), ``inlier_fraction``, ``luma_median``.

    Raises
    ------
    KeyingError
        When no saturated colour dominates the samples (no backdrop visible).
    """
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3 or s.shape[0] < 10:
        raise ValueError(f"samples must have shape (K, 3) with K >= 10, got {s.shape}")
    y = s @ M_Y
    c = s @ M_C.T
    sat = np.hypot(c[:, 0], c[:, 1])
    hue = np.arctan2(c[:, 1], c[:, 0])
    cand = (sat > _MIN_SAT) & (y > 4.0)
    if backdrop_color is not None:
        if backdrop_color not in NAMED_COLORS_BGR or backdrop_color in ("black", "white"):
            raise ValueError(f"backdrop_color must be a chromatic colour name (green, blue, red), got {backdrop_color!r}")
        h0 = _hue_of(NAMED_COLORS_BGR[backdrop_color])
        cand &= np.abs(np.angle(np.exp(1j * (hue - h0)))) < np.deg2rad(60)
    if cand.sum() < max(50, 0.01 * s.shape[0]):
        raise KeyingError("no backdrop colour found: too few saturated pixels in the samples")
    bins = 72
    hist = np.bincount(((hue[cand] + np.pi) / (2 * np.pi) * bins).astype(int) % bins, minlength=bins).astype(float)
    hist = hist + 0.5 * (np.roll(hist, 1) + np.roll(hist, -1))
    peak = (np.argmax(hist) + 0.5) / bins * 2 * np.pi - np.pi
    sel = cand & (np.abs(np.angle(np.exp(1j * (hue - peak)))) < _HUE_HALF_WIDTH)
    ok = y > 0
    n0, cov, inl = _fit_component(c, y, sel, ok, iterations)
    frac = float(inl.mean())
    if inl.sum() < max(50, 0.01 * s.shape[0]):
        raise KeyingError(f"no backdrop colour found: only {100 * frac:.2f} % of the samples fit a backdrop model")
    components = [{"n0": n0.tolist(), "cov": cov.tolist()}]
    covered = inl.copy()
    # a studio often has two greens (wall and floor, differently painted or lit): fit
    # further components to the backdrop-hue pixels the first one leaves out
    for _ in range(max_components - 1):
        rest = sel & ~covered
        if rest.sum() < 0.05 * sel.sum():
            break
        try:
            n1, cov1, inl1 = _fit_component(c, y, rest, ok & ~covered, iterations)
        except KeyingError:
            break
        if inl1.sum() < 0.05 * sel.sum():
            break
        components.append({"n0": n1.tolist(), "cov": cov1.tolist()})
        covered |= inl1
    return {
        "n0": n0.tolist(),
        "cov": cov.tolist(),
        "hue": float(np.arctan2(n0[1], n0[0])),
        "components": components,
        "inlier_fraction": float(covered.mean()),
        "luma_median": float(np.median(y[inl])),
    }


#: Chroma (units of :data:`M_C`) a pixel needs to count as a backdrop colour in :func:`backdrop_share`.
BACKDROP_MIN_SAT = 24.0


def backdrop_share(samples: np.ndarray) -> tuple[float, float]:
    """Share of the samples in the dominant saturated hue, and that hue (radians).

    A backdrop is a large region of one saturated colour: the share counts the samples
    whose chroma exceeds :data:`BACKDROP_MIN_SAT` and whose hue lies within 20 degrees
    of the most common saturated hue (a 72-bin histogram, neighbours added). Greys,
    wood and skin are too weakly saturated to count much.

    Parameters
    ----------
    samples : (K, 3) float ndarray
        BGR pixel values.

    Returns
    -------
    share : float
        In [0, 1].
    hue : float
    """
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3 or s.shape[0] == 0:
        raise ValueError(f"samples must have shape (K, 3) with K >= 1, got {s.shape}")
    c = s @ M_C.T
    sat = np.hypot(c[:, 0], c[:, 1])
    hue = np.arctan2(c[:, 1], c[:, 0])
    sel = sat > BACKDROP_MIN_SAT
    if not sel.any():
        return 0.0, 0.0
    bins = 72
    hist = np.bincount(((hue[sel] + np.pi) / (2 * np.pi) * bins).astype(int) % bins, minlength=bins).astype(float)
    hist = hist + 0.5 * (np.roll(hist, 1) + np.roll(hist, -1))
    peak = (np.argmax(hist) + 0.5) / bins * 2 * np.pi - np.pi
    near = sel & (np.abs(np.angle(np.exp(1j * (hue - peak)))) < _HUE_HALF_WIDTH)
    return float(near.mean()), float(peak)


def _fit_component(
    c: np.ndarray, y: np.ndarray, sel: np.ndarray, ok: np.ndarray, iterations: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concentration steps of one residual Gaussian, started from the samples ``sel``."""
    n0 = np.median(c[sel] / y[sel, None], axis=0)
    q99 = chi_radius(0.01, 2) ** 2
    # consistency factor of a covariance estimated from the Gaussian core inside chi2_2(0.99)
    consistency = 0.99 / chi2_cdf(q99, 4)
    r = c - y[:, None] * n0
    cov = np.cov(r[sel].T) + np.eye(2) * 0.25
    for _ in range(iterations):
        inv = np.linalg.inv(cov)
        d2 = np.einsum("ki,ij,kj->k", r, inv, r)
        inl = ok & (d2 < q99)
        if inl.sum() < 20:
            raise KeyingError("no backdrop colour found: the chroma model has no consistent inliers")
        yi = y[inl]
        n0 = (yi[:, None] * c[inl]).sum(0) / max((yi * yi).sum(), 1e-9)
        r = c - y[:, None] * n0
        new = np.cov(r[inl].T) * consistency + np.eye(2) * 0.25  # floor: uint8 quantization
        if np.allclose(new, cov, rtol=1e-4):
            cov = new
            break
        cov = new
    inv = np.linalg.inv(cov)
    d2 = np.einsum("ki,ij,kj->k", r, inv, r)
    return n0, cov, ok & (d2 < q99)


def chroma_matrix(model: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Linear maps from BGR to whitened residual and to chroma-along-backdrop in sigma units.

    Returns
    -------
    W : (2, 3) ndarray
        ``w = W @ bgr`` is the residual ``c - Y n0`` whitened by the backdrop covariance.
    A : (1, 3) ndarray
        ``A @ bgr`` is the pixel's chroma along the backdrop hue, in units of the residual
        spread along that hue.
    """
    return _chroma_matrix(tuple(np.ravel(model["n0"])), tuple(np.ravel(model["cov"])))


@lru_cache(maxsize=256)
def _chroma_matrix(n0_t: tuple, cov_t: tuple) -> tuple[np.ndarray, np.ndarray]:
    n0 = np.asarray(n0_t, float)
    cov = np.asarray(cov_t, float).reshape(2, 2)
    evals, evecs = np.linalg.eigh(cov)
    whiten = evecs @ np.diag(1.0 / np.sqrt(evals)) @ evecs.T
    resid = M_C - np.outer(n0, M_Y)  # (2, 3): residual as a function of BGR
    W = whiten @ resid
    u = n0 / max(np.linalg.norm(n0), 1e-12)
    sigma_u = float(np.sqrt(u @ cov @ u))
    A = (u @ M_C)[None, :] / sigma_u
    return W.astype(np.float32), A.astype(np.float32)


def chroma_distance(image: np.ndarray, model: dict[str, Any], *, t_hi: float) -> np.ndarray:
    """Backdrop distance of every pixel, in units of the backdrop's spread.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray
        BGR frame.
    model : dict
        From :func:`estimate_chroma_model`.
    t_hi : float
        Solid-foreground threshold; pixels whose chroma along the backdrop hue is
        below ``t_hi`` spreads (too dark or too grey to be backdrop) get a distance of
        at least ``t_hi`` minus that chroma.

    Returns
    -------
    (H, W) float32 ndarray
        ``max(min_k |whitened residual_k|, t_hi - chroma_along_backdrop)``, >= 0.
    """
    W, A = chroma_matrix(model)
    f = image.astype(np.float32)
    d = cv2.magnitude(cv2.transform(f, W[0:1]), cv2.transform(f, W[1:2]))
    for comp in model.get("components", [])[1:]:
        Wk, _ = chroma_matrix(comp)
        d = cv2.min(d, cv2.magnitude(cv2.transform(f, Wk[0:1]), cv2.transform(f, Wk[1:2])))
    along = cv2.transform(f, -A)  # -chroma along the backdrop hue
    dark = cv2.add(along, float(t_hi))
    return cv2.max(d, dark)
