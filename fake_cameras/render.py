"""Ray-cast rendering of a creature in a green-screen studio.

Every pixel's ray comes from the distorted camera model
(:meth:`calib.camera.Camera.pixel_grid_rays`, cached per camera), so images,
masks and depth follow exactly the calibration the rest of the project uses.
The creature's tapered capsules are intersected analytically (ray / round-cone
intersection after I. Quilez), only for rays that pass the creature's
bounding sphere and, per capsule, the capsule's bounding sphere.

The studio: a green cylindrical wall around the volume and a green floor
(z = 0), unevenly lit (smooth gradients plus lens vignetting); the creature
casts a soft-edged shadow on the floor (a ray from each floor point to the key
light, tested against the creature), it is Lambert-shaded by a key and a fill
light with a faint procedural texture painted on its body, picks up green spill near its
silhouette, and the sensor adds Gaussian noise after a slight optical blur.

The ground-truth mask is exactly the set of pixels whose centre ray hits the
creature; ``label`` holds the limb label of the capsule hit (-1 body,
-2 background); depth is the camera-frame ``Z`` in millimetres of whatever the
ray hits first (creature, floor or wall).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, fields

import cv2
import numpy as np

from calib.camera import Camera
from calib.camera import cached_pixel_grid_rays as camera_rays
from fake_cameras.creatures import Pose, round_cone_sdf_pairs

__all__ = ["Backdrop", "View", "render_view", "intersect_round_cones", "BACKGROUND", "camera_rays"]

BACKGROUND = -2  # label of pixels that see no creature


@dataclass(frozen=True)
class Backdrop:
    """Studio and image-formation parameters (all colours BGR, 0..255).

    Parameters
    ----------
    wall_color, floor_color : (3,) float
        Green of the cylindrical wall and of the floor.
    ceiling_color : (3,) float
        What rays see above the wall (rare).
    wall_radius, wall_height : float
        Cylinder around ``center`` (mm); every camera must be inside it.
    center : (float, float)
        Axis of the wall cylinder (x, y).
    unevenness : float
        Depth of the smooth lighting gradients on wall and floor (0 = flat).
    vignette : float
        Brightness lost in the image corners (0 = none).
    creature_color : (3,) float
        Albedo of the creature (not green).
    texture : float
        Amplitude of the creature's procedural texture.
    texture_scale : float
        Its wavelengths, relative to the default (0.5: twice as fine).
    painted : bool
        The texture is painted on the body: evaluated at every point's rest position
        (:attr:`fake_cameras.creatures.Pose.rest`), so it moves with the part that carries it,
        as a real subject's skin does. False: a function of the world position (the texture
        stands still while the subject moves through it; what the simulator did before).
    key_light, fill_light : (3,) float
        Directions *towards* the lights (normalized internally).
    key_intensity, fill_intensity, ambient : float
    shadow_strength : float
        Fraction of floor light blocked in the creature's shadow.
    shadow_softness : float
        Width of the shadow's penumbra per millimetre of height of the
        occluding capsule above the floor (the light's angular size), mm/mm.
    spill : float
        Strength of the green spill at the silhouette edge (0 = none).
    spill_width : float
        Decay length (px) of the spill inwards from the edge.
    blur_sigma : float
        Optical blur (px) before the sensor noise; 0 = none.
    wall_texture, floor_texture : float
        Strength (0..1) of a pattern of coloured panels, posters and stripes on the wall, and
        of tiles and mats on the floor (a lab's walls and floor rather than a backdrop's
        uniform colour); 0 = the uniform colour.
    lights : int
        Bright lamps on the wall, above the cameras (saturating white blobs).
    figure : (float, float) or None
        A second person standing still at ``(x, y)`` (a column 360 mm wide and 1.55 m high
        with a head, 1.8 m in all), in front of the wall: part of the background, not of
        the masks. Put it outside the capture volume and beyond the cameras' ring so that it
        never hides the subject.
    figure_color : (3,) float
        Its albedo.
    """

    wall_color: tuple[float, float, float] = (45.0, 175.0, 55.0)
    floor_color: tuple[float, float, float] = (50.0, 160.0, 45.0)
    ceiling_color: tuple[float, float, float] = (90.0, 95.0, 90.0)
    wall_radius: float = 3200.0
    wall_height: float = 3200.0
    center: tuple[float, float] = (0.0, 0.0)
    unevenness: float = 0.25
    vignette: float = 0.25
    creature_color: tuple[float, float, float] = (70.0, 125.0, 205.0)
    texture: float = 0.08
    texture_scale: float = 1.0
    painted: bool = True
    key_light: tuple[float, float, float] = (0.25, -0.18, 1.0)
    fill_light: tuple[float, float, float] = (-0.6, 0.5, 0.4)
    key_intensity: float = 0.75
    fill_intensity: float = 0.3
    ambient: float = 0.25
    shadow_strength: float = 0.5
    shadow_softness: float = 0.03
    spill: float = 0.35
    spill_width: float = 3.0
    blur_sigma: float = 0.5
    wall_texture: float = 0.0
    floor_texture: float = 0.0
    lights: int = 0
    figure: tuple[float, float] | None = None
    figure_color: tuple[float, float, float] = (60.0, 70.0, 140.0)

    def __repr__(self) -> str:
        """The fields' repr, leaving out the lab fields (``wall_texture`` onwards) at their defaults:
        the render cache keys on it, so renders of the green studio keep their cache entries."""
        lab = ("wall_texture", "floor_texture", "lights", "figure", "figure_color")
        parts = []
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in lab and v == f.default:
                continue
            parts.append(f"{f.name}={v!r}")
        return f"Backdrop({', '.join(parts)})"

    def __post_init__(self) -> None:
        for name in ("wall_radius", "wall_height", "texture_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"backdrop.{name} must be positive")
        for name in (
            "unevenness",
            "vignette",
            "texture",
            "shadow_strength",
            "spill",
            "spill_width",
            "blur_sigma",
            "shadow_softness",
            "ambient",
            "key_intensity",
            "fill_intensity",
        ):
            if not getattr(self, name) >= 0:
                raise ValueError(f"backdrop.{name} must be >= 0")
        for name in ("vignette", "shadow_strength", "unevenness", "wall_texture", "floor_texture"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"backdrop.{name} must be within 0..1")
        if isinstance(self.lights, bool) or not isinstance(self.lights, int) or not 0 <= self.lights <= 16:
            raise ValueError(f"backdrop.lights must be an integer within 0..16, got {self.lights!r}")


@dataclass(frozen=True, eq=False)
class View:
    """One rendered image with its ground truth.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray
        BGR image.
    mask : (H, W) bool ndarray
        Pixels whose centre ray hits the creature.
    depth : (H, W) uint16 ndarray or None
        Camera-frame Z (mm) of the first surface hit (creature, floor or wall).
    label : (H, W) int16 ndarray
        Limb label of the capsule hit (-1 body), -2 (``BACKGROUND``) elsewhere.
    """

    image: np.ndarray
    mask: np.ndarray
    depth: np.ndarray | None
    label: np.ndarray


# -- ray / round-cone intersection -------------------------------------------


def intersect_round_cones(
    origins: np.ndarray,
    dirs: np.ndarray,
    pa: np.ndarray,
    pb: np.ndarray,
    ra: np.ndarray,
    rb: np.ndarray,
    *,
    normals: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """First intersection of rays with round cones, pairwise.

    A round cone is the convex hull of two spheres; it is the union of both
    spheres and of the truncated cone tangent to them, so the first hit is the
    nearest of the two sphere entries and of the cone-quadric roots that lie
    on the tangent band (after I. Quilez, "Rounded cone - intersection").

    Parameters
    ----------
    origins : (P, 3) or (3,) float ndarray
    dirs : (P, 3) float ndarray
        Unit directions.
    pa, pb : (P, 3) float ndarray
        Sphere centres.
    ra, rb : (P,) float ndarray
        Sphere radii.
    normals : bool, optional
        Also return unit surface normals at the hits.

    Returns
    -------
    t : (P,) float ndarray
        Ray parameter of the first hit with ``t > 0``, ``inf`` where the ray misses.
    normal : (P, 3) float ndarray or None
    """
    d = dirs
    ba = pb - pa
    oa = origins - pa
    ob = origins - pb
    rr = ra - rb

    def dot(a, b):
        return np.einsum("ij,ij->i", a, b) if a.ndim == 2 and b.ndim == 2 else (a * b).sum(-1)

    m0 = dot(ba, ba)
    m1 = dot(ba, oa)
    m2 = dot(ba, d)
    m3 = dot(d, oa)
    m5 = dot(oa, oa)
    m6 = dot(ob, d)
    m7 = dot(ob, ob)
    inf = np.inf
    # spheres
    h1 = m3 * m3 - m5 + ra * ra
    h2 = m6 * m6 - m7 + rb * rb
    with np.errstate(invalid="ignore"):
        t1 = np.where(h1 >= 0, -m3 - np.sqrt(np.maximum(h1, 0)), inf)
        t2 = np.where(h2 >= 0, -m6 - np.sqrt(np.maximum(h2, 0)), inf)
    t1 = np.where(t1 > 0, t1, inf)
    t2 = np.where(t2 > 0, t2, inf)
    best = np.minimum(t1, t2)
    kind = np.where(t1 <= t2, 0, 1)
    # tangent band of the cone
    d2 = m0 - rr * rr
    ok = d2 > 1e-9 * np.maximum(m0, 1e-300)
    k2 = d2 - m2 * m2
    k1 = d2 * m3 - m1 * m2 + m2 * rr * ra
    k0 = d2 * m5 - m1 * m1 + 2.0 * m1 * rr * ra - m0 * ra * ra
    h = k1 * k1 - k0 * k2
    ok &= (h >= 0) & (np.abs(k2) > 1e-12 * np.maximum(d2, 1e-300))
    tl = np.full_like(best, inf)
    yl = np.zeros_like(best)
    if np.any(ok):
        sq = np.sqrt(np.where(ok, h, 0.0))
        k2s = np.where(ok, k2, 1.0)
        for sgn in (-1.0, 1.0):
            tc = (sgn * sq - k1) / k2s
            y = m1 - ra * rr + tc * m2
            valid = ok & (tc > 0) & (y > 0) & (y < d2)
            take = valid & (tc < tl)
            tl = np.where(take, tc, tl)
            yl = np.where(take, y, yl)
    use_l = tl < best
    best = np.where(use_l, tl, best)
    kind = np.where(use_l, 2, kind)
    if not normals:
        return best, None
    tt = np.where(np.isfinite(best), best, 0.0)[:, None]
    pa_hit = oa + tt * d
    n = np.where(
        (kind == 2)[:, None],
        d2[:, None] * pa_hit - ba * yl[:, None],
        np.where((kind == 0)[:, None], pa_hit, ob + tt * d),
    )
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.where(nn > 0, nn, 1.0)
    return best, n


# -- per-camera precomputation --------------------------------------------------


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


class _Scene:
    """Everything about one camera in the studio that does not change per frame."""

    def __init__(self, camera: Camera, bd: Backdrop):
        w, h = camera.size
        self.w, self.h = w, h
        origin, dirs = camera_rays(camera)
        self.origin = origin
        self.dirs = dirs.reshape(-1, 3)
        self.dz = self.dirs @ camera.R[2]
        cx, cy = bd.center
        o = origin
        if math.hypot(o[0] - cx, o[1] - cy) >= bd.wall_radius or not 0 < o[2] < bd.wall_height:
            raise ValueError(
                f"camera {camera.name!r} at {np.round(o, 1).tolist()} is outside the backdrop "
                f"(wall radius {bd.wall_radius}, height {bd.wall_height}); enlarge backdrop.wall_radius"
            )
        D = self.dirs
        # wall: |o_xy + t d_xy - c|^2 = R^2, the positive root (camera inside)
        oxy = np.array([o[0] - cx, o[1] - cy])
        a = D[:, 0] ** 2 + D[:, 1] ** 2
        b = 2 * (D[:, 0] * oxy[0] + D[:, 1] * oxy[1])
        c = oxy @ oxy - bd.wall_radius**2
        disc = np.sqrt(np.maximum(b * b - 4 * a * c, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            t_wall = np.where(a > 1e-12, (-b + disc) / (2 * np.where(a > 1e-12, a, 1.0)), np.inf)
            t_floor = np.where(D[:, 2] < -1e-12, -o[2] / np.where(D[:, 2] < -1e-12, D[:, 2], -1.0), np.inf)
            t_ceil = np.where(D[:, 2] > 1e-12, (bd.wall_height - o[2]) / np.where(D[:, 2] > 1e-12, D[:, 2], 1.0), np.inf)
        t_bg = np.minimum(np.minimum(t_wall, t_floor), t_ceil)
        P = o + t_bg[:, None] * D
        floor = (t_floor <= t_wall) & (t_floor <= t_ceil)
        ceil = (~floor) & (t_ceil < t_wall)
        wall = ~floor & ~ceil
        un = bd.unevenness
        az = np.arctan2(P[:, 1] - cy, P[:, 0] - cx)
        rr = np.hypot(P[:, 0] - cx, P[:, 1] - cy) / bd.wall_radius
        zz = np.clip(P[:, 2] / bd.wall_height, 0, 1)
        light_wall = 1.0 + un * (0.6 * np.cos(az - 0.8) + 0.25 * np.sin(2 * az + 0.3) - 0.8 * (zz - 0.3))
        light_floor = 1.0 + un * (0.5 - 1.4 * rr * rr + 0.3 * np.cos(az + 1.7) * rr)
        col = np.empty((D.shape[0], 3), dtype=np.float32)
        col[:] = np.asarray(bd.ceiling_color, dtype=np.float32)
        col[wall] = (_wall_colour(bd, az[wall], zz[wall]) * light_wall[wall, None]).astype(np.float32)
        col[floor] = (_floor_colour(bd, P[floor]) * light_floor[floor, None]).astype(np.float32)
        if bd.lights:
            col[wall] = np.maximum(col[wall], _lamps(bd, az[wall], zz[wall])[:, None])
        if bd.figure is not None:
            t_fig, fig_col = _figure_hits(bd, o, D)
            front = t_fig < t_bg
            col[front] = fig_col[front]
            t_bg = np.where(front, t_fig, t_bg)
            floor &= ~front
        self.background = col.reshape(h, w, 3)
        self.bg_depth = (t_bg * self.dz).astype(np.float32).reshape(h, w)
        self.floor_idx = np.flatnonzero(floor)
        self.floor_pts = P[self.floor_idx]
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        r2 = ((uu - (w - 1) / 2) ** 2 + (vv - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
        self.vignette = (1.0 - bd.vignette * r2).astype(np.float32)
        self.background *= self.vignette[:, :, None]
        self.key = _unit(bd.key_light)
        self.fill = _unit(bd.fill_light)
        self._tile_rays(w, h)
        self._floor_in_light_space(w, h)

    def _tile_rays(self, w: int, h: int) -> None:
        """Image tiles: pixel indices (padded by repetition), centre ray and angular radius."""
        ts = _TILE
        ty, tx = -(-h // ts), -(-w // ts)
        grid = np.pad(np.arange(h * w).reshape(h, w), ((0, ty * ts - h), (0, tx * ts - w)), mode="edge")
        self.tile_pix = np.ascontiguousarray(grid.reshape(ty, ts, tx, ts).transpose(0, 2, 1, 3).reshape(ty * tx, ts * ts))
        td = self.dirs[self.tile_pix]  # (T, ts*ts, 3)
        tc = td.sum(1)
        tc /= np.linalg.norm(tc, axis=1, keepdims=True)
        self.tile_dir = tc
        self.tile_ang = np.arccos(np.clip(np.einsum("tpk,tk->tp", td, tc).min(1), -1.0, 1.0)) + 1e-6

    def _floor_in_light_space(self, w: int, h: int) -> None:
        """The floor in light space (orthographic along the key light), per pixel and per tile."""
        e1 = np.cross(self.key, [0.0, 0.0, 1.0] if abs(self.key[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(self.key, e1)
        self.light_basis = np.stack([e1, e2], axis=1)  # (3, 2)
        self.is_floor = np.zeros(h * w, dtype=bool)
        self.is_floor[self.floor_idx] = True
        uv = np.full((h * w, 2), np.nan)
        uv[self.floor_idx] = self.floor_pts @ self.light_basis
        self.floor_uv = uv
        tuv = uv[self.tile_pix]  # (T, ts*ts, 2)
        with np.errstate(invalid="ignore"):
            has = self.is_floor[self.tile_pix].any(1)
            lo = np.where(has[:, None], np.nanmin(np.where(np.isnan(tuv), np.inf, tuv), axis=1), np.inf)
            hi = np.where(has[:, None], np.nanmax(np.where(np.isnan(tuv), -np.inf, tuv), axis=1), -np.inf)
        self.tile_uv_lo, self.tile_uv_hi = lo, hi


_PALETTE = np.array([[60, 70, 90], [150, 160, 170], [200, 200, 205], [120, 60, 50],
                     [90, 120, 110], [30, 30, 35], [170, 120, 80]], dtype=np.float64)  # BGR: a lab's colours


def _wall_colour(bd: Backdrop, az: np.ndarray, zz: np.ndarray) -> np.ndarray:
    """(K, 3) wall albedo: the wall colour, mixed by ``wall_texture`` with panels and stripes."""
    base = np.broadcast_to(np.asarray(bd.wall_color, float), (az.size, 3))
    if bd.wall_texture <= 0:
        return base
    panel = (np.floor((az + np.pi) / (2 * np.pi) * 23).astype(int) * 7 + np.floor(zz * 5).astype(int) * 3) % len(_PALETTE)
    stripe = 0.15 * np.sin(az * 160.0) * (zz > 0.55)
    tex = _PALETTE[panel] * (1.0 + stripe[:, None])
    return (1 - bd.wall_texture) * base + bd.wall_texture * tex


def _floor_colour(bd: Backdrop, pts: np.ndarray) -> np.ndarray:
    """(K, 3) floor albedo: the floor colour, mixed by ``floor_texture`` with tiles and mats."""
    base = np.broadcast_to(np.asarray(bd.floor_color, float), (pts.shape[0], 3))
    if bd.floor_texture <= 0:
        return base
    i = np.floor((pts[:, 0] - bd.center[0]) / 450.0).astype(int)
    j = np.floor((pts[:, 1] - bd.center[1]) / 450.0).astype(int)
    tile = _PALETTE[(3 * i + 5 * j) % len(_PALETTE)] * (0.85 + 0.15 * ((i + j) % 2))[:, None]
    return (1 - bd.floor_texture) * base + bd.floor_texture * tile


def _lamps(bd: Backdrop, az: np.ndarray, zz: np.ndarray) -> np.ndarray:
    """(K,) brightness of ``lights`` lamps high on the wall (saturating, 255 at their centres)."""
    out = np.zeros(az.shape, float)
    for k in range(bd.lights):
        a0 = 2 * np.pi * k / bd.lights + 0.4
        da = np.angle(np.exp(1j * (az - a0)))
        out = np.maximum(out, 400.0 * np.exp(-0.5 * ((da / 0.05) ** 2 + ((zz - 0.8) / 0.04) ** 2)))
    return np.minimum(out, 255.0)


def _figure_hits(bd: Backdrop, o: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters (inf: missed) and colours of the still figure: a vertical column and a head."""
    fx, fy = bd.figure  # type: ignore[misc]
    r, top, head_r = 180.0, 1550.0, 120.0
    oxy = np.array([o[0] - fx, o[1] - fy])
    a = D[:, 0] ** 2 + D[:, 1] ** 2
    b = 2 * (D[:, 0] * oxy[0] + D[:, 1] * oxy[1])
    c = oxy @ oxy - r * r
    disc = b * b - 4 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        t_col = np.where((disc >= 0) & (a > 1e-12), (-b - np.sqrt(np.maximum(disc, 0))) / (2 * np.where(a > 1e-12, a, 1)), np.inf)
    z_col = o[2] + t_col * D[:, 2]
    t_col = np.where((t_col > 0) & (z_col >= 0) & (z_col <= top), t_col, np.inf)
    oc = o - np.array([fx, fy, top + head_r])
    bh = D @ oc
    ch = oc @ oc - head_r**2
    dh = bh * bh - ch
    t_head = np.where(dh >= 0, -bh - np.sqrt(np.maximum(dh, 0)), np.inf)
    t_head = np.where(t_head > 0, t_head, np.inf)
    t = np.minimum(t_col, t_head)
    P = o + np.where(np.isfinite(t), t, 0)[:, None] * D
    n = np.zeros_like(P)
    n[:, 0], n[:, 1] = P[:, 0] - fx, P[:, 1] - fy
    head = t_head < t_col
    n[head] = P[head] - np.array([fx, fy, top + head_r])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    shade = bd.ambient + bd.key_intensity * np.maximum(n @ _unit(bd.key_light), 0.0)
    col = np.asarray(bd.figure_color, float)[None, :] * shade[:, None]
    col[head] = np.array([90.0, 120.0, 190.0]) * shade[head, None]  # skin
    return t, col.astype(np.float32)


_TILE = 16
_SCENE_CACHE: OrderedDict = OrderedDict()
_CACHE_LOCK = threading.Lock()
_CACHE_SIZE = 32


def _scene(camera: Camera, bd: Backdrop) -> _Scene:
    key = (camera, bd)
    with _CACHE_LOCK:
        hit = _SCENE_CACHE.get(key)
        if hit is not None:
            _SCENE_CACHE.move_to_end(key)
            return hit
    sc = _Scene(camera, bd)
    with _CACHE_LOCK:
        _SCENE_CACHE[key] = sc
        while len(_SCENE_CACHE) > _CACHE_SIZE:
            _SCENE_CACHE.popitem(last=False)
    return sc


def _bbox(flat_idx: np.ndarray, w: int, h: int, pad: int) -> tuple[slice, slice]:
    rows = flat_idx // w
    cols = flat_idx % w
    return (
        slice(max(int(rows.min()) - pad, 0), min(int(rows.max()) + pad + 1, h)),
        slice(max(int(cols.min()) - pad, 0), min(int(cols.max()) + pad + 1, w)),
    )


# -- the renderer -----------------------------------------------------------------


def studio_options(backdrop, noise_sigma) -> tuple[Backdrop, float]:
    """The checked studio of a render (None: the default :class:`Backdrop`) and its sensor
    noise (a finite number >= 0); a ValueError naming the parameter otherwise."""
    bd = Backdrop() if backdrop is None else backdrop
    if not isinstance(bd, Backdrop):
        raise ValueError(f"backdrop must be a fake_cameras.render.Backdrop, got {type(bd).__name__}")
    try:
        sigma = float(noise_sigma)
    except (TypeError, ValueError):
        raise ValueError(f"noise_sigma must be a number, got {noise_sigma!r}") from None
    if not (sigma >= 0 and math.isfinite(sigma)):
        raise ValueError(f"noise_sigma must be >= 0, got {noise_sigma!r}")
    return bd, sigma


def render_view(
    camera: Camera,
    pose: Pose | None,
    *,
    backdrop: Backdrop | None = None,
    rng: np.random.Generator | None = None,
    depth: bool = False,
    noise_sigma: float = 2.0,
) -> View:
    """Render what ``camera`` sees of ``pose`` in the green studio.

    Parameters
    ----------
    camera : calib.Camera
        True camera (its distortion is rendered).
    pose : fake_cameras.creatures.Pose or None
        The creature; None renders the empty studio (a background plate).
    backdrop : Backdrop, optional
        Studio and image-formation parameters (default ``Backdrop()``).
    rng : numpy.random.Generator, optional
        Source of the sensor noise; None draws fresh (non-reproducible) noise.
    depth : bool, optional
        Also return the depth image.
    noise_sigma : float, optional
        Standard deviation of the Gaussian sensor noise, grey levels.

    Returns
    -------
    View
        ``image (H, W, 3) uint8``, ``mask (H, W) bool``, ``depth (H, W) uint16`` or None,
        ``label (H, W) int16``.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a calib.Camera, got {type(camera).__name__}")
    if pose is not None and not isinstance(pose, Pose):
        raise ValueError(f"pose must be a fake_cameras.creatures.Pose or None, got {type(pose).__name__}")
    bd, sigma = studio_options(backdrop, noise_sigma)
    if rng is None:
        rng = np.random.default_rng()
    sc = _scene(camera, bd)
    img = sc.background.copy()
    hits = None
    if pose is not None:
        _shadow(sc, pose, bd, img)
        ray, cap, th, n = _cast_tiles(sc, pose)
        pts = sc.origin + th[:, None] * sc.dirs[ray]
        body = pose.rest is not None and bd.painted
        tex = _texture(_rest_points(pose.rest[cap], pts) if body else pts, bd)
        hits = Hits(ray=ray, t=th, normals=n, texture=tex, label=pose.limb[cap].astype(np.int16))
    return compose_view(sc, bd, img, hits, depth=depth, sigma=sigma, rng=rng)


@dataclass(frozen=True)
class Hits:
    """What a renderer found along the pixel rays of one camera: the first surface hit of each.

    ``ray (K,)`` flat pixel indices, ``t (K,)`` distances along the unit rays (mm), ``normals
    (K, 3)`` unit surface normals, ``texture (K,)`` the procedural texture's brightness factor
    (:func:`_texture`) and ``label (K,) int16`` the label of each hit.
    """

    ray: np.ndarray
    t: np.ndarray
    normals: np.ndarray
    texture: np.ndarray
    label: np.ndarray


def compose_view(sc: _Scene, bd: Backdrop, img: np.ndarray, hits: Hits | None, *, depth: bool, sigma: float,
                 rng: np.random.Generator) -> View:
    """The image formation every renderer shares, from its hits on the (shadowed) background ``img``.

    Lambert shading by the key and fill lights times the texture, the subject's colour and the
    vignetting; mask, label (:data:`BACKGROUND` elsewhere) and depth (camera-frame Z, rounded to
    uint16 mm) of the hits; green spill, optical blur and sensor noise. ``img`` (H, W, 3) float32
    is written to. :func:`render_view` (capsules) and :mod:`fake_cameras.mesh_render` (meshes)
    differ only in how they find the hits.
    """
    h, w = sc.h, sc.w
    mask = np.zeros((h, w), dtype=bool)
    label = np.full((h, w), BACKGROUND, dtype=np.int16)
    depth_img = sc.bg_depth.copy() if depth else None
    if hits is not None and hits.ray.size:
        ray, n = hits.ray, hits.normals
        shade = (
            bd.ambient
            + bd.key_intensity * np.maximum(n @ sc.key, 0.0)
            + bd.fill_intensity * np.maximum(n @ sc.fill, 0.0)
        )
        rows, cols = np.divmod(ray, w)
        col = np.asarray(bd.creature_color)[None, :] * (shade * hits.texture * sc.vignette[rows, cols])[:, None]
        img[rows, cols] = col.astype(np.float32)
        mask[rows, cols] = True
        label[rows, cols] = hits.label
        if depth_img is not None:
            depth_img[rows, cols] = (hits.t * sc.dz[ray]).astype(np.float32)
        if bd.spill > 0:
            _spill(img, mask, ray, w, h, bd)
    if bd.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), bd.blur_sigma)
    image = sensor_noise(img, sigma, rng)
    dimg = None
    if depth_img is not None:
        dimg = np.clip(np.round(depth_img), 0, 65535).astype(np.uint16)
    return View(image=image, mask=mask, depth=dimg, label=label)


def _rest_points(rest: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """World points mapped back to their capsule's rest position: ``R^T (p - t)`` per point."""
    return np.einsum("kji,kj->ki", rest[:, :, :3], pts - rest[:, :, 3])


def _texture(p: np.ndarray, bd: Backdrop) -> np.ndarray:
    """Brightness factor of the creature's procedural texture at points ``p`` (K, 3), mm."""
    q = p / bd.texture_scale
    return 1.0 + bd.texture * (
        np.sin(q[:, 0] / 23.0) * np.sin(q[:, 1] / 19.0) * np.sin(q[:, 2] / 17.0)
        + 0.3 * np.sin((q[:, 0] + q[:, 1] + q[:, 2]) / 7.0)
    )


def sensor_noise(img: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Add Gaussian noise to a float32 BGR image and quantize it to uint8 (rounding, saturating).

    The noise comes from OpenCV's fast generator, seeded from ``rng`` (reproducible).
    ``img`` is modified in place.
    """
    if sigma > 0:
        noise = np.empty((img.shape[0], img.size // img.shape[0]), dtype=np.float32)
        cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
        cv2.randn(noise, 0.0, float(sigma))  # single channel: every value gets the same sigma
        img += noise.reshape(img.shape)
    np.maximum(img, 0.0, out=img)
    return cv2.convertScaleAbs(img)


def _cast_tiles(sc: _Scene, pose: Pose):
    """First hits of the camera's pixel rays with the pose.

    Returns ``(pixel (K,), capsule (K,), t (K,), normal (K, 3))`` for the pixels that hit.
    """
    cen = (pose.p0 + pose.p1) / 2.0
    rad = np.linalg.norm(pose.p1 - pose.p0, axis=1) / 2.0 + np.maximum(pose.r0, pose.r1) + 1e-6
    v = cen - sc.origin
    dist = np.linalg.norm(v, axis=1)
    cosang = (sc.tile_dir @ v.T) / dist[None, :]
    ang = np.arccos(np.clip(cosang, -1.0, 1.0))
    lim = sc.tile_ang[:, None] + np.arcsin(np.clip(rad / dist, 0.0, 1.0))[None, :]
    ti, ci = np.nonzero(ang <= lim)
    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3)))
    if ti.size == 0:
        return empty
    npix = sc.tile_pix.shape[1]
    ray = sc.tile_pix[ti].ravel()
    cap = np.repeat(ci, npix)
    D = sc.dirs[ray]
    proj = np.einsum("ij,ij->i", D, v[cap])
    keep = (dist[cap] ** 2 - proj * proj <= rad[cap] ** 2) & (proj > -rad[cap])
    ray, cap, D = ray[keep], cap[keep], D[keep]
    if ray.size == 0:
        return empty
    t, nrm = intersect_round_cones(sc.origin, D, pose.p0[cap], pose.p1[cap], pose.r0[cap], pose.r1[cap])
    hit = np.isfinite(t)
    ray, cap, t, nrm = ray[hit], cap[hit], t[hit], nrm[hit]
    if ray.size == 0:
        return empty
    tbuf = np.full(sc.h * sc.w, np.inf)
    np.minimum.at(tbuf, ray, t)
    win = t == tbuf[ray]
    ray, cap, t, nrm = ray[win], cap[win], t[win], nrm[win]
    # padded tiles and exact ties can repeat a pixel: keep one entry per pixel
    ray, first = np.unique(ray, return_index=True)
    return ray, cap[first], t[first], nrm[first]


def _shadow(sc: _Scene, pose: Pose, bd: Backdrop, img: np.ndarray) -> None:
    """Darken the floor where the key light is blocked by the creature.

    The key light is directional, so the shadow of a round cone on the floor
    is its orthographic projection along the light: the 2-D round cone of the
    projected end discs (same radii). Floor points are tested against it in
    light space; the penumbra widens with the occluder's height.
    """
    if bd.shadow_strength <= 0 or sc.floor_idx.size == 0:
        return
    E = sc.light_basis
    a2 = pose.p0 @ E
    b2 = pose.p1 @ E
    r0, r1 = pose.r0, pose.r1
    height = np.maximum((pose.p0[:, 2] + pose.p1[:, 2]) / 2.0, 0.0)
    pen = 1.0 + bd.shadow_softness * height  # penumbra half-width, mm
    lo = np.minimum(a2 - r0[:, None], b2 - r1[:, None]) - pen[:, None]
    hi = np.maximum(a2 + r0[:, None], b2 + r1[:, None]) + pen[:, None]
    ov = (
        (sc.tile_uv_lo[:, None, 0] <= hi[None, :, 0])
        & (sc.tile_uv_hi[:, None, 0] >= lo[None, :, 0])
        & (sc.tile_uv_lo[:, None, 1] <= hi[None, :, 1])
        & (sc.tile_uv_hi[:, None, 1] >= lo[None, :, 1])
    )
    ti, ci = np.nonzero(ov)
    if ti.size == 0:
        return
    npix = sc.tile_pix.shape[1]
    pix = sc.tile_pix[ti].ravel()
    cap = np.repeat(ci, npix)
    keep = sc.is_floor[pix]
    pix, cap = pix[keep], cap[keep]
    if pix.size == 0:
        return
    uv = sc.floor_uv[pix]
    inside = (uv >= lo[cap]).all(1) & (uv <= hi[cap]).all(1)
    pix, cap, uv = pix[inside], cap[inside], uv[inside]
    if pix.size == 0:
        return
    d = round_cone_sdf_pairs(uv, a2[cap], b2[cap], r0[cap], r1[cap])
    x = np.clip(0.5 - d / (2.0 * pen[cap]), 0.0, 1.0)
    sv = x * x * (3.0 - 2.0 * x)
    pos = sv > 0
    pix, sv = pix[pos], sv[pos]
    if pix.size == 0:
        return
    buf = np.zeros(sc.h * sc.w, dtype=np.float64)
    np.maximum.at(buf, pix, sv)
    upix = np.unique(pix)
    rows, cols = np.divmod(upix, sc.w)
    img[rows, cols] *= (1.0 - bd.shadow_strength * buf[upix]).astype(np.float32)[:, None]


def _spill(img: np.ndarray, mask: np.ndarray, hidx: np.ndarray, w: int, h: int, bd: Backdrop) -> None:
    pad = 2
    rs, cs = _bbox(hidx, w, h, pad)
    sub = mask[rs, cs].astype(np.uint8)
    # distance of creature pixels to the nearest background pixel (image border counts as inside)
    padded = cv2.copyMakeBorder(sub, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, 3)[1:-1, 1:-1]
    wgt = (bd.spill * np.exp(-(dist - 1.0) / max(bd.spill_width, 1e-6))).astype(np.float32)
    wgt[sub == 0] = 0.0
    region = img[rs, cs]
    g = region[:, :, 1]
    region[:, :, 0] *= 1.0 - 0.5 * wgt
    region[:, :, 2] *= 1.0 - 0.5 * wgt
    region[:, :, 1] = g * (1.0 - wgt) + wgt * np.maximum(g, 165.0)
