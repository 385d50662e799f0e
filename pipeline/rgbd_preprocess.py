"""One RGB-D camera's frames made ready for template tracking (Tzionas & Gall 2016, §3.1).

Per frame, as in the paper: points outside the capture volume are dropped; optionally the
hands that bend the object are removed where a Gaussian mixture over colour says skin
(the paper uses the skin model of Jones & Rehg [21]; here a mixture in the CrCb plane,
:data:`SKIN_GMM`, or one fitted to the user's own skin samples, :func:`fit_skin_model`);
depth is smoothed by a bilateral filter (OpenCV) and normals are computed from the depth
image (cross product of the image-space derivatives of the back-projected points, the
simple member of the family of [23]). Filter, normals and depth edges are computed on the
window around the pixels kept (the object is a few per cent of the image): every pixel's
values depend only on pixels within the filter's radius plus one, so they are the whole
image's. Which template vertices the camera can see comes from a z-buffer render of the
template (:func:`render_depth`, :func:`visible_vertices`); :func:`rigid_icp` places a
roughly placed template on the first frame.

What is hand-written and why: OpenCV's contrib build here has no ``rgbd`` module (its
normal estimators), and no maintained package renders a z-buffer of a mesh on a CPU
without a display or an OpenGL stack; both are short vectorised numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from calib.camera import Camera, cached_pixel_grid_rays, cached_pixel_ray_depths
from pipeline.mesh_primitives import rigid_fit, vertex_normals
from pipeline.tracking import TrackingError, closest_pairs

__all__ = [
    "SKIN_GMM",
    "DepthFrame",
    "back_project",
    "bilateral_depth",
    "depth_normals",
    "skin_mask",
    "fit_skin_model",
    "preprocess_depth",
    "render_depth",
    "visible_vertices",
    "depth_edges",
    "contour_pairs",
    "rigid_icp",
]

# (weight, mean (Cr, Cb), covariance) of skin in YCrCb (8-bit OpenCV convention): two
# components covering light and dark skin tones, as reported for the CrCb skin cluster
# (Cr 135..180, Cb 85..135; Chai & Ngan 1999, Jones & Rehg 2002).
SKIN_GMM = (
    (0.6, (152.0, 110.0), ((60.0, -25.0), (-25.0, 50.0))),
    (0.4, (145.0, 118.0), ((90.0, -30.0), (-30.0, 80.0))),
)


@dataclass
class DepthFrame:
    """A preprocessed depth frame.

    Parameters
    ----------
    points : (P, 3) float ndarray
        World points (mm) inside the capture volume, not skin, with a valid normal.
    normals : (P, 3) float ndarray
        Unit normals, facing the camera.
    pixels : (P, 2) int ndarray
        (column, row) of every point.
    valid : (H, W) bool ndarray
        Pixels that gave a point.
    contour : (K, 2) float ndarray
        Sub-pixel (column, row) of the depth discontinuities: pixels with data next to a pixel without
        data or much further away (the occluding side of a depth edge).
    depth : (H, W) float ndarray, optional
        The filtered camera-frame Z, mm (0 where ``valid`` is False).
    """

    points: np.ndarray
    normals: np.ndarray
    pixels: np.ndarray
    valid: np.ndarray
    contour: np.ndarray
    depth: np.ndarray | None = None


def back_project(depth, camera: Camera) -> np.ndarray:
    """(H, W, 3) world points of a depth image (camera-frame Z in mm); NaN where depth is 0."""
    z = np.asarray(depth, dtype=np.float64)
    d = cached_pixel_grid_rays(camera)[1]
    if z.shape != d.shape[:2]:
        raise ValueError(f"depth must have the camera's shape {d.shape[:2]}, got {z.shape}")
    return _back_project(z, camera, (slice(None), slice(None)))


def _back_project(depth, camera: Camera, window: tuple[slice, slice]) -> np.ndarray:
    """:func:`back_project` of the ``window`` (rows, columns) of the image, ``depth`` its pixels."""
    z = np.asarray(depth, dtype=np.float64)
    o, d = cached_pixel_grid_rays(camera)
    t = np.where(z > 0, z / cached_pixel_ray_depths(camera)[window], np.nan)
    return o + d[window] * t[..., None]


def _in_bounds(depth: np.ndarray, camera: Camera, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose back-projected point (:func:`back_project`) lies in the box ``lo..hi``,
    one coordinate at a time (no (H, W, 3) image of points)."""
    o, d = cached_pixel_grid_rays(camera)
    z = np.asarray(depth, dtype=np.float64)
    t = np.where(z > 0, z / cached_pixel_ray_depths(camera), np.nan)
    inside = z > 0
    with np.errstate(invalid="ignore"):
        for k in range(3):
            c = o[k] + d[..., k] * t
            inside &= (c >= lo[k]) & (c <= hi[k])
    return inside


