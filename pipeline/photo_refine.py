"""Photo-consistent refinement of a visual-hull surface: each vertex moves inward to the depth
where the cameras' colours agree.

The visual hull (Laurentini 1994) cannot carve concavities: between the legs, under the belly
and at the junctions of limbs and body the silhouettes leave material that no camera's
outline removes, and even on convex parts a hull from a few cameras lies outside the subject
(its polyhedral cells, the marching-cubes level). The subject's surface, unlike empty space
inside the hull, looks the same from every camera that sees it (Lambertian shading and its
own texture): Kutulakos & Seitz 2000 ("A theory of shape by space carving") carve the voxels
whose projections disagree. This module is the surface-based form of that idea used by
"carved visual hulls" (Furukawa & Ponce 2006) and silhouette-and-stereo fusion (Esteban &
Schmitt 2004): the hull mesh is the starting surface and every vertex searches along its
inward normal for the depth of best multi-view agreement.

Per round:

1. **Cameras per vertex.** A camera counts for a vertex when the current mesh does not hide it
   (a z-buffer of the mesh's triangles rasterised into the camera, with a depth tolerance of
   half a voxel plus what the surface's slope makes of the sub-pixel offset), when the vertex
   faces it (its normal within ``max_angle`` of the viewing ray) and when its patch stays inside
   the camera's silhouette. Its weight falls linearly in the cosine of the viewing angle, from
   1 head-on to 0 at ``max_angle``: grazing views see the surface foreshortened and blurred and
   pull the match inward.
2. **Score along the normal.** At candidate depths ``d`` (``-outward .. inward`` voxels, steps
   of ``step``) the vertex's patch -- its nearest mesh neighbours within ``patch_radius``, each
   moved along its own normal (``v_j - d n_j``), so the patch keeps the surface's curvature
   where a flat tangent patch would cut into a limb -- is projected into every camera (the
   projection's Jacobian at the vertex, lens distortion included) and sampled bilinearly in
   the grey images. The score is the weighted mean normalised cross-correlation over the pairs
   of cameras; with ``z_c`` the zero-mean patch of camera ``c`` divided by
   ``sqrt(|x - mean|^2 + K sigma^2)`` (``sigma`` the sensor noise, so a flat patch scores near
   0, not at random), the weighted sum over pairs is
   ``(|sum_c w_c z_c|^2 - sum_c w_c^2 |z_c|^2) / 2``: one pass over the cameras, not over pairs.
   Candidates past the medial axis of the current surface (nearer to another part of it than
   to their own vertex: through a thin limb) are ruled out.
3. **Regularised offsets.** Each vertex's best depth (a parabola through the peak) is weighted
   by the peak's correlation times the weight of the camera pairs behind it (capped at 1; 0
   with fewer than two cameras or a peak at the end of the range), and the offsets are
   smoothed over the mesh by a screened Laplacian solve ``(W + lambda L) d = W d*``
   (``scipy.sparse.linalg.spsolve``, ``L`` the graph Laplacian), reweighted three times with
   Cauchy weights of each match's residual to the smooth solution (half a voxel): a vertex
   without texture follows its neighbours, and a wrong match neither makes a spike nor drags
   the unseen surface around it (Esteban & Schmitt 2004, section 4, weigh the texture force
   against smoothness alike).
4. Vertices move by ``-d n``; normals, visibility and the search are redone for the next round
   with the range shrunk around the new surface.

The silhouettes keep a camera out of a vertex's score where its patch would reach the
backdrop: there the colours mix with the backdrop and its spill, which are not the subject's.
Silhouette rims are *not* held in place: every point of a hull's surface lies on some camera's
silhouette cone, in the concavities too, so "on a mask edge" does not say "on the subject".

What the cameras cannot see stays as the hull has it: a vertex seen by fewer than two cameras
gets no match of its own and follows its neighbours through the smoothing (on a rig with every
camera above the floor, most of the excess under a quadruped's belly, which faces down).

Hand-written because no well-kept library does multi-view patch matching along a mesh's
normals on arrays (OpenMVS and COLMAP work on whole reconstructions from files); the pieces
that exist are used: OpenCV's ``remap`` for bilinear sampling and its distance transform for
the room inside the silhouettes, SciPy's k-d tree and sparse solver.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from calib.camera import Camera
from pipeline.mesh_primitives import check_mesh, vertex_normals

__all__ = ["refine_surface"]


def _check_inputs(vertices, faces, images, masks, cameras):
    v, f = check_mesh(vertices, faces, min_vertices=4, min_faces=1)
    cams = list(cameras)
    if len(cams) < 2 or not all(isinstance(c, Camera) for c in cams):
        raise ValueError("cameras must be a sequence of at least two calib.camera.Camera")
    imgs = list(images)
    if len(imgs) != len(cams):
        raise ValueError(f"images must hold one image per camera ({len(cams)}), got {len(imgs)}")
    grey = []
    for c, im in zip(cams, imgs):
        a = np.asarray(im)
        if not np.issubdtype(a.dtype, np.number) or a.dtype == bool:
            raise ValueError(f"images must hold numbers, got {a.dtype}")
        if a.ndim == 3 and a.shape[2] == 3:
            a = a.astype(np.float32) @ np.array([0.114, 0.587, 0.299], np.float32)  # BGR -> luma
        if a.ndim != 2 or a.shape != (c.height, c.width):
            raise ValueError(f"images must be (H, W) or (H, W, 3) of each camera's size, got "
                             f"{np.shape(im)} for a {c.width}x{c.height} camera")
        grey.append(np.ascontiguousarray(a, dtype=np.float32))
    ms = list(masks)
    if len(ms) != len(cams):
        raise ValueError(f"masks must hold one mask per camera ({len(cams)}), got {len(ms)}")
    for c, m in zip(cams, ms):
        if np.shape(m) != (c.height, c.width):
            raise ValueError(f"masks must be (H, W) of each camera's size, got {np.shape(m)}")
    return v, f.astype(np.int64), grey, [np.asarray(m, dtype=bool) for m in ms], cams


def _number(name: str, value: Any, *, strict: bool = True, high: float = np.inf) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not (np.isfinite(x) and (x > 0 if strict else x >= 0) and x < high):
        bound = "> 0" if strict else ">= 0"
        upper = f" and < {high:g}" if np.isfinite(high) else ""
        raise ValueError(f"{name} must be {bound}{upper}, got {value!r}")
    return x


def _integer(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def refine_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray],
    cameras: Sequence[Camera],
    *,
    voxel: float,
    inward: float = 4.0,
    outward: float = 1.0,
    step: float = 0.25,
    patch_radius: float = 2.0,
    patch_vertices: int = 40,
    noise_sigma: float | None = None,
    max_angle: float = 70.0,
    smoothness: float = 8.0,
    rounds: int = 1,
) -> np.ndarray:
    """Move the vertices of a hull surface along their normals to where the cameras agree.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Surface vertices, world units (those of the cameras).
    faces : (F, 3) int ndarray
        Triangles with outward normals (counter-clockwise seen from outside).
    images : sequence of (H, W, 3) BGR or (H, W) grey ndarray
        One image per camera, of the same instant.
    masks : sequence of (H, W) bool ndarray
        The silhouettes in the same images (the hull's).
    cameras : sequence of calib.camera.Camera
        At least two.
    voxel : float
        The surface's voxel size (world units); the lengths below are in voxels.
    inward, outward : float, optional
        Search range along the normal, voxels (a hull lies outside the subject: mostly inward).
    step : float, optional
        Depth step of the search, voxels.
    patch_radius : float, optional
        Radius of a vertex's patch (its mesh neighbours within it), voxels.
    patch_vertices : int, optional
        At most this many neighbours per patch (the nearest).
    noise_sigma : float or None, optional
        Sensor noise of the grey images (grey levels), which damps the correlation of flat
        patches; None: estimated from the images (Immerkaer 1996).
    max_angle : float, optional
        A camera counts for a vertex when the angle between the vertex's normal and the
        direction to the camera is below this (degrees); its weight falls linearly in the
        cosine from 1 (head-on) to 0 (at the limit).
    smoothness : float, optional
        Weight ``lambda`` of the Laplacian smoothing of the offsets (a match's confidence is
        at most about 1).
    rounds : int, optional
        Search-and-move rounds (normals and visibility redone each round).

    Returns
    -------
    (V, 3) float ndarray
        The refined vertices (the faces are unchanged).

    Raises
    ------
    ValueError
        A malformed argument (the message names it).

    References
    ----------
    K. N. Kutulakos, S. M. Seitz, "A theory of shape by space carving", IJCV 38(3), 2000.
    Y. Furukawa, J. Ponce, "Carved visual hulls for image-based modeling", ECCV 2006.
    C. Hernandez Esteban, F. Schmitt, "Silhouette and stereo fusion for 3D object modeling",
    CVIU 96(3), 2004.
    J. Immerkaer, "Fast noise variance estimation", CVIU 64(2), 1996.
    """
    v, f, grey, ms, cams = _check_inputs(vertices, faces, images, masks, cameras)
    vox = _number("voxel", voxel)
    inward = _number("inward", inward, strict=False)
    outward = _number("outward", outward, strict=False)
    if inward + outward <= 0:
        raise ValueError("inward + outward must be > 0 (voxels): nothing to search")
    step = _number("step", step)
    if (inward + outward) / step < 2:
        raise ValueError(f"step must be at most half the search range (inward + outward = {inward + outward:g} "
                         f"voxels) for a peak to be found, got {step!r}")
    radius = _number("patch_radius", patch_radius) * vox
    k = _integer("patch_vertices", patch_vertices, 3)
    sigma = _noise_sigma(grey) if noise_sigma is None else _number("noise_sigma", noise_sigma, strict=False)
    cos_max = float(np.cos(np.radians(_number("max_angle", max_angle, high=90.0))))
    smoothness = _number("smoothness", smoothness, strict=False)
    rounds = _integer("rounds", rounds, 1)

    lap = _graph_laplacian(f, len(v))
    room = [_room(m) for m in ms]
    lo, hi = -outward, inward
    for _ in range(rounds):
        normals = vertex_normals(v, f)
        vis = _visibility(v, f, normals, cams, room, vox, cos_max, radius)
        depths = np.arange(lo, hi + 1e-9, step) * vox
        score = _scores(v, normals, vis, depths, grey, cams, radius, k, sigma)
        score[_past_medial_axis(v, normals, depths)] = -1.0
        target, weight = _best_depths(score, depths, vis)
        d = _robust_offsets(target, weight, lap, smoothness, vox)
        v = v - d[:, None] * normals
        span = max(hi - lo, 4 * step) / 4.0  # the next round looks around the new surface
        lo, hi = -span, span
    return v


# -- steps -----------------------------------------------------------------------------------


def _noise_sigma(grey: Sequence[np.ndarray]) -> float:
    """Median over the images of Immerkaer's (1996) noise estimate: the mean absolute response
    to the difference of two Laplacians, which cancels smooth image content."""
    import cv2

    kern = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    est = []
    for g in grey:
        r = cv2.filter2D(g, cv2.CV_32F, kern)[1:-1, 1:-1]
        est.append(np.sqrt(np.pi / 2.0) * float(np.abs(r).mean()) / 6.0)
    return float(np.median(est))


def _room(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32: pixels from each foreground pixel to the nearest background (0 outside)."""
    import cv2

    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)


