"""Which limb of a take's spine every vertex of a template lies on, or the body: cut where the section narrows.

A take's spine (Brostow et al. 2004, :mod:`pipeline.spine`) is built from every frame's visual hull, so it
does not share the tracking's drift; but each limb axis starts at a junction in the middle of the body, so
the nearest axis (or the heaviest bone, :func:`pipeline.armature_limbs.vertex_limbs`) hands the limbs much
of the body. :func:`template_labels` finds where each limb leaves the body from the template's own shape:

1. Stations along every limb axis, one mesh edge apart; at each, rays in the plane normal to the axis give
   the distance to the surface all round (the section's radii; a station outside the mesh has none).
2. The body's sections are those within one limb radius of the junction, the limb's those of the distal
   half of its axis. Walking in from the tip, the limb ends at the first station whose section is nearer
   the body's than the limb's just distal of it (above the geometric mean of the two) in its median radius
   (smoothed over one limb radius of stations: the section widens into the body) or in its widest radius
   (scaled by the limb's own widest over median: the section reaches into the body, as where a starfish's
   arm meets the lobes of its disc), or that lies outside the mesh.
3. A vertex is on the limb when its nearest point on the axis lies beyond that cut and it is no further
   from the axis than the widest section within one limb radius of that point (the template's own
   section there); on two limbs, the one it is relatively nearer to.
4. Proximal of the cut the limb may still lie beside the body (an upper arm hanging against the torso, an
   outer hip, an arm's root in a disc), where the section around the spine's axis is the body's and the axis
   itself may run along the crease rather than through the limb. The limb's own centre line goes on from
   the cut inward, one mesh edge a step, in the limb's own frame: the rays of each section that stay within
   the limb's diameter (its free side) are fitted a circle and the centre moves to it. The walk stops where
   those rays do not cover one contiguous half of the directions (inside the body; a flat body bounded by
   its two faces only), where the circle is nearer the body's radius than the limb's (geometric mean, as
   the cut) or grows by more than the step (the surface turns more across the limb than along it: the
   body's, which the limb meets there), outside the mesh, or as far in as the axis's own cut. A vertex within that circle of the
   centre line (and one mesh edge: the circle runs through the surface) is on the limb too. Every limb
   keeps its largest connected piece of the template; everything else is the body.

With every frame's surface (``surfaces=``: the take's per-frame surfaces, free of the tracking's drift),
the body is also split by its motion near the limbs: the body-labelled template follows each frame's
surface as one rigid piece (trimmed ICP, frame to frame from the template's frame), and so does the
proximal half of every limb (its vertices nearer the body than the limb's median). A body vertex that
the body's motion does not keep on the surfaces (its root mean square distance over the frames above one
mesh edge, the surfaces' resolution) and that the motion of the limb nearest to it keeps nearer goes to
that limb (the outer hip and shoulder, an arm hanging against the body); then every limb keeps
its largest connected piece again.

The cut follows the subject: the limb's and the body's radii come from the template, the window from the
limb's radius, the step from the mesh; no length or ratio is set by hand (the geometric mean is the
midpoint of two radii on a scale of ratios; a ray from inside a round section crosses at most its diameter;
a limb beside the body shows at least half its round; a surface steeper than 45 degrees to the axis is
turning away from it); the motion split's threshold is the mesh's edge and its one
fixed choice the share of nearest pairs a rigid fit keeps (80 %). Written by hand: sections of a mesh along a curved axis and
the walk from the tip are no library's; the rays are trimesh's (Embree when installed), the nearest
points scipy's KD-tree; the rigid fit is Kabsch's (the trimmed ICP around it is a few lines).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.armature_limbs import BODY, check_limbs
from pipeline.mesh_primitives import check_mesh, check_points, edge_components, rigid_fit

__all__ = ["BODY", "template_labels", "axis_labels", "nearest_limb", "proximal_half", "root_tubes"]


_KEEP = 0.8  # the nearest pairs a rigid fit keeps (the rest: where the piece's surface moved apart from it)
_ITERATIONS = 30  # ICP rounds a frame at most
_RAYS = 16  # directions of every section (a hull's section has about as many sides as twice the cameras)
_COS45 = np.sqrt(0.5)  # a surface steeper than 45 degrees to a tube's radial direction turns across the tube; a root's
# axis further than that from its limb's runs across the limb


def template_labels(spine, vertices, faces, *, reference: int | None = None, surfaces=None) -> np.ndarray:
    """The spine limb of every template vertex, or :data:`BODY`.

    Parameters
    ----------
    spine : pipeline.spine_format.Spine or path
        The take's spine, its ``spine.json`` or the results directory that holds it.
    vertices : (V, 3) float array_like
        The template, in the spine's units and in the pose of the spine's frame ``reference``
        (a tracked template: the reference frame's surface, :func:`pipeline.track.track_results`).
    faces : (F, 3) int array_like
        Its triangles (a closed surface: a station is inside it when most of its rays leave through it).
    reference : int, optional
        Position of the template's frame in the spine (default:
        :func:`pipeline.armature_spine.reference_frame`); every limb axis must be seen there.
    surfaces : sequence of (n_f, 3) float array_like, optional
        The vertices of the take's surface at every frame of the spine, in its order (a results
        directory's ``meshes/``, :func:`pipeline.track_frames.surface_meshes`); the template's frame is the
        one at ``reference``. With them the body is also split by its motion (module docstring); without
        them (default) the labels come from the template's shape alone.

    Returns
    -------
    (V,) int64 ndarray
        Index into ``spine.limb_ids``, or :data:`BODY`.

    Raises
    ------
    ValueError
        Naming the parameter: not a spine, a mesh that is not (V, 3) / (F, 3) or indexes past its vertices,
        a reference outside the spine or without every limb
        (:class:`pipeline.armature_spine.NoCompleteFrameError`), surfaces that are not one (n, 3) point
        array for every frame of the spine.
    """
    from pipeline.armature_spine import reference_frame

    spine = _spine(spine)
    V, F = check_mesh(vertices, faces, min_vertices=1, min_faces=1)
    if reference is not None and (isinstance(reference, bool) or not isinstance(reference, (int, np.integer))):
        raise ValueError(f"reference must be a frame position (int) or None, got {reference!r}")
    ref = reference_frame(spine, prefer=reference)
    if surfaces is not None and len(surfaces) != len(spine.frame_indices):
        raise ValueError(f"surfaces must hold one surface for each of the spine's {len(spine.frame_indices)} frames, "
                         f"got {len(surfaces)}")
    return axis_labels([np.asarray(spine.axes[lid][ref], dtype=np.float64) for lid in spine.limb_ids], V, F,
                       surfaces=surfaces, frame=ref)


def axis_labels(axes, vertices, faces, *, surfaces=None, frame: int = 0) -> np.ndarray:
    """:func:`template_labels` with the limb axes given: polylines from their junction to their tip.

    Parameters
    ----------
    axes : sequence of (n_k, 3) float array_like
        One polyline per limb (n_k >= 2 points), from the junction in the body to the tip, in the pose of
        the template.
    vertices : (V, 3) float array_like
    faces : (F, 3) int array_like
    surfaces : sequence of (n_f, 3) float array_like, optional
        Every frame's surface vertices (:func:`template_labels`); the template's is ``surfaces[frame]``.
    frame : int
        Position of the template's frame in ``surfaces``.

    Returns
    -------
    (V,) int64 ndarray
        Index into ``axes``, or :data:`BODY`.
    """
    import trimesh

    V, F = check_mesh(vertices, faces, min_vertices=1, min_faces=1)
    polylines = []
    for a in axes:
        polylines.append(check_points(a, name="axes", min_points=2))
    mesh = trimesh.Trimesh(V, F, process=False)
    step = _edge_step(mesh)
    K = len(polylines)
    relative = np.full((len(V), K), np.inf)  # distance to the limb's axis over its section's radius
    for k, axis in enumerate(polylines):
        s, d, reach = _limb_reach(mesh, axis, V, step)
        on = np.isfinite(reach) & (d <= reach)
        relative[on, k] = d[on] / np.maximum(reach[on], 1e-12)
    labels = np.where(np.isfinite(relative).any(1), relative.argmin(1), BODY).astype(np.int64)
    labels = _largest_pieces(labels, mesh.edges_unique, K)
    if surfaces is None:
        return labels
    moved = _motion_split(V, labels, _surfaces(surfaces, frame), frame, K, step)
    return _largest_pieces(moved, mesh.edges_unique, K)


def _surfaces(surfaces, frame) -> list[np.ndarray]:
    out = [check_points(S, name="surfaces", min_points=1) for S in surfaces]
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or not 0 <= frame < len(out):
        raise ValueError(f"frame must be a position in surfaces (0..{len(out) - 1}), got {frame!r}")
    return out


def _motion_split(V: np.ndarray, labels: np.ndarray, surfaces: list, ref: int, K: int, step: float) -> np.ndarray:
    """Body vertices that the body's rigid motion keeps further than one mesh edge ``step`` (root mean
    square over the frames) from the surfaces, and the nearest limb's proximal half's motion nearer, go to
    that limb."""
    from scipy.spatial import cKDTree

    body = labels == BODY
    limbs = [np.flatnonzero(labels == k) for k in range(K)]
    if body.sum() < 3 or not any(len(i) >= 3 for i in limbs):
        return labels
    trees = [cKDTree(S) for S in surfaces]
    motion = _follow(V[body], trees, ref)
    sb = _mean_square(V[body], trees, motion)
    near = nearest_limb(V[body], V, labels)
    sk = np.full(len(sb), np.inf)
    for k, idx in enumerate(limbs):
        on = near == k
        if len(idx) < 3 or not on.any():
            continue
        sk[on] = _mean_square(V[body][on], trees, _follow(V[proximal_half(V, labels, k)], trees, ref, start=motion))
    move = (sk < sb) & (sb > step ** 2)
    out = labels.copy()
    out[np.flatnonzero(body)[move]] = near[move]
    return out


def nearest_limb(points, vertices, labels, *, min_vertices: int = 1) -> np.ndarray:
    """The limb nearest to every point: the limb whose nearest vertex is nearest.

    Parameters
    ----------
    points : (n, 3) float array_like
        The points to label (finite).
    vertices : (V, 3) float array_like
        The template's vertices (finite).
    labels : (V,) int array_like
        Limb of every vertex (0, 1, ...) or :data:`BODY`.
    min_vertices : int, keyword-only
        Limbs with fewer vertices are never nearest.

    Returns
    -------
    (n,) int64 ndarray
        The nearest limb's label, or :data:`BODY` for every point when no limb has ``min_vertices``.
    """
    from scipy.spatial import cKDTree

    X, V = check_points(points), check_points(vertices, name="vertices")
    lab = check_limbs(labels, len(V), name="labels").astype(np.int64)
    if not _is_int(min_vertices) or min_vertices < 1:
        raise ValueError(f"min_vertices must be an integer >= 1, got {min_vertices!r}")
    limbs = [np.flatnonzero(lab == k) for k in range(int(lab.max(initial=BODY)) + 1)]
    limbs = [idx if len(idx) >= min_vertices else idx[:0] for idx in limbs]
    if not any(len(idx) for idx in limbs) or len(X) == 0:
        return np.full(len(X), BODY, dtype=np.int64)
    gaps = np.stack([cKDTree(V[idx]).query(X)[0] if len(idx) else np.full(len(X), np.inf) for idx in limbs], 1)
    return gaps.argmin(1).astype(np.int64)


def proximal_half(vertices, labels, limb: int) -> np.ndarray:
    """The vertices of one limb nearer the body than the limb's median: the part that moves about its root.

    Parameters
    ----------
    vertices : (V, 3) float array_like
        The template's vertices (finite).
    labels : (V,) int array_like
        Limb of every vertex or :data:`BODY`; the body must have a vertex.
    limb : int
        The limb's label (>= 0).

    Returns
    -------
    (m,) int64 ndarray
        Indices of the limb's vertices whose distance to the nearest body vertex is at most the median of its
        vertices' (at least half of them; empty for a limb with no vertex).
    """
    from scipy.spatial import cKDTree

    V = check_points(vertices, name="vertices")
    lab = check_limbs(labels, len(V), name="labels").astype(np.int64)
    if not _is_int(limb) or limb < 0:
        raise ValueError(f"limb must be a limb's label (an integer >= 0), got {limb!r}")
    if not (lab == BODY).any():
        raise ValueError("labels: the body has no vertex")
    idx = np.flatnonzero(lab == int(limb))
    if len(idx) == 0:
        return idx
    gap = cKDTree(V[lab == BODY]).query(V[idx])[0]
    return idx[gap <= np.median(gap)]


def root_tubes(vertices, faces, labels) -> np.ndarray:
    """Body vertices on a limb's root, where the surface merged the limb into the body, given to the limb.

    A limb's root is its vertices within two of its radii of the body (its radius: their median distance to
    the principal axis of all its vertices); its tube is the principal axis of the root, pointing into the body:
    from the limb's centroid towards the centroid of the body vertices nearest the root's vertices (beside the
    body the limb sets the direction; where the root is all of the limb, the body does). The tube's radius is the
    root's median distance to that axis; a root whose axis lies more
    than 45 degrees from the limb's is about as wide as it is long and has no tube. A body vertex goes to the
    limb when its projection on the axis lies past the root's centroid and no more than one tube radius past
    the root's farthest vertex, it lies within the tube's radius and one mesh edge (the median edge) of the
    axis, and its normal is within 45 degrees of pointing away from the axis (the limb's own surface; a
    surface turning across the tube is the body's). In two tubes it goes to the one it is relatively nearer
    the axis of (distance over radius); then every limb keeps its largest connected piece of the mesh.

    Parameters
    ----------
    vertices : (V, 3) float array_like
        The template (finite).
    faces : (F, 3) int array_like
        Its triangles, all wound the same way (a closed surface: its normals are turned out of it, whichever way
        the triangles wind).
    labels : (V,) int array_like
        Limb of every vertex (0, 1, ...) or :data:`BODY`.

    Returns
    -------
    (V,) int64 ndarray
        The labels with those body vertices given to their limb, and every limb vertex outside its limb's largest
        connected piece given to the body. A limb whose root has fewer than 3 vertices (or no body) has no tube
        either.

    Raises
    ------
    ValueError
        Naming the parameter: a mesh that is not (V, 3) / (F, 3) or indexes past its vertices, edges whose median
        length is zero, labels that are not an integer >= :data:`BODY` for every vertex.
    """
    import trimesh

    from pipeline.mesh_primitives import outward_normals

    V, F = check_mesh(vertices, faces, min_vertices=1, min_faces=1)
    lab = check_limbs(labels, len(V), name="labels").astype(np.int64)
    K = int(lab.max(initial=BODY)) + 1
    mesh = trimesh.Trimesh(V, F, process=False)
    step = _edge_step(mesh)
    normals = outward_normals(V, F)
    relative = np.full((len(V), max(K, 1)), np.inf)
    for k in range(K):
        tube = _root_tube(V, lab, k)
        if tube is not None:
            relative[:, k] = _in_tube(V, normals, lab == BODY, *tube, step)
    give = np.isfinite(relative).any(1)
    out = lab.copy()
    out[give] = relative[give].argmin(1)
    return _largest_pieces(out, mesh.edges_unique, K)


def _edge_step(mesh) -> float:
    """The median length of the mesh's edges (its resolution); ValueError when that is zero."""
    step = float(np.median(mesh.edges_unique_length))
    if not step > 0:
        raise ValueError("vertices and faces must make a surface with edges of non-zero length")
    return step


def _root_tube(V: np.ndarray, labels: np.ndarray, k: int):
    """Limb ``k``'s root tube: (the root's centroid, the unit axis into the body, the radius, how far along the
    axis the root reaches), or None when the root has fewer than 3 vertices or its axis lies more than 45 degrees
    from the limb's."""
    from scipy.spatial import cKDTree

    idx, body = np.flatnonzero(labels == k), np.flatnonzero(labels == BODY)
    if len(idx) < 3 or not len(body):
        return None
    gap, nearest = cKDTree(V[body]).query(V[idx])
    centre, along = _principal_axis(V[idx])
    radius = np.median(np.linalg.norm(np.cross(V[idx] - centre, along), axis=1))
    near = gap <= 2 * radius
    root = V[idx[near]]
    if len(root) < 3:
        return None
    centre, axis = _principal_axis(root)
    if abs(axis @ along) < _COS45:  # a root about as wide as it is long: its axis is no direction of the limb's
        return None
    if (V[body[nearest[near]]].mean(0) - V[idx].mean(0)) @ axis < 0:  # from the limb to the body nearest its root
        axis = -axis
    radius = float(np.median(np.linalg.norm(np.cross(root - centre, axis), axis=1)))
    return centre, axis, radius, float(((root - centre) @ axis).max())


def _in_tube(V: np.ndarray, normals: np.ndarray, body: np.ndarray, centre: np.ndarray, axis: np.ndarray,
             radius: float, reach: float, step: float) -> np.ndarray:
    """(V,): every body vertex's distance to the tube's axis over its radius where :func:`root_tubes` puts it in
    the tube, inf elsewhere."""
    along = (V - centre) @ axis
    radial = (V - centre) - along[:, None] * axis
    d = np.linalg.norm(radial, axis=1)
    facing = (d > 0) & (np.einsum("ij,ij->i", normals, radial) >= _COS45 * d)
    inside = body & (along > 0) & (along <= reach + radius) & (d <= radius + step) & facing
    return np.where(inside, d / max(radius, 1e-12), np.inf)


def _principal_axis(X: np.ndarray):
    """(centroid, unit direction of largest spread) of the points ``X``."""
    centre = X.mean(0)
    return centre, np.linalg.svd(X - centre, full_matrices=False)[2][0]


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _follow(X: np.ndarray, trees: list, ref: int, start=None):
    """(R (n, 3, 3), t (n, 3)): the rigid motion carrying points X of frame ``ref`` onto every frame's
    surface, frame to frame out from ``ref``; with ``start`` (another piece's motions) each frame also tries
    that one's and keeps the closer fit."""
    n = len(trees)
    R, t = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    for order in (range(ref + 1, n), range(ref - 1, -1, -1)):
        r, s = np.eye(3), np.zeros(3)
        for f in order:
            fits = [_icp(X, trees[f], r, s)]
            if start is not None:
                fits.append(_icp(X, trees[f], start[0][f], start[1][f]))
            r, s, _ = min(fits, key=lambda x: x[2])
            R[f], t[f] = r, s
    return R, t


def _icp(X: np.ndarray, tree, R: np.ndarray, t: np.ndarray):
    """Trimmed point-to-point ICP from (R, t): (R, t, mean squared distance of the nearest pairs kept)."""
    for _ in range(_ITERATIONS):
        Y = X @ R.T + t
        d, j = tree.query(Y)
        keep = d <= np.quantile(d, _KEEP)
        R2, t2 = rigid_fit(Y[keep], tree.data[j[keep]])
        R, t = R2 @ R, R2 @ t + t2
        if np.linalg.norm(t2) < 1e-3 and np.abs(R2 - np.eye(3)).max() < 1e-5:
            break
    d = np.sort(tree.query(X @ R.T + t)[0])
    return R, t, float(np.mean(d[:max(1, int(_KEEP * len(d)))] ** 2))


def _mean_square(X: np.ndarray, trees: list, motion) -> np.ndarray:
    """(len(X),) every point's mean over the frames of its squared distance to the surface under ``motion``."""
    R, t = motion
    return np.mean([trees[f].query(X @ R[f].T + t[f])[0] ** 2 for f in range(len(trees))], axis=0)


def _spine(spine):
    """A Spine from a Spine, a spine.json or a results directory; ValueError naming ``spine``."""
    from pipeline.spine_format import Spine, read_spine

    if isinstance(spine, Spine):
        return spine
    if isinstance(spine, (str, Path)):
        path = Path(spine)
        path = path / "spine.json" if path.is_dir() else path
        if not path.is_file():
            raise ValueError(f"spine: no spine file at {path}")
        return read_spine(path)
    raise ValueError(f"spine must be a pipeline.spine_format.Spine or a path, got {type(spine).__name__}")


def _limb_reach(mesh, axis: np.ndarray, V: np.ndarray, step: float):
    """(s, d, reach) of every vertex for one limb axis: arc length of its nearest axis point, its distance
    to the limb's axis, and how far from that axis the limb reaches there (nan: not the limb)."""
    ss, P, T = _stations(axis, step)
    R = _section_radii(mesh, P, T)
    s, d = _nearest_on_polyline(V, axis)
    cut, window = _cut(ss, R)
    if cut is None:
        return s, d, np.full(len(V), np.nan)
    with np.errstate(all="ignore"):
        widest = _nan_stat(R, np.nanmax)
    reach_st = _running(np.where(ss >= cut, widest, np.nan), window, np.nanmax)
    reach = np.interp(s, ss, np.nan_to_num(reach_st, nan=-1.0))
    reach[(s < cut) | (reach < 0)] = np.nan
    i0 = int(np.flatnonzero(ss >= cut)[0])
    C, r = _root(mesh, ss, P, R, i0, window, step)
    if len(C):  # the limb's root beside the body: within its own section of its own centre line
        line = np.vstack([C[::-1], P[i0]])
        s2, d2 = _nearest_on_polyline(V, line)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
        # the fitted circle passes through the surface: a vertex within one mesh edge of it is on it
        r2 = np.interp(s2, arc, np.concatenate([r[::-1], r[:1]])) + step
        on = (s2 > 0) & (s2 < arc[-1]) & (d2 <= r2) & ~(d <= reach)
        d, reach = np.where(on, d2, d), np.where(on, r2, reach)
    return s, d, reach


def _root(mesh, ss: np.ndarray, P: np.ndarray, R: np.ndarray, i0: int, window: int, step: float):
    """(centres (m, 3), radii (m,)) of the limb's own sections proximal of its cut (station ``i0``), one mesh
    edge apart from the cut inward: the limb's root where it lies beside the body (an upper arm against the
    torso, an outer hip, an arm's root in a disc), which the spine's axis does not run through.

    Each step goes on along the limb's own centre line; the section there keeps the rays that stay within
    the limb's diameter (twice its radius just distal of the cut: the far side of its own section), fits
    them a circle (the limb's section, its free side) and moves the centre to it. The walk stops where
    those rays do not cover one contiguous half of the directions (the limb no longer shows a free side:
    it is inside the body, or in a flat body whose section only the two faces bound), where the fitted
    radius is nearer the body's than the limb's (above their geometric mean, as :func:`_cut`) or grows by
    more than the step from the last section's (the cut's: the limb's radius just distal of it), outside
    the mesh, or after as many steps as the axis has before its cut."""
    with np.errstate(all="ignore"):
        med = _nan_stat(R, np.nanmedian)
    r_limb = _nan_stat(_running(med, window, np.nanmedian)[i0:i0 + window + 1], np.nanmedian)
    r_body = _nan_stat(med[ss <= _nan_stat(med[ss >= ss[-1] / 2], np.nanmedian)], np.nanmedian)
    j = min(len(ss) - 1, i0 + 2 * window)
    c, t = P[i0].copy(), P[i0] - P[j]
    if not (np.isfinite(r_limb) and np.isfinite(r_body)) or not np.linalg.norm(t) > 0:
        return np.zeros((0, 3)), np.zeros(0)
    t /= np.linalg.norm(t)
    th = np.linspace(0.0, 2 * np.pi, _RAYS, endpoint=False)
    centres, radii = [], []
    last = r_limb
    while len(centres) < i0:
        nxt = c + step * t
        Rr = _section_radii(mesh, nxt[None], t[None])[0]
        own = Rr <= 2 * r_limb
        if not np.isfinite(Rr).any() or _longest_run(own) < _RAYS / 2:
            break
        U, W = _section_frame(t[None])
        x, y, r = _circle(Rr[own] * np.cos(th[own]), Rr[own] * np.sin(th[own]))
        if not r <= min(np.sqrt(r_limb * r_body), last + step):
            break
        last = r
        if np.hypot(x, y) <= r:  # the predicted centre lies in the fitted section: move it to its centre
            nxt = nxt + x * U[0] + y * W[0]
        move = nxt - c  # the direction turns half-way to the last step's: the centre line bends with the limb
        t = t + move / np.linalg.norm(move)
        t /= np.linalg.norm(t)
        c = nxt
        centres.append(c)
        radii.append(r)
    return np.array(centres).reshape(-1, 3), np.array(radii)


def _longest_run(x: np.ndarray) -> int:
    """The longest circular run of True in a boolean array."""
    if x.all():
        return len(x)
    x = np.roll(x, -int(np.flatnonzero(~x)[0]))  # start on a False: no run wraps round
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], x.astype(np.int8), [0]]))))[::2]
    return int(runs.max()) if len(runs) else 0


