"""The takes under the data root (``DATA/takes/<take>.h5``): list, read, import, delete.

Reading goes through :class:`stage.store.TakeReader`; this module only
adds id validation, the data-root confinement and upload handling.
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any, AsyncIterator, Callable

import numpy as np

from api.errors import ConflictError, NotFoundError, UnavailableError, UploadTooLargeError
from api.paths import check_take_id, confined, confined_entries, inside
from calib.fileio import json_ready, replace_durably
from stage.workers import process_alive

__all__ = ["TakeLibrary", "HDF5_SIGNATURE", "InvalidTakeError"]

log = logging.getLogger(__name__)

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


class InvalidTakeError(ValueError):
    """A file that is not a readable take (400)."""


def _is_hdf5(path: Path) -> bool:
    # the superblock signature sits at 0, 512, 1024, 2048... (HDF5 file format spec, section II.A)
    size = path.stat().st_size
    with open(path, "rb") as f:
        off = 0
        while off + 8 <= size and off <= 1 << 20:
            f.seek(off)
            if f.read(8) == HDF5_SIGNATURE:
                return True
            off = 512 if off == 0 else off * 2
    return False


def _open_reader(path: Path):
    try:
        from stage.store import TakeReader
    except ImportError as exc:
        raise UnavailableError(f"reading takes needs stage.store ({exc})") from None
    return TakeReader(path)


@contextmanager
def _reading(path: Path, take_id: str):
    """A TakeReader whose errors name the take id, not the server's path."""
    try:
        with _open_reader(path) as r:
            yield r
    except (OSError, ValueError) as exc:
        if isinstance(exc, (NotFoundError, UnavailableError)):
            raise
        msg = str(exc).replace(f"{path}: ", "").replace(str(path), take_id)
        raise InvalidTakeError(f"take {take_id!r}: {msg}") from None


