"""Scores of an armature against a hand-made or simulated skeleton and its rigid parts.

What the rig's accuracy is judged by (docs/armature-format.md, "Where it goes wrong"):

* :func:`articulation_bends`: how far every true joint bends during a sequence -- the largest change,
  over frames, of the angle between the bone that ends at the joint and each bone that starts there
  (positions only: a twist about a bone is not seen);
* :func:`articulation_scores`: a true articulation counts as found when a found one lies within
  ``tol`` (5 %) of the subject's size, median distance over frames; recall over the true
  articulations that bend by at least ``min_bend`` (10 degrees), precision over the found ones against
  every true articulation (one that barely bends included: a joint found there is not wrong);
* :func:`segment_agreement`: per-vertex agreement of a segmentation with the true rigid parts --
  *purity* (the share of vertices whose segment's majority part is their own: fused parts lower it)
  and *completeness* (the share whose part's majority segment is their own: cut parts lower it);
* :func:`bending_parts`: the true parts joined across the joints that do not bend (no motion can
  separate them).

Written by hand: a few lines of array arithmetic that no library offers in this form.
"""

from __future__ import annotations

import numpy as np

__all__ = ["articulation_bends", "articulation_scores", "segment_agreement", "bending_parts"]


def _joints(joints, name: str = "joints") -> np.ndarray:
    J = np.asarray(joints, dtype=np.float64)
    if J.ndim != 3 or J.shape[2] != 3 or J.shape[0] < 1:
        raise ValueError(f"{name} must have shape (T, K, 3) with T >= 1, got {J.shape}")
    return J


