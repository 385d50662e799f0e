"""Build a take from another rig's footage (images or videos plus a calibration).

``DIR`` holds one entry per camera of the calibration, named like the camera:

* a folder ``DIR/<name>/`` of images (sorted by file name), one per frame;
* a video file ``DIR/<name>.mp4`` (``.avi .mkv .mov .webm .mjpeg``...);
* a single image ``DIR/<name>.png`` (``.jpg .bmp .tif``...), a static take;
* or the image the calibration itself names (``camera.meta["image"]``, as in a
  Middlebury ``*_par.txt``), e.g. the dino: one folder of images named in the
  par file.

Frame set ``k`` is the ``k``-th frame of every camera; a camera with fewer
frames is missing from the later sets. Timestamps are synthetic
(``k / fps``). JPEG images are stored byte for byte (nothing re-encoded) unless
``storage="raw"``. The calibration keeps its own units (``Calibration.units``).
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
from calib.formats import read_calibration
from stage.frame import Frame
from stage.rig import check_plane
from stage.store import CameraSpec, DiskFullError, TakeReader, TakeWriter

__all__ = ["ImportResult", "import_take", "find_sources", "IMAGE_EXTS", "VIDEO_EXTS"]

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
    fps: float = 30.0,
    storage: str = "auto",
    compression: str = "none",
    overwrite: bool = False,
    max_frames: int | None = None,
    support_plane: Sequence[float] | None = None,
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
    fps : float
        Frame rate of the synthetic timestamps.
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
    progress : callable, optional
        ``progress(done, total)`` after each set.

    Raises
    ------
    ValueError
        Missing entry for a camera, unreadable image or video, an image whose
        size differs from the calibration's, bad arguments.
    """
    _check_options(fps=fps, storage=storage, max_frames=max_frames)
    rig: dict[str, Any] = {"name": "imported", "source": str(Path(images).resolve()), "fps": fps}
    if support_plane is not None:
        rig["support_plane"] = check_plane(support_plane).tolist()
    calib = _load_calibration(calibration)
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: take already exists (use --overwrite to replace it)")
    sources = find_sources(images, calib)
    counts = {c: sources[c].count() for c in calib.names}
    n_sets = _set_count(counts, max_frames)
    kinds = {cam.name: _storage_of(sources[cam.name], storage, cam.name) for cam in calib}
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
        os.replace(tmp, out)
    except DiskFullError as exc:
        _remove(tmp)
        raise DiskFullError(f"{out}: import stopped, nothing written: {str(exc).replace(str(tmp), tmp.name)}") from None
    except BaseException:
        _remove(tmp)
        raise
    with TakeReader(out) as r:
        fc = r.frame_counts()
    return ImportResult(path=out, sets=k, frames=fc, storage=kinds, units=calib.units)


def _check_options(*, fps: float, storage: str, max_frames: int | None) -> None:
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
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