def bilateral_depth(depth, *, sigma_space: float = 1.0, sigma_depth: float = 3.0) -> np.ndarray:
    """Bilateral filter of a depth image (mm); pixels without depth stay 0 and do not bleed in.

    Parameters
    ----------
    sigma_space : float
        Spatial sigma, pixels.
    sigma_depth : float
        Range sigma, mm (depth jumps larger than a few sigma are edges and are kept).
    """
    z = np.asarray(depth, dtype=np.float32)
    valid = z > 0
    if not valid.any():
        return np.zeros_like(z)
    d = int(2 * math.ceil(2 * sigma_space) + 1)
    # pixels without depth are pushed far away so that the range kernel ignores them
    far = np.where(valid, z, z[valid].max() + 1000.0 * sigma_depth).astype(np.float32)
    out = cv2.bilateralFilter(far, d, float(sigma_depth), float(sigma_space))
    return np.where(valid, out, 0.0).astype(np.float32)


def depth_normals(points: np.ndarray, camera: Camera, *, max_jump: float = 10.0) -> np.ndarray:
    """(H, W, 3) unit normals of back-projected depth points, facing the camera; NaN where unknown.

    Central differences along rows and columns; a normal is unknown where a neighbour has
    no depth or lies more than ``max_jump`` mm away (a depth edge).
    """
    P = np.asarray(points, dtype=np.float64)
    du = np.full_like(P, np.nan)
    dv = np.full_like(P, np.nan)
    du[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dv[1:-1] = P[2:] - P[:-2]
    jump = np.maximum(np.linalg.norm(du, axis=-1), np.linalg.norm(dv, axis=-1))
    n = np.cross(du, dv)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / nn
    bad = ~np.isfinite(n).all(-1) | ~(jump <= 2 * max_jump) | (nn[..., 0] <= 0)
    view = P - camera.center
    flip = np.einsum("hwi,hwi->hw", np.nan_to_num(n), np.nan_to_num(view)) > 0
    n[flip] *= -1
    n[bad] = np.nan
    return n


def _gmm_loglik(x: np.ndarray, gmm) -> np.ndarray:
    out = np.full(len(x), -np.inf)
    for w, mu, cov in gmm:
        C = np.asarray(cov, float)
        Ci = np.linalg.inv(C)
        d = x - np.asarray(mu, float)
        m = np.einsum("ni,ij,nj->n", d, Ci, d)
        ll = math.log(w) - 0.5 * (m + math.log(np.linalg.det(C)) + 2 * math.log(2 * math.pi))
        out = np.logaddexp(out, ll)
    return out


def skin_mask(image, *, model=SKIN_GMM, threshold: float = -12.0) -> np.ndarray:
    """(H, W) bool: pixels of a BGR image whose colour the skin mixture finds likely.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray, BGR
    model : sequence of (weight, mean (2,), covariance (2, 2))
        Gaussian mixture over (Cr, Cb) (:data:`SKIN_GMM`, or :func:`fit_skin_model`).
    threshold : float
        Log-likelihood above which a pixel is skin.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8 BGR, got {img.shape} {img.dtype}")
    ycc = cv2.cvtColor(img, cv2.COLOR_BGR2YCrCb).reshape(-1, 3).astype(np.float64)
    ll = _gmm_loglik(ycc[:, 1:], model)
    dark = ycc[:, 0] < 30  # chroma is meaningless in the dark
    return ((ll > threshold) & ~dark).reshape(img.shape[:2])


def fit_skin_model(pixels_bgr, *, components: int = 2, seed: int = 0):
    """Fit a skin mixture (for :func:`skin_mask`) to sample skin pixels, with OpenCV's EM.

    Parameters
    ----------
    pixels_bgr : (N, 3) uint8 ndarray
        Skin colours, N >= 10 * components.
    """
    px = np.asarray(pixels_bgr, dtype=np.uint8).reshape(-1, 3)
    if len(px) < 10 * components:
        raise ValueError(f"pixels_bgr: need at least {10 * components} samples, got {len(px)}")
    ycc = cv2.cvtColor(px[None], cv2.COLOR_BGR2YCrCb)[0, :, 1:].astype(np.float64)
    em = cv2.ml.EM_create()
    em.setClustersNumber(int(components))
    em.setCovarianceMatrixType(cv2.ml.EM_COV_MAT_GENERIC)
    cv2.setRNGSeed(seed)
    em.trainEM(ycc)
    w = em.getWeights().ravel()
    means = em.getMeans()
    covs = em.getCovs()
    return tuple((float(w[k]), tuple(means[k]), np.asarray(covs[k]) + 1e-3 * np.eye(2)) for k in range(len(w)))


def preprocess_depth(
    depth,
    camera: Camera,
    *,
    bounds=None,
    image=None,
    remove_skin: bool = False,
    skin_model=SKIN_GMM,
    sigma_space: float = 1.0,
    sigma_depth: float = 3.0,
    max_points: int = 20000,
) -> DepthFrame:
    """The paper's per-frame preprocessing of one depth image (§3.1).

    Parameters
    ----------
    depth : (H, W) uint16 ndarray
        Camera-frame Z, mm (0 = no return).
    camera : calib.Camera
        The camera the depth is registered to.
    bounds : ((3,), (3,)), optional
        Capture volume (lo, hi) in world mm; points outside are dropped.
    image : (H, W, 3) uint8 ndarray, optional
        The colour image (needed for ``remove_skin``).
    remove_skin : bool
        Drop pixels the skin mixture accepts (the hands bending the object).
    max_points : int
        Keep at most this many points (regular subsampling).

    Returns
    -------
    DepthFrame
    """
    z = np.asarray(depth)
    if z.ndim != 2:
        raise ValueError(f"depth must be a (H, W) image, got shape {z.shape}")
    if remove_skin and image is None:
        raise ValueError("remove_skin needs the colour image")
    if z.shape != (camera.size[1], camera.size[0]):
        raise ValueError(f"depth must have the camera's shape {(camera.size[1], camera.size[0])}, got {z.shape}")
    if bounds is not None:
        try:
            box = np.asarray(bounds, dtype=np.float64)
        except (TypeError, ValueError):
            box = np.empty(0)
        if box.shape != (2, 3) or np.any(box[0] > box[1]):  # a NaN corner keeps no pixel (the frame has no data)
            raise ValueError(f"bounds must be (low (3,), high (3,)) corners with low <= high, got {bounds!r}")
    valid = z > 0
    if bounds is not None:
        lo, hi = box
        valid &= _in_bounds(z, camera, lo, hi)
    if remove_skin:
        valid &= ~skin_mask(image, model=skin_model)
    # the filter, normals and edges of a pixel depend only on pixels within the filter's radius (plus one):
    # computed on the window around the kept pixels, they are those of the whole image
    win = _window(valid, margin=int(math.ceil(2 * sigma_space)) + 1)
    off = np.array([win[1].start, win[0].start])
    seen = valid[win].copy()  # depth kept, before the normals are required
    zf = bilateral_depth(np.where(seen, z[win], 0), sigma_space=sigma_space, sigma_depth=sigma_depth)
    P = _back_project(zf, camera, win)
    N = depth_normals(P, camera, max_jump=2.0 * sigma_depth)
    ok = seen & np.isfinite(N).all(-1) & np.isfinite(P).all(-1)
    valid[win] = ok
    contour = depth_edges(np.where(seen, zf, 0.0), jump=4.0 * sigma_depth) + off
    rows, cols = np.nonzero(ok)
    if len(rows) > max_points:
        keep = np.linspace(0, len(rows) - 1, max_points).astype(np.int64)
        rows, cols = rows[keep], cols[keep]
    depth_mm = np.zeros(z.shape)
    depth_mm[win] = np.where(ok, zf, 0.0)
    return DepthFrame(points=P[rows, cols], normals=N[rows, cols], pixels=np.stack([cols, rows], 1) + off, valid=valid,
                      contour=contour, depth=depth_mm)


def _window(mask: np.ndarray, *, margin: int) -> tuple[slice, slice]:
    """(rows, columns) slices of the bounding box of ``mask`` grown by ``margin`` pixels, within the image."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if len(rows) == 0:
        return slice(0, 0), slice(0, 0)
    h, w = mask.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)))


