"""Simulated multi-view takes of a mesh sequence: real creature motion filmed by the dome.

:func:`simulate_mesh_take` renders every frame of a triangle-mesh sequence (the same connectivity
on every frame, e.g. the Sumner & Popovic 2004 horse gallop of ``../shared/data/horse_gallop``)
through the cameras of :func:`fake_cameras.dome.make_dome` with the Embree renderer of
:mod:`fake_cameras.mesh_render`. The texture is painted on the surface (read at every hit's rest
position), so it moves with the skin. The result is a :class:`fake_cameras.take.SimulatedTake`
with the capsule creatures' layout, so :func:`fake_cameras.record.record_take` stores it and
``stage process`` / ``stage track`` run on it unchanged; its ground truth is the mesh sequence
itself (``SimulatedTake.mesh_vertices`` / ``mesh_faces``, written beside the take in
``TAKE.gt.npz``), and named tip vertices give the limb tips of every frame.

:func:`stand_in_volume` turns a sequence from another tool's axes (e.g. y up) into the studio's
(z up, mm), scaled to fill a stated fraction of the capture volume and standing on its floor.
The studio, the cameras, the plates and the on-disk cache are :mod:`fake_cameras.take`'s.

:func:`snap_to_mesh` gives the true surface point a point started on (closest point, as triangle
and barycentric coordinates; carried by the same barycentrics on later frames, exact for one
connectivity). Hand-written because trimesh's closest-point query needs ``rtree``, which the
project does not depend on: a k-d tree of triangle centroids bounds the candidates exactly (a
triangle can hold a point nearer than the nearest vertex only if its centroid lies within that
distance plus its centroid-to-corner radius; triangles are queried in classes of similar radius),
and Ericson's closest point on a triangle (Real-Time Collision Detection, 2005, section 5.1.5),
vectorised, picks among them.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping

import numpy as np
from scipy.spatial import cKDTree

from calib.calibration import Calibration
from fake_cameras.render import Backdrop
from fake_cameras.take import (
    RENDER_VERSION,
    SimulatedTake,
    cached_render,
    check_fps,
    check_noise,
    render_plate,
    studio,
)
from stage.rig import Volume

__all__ = ["simulate_mesh_take", "stand_in_volume", "snap_to_mesh", "closest_on_triangles"]

#: Up axis of another tool's coordinates -> rotation into the studio's (z up), a proper rotation.
_UP = {
    0: np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]),  # x up: (x, y, z) -> (y, z, x)
    1: np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]),  # y up: (x, y, z) -> (z, x, y)
    2: np.eye(3),
}


def stand_in_volume(vertices, *, volume: Volume | None = None, up_axis: int = 1, fill: float = 0.8) -> tuple[np.ndarray, float]:
    """Turn a mesh sequence into the studio: z up, millimetres, centred, on the floor.

    The rotation takes ``up_axis`` to the studio's z (a cyclic permutation of the axes, so no
    mirror); the scale makes the longest side of the bounding box of the *whole sequence*
    ``fill`` times the capture volume's smallest side; the sequence's bounding box is centred
    over the volume's centre and its lowest point over the take lies on the volume's floor.

    Parameters
    ----------
    vertices : (F, V, 3) float ndarray
        The sequence in its own units.
    volume : stage.rig.Volume, optional
        Default ``Volume()``.
    up_axis : {0, 1, 2}, optional
        The sequence's up axis (1: y up).
    fill : float, optional
        Fraction of the volume's smallest side, in (0, 1].

    Returns
    -------
    vertices : (F, V, 3) float ndarray
        Studio coordinates, mm.
    scale : float
        Millimetres per unit of the input.
    """
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[2] != 3 or V.shape[0] < 1 or V.shape[1] < 3 or not np.isfinite(V).all():
        raise ValueError(f"vertices must be finite with shape (F, V >= 3, 3), got {V.shape}")
    vol = Volume() if volume is None else volume
    if not isinstance(vol, Volume):
        raise ValueError(f"volume must be a stage.rig.Volume, got {type(vol).__name__}")
    if up_axis not in _UP or isinstance(up_axis, bool):
        raise ValueError(f"up_axis must be 0, 1 or 2, got {up_axis!r}")
    if not (isinstance(fill, (int, float)) and 0 < fill <= 1):
        raise ValueError(f"fill must be within (0, 1], got {fill!r}")
    W = V @ _UP[up_axis].T
    lo, hi = W.reshape(-1, 3).min(0), W.reshape(-1, 3).max(0)
    extent = float((hi - lo).max())
    if extent <= 0:
        raise ValueError("vertices: the sequence has no extent")
    scale = fill * float(min(vol.size)) / extent
    base = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    floor = np.array([vol.center[0], vol.center[1], vol.bounds[0][2]])
    return (W - base) * scale + floor, scale


def simulate_mesh_take(
    vertices,
    faces,
    *,
    name: str = "mesh",
    n_cameras: int = 8,
    size: tuple[int, int] = (640, 480),
    fps: float = 30.0,
    seed: int = 0,
    texture_points=None,
    tip_vertices: Mapping[str, int] | None = None,
    depth: bool = False,
    cache: bool = True,
    noise_sigma: float = 2.0,
    volume: Volume | None = None,
    backdrop: Backdrop | None = None,
    calibration: Calibration | None = None,
    distortion: bool = True,
) -> SimulatedTake:
    """Render a multi-view take of a mesh sequence in the dome, with the sequence as ground truth.

    Parameters
    ----------
    vertices : (F, V, 3) float ndarray
        The mesh on every frame, studio coordinates (mm, z up; see :func:`stand_in_volume`);
        every frame inside the capture volume. 1 <= F <= 10000.
    faces : (T, 3) int ndarray
        Outward-oriented triangles, the same on every frame.
    name : str, optional
        The subject's name (``SimulatedTake.subject``).
    n_cameras, size, seed, depth, cache, noise_sigma, volume, backdrop, calibration, distortion
        As :func:`fake_cameras.take.simulate_take` (8 cameras by default).
    fps : float, optional
        Frame ``f`` shows time ``f / fps``.
    texture_points : (V, 3) float ndarray, optional
        Where each vertex reads the painted texture (default frame 0's vertices: painted on the
        surface, it moves with it).
    tip_vertices : dict str -> int, optional
        Named limb tips as vertex indices: ``SimulatedTake.tips`` holds their positions on every
        frame (``limb_names`` in the dict's order; no limb axes).

    Returns
    -------
    SimulatedTake
        ``poses`` None per frame, ``creature`` None, ``labels`` -1 on the mesh and -2 elsewhere,
        ``mesh_vertices`` the sequence and ``mesh_faces`` the triangles.
    """
    V, Fc = _check_sequence(vertices, faces)
    fps_f = check_fps(fps)
    sigma = check_noise(noise_sigma)
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty string, got {name!r}")
    vol, calib, bd = studio(volume=volume, n_cameras=n_cameras, size=size, seed=seed, distortion=distortion,
                            calibration=calibration, backdrop=backdrop)
    _check_inside(V, vol)
    tp = V[0] if texture_points is None else np.asarray(texture_points, dtype=np.float64)
    if tp.shape != V.shape[1:] or not np.isfinite(tp).all():
        raise ValueError(f"texture_points must be finite with shape {V.shape[1:]}, got {tp.shape}")
    tips_idx = _check_tips(tip_vertices, V.shape[1])
    n_frames = V.shape[0]
    params = dict(subject=name, frames=n_frames, fps=fps_f, seed=int(seed), depth=bool(depth), noise_sigma=sigma,
                  volume={"center": list(vol.center), "size": list(vol.size)}, mesh=True)
    digest = hashlib.sha1()
    for a in (np.round(V, 6), Fc, np.round(tp, 6)):
        digest.update(np.ascontiguousarray(a).tobytes())
    # "mesh_render": bump when mesh_render's output changes (RENDER_VERSION is the capsule renderer's).
    # 2: the vertex normals are pipeline.tracking's (the same to 3e-16; no pixel changed on the checked frames)
    key_src = json.dumps({"v": RENDER_VERSION, "mesh_render": 2, "params": params, "calibration": calib.to_dict(),
                          "backdrop": repr(bd), "mesh": digest.hexdigest()}, sort_keys=True)
    arrays = cached_render(key_src, lambda: _render_frames(calib, V, Fc, tp, bd, int(seed), bool(depth), sigma),
                           cache=cache)
    names = tuple(tips_idx)
    return SimulatedTake(
        subject=name, calibration=calib, images=arrays["images"], masks=arrays["masks"], labels=arrays["labels"],
        depth=arrays["depth"], plate=arrays["plate"], poses=[None] * n_frames,
        tips=[{n: V[f, i].copy() for n, i in tips_idx.items()} for f in range(n_frames)],
        axes=[{} for _ in range(n_frames)], fps=fps_f, times=np.arange(n_frames) / fps_f, limb_names=names,
        creature=None, volume=vol, params=params, mesh_vertices=V, mesh_faces=Fc,
    )


def _check_sequence(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[2] != 3 or not 1 <= V.shape[0] <= 10000 or V.shape[1] < 3 or not np.isfinite(V).all():
        raise ValueError(f"vertices must be finite with shape (F, V >= 3, 3), 1 <= F <= 10000, got {V.shape}")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be integers with shape (T >= 1, 3), got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= V.shape[1]:
        raise ValueError(f"faces must index the {V.shape[1]} vertices, got indices {f.min()}..{f.max()}")
    return V, f.astype(np.int64)


def _check_inside(V: np.ndarray, vol: Volume) -> None:
    lo, hi = (np.asarray(b, dtype=np.float64) for b in vol.bounds)
    out = ((V < lo) | (V > hi)).any(axis=2).any(axis=1)
    if out.any():
        k = int(np.flatnonzero(out)[0])
        raise ValueError(f"vertices: frame {k} leaves the capture volume {lo.tolist()}..{hi.tolist()} "
                         f"(spans {V[k].min(0).round(1).tolist()}..{V[k].max(0).round(1).tolist()}); "
                         "place the mesh in the volume (fake_cameras.mesh_take.stand_in_volume)")


def _check_tips(tip_vertices, n_vertices: int) -> dict[str, int]:
    if tip_vertices is None:
        return {}
    if not isinstance(tip_vertices, Mapping):
        raise ValueError(f"tip_vertices must map names to vertex indices, got {type(tip_vertices).__name__}")
    out = {}
    for n, i in tip_vertices.items():
        if not isinstance(n, str) or isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < n_vertices:
            raise ValueError(f"tip_vertices: {n!r} -> {i!r} is not a name and a vertex index within 0..{n_vertices - 1}")
        out[n] = int(i)
    return out


def _render_frames(calib: Calibration, V, faces, tp, bd: Backdrop, seed: int, depth: bool, sigma: float) -> dict:
    """Every frame through every camera (one Embree scene a frame), and the plates."""
    from fake_cameras.mesh_render import render_mesh_views

    C, n_frames = len(calib), len(V)
    sizes = {c.size for c in calib}
    if len(sizes) != 1:
        raise ValueError(f"calibration: all cameras must have the same size to form a take, got {sorted(sizes)}")
    w, h = sizes.pop()
    images = np.empty((n_frames, C, h, w, 3), dtype=np.uint8)
    masks = np.empty((n_frames, C, h, w), dtype=bool)
    labels = np.empty((n_frames, C, h, w), dtype=np.int8)
    dep = np.empty((n_frames, C, h, w), dtype=np.uint16) if depth else None
    for f in range(n_frames):
        views = render_mesh_views(calib, V[f], faces, texture_points=tp, backdrop=bd,
                                  rng=np.random.default_rng([seed, f]), depth=depth, noise_sigma=sigma)
        for c, v in enumerate(views):
            images[f, c], masks[f, c], labels[f, c] = v.image, v.mask, v.label
            if dep is not None:
                dep[f, c] = v.depth
    plate = np.stack([render_plate(cam, bd, seed, c, sigma) for c, cam in enumerate(calib)])
    return {"images": images, "masks": masks, "labels": labels, "depth": dep, "plate": plate}


def closest_on_triangles(points, a, b, c) -> np.ndarray:
    """Barycentric coordinates (N, 3) of the closest point of triangle ``(a, b, c)[i]`` to ``points[i]``.

    Ericson 2005, section 5.1.5 (Voronoi regions of the vertices, edges and face), vectorised;
    all arguments (N, 3). Degenerate triangles fall to their vertex or edge regions.
    """
    p, a, b, c = (_as_rows(x, name) for x, name in ((points, "points"), (a, "a"), (b, "b"), (c, "c")))
    for x, name in ((a, "a"), (b, "b"), (c, "c")):
        if len(x) != len(p):
            raise ValueError(f"{name} must have one triangle corner per point, shape ({len(p)}, 3), got {x.shape}")
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    out = np.empty((len(p), 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        out[:] = np.stack([va, vb, vc], axis=1) / np.where(den != 0, den, 1.0)[:, None]  # inside the face
        cases = [  # (region, weight of b, weight of c), later regions win
            (vc <= 0) & (d1 >= 0) & (d3 <= 0), d1 / (d1 - d3), 0.0,  # edge ab
            (vb <= 0) & (d2 >= 0) & (d6 <= 0), 0.0, d2 / (d2 - d6),  # edge ac
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), None, None,  # edge bc
            (d1 <= 0) & (d2 <= 0), 0.0, 0.0,  # vertex a
            (d3 >= 0) & (d4 <= d3), 1.0, 0.0,  # vertex b
            (d6 >= 0) & (d5 <= d6), 0.0, 1.0,  # vertex c
        ]
        for k in range(0, len(cases), 3):
            m, wb, wc = cases[k], cases[k + 1], cases[k + 2]
            if wb is None:  # edge bc
                w = ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[m]
                out[m] = np.stack([np.zeros_like(w), 1 - w, w], axis=1)
                continue
            wb = np.broadcast_to(wb, m.shape)[m]
            wc = np.broadcast_to(wc, m.shape)[m]
            out[m] = np.stack([1 - wb - wc, wb, wc], axis=1)
    return np.nan_to_num(out, nan=1.0 / 3)


def _as_rows(x, name: str) -> np.ndarray:
    """``x`` as a finite (N, 3) float array, or a ValueError naming ``name``."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a numeric (N, 3) array, got {type(x).__name__}") from None
    if a.ndim != 2 or a.shape[1] != 3 or not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite with shape (N, 3), got {a.shape}")
    return a


