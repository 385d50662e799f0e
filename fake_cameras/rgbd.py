"""Simulated single RGB-D takes: one OAK-like camera filming an articulated object bent by hand.

The objects of Tzionas & Gall (2016, §5), as chains of capsules (round cones) joined at
their end spheres:

``pipe_half``   a 300 mm pipe (radius 15 mm) with one joint at 1/2 of its length;
``pipe_3q``     the same pipe with its joint at 3/4;
``lamp``        a desk lamp: base, two arms and a head, three joints.

Over the take every joint bends from the rest pose to ``bend`` degrees (default 75, well
past 45) about the camera's viewing axis, each joint starting at its own time, with a
smooth (smoothstep) ramp. The template is the object's rest surface (marching cubes of
the exact signed distance, :func:`template_mesh`); every template vertex belongs to the
capsule it lies on at rest and moves rigidly with it, which gives per-vertex ground truth
on every frame. Images and depth come from :func:`fake_cameras.render.render_view` (the
green studio), depth with Gaussian noise growing with distance like a stereo camera's. The
objects' texture is painted on them (:class:`fake_cameras.creatures.Pose` ``rest``: it moves
with every part, as a real object's does) and finer than the creatures' (:data:`TEXTURE`,
:data:`TEXTURE_SCALE`).

:func:`simulate_rgbd_take` returns a :class:`SimulatedRGBDTake`; :func:`record_rgbd_take`
writes it as a take file (one camera with depth), the template as ``TAKE.template.ply``
and the ground truth as ``TAKE.gt.npz`` beside it (:func:`load_rgbd_ground_truth`).

Any mesh sequence with the same connectivity on every frame (a real tracked motion, an
animation) becomes such a take with :func:`simulate_mesh_rgbd_take` (rendered by
:func:`fake_cameras.mesh_render.render_mesh`, any calibrated camera; the template is frame 0's
mesh, every vertex its own truth), and a sequence given in a sensor's own camera frame, filmed
from that sensor's pose, with :func:`simulate_sensor_rgbd_take`.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera
from fake_cameras.creatures import Pose
from fake_cameras.render import Backdrop, render_view

__all__ = [
    "OBJECTS",
    "ArticulatedObject",
    "SimulatedRGBDTake",
    "make_object",
    "template_mesh",
    "oak_camera",
    "simulate_rgbd_take",
    "record_rgbd_take",
    "load_rgbd_ground_truth",
    "template_path",
    "oak_sensor_camera",
    "simulate_mesh_rgbd_take",
    "simulate_sensor_rgbd_take",
    "stereo_depth_noise",
]

OBJECTS = ("pipe_half", "pipe_3q", "lamp")
TEXTURE = 0.15  # amplitude of the objects' painted texture (fake_cameras.render.Backdrop.texture)
TEXTURE_SCALE = 0.5  # its wavelengths relative to the creatures' (about 9 to 60 mm)


def _rot(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


@dataclass(frozen=True)
class ArticulatedObject:
    """A chain of capsules joined end to end.

    Parameters
    ----------
    name : str
    points : (S+1, 3) float ndarray
        Chain joints at rest, mm (segment ``k`` runs from ``points[k]`` to ``points[k+1]``).
    radii : (S+1,) float ndarray
        Radius at every chain point, mm.
    joints : tuple of int
        Chain points that bend (indices into ``points``, never the ends).
    axis : (3,) float ndarray
        Bending axis of every joint (the camera's viewing direction).
    """

    name: str
    points: np.ndarray
    radii: np.ndarray
    joints: tuple[int, ...]
    axis: np.ndarray

    @property
    def n_segments(self) -> int:
        return int(len(self.points) - 1)

    @property
    def length(self) -> float:
        """Length of the chain plus its end caps, mm."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum()
        return float(seg + self.radii[0] + self.radii[-1])

    def segment_transforms(self, angles) -> tuple[np.ndarray, np.ndarray]:
        """Rigid motion of every segment for the given joint angles (radians).

        Returns
        -------
        R : (S, 3, 3) float ndarray
        t : (S, 3) float ndarray
            A rest point ``x`` of segment ``k`` moves to ``R[k] @ x + t[k]``.
        """
        angles = np.asarray(angles, dtype=np.float64).reshape(-1)
        if angles.shape != (len(self.joints),):
            raise ValueError(f"angles must have {len(self.joints)} values, got {angles.shape}")
        S = self.n_segments
        R = np.zeros((S, 3, 3))
        t = np.zeros((S, 3))
        Rc, tc = np.eye(3), np.zeros(3)
        bend = dict(zip(self.joints, angles))
        for k in range(S):
            if k in bend:  # segment k starts at a joint: rotate about the joint's current position
                p = Rc @ self.points[k] + tc
                Rj = _rot(self.axis, bend[k])  # planar chain: every joint bends about the same axis
                Rc, tc = Rj @ Rc, Rj @ (tc - p) + p
            R[k], t[k] = Rc, tc
        return R, t

    def pose(self, angles) -> Pose:
        """The capsules for the given joint angles (a :class:`fake_cameras.creatures.Pose`)."""
        R, t = self.segment_transforms(angles)
        p0 = np.einsum("kij,kj->ki", R, self.points[:-1]) + t
        p1 = np.einsum("kij,kj->ki", R, self.points[1:]) + t
        return Pose(p0=p0, p1=p1, r0=self.radii[:-1], r1=self.radii[1:], limb=np.arange(self.n_segments),
                    rest=np.concatenate([R, t[:, :, None]], axis=2))


def make_object(name: str, *, base=(0.0, 0.0, 300.0)) -> ArticulatedObject:
    """One of :data:`OBJECTS`, standing in the x-z plane around ``base`` (mm); it bends about +y."""
    if name not in OBJECTS:
        raise ValueError(f"name must be one of {', '.join(OBJECTS)}, got {name!r}")
    b = np.asarray(base, dtype=np.float64)
    if name in ("pipe_half", "pipe_3q"):
        L, r = 300.0, 15.0
        at = 0.5 if name == "pipe_half" else 0.75
        z = np.array([0.0, at * L, L]) - L / 2
        pts = b + np.stack([np.zeros(3), np.zeros(3), z], axis=1)
        return ArticulatedObject(name, pts, np.full(3, r), (1,), np.array([0.0, 1.0, 0.0]))
    # lamp: a flat base, a lower and an upper arm, a conical head
    pts = b + np.array([[-150.0, 0, -150], [-60.0, 0, -150], [-60.0, 0, 20], [90.0, 0, 110], [150.0, 0, 60]])
    radii = np.array([22.0, 22.0, 11.0, 11.0, 24.0])
    return ArticulatedObject(name, pts, radii, (1, 2, 3), np.array([0.0, 1.0, 0.0]))


def template_mesh(obj: ArticulatedObject, *, spacing: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The rest surface of ``obj``: marching cubes of its exact signed distance.

    Parameters
    ----------
    spacing : float, optional
        Grid step, mm (default 3 mm for the pipes, 5 mm for the lamp).

    Returns
    -------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
        Outward-oriented, closed.
    """
    from skimage.measure import marching_cubes

    h = float(spacing if spacing is not None else (5.0 if obj.name == "lamp" else 3.0))
    pose = obj.pose(np.zeros(len(obj.joints)))
    lo, hi = pose.bounds()
    lo, hi = lo - 2 * h, hi + 2 * h
    axes = [np.arange(lo[i], hi[i] + h, h) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    sdf = pose.sdf(G).reshape(len(axes[0]), len(axes[1]), len(axes[2]))
    v, f, _, _ = marching_cubes(sdf, 0.0, spacing=(h, h, h))
    v = v + lo
    f = f.astype(np.int64)  # skimage orients the triangles towards increasing distance: outward
    return v, f


def oak_camera(*, size=(640, 400), distance: float = 800.0, target=(0.0, 0.0, 300.0), name: str = "oak") -> Camera:
    """An OAK-D-like colour camera with aligned depth (71 degrees horizontal field of view).

    It looks along +y at ``target`` from ``distance`` mm, level, no lens distortion.
    """
    w, h = (int(s) for s in size)
    f = 0.5 * w / math.tan(math.radians(71.0) / 2)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # x right, y down (= -z), z forward (= +y)
    c = np.asarray(target, dtype=np.float64) - np.array([0.0, distance, 0.0])
    return Camera(name, K, np.zeros(5), R, -R @ c, (w, h))


@dataclass(frozen=True, eq=False)
class SimulatedRGBDTake:
    """A single-camera RGB-D take of an articulated object, with per-vertex ground truth.

    Parameters
    ----------
    object : ArticulatedObject or None
        None for a take of a mesh sequence (:func:`simulate_mesh_rgbd_take`).
    calibration : calib.Calibration
        The one camera.
    images : (F, H, W, 3) uint8 ndarray
    depth : (F, H, W) uint16 ndarray
        Camera-frame Z in mm (0 = no return).
    template_vertices : (V, 3) float ndarray
    template_faces : (T, 3) int ndarray
    vertex_segment : (V,) int ndarray
        Capsule every template vertex moves with.
    truth : (F, V, 3) float ndarray
        Every template vertex on every frame.
    angles : (F, J) float ndarray
        Joint angles, radians.
    joint_positions : (F, J, 3) float ndarray
    fps : float
    params : dict
    length : float, optional
        The object's length, mm; default the articulated object's.
    """

    object: ArticulatedObject | None
    calibration: Calibration
    images: np.ndarray
    depth: np.ndarray
    template_vertices: np.ndarray
    template_faces: np.ndarray
    vertex_segment: np.ndarray
    truth: np.ndarray
    angles: np.ndarray
    joint_positions: np.ndarray
    fps: float
    params: dict
    length: float | None = None

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def size(self) -> float:
        """The object's length, mm (what errors are a fraction of)."""
        return float(self.length) if self.length is not None else self.object.length


def _angles(obj: ArticulatedObject, frames: int, bend: float) -> np.ndarray:
    J = len(obj.joints)
    u = np.linspace(0.0, 1.0, frames)
    out = np.zeros((frames, J))
    sign = np.array([1.0, -1.0, 1.0])[:J] if J > 1 else np.array([1.0])
    for j in range(J):
        a, b = (0.0, 1.0) if J == 1 else (0.45 * j / (J - 1), 0.55 + 0.45 * j / (J - 1))
        x = np.clip((u - a) / (b - a), 0, 1)
        out[:, j] = sign[j] * math.radians(bend) * x * x * (3 - 2 * x)
    return out


def simulate_rgbd_take(
    name: str = "pipe_half",
    *,
    frames: int = 30,
    fps: float = 30.0,
    bend: float = 75.0,
    size: tuple[int, int] = (640, 400),
    distance: float = 800.0,
    depth_noise: float = 1.0,
    spacing: float | None = None,
    seed: int = 0,
) -> SimulatedRGBDTake:
    """Render a single RGB-D camera's take of one of :data:`OBJECTS` being bent.

    Parameters
    ----------
    name : {"pipe_half", "pipe_3q", "lamp"}
    frames : int, optional
        2..2000 frames; the bend runs over the whole take.
    fps : float, optional
    bend : float, optional
        Final angle of every joint, degrees (0..150).
    size : (int, int), optional
        Image (width, height).
    distance : float, optional
        Camera to object, mm.
    depth_noise : float, optional
        Depth noise standard deviation at 1 m, mm (grows with the square of the distance).
    spacing : float, optional
        Template grid step (:func:`template_mesh`).
    seed : int, optional

    Returns
    -------
    SimulatedRGBDTake
    """
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or not 2 <= frames <= 2000:
        raise ValueError(f"frames must be an integer within 2..2000, got {frames!r}")
    if not (isinstance(bend, (int, float)) and 0 <= bend <= 150):
        raise ValueError(f"bend must be within 0..150 degrees, got {bend!r}")
    if not (isinstance(depth_noise, (int, float)) and depth_noise >= 0):
        raise ValueError(f"depth_noise must be >= 0, got {depth_noise!r}")
    if not (isinstance(fps, (int, float)) and 0 < fps <= 1000):
        raise ValueError(f"fps must be within (0, 1000], got {fps!r}")
    obj = make_object(name)
    cam = oak_camera(size=size, distance=distance, target=obj.points.mean(0))
    V, T = template_mesh(obj, spacing=spacing)
    rest = obj.pose(np.zeros(len(obj.joints)))
    seg = rest.capsule_sdf(V).argmin(axis=1)
    angles = _angles(obj, int(frames), float(bend))
    rng = np.random.default_rng(seed)
    # the texture is painted on the object (it moves with every part) and finer than the creatures'
    bd = Backdrop(wall_radius=4000.0, wall_height=4000.0, texture=TEXTURE, texture_scale=TEXTURE_SCALE)
    F = int(frames)
    w, h = cam.size
    images = np.empty((F, h, w, 3), np.uint8)
    depth = np.empty((F, h, w), np.uint16)
    truth = np.empty((F, len(V), 3))
    jpos = np.empty((F, len(obj.joints), 3))
    for k in range(F):
        R, t = obj.segment_transforms(angles[k])
        truth[k] = np.einsum("vij,vj->vi", R[seg], V) + t[seg]
        jpos[k] = [R[j] @ obj.points[j] + t[j] for j in obj.joints]
        view = render_view(cam, obj.pose(angles[k]), backdrop=bd, rng=np.random.default_rng([seed, k]), depth=True)
        images[k] = view.image
        depth[k] = stereo_depth_noise(view.depth, sigma=depth_noise, rng=rng)
    params = dict(name=name, frames=F, fps=float(fps), bend=float(bend), size=[w, h], distance=float(distance),
                  depth_noise=float(depth_noise), spacing=spacing, seed=int(seed))
    return SimulatedRGBDTake(
        object=obj, calibration=Calibration((cam,)), images=images, depth=depth, template_vertices=V,
        template_faces=T, vertex_segment=seg, truth=truth, angles=angles, joint_positions=jpos,
        fps=float(fps), params=params,
    )


def stereo_depth_noise(z: np.ndarray, *, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """A stereo camera's depth from true depth: Gaussian noise of ``sigma`` mm at 1 m, growing with
    the square of the distance, rounded to whole mm; 0 (no return) stays 0.

    Parameters
    ----------
    z : (H, W) ndarray
        True camera-frame Z, mm (0 = nothing).
    sigma : float
        Standard deviation at 1 m, mm.
    rng : numpy.random.Generator
        One normal draw per pixel.

    Returns
    -------
    (H, W) uint16 ndarray
    """
    try:
        z = np.asarray(z, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"z must be a numeric (H, W) depth image, got {type(z).__name__}") from None
    if z.ndim != 2 or not np.isfinite(z).all() or (z < 0).any():
        raise ValueError(f"z must be a finite (H, W) depth image >= 0 (mm, 0 = nothing), got shape {z.shape}"
                         + ("" if z.ndim != 2 or z.size == 0 else f", values {z.min():g}..{z.max():g}"))
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float, np.integer, np.floating)) \
            or not (math.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be a finite number >= 0 (mm at 1 m), got {sigma!r}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    noisy = z + rng.normal(0.0, 1.0, z.shape) * sigma * (z / 1000.0) ** 2
    return np.where(z > 0, np.clip(np.round(noisy), 1, 65535), 0).astype(np.uint16)


def oak_sensor_camera(*, size=(640, 400), height: float = 1000.0, name: str = "oak") -> tuple[Camera, np.ndarray]:
    """The OAK-like camera (:func:`oak_camera`'s intrinsics) at the pose of a sensor whose camera
    frame the data are given in (a recorded sequence's own coordinates).

    The studio (:class:`fake_cameras.render.Backdrop`) stands on the floor ``z = 0`` with z up,
    so the sensor's camera frame cannot be the world frame itself (the camera would stand on the
    floor). The world frame is placed so that the camera is level, ``height`` mm above the floor,
    looking along +y (as :func:`oak_camera`); a point ``x`` of the sensor's frame is at
    ``world_from_sensor[:3, :3] @ x + world_from_sensor[:3, 3]`` in the world, and the camera
    sees it exactly where the sensor saw it (same camera-frame coordinates, same depth).

    Returns
    -------
    camera : calib.Camera
    world_from_sensor : (4, 4) float ndarray
        Rigid motion from the sensor's camera frame to the world.
    """
    if not (isinstance(height, (int, float)) and 0 < height < 4000):
        raise ValueError(f"height must be within (0, 4000) mm, got {height!r}")
    cam = oak_camera(size=size, distance=0.0, target=(0.0, 0.0, float(height)), name=name)
    T = np.eye(4)
    T[:3, :3] = cam.R.T
    T[:3, 3] = cam.center
    return cam, T


def simulate_mesh_rgbd_take(
    vertices: np.ndarray,
    faces: np.ndarray,
    camera: Camera,
    *,
    texture_points: np.ndarray | None = None,
    fps: float = 30.0,
    depth_noise: float = 1.0,
    backdrop: Backdrop | None = None,
    vertex_segment: np.ndarray | None = None,
    joint_positions: np.ndarray | None = None,
    length: float | None = None,
    name: str = "mesh",
    seed: int = 0,
) -> SimulatedRGBDTake:
    """Render a single RGB-D camera's take of a mesh sequence (the same connectivity every frame).

    Colour and depth come from :func:`fake_cameras.mesh_render.render_mesh` in the objects' green
    studio, depth with the stereo noise of :func:`simulate_rgbd_take` (:func:`stereo_depth_noise`).
    The template is frame 0's mesh and every vertex is its own ground truth on every frame.

    Parameters
    ----------
    vertices : (F, V, 3) float ndarray
        The mesh on every frame, world coordinates (mm).
    faces : (T, 3) int ndarray
    camera : calib.Camera
        Any calibrated camera inside the studio (e.g. :func:`oak_sensor_camera`).
    texture_points : (V, 3) float ndarray, optional
        Where each vertex reads the painted texture; default frame 0's vertices (painted on the
        surface at frame 0: it moves with the surface).
    fps : float, optional
    depth_noise : float, optional
        Depth noise standard deviation at 1 m, mm.
    backdrop : fake_cameras.render.Backdrop, optional
        Default: the objects' studio and texture (:data:`TEXTURE`, :data:`TEXTURE_SCALE`).
    vertex_segment : (V,) int ndarray, optional
        Part of every vertex (default 0), kept in the ground truth.
    joint_positions : (F, J, 3) float ndarray, optional
        True joints on every frame (default none), kept in the ground truth.
    length : float, optional
        The object's length, mm (what errors are a fraction of); default its bounding box's
        longest side at frame 0.
    name : str, optional
    seed : int, optional

    Returns
    -------
    SimulatedRGBDTake
        ``object`` None, ``angles`` (F, 0).
    """
    from fake_cameras.mesh_render import render_mesh

    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[2] != 3 or not 2 <= V.shape[0] <= 2000 or not np.isfinite(V).all():
        raise ValueError(f"vertices must be finite with shape (F, V, 3), 2 <= F <= 2000, got {V.shape}")
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a calib.Camera, got {type(camera).__name__}")
    if not (isinstance(depth_noise, (int, float)) and depth_noise >= 0):
        raise ValueError(f"depth_noise must be >= 0, got {depth_noise!r}")
    if not (isinstance(fps, (int, float)) and 0 < fps <= 1000):
        raise ValueError(f"fps must be within (0, 1000], got {fps!r}")
    F, NV = V.shape[:2]
    seg = np.zeros(NV, np.int64) if vertex_segment is None else np.asarray(vertex_segment, dtype=np.int64)
    if seg.shape != (NV,):
        raise ValueError(f"vertex_segment must have shape ({NV},), got {seg.shape}")
    jpos = np.zeros((F, 0, 3)) if joint_positions is None else np.asarray(joint_positions, dtype=np.float64)
    if jpos.ndim != 3 or jpos.shape[0] != F or jpos.shape[2] != 3:
        raise ValueError(f"joint_positions must have shape ({F}, J, 3), got {jpos.shape}")
    uv, z = camera.project(V[0], return_depth=True)
    seen = (z > 0) & camera.in_image(uv)
    if seen.mean() < 0.5:
        raise ValueError(f"vertices: only {100 * seen.mean():.0f} % of frame 0's mesh is in view of camera "
                         f"{camera.name!r} (in front of it and inside its image); place the camera or the mesh")
    try:
        size = float(np.ptp(V[0], axis=0).max()) if length is None else float(length)
    except (TypeError, ValueError):
        raise ValueError(f"length must be a positive number (mm), got {length!r}") from None
    if not (size > 0 and math.isfinite(size)):
        raise ValueError(f"length must be a positive number (mm), got {length!r}")
    bd = backdrop if backdrop is not None else Backdrop(wall_radius=4000.0, wall_height=4000.0, texture=TEXTURE,
                                                        texture_scale=TEXTURE_SCALE)
    tp = V[0] if texture_points is None else texture_points
    rng = np.random.default_rng(seed)
    w, h = camera.size
    images = np.empty((F, h, w, 3), np.uint8)
    depth = np.empty((F, h, w), np.uint16)
    for k in range(F):
        view = render_mesh(camera, V[k], faces, texture_points=tp, backdrop=bd,
                           rng=np.random.default_rng([seed, k]), depth=True)
        images[k] = view.image
        depth[k] = stereo_depth_noise(view.depth, sigma=depth_noise, rng=rng)
    params = dict(name=str(name), frames=F, fps=float(fps), size=[w, h], depth_noise=float(depth_noise), seed=int(seed),
                  camera=camera.to_dict())
    return SimulatedRGBDTake(
        object=None, calibration=Calibration((camera,)), images=images, depth=depth, template_vertices=V[0].copy(),
        template_faces=np.asarray(faces, dtype=np.int64), vertex_segment=seg, truth=V, angles=np.zeros((F, 0)),
        joint_positions=jpos, fps=float(fps), params=params, length=size,
    )


def simulate_sensor_rgbd_take(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    size=(640, 400),
    height: float = 1000.0,
    joint_positions: np.ndarray | None = None,
    **kwargs,
) -> SimulatedRGBDTake:
    """:func:`simulate_mesh_rgbd_take` of a mesh sequence given in a sensor's camera frame (mm), filmed
    by the OAK-like camera at that sensor's pose (:func:`oak_sensor_camera`).

    The take's vertices, template and joints are in the studio's world frame
    (``world_from_sensor`` applied; ``take.params["world_from_sensor"]``); the camera sees every
    point where the sensor saw it. Other keyword options are :func:`simulate_mesh_rgbd_take`'s.

    Parameters
    ----------
    vertices : (F, V, 3) float ndarray
        Sensor camera frame, mm.
    faces : (T, 3) int ndarray
    size : (int, int), optional
        Image (width, height).
    height : float, optional
        The camera's height above the studio's floor, mm.
    joint_positions : (F, J, 3) float ndarray, optional
        Sensor camera frame, mm.
    """
    cam, T = oak_sensor_camera(size=size, height=height)
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[2] != 3:
        raise ValueError(f"vertices must have shape (F, V, 3), got {V.shape}")
    J = None if joint_positions is None else np.asarray(joint_positions, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    tk = simulate_mesh_rgbd_take(V @ T[:3, :3].T + T[:3, 3], faces, cam, joint_positions=J, **kwargs)
    tk.params["world_from_sensor"] = T.tolist()
    return tk


def record_rgbd_take(take: SimulatedRGBDTake, path: str | os.PathLike, *, drop_depth=(), overwrite: bool = True) -> Path:
    """Write a simulated RGB-D take: ``TAKE.h5``, ``TAKE.template.ply`` and ``TAKE.gt.npz``.

    Parameters
    ----------
    take : SimulatedRGBDTake
    path : path
        The ``.h5`` file.
    drop_depth : iterable of int, optional
        Frames stored without depth (an all-zero depth image, as a camera that lost its stereo).
    overwrite : bool

    Returns
    -------
    Path
        The take file.
    """
    import trimesh

    from stage.frame import Frame
    from stage.store import CameraSpec, TakeWriter

    if not isinstance(take, SimulatedRGBDTake):
        raise ValueError(f"take must be a SimulatedRGBDTake, got {type(take).__name__}")
    path = Path(path)
    cam = take.calibration[0]
    w, h = cam.size
    drop = {int(i) for i in drop_depth}
    period = int(round(1e9 / take.fps))
    with TakeWriter(path, [CameraSpec(cam.name, w, h, depth=True)], calibration=take.calibration,
                    fps=take.fps, overwrite=overwrite) as wr:
        for k in range(take.n_frames):
            d = np.zeros_like(take.depth[k]) if k in drop else take.depth[k]
            wr.write_set({cam.name: Frame(take.images[k], cam.name, k, k * period, k * period, depth=d)}, time_ns=k * period)
    trimesh.Trimesh(take.template_vertices, take.template_faces, process=False).export(template_path(path))
    np.savez_compressed(
        path.with_name(path.stem + ".gt.npz"),
        truth=take.truth, vertex_segment=take.vertex_segment, angles=take.angles,
        joint_positions=take.joint_positions, length=np.asarray(take.size),
        template_vertices=take.template_vertices, template_faces=take.template_faces,
        params=np.asarray(json.dumps(take.params)),
    )
    return path


def template_path(take_path: str | os.PathLike) -> Path:
    """``TAKE.template.ply`` beside ``TAKE.h5``."""
    p = Path(take_path)
    return p.with_name(p.stem + ".template.ply")


def load_rgbd_ground_truth(take_path: str | os.PathLike) -> dict:
    """Read ``TAKE.gt.npz`` written by :func:`record_rgbd_take` (``truth (F, V, 3)``, ``length``, ...)."""
    p = Path(take_path)
    p = p if p.suffix == ".npz" else p.with_name(p.stem + ".gt.npz")
    if not p.is_file():
        raise FileNotFoundError(f"{p}: ground truth file not found")
    with np.load(p, allow_pickle=False) as z:
        out = {k: z[k] for k in z.files if k != "params"}
        out["params"] = json.loads(str(z["params"]))
    out["length"] = float(out["length"])
    return out