def depth_edges(depth, *, jump: float = 12.0) -> np.ndarray:
    """(K, 2) sub-pixel (column, row) of occluding depth edges.

    A pixel with depth whose 4-neighbour has none, or lies more than ``jump`` mm further away,
    is on the occluding side of an edge (as the edge detector of [26] on depth data); the edge
    itself is taken half a pixel towards that neighbour, where the silhouette passes.
    """
    z = np.asarray(depth, dtype=np.float64)
    valid = z > 0
    far = np.where(valid, z, np.inf)
    out = []
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        nb = np.full_like(far, -np.inf)  # outside the image: no edge
        rs = slice(dr, None) if dr > 0 else slice(None, dr if dr < 0 else None)
        rd = slice(None, -dr) if dr > 0 else slice(-dr if dr < 0 else None, None)
        cs = slice(dc, None) if dc > 0 else slice(None, dc if dc < 0 else None)
        cd = slice(None, -dc) if dc > 0 else slice(-dc if dc < 0 else None, None)
        nb[rd, cd] = far[rs, cs]  # nb[r, c] = far[r + dr, c + dc]
        rows, cols = np.nonzero(valid & (nb > z + jump))
        out.append(np.stack([cols + 0.5 * dc, rows + 0.5 * dr], 1))
    return np.concatenate(out).astype(np.float64)


