"""Build a take from another rig's footage (images or videos plus a calibration).

``DIR`` holds one entry per camera of the calibration, named like the camera:

* a folder ``DIR/<name>/`` of images (sorted by file name), one per frame;
* a video file ``DIR/<name>.mp4`` (``.avi .mkv .mov .webm .mjpeg``...);
* a single image ``DIR/<name>.png`` (``.jpg .bmp .tif``...), a static take;
* or the image the calibration itself names (``camera.meta["image"]``, as in a
  Middlebury ``*_par.txt``), e.g. the dino: one folder of images named in the
  par file.

Footage whose size differs from the calibration's is reconciled when the difference is
one a recording explains, with a warning naming the camera: an integer binning (the
footage a whole fraction of the calibrated size: intrinsics scaled), a codec's 16-pixel
alignment (the calibration's size rounded up to 16 while the footage is not: the
footage is the calibrated window's top-left part, intrinsics unchanged), or a calibration
that does not store the image size (EasyMocap: the footage's size is taken). Any other
difference is an error. ``scale`` resizes every frame on import (e.g. 0.5 for a quick
look at 1080p footage) and scales the intrinsics to match.

Frame set ``k`` is the ``k``-th frame of every camera; a camera with fewer
frames is missing from the later sets. Timestamps are synthetic
(``k / fps``); without ``fps`` the rate is the videos' own (the median of the rates their
files state, a warning when they differ by more than 1 %), else 30 for image folders.
JPEG images are stored byte for byte (nothing re-encoded) unless ``storage="raw"``. The
calibration keeps its own units (``Calibration.units``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import cv2
import numpy as np

from calib.calibration import Calibration
from calib.fileio import replace_durably
from calib.formats import read_calibration
from stage.frame import Frame
from stage.rig import check_plane
from stage.store import CameraSpec, DiskFullError, TakeReader, TakeWriter

__all__ = ["ImportResult", "import_take", "import_masks", "check_mask_folders", "find_sources", "fit_to_footage", "footage_fps",
           "scaled_calibration", "IMAGE_EXTS", "VIDEO_EXTS"]

log = logging.getLogger(__name__)

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
VIDEO_EXTS = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".mjpeg", ".mjpg", ".m4v", ".mpg")
_JPEG_EXTS = (".jpg", ".jpeg")


@dataclass(frozen=True)
class _Source:
    camera: str
    kind: str  # "folder" | "video" | "image"
    path: Path
    files: tuple[Path, ...] = ()

    def count(self) -> int:
        if self.kind == "video":
            cap = cv2.VideoCapture(str(self.path))
            try:
                return max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
            finally:
                cap.release()
        return len(self.files)

    @property
    def all_jpeg(self) -> bool:
        return self.kind != "video" and all(f.suffix.lower() in _JPEG_EXTS for f in self.files)


@dataclass
class ImportResult:
    path: Path
    sets: int
    frames: dict[str, int]
    storage: dict[str, str]
    units: str
    fps: float = 30.0
    fps_source: str = "given"


def find_sources(images: str | os.PathLike, calibration: Calibration) -> dict[str, _Source]:
    """Locate every calibrated camera's footage in ``images`` (see module doc).

    Raises
    ------
    FileNotFoundError
        ``images`` is not a directory.
    ValueError
        A camera has no entry (the message lists what the folder holds).
    """
    root = Path(images)
    if not root.is_dir():
        raise FileNotFoundError(f"--images {root}: not a directory")
    entries = {p.name: p for p in root.iterdir()}
    out: dict[str, _Source] = {}
    missing = []
    for cam in calibration:
        name = cam.name
        folder = root / name
        if folder.is_dir():
            files = tuple(sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS), key=lambda p: p.name))
            if not files:
                raise ValueError(f"camera {name}: folder {folder} holds no images ({', '.join(IMAGE_EXTS)})")
            out[name] = _Source(name, "folder", folder, files)
            continue
        cands = [entries[n] for n in sorted(entries) if Path(n).stem == name and entries[n].is_file()]
        videos = [p for p in cands if p.suffix.lower() in VIDEO_EXTS]
        imgs = [p for p in cands if p.suffix.lower() in IMAGE_EXTS]
        named = cam.meta.get("image") if isinstance(cam.meta, dict) else None
        if named and (root / named).is_file():
            out[name] = _Source(name, "image", root / named, (root / named,))
        elif videos:
            out[name] = _Source(name, "video", videos[0])
        elif imgs:
            out[name] = _Source(name, "image", imgs[0], (imgs[0],))
        else:
            missing.append(name)
    if missing:
        have = ", ".join(sorted(entries)[:20]) or "nothing"
        raise ValueError(
            f"--images {root}: no entry for camera(s) {', '.join(missing)} "
            f"(expected a folder <name>/, a video <name>.mp4 or an image <name>.png; the folder holds: {have})"
        )
    return out


def _read_image(path: Path, camera: str) -> tuple[np.ndarray, bytes | None]:
    data = path.read_bytes() if path.is_file() else None
    if data is None:
        raise ValueError(f"camera {camera}: image {path} cannot be read")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"camera {camera}: image {path} is not a readable image")
    enc = data if path.suffix.lower() in _JPEG_EXTS else None
    return img, enc


def _frames(src: _Source) -> Iterator[tuple[np.ndarray, bytes | None, str]]:
    if src.kind == "video":
        cap = cv2.VideoCapture(str(src.path))
        if not cap.isOpened():
            raise ValueError(f"camera {src.camera}: video {src.path} cannot be opened")
        try:
            k = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    if k == 0:
                        raise ValueError(f"camera {src.camera}: video {src.path} has no readable frame")
                    return
                if img.ndim == 2:
                    img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
                yield img, None, f"{src.path} frame {k}"
                k += 1
        finally:
            cap.release()
    else:
        for f in src.files:
            img, enc = _read_image(f, src.camera)
            yield img, enc, str(f)


def import_take(
    images: str | os.PathLike,
    calibration: str | os.PathLike | Calibration,
    out: str | os.PathLike,
    *,
    fps: float | None = None,
    storage: str = "auto",
    compression: str = "none",
    overwrite: bool = False,
    max_frames: int | None = None,
    support_plane: Sequence[float] | None = None,
    scale: float = 1.0,
    masks: str | os.PathLike | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ImportResult:
    """Write a take from footage in ``images`` and a calibration.

    Parameters
    ----------
    images : path
        Directory with one entry per calibrated camera (see module doc).
    calibration : path or Calibration
        A calibration file in any format :func:`calib.formats.read_calibration`
        reads (aniposelib TOML, OpenCV YAML, Middlebury ``*_par.txt``, JSON).
    out : path
        Take to write.
    fps : float, optional
        Frame rate of the synthetic timestamps (default: the videos' own, :func:`footage_fps`; 30 when no
        camera's footage is a video that states its rate).
    storage : {"auto", "raw", "jpeg"}
        ``auto``: JPEG bytes as they are for cameras whose frames are all JPEG
        files, raw otherwise.
    compression : {"none", "lz4", "gzip"}
        Filter of raw frames.
    max_frames : int, optional
        Import at most this many frame sets.
    support_plane : (4,) floats, optional
        ``(a, b, c, d)`` of the plane the subject stands on (``a x + b y + c z + d >= 0``
        is kept), in the calibration's units; stored in the take's rig, where
        :func:`pipeline.process.process_take` finds it.
    scale : float
        Resize every frame by this factor, in (0, 1] (area averaging); the intrinsics
        follow. Frames are then stored raw.
    masks : path, optional
        Silhouettes made elsewhere: one folder per camera, named like it, one image per
        frame (sorted by name; non-zero = subject), the footage's size. Stored as the
        take's masks (``stage process`` then skips keying). Checked before anything is
        written: a missing or extra folder, a wrong count or a wrong size is one error
        naming the camera and the file.
    progress : callable, optional
        ``progress(done, total)`` after each set.

    Raises
    ------
    ValueError
        Missing entry for a camera, unreadable image or video, an image whose
        size differs from the calibration's, bad arguments.
    """
    _check_options(fps=fps, storage=storage, max_frames=max_frames, scale=scale)
    plane = check_plane(support_plane).tolist() if support_plane is not None else None
    calib = _load_calibration(calibration)
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: take already exists (use --overwrite to replace it)")
    sources = find_sources(images, calib)
    fps, fps_source = (float(fps), "given") if fps is not None else footage_fps(sources)
    rig: dict[str, Any] = {"name": "imported", "source": str(Path(images).resolve()), "fps": fps,
                           **({"support_plane": plane} if plane is not None else {})}
    footage = {c: _first_size(sources[c]) for c in calib.names}
    calib = fit_to_footage(calib, footage)
    if scale != 1:
        calib = scaled_calibration(calib, scale)
        rig["import_scale"] = float(scale)
    counts = {c: sources[c].count() for c in calib.names}
    n_sets = _set_count(counts, max_frames)
    mask_files = check_mask_folders(masks, calib, counts, footage, max_frames) if masks is not None else None
    kinds = {cam.name: "raw" if scale != 1 and storage == "auto" else _storage_of(sources[cam.name], storage, cam.name)
             for cam in calib}
    specs = [CameraSpec(cam.name, cam.width, cam.height, storage=kinds[cam.name]) for cam in calib]
    reader = _SetReader(calib, {c: _frames(sources[c]) for c in calib.names}, kinds, period=1e9 / fps)
    tmp = out.with_name(out.name + ".part")
    if tmp.exists():
        tmp.unlink()
    k = 0
    try:
        with TakeWriter(
            tmp,
            specs,
            rig=rig,
            calibration=calib,
            compression=compression,
            fps=fps,
            attrs={"imported": True, "images": str(Path(images).resolve()), "units": calib.units},
            expected_sets=n_sets if max(counts.values()) > 0 else None,
        ) as w:
            while max_frames is None or k < max_frames:
                frames = reader.next_set(k)
                if frames is None:
                    break
                w.write_set(frames, time_ns=reader.time_ns(k))
                k += 1
                if progress is not None:
                    progress(k, max(n_sets, k))
        replace_durably(tmp, out)
        if mask_files is not None:
            try:
                _store_masks(out, calib, mask_files, source=Path(masks))  # type: ignore[arg-type]
            except BaseException:
                from stage.store import derived_path

                _remove(derived_path(out))
                _remove(out)
                raise
    except DiskFullError as exc:
        _remove(tmp)
        raise DiskFullError(f"{out}: import stopped, nothing written: {str(exc).replace(str(tmp), tmp.name)}") from None
    except BaseException:
        _remove(tmp)
        raise
    with TakeReader(out) as r:
        fc = r.frame_counts()
    return ImportResult(path=out, sets=k, frames=fc, storage=kinds, units=calib.units, fps=fps, fps_source=fps_source)


def footage_fps(sources: dict[str, _Source]) -> tuple[float, str]:
    """The frame rate of the footage (:func:`find_sources`' entries) -> (fps, where it comes from).

    The median of the rates the cameras' video files state (OpenCV's ``CAP_PROP_FPS``; a rate outside
    (0, 1000] is no rate), with a warning naming them when they differ by more than 1 % (frame set ``k``
    is the ``k``-th frame of every camera: such videos are not in step); 30 when no camera's footage is a
    video that states its rate (image folders, single images).
    """
    rates = {}
    for name, src in sources.items():
        if src.kind != "video":
            continue
        cap = cv2.VideoCapture(str(src.path))
        try:
            rate = float(cap.get(cv2.CAP_PROP_FPS))
        finally:
            cap.release()
        if np.isfinite(rate) and 0 < rate <= 1000:
            rates[name] = rate
    if not rates:
        return 30.0, "default"
    values = np.array(list(rates.values()))
    fps = float(np.median(values))
    if values.max() > 1.01 * values.min():
        log.warning("the videos' frame rates differ (%s): frame set k is the k-th frame of every camera, so they are "
                    "not in step; the take's rate is their median, %g fps",
                    ", ".join(f"{c} {r:g} fps" for c, r in rates.items()), fps)
    return fps, "videos"


def check_mask_folders(
    masks: str | os.PathLike,
    calib: Calibration,
    counts: dict[str, int],
    footage: dict[str, tuple[int, int]],
    max_frames: int | None = None,
) -> dict[str, list[Path]]:
    """The mask files of every camera, checked against the footage (names, counts, sizes).

    Raises
    ------
    FileNotFoundError
        ``masks`` is not a directory.
    ValueError
        A camera without a folder, a folder no camera has, a count that differs from the
        camera's frames, an unreadable image or one whose size differs from the footage's:
        one message naming the camera and the file.
    """
    from PIL import Image

    root = Path(masks)
    if not root.is_dir():
        raise FileNotFoundError(f"--masks {root}: not a directory")
    folders = {p.name for p in root.iterdir() if p.is_dir()}
    missing = [c for c in calib.names if c not in folders]
    if missing:
        raise ValueError(f"--masks {root}: no folder for camera(s) {', '.join(missing)} "
                         f"(one folder per camera, named as in the calibration: {', '.join(calib.names)})")
    extra = sorted(folders - set(calib.names))
    if extra:
        raise ValueError(f"--masks {root}: folder(s) {', '.join(extra)} name no camera of the calibration "
                         f"({', '.join(calib.names)})")
    out: dict[str, list[Path]] = {}
    for c in calib.names:
        files = sorted((p for p in (root / c).iterdir() if p.suffix.lower() in IMAGE_EXTS), key=lambda p: p.name)
        want = counts[c] if max_frames is None else min(counts[c], max_frames)
        if len(files) < want or (max_frames is None and len(files) != want):
            raise ValueError(f"camera {c}: {root / c} holds {len(files)} mask image(s) but the footage has {want} frames")
        files = files[:want]
        for f in files:
            try:
                with Image.open(f) as im:
                    size = (int(im.size[0]), int(im.size[1]))
            except (OSError, ValueError):
                raise ValueError(f"camera {c}: mask {f} is not a readable image") from None
            if size != tuple(footage[c]):
                raise ValueError(f"camera {c}: mask {f} is {size[0]}x{size[1]} but the footage is "
                                 f"{footage[c][0]}x{footage[c][1]}")
        out[c] = files
    return out


def import_masks(take: str | os.PathLike, masks: str | os.PathLike) -> dict[str, int]:
    """Store silhouettes made elsewhere as a take's masks (keying then skipped).

    Parameters
    ----------
    take : path
        An existing take.
    masks : path
        One folder per camera of the take, one image per frame, the frames' size
        (see :func:`check_mask_folders`); checked completely before anything is stored.

    Returns
    -------
    dict
        Masks stored per camera.
    """
    with TakeReader(take) as r:
        if not r.has_calibration:
            raise ValueError(f"{take}: the take has no calibration")
        calib = r.calibration
        calib = Calibration(tuple(calib[c] for c in r.cameras), units=calib.units)
        counts = r.frame_counts()
        sizes = {c: tuple(r.image_size(c)) for c in r.cameras}
    files = check_mask_folders(masks, calib, counts, sizes)  # type: ignore[arg-type]
    _store_masks(Path(take), calib, files, source=Path(masks))
    return {c: len(f) for c, f in files.items()}


def _store_masks(take: Path, calib: Calibration, files: dict[str, list[Path]], *, source: Path) -> None:
    """Read every camera's mask images (resized to the take's frames) and store them as its masks."""
    from stage.store import write_arrays

    arrays = []
    for cam in calib:
        masks = np.zeros((len(files[cam.name]), cam.height, cam.width), bool)
        for i, f in enumerate(files[cam.name]):
            m = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if m is None:
                raise ValueError(f"camera {cam.name}: mask {f} is not a readable image")
            if m.shape != masks.shape[1:]:
                m = cv2.resize(m, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
                m = np.where(m >= 128, 255, 0).astype(np.uint8)
            masks[i] = m > 0
        n = masks.shape[0]
        meta = {"key": {"mode": "imported", "source": str(source.resolve() / cam.name)}, "valid": [True] * n,
                "reasons": [""] * n}
        arrays.append((f"cameras/{cam.name}", "masks", masks, meta))
        arrays.append((f"cameras/{cam.name}", "mask_valid", np.ones(n, np.uint8), {"reasons": [""] * n}))
    write_arrays(take, arrays)


def _first_size(src: _Source) -> tuple[int, int]:
    """(width, height) of a source's first frame."""
    img = next(_frames(src))[0]
    return int(img.shape[1]), int(img.shape[0])


