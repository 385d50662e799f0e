"""Shape from silhouette across time: one frame's visual hull carved by every other frame's silhouettes.

A frame's visual hull keeps every point that all of its cameras see on the subject, so it
holds volume no camera can carve: the hollows between limbs, the belly under a body seen
only from the sides. The subject moves, so every other frame of the take is a further view
of the same body: a point of frame ``t`` carried by the subject's motion to frame ``s`` must
project inside frame ``s``'s silhouettes too (Cheung, Baker & Kanade 2003, "Shape-from-
silhouette of articulated objects and its use for human body kinematics estimation and motion
capture", CVPR; the same authors' "Shape-from-silhouette across time", IJCV 2005). Cheung et
al. estimate each part's rigid motion from the silhouettes and colours; here the motion is
the tracked template's (``stage track``): every point moves as the vertices of the template
nearest it move, their best rigid motion (Kabsch) between the two frames.

The hull is a signed distance field instead of an occupancy: per camera the distance of a
point's projection to the silhouette's outline (pixels, positive inside), times the pixel's
footprint at the point's depth, the least over cameras and frames. Its zero level lies
between the voxel centres, so the surface is not the occupancy's staircase.

One frame's mis-tracked motion, or one mask's keying hole, must not carve the body: the
least value of all cameras and frames is left out (``ignore``), and only points within
``band`` voxels inside the frame's own hull surface are carried (deeper in, the frame's own
silhouettes decide; outside it nothing is left to carve). Written by hand: scikit-image,
trimesh and OpenCV carve no hull across time; the signed distance images come from OpenCV's
distance transform.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from calib.camera import Camera
from pipeline.mesh_primitives import check_points
from pipeline.volume import Grid

__all__ = ["carve_across_time", "local_motions", "signed_distance_image", "silhouette_distance"]


def signed_distance_image(mask) -> np.ndarray:
    """Signed distance of every pixel to a silhouette's outline, pixels.

    Parameters
    ----------
    mask : (H, W) bool ndarray
        Foreground True.

    Returns
    -------
    (H, W) float32 ndarray
        Positive on the foreground (distance to the nearest background pixel), negative on the
        background (minus the distance to the nearest foreground pixel); exact Euclidean
        distances between pixel centres (OpenCV's ``distanceTransform``, ``DIST_MASK_PRECISE``).
    """
    import cv2

    m = np.asarray(mask)
    if m.ndim != 2 or m.dtype != bool or m.size == 0:
        raise ValueError(f"mask must be a non-empty (H, W) bool array, got {m.dtype} {m.shape}")
    u = m.astype(np.uint8)
    inside = cv2.distanceTransform(u, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - u, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return (inside - outside).astype(np.float32)


def _camera_values(X: np.ndarray, image: np.ndarray, cam: Camera, margin: float = 0.0) -> np.ndarray:
    """One camera's signed distance (world units) of every point: +inf where the camera does not see it."""
    import cv2

    uv, z = cam.project(X, return_depth=True)
    h, w = image.shape
    seen = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
    n = len(X)
    rows = -(-n // 1024)  # OpenCV's maps are at most 32767 long: laid out as rows of 1024
    maps = np.zeros((2, rows * 1024), np.float32)
    maps[:, :n] = uv.T
    px = cv2.remap(image, maps[0].reshape(rows, 1024), maps[1].reshape(rows, 1024), cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_REPLICATE).reshape(-1)[:n]
    out = np.full(len(X), np.inf)
    out[seen] = (px[seen] + margin) * z[seen] / float(cam.K[0, 0])
    return out


def silhouette_distance(points, images: Sequence, cameras: Sequence[Camera], *, margin: float = 0.0) -> np.ndarray:
    """Every camera's signed distance of points to its silhouette, world units.

    Parameters
    ----------
    points : (N, 3) float ndarray
        World units.
    images : sequence of (H, W) float ndarrays or None
        Per camera, :func:`signed_distance_image` of its silhouette (None: no mask, no value).
    cameras : sequence of Camera
        In the order of ``images``.
    margin : float or (C,) float array-like, optional
        Pixels added to every signed distance, for all cameras or one per camera: the
        silhouettes grown by that much (a conservative hull, as ``stage process``'s
        ``silhouette_margin``; :func:`pipeline.carve.carve_results` grows each camera's by
        what its calibration says of its own accuracy).

    Returns
    -------
    (C, N) float ndarray
        Pixels of signed distance (bilinear) times the pixel's footprint at the point's depth
        (depth over the focal length); positive inside the silhouette, ``+inf`` where the camera
        has no mask or does not see the point (behind it, outside its image).
    """
    X = check_points(points)
    if len(images) != len(cameras):
        raise ValueError(f"images must have one entry per camera ({len(cameras)}), got {len(images)}")
    margins = _margins(margin, len(cameras))
    out = np.full((len(cameras), len(X)), np.inf)
    for c, (image, cam) in enumerate(zip(images, cameras)):
        if not isinstance(cam, Camera):
            raise ValueError(f"cameras[{c}] must be a Camera, got {type(cam).__name__}")
        if image is None:
            continue
        im = np.asarray(image, dtype=np.float32)
        if im.shape != (cam.height, cam.width):
            raise ValueError(f"images[{c}] must have camera {cam.name}'s shape {(cam.height, cam.width)}, got {im.shape}")
        out[c] = _camera_values(X, im, cam, float(margins[c]))
    return out


def _margins(margin, n: int) -> np.ndarray:
    """``margin`` (pixels: one for every camera, or (n,) one each) as an (n,) array, or a ValueError."""
    m = np.asarray(margin, dtype=np.float64) if not isinstance(margin, bool) else np.array(np.nan)
    if m.ndim == 0:
        m = np.full(n, float(m))
    if m.shape != (n,) or not np.all(np.isfinite(m)) or np.any(m < 0):
        raise ValueError(f"margin must be a non-negative number of pixels or one per camera ({n}), got {margin!r}")
    return m


def local_motions(before, after, *, neighbours: int = 100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each vertex's rigid motion between two frames: the best (Kabsch) of its nearest vertices.

    Parameters
    ----------
    before, after : (V, 3) float ndarray
        The same vertices (a tracked template) at two frames.
    neighbours : int, optional
        Vertices per neighbourhood, the vertex itself included (nearest at ``before``;
        clipped to ``V``). About a five-voxel radius on a hull's surface, whose vertices are
        about a voxel apart: large enough that a few vertices' tracking noise averages out,
        small enough to stay on one body part away from the joints.

    Returns
    -------
    R : (V, 3, 3) float ndarray
    c0, c1 : (V, 3) float ndarray
        A point ``x`` near vertex ``i`` moves to ``R[i] @ (x - c0[i]) + c1[i]``.
    """
    P, Q = check_points(before, name="before"), check_points(after, name="after")
    if P.shape != Q.shape:
        raise ValueError(f"after must have the shape of before {P.shape}, got {Q.shape}")
    return _kabsch(P, Q, _neighbourhoods(P, neighbours))


def _neighbourhoods(P: np.ndarray, neighbours):
    """(V, V) sparse sums over every vertex's ``neighbours`` nearest vertices (itself included), CSR."""
    from scipy.sparse import csr_matrix
    from scipy.spatial import cKDTree

    if isinstance(neighbours, bool) or not isinstance(neighbours, (int, np.integer)) or neighbours < 3:
        raise ValueError(f"neighbours must be an integer >= 3, got {neighbours!r}")
    if len(P) < 3:
        raise ValueError(f"the template must hold at least 3 vertices, got {len(P)}")
    k = min(int(neighbours), len(P))
    nn = cKDTree(P).query(P, k=k)[1]
    return csr_matrix((np.ones(nn.size), nn.ravel(), np.arange(0, nn.size + 1, k)), shape=(len(P), len(P)))


def _kabsch(P: np.ndarray, Q: np.ndarray, W) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best rigid motion of every neighbourhood (rows of ``W``, :func:`_neighbourhoods`) from ``P``
    to ``Q`` (Kabsch, no reflections); the cross-covariance from sparse sums,
    ``sum a b^T - k c0 c1^T``, about the points' common centroid."""
    o = P.mean(axis=0)
    A, B = P - o, Q - o
    k = np.asarray(W.sum(axis=1)).reshape(-1, 1)
    c0, c1 = W @ A / k, W @ B / k
    H = (W @ (A[:, :, None] * B[:, None, :]).reshape(len(P), 9)).reshape(-1, 3, 3) \
        - k[:, :, None] * c0[:, :, None] * c1[:, None, :]
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("vji,vkj->vik", Vt, U)))  # det(V U^T)
    D = np.ones((len(H), 3))
    D[:, 2] = np.where(d == 0, 1.0, d)
    R = np.einsum("vji,vj,vkj->vik", Vt, D, U)
    return R, c0 + o, c1 + o


def carve_across_time(grid: Grid, frame: int, tracks: Mapping[int, np.ndarray], images: Mapping[int, Sequence],
                      cameras: Sequence[Camera], *, band: float = 3.0, neighbours: int = 100,
                      ignore: int = 1, margin: float = 0.0) -> np.ndarray:
    """One frame's silhouette field, carved by the other frames' silhouettes through the tracked motion.

    Parameters
    ----------
    grid : Grid
        The reconstruction's grid (world units).
    frame : int
        The frame carved: a key of ``tracks`` and of ``images``.
    tracks : mapping int -> (V, 3) float ndarray
        The tracked template at every frame tracked (the same vertices in every frame).
    images : mapping int -> sequence of (H, W) float ndarray or None
        Per frame, every camera's :func:`signed_distance_image` (None: that camera has no mask).
        The frames used are ``frame`` and every other frame in both ``tracks`` and ``images``.
    cameras : sequence of Camera
    band : float, optional
        Voxels: points inside the frame's own hull up to this deep (and those within one
        voxel outside it) are carried to the other frames; the rest keep the frame's own value.
    neighbours : int, optional
        See :func:`local_motions`.
    ignore : int, optional
        How many of the least values per point (over all cameras and frames) are left out.
    margin : float or (C,) float array-like, optional
        Pixels by which every silhouette is grown, for all cameras or one per camera
        (:func:`silhouette_distance`).

    Returns
    -------
    (nx, ny, nz) float ndarray
        Signed distance on ``grid``'s voxel centres, world units, positive inside (finite:
        points no camera sees get minus the grid's diagonal); its zero level is the carved surface
        (:func:`pipeline.surface.surface_from_field` with ``level=0``, ``inside="above"``).

    References
    ----------
    Cheung, Baker & Kanade, "Shape-from-silhouette of articulated objects and its use for human
    body kinematics estimation and motion capture", CVPR 2003.
    """
    if not isinstance(grid, Grid):
        raise ValueError(f"grid must be a pipeline.volume.Grid, got {type(grid).__name__}")
    if frame not in tracks or frame not in images:
        raise ValueError(f"frame {frame!r} must be a key of tracks and of images")
    if not np.isfinite(band) or band <= 0:
        raise ValueError(f"band must be a positive number of voxels, got {band!r}")
    if isinstance(ignore, bool) or not isinstance(ignore, (int, np.integer)) or ignore < 0:
        raise ValueError(f"ignore must be a non-negative integer, got {ignore!r}")
    V = check_points(tracks[frame], name=f"tracks[{frame}]")
    margin = _margins(margin, len(cameras))
    C = grid.centers()
    own = silhouette_distance(C, images[frame], cameras, margin=margin)  # (cameras, voxels)
    field = own.min(axis=0)
    big = float(np.linalg.norm(np.asarray(grid.shape) * grid.voxel))
    field[np.isinf(field)] = -big  # no camera sees it: carved
    # carried: the points inside the frame's own hull up to ``band`` voxels deep, and those within a voxel
    # outside it, whose values place the zero level between them and the inside ones (farther out the
    # least value can only fall further below zero: nothing to carve there)
    near = np.flatnonzero((field > -grid.voxel) & (field < float(band) * grid.voxel))
    others = [s for s in tracks if s != frame and s in images]
    if len(near) and others:
        from scipy.spatial import cKDTree

        X = C[near]
        nearest = cKDTree(V).query(X)[1]
        used, nearest = np.unique(nearest, return_inverse=True)  # only the vertices some point is nearest
        W = _neighbourhoods(V, neighbours)[used]
        values = [own[:, near]]
        for s in others:
            Q = check_points(tracks[s], name=f"tracks[{s}]")
            if Q.shape != V.shape:
                raise ValueError(f"tracks[{s}] must have the shape of tracks[{frame}] {V.shape}, got {Q.shape}")
            R, c0, c1 = _kabsch(V, Q, W)
            R, c0, c1 = R[nearest], c0[nearest], c1[nearest]
            Xs = np.einsum("nij,nj->ni", R, X - c0) + c1
            values.append(silhouette_distance(Xs, images[s], cameras, margin=margin))
        A = np.concatenate(values)
        q = min(int(ignore), len(A) - 1)
        field[near] = np.minimum(np.partition(A, q, axis=0)[q], big)
    return field.reshape(grid.shape)