def _graph_laplacian(f: np.ndarray, n: int):
    from scipy.sparse import coo_matrix, diags

    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    a = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    return diags(np.asarray(a.sum(axis=1)).ravel()) - a


def _visibility(v: np.ndarray, f: np.ndarray, normals: np.ndarray, cams: Sequence[Camera],
                room: Sequence[np.ndarray], vox: float, cos_max: float, radius: float) -> np.ndarray:
    """(C, V) float weight of each camera for each vertex.

    0 where the mesh's z-buffer hides the vertex, where it faces away by more than the limit
    or where its patch would reach past the silhouette; else rising linearly in the cosine of
    the viewing angle to 1 for a camera looking straight at it (grazing views see the surface
    foreshortened and blurred: they bias the match).
    """
    vis = np.zeros((len(cams), len(v)), np.float64)
    for ci, cam in enumerate(cams):
        to_cam = cam.center[None, :] - v
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        cosine = np.einsum("ij,ij->i", to_cam, normals)
        pix, z = cam.project(v, return_depth=True)
        inside = cam.in_image(pix, margin=1.0) & (z > 0)
        zbuf = _zbuffer(pix, z, f, cam.height, cam.width)
        col = np.clip(np.round(pix[:, 0]).astype(np.int64), 0, cam.width - 1)
        row = np.clip(np.round(pix[:, 1]).astype(np.int64), 0, cam.height - 1)
        # the buffer is read at the vertex's nearest pixel centre, up to 0.71 pixels away, where an
        # oblique surface's own depth differs by that distance times the tangent of the view angle
        slope = np.sqrt(1.0 - np.clip(cosine, 0.17, 1.0) ** 2) / np.clip(cosine, 0.17, 1.0)
        seen = z <= zbuf[row, col] + 0.5 * vox + 0.71 * slope * z / float(cam.K[0, 0])
        clear = room[ci][row, col] >= radius * float(cam.K[0, 0]) / np.maximum(z, 1e-9)
        ok = inside & seen & clear
        vis[ci] = np.where(ok, np.clip((cosine - cos_max) / (1.0 - cos_max), 0.0, 1.0), 0.0)
    return vis


