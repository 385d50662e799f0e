"""Colour feature tracks for one RGB-D camera: where the template's visible vertices went.

Depth pairs (point-to-plane) see a surface move only along its normal: a round part's twist
about its own axis, or a slide along it, leaves the depth image unchanged. The colour image
of an RGB-D sensor does see it when the object carries any texture. Here every template
vertex that the camera and the data see on the previous frame is projected into the previous
colour image and followed into the current one by pyramidal Lucas-Kanade optical flow
(OpenCV's ``calcOpticalFlowPyrLK``, Bouguet 2000), kept only when the flow tracked back
returns within ``max_error`` pixels of its start (forward-backward check) and lands on a
pixel whose depth is smooth. Pixels without data are filled with the object's mean grey
first (the static background otherwise holds thin parts' flow back) and the shading is
taken out by a high-pass filter; the landing pixel is lifted to 3D with the current frame's
filtered depth. The tracker uses these as extra, gated correspondences across the viewing
ray (:meth:`pipeline.tracking.TemplateTracker.fit`, ``tracks=``); along it the lifted point
carries the depth's noise, and the depth pairs hold that direction.

With the template's triangles and a prediction of the frame (``faces=``, ``predicted=``, what
:func:`pipeline.track_rgbd.track_rgbd_take` passes), every track is then refined with its window
warped by the prediction's local image motion (:func:`_local_warps`, :func:`_warped_lk`), on
the object's pixels only: OpenCV's window only translates, and a part that turns within the
image turns the texture inside it; the silhouette is no point of the surface (a round end's
outline stays put while it turns) and the background does not move with the object. The
multi-view colour tracks (:func:`pipeline.track.track_results`, ``colour=True``) use the same
refinement per camera, with that camera's keyed masks as the object's pixels.

Vertices a pixel or two apart see nearly the same window, so they share one (``cell``): the
visible vertices are grouped by 3-px cells (and depth slabs), one window is followed per
group and every member is placed through that window's own model (its track and warp), which
costs a fraction of a window each at the same accuracy. The measurements behind these choices
(shared windows, warped and object-only windows, the background fill): docs/tracking.md,
"Colour feature tracks: measurements".

Hand-written here: the choice of points, the lifting to 3D and the warped-window refinement
(an inverse-compositional Gauss-Newton step, Baker & Matthews 2004, for the translation of a
window whose shape change is given, weighted by the masks; OpenCV's Lucas-Kanade has no warp
model and no weights); the pyramidal flow is OpenCV's.
"""

from __future__ import annotations

import numpy as np

from calib.camera import Camera

__all__ = ["colour_tracks", "ray_points"]


def _gray(image) -> np.ndarray:
    import cv2

    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.uint8, copy=False)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"previous_image and image must be (H, W) or (H, W, 3), got shape {img.shape}")
    return cv2.cvtColor(img.astype(np.uint8, copy=False), cv2.COLOR_BGR2GRAY)


def _check_options(*, window, levels, max_error, max_jump, highpass, cell) -> None:
    if int(window) != window or window < 3:
        raise ValueError(f"window must be an integer >= 3, got {window!r}")
    if int(levels) != levels or levels < 0:
        raise ValueError(f"levels must be an integer >= 0, got {levels!r}")
    for name, v in (("max_error", max_error), ("max_jump", max_jump)):
        if not v > 0:
            raise ValueError(f"{name} must be > 0, got {v!r}")
    if not highpass >= 0:
        raise ValueError(f"highpass must be >= 0, got {highpass!r}")
    if not cell >= 0:
        raise ValueError(f"cell must be >= 0, got {cell!r}")


