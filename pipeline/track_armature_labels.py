"""The labels the round's armature of the limbs follows (``track_with_armature(parts="limbs")``).

The template's labels with every frame's surface (:func:`_surface_labels`), a piece of the body that does not move with
it as a limb of its own (:func:`_unclaimed_limbs`), the limbs' roots given back (:func:`_rooted`), and the spine's limb
axes they index (:func:`_limb_chain`); docs/tracking.md, "The round's armature from the labels".
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("pipeline.track")

_JOB_PARTS = "parameters track.armature_parts 'limbs'"  # parts="limbs" in a job's words (a warning's job_message)


def _limb_chain(root: Path, labels, refi: int, n_frames: int):
    """``parts="limbs"``: (labels, the spine's limb axes at the reference position ``refi``), or None (one line
    says why) without labels or a spine of the take's frames that sees every limb of the labels there."""
    from pipeline.armature_files import spine_limb_axes
    from pipeline.spine_format import SpineFormatError, read_spine

    why = None
    if labels is None:
        why = "no labels"
    else:
        try:
            spine = read_spine(root / "spine.json")
            if spine.frame_count != n_frames:
                raise ValueError(f"it has {spine.frame_count} frames, the take {n_frames}")
            if not _body_measurable(labels):
                raise ValueError("the labels' body has too few vertices")
            return labels, spine_limb_axes(spine, labels, refi)
        except (OSError, SpineFormatError, ValueError) as exc:
            why = f"no usable spine.json ({exc})"
    log.warning("parts='limbs': the armature's parts come from the motion: %s", why,
                extra={"job_message": f"{_JOB_PARTS}: the armature's parts come from the motion: {why}"})
    return None


def _surface_points(by_frame: dict, frames: list[int]):
    """Every frame's surface vertices in ``frames`` order, or None (one line says why)."""
    from pipeline.meshio import load_mesh

    try:
        return [load_mesh(by_frame[k], largest=False)[0] for k in frames]
    except (OSError, ValueError) as exc:
        log.warning("parts='limbs': the surfaces cannot be read (%s); the armature's labels are the tracking's", exc,
                    extra={"job_message": f"{_JOB_PARTS}: the surfaces are unreadable ({exc}): the tracking's labels"})
        return None


def _surface_labels(root: Path, template: np.ndarray, faces: np.ndarray, refi: int, surfaces: list,
                    fallback: np.ndarray) -> np.ndarray:
    """``labels="spine"`` for the armature's parts: :func:`pipeline.template_labels.template_labels` with every frame's
    surface (the body also split by its motion there), or ``fallback`` (one line says why)."""
    from pipeline.template_labels import template_labels

    try:
        return np.asarray(template_labels(root, template, faces, reference=refi, surfaces=surfaces), dtype=np.int64)
    except ValueError as exc:
        log.warning("parts='limbs': the armature's labels are the tracking's (no labels from the surfaces: %s)", exc,
                    extra={"job_message": f"{_JOB_PARTS}: the tracking's labels (none from the surfaces: {exc})"})
        return fallback