class TakeLibrary:
    """Takes of one data root.

    Parameters
    ----------
    takes_dir : Path
        ``DATA/takes``.
    max_upload_bytes : int
        Largest accepted upload.
    """

    def __init__(self, takes_dir: Path, *, max_upload_bytes: int, data_root: Path | None = None) -> None:
        self.takes_dir = Path(takes_dir).resolve()
        self.data_root = Path(data_root).resolve() if data_root is not None else self.takes_dir.parent
        self.max_upload_bytes = int(max_upload_bytes)

    # -- lookup ------------------------------------------------------------------------------
    def path(self, take_id: str) -> Path:
        """The file of an existing take (raises :class:`NotFoundError` / :class:`InvalidIdError`)."""
        check_take_id(take_id)
        p = inside(self.takes_dir, f"{take_id}.h5")
        if not p.is_file():
            raise NotFoundError(f"no take {take_id!r}")
        return p

    def list(self) -> list[dict[str, Any]]:
        """``[{"id", "size_bytes", "modified"}]`` sorted by id."""
        out = []
        for p in confined_entries(self.takes_dir, "*.h5", root=self.takes_dir):
            tid = p.stem
            try:
                check_take_id(tid)  # not the derived data (masks...) of a take
            except ValueError:
                continue
            try:
                st = p.stat()
            except OSError:
                continue
            out.append({"id": tid, "size_bytes": st.st_size, "modified": st.st_mtime})
        return out

    def info(self, take_id: str) -> dict[str, Any]:
        """Cameras, frame count, sync statistics and calibration of a take."""
        p = self.path(take_id)
        st = p.stat()
        out: dict[str, Any] = {"id": take_id, "size_bytes": st.st_size, "modified": st.st_mtime}
        with _reading(p, take_id) as r:
            out.update(_describe(r))
        return out

    def attach_calibration(self, take_id: str, calibration: Any) -> dict[str, Any]:
        """Make ``calibration``, cut to the take's cameras, the take's (in its derived file, which readers
        prefer: the recording is not rewritten); returns the take's description after.

        Raises
        ------
        ValueError
            ``calibration`` is not a Calibration.
        ConflictError
            It lacks one of the take's cameras, or the take is still being written.
        """
        from calib.calibration import Calibration
        from stage.store import attach_calibration

        if not isinstance(calibration, Calibration):
            raise ValueError(f"calibration must be a calib.Calibration, got {type(calibration).__name__}")
        p = self.path(take_id)
        with _reading(p, take_id) as r:
            cams, complete = list(r.cameras), bool(r.complete)
        if not complete:
            raise ConflictError(f"take {take_id!r} is still being written; calibrate it once it is closed")
        missing = [c for c in cams if c not in calibration.names]
        if missing:
            raise ConflictError(f"the calibration has no camera {', '.join(missing)} of take {take_id!r} "
                                f"(it has {', '.join(calibration.names)})")
        attach_calibration(p, Calibration(cameras=tuple(calibration[c] for c in cams), units=calibration.units,
                                          meta=dict(calibration.meta)))
        log.info("take %s: calibration attached", take_id)
        return self.info(take_id)

    def image(self, take_id: str, index: int, camera: str, *, kind: str, fmt: str) -> bytes:
        """Frame ``index`` of ``camera`` (``kind="image"``) or its mask (``"mask"``), encoded as PNG or JPEG."""
        import cv2

        if kind not in ("image", "mask"):
            raise ValueError(f"kind must be 'image' or 'mask', got {kind!r}")
        if fmt not in ("png", "jpg", "jpeg"):
            raise ValueError(f"format must be png or jpg, got {fmt!r}")
        if index < 0:
            raise ValueError("frame index must be >= 0")
        p = self.path(take_id)
        with _reading(p, take_id) as r:
            arr = _read_view(r, index, camera, kind)
        if arr.dtype == bool:
            arr = arr.astype(np.uint8) * 255
        ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", arr)
        if not ok:
            raise ValueError("could not encode the image")
        return buf.tobytes()

    # -- changes -----------------------------------------------------------------------------
    def _target(self, take_id: str) -> Path:
        check_take_id(take_id)
        p = inside(self.takes_dir, f"{take_id}.h5")
        if p.exists():
            raise ConflictError(f"take {take_id!r} already exists")
        return p

    def _tmp(self) -> Path:
        self.takes_dir.mkdir(parents=True, exist_ok=True)
        return self.takes_dir / f".upload-{os.getpid()}-{uuid.uuid4().hex}.part"

    def remove_stale_uploads(self) -> list[str]:
        """Remove the ``.upload-<pid>-<hex>.part`` files of uploads whose server process is gone (a
        killed server, a dropped connection it never saw end); those of a live server sharing the
        data root stay. Files of the older name ``.upload-<hex>.part`` carry no pid: removed.
        Returns the names removed."""
        gone = []
        for p in self.takes_dir.glob(".upload-*.part"):
            parts = p.name[len(".upload-"):-len(".part")].split("-")
            pid = int(parts[0]) if len(parts) == 2 and parts[0].isdigit() else None
            if pid is not None and pid != os.getpid() and process_alive(pid):
                continue
            try:
                p.unlink()
                gone.append(p.name)
            except OSError as exc:
                log.warning("cannot remove the stale upload %s: %s", p.name, exc)
        if gone:
            log.info("removed %d stale upload file(s) of a server that is gone: %s", len(gone), ", ".join(gone))
        return gone

    def _finish(self, tmp: Path, take_id: str) -> dict[str, Any]:
        try:
            if not _is_hdf5(tmp):
                raise InvalidTakeError("the upload is not an HDF5 take file")
            try:
                with _open_reader(tmp) as r:
                    _describe(r)
            except UnavailableError:
                pass  # cannot check deeper without stage.store; the signature was checked
            except (OSError, KeyError, ValueError) as exc:
                msg = str(exc).replace(str(tmp), "upload").replace(f"{tmp}: ", "")
                raise InvalidTakeError(f"the upload is not a readable take: {msg}") from None
            target = self._target(take_id)
            replace_durably(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        log.info("imported take %s", take_id)
        return {"id": take_id, "size_bytes": target.stat().st_size}

    def _limited(self, f) -> Callable[[bytes], None]:
        """A writer into ``f`` that raises :class:`UploadTooLargeError` past the upload limit."""
        written = [0]

        def write(chunk: bytes) -> None:
            written[0] += len(chunk)
            if written[0] > self.max_upload_bytes:
                raise UploadTooLargeError(f"upload larger than the limit of {self.max_upload_bytes} bytes")
            f.write(chunk)

        return write

    async def import_stream(self, take_id: str, chunks: AsyncIterator[bytes], *, expected: int | None = None) -> dict[str, Any]:
        """Write an uploaded take (raw HDF5 bytes) under ``take_id``, enforcing the size limit.

        ``expected``: the declared body size (Content-Length), checked against the free space first.
        """
        self._target(take_id)  # fail early on bad or existing ids
        if expected is not None:
            _check_space(self.takes_dir, expected, "the uploaded take")
        tmp = self._tmp()
        try:
            with _disk_full_as_error(self.takes_dir), open(tmp, "wb") as f:
                write = self._limited(f)
                async for chunk in chunks:
                    write(chunk)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return self._finish(tmp, take_id)

    def import_file(self, take_id: str, fileobj) -> dict[str, Any]:
        """Write an uploaded take from a file object (multipart upload), enforcing the size limit."""
        self._target(take_id)
        tmp = self._tmp()
        try:
            with _disk_full_as_error(self.takes_dir), open(tmp, "wb") as f:
                write = self._limited(f)
                while chunk := fileobj.read(1 << 20):
                    write(chunk)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return self._finish(tmp, take_id)

    def import_path(self, take_id: str, rel_path: str, *, masks: str | None = None) -> dict[str, Any]:
        """Copy a take file from ``rel_path`` (relative to the data root, never outside it); ``masks``
        (a folder relative to the data root, one folder per camera) are checked before anything is
        copied and stored as the take's masks (:func:`stage.importer.import_masks`)."""
        if not rel_path or Path(rel_path).is_absolute():
            raise ValueError("path must be relative to the data root")
        src = inside(self.data_root, rel_path)
        if not src.is_file():
            raise NotFoundError(f"no file {rel_path!r} in the data root")
        mask_dir = self._mask_dir(src, masks) if masks is not None else None
        if src.stat().st_size > self.max_upload_bytes:
            raise UploadTooLargeError(f"file larger than the limit of {self.max_upload_bytes} bytes")
        self._target(take_id)
        src_derived = _derived(src)
        derived = src_derived.is_file() and confined(src_derived, self.data_root)
        _check_space(self.takes_dir, src.stat().st_size + (src_derived.stat().st_size if derived else 0), "the imported take")
        tmp = self._tmp()
        try:
            shutil.copyfile(src, tmp)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        out = self._finish(tmp, take_id)
        if derived:  # the take's masks and other derived data travel with it
            dst = _derived(self.takes_dir / f"{take_id}.h5")
            part = dst.with_name(f".{dst.name}.{uuid.uuid4().hex}.part")
            try:
                shutil.copyfile(src_derived, part)
                replace_durably(part, dst)
            finally:
                part.unlink(missing_ok=True)
        if mask_dir is not None:
            from stage.importer import import_masks

            dst = self.takes_dir / f"{take_id}.h5"
            try:
                import_masks(dst, mask_dir)
            except BaseException:
                self.delete(take_id)
                raise
        return out

    def _mask_dir(self, src: Path, masks: str) -> Path:
        """The masks folder inside the data root, checked against the take before it is copied."""
        from stage.importer import check_mask_folders
        from stage.store import TakeReader

        if Path(masks).is_absolute():
            raise ValueError("masks must be relative to the data root")
        d = inside(self.data_root, masks)
        if not d.is_dir():
            raise NotFoundError(f"no folder {masks!r} in the data root")
        with TakeReader(src) as r:
            if not r.has_calibration:
                raise ValueError(f"{src.name}: the take has no calibration")
            calib = r.calibration
            sizes = {c: tuple(r.image_size(c)) for c in r.cameras}
            counts = r.frame_counts()
            cams = type(calib)(tuple(calib[c] for c in r.cameras), units=calib.units)
        check_mask_folders(d, cams, counts, sizes)  # type: ignore[arg-type]
        return d

    def delete(self, take_id: str) -> None:
        p = self.path(take_id)
        p.unlink()
        _derived(p).unlink(missing_ok=True)
        log.info("deleted take %s", take_id)


def _derived(take: Path) -> Path:
    """The derived-data file beside a take (``TAKE.derived.h5``, see ``docs/take-format.md``)."""
    return take.with_name(take.stem + ".derived.h5")


def _disk_full_as_error(directory: Path):
    from stage.store.space import raise_disk_full

    return raise_disk_full(directory, "the uploaded take", detail="nothing was stored")


def _check_space(directory: Path, need: int, what: str) -> None:
    from stage.store.space import check_free_space

    check_free_space(directory, need + (1 << 20), what)


def _describe(r: Any) -> dict[str, Any]:
    """What a :class:`stage.store.TakeReader` tells about its take."""
    cal = r.calibration
    return {
        "cameras": [
            {"id": c, "frames": r.n_frames(c), **{k: json_ready(v) for k, v in r.camera_info(c).items()}}
            for c in r.cameras
        ],
        "frames": int(r.n_sets),
        "complete": bool(r.complete),
        "fps": r.fps,
        "measured_fps": r.measured_fps(),
        "duration_s": r.duration_s,
        "compression": r.compression,
        "sync": json_ready(r.sync_stats),
        "masks": r.masks_present(),
        "calibration": cal.to_dict() if cal is not None else None,
    }


def _read_view(r: Any, index: int, camera: str, kind: str) -> np.ndarray:
    """Image (H, W, 3) uint8 or mask (H, W) bool of ``camera`` in frame set ``index``."""
    if camera not in r.cameras:
        raise NotFoundError(f"no camera {camera!r} in this take (cameras: {', '.join(r.cameras)})")
    if not 0 <= index < r.n_sets:
        raise NotFoundError(f"no frame {index} (the take has {r.n_sets} frames)")
    row = r.set_rows(index)[camera]
    if row < 0:
        raise NotFoundError(f"camera {camera!r} has no frame in frame set {index} (dropped)")
    if kind == "image":
        return np.asarray(r.frame(camera, row))
    masks = r.masks(camera)
    if masks is None:
        raise NotFoundError(f"camera {camera!r} has no masks (run keying first)")
    if row >= masks.shape[0]:
        raise NotFoundError(f"no mask for frame {index} of camera {camera!r}")
    return masks[row]