def _masked(gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
    if mask.shape != gray.shape:
        raise ValueError(f"masks must have the images' shape {gray.shape}, got {mask.shape}")
    out = gray.copy()
    if mask.any():
        out[~mask] = np.uint8(round(float(gray[mask].mean())))
    return out


def _highpass(gray: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    g = gray.astype(np.float32)
    return np.clip(2.0 * (g - cv2.GaussianBlur(g, (0, 0), sigma)) + 128.0, 0, 255).astype(np.uint8)


def _highpass_inside(gray: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """``_highpass`` of the object's pixels alone (normalised convolution: the local mean of the
    object's pixels only); 128 elsewhere. ``sigma`` 0: the object's pixels unchanged."""
    import cv2

    m = mask.astype(np.float32)
    g = gray.astype(np.float32)
    if sigma <= 0:  # no high-pass: the object's pixels as they are, its mean elsewhere
        return np.where(mask, g, float(g[mask].mean()) if mask.any() else 128.0).astype(np.uint8)
    mean = cv2.GaussianBlur(g * m, (0, 0), sigma) / np.maximum(cv2.GaussianBlur(m, (0, 0), sigma), 1e-6)
    out = np.where(mask, 2.0 * (g - mean) + 128.0, 128.0)
    return np.clip(out, 0, 255).astype(np.uint8)


def _lift(uv: np.ndarray, depth: np.ndarray, camera: Camera, max_jump: float):
    """World points at sub-pixel ``uv`` from bilinear depth; ``ok`` where all four neighbours have
    depth within ``max_jump`` mm of each other (no depth edge under the point)."""
    h, w = depth.shape
    c0 = np.floor(uv[:, 0]).astype(np.int64)
    r0 = np.floor(uv[:, 1]).astype(np.int64)
    ok = (c0 >= 0) & (r0 >= 0) & (c0 < w - 1) & (r0 < h - 1)
    c0, r0 = np.where(ok, c0, 0), np.where(ok, r0, 0)
    z = np.stack([depth[r0, c0], depth[r0, c0 + 1], depth[r0 + 1, c0], depth[r0 + 1, c0 + 1]], axis=1)
    ok &= np.all(z > 0, axis=1) & (np.ptp(z, axis=1) <= max_jump)
    fx, fy = uv[:, 0] - c0, uv[:, 1] - r0
    zi = (z[:, 0] * (1 - fx) * (1 - fy) + z[:, 1] * fx * (1 - fy) + z[:, 2] * (1 - fx) * fy + z[:, 3] * fx * fy)
    pts = np.full((len(uv), 3), np.nan)
    if ok.any():
        pts[ok] = camera.unproject(uv[ok], zi[ok])
    return pts, ok


def _local_warps(before, after, faces) -> np.ndarray:
    """(V, 2, 2): the linear image motion around every vertex, ``after`` offsets = ``A @ before`` offsets.

    Least squares over the edges of the vertex's triangles (its one-ring; on a closed mesh every
    edge counts twice, evenly); the identity where those edges do not span the image plane.

    Parameters
    ----------
    before, after : (V, 2) float ndarray
        The vertices' pixels on the two images.
    faces : (F, 3) int ndarray
    """
    f = np.asarray(faces, dtype=np.int64)
    i, j = f.ravel(), np.roll(f, -1, axis=1).ravel()  # every triangle's three edges
    d0, d1 = before[j] - before[i], after[j] - after[i]
    V = len(before)
    terms = np.concatenate([np.einsum("ei,ej->eij", d0, d0).reshape(-1, 4), np.einsum("ei,ej->eij", d1, d0).reshape(-1, 4)], 1)
    both = np.concatenate([i, j])
    sums = np.stack([np.bincount(both, weights=np.tile(terms[:, c], 2), minlength=V) for c in range(8)], 1)
    M, N = sums[:, :4].reshape(V, 2, 2), sums[:, 4:].reshape(V, 2, 2)
    det = np.linalg.det(M)
    good = det > 1e-6 * np.einsum("vii->v", M) ** 2
    A = np.tile(np.eye(2), (V, 1, 1))
    A[good] = N[good] @ np.linalg.inv(M[good])
    return A


def _warped_lk(src, dst, p_src, p_dst, warps, *, window: int = 15, iterations: int = 10, eps: float = 0.02,
               weights=None):
    """Lucas-Kanade with warped windows: ``p`` such that ``dst(p + A x) = src(p_src + x)`` over the window.

    The translation alone is solved, by inverse-compositional Gauss-Newton steps (Baker & Matthews
    2004: the Hessian comes from ``src``'s gradients, once per window); the window's shape change
    ``A`` (a turn, foreshortening) is given, from a prediction.

    Parameters
    ----------
    src, dst : (H, W) ndarray
    p_src : (T, 2) float ndarray
        Window centres on ``src``.
    p_dst : (T, 2) float ndarray
        Starts on ``dst``.
    warps : (T, 2, 2) float ndarray
    weights : ((H, W), (H, W)) float ndarray, optional
        Per-pixel weights of ``src`` and ``dst`` (the object's masks): a window pixel counts
        with the product of its weights on both images (on ``dst``, at the start).

    Returns
    -------
    p : (T, 2) float ndarray
    converged : (T,) bool ndarray
    """
    import cv2

    def sample(img, qx, qy):  # bilinear at (n, K) float32 x and y maps; OpenCV maps have fewer than 2**15 rows
        parts = [cv2.remap(img, qx[i:i + 32000], qy[i:i + 32000], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                 for i in range(0, max(len(qx), 1), 32000)]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    s, d = np.asarray(src, np.float32), np.asarray(dst, np.float32)
    gx = cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    ws = np.ones_like(s) if weights is None else np.asarray(weights[0], np.float32)
    r = (int(window) - 1) / 2
    grid = np.stack(np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1)), -1).reshape(-1, 2).astype(np.float32)
    # window pixels in float32, as the maps are: a pixel position of at most 2**15 is kept to 0.004 px; x and y
    # apart, (T, K) each (a trailing axis of 2 makes every elementwise pass a loop of two)
    ps = np.asarray(p_src, np.float32)
    t = sample(cv2.merge([s, gx, gy, ws]), ps[:, :1] + grid[:, 0], ps[:, 1:] + grid[:, 1])  # (T, K, 4)
    tmpl, jx, jy, w = (np.ascontiguousarray(t[..., c]) for c in range(4))
    A = np.asarray(warps, np.float64)
    Af = A.astype(np.float32)
    p = np.asarray(p_dst, np.float64).copy()
    pf = p.astype(np.float32)
    off = grid @ Af.transpose(0, 2, 1)  # (T, K, 2): A @ x
    qx, qy = pf[:, :1] + off[..., 0], pf[:, 1:] + off[..., 1]  # the window's pixels on dst at the start
    if weights is not None:
        w = w * sample(np.asarray(weights[1], np.float32), qx, qy)
    wx, wy = w * jx, w * jy
    hxx, hxy, hyy = (np.einsum("tk,tk->t", a, b).astype(np.float64) for a, b in ((wx, jx), (wx, jy), (wy, jy)))
    det = hxx * hyy - hxy * hxy
    ok = det > 1e-9 * np.maximum(hxx + hyy, 1e-12) ** 2
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    live = np.flatnonzero(ok)  # the windows still iterating, and their arrays
    arrays = [qx, qy, tmpl, wx, wy, hxx, hxy, hyy, inv, A]
    if len(live) < len(p):  # copies of the windows that can iterate only when some cannot
        arrays = [x[live] for x in arrays]
    dp = np.zeros((len(live), 2))
    converged = np.zeros(len(p), bool)
    for it in range(int(iterations)):
        if len(live) == 0:
            break
        q1, q2, tm, ax, ay, h11, h12, h22, iv, Al = arrays
        df = dp.astype(np.float32)
        e = sample(d, q1 + df[:, :1], q2 + df[:, 1:]) - tm
        bx, by = np.einsum("tk,tk->t", ax, e).astype(np.float64), np.einsum("tk,tk->t", ay, e).astype(np.float64)
        dx, dy = (h22 * bx - h12 * by) * iv, (h11 * by - h12 * bx) * iv
        step = -np.stack([Al[:, 0, 0] * dx + Al[:, 0, 1] * dy, Al[:, 1, 0] * dx + Al[:, 1, 1] * dy], axis=1)
        dp += step
        done = np.linalg.norm(step, axis=1) < eps
        p[live] = np.asarray(p_dst, np.float64)[live] + dp
        converged[live] = done  # a window that moves again is no longer settled
        if it >= 3 and done.any():  # the first rounds run on all windows; then only on those still moving
            keep = ~done
            live, dp, arrays = live[keep], dp[keep], [x[keep] for x in arrays]
    converged &= np.isfinite(p).all(axis=1)
    return np.where(np.isfinite(p), p, 0.0), converged


def _refine_warped(a, b, warps, u0, u1, st, lk, inside=None):
    """The flow's result refined with the prediction's local warps ``(T, 2, 2)``, forward and back;
    with ``inside`` (the two masks) the windows use the object's pixels only. The way back starts
    where the pyramidal flow from the forward result goes on its own (no initial flow): started
    from the forward track's origin it would stay there and pass any match, a wrong one too."""
    import cv2

    window = lk["winSize"][0]
    p0 = u0.reshape(-1, 2).astype(np.float64)
    wf = None if inside is None else tuple(m.astype(np.float32) for m in inside)
    wb = None if wf is None else wf[::-1]
    p1, ok1 = _warped_lk(a, b, p0, u1.reshape(-1, 2), warps, window=window, weights=wf)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1.astype(np.float32).reshape(-1, 1, 2), None, **lk)
    det = np.linalg.det(warps)
    turnable = np.abs(det) > 1e-9
    inv = np.linalg.inv(np.where(turnable[:, None, None], warps, np.eye(2)))
    pb, ok2 = _warped_lk(b, a, p1, back.reshape(-1, 2), inv, window=window, weights=wb)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & ok1 & ok2 & turnable
    return ok, p1.astype(np.float32).reshape(-1, 1, 2), np.linalg.norm(pb - p0, axis=1)


def _cell_groups(uv: np.ndarray, depth: np.ndarray, cell: float, depth_step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points grouped by pixel cells of ``cell`` px and depth slabs of ``depth_step`` mm.

    Returns ``(reps, group)``: ``reps[g]`` is the member of group ``g`` nearest the group's mean
    pixel, ``group[i]`` the group of point ``i``. ``cell`` 0: every point its own group.
    """
    n = len(uv)
    if cell <= 0 or n == 0:
        return np.arange(n), np.arange(n)
    key = np.column_stack([np.floor(uv / cell), np.floor(depth / depth_step)]).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    count = np.bincount(group)
    mean = np.stack([np.bincount(group, weights=uv[:, c]) for c in range(2)], 1) / count[:, None]
    order = np.lexsort((np.linalg.norm(uv - mean[group], axis=1), group))
    first = np.r_[True, group[order][1:] != group[order][:-1]]
    return order[first], group


def _rep_warps(V, predicted, faces, camera: Camera, vertices) -> np.ndarray:
    """(R, 2, 2): the prediction's local image motion at ``vertices``, from their triangles alone."""
    f = np.asarray(faces, dtype=np.int64)
    mark = np.zeros(len(V), bool)
    mark[vertices] = True
    f = f[mark[f].any(axis=1)]
    return _local_warps(camera.project(V), camera.project(predicted), f)[vertices]


def _follow(a, b, u0, guess, warps, *, window: int, levels: int, inside=None):
    """Pyramidal flow of windows at ``u0`` (R, 2) from ``a`` into ``b`` (from ``guess`` when
    given), refined through ``warps`` when given; ``(ok, u1 (R, 2) float64, forward-backward error)``."""
    import cv2

    lk = dict(winSize=(int(window), int(window)), maxLevel=int(levels),
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p0 = np.asarray(u0, np.float32).reshape(-1, 1, 2)
    if guess is not None:
        start = np.asarray(guess, np.float32).reshape(-1, 1, 2)
        u1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, start, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    else:
        u1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, **lk)
    if warps is not None:
        ok, u1, fb = _refine_warped(a, b, warps, p0, u1, st, lk, inside)
    else:
        ub, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, u1, None, **lk)
        fb = np.linalg.norm((ub - p0).reshape(-1, 2), axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1)
    return ok, u1.reshape(-1, 2).astype(np.float64), fb


def colour_tracks(previous_image, image, vertices, visible, camera: Camera, depth, *, masks=None, predicted=None,
                  highpass: float = 6.0, window: int = 15, levels: int = 3, max_error: float = 0.3,
                  max_jump: float = 5.0, faces=None, cell: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Follow visible template vertices from the previous colour image into the current one.

    Parameters
    ----------
    previous_image, image : (H, W, 3) BGR or (H, W) uint8 ndarray
        Consecutive colour images of the camera (registered to its depth).
    vertices : (V, 3) float ndarray
        The template on the previous frame, world mm.
    visible : (V,) bool ndarray
        Vertices the camera and the data saw on the previous frame.
    camera : calib.Camera
    masks : ((H, W) bool ndarray, (H, W) bool ndarray), optional
        The object's pixels on both images (the frames' :attr:`~pipeline.rgbd_preprocess.DepthFrame.valid`):
        everything else is filled with the object's mean grey level first, so the static
        background inside a window does not hold the flow back (on thin parts every window
        holds background; docs/tracking.md, "Colour feature tracks: measurements").
    predicted : (V, 3) float ndarray, optional
        A prediction of the current frame: the flow starts from its projection (fast motions).
    depth : (H, W) float ndarray
        The current frame's filtered camera-frame Z, mm (0 = none;
        :attr:`pipeline.rgbd_preprocess.DepthFrame.depth`).
    window : int
        Lucas-Kanade window, pixels.
    levels : int
        Pyramid levels above the full image (motions of tens of pixels).
    max_error : float
        Forward-backward error allowed, pixels.
    highpass : float
        Shading is taken out first (the image minus its Gaussian blur of this sigma, pixels;
        0: not): a part turning under the lights changes its shading, not its texture.
    max_jump : float
        Depth spread allowed under a landing point, mm.
    faces : (F, 3) int ndarray, optional
        The template's triangles. With ``predicted``, every track is refined with its window
        warped by the prediction's local image motion (a turn, foreshortening: least squares
        over the edges of the vertex's triangles), and the forward-backward check runs
        on the refined tracks, backwards through the inverse warp. Lucas-Kanade's window is
        otherwise translated only, which moves the tracks of a turning part off across the ray
        (docs/tracking.md, "Colour feature tracks: measurements").
        With ``masks`` too, the high-pass and the refinement use the object's pixels only.
    cell : float
        Pixel cell, px (0: every vertex its own window). Vertices a pixel or two apart see
        nearly the same window: the visible vertices are grouped by cells of this size (and
        by depth slabs of ``max_jump``, so the two sides of an occluding edge do not share),
        one window is followed per group, at the member nearest the group's middle, and every
        member is placed where that window's model puts it, ``u + A (x - x_r)`` (the window's
        track ``u``, its warp ``A``, the member's and the window's pixels ``x``, ``x_r``); each
        member is then lifted with its own depth. The default, a fifth of the default window,
        keeps every member within 2.2 px of its window's centre.

    Returns
    -------
    index : (T,) int ndarray
        Template vertices followed.
    targets : (T, 3) float ndarray
        Where they are on the current frame, world mm.
    rays : (T, 3) float ndarray
        Unit viewing directions of the targets: the flow measures the two directions across
        them; along them, the target carries the depth's noise.
    """
    a, b = _gray(previous_image), _gray(image)
    if a.shape != b.shape:
        raise ValueError(f"previous_image and image must have the same shape, got {a.shape} and {b.shape}")
    z = np.asarray(depth, dtype=np.float64)
    if z.shape != b.shape:
        raise ValueError(f"depth must have the images' shape {b.shape}, got {z.shape}")
    if masks is not None and len(masks) != 2:
        raise ValueError(f"masks must be a pair (previous, current), got {len(masks)} arrays")
    if masks is not None and any(np.shape(m) != b.shape for m in masks):
        raise ValueError(f"masks must have the images' shape {b.shape}, got {[np.shape(m) for m in masks]}")
    V = np.asarray(vertices, dtype=np.float64)
    vis = np.asarray(visible, bool)
    if V.ndim != 2 or V.shape[1] != 3 or vis.shape != (len(V),):
        raise ValueError(f"vertices must be (V, 3) and visible (V,), got {V.shape} and {vis.shape}")
    if predicted is not None and np.shape(predicted) != V.shape:
        raise ValueError(f"predicted must have the vertices' shape {V.shape}, got {np.shape(predicted)}")
    _check_options(window=window, levels=levels, max_error=max_error, max_jump=max_jump, highpass=highpass, cell=cell)
    if faces is not None:
        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer) or (f.size and (f.min() < 0 or f.max() >= len(V))):
            raise ValueError(f"faces must be (F, 3) integer indices into the {len(V)} vertices, got shape {f.shape}")
    warped = faces is not None and predicted is not None
    inside = None
    if masks is not None and warped:  # the object's own pixels only, mean and shading from them alone
        inside = tuple(np.asarray(m, bool) for m in masks)
        a, b = (_highpass_inside(img, m, highpass) for img, m in zip((a, b), inside))
    else:
        if masks is not None:
            a, b = (_masked(img, np.asarray(m, bool)) for img, m in zip((a, b), masks))
        if highpass > 0:
            a, b = (_highpass(img, highpass) for img in (a, b))
    idx = np.flatnonzero(vis)
    if len(idx) == 0:
        return idx, np.zeros((0, 3)), np.zeros((0, 3))
    uv, zv = camera.project(V[idx], return_depth=True)
    reps, group = _cell_groups(uv, zv, float(cell), max_jump)
    P = None if predicted is None else np.asarray(predicted, float)
    warps = _rep_warps(V, P, faces, camera, idx[reps]) if warped else None
    ok, u1, fb = _follow(a, b, uv[reps], None if P is None else camera.project(P[idx[reps]]), warps,
                         window=window, levels=levels, inside=inside)
    # every vertex where its group's window model puts it: dst(p + A x) = src(p0 + x), A = I unwarped
    offset = uv - uv[reps][group]
    u1 = u1[group] + (offset if warps is None else np.einsum("tij,tj->ti", warps[group], offset))
    ok, fb = ok[group], fb[group]
    ok &= fb <= max_error
    pts, lifted = _lift(u1, z, camera, max_jump)
    ok &= lifted
    rays = pts[ok] - camera.center
    return idx[ok], pts[ok], rays / np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)


def _check_rays(idx, targets, rays, n):
    """``ray_points``' arguments as arrays, or ValueError naming the one that is wrong."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    i = np.asarray(idx)
    if i.ndim != 1 or not (np.issubdtype(i.dtype, np.integer) or i.size == 0):
        raise ValueError(f"idx must be a (T,) integer array, got shape {i.shape} and dtype {i.dtype}")
    i = i.astype(np.int64)
    if i.size and (i.min() < 0 or i.max() >= n):
        raise ValueError(f"idx must lie in 0..n-1 = 0..{n - 1}, got values in {i.min()}..{i.max()}")
    t = np.asarray(targets, dtype=np.float64)
    if t.shape != (len(i), 3) or not np.isfinite(t).all():
        raise ValueError(f"targets must be a finite ({len(i)}, 3) array (one point a track), got shape {t.shape}")
    r = np.asarray(rays, dtype=np.float64)
    if r.shape != (len(i), 3) or not np.isfinite(r).all():
        raise ValueError(f"rays must be a finite ({len(i)}, 3) array (one direction a track), got shape {r.shape}")
    if r.size and np.abs(np.linalg.norm(r, axis=1) - 1.0).max() > 1e-6:
        raise ValueError("rays must be unit directions (norm 1 within 1e-6)")
    return i, t, r, int(n)


def ray_points(idx, targets, rays, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, the point nearest all its tracks' viewing rays (least squares).

    Parameters
    ----------
    idx : (T,) int ndarray
        The vertex of every track.
    targets : (T, 3) float ndarray
        A point on every track's ray.
    rays : (T, 3) float ndarray
        Unit directions of the rays.
    n : int
        Vertices.

    Returns
    -------
    ok : (n,) bool ndarray
        Vertices with two rays or more that are not parallel (their point is determined).
    points : (n, 3) float ndarray
        The point of every ``ok`` vertex (zero elsewhere).

    Raises
    ------
    ValueError
        Naming the argument: ``n`` not an integer >= 0, ``idx`` not (T,) integers in 0..n-1,
        ``targets`` or ``rays`` not finite (T, 3), ``rays`` not of norm 1.
    """
    idx, targets, rays, n = _check_rays(idx, targets, rays, n)
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]  # projectors across each ray
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    np.add.at(A, idx, P)
    np.add.at(b, idx, np.einsum("tij,tj->ti", P, targets))
    ok = np.bincount(idx, minlength=n) >= 2
    ok[ok] = np.linalg.cond(A[ok]) < 1e6
    x = np.zeros((n, 3))
    x[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    return ok, x
