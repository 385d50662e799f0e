"""Ray-cast rendering of a triangle mesh in the green studio, for any camera of a calibration.

The counterpart of :func:`fake_cameras.render.render_view` for a subject given as a triangle
mesh (a tracked or animated mesh sequence, a scan) instead of capsules: the same pixel rays
(:func:`calib.camera.cached_pixel_grid_rays`, so the camera's lens distortion is rendered
exactly), the same studio background and the same image formation
(:func:`fake_cameras.render.compose_view`: vignetting, Lambert shading by the key and fill lights,
procedural texture, green spill, optical blur, sensor noise) into the same :class:`View` (image,
mask, depth, label).

Why ray casting with Embree (``embreex``, through which ``trimesh`` also casts rays) rather than
a z-buffer rasteriser: a rasteriser draws straight-edged triangles in the undistorted image, so a
distorted camera of a real calibration would need per-pixel rays anyway. Embree's scene (with the
vertex normals) is built once per frame and serves any number of cameras (:func:`render_mesh_views`);
its speed is measured by ``stage bench render`` (docs/tracking.md, "The renderer's speed").
Only the rays of image tiles (16 px, as in :mod:`fake_cameras.render`) that can see the mesh's
bounding sphere are cast.

The texture is read at each hit's *texture point*: the barycentric blend of its triangle's
``texture_points`` (per vertex). Pass the mesh's rest (first-frame) vertices and the texture is
painted on the surface and moves with it, as :class:`fake_cameras.render.Backdrop` ``painted``
does for the capsules; without them it is a function of the world position. Shading uses the
vertex normals (area-weighted, :func:`pipeline.mesh_primitives.vertex_normals`, interpolated over the
triangle), so a fine mesh looks smooth.
The mesh casts a hard shadow on the floor: a ray from every floor pixel near the mesh's
shadow towards the key light, tested against the same scene (the optical blur softens its edge).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera
from fake_cameras.render import Backdrop, Hits, View, _scene, _texture, compose_view, studio_options
from pipeline.mesh_primitives import check_mesh, vertex_normals

__all__ = ["MeshScene", "render_mesh", "render_mesh_views"]

BODY = -1  # label of mesh pixels without a face label


class MeshScene:
    """One frame's mesh in an Embree scene, with what shading needs; cast rays at it from any camera.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        World coordinates, the calibration's units (mm).
    faces : (F, 3) int ndarray
        Triangles, outward-oriented (their normals shade).
    texture_points : (V, 3) float ndarray, optional
        Where each vertex reads the texture (its rest position); default ``vertices``.
    face_label : (F,) int ndarray, optional
        Label of each triangle's pixels (default :data:`BODY`).
    """

    def __init__(self, vertices, faces, *, texture_points=None, face_label=None):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.vertices, self.faces = check_mesh(vertices, faces, min_vertices=3, min_faces=1)
        V, F = len(self.vertices), len(self.faces)
        tp = self.vertices if texture_points is None else np.asarray(texture_points, dtype=np.float64)
        if tp.shape != (V, 3) or not np.isfinite(tp).all():
            raise ValueError(f"texture_points must be finite with shape ({V}, 3), got {tp.shape}")
        self.texture_points = tp
        lab = np.full(F, BODY, np.int16) if face_label is None else np.asarray(face_label)
        if lab.shape != (F,) or not np.issubdtype(lab.dtype, np.integer):
            raise ValueError(f"face_label must be integers with shape ({F},), got {lab.shape} {lab.dtype}")
        self.face_label = lab.astype(np.int16)
        self.normals = vertex_normals(self.vertices, self.faces)
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        # Embree works in float32: centre the scene so coordinates stay small
        self.offset = (lo + hi) / 2
        self.radius = float(np.linalg.norm(hi - lo) / 2) + 1e-6
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self._scene, (self.vertices - self.offset).astype(np.float32), self.faces.astype(np.int32))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits of rays (unit ``dirs``): ``(t (N,), face (N,), barycentric (N, 3))``; face -1 misses.

        ``t`` is the distance along the ray (inf where it misses), recomputed in float64 from the
        hit triangle's plane.
        """
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64), dirs.shape)
        res = self._scene.run((o - self.offset).astype(np.float32), np.ascontiguousarray(dirs, np.float32), output=1)
        face = res["primID"].astype(np.int64)
        face[res["geomID"] < 0] = -1
        hit = face >= 0
        bary = np.zeros((len(face), 3))
        u, v = res["u"][hit].astype(np.float64), res["v"][hit].astype(np.float64)
        bary[hit] = np.stack([1.0 - u - v, u, v], axis=1)
        t = np.full(len(face), np.inf)
        if hit.any():
            tri = self.vertices[self.faces[face[hit]]]  # (K, 3, 3)
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            den = np.einsum("ij,ij->i", n, dirs[hit])
            num = np.einsum("ij,ij->i", n, tri[:, 0] - o[hit])
            safe = np.abs(den) > 1e-12 * np.linalg.norm(n, axis=1)
            t[hit] = np.where(safe, num / np.where(safe, den, 1.0), res["tfar"][hit])
        return t, face, bary

    def blocked(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(N,) bool: does the ray from each origin along its direction meet the mesh."""
        if len(origins) == 0:
            return np.zeros(0, dtype=bool)
        res = self._scene.run((origins - self.offset).astype(np.float32), np.ascontiguousarray(dirs, np.float32))
        return np.asarray(res) >= 0

    def interpolate(self, values: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Per-vertex ``values`` (V, C) blended at hits ``(face, bary)``: (K, C)."""
        return np.einsum("kj,kjc->kc", bary, values[self.faces[face]])


def render_mesh_views(
    cameras: Calibration | Sequence[Camera],
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    texture_points: np.ndarray | None = None,
    face_label: np.ndarray | None = None,
    backdrop: Backdrop | None = None,
    rng: np.random.Generator | None = None,
    depth: bool = False,
    noise_sigma: float = 2.0,
) -> list[View]:
    """Render one mesh (one frame) from every camera, in the green studio.

    Parameters
    ----------
    cameras : calib.Calibration or sequence of calib.Camera
        True cameras (their distortion is rendered); each must be inside the backdrop's wall.
    vertices : (V, 3) float ndarray
        World coordinates (mm).
    faces : (F, 3) int ndarray
        Outward-oriented triangles.
    texture_points : (V, 3) float ndarray, optional
        Each vertex's rest position, where it reads the texture (painted on the surface);
        default the vertices themselves (the texture of the world position).
    face_label : (F,) int ndarray, optional
        Label of every triangle, written to :attr:`View.label` (default -1, body).
    backdrop : fake_cameras.render.Backdrop, optional
        Studio and image formation (default ``Backdrop()``); its ``creature_color``,
        ``texture``, ``texture_scale``, lights, shadow, spill, blur and vignette apply.
    rng : numpy.random.Generator, optional
        Source of the sensor noise (drawn camera after camera); None draws fresh noise.
    depth : bool, optional
        Also return each camera's depth image (camera-frame Z, mm, of the first surface hit).
    noise_sigma : float, optional
        Gaussian sensor noise, grey levels.

    Returns
    -------
    list of View
        One per camera, in order.
    """
    cams = list(cameras.cameras if isinstance(cameras, Calibration) else cameras)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise ValueError("cameras must be a calib.Calibration or a non-empty sequence of calib.Camera")
    bd, sigma = studio_options(backdrop, noise_sigma)
    mesh = MeshScene(vertices, faces, texture_points=texture_points, face_label=face_label)
    rng = np.random.default_rng() if rng is None else rng
    return [_render_camera(cam, mesh, bd, rng, depth, sigma) for cam in cams]


def render_mesh(camera: Camera, vertices: np.ndarray, faces: np.ndarray, **kwargs) -> View:
    """:func:`render_mesh_views` for one camera (same keyword options)."""
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a calib.Camera, got {type(camera).__name__}")
    return render_mesh_views([camera], vertices, faces, **kwargs)[0]


def _candidate_pixels(sc, mesh: MeshScene) -> np.ndarray:
    """Pixels of the tiles whose rays can meet the mesh's bounding sphere."""
    v = mesh.offset - sc.origin
    dist = float(np.linalg.norm(v))
    if dist <= mesh.radius:  # the camera is within the bounding sphere: every ray
        return np.arange(sc.h * sc.w)
    ang = np.arccos(np.clip(sc.tile_dir @ v / dist, -1.0, 1.0))
    near = ang <= sc.tile_ang + math.asin(min(mesh.radius / dist, 1.0))
    keep = np.zeros(sc.h * sc.w, dtype=bool)
    keep[sc.tile_pix[near].ravel()] = True  # (padded tiles repeat edge pixels)
    return np.flatnonzero(keep)


def _render_camera(cam: Camera, mesh: MeshScene, bd: Backdrop, rng, depth: bool, sigma: float) -> View:
    sc = _scene(cam, bd)
    img = sc.background.copy()
    _shadow(sc, mesh, bd, img)
    ray = _candidate_pixels(sc, mesh)
    t, face, bary = mesh.cast(sc.origin, sc.dirs[ray])
    hit = face >= 0
    ray, t, face, bary = ray[hit], t[hit], face[hit], bary[hit]
    n = mesh.interpolate(mesh.normals, face, bary)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    tex = _texture(mesh.interpolate(mesh.texture_points, face, bary), bd)
    hits = Hits(ray=ray, t=t, normals=n, texture=tex, label=mesh.face_label[face])
    return compose_view(sc, bd, img, hits, depth=depth, sigma=sigma, rng=rng)


def _shadow(sc, mesh: MeshScene, bd: Backdrop, img: np.ndarray) -> None:
    """Darken the floor pixels from which the key light is hidden by the mesh (a ray each)."""
    if bd.shadow_strength <= 0 or sc.floor_idx.size == 0:
        return
    # the mesh's bounding sphere seen along the key light (orthographic): a disc in light space
    c = mesh.offset @ sc.light_basis
    uv = sc.floor_uv[sc.floor_idx]
    near = np.linalg.norm(uv - c, axis=1) <= mesh.radius
    pix, pts = sc.floor_idx[near], sc.floor_pts[near]
    if pix.size == 0:
        return
    dark = mesh.blocked(pts, np.broadcast_to(sc.key, pts.shape))
    rows, cols = np.divmod(pix[dark], sc.w)
    img[rows, cols] *= np.float32(1.0 - bd.shadow_strength)