def _circle(x: np.ndarray, y: np.ndarray):
    """(cx, cy, r): the least-squares circle through points (x, y) (Kasa's algebraic fit)."""
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    (a, b, c), *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    cx, cy = a / 2, b / 2
    return cx, cy, float(np.sqrt(max(c + cx * cx + cy * cy, 0.0)))


def _cut(ss: np.ndarray, R: np.ndarray):
    """(arc length where the limb starts, window in stations) from the sections' radii R (n, rays);
    (None, 0) when the axis has no section inside the mesh near its junction or over its distal half."""
    with np.errstate(all="ignore"):
        med = _nan_stat(R, np.nanmedian)
        widest = _nan_stat(R, np.nanmax)
    length = ss[-1]
    distal = ss >= length / 2
    r_limb = _nan_stat(med[distal], np.nanmedian)
    if not np.isfinite(r_limb):
        return None, 0
    near = ss <= r_limb  # within one limb radius of the junction: the body's sections
    r_body, w_body = _nan_stat(med[near], np.nanmedian), _nan_stat(widest[near], np.nanmedian)
    with np.errstate(all="ignore"):
        round_limb = _nan_stat((widest / med)[distal], np.nanmedian)  # the limb's own widest over median radius
    if not (np.isfinite(r_body) and np.isfinite(w_body) and np.isfinite(round_limb)):
        return None, 0
    step = ss[1] - ss[0] if len(ss) > 1 else 1.0
    window = max(1, int(round(r_limb / step)))
    smooth = _running(med, window, np.nanmedian)
    n = len(ss)
    # the limb's radius just distal of every station: its smoothed sections one to two windows further out
    ahead = np.array([_nan_stat(smooth[i + window:i + 2 * window + 1], np.nanmedian) if i + window < n else np.nan
                      for i in range(n)])
    ahead = np.where(np.isfinite(ahead), ahead, r_limb)
    # a section nearer the body's than the limb's (geometric mean), in its median or its widest radius; or
    # a station outside the mesh (nan)
    wide = ~(smooth <= np.sqrt(r_body * ahead)) | ~(widest <= np.sqrt(w_body * round_limb * ahead))
    wide &= ss < length - r_limb  # the tip's cap narrows to nothing: never a cut
    return (ss[np.flatnonzero(wide)[-1]] + step / 2 if wide.any() else 0.0), window