def contour_pairs(vertices, normals, faces, camera: Camera, contour, *, gate: float, rim: float = 0.5):
    """The contour term's pairs: every depth edge pixel and the closest projected rim vertex.

    Rim vertices are those the camera sees at a grazing angle (``|cos| < rim`` between the
    normal and the viewing ray) and not behind the z-buffer. The pair's target is the point of
    the edge pixel's projection ray nearest to the vertex, so that ``||V - target||`` is the
    vertex's distance to the ray (the Pluecker-line distance of the paper's eq. 3).

    Returns
    -------
    vertex_index : (K',) int ndarray
    targets : (K', 3) float ndarray
    """
    v = np.asarray(vertices, dtype=np.float64)
    c = np.asarray(contour, dtype=np.float64)
    if len(c) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    view = v - camera.center
    dist = np.linalg.norm(view, axis=1)
    cosang = np.einsum("ij,ij->i", normals, view) / np.maximum(dist, 1e-12)
    cand = np.flatnonzero(np.abs(cosang) < rim)
    if len(cand) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    uv, z, row, col, inside = _project_to_pixels(v[cand], camera)
    ok = np.zeros(len(cand), bool)
    ok[inside] = z[inside] <= render_depth(v, faces, camera)[row[inside], col[inside]] + 0.3 * gate
    cand, uv, z = cand[ok], uv[ok], z[ok]
    if len(cand) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    f = float(camera.K[0, 0])
    d2, k = cKDTree(uv).query(c, distance_upper_bound=gate * f / float(np.median(z)))
    keep = np.isfinite(d2)
    vi = cand[k[keep]]
    o, dirs = camera.rays(c[keep])
    o = np.broadcast_to(np.asarray(o, dtype=np.float64), dirs.shape)
    t = np.einsum("ij,ij->i", v[vi] - o, dirs)
    return vi, o + dirs * t[:, None]


