"""Simulated takes: a creature filmed by the dome, with ground truth.

:func:`simulate_take` renders ``frames`` time steps of a subject through every
camera of :func:`fake_cameras.dome.make_dome` and returns the images together
with everything the pipeline is scored against (true calibration, silhouette
masks, limb labels, tips and limb axes per frame, optional depth) and a
background plate per camera. Rendered takes are cached on disk
(``$CAPTURE_STAGE_CACHE/sim`` or ``~/.cache/capture-stage/sim``), keyed by every
parameter and the renderer version, so tests and the demo render once.

:func:`write_ground_truth` stores the ground truth beside a take file
(``TAKE.gt.npz``); :func:`load_ground_truth` reads it back.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calib.calibration import Calibration
from calib.fileio import replace_durably
from fake_cameras.creatures import CREATURES, Creature, Pose, make_creature
from fake_cameras.dome import MAX_CAMERAS, MIN_CAMERAS, make_dome
from fake_cameras.render import Backdrop, render_view
from stage.rig import Volume

__all__ = [
    "SUBJECTS",
    "SimulatedTake",
    "STAGES",
    "stage_backdrop",
    "simulate_take",
    "write_ground_truth",
    "load_ground_truth",
    "ground_truth_path",
    "cache_dir",
]

log = logging.getLogger(__name__)

SUBJECTS = (*CREATURES, "empty")
RENDER_VERSION = 2  # bump when rendering changes: invalidates cached takes


@dataclass(frozen=True, eq=False)
class SimulatedTake:
    """A rendered take and its ground truth.

    Parameters
    ----------
    subject : str
    calibration : calib.Calibration
        The true cameras.
    images : (F, C, H, W, 3) uint8 ndarray
        BGR images.
    masks : (F, C, H, W) bool ndarray
        Ground-truth silhouettes (pixel centre rays that hit the creature).
    labels : (F, C, H, W) int8 ndarray
        Limb label per pixel (index into ``limb_names``), -1 body, -2 background.
    depth : (F, C, H, W) uint16 ndarray or None
        Camera-frame Z in mm of the first surface hit.
    plate : (C, H, W, 3) uint8 ndarray
        The empty studio seen by each camera (one noisy shot, like a real plate).
    poses : list of Pose or None
        The creature per frame (None for the empty subject).
    tips : list of dict str -> (3,) ndarray
        Limb tips per frame.
    axes : list of dict str -> (K, 3) ndarray
        Limb axes (junction to tip) per frame.
    fps : float
    times : (F,) float ndarray
        Time of each frame, seconds.
    limb_names : tuple of str
    creature : Creature or None
    volume : stage.rig.Volume
    params : dict
        The parameters the take was made with.
    mesh_vertices : (F, V, 3) float ndarray or None
        A mesh subject's surface on every frame (same connectivity every frame, so a vertex is
        its own ground truth over time); None for the capsule creatures.
    mesh_faces : (T, 3) int ndarray or None
        Its triangles.
    """

    subject: str
    calibration: Calibration
    images: np.ndarray
    masks: np.ndarray
    labels: np.ndarray
    depth: np.ndarray | None
    plate: np.ndarray
    poses: list
    tips: list
    axes: list
    fps: float
    times: np.ndarray
    limb_names: tuple[str, ...]
    creature: Creature | None
    volume: Volume
    params: dict = field(default_factory=dict)
    mesh_vertices: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def n_cameras(self) -> int:
        return int(self.images.shape[1])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return int(self.images.shape[3]), int(self.images.shape[2])

    def select(self, frames) -> "SimulatedTake":
        """The take's frames in another order (e.g. a captured take's: frame set ``s`` shows
        scene frame ``frames[s]``), the ground truth with them.

        Parameters
        ----------
        frames : (S,) int array_like
            Scene frames, each in ``0..F-1``.
        """
        idx = np.asarray(frames)
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) or (idx.size and not (
                0 <= idx.min() and idx.max() < self.n_frames)):
            raise ValueError(f"frames must be a 1-d integer array within 0..{self.n_frames - 1}")
        pick = [int(i) for i in idx]
        return replace(
            self, images=self.images[idx], masks=self.masks[idx], labels=self.labels[idx],
            depth=None if self.depth is None else self.depth[idx],
            poses=[self.poses[i] for i in pick], tips=[self.tips[i] for i in pick],
            axes=[self.axes[i] for i in pick], times=np.asarray(self.times)[idx],
            mesh_vertices=None if self.mesh_vertices is None else np.asarray(self.mesh_vertices)[idx],
        )

    def tip_array(self) -> np.ndarray:
        """(F, L, 3) limb tips in ``limb_names`` order."""
        if not self.limb_names:
            return np.zeros((self.n_frames, 0, 3))
        return np.stack([np.stack([t[n] for n in self.limb_names]) for t in self.tips])


def cache_dir() -> Path:
    """Directory of cached simulated takes."""
    root = os.environ.get("CAPTURE_STAGE_CACHE")
    base = Path(root) if root else Path.home() / ".cache" / "capture-stage"
    return base / "sim"


def _check_size(size) -> tuple[int, int]:
    try:
        w, h = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be (width, height), got {size!r}") from None
    if w < 16 or h < 16 or w > 4096 or h > 4096:
        raise ValueError(f"size must be (width, height) within 16..4096 pixels, got {size!r}")
    return w, h


def _render_camera(args) -> dict:
    """Render every frame of one camera (runs in a worker process)."""
    cam, poses, backdrop, seed, ci, depth, noise, plate_noise = args
    w, h = cam.size
    F = len(poses)
    images = np.empty((F, h, w, 3), dtype=np.uint8)
    masks = np.empty((F, h, w), dtype=bool)
    labels = np.empty((F, h, w), dtype=np.int8)
    dep = np.empty((F, h, w), dtype=np.uint16) if depth else None
    for f, pose in enumerate(poses):
        v = render_view(cam, pose, backdrop=backdrop, rng=np.random.default_rng([seed, ci, f]), depth=depth, noise_sigma=noise)
        images[f] = v.image
        masks[f] = v.mask
        labels[f] = v.label
        if dep is not None:
            dep[f] = v.depth
    plate = render_plate(cam, backdrop, seed, ci, plate_noise)
    return {"images": images, "masks": masks, "labels": labels, "depth": dep, "plate": plate}


def render_plate(cam, backdrop: Backdrop, seed: int, ci: int, noise: float) -> np.ndarray:
    """(H, W, 3) uint8: the empty studio seen by camera ``ci`` (one noisy shot, like a real plate)."""
    return render_view(cam, None, backdrop=backdrop, rng=np.random.default_rng([seed, ci, 1 << 30]), noise_sigma=noise).image


def _default_workers(n_pixels: int) -> int:
    env = os.environ.get("CAPTURE_STAGE_SIM_WORKERS")
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            log.warning("ignoring CAPTURE_STAGE_SIM_WORKERS=%r (not an integer)", env)
    if n_pixels < 8_000_000:  # ~25 views of 640x480: not worth starting processes
        return 1
    return max(1, min(2, os.cpu_count() or 1))


def simulate_take(
    subject: str = "starfish",
    *,
    n_cameras: int = 12,
    frames: int = 30,
    fps: float = 30.0,
    size: tuple[int, int] = (640, 480),
    seed: int = 0,
    depth: bool = False,
    cache: bool = True,
    noise_sigma: float = 2.0,
    volume: Volume | None = None,
    backdrop: Backdrop | None = None,
    calibration: Calibration | None = None,
    scale: float = 1.0,
    tuck: tuple[float, float] | None = None,
    spur: tuple[float, float] | None = None,
    distortion: bool = True,
    workers: int | None = None,
    travel: tuple[float, float] | None = None,
    start: float = 0.0,
) -> SimulatedTake:
    """Render a take of a simulated subject with ground truth.

    Parameters
    ----------
    subject : {"starfish", "quadruped", "biped", "empty"}
    n_cameras : int, optional
        Cameras of the dome, 4..24 (ignored when ``calibration`` is given).
    frames : int, optional
        Number of frames (1..10000); frame ``f`` shows time ``start + f / fps``.
    fps : float, optional
    size : (int, int), optional
        Image (width, height) (ignored when ``calibration`` is given).
    seed : int, optional
        Seeds the dome, the creature's motion and the sensor noise.
    depth : bool, optional
        Also render depth images.
    cache : bool, optional
        Read/write the on-disk cache (:func:`cache_dir`).
    noise_sigma : float, optional
        Sensor noise, grey levels.
    volume : stage.rig.Volume, optional
        Capture volume; the creature stands at its centre.
    backdrop : fake_cameras.render.Backdrop, optional
    calibration : calib.Calibration, optional
        Film with these cameras instead of a dome.
    scale : float, optional
        Creature size factor (see :func:`fake_cameras.creatures.make_creature`).
    tuck, spur : (float, float), optional
        Hard-case time intervals (see :mod:`fake_cameras.creatures`).
    distortion : bool, optional
        Lens distortion of the dome cameras.
    workers : int, optional
        Rendering processes; default 1 for small takes, else up to 2
        (environment ``CAPTURE_STAGE_SIM_WORKERS`` overrides).
    travel : (float, float), optional
        The creature walks across the floor by ``(dx, dy)`` mm over the take, at constant
        speed, its path centred on the volume's centre (a subject that leaves every pixel
        for a while, as a plate from the take needs).
    start : float, optional
        Time of the first frame, seconds, >= 0: the take starts ``start`` seconds into the
        creature's motion, so its frame 0 shows the pose the default take (``start=0``) shows at
        time ``start``, and ``SimulatedTake.times`` are ``start + f / fps`` (the scores evaluate the
        creature at them). A time, not a phase: a creature's limbs and body move at different
        periods (the biped's limbs swing at 0.8 Hz, a quarter cycle is 0.3125 s; its body sways
        over 4 s). ``tuck`` and ``spur`` are times of the same clock; the texture stays painted on
        the body as at time 0. Default 0: the takes and their cache keys are those made without it.

    Returns
    -------
    SimulatedTake
    """
    if subject not in SUBJECTS:
        raise ValueError(f"subject must be one of {', '.join(SUBJECTS)}, got {subject!r}")
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or not 1 <= frames <= 10000:
        raise ValueError(f"frames must be an integer within 1..10000, got {frames!r}")
    fps_f = check_fps(fps)
    check_noise(noise_sigma)
    start = _check_start(start)
    vol, calib, backdrop = studio(
        volume=volume, n_cameras=n_cameras, size=size, seed=seed, distortion=distortion,
        calibration=calibration, backdrop=backdrop,
    )
    times = np.arange(int(frames), dtype=np.float64) / fps_f
    if start:
        times = start + times
    creature, poses = _creature_poses(subject, times, vol, scale=scale, seed=seed, tuck=tuck, spur=spur, travel=travel)
    limb_names = tuple(creature.names) if creature is not None else ()
    params = dict(
        subject=subject,
        frames=int(frames),
        fps=fps_f,
        seed=int(seed),
        depth=bool(depth),
        noise_sigma=float(noise_sigma),
        scale=float(scale),
        tuck=list(creature.tuck) if creature is not None and creature.tuck else None,
        spur=list(creature.spur) if creature is not None and creature.spur else None,
        volume={"center": list(vol.center), "size": list(vol.size)},
        **({"travel": [float(v) for v in travel]} if travel is not None else {}),
        **({"start": start} if start else {}),
    )
    key_src = json.dumps(
        {"v": RENDER_VERSION, "params": params, "calibration": calib.to_dict(), "backdrop": repr(backdrop),
         "poses": _poses_digest(poses)},
        sort_keys=True,
    )
    arrays = cached_render(
        key_src, lambda: _render_all(calib, poses, backdrop, int(seed), bool(depth), float(noise_sigma), workers),
        cache=cache,
    )
    return SimulatedTake(
        subject=subject,
        calibration=calib,
        images=arrays["images"],
        masks=arrays["masks"],
        labels=arrays["labels"],
        depth=arrays["depth"],
        plate=arrays["plate"],
        poses=poses,
        tips=[dict(p.tips) if p is not None else {} for p in poses],
        axes=[dict(p.axes) if p is not None else {} for p in poses],
        fps=fps_f,
        times=times,
        limb_names=limb_names,
        creature=creature,
        volume=vol,
        params=params,
    )


def _check_start(start) -> float:
    """``start`` as a float: a finite number of seconds >= 0."""
    if isinstance(start, bool) or not isinstance(start, (int, float, np.integer, np.floating)) or not (
            math.isfinite(start) and start >= 0):
        raise ValueError(f"start must be a finite number of seconds >= 0, got {start!r}")
    return float(start)


def _creature_poses(subject: str, times: np.ndarray, vol: Volume, *, scale, seed, tuck, spur, travel):
    """The creature standing at the volume's centre and its pose at every time (``travel``: walking
    across the floor, its path centred there); ``(None, [None, ...])`` for the empty stage."""
    if subject == "empty":
        return None, [None] * len(times)
    creature = make_creature(subject, scale=scale, seed=seed, tuck=tuck, spur=spur, origin=(vol.center[0], vol.center[1]))
    if travel is None:
        return creature, [creature.pose(t) for t in times]
    dx, dy = (float(v) for v in travel)
    u = np.linspace(-0.5, 0.5, len(times)) if len(times) > 1 else np.zeros(1)
    poses = [make_creature(subject, scale=scale, seed=seed, tuck=tuck, spur=spur,
                           origin=(vol.center[0] + a * dx, vol.center[1] + a * dy)).pose(t)
             for a, t in zip(u, times)]
    return creature, poses


# -- the studio and the cache, shared by every kind of simulated take ------------------

_ARRAYS = ("images", "masks", "labels", "depth", "plate")


def check_fps(fps) -> float:
    """``fps`` as a float within (0, 1000] (ValueError naming ``fps`` otherwise)."""
    try:
        fps_f = float(fps)
    except (TypeError, ValueError):
        raise ValueError(f"fps must be a number, got {fps!r}") from None
    if not (math.isfinite(fps_f) and 0 < fps_f <= 1000):
        raise ValueError(f"fps must be within (0, 1000], got {fps!r}")
    return fps_f


def check_noise(noise_sigma) -> float:
    """``noise_sigma`` as a float >= 0 (ValueError naming it otherwise)."""
    if isinstance(noise_sigma, bool) or not (isinstance(noise_sigma, (int, float)) and math.isfinite(noise_sigma)
                                             and noise_sigma >= 0):
        raise ValueError(f"noise_sigma must be a number >= 0, got {noise_sigma!r}")
    return float(noise_sigma)


def studio(
    *,
    volume: Volume | None,
    n_cameras: int,
    size,
    seed: int,
    distortion: bool,
    calibration: Calibration | None,
    backdrop: Backdrop | None,
) -> tuple[Volume, Calibration, Backdrop]:
    """The capture volume, the cameras (a dome unless ``calibration`` is given) and the studio.

    Validates the options of :func:`simulate_take` of the same names; the default backdrop's
    wall stands well behind every camera.
    """
    vol = Volume() if volume is None else volume
    if not isinstance(vol, Volume):
        raise ValueError(f"volume must be a stage.rig.Volume, got {type(vol).__name__}")
    if calibration is None:
        if isinstance(n_cameras, bool) or not isinstance(n_cameras, (int, np.integer)) or not MIN_CAMERAS <= n_cameras <= MAX_CAMERAS:
            raise ValueError(f"n_cameras must be an integer within {MIN_CAMERAS}..{MAX_CAMERAS}, got {n_cameras!r}")
        w, h = _check_size(size)
        calib = make_dome(int(n_cameras), size=(w, h), volume=vol, seed=seed, distortion=distortion)
    else:
        if not isinstance(calibration, Calibration):
            raise ValueError(f"calibration must be a calib.Calibration, got {type(calibration).__name__}")
        calib = calibration
    if backdrop is None:
        reach = max(np.linalg.norm(calib.centers()[:, :2] - np.asarray(vol.center[:2]), axis=1).max(), 1.0)
        top = max(float(calib.centers()[:, 2].max()), float(vol.bounds[1][2]))
        backdrop = Backdrop(
            wall_radius=float(max(3200.0, 1.6 * reach)),
            wall_height=float(max(3200.0, 1.5 * top)),
            center=(float(vol.center[0]), float(vol.center[1])),
        )
    elif not isinstance(backdrop, Backdrop):
        raise ValueError(f"backdrop must be a fake_cameras.render.Backdrop, got {type(backdrop).__name__}")
    return vol, calib, backdrop


#: Stages :func:`stage_backdrop` builds besides the full green backdrop.
STAGES = ("green", "floor", "none")


def stage_backdrop(kind: str, *, calibration: Calibration, volume: Volume) -> Backdrop:
    """The studio of a stage whose backdrop does not fill the view, with ground truth as usual.

    Parameters
    ----------
    kind : {"green", "floor", "none"}
        ``green``: the default full backdrop. ``floor``: only the floor is green; the wall is
        textured (panels, posters, stripes), bright lamps hang on it and a second person
        stands still outside the capture volume. ``none``: no backdrop at all, a lab: a
        textured wall and tiled floor, the lamps and the still second person (key it with a
        plate from the take).
    calibration : Calibration
    volume : stage.rig.Volume

    Returns
    -------
    Backdrop
    """
    if kind not in STAGES:
        raise ValueError(f"kind must be one of {STAGES}, got {kind!r}")
    centres = calibration.centers()
    reach = max(np.linalg.norm(centres[:, :2] - np.asarray(volume.center[:2]), axis=1).max(), 1.0)
    top = max(float(centres[:, 2].max()), float(volume.bounds[1][2]))
    radius = float(max(3200.0, 1.6 * reach))
    base = dict(wall_radius=radius, wall_height=float(max(3200.0, 1.5 * top)),
                center=(float(volume.center[0]), float(volume.center[1])))
    if kind == "green":
        return Backdrop(**base)
    # the second person: between the cameras' ring and the wall, never between a camera and the subject
    ring = 0.5 * (reach + radius)
    figure = (float(volume.center[0] + ring * np.cos(2.2)), float(volume.center[1] + ring * np.sin(2.2)))
    lab = dict(wall_color=(80.0, 85.0, 95.0), wall_texture=0.9, lights=3, figure=figure, spill=0.0)
    if kind == "floor":
        return Backdrop(**base, **lab)
    return Backdrop(**base, **lab, floor_color=(110.0, 115.0, 120.0), floor_texture=0.8)


def cached_render(key_src: str, render, *, cache: bool = True, names: tuple[str, ...] = _ARRAYS) -> dict:
    """The arrays of a take (``names``; by default ``images``, ``masks``, ``labels``, ``depth``,
    ``plate``): read from the on-disk cache under the digest of ``key_src`` (every parameter of the
    take), else ``render()`` and stored. ``depth`` may be None."""
    key = hashlib.sha1(key_src.encode()).hexdigest()[:20]
    arrays = _load_cached(key, names) if cache else None
    if arrays is None:
        arrays = render()
        if cache:
            _store_cached(key, arrays, key_src, names)
    return arrays


def _render_all(calib: Calibration, poses: list, backdrop: Backdrop, seed: int, depth: bool, noise: float, workers) -> dict:
    C, F = len(calib), len(poses)
    n_pixels = sum(c.width * c.height for c in calib) * F
    nw = _default_workers(n_pixels) if workers is None else int(workers)
    if nw < 1:
        raise ValueError(f"workers must be >= 1, got {workers!r}")
    sizes = {c.size for c in calib}
    if len(sizes) != 1:
        raise ValueError(f"calibration: all cameras must have the same size to form a take, got {sorted(sizes)}")
    w, h = sizes.pop()
    jobs = [(cam, poses, backdrop, seed, ci, depth, noise, noise) for ci, cam in enumerate(calib)]
    if nw > 1 and C > 1:
        import multiprocessing as mp

        with ProcessPoolExecutor(max_workers=min(nw, C), mp_context=mp.get_context("spawn")) as ex:
            results = list(ex.map(_render_camera, jobs))
    else:
        results = [_render_camera(j) for j in jobs]
    images = np.empty((F, C, h, w, 3), dtype=np.uint8)
    masks = np.empty((F, C, h, w), dtype=bool)
    labels = np.empty((F, C, h, w), dtype=np.int8)
    dep = np.empty((F, C, h, w), dtype=np.uint16) if depth else None
    plate = np.empty((C, h, w, 3), dtype=np.uint8)
    for ci, r in enumerate(results):
        images[:, ci] = r["images"]
        masks[:, ci] = r["masks"]
        labels[:, ci] = r["labels"]
        if dep is not None:
            dep[:, ci] = r["depth"]
        plate[ci] = r["plate"]
    return {"images": images, "masks": masks, "labels": labels, "depth": dep, "plate": plate}


def _poses_digest(poses: list) -> str:
    """A digest of the posed capsules: the cache key follows the creature's shape and motion,
    not only its name (a changed creature is rendered anew)."""
    h = hashlib.sha1()
    for pose in poses:
        if pose is None:
            h.update(b"-")
            continue
        for a in (pose.p0, pose.p1, pose.r0, pose.r1):
            h.update(np.round(np.asarray(a, np.float64), 6).tobytes())
        h.update(np.asarray(pose.limb, np.int64).tobytes())
        if pose.rest is not None:  # where the painted texture lies on the body
            h.update(np.round(pose.rest, 9).tobytes())
    return h.hexdigest()


def _load_cached(key: str, names: tuple[str, ...] = _ARRAYS) -> dict | None:
    d = cache_dir() / key
    if not (d / "done").is_file():
        return None
    try:
        out = {}
        for name in names:
            p = d / f"{name}.npy"
            if name == "depth" and not p.is_file():
                out[name] = None
                continue
            if name == "masks":
                packed = np.load(p)
                shape = tuple(json.loads((d / "masks.json").read_text())["shape"])
                out[name] = np.unpackbits(packed, axis=-1, count=shape[-1]).astype(bool).reshape(shape)
            else:
                # copy-on-write map: fast to open, writable, never written back
                out[name] = np.asarray(np.load(p, mmap_mode="c"))
        log.debug("simulated take %s read from the cache", key)
        return out
    except (OSError, ValueError, KeyError) as exc:
        log.warning("ignoring unreadable cached take %s: %s", d, exc)
        return None


def _store_cached(key: str, arrays: dict, key_src: str, names: tuple[str, ...] = _ARRAYS) -> None:
    root = cache_dir()
    final = root / key
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=root))
        for name in names:
            a = arrays[name]
            if a is None:
                continue
            if name == "masks":
                np.save(tmp / "masks.npy", np.packbits(a, axis=-1))
                (tmp / "masks.json").write_text(json.dumps({"shape": list(a.shape)}))
            else:
                np.save(tmp / f"{name}.npy", a)
        (tmp / "key.json").write_text(key_src)
        (tmp / "done").write_text("ok")
        try:
            os.rename(tmp, final)
        except OSError:  # someone else stored it first
            shutil.rmtree(tmp, ignore_errors=True)
    except OSError as exc:
        log.warning("could not cache the simulated take in %s: %s", root, exc)


# -- ground truth files --------------------------------------------------------------


def ground_truth_path(take_path: str | Path) -> Path:
    """``TAKE.gt.npz`` beside ``TAKE.h5`` (or the path itself if it ends in ``.npz``)."""
    p = Path(take_path)
    if p.suffix == ".npz":
        return p
    return p.with_name(p.stem + ".gt.npz")


def write_ground_truth(take: SimulatedTake, path: str | Path) -> Path:
    """Write a take's ground truth beside the take file.

    Parameters
    ----------
    take : SimulatedTake
    path : str or Path
        The take file (``TAKE.h5`` -> ``TAKE.gt.npz``) or an explicit ``.npz`` path.

    Returns
    -------
    Path
        The file written. It holds ``masks`` (bit-packed along the width;
        ``mask_shape``), ``labels``, ``calibration`` (JSON), ``limb_names``,
        ``tips`` (F, L, 3), ``axis_<limb>`` (F, K, 3), the capsules per frame
        (``p0``/``p1`` (F, M, 3), ``r0``/``r1``/``limb`` (F, M), padded; ``n_capsules`` (F,)),
        when the poses carry them their rest motions (``rest`` (F, M, 3, 4), padded; ``has_rest`` (F,)),
        ``times``, ``fps`` and ``params`` (JSON); for a mesh subject ``mesh_vertices`` (F, V, 3) and
        ``mesh_faces`` (T, 3) (its tips without ``axis_<limb>``). Read it with :func:`load_ground_truth`.
    """
    if not isinstance(take, SimulatedTake):
        raise ValueError(f"take must be a SimulatedTake, got {type(take).__name__}")
    out = ground_truth_path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    F = take.n_frames
    data: dict[str, np.ndarray] = {
        "masks": np.packbits(take.masks, axis=-1),
        "mask_shape": np.asarray(take.masks.shape),
        "labels": np.asarray(take.labels),
        "calibration": np.asarray(json.dumps(take.calibration.to_dict())),
        "limb_names": np.asarray(list(take.limb_names), dtype=str),
        "tips": take.tip_array(),
        "times": take.times,
        "fps": np.asarray(take.fps),
        "subject": np.asarray(take.subject),
        "params": np.asarray(json.dumps(take.params)),
    }
    for name in take.limb_names:
        if all(name in a for a in take.axes):  # a mesh subject's tips come without limb axes
            data[f"axis_{name}"] = np.stack([a[name] for a in take.axes])
    if take.mesh_vertices is not None:
        data.update(mesh_vertices=np.asarray(take.mesh_vertices), mesh_faces=np.asarray(take.mesh_faces))
    if take.poses and take.poses[0] is not None:
        M = max(p.n_capsules for p in take.poses)
        p0 = np.full((F, M, 3), np.nan)
        p1 = np.full((F, M, 3), np.nan)
        r0 = np.full((F, M), np.nan)
        r1 = np.full((F, M), np.nan)
        limb = np.full((F, M), -9, dtype=np.int16)
        n = np.zeros(F, dtype=np.int32)
        for f, p in enumerate(take.poses):
            m = p.n_capsules
            p0[f, :m], p1[f, :m], r0[f, :m], r1[f, :m], limb[f, :m] = p.p0, p.p1, p.r0, p.r1, p.limb
            n[f] = m
        data.update(p0=p0, p1=p1, r0=r0, r1=r1, limb=limb, n_capsules=n)
        if any(p.rest is not None for p in take.poses):  # the body-painted texture's rest motions
            rest = np.full((F, M, 3, 4), np.nan)
            for f, p in enumerate(take.poses):
                if p.rest is not None:
                    rest[f, : p.n_capsules] = p.rest
            data.update(rest=rest, has_rest=np.array([p.rest is not None for p in take.poses]))
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez_compressed(tmp, **data)
    replace_durably(tmp, out)
    return out


def load_ground_truth(path: str | Path) -> dict:
    """Read a file written by :func:`write_ground_truth`.

    Returns
    -------
    dict
        ``masks (F, C, H, W) bool``, ``labels``, ``calibration`` (Calibration),
        ``limb_names`` (list), ``tips (F, L, 3)``, ``axes`` (dict limb -> (F, K, 3)),
        ``times``, ``fps``, ``subject``, ``params`` and, for creatures, ``poses``
        (list of Pose; ``Pose.rest`` as written, None from files that do not store it), for
        mesh subjects ``mesh_vertices (F, V, 3)`` and ``mesh_faces (T, 3)``.
    """
    p = ground_truth_path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: ground truth file not found")
    with np.load(p, allow_pickle=False) as z:
        shape = tuple(int(s) for s in z["mask_shape"])
        names = [str(s) for s in z["limb_names"]]
        out = {
            "masks": np.unpackbits(z["masks"], axis=-1, count=shape[-1]).astype(bool).reshape(shape),
            "labels": z["labels"],
            "calibration": Calibration.from_dict(json.loads(str(z["calibration"]))),
            "limb_names": names,
            "tips": z["tips"],
            "axes": {n: z[f"axis_{n}"] for n in names if f"axis_{n}" in z.files},
            "times": z["times"],
            "fps": float(z["fps"]),
            "subject": str(z["subject"]),
            "params": json.loads(str(z["params"])),
        }
        if "mesh_vertices" in z.files:
            out["mesh_vertices"], out["mesh_faces"] = z["mesh_vertices"], z["mesh_faces"]
        if "p0" in z.files:
            poses = []
            P0, P1, R0, R1, LB, NC = (z[k] for k in ("p0", "p1", "r0", "r1", "limb", "n_capsules"))
            # files written before the rest motions were stored: texture fixed in the world, as then
            rest, has_rest = (z["rest"], z["has_rest"]) if "rest" in z.files else (None, np.zeros(shape[0], bool))
            for f in range(shape[0]):
                m = int(NC[f])
                tips = {n: out["tips"][f, i] for i, n in enumerate(names)}
                axes = {n: out["axes"][n][f] for n in names}
                poses.append(
                    Pose(
                        p0=P0[f, :m],
                        p1=P1[f, :m],
                        r0=R0[f, :m],
                        r1=R1[f, :m],
                        limb=LB[f, :m],
                        names=tuple(names),
                        tips=tips,
                        axes=axes,
                        time=float(out["times"][f]),
                        rest=rest[f, :m] if has_rest[f] else None,
                    )
                )
            out["poses"] = poses
    return out