def snap_to_mesh(vertices, faces, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest point of a triangle mesh to every point, as triangle and barycentric coordinates.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (T, 3) int ndarray
    points : (N, 3) float ndarray

    Returns
    -------
    triangle : (N,) int ndarray
    barycentric : (N, 3) float ndarray
        The closest point is ``barycentric[i] @ vertices[faces[triangle[i]]]``.
    distance : (N,) float ndarray
    """
    V, F = _check_sequence(np.asarray(vertices, dtype=np.float64)[None], faces)
    V = V[0]
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or not np.isfinite(P).all():
        raise ValueError(f"points must be finite with shape (N, 3), got {P.shape}")
    used = np.unique(F)
    d_vertex = cKDTree(V[used]).query(P)[0]
    tri = V[F]
    centroid = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroid[:, None], axis=2).max(axis=1)
    # triangles in classes of similar radius (doubling), each class's bound its own largest radius
    cls = np.floor(np.log2(np.maximum(radius / max(np.median(radius), 1e-300), 1.0))).astype(np.int64)
    owners, tris = [], []
    for c in np.unique(cls):
        members = np.flatnonzero(cls == c)
        cand = cKDTree(centroid[members]).query_ball_point(P, d_vertex + radius[members].max() + 1e-9)
        n = np.fromiter((len(x) for x in cand), dtype=np.int64, count=len(P))
        owners.append(np.repeat(np.arange(len(P)), n))
        tris.append(members[np.concatenate([np.asarray(x, dtype=np.int64) for x in cand])] if n.sum() else members[:0])
    owner, t = np.concatenate(owners), np.concatenate(tris)
    bary = closest_on_triangles(P[owner], tri[t, 0], tri[t, 1], tri[t, 2])
    d = np.linalg.norm(np.einsum("nj,njc->nc", bary, tri[t]) - P[owner], axis=1)
    order = np.lexsort((d, owner))  # per point, nearest first
    first = order[np.r_[True, owner[order][1:] != owner[order][:-1]]]
    return t[first], bary[first], d[first]