def _stations(axis: np.ndarray, step: float):
    """(arc length, point, unit tangent) every ``step`` along a polyline."""
    seg = np.linalg.norm(np.diff(axis, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    ss = np.arange(0.0, arc[-1] + step / 2, step) if arc[-1] > 0 else np.zeros(1)
    P = np.stack([np.interp(ss, arc, axis[:, c]) for c in range(3)], axis=1)
    T = np.gradient(P, axis=0) if len(P) > 1 else np.zeros_like(P)
    n = np.linalg.norm(T, axis=1, keepdims=True)
    T = np.where(n > 0, T / np.maximum(n, 1e-12), [[0.0, 0.0, 1.0]])
    return ss, P, T


def _section_radii(mesh, P: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(n, rays) distance from every station to the surface in its normal plane; nan rows outside the mesh."""
    n = len(P)
    U, W = _section_frame(T)
    th = np.linspace(0.0, 2 * np.pi, _RAYS, endpoint=False)
    D = (np.cos(th)[None, :, None] * U[:, None] + np.sin(th)[None, :, None] * W[:, None]).reshape(-1, 3)
    origins = np.repeat(P, _RAYS, axis=0)
    tri, ray, loc = mesh.ray.intersects_id(origins, D, multiple_hits=False, return_locations=True)
    R = np.full(n * _RAYS, np.nan)
    R[ray] = np.linalg.norm(loc - origins[ray], axis=1)
    # inside a closed surface every ray leaves through it: its first face turns away from the station
    outward = 1.0 if mesh.volume >= 0 else -1.0
    leaves = np.zeros(n * _RAYS, dtype=bool)
    leaves[ray] = outward * np.einsum("ij,ij->i", mesh.face_normals[tri], D[ray]) > 0
    R = R.reshape(n, _RAYS)
    R[leaves.reshape(n, _RAYS).sum(1) <= _RAYS // 2] = np.nan
    return R


def _section_frame(T: np.ndarray):
    """(U, W): unit vectors spanning the plane normal to every unit tangent T (n, 3); ray k of a section
    points along cos(2 pi k / rays) U + sin(2 pi k / rays) W."""
    helper = np.where(np.abs(T[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    U = np.cross(T, helper)
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    return U, np.cross(T, U)


def _nan_stat(x, fn):
    """fn over the finite entries of x (along the last axis for 2-D); nan where there are none."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        return float(fn(x)) if np.isfinite(x).any() else np.nan
    out = np.full(len(x), np.nan)
    ok = np.isfinite(x).any(1)
    out[ok] = fn(x[ok], axis=1)
    return out


def _running(x: np.ndarray, half: int, fn) -> np.ndarray:
    """fn over the finite entries of every window ``[i - half, i + half]``; nan where there are none."""
    pad = np.concatenate([np.full(half, np.nan), x, np.full(half, np.nan)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half + 1)
    return _nan_stat(win, fn)


def _nearest_on_polyline(X: np.ndarray, axis: np.ndarray):
    """(arc length, distance) of every point's nearest point on a polyline (K >= 2 points)."""
    A, B = axis[:-1], axis[1:]
    D = B - A
    L2 = np.maximum((D * D).sum(1), 1e-12)
    start = np.concatenate([[0.0], np.cumsum(np.sqrt((D * D).sum(1)))])[:-1]
    best_d = np.full(len(X), np.inf)
    best_s = np.zeros(len(X))
    for b in range(len(A)):  # one segment at a time: (V,) arrays, whatever the template's size
        t = np.clip((X - A[b]) @ D[b] / L2[b], 0.0, 1.0)
        dist = np.linalg.norm(X - (A[b] + t[:, None] * D[b]), axis=1)
        better = dist < best_d
        best_d[better] = dist[better]
        best_s[better] = start[b] + t[better] * np.sqrt(L2[b])
    return best_s, best_d


def _largest_pieces(labels: np.ndarray, edges: np.ndarray, K: int) -> np.ndarray:
    """Every limb keeps its largest edge-connected piece; its other pieces become the body."""
    same = labels[edges[:, 0]] == labels[edges[:, 1]]
    piece = edge_components(edges[same], len(labels))
    out = labels.copy()
    for k in range(K):
        idx = np.flatnonzero(labels == k)
        if len(idx):
            keep = np.bincount(piece[idx]).argmax()
            out[idx[piece[idx] != keep]] = BODY
    return out