def _zbuffer(pix: np.ndarray, z: np.ndarray, f: np.ndarray, h: int, w: int, max_size: int = 64) -> np.ndarray:
    """(H, W) depth of the nearest triangle at every pixel centre (inf: none); triangles are
    rasterised together, one pass per pixel offset inside their bounding boxes."""
    zbuf = np.full(h * w, np.inf, np.float64)
    tri = pix[f]  # (F, 3, 2)
    tz = z[f]
    ok = (tz > 0).all(axis=1)
    lo = np.floor(tri.min(axis=1) + 0.5).astype(np.int64)  # first pixel centre inside the box
    hi = np.floor(tri.max(axis=1) + 0.5).astype(np.int64)
    size = np.minimum(hi - lo + 1, max_size)
    ok &= (hi[:, 0] >= 0) & (hi[:, 1] >= 0) & (lo[:, 0] < w) & (lo[:, 1] < h)
    idx = np.flatnonzero(ok)
    a, b, c = tri[idx, 0], tri[idx, 1], tri[idx, 2]
    den = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    good = np.abs(den) > 1e-12
    idx, a, b, c, den = idx[good], a[good], b[good], c[good], den[good]
    za, zb, zc = tz[idx, 0], tz[idx, 1], tz[idx, 2]
    for dy in range(int(size[idx, 1].max(initial=0))):
        for dx in range(int(size[idx, 0].max(initial=0))):
            sel = (size[idx, 0] > dx) & (size[idx, 1] > dy)
            px = (lo[idx, 0] + dx).astype(np.float64)
            py = (lo[idx, 1] + dy).astype(np.float64)
            l1 = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1])) / den
            l2 = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / den
            l0 = 1.0 - l1 - l2
            hit = sel & (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9) & (px >= 0) & (py >= 0) & (px < w) & (py < h)
            if hit.any():
                depth = l0[hit] * za[hit] + l1[hit] * zb[hit] + l2[hit] * zc[hit]
                np.minimum.at(zbuf, py[hit].astype(np.int64) * w + px[hit].astype(np.int64), depth)
    return zbuf.reshape(h, w)