def _unclaimed_limbs(vertices, faces, labels, axes, surfaces, *, reference: int = 0, keep: float = 0.5,
                    rounds: int = 3) -> tuple[np.ndarray, list]:
    """Pieces of the body that do not move with it, as limbs of their own (a limb the spine has no axis for).

    The body's rigid motion (the best rigid motion of its tracked vertices from the ``reference`` frame,
    :func:`pipeline.rigid_parts.rigid_motions`, refitted ``rounds`` times to the ``keep`` share of them it
    carries best) is applied to every body vertex; those it keeps further than one mesh edge (the mean edge of the
    template; root mean square over the frames) from the frame's surface, and that the motion of their nearest
    labelled limb does not keep within one mesh edge either (:func:`_claimed`: a limb the piece touches, as a forearm
    lying against a thigh, is not fused into it), form connected pieces over the mesh, and a
    piece with at least as many vertices as the smallest labelled limb (and leaving the body at least 8, to measure
    its noise on) becomes a limb, its axis the line from
    the centroid of its vertices next to the rest of the body to its vertex farthest from there.

    Parameters
    ----------
    vertices : (T, V, 3) float ndarray
        The tracked template.
    faces : (F, 3) int ndarray
    labels : (V,) int ndarray
        Limb of every vertex (index into ``axes``) or -1 for the body.
    axes : list of (n, 3) float ndarray
        Every limb's axis at frame ``reference``.
    surfaces : list of (n_t, 3) float ndarray
        Every frame's surface vertices.
    reference : int
    keep : float
        Share of the body's vertices its motion is refitted to.
    rounds : int

    Returns
    -------
    labels : (V,) int64 ndarray
        With the new limbs numbered after the given ones.
    axes : list of (n, 3) float ndarray
        The given axes, then the new limbs'.
    """
    from scipy.spatial import cKDTree

    from pipeline.mesh_primitives import edge_components
    from pipeline.rigid_parts import rigid_motions

    vs, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    out, axes = np.asarray(labels, dtype=np.int64).copy(), list(axes)
    body = np.flatnonzero(out == -1)
    sizes = np.bincount(out[out >= 0], minlength=len(axes))
    if not _body_measurable(out) or not (sizes > 0).any() or len(surfaces) != len(vs):
        return out, axes
    V = vs[reference]
    ids = body
    for _ in range(rounds):  # the body's motion, from the share of its vertices that follows it best
        R, t = rigid_motions(vs[:, ids], reference=reference)
        gap = np.linalg.norm(np.einsum("tij,vj->tvi", R, V[body]) + t[:, None] - vs[:, body], axis=2).mean(0)
        ids = body[np.argsort(gap)[:max(3, int(keep * len(body)))]]
    trees = [cKDTree(S) for S in surfaces]
    rms = _surface_rms(*rigid_motions(vs[:, ids], reference=reference), V[body], trees)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edge = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1).mean()
    off = np.zeros(len(V), dtype=bool)
    off[body[rms > edge]] = True
    candidates = np.flatnonzero(off)
    off[candidates[_claimed(vs, out, candidates, trees, reference, edge)]] = False
    inner = e[off[e[:, 0]] & off[e[:, 1]]]
    piece = edge_components(inner, len(V))
    rest = (out == -1) & ~off
    for p in np.unique(piece[off]):
        mine = off & (piece == p)
        if mine.sum() < sizes[sizes > 0].min() or not _body_measurable(np.where(mine, len(axes), out)):
            continue
        next_to_body = np.unique(e[mine[e[:, 0]] & rest[e[:, 1]], 0])
        if len(next_to_body) == 0:
            continue
        root = V[next_to_body].mean(0)
        far = V[mine][np.argmax(np.linalg.norm(V[mine] - root, axis=1))]
        out[mine] = len(axes)
        axes.append(np.stack([root, far]))
    return out, axes


def _rooted(template: np.ndarray, faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The armature's labels with the limbs' roots the body holds given back
    (:func:`pipeline.template_labels.root_tubes`), unless the body would keep too few vertices to measure the cuts'
    noise on (:func:`_body_measurable`)."""
    from pipeline.template_labels import root_tubes

    out = root_tubes(template, faces, labels)
    return out if _body_measurable(out) else labels


def _body_measurable(labels: np.ndarray) -> bool:
    """Whether the labels' body keeps enough vertices (twice :data:`pipeline.limb_segments.MIN_VERTICES`) for the
    round's :func:`pipeline.limb_segments.limb_segments` to measure the cuts' noise on."""
    from pipeline.armature_limbs import BODY
    from pipeline.limb_segments import MIN_VERTICES

    return bool((np.asarray(labels) == BODY).sum() >= 2 * MIN_VERTICES)


def _claimed(vs: np.ndarray, labels: np.ndarray, body: np.ndarray, trees: list, reference: int,
             edge: float) -> np.ndarray:
    """(len(body),) bool: the body vertices ``body`` that the rigid motion of their nearest labelled limb keeps within
    ``edge`` of every frame's surface (KD-trees ``trees``; root mean square over the frames); a limb of fewer than 3
    vertices is nobody's nearest. A limb's motion is that of its proximal half
    (:func:`pipeline.template_labels.proximal_half`, as :func:`pipeline.template_labels.template_labels` takes it),
    fitted to its tracked vertices ``vs`` (T, V, 3) from frame ``reference``."""
    from pipeline.rigid_parts import rigid_motions
    from pipeline.template_labels import nearest_limb, proximal_half

    V = vs[reference]
    near = nearest_limb(V[body], V, labels, min_vertices=3)
    out = np.zeros(len(body), dtype=bool)
    for k in np.unique(near[near >= 0]):
        mine = np.flatnonzero(near == k)
        rms = _surface_rms(*rigid_motions(vs[:, proximal_half(V, labels, k)], reference=reference), V[body[mine]],
                           trees)
        out[mine[rms <= edge]] = True
    return out


def _surface_rms(R: np.ndarray, t: np.ndarray, X: np.ndarray, trees: list) -> np.ndarray:
    """(n,): the distance of the points ``X`` carried by the rigid motions ``R`` (T, 3, 3), ``t`` (T, 3) from every
    frame's surface (KD-trees ``trees``), root mean square over the frames."""
    carried = np.einsum("tij,vj->tvi", R, X) + t[:, None]
    return np.sqrt(np.mean([tree.query(c)[0] ** 2 for tree, c in zip(trees, carried)], axis=0))
