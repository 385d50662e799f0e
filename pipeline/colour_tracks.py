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

Measured on the simulated lamp (30 frames, the true previous frame as start): the targets lie
0.1 to 0.3 mm across the ray from the truth at rest and 0.7 to 1.1 mm (median) while parts
move 20 to 37 mm a frame; without the background fill a thin arm's tracks lagged by 1 to 2 mm
a frame.

Hand-written here: only the choice of points and the lifting to 3D; the flow is OpenCV's.
"""

from __future__ import annotations

import numpy as np

from calib.camera import Camera

__all__ = ["colour_tracks"]


def _gray(image) -> np.ndarray:
    import cv2

    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.uint8, copy=False)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"previous_image and image must be (H, W) or (H, W, 3), got shape {img.shape}")
    return cv2.cvtColor(img.astype(np.uint8, copy=False), cv2.COLOR_BGR2GRAY)


def _check_options(*, window, levels, max_error, max_jump, highpass) -> None:
    if int(window) != window or window < 3:
        raise ValueError(f"window must be an integer >= 3, got {window!r}")
    if int(levels) != levels or levels < 0:
        raise ValueError(f"levels must be an integer >= 0, got {levels!r}")
    for name, v in (("max_error", max_error), ("max_jump", max_jump)):
        if not v > 0:
            raise ValueError(f"{name} must be > 0, got {v!r}")
    if not highpass >= 0:
        raise ValueError(f"highpass must be >= 0, got {highpass!r}")


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


def colour_tracks(previous_image, image, vertices, visible, camera: Camera, depth, *, masks=None, predicted=None,
                  highpass: float = 6.0, window: int = 15, levels: int = 3, max_error: float = 0.3,
                  max_jump: float = 5.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        background inside a window does not hold the flow back (on thin parts, where every
        window holds background, it did by about 7 % of the motion).
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
    import cv2

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
    _check_options(window=window, levels=levels, max_error=max_error, max_jump=max_jump, highpass=highpass)
    if masks is not None:
        a, b = (_masked(img, np.asarray(m, bool)) for img, m in zip((a, b), masks))
    if highpass > 0:
        a, b = (_highpass(img, highpass) for img in (a, b))
    idx = np.flatnonzero(vis)
    if len(idx) == 0:
        return idx, np.zeros((0, 3)), np.zeros((0, 3))
    u0 = np.asarray(camera.project(V[idx]), dtype=np.float32).reshape(-1, 1, 2)
    lk = dict(winSize=(int(window), int(window)), maxLevel=int(levels),
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    if predicted is not None:
        guess = np.asarray(camera.project(np.asarray(predicted, float)[idx]), dtype=np.float32).reshape(-1, 1, 2)
        u1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, u0, guess.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    else:
        u1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, u0, None, **lk)
    ub, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, u1, None, **lk)
    fb = np.linalg.norm((ub - u0).reshape(-1, 2), axis=1)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb <= max_error)
    pts, lifted = _lift(u1.reshape(-1, 2).astype(np.float64), z, camera, max_jump)
    ok &= lifted
    rays = pts[ok] - camera.center
    return idx[ok], pts[ok], rays / np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