def _project_to_pixels(points: np.ndarray, camera: Camera):
    """Project ``points``: image coordinates ``uv`` (N, 2), camera-frame depth ``z`` (N,), the
    nearest pixel's ``row`` and ``col`` (N,) and ``inside`` (N,) bool, in the image and in front
    of the camera (the pixel is meaningful only there)."""
    uv, z = camera.project(points, return_depth=True)
    uv = np.asarray(uv)
    z = np.asarray(z).reshape(-1)
    w, h = camera.size
    col = np.round(uv[:, 0]).astype(np.int64)
    row = np.round(uv[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h) & (z > 0)
    return uv, z, row, col, inside


def render_depth(vertices, faces, camera: Camera) -> np.ndarray:
    """Z-buffer render of a mesh: (H, W) camera-frame Z of the nearest triangle, ``inf`` where none.

    Vertices are projected through the camera model (distortion included); triangles are
    filled in image space with depth interpolated linearly (pixel centres at integer coordinates).
    """
    v = np.asarray(vertices, dtype=np.float64)
    uv, z = camera.project(v, return_depth=True)
    return _zbuffer(np.asarray(uv, dtype=np.float64), np.asarray(z, dtype=np.float64).reshape(-1),
                    np.asarray(faces, dtype=np.int64), camera.size)


def _zbuffer(uv: np.ndarray, z: np.ndarray, f: np.ndarray, size) -> np.ndarray:
    """:func:`render_depth` of projected vertices (``uv`` (V, 2), depth ``z`` (V,)); one array per
    triangle corner (column operations: reductions over an axis of length 3 cost more than the rest)."""
    w, h = size
    zbuf = np.full(h * w, np.inf)
    f = f[(z[f[:, 0]] > 1e-6) & (z[f[:, 1]] > 1e-6) & (z[f[:, 2]] > 1e-6)]
    if len(f) == 0:
        return zbuf.reshape(h, w)
    (ax, ay), (bx, by), (cx, cy) = (uv[f[:, c]].T for c in range(3))
    # pixel centres at integer coordinates (the camera model's convention)
    x0 = np.clip(np.ceil(np.minimum(np.minimum(ax, bx), cx)), 0, w).astype(np.int64)
    x1 = np.clip(np.floor(np.maximum(np.maximum(ax, bx), cx)), -1, w - 1).astype(np.int64)
    y0 = np.clip(np.ceil(np.minimum(np.minimum(ay, by), cy)), 0, h).astype(np.int64)
    y1 = np.clip(np.floor(np.maximum(np.maximum(ay, by), cy)), -1, h - 1).astype(np.int64)
    nx = np.maximum(x1 - x0 + 1, 0)
    ny = np.maximum(y1 - y0 + 1, 0)
    cnt = nx * ny
    ok = cnt > 0
    tri = np.repeat(np.flatnonzero(ok), cnt[ok])
    if tri.size == 0:
        return zbuf.reshape(h, w)
    start = np.repeat(np.cumsum(cnt[ok]) - cnt[ok], cnt[ok])
    k = np.arange(tri.size) - start
    ntri = nx[tri]
    px = (x0[tri] + k % ntri).astype(np.float64)
    py = (y0[tri] + k // ntri).astype(np.float64)
    ax, ay, bx, by, cx, cy = ax[tri], ay[tri], bx[tri], by[tri], cx[tri], cy[tri]
    den = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
    good = np.abs(den) > 1e-12
    den = np.where(good, den, 1.0)
    l0 = ((by - cy) * (px - cx) + (cx - bx) * (py - cy)) / den
    l1 = ((cy - ay) * (px - cx) + (ax - cx) * (py - cy)) / den
    l2 = 1.0 - l0 - l1
    inside = good & (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
    ft = f[tri]
    zz = l0 * z[ft[:, 0]] + l1 * z[ft[:, 1]] + l2 * z[ft[:, 2]]
    idx = py.astype(np.int64) * w + px.astype(np.int64)
    np.minimum.at(zbuf, idx[inside], zz[inside])
    return zbuf.reshape(h, w)


def visible_vertices(vertices, faces, camera: Camera, *, tolerance: float = 3.0, normals=None, observed=None) -> np.ndarray:
    """(V,) bool: vertices the camera sees (in the image, front-facing, not behind the z-buffer).

    With ``observed`` (the frame's :attr:`DepthFrame.valid`), only vertices that the *data*
    sees too: those projecting onto a pixel that gave a point. Vertices near the silhouette,
    where a depth camera returns nothing usable, would otherwise all be pulled onto the
    nearest observed point, towards the camera: the thinning of the paper's Fig. 4.

    Parameters
    ----------
    tolerance : float
        A vertex counts as seen when it lies at most this far (mm) behind the rendered surface.
    normals : (V, 3) float ndarray, optional
        Vertex normals (default: computed); back-facing vertices are not visible.
    observed : (H, W) bool ndarray, optional
        Pixels with data.
    """
    v = np.asarray(vertices, dtype=np.float64)
    uv, z, row, col, inside = _project_to_pixels(v, camera)
    row, col = row[inside], col[inside]
    vis = np.zeros(len(v), bool)
    zbuf = _zbuffer(np.asarray(uv, dtype=np.float64), z.astype(np.float64), np.asarray(faces, dtype=np.int64), camera.size)
    vis[inside] = z[inside] <= zbuf[row, col] + tolerance
    if observed is not None:
        vis[inside] &= np.asarray(observed, bool)[row, col]
    n = vertex_normals(v, faces) if normals is None else np.asarray(normals)
    vis &= np.einsum("ij,ij->i", n, v - camera.center) < 0
    return vis


def rigid_icp(
    vertices,
    faces,
    points,
    normals,
    camera: Camera,
    *,
    gate: float,
    iterations: int = 40,
    min_fit: float = 0.6,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Place a roughly placed template rigidly on one frame's depth points (point-to-point ICP).

    Pairs both ways (visible vertices -> points, points -> vertices) with the 45 degree
    normal test; the distance gate starts at 4 x ``gate`` and halves down to ``gate``.

    Returns
    -------
    R : (3, 3), t : (3,)
        ``vertices @ R.T + t`` is the placed template.
    fit : float
        Fraction of the data points within ``gate`` of the placed template (normals agreeing).

    Raises
    ------
    TrackingError
        When fewer than ``min_fit`` of the data points are explained (the template is too far
        from the data, or is another object).
    """
    V0 = np.asarray(vertices, dtype=np.float64)
    X = np.asarray(points, dtype=np.float64)
    N = np.asarray(normals, dtype=np.float64)
    if len(X) < 10:
        raise TrackingError(f"the first frame has only {len(X)} depth points in the capture volume: nothing to place the template on")
    tree_x = cKDTree(X)
    R, t = np.eye(3), np.zeros(3)
    g = 4.0 * gate
    for it in range(int(iterations)):
        V = V0 @ R.T + t
        vn = vertex_normals(V, faces)
        vis = np.flatnonzero(visible_vertices(V, faces, camera, normals=vn, tolerance=0.3 * gate))
        i, j = closest_pairs(V[vis], vn[vis], tree_x, N, gate=g)
        jd, iv = closest_pairs(X, N, cKDTree(V), vn, gate=g)
        A = np.concatenate([V[vis[i]], V[iv]])
        B = np.concatenate([X[j], X[jd]])
        if len(A) < 6:
            raise TrackingError(
                f"rigid ICP cannot place the template: no template point lies within {g:.0f} mm of the data "
                "(is the template roughly placed in the camera's world frame, in mm?)"
            )
        dR, dt = rigid_fit(A, B)
        R, t = dR @ R, dR @ t + dt
        if it >= 5 and g > gate:
            g = max(gate, g / 2)
        if g == gate and np.linalg.norm(dt) < 1e-3 * gate and abs(np.trace(dR) - 3) < 1e-8:
            break
    V = V0 @ R.T + t
    jd, _ = closest_pairs(X, N, cKDTree(V), vertex_normals(V, faces), gate=gate)
    fit = len(jd) / len(X)
    if fit < min_fit:
        raise TrackingError(
            f"rigid ICP cannot place the template: only {100 * fit:.0f} % of the depth points lie within "
            f"{gate:.0f} mm of it (need {100 * min_fit:.0f} %)"
        )
    return R, t, float(fit)