def _neighbourhoods(v: np.ndarray, normals: np.ndarray, radius: float, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(V, K) indices of each vertex's patch (its nearest vertices within ``radius`` whose normals
    agree within 60 degrees, itself first) and (V, K) bool validity."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(v).query(v, k=min(k, len(v)))
    ok = np.isfinite(dist) & (dist <= radius)
    idx = np.where(ok, idx, 0)
    ok &= np.einsum("ikj,ij->ik", normals[idx], normals) > 0.5
    return idx, ok


def _jacobians(cam: Camera, v: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (V, 2) of the vertices and the (V, 2, 3) Jacobian of the projection there
    (central differences of ``h``, lens distortion included)."""
    pix = cam.project(v)
    e = np.eye(3) * h
    plus = cam.project((v[:, None, :] + e[None]).reshape(-1, 3)).reshape(len(v), 3, 2)
    minus = cam.project((v[:, None, :] - e[None]).reshape(-1, 3)).reshape(len(v), 3, 2)
    return pix, np.transpose(plus - minus, (0, 2, 1)) / (2 * h)


def _scores(v, normals, vis, depths, images, cams, radius, samples, sigma) -> np.ndarray:
    """(V, D) mean pairwise NCC of each vertex's patch at every candidate depth.

    The patch is the vertex's neighbourhood on the mesh moved with it along the normals
    (``v_j - d n_j``), so it keeps the surface's curvature (a flat tangent patch on a limb
    cuts into it and biases the depth inward); its pixels come from the projection's
    Jacobian at the vertex (the patch is small against the camera distance).
    """
    import cv2

    nb, nb_ok = _neighbourhoods(v, normals, radius, samples)
    proj = [_jacobians(cam, v, 0.25 * radius) for cam in cams]
    n_d = len(depths)
    out = np.zeros((len(v), n_d), np.float32)
    chunk = max(1, 30000 // n_d)  # OpenCV's remap takes maps of fewer than 32767 rows
    for s in range(0, len(v), chunk):
        sl = slice(s, min(s + chunk, len(v)))
        n = sl.stop - sl.start
        idx, m = nb[sl], nb_ok[sl].astype(np.float32)[:, None, :]  # (n, K), (n, 1, K)
        cnt = m.sum(axis=2, keepdims=True)
        rel = v[idx] - v[sl, None, :]  # (n, K, 3): the patch at depth d is rel - d * normals[idx]
        nrm = normals[idx]
        zsum = np.zeros((n, n_d, idx.shape[1]), np.float32)
        zsq = np.zeros((n, n_d), np.float32)
        wsum = np.zeros(n, np.float64)
        wsq = np.zeros(n, np.float64)
        for ci in range(len(cams)):
            use = vis[ci, sl]
            if not (use > 0).any():
                continue
            p0, jac = proj[ci][0][sl], proj[ci][1][sl]
            at = np.einsum("nab,nkb->nka", jac, rel)  # pixel offsets of the patch at depth 0
            per_depth = np.einsum("nab,nkb->nka", jac, nrm)  # and their change per unit of depth
            uv = (p0[:, None, None, :] + at[:, None]) - depths[None, :, None, None] * per_depth[:, None]
            mx = np.ascontiguousarray(uv[..., 0], dtype=np.float32).reshape(n * n_d, -1)
            my = np.ascontiguousarray(uv[..., 1], dtype=np.float32).reshape(n * n_d, -1)
            x = cv2.remap(images[ci], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(uv.shape[:3])
            x = (x - (x * m).sum(axis=2, keepdims=True) / cnt) * m
            z = x / np.sqrt(np.einsum("ijk,ijk->ij", x, x) + cnt[..., 0] * sigma * sigma)[..., None]
            w = use.astype(np.float32)[:, None, None]
            zsum += w * z
            zsq += (w * w)[..., 0] * np.einsum("ijk,ijk->ij", z, z)
            wsum += use
            wsq += use * use
        # sum_{i<j} w_i w_j z_i.z_j over the sum of the pair weights
        pairs = 0.5 * (wsum * wsum - wsq)
        norm = np.where(pairs > 1e-9, pairs, np.inf)[:, None]
        out[sl] = (0.5 * (np.einsum("ijk,ijk->ij", zsum, zsum) - zsq)) / norm
    return out


def _past_medial_axis(v: np.ndarray, normals: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """(V, D) bool: the candidate ``v - d n`` lies nearer to another part of the surface than to
    its own vertex's (past the medial axis of the current surface: through a thin limb), where
    the true surface cannot be."""
    from scipy.spatial import cKDTree

    inward = depths > 0
    out = np.zeros((len(v), len(depths)), bool)
    if not inward.any():
        return out
    pts = v[:, None, :] - depths[None, inward, None] * normals[:, None, :]
    dist, _ = cKDTree(v).query(pts.reshape(-1, 3))
    out[:, inward] = dist.reshape(len(v), -1) < 0.75 * depths[None, inward]
    # once past the axis, every deeper candidate is too
    return np.logical_or.accumulate(out, axis=1)


def _best_depths(score: np.ndarray, depths: np.ndarray, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, the depth of the highest score (parabola through the peak) and its confidence:
    the peak's correlation times the weight of the camera pairs behind it (capped at 1, two
    head-on cameras), so a match from grazing views counts little."""
    k = np.argmax(score, axis=1)
    rows = np.arange(len(score))
    best = depths[k].astype(np.float64)
    inner = (k > 0) & (k < len(depths) - 1)
    i = rows[inner]
    s0, s1, s2 = score[i, k[inner] - 1], score[i, k[inner]], score[i, k[inner] + 1]
    den = s0 - 2 * s1 + s2
    off = np.where(den < 0, 0.5 * (s0 - s2) / np.where(den < 0, den, -1.0), 0.0)
    best[inner] += np.clip(off, -0.5, 0.5) * (depths[1] - depths[0])
    pairs = 0.5 * (vis.sum(axis=0) ** 2 - (vis * vis).sum(axis=0))
    weight = np.clip(score[rows, k], 0.0, None).astype(np.float64) * np.minimum(pairs, 1.0)
    weight[~inner] = 0.0  # a peak at the end of the range is no peak: the surface lies beyond it
    return best, weight