def articulation_bends(joints, parents) -> np.ndarray:
    """Degrees every joint bends over a sequence (0 for the root and the tips).

    Parameters
    ----------
    joints : (T, K, 3) float array_like
        Joint positions per frame.
    parents : (K,) int array_like
        Parent of every joint (-1: the root).

    Returns
    -------
    (K,) float ndarray
        For joint ``j`` with parent ``p``: the largest, over the bones ``j -> c`` that start at it, of
        the range over frames of the angle between ``j - p`` and ``c - j``.
    """
    J = _joints(joints)
    par = np.asarray(parents).reshape(-1)
    if len(par) != J.shape[1] or not np.issubdtype(par.dtype, np.integer) or par.min(initial=0) < -1 \
            or par.max(initial=-1) >= len(par):
        raise ValueError(f"parents must be {J.shape[1]} joint indices (-1 for the root), got {par!r}")
    out = np.zeros(J.shape[1])
    for j in range(J.shape[1]):
        p = par[j]
        if p < 0:
            continue
        a = J[:, j] - J[:, p]
        for c in np.flatnonzero(par == j):
            b = J[:, c] - J[:, j]
            cos = (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
            ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
            out[j] = max(out[j], float(ang.max() - ang.min()))
    return out


def articulation_scores(found, true, *, size: float, articulates=None, bending=None, tol: float = 0.05) -> dict:
    """Recall and precision of found articulations against true ones.

    Parameters
    ----------
    found : (T, F, 3) float array_like
        Found articulations per frame.
    true : (T, K, 3) float array_like
        True joints per frame.
    size : float
        The subject's size (> 0).
    articulates : (K,) bool array_like, optional
        True joints that are articulations (default all): what a found one may match.
    bending : (K,) bool array_like, optional
        True articulations that bend enough to be found (default ``articulates``): what recall counts.
    tol : float
        Fraction of ``size`` within which a found articulation matches (median over frames).

    Returns
    -------
    dict
        ``recall``, ``precision``, ``found`` (F), ``bending`` (number counted for recall),
        ``error`` (median over the bending articulations of the distance to the nearest found one,
        fraction of size; nan without found ones), ``distances`` ((F, K) median distances / size).
    """
    Fd, Tr = _joints(found, "found"), _joints(true, "true")
    if Fd.shape[0] != Tr.shape[0]:
        raise ValueError(f"found and true must have the same frames, got {Fd.shape[0]} and {Tr.shape[0]}")
    if not (np.isfinite(size) and size > 0):
        raise ValueError(f"size must be > 0, got {size}")
    K = Tr.shape[1]
    art = np.ones(K, bool) if articulates is None else np.asarray(articulates, dtype=bool).reshape(-1)
    bend = art.copy() if bending is None else np.asarray(bending, dtype=bool).reshape(-1)
    if art.shape != (K,) or bend.shape != (K,):
        raise ValueError(f"articulates and bending must have {K} entries")
    if Fd.shape[1] == 0 or not art.any():
        return {"recall": 0.0, "precision": 0.0, "found": int(Fd.shape[1]), "bending": int(bend.sum()),
                "error": float("nan"), "distances": np.zeros((Fd.shape[1], K))}
    D = np.nanmedian(np.linalg.norm(Fd[:, :, None] - Tr[:, None, :], axis=3), axis=0) / float(size)
    near = D[:, bend].min(0) if bend.any() else np.zeros(0)
    return {
        "recall": float((near < tol).mean()) if bend.any() else 1.0,
        "precision": float((D[:, art].min(1) < tol).mean()),
        "found": int(Fd.shape[1]),
        "bending": int(bend.sum()),
        "error": float(np.median(near)) if bend.any() else float("nan"),
        "distances": D,
    }


def segment_agreement(labels, truth) -> tuple[float, float]:
    """Purity and completeness of a segmentation against the true parts (per vertex, 0..1).

    Parameters
    ----------
    labels, truth : (V,) int array_like
        Found segment and true part of every vertex (integers >= 0).

    Returns
    -------
    purity : float
        Share of the vertices whose segment's majority true part is their own (1: no fused parts).
    completeness : float
        Share of the vertices whose true part's majority segment is their own (1: no cut parts).
    """
    L = np.asarray(labels).reshape(-1)
    G = np.asarray(truth).reshape(-1)
    if L.shape != G.shape or len(L) == 0:
        raise ValueError(f"labels and truth must have the same length > 0, got {L.shape} and {G.shape}")
    if not (np.issubdtype(L.dtype, np.integer) and np.issubdtype(G.dtype, np.integer)) or L.min() < 0 or G.min() < 0:
        raise ValueError("labels and truth must be integers >= 0")
    C = np.zeros((int(L.max()) + 1, int(G.max()) + 1))
    np.add.at(C, (L, G), 1.0)
    return float(C.max(1).sum() / len(L)), float(C.max(0).sum() / len(L))


def bending_parts(part_of_vertex, part_parent, bends) -> np.ndarray:
    """The true parts joined across the joints that do not bend.

    Parameters
    ----------
    part_of_vertex : (V,) int array_like
        True part of every vertex, ``0 .. P-1``.
    part_parent : (P,) int array_like
        Parent part of every part (-1: none).
    bends : (P,) bool array_like
        Whether the joint between a part and its parent bends.

    Returns
    -------
    (V,) int ndarray
        Part of every vertex after joining, ``0 .. Q-1``.
    """
    pv = np.asarray(part_of_vertex).reshape(-1)
    pp = np.asarray(part_parent).reshape(-1)
    b = np.asarray(bends, dtype=bool).reshape(-1)
    if pp.shape != b.shape or len(pv) == 0 or pv.min() < 0 or pv.max() >= len(pp):
        raise ValueError("part_of_vertex must index part_parent, and bends must have one entry per part")
    root = np.arange(len(pp))
    for i in range(len(pp)):  # follow the parents while the joint does not bend
        r = i
        for _ in range(len(pp)):
            if pp[r] < 0 or b[r]:
                break
            r = pp[r]
        root[i] = r
    _, inv = np.unique(root[pv], return_inverse=True)
    return inv.astype(np.int64)