def _scaled_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of an image resized by (sx, sy) (pixel centres at integer coordinates)."""
    K2 = np.array(K, float)
    K2[0, 0], K2[0, 1], K2[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 1], K2[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
    return K2


def scaled_calibration(calib: Calibration, scale: float) -> Calibration:
    """Every camera's intrinsics and size for frames resized by ``scale`` (sizes rounded)."""
    cams = []
    for c in calib:
        w, h = max(1, int(round(c.width * scale))), max(1, int(round(c.height * scale)))
        meta = {**c.meta, "import_scale": float(scale)}
        cams.append(c.replace(K=_scaled_K(c.K, w / c.width, h / c.height), size=(w, h), meta=meta))
    return Calibration(tuple(cams), units=calib.units, meta=dict(calib.meta))


def _align16(n: int) -> int:
    return -(-int(n) // 16) * 16


def fit_to_footage(calib: Calibration, sizes: dict[str, tuple[int, int]]) -> Calibration:
    """The calibration reconciled with the footage's frame sizes (see the module docstring).

    Raises
    ------
    ValueError
        A camera whose footage size no recording rule explains (names the camera and both sizes).
    """
    cams = []
    for c in calib:
        w, h = sizes[c.name]
        W, H = c.size
        if (w, h) == (W, H):
            cams.append(c)
            continue
        if c.meta.get("size_guessed"):
            log.warning("camera %s: the calibration stores no image size; the footage's %dx%d is used", c.name, w, h)
            cams.append(c.replace(size=(w, h), meta={k: v for k, v in c.meta.items() if k != "size_guessed"}))
        elif W % w == 0 and H % h == 0 and W // w == H // h:
            f = W // w
            log.warning("camera %s: footage %dx%d is the calibrated %dx%d binned by %d; intrinsics scaled",
                        c.name, w, h, W, H, f)
            cams.append(c.replace(K=_scaled_K(c.K, 1 / f, 1 / f), size=(w, h)))
        elif all(a == b or (b % 16 == 0 and _align16(a) == b) for a, b in ((w, W), (h, H))):
            log.warning("camera %s: footage %dx%d is the calibrated %dx%d less the codec's 16-pixel alignment; "
                        "the calibrated window's top-left %dx%d is used (intrinsics unchanged)", c.name, w, h, W, H, w, h)
            cams.append(c.replace(size=(w, h)))
        else:
            raise ValueError(f"camera {c.name}: the footage is {w}x{h} but the calibration says {W}x{H} "
                             "(neither a binning nor a codec's alignment explains it)")
    return Calibration(tuple(cams), units=calib.units, meta=dict(calib.meta))


def _check_options(*, fps: float | None, storage: str, max_frames: int | None, scale: float = 1.0) -> None:
    if not (isinstance(scale, (int, float)) and 0 < scale <= 1):
        raise ValueError(f"scale must be in (0, 1], got {scale!r}")
    if fps is not None and not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    if storage not in ("auto", "raw", "jpeg"):
        raise ValueError(f"storage must be 'auto', 'raw' or 'jpeg', got {storage!r}")
    if max_frames is not None and (not isinstance(max_frames, int) or max_frames < 1):
        raise ValueError(f"max_frames must be a positive integer, got {max_frames!r}")


def _load_calibration(calibration: str | os.PathLike | Calibration) -> Calibration:
    if isinstance(calibration, Calibration):
        return calibration
    if isinstance(calibration, (str, os.PathLike)):
        return read_calibration(calibration)
    raise ValueError(f"calibration must be a path or a Calibration, got {type(calibration).__name__}")


def _set_count(counts: dict[str, int], max_frames: int | None) -> int:
    """Frame sets to expect: the longest camera's count (1 when no count is known: videos
    whose frame count is unknown are read until they end), at most ``max_frames``."""
    n_sets = max(counts.values()) or 1
    if len(set(counts.values())) > 1:
        log.warning("cameras have different frame counts (%s); the shorter ones are missing from later sets",
                    ", ".join(f"{c}: {n}" for c, n in counts.items()))
    return n_sets if max_frames is None else min(n_sets, max_frames)


def _storage_of(src: _Source, storage: str, camera: str) -> str:
    """``raw`` or ``jpeg`` for one camera (``auto``: JPEG bytes as they are when every frame is a JPEG file)."""
    if storage == "auto":
        return "jpeg" if src.all_jpeg else "raw"
    if storage == "jpeg" and not src.all_jpeg:
        log.info("camera %s: frames are not JPEG files; they will be JPEG-encoded for storage", camera)
    return storage


class _SetReader:
    """The next frame set of every camera's frame iterator; a camera that has ended is
    missing (``None``) from later sets."""

    def __init__(self, calib: Calibration, iters: dict[str, Iterator], kinds: dict[str, str], *, period: float) -> None:
        self.calib, self.iters, self.kinds, self.period = calib, iters, kinds, period
        self.done = {c: False for c in calib.names}

    def time_ns(self, k: int) -> int:
        return int(round(k * self.period))

    def next_set(self, k: int) -> dict[str, Frame | None] | None:
        """Set ``k``, or ``None`` once every camera has ended."""
        frames = {cam.name: self._next_frame(cam, k) for cam in self.calib}
        return None if all(self.done.values()) else frames

    def _next_frame(self, cam, k: int) -> Frame | None:
        c = cam.name
        if self.done[c]:
            return None
        try:
            img, enc, where = next(self.iters[c])
        except StopIteration:
            self.done[c] = True
            return None
        h, wd = img.shape[:2]
        if (wd, h) != tuple(cam.size) and cam.meta.get("import_scale"):
            img, enc = cv2.resize(img, tuple(cam.size), interpolation=cv2.INTER_AREA), None
        h, wd = img.shape[:2]
        if (wd, h) != tuple(cam.size):
            raise ValueError(f"camera {c}: {where} is {wd}x{h} but the calibration says {cam.width}x{cam.height}")
        if cam.meta.get("mirror"):  # a camera that delivers mirrored images: flip back
            img, enc = np.ascontiguousarray(img[:, ::-1]), None
        t = self.time_ns(k)
        return Frame(img, c, k, t, t, encoded=enc if self.kinds[c] == "jpeg" else None)


def _remove(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError as exc:  # pragma: no cover - e.g. the directory went read-only
        log.warning("could not remove %s: %s", path, exc)