#: Reweighting rounds of the offsets, the Cauchy scale (voxels) and the pull of a vertex
#: without any match towards no offset (relative to a match's confidence of about 1).
_REWEIGHT_ROUNDS, _CAUCHY_SCALE, _NO_MATCH_PULL = 3, 0.5, 1e-3


def _robust_offsets(target: np.ndarray, weight: np.ndarray, lap, smoothness: float, vox: float) -> np.ndarray:
    """The smoothed offsets with matches that disagree with their neighbourhood down-weighted
    (iteratively reweighted least squares, Cauchy weights ``1 / (1 + (r / c)^2)`` of the
    residual ``r`` to the smooth solution, ``c`` half a voxel): one wrong match does not drag
    the unseen surface around it."""
    d = _smooth_offsets(target, weight, lap, smoothness, _NO_MATCH_PULL)
    for _ in range(_REWEIGHT_ROUNDS):
        r = (target - d) / (_CAUCHY_SCALE * vox)
        d = _smooth_offsets(target, weight / (1.0 + r * r), lap, smoothness, _NO_MATCH_PULL)
    return d


def _smooth_offsets(target: np.ndarray, weight: np.ndarray, lap, smoothness: float, eps: float) -> np.ndarray:
    """``argmin_d sum w (d - d*)^2 + lambda d^T L d``: the screened Laplacian solve."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import spsolve

    a = diags(weight + eps) + smoothness * lap
    return np.asarray(spsolve(a.tocsc(), weight * target), dtype=np.float64)
