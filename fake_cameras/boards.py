"""Calibration boards waved through the volume, rendered through the true cameras.

The board's printable image comes from :mod:`calib.boards` (a chessboard drawn
from its definition, a ChArUco board from OpenCV's
``cv2.aruco.CharucoBoard.generateImage``). Every pixel's ray (the distorted
camera model, as for the creatures) is intersected with the board plane and the
board texture is looked up bilinearly (``cv2.remap``) from a pre-filtered
pyramid level that matches the pixel's footprint (anti-aliasing), then shaded,
composited over the green studio, blurred slightly and given sensor noise.
OpenCV's detectors work on the result; the true corners are returned with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from calib.boards import Charuco, Chessboard
from calib.calibration import Calibration
from fake_cameras.render import Backdrop, _scene, sensor_noise
from stage.rig import Volume

__all__ = ["BoardViews", "board_poses", "render_board_views", "render_board"]


@dataclass(frozen=True, eq=False)
class BoardViews:
    """Rendered board views with their ground truth.

    Parameters
    ----------
    board : calib.boards.Chessboard or calib.boards.Charuco
    calibration : calib.Calibration
        The true cameras.
    images : (V, C, H, W, 3) uint8 ndarray
        View ``v`` (one board pose) seen by camera ``c``.
    poses : (V, 4, 4) float ndarray
        Board -> world transforms (board frame of :mod:`calib.boards`: corners
        in ``z = 0``, ``z`` pointing into the printed face).
    object_points : (N, 3) float ndarray
        Corners in the board frame (mm); ChArUco row ``k`` is corner id ``k``.
    corners_3d : (V, N, 3) float ndarray
        Corners in the world.
    corners_2d : (V, C, N, 2) float ndarray
        True projections of the corners (with distortion).
    visible : (V, C, N) bool ndarray
        The camera sees the printed face and the corner lies inside the image
        (3 px margin).
    """

    board: Chessboard | Charuco
    calibration: Calibration
    images: np.ndarray
    poses: np.ndarray
    object_points: np.ndarray
    corners_3d: np.ndarray
    corners_2d: np.ndarray
    visible: np.ndarray


def _check_board(board) -> None:
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a calib.boards.Chessboard or Charuco, got {type(board).__name__}")


def board_poses(
    board: Chessboard | Charuco,
    calibration: Calibration,
    n_views: int,
    *,
    seed: int = 0,
    volume: Volume | None = None,
    max_tilt_deg: float = 35.0,
    spread: float = 0.5,
    close_fraction: float = 1 / 3,
) -> np.ndarray:
    """Random board -> world poses in the volume, facing the cameras in turn.

    Parameters
    ----------
    board : calib.boards.Chessboard or Charuco
    calibration : calib.Calibration
    n_views : int
    seed : int, optional
    volume : stage.rig.Volume, optional
    max_tilt_deg : float, optional
        Largest angle between the board's face normal and the direction to its camera.
    spread : float, optional
        Fraction of the volume over which the board centre wanders (the
        centre stays inside the volume, the whole board above the floor; like
        an operator's, the board may reach out of the volume at its edges).
        A board as large as the volume therefore still moves through it, and
        its corners reach beyond the centre of the images, which the
        intrinsics (focal length versus lens distortion) need.
    close_fraction : float, optional
        Fraction of the rounds of the rig in which the board is held up close to each
        camera in turn (default: every third round, from the third on), as an
        operator does to cover the edges and corners of each image: the board fills
        about half of that camera's width, pushed towards a random image corner
        (other cameras may not see it at all).

    Returns
    -------
    (V, 4, 4) float ndarray
    """
    _check_board(board)
    vol = Volume() if volume is None else volume
    rng = np.random.default_rng(seed)
    centers = calibration.centers()
    c = np.asarray(vol.center, dtype=np.float64)
    half = np.asarray(vol.size, dtype=np.float64) / 2
    x0, y0, x1, y1 = board.outline_mm
    mid = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    outline = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    floor_clear = board.square_mm  # lowest board point above z = 0
    out = np.empty((int(n_views), 4, 4))
    first = int(rng.integers(len(centers)))
    if not 0.0 <= float(close_fraction) <= 1.0:
        raise ValueError(f"close_fraction must be within [0, 1], got {close_fraction!r}")
    width = max(x1 - x0, y1 - y0)
    for v in range(int(n_views)):
        ci = (first + v) % len(centers)  # the operator walks the board round the rig
        cam = centers[ci]
        p = c + rng.uniform(-1, 1, 3) * half * spread
        rnd = v // len(centers)  # every camera gets its close-ups in turn, not by chance
        if math.floor((rnd + 1) * close_fraction + 1e-9) > math.floor(rnd * close_fraction + 1e-9):
            cm = calibration.cameras[ci]
            (fx, _, cx), (_, fy, cy) = cm.K[0], cm.K[1]
            w_img, h_img = cm.size
            d = fx * width / (0.5 * w_img)
            u = cx + rng.choice([-1, 1]) * rng.uniform(0.08, 0.2) * w_img
            vv = cy + rng.choice([-1, 1]) * rng.uniform(0.08, 0.2) * h_img
            ray = cm.R.T @ np.array([(u - cx) / fx, (vv - cy) / fy, 1.0])
            p = cam + d * ray / np.linalg.norm(ray)
        toward = (cam - p) / np.linalg.norm(cam - p)
        tilt = math.radians(rng.uniform(0, max_tilt_deg))
        k = np.cross(toward, rng.normal(size=3))
        k /= np.linalg.norm(k)
        n = toward * math.cos(tilt) + np.cross(k, toward) * math.sin(tilt) + k * (k @ toward) * (1 - math.cos(tilt))
        z = -n  # board z points into the face, away from the viewer
        up = np.array([0.0, 0.0, 1.0])
        x = np.cross(up, z) if abs(z @ up) < 0.95 else np.array([1.0, 0.0, 0.0])
        x -= z * (x @ z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        a = math.radians(rng.uniform(-30, 30))
        x, y = math.cos(a) * x + math.sin(a) * y, -math.sin(a) * x + math.cos(a) * y
        R = np.stack([x, y, z], axis=1)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = p - R @ mid
        low = float((outline @ R.T + T[:3, 3])[:, 2].min())
        if low < floor_clear:  # lift the board off the floor
            T[2, 3] += floor_clear - low
        out[v] = T
    return out


def floor_pose(origin: tuple[float, float, float] = (0.0, 0.0, 0.5)) -> np.ndarray:
    """Board -> world pose of a board lying face up on the floor, its origin at ``origin``.

    This is how a lab fixes the world frame: the board's x axis along world x, the
    printed face up. Calibrating with this view as the world frame
    (``calib.extrinsics.calibrate_extrinsics(world="board", world_frame=...)``, which
    turns the board frame 180 degrees about x) gives back the simulator's world frame
    (up to the 0.5 mm the board floats above the floor so it does not z-fight).

    Returns
    -------
    (4, 4) float ndarray
    """
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # board z points into the face, i.e. down
    T[:3, 3] = np.asarray(origin, dtype=np.float64)
    return T


_SUPERSAMPLE = 3


class _Texture:
    """The board image and a pyramid of pre-filtered copies (float32, 0..1 reflectance)."""

    def __init__(self, board, px_per_mm: float):
        self.px_per_mm = px_per_mm
        img = board.image(px_per_mm=px_per_mm).astype(np.float32) / 255.0
        self.A = board.image_transform(px_per_mm=px_per_mm)
        self.size = (img.shape[1], img.shape[0])
        refl = 0.05 + 0.85 * img  # paper is not perfectly white, ink not perfectly black
        self.levels = [(0.0, refl)]
        for k in range(1, 6):
            s = 0.5 * 2.0 ** (k - 1)
            self.levels.append((s, cv2.GaussianBlur(refl, (0, 0), s)))

    def level(self, texels_per_pixel: float) -> np.ndarray:
        want = 0.45 * texels_per_pixel
        return min(self.levels, key=lambda lv: abs(lv[0] - want))[1]


def render_board(
    camera,
    pose: np.ndarray,
    board: Chessboard | Charuco,
    *,
    backdrop: Backdrop | None = None,
    rng: np.random.Generator | None = None,
    noise_sigma: float = 2.0,
    px_per_mm: float = 4.0,
    _texture: _Texture | None = None,
) -> np.ndarray:
    """Render one board pose through one camera in the green studio.

    Parameters
    ----------
    camera : calib.Camera
    pose : (4, 4) float ndarray
        Board -> world.
    board : calib.boards.Chessboard or Charuco
    backdrop : fake_cameras.render.Backdrop, optional
    rng : numpy.random.Generator, optional
    noise_sigma : float, optional
    px_per_mm : float, optional
        Resolution of the board texture.

    Returns
    -------
    (H, W, 3) uint8 ndarray
    """
    _check_board(board)
    bd = Backdrop() if backdrop is None else backdrop
    if not (noise_sigma >= 0):
        raise ValueError(f"noise_sigma must be >= 0, got {noise_sigma!r}")
    T = np.asarray(pose, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"pose must be a (4, 4) board -> world transform, got shape {T.shape}")
    if _texture is None:
        px_per_mm = max(round(board.square_mm * float(px_per_mm)), 8) / board.square_mm
        tex = _Texture(board, px_per_mm)
    else:
        tex = _texture
    rng = np.random.default_rng() if rng is None else rng
    sc = _scene(camera, bd)
    h, w = sc.h, sc.w
    img = sc.background.copy()
    R, tb = T[:3, :3], T[:3, 3]
    nrm = R[:, 2]
    o = sc.origin
    if (o - tb) @ nrm < 0:  # the camera is in front of the printed face
        # the board plate's outline in the image (with a margin for distortion)
        tw, th = tex.size
        Ainv = np.linalg.inv(tex.A)
        corners_uv = np.array([[-0.5, -0.5, 1], [tw - 0.5, -0.5, 1], [tw - 0.5, th - 0.5, 1], [-0.5, th - 0.5, 1]])
        loc = (Ainv @ corners_uv.T).T[:, :2]
        world = np.c_[loc, np.zeros(4)] @ R.T + tb
        pix, z = camera.project(world, return_depth=True)
        if np.all(z > 0):
            m = 0.06 * max(w, h) + 2
            u0, v0 = np.floor(pix.min(0) - m).astype(int)
            u1, v1 = np.ceil(pix.max(0) + m).astype(int)
            u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w - 1), min(v1, h - 1)
            if u1 > u0 and v1 > v0:
                D = sc.dirs.reshape(h, w, 3)[v0 : v1 + 1, u0 : u1 + 1]
                denom = D @ nrm
                t = ((tb - o) @ nrm) / np.where(np.abs(denom) > 1e-12, denom, 1e-12)
                X = o + t[..., None] * D
                L = (X - tb) @ R  # board-frame coordinates
                uv = L[..., :2] @ tex.A[:2, :2].T + tex.A[:2, 2]
                uv[t <= 0] = -1e6
                ss = _SUPERSAMPLE
                # 3x3 samples per pixel: the board-plane mapping is smooth, so the
                # sub-pixel texture coordinates are interpolated from the pixel centres
                uvs = cv2.resize(uv.astype(np.float32), None, fx=ss, fy=ss, interpolation=cv2.INTER_LINEAR)
                inside = (
                    (uvs[..., 0] >= -0.5) & (uvs[..., 0] <= tw - 0.5) & (uvs[..., 1] >= -0.5) & (uvs[..., 1] <= th - 0.5)
                )
                if inside.any():
                    # texels per image pixel at the board (footprint)
                    dist = float(np.linalg.norm(tb + R @ np.r_[loc.mean(0), 0] - o))
                    cosang = abs(float(((tb - o) / np.linalg.norm(tb - o)) @ nrm))
                    foot = dist / camera.K[0, 0] / math.sqrt(max(cosang, 0.2))
                    level = tex.level(foot * tex.px_per_mm / ss)
                    refl = cv2.remap(level, uvs[..., 0], uvs[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                    refl *= inside
                    hh, ww = uv.shape[:2]
                    refl = cv2.resize(refl, (ww, hh), interpolation=cv2.INTER_AREA)
                    alpha = cv2.resize(inside.astype(np.float32), (ww, hh), interpolation=cv2.INTER_AREA)
                    front = -nrm
                    light = bd.ambient + bd.key_intensity * max(front @ sc.key, 0.0) + bd.fill_intensity * max(front @ sc.fill, 0.0)
                    val = (255.0 * min(light, 1.15) * refl) * sc.vignette[v0 : v1 + 1, u0 : u1 + 1]
                    region = img[v0 : v1 + 1, u0 : u1 + 1]
                    region *= (1.0 - alpha)[..., None]
                    region += val[..., None]
    if bd.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), bd.blur_sigma)
    return sensor_noise(img, float(noise_sigma), rng)


def render_board_views(
    board: Chessboard | Charuco,
    calibration: Calibration,
    n_views: int,
    *,
    seed: int = 0,
    noise_sigma: float = 2.0,
    volume: Volume | None = None,
    backdrop: Backdrop | None = None,
    poses: np.ndarray | None = None,
    max_tilt_deg: float = 35.0,
    px_per_mm: float | None = None,
) -> BoardViews:
    """Wave a board through the volume and film it with every camera.

    Parameters
    ----------
    board : calib.boards.Chessboard or Charuco
    calibration : calib.Calibration
        True cameras (e.g. :func:`fake_cameras.dome.make_dome`).
    n_views : int
        Number of board poses (1..1000).
    seed : int, optional
        Seeds the poses and the noise.
    noise_sigma : float, optional
        Sensor noise, grey levels.
    volume : stage.rig.Volume, optional
    backdrop : fake_cameras.render.Backdrop, optional
    poses : (V, 4, 4) float ndarray, optional
        Board -> world poses to use instead of random ones (``n_views`` must match).
    max_tilt_deg : float, optional
        See :func:`board_poses`.
    px_per_mm : float, optional
        Board texture resolution; default: about 4 texels per image pixel at
        the nearest camera.

    Returns
    -------
    BoardViews
    """
    _check_board(board)
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a calib.Calibration, got {type(calibration).__name__}")
    if isinstance(n_views, bool) or not isinstance(n_views, (int, np.integer)) or not 1 <= n_views <= 1000:
        raise ValueError(f"n_views must be an integer within 1..1000, got {n_views!r}")
    if not (isinstance(noise_sigma, (int, float)) and math.isfinite(noise_sigma) and noise_sigma >= 0):
        raise ValueError(f"noise_sigma must be a number >= 0, got {noise_sigma!r}")
    sizes = {c.size for c in calibration}
    if len(sizes) != 1:
        raise ValueError("calibration: all cameras must have the same image size")
    w, h = sizes.pop()
    vol = Volume() if volume is None else volume
    if poses is None:
        P = board_poses(board, calibration, int(n_views), seed=seed, volume=vol, max_tilt_deg=max_tilt_deg)
    else:
        P = np.asarray(poses, dtype=np.float64)
        if P.shape != (int(n_views), 4, 4):
            raise ValueError(f"poses must have shape ({n_views}, 4, 4), got {P.shape}")
    if backdrop is None:
        reach = np.linalg.norm(calibration.centers()[:, :2] - np.asarray(vol.center[:2]), axis=1).max()
        top = max(float(calibration.centers()[:, 2].max()), float(vol.bounds[1][2]))
        backdrop = Backdrop(
            wall_radius=float(max(3200.0, 1.6 * reach)),
            wall_height=float(max(3200.0, 1.5 * top)),
            center=(float(vol.center[0]), float(vol.center[1])),
        )
    if px_per_mm is None:
        d = np.linalg.norm(calibration.centers() - np.asarray(vol.center), axis=1).min()
        f = max(c.K[0, 0] for c in calibration)
        near = max(d - 0.5 * float(np.linalg.norm(vol.size)), 100.0)
        px_per_mm = float(np.clip(4.0 * f / near, 2.0, 12.0))
    # whole texels per square, so the generated pattern has no rounding offsets
    px_per_mm = max(round(board.square_mm * float(px_per_mm)), 8) / board.square_mm
    tex = _Texture(board, px_per_mm)
    obj = board.object_points()
    V, C, N = int(n_views), len(calibration), obj.shape[0]
    images = np.empty((V, C, h, w, 3), dtype=np.uint8)
    c3 = np.einsum("vij,nj->vni", P[:, :3, :3], obj) + P[:, None, :3, 3]
    c2 = np.empty((V, C, N, 2))
    vis = np.zeros((V, C, N), dtype=bool)
    for v in range(V):
        for ci, cam in enumerate(calibration):
            images[v, ci] = render_board(
                cam, P[v], board, backdrop=backdrop, rng=np.random.default_rng([seed, v, ci]),
                noise_sigma=noise_sigma, _texture=tex,
            )
            pix, z = cam.project(c3[v], return_depth=True)
            c2[v, ci] = pix
            facing = (cam.center - P[v, :3, 3]) @ P[v, :3, 2] < 0
            vis[v, ci] = facing & (z > 0) & cam.in_image(pix, margin=3.0)
    return BoardViews(
        board=board, calibration=calibration, images=images, poses=P, object_points=obj,
        corners_3d=c3, corners_2d=c2, visible=vis,
    )
