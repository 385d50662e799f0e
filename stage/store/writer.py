"""Write one take, frame set by frame set, in SWMR mode (layout in ``docs/take-format.md``).

Every dataset is created up front, extended as frames arrive, and the file is flushed after
every frame set, so

* a reader (``stage info``, the pipeline) can open a take while it is written;
* a writer killed mid-take loses at most the frame set in flight: readers count only the sets
  recorded in the commit counter, which is written and flushed after the set's frames;
* a full disk ends the take cleanly: the writer holds a small reserve of disk space (an
  unlinked, preallocated file it keeps open, so even a killed writer leaves nothing behind),
  releases it when a write fails with ``ENOSPC``, closes the take with every committed set and
  raises :class:`~stage.store.space.DiskFullError`.

The file is written once: nothing opens a closed take for writing again (derived data goes to
the derived file beside it, :mod:`stage.store.derived`).
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import h5py
import numpy as np

from stage import __version__
from stage.frame import Frame
from stage.store._format import FORMAT, RESERVED, CameraSpec, derived_filter_kwargs, filter_kwargs, to_json
from stage.store.derived import derived_path
from stage.store.h5repair import close_all as _close_file
from stage.store.jpeg import encode_jpeg
from stage.store.space import DiskFullError, check_free_space, format_bytes, is_disk_full

__all__ = ["TakeWriter", "estimate_take_bytes"]

log = logging.getLogger("stage.store")

_JPEG_BLOCK = 4 << 20  # grow the JPEG byte stream 4 MiB at a time
_HEADER_BYTES = 256 << 10  # metadata of an empty take, generously
# every chunk carries HDF5's Fletcher-32 checksum (after compression): a flipped bit in stored
# frames is an error on read (stage.store.verify finds all of them) instead of a wrong pixel
_SUM = {"fletcher32": True}


def _set_bytes(cameras: Sequence[CameraSpec], compression: str) -> int:
    """Expected bytes of one frame set: raw frames as they are (compressed: half), JPEG about 1/10."""
    n = 0
    for c in cameras:
        raw = c.frame_bytes()
        if c.storage == "jpeg":
            n += raw // 10
        else:
            n += raw if compression == "none" else raw // 2
    return n + 64 * len(cameras)


def estimate_take_bytes(cameras: Sequence[CameraSpec], n_sets: int, *, compression: str = "none") -> int:
    """About how many bytes a take of ``n_sets`` frame sets of these cameras takes on disk."""
    return _HEADER_BYTES + int(n_sets) * _set_bytes(list(cameras), compression)


def _check_cameras(cameras: Sequence[CameraSpec]) -> tuple[list[CameraSpec], list[str]]:
    cams = list(cameras)
    if not cams or not all(isinstance(c, CameraSpec) for c in cams):
        raise ValueError("cameras must be a non-empty sequence of CameraSpec")
    ids = [c.id for c in cams]
    if len(set(ids)) != len(ids):
        raise ValueError(f"cameras: duplicate camera ids {ids}")
    return cams, ids


def _check_numbers(block: int, fps: float | None, expected_sets: int | None) -> None:
    if int(block) < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    if expected_sets is not None and (not isinstance(expected_sets, (int, np.integer)) or expected_sets < 0):
        raise ValueError(f"expected_sets must be a non-negative integer, got {expected_sets!r}")


def _check_arrays(arrays: Mapping[str, np.ndarray] | None, ids: list[str]) -> dict[str, np.ndarray]:
    out = {}
    for key, a in (arrays or {}).items():
        parts = str(key).strip("/").split("/")
        if len(parts) != 3 or parts[0] != "cameras" or parts[1] not in ids or parts[2] in RESERVED or not parts[2]:
            raise ValueError(f"arrays: {key!r} must be 'cameras/<camera id>/<name>' (name not one of the capture's datasets)")
        arr = np.asarray(a)
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"arrays[{key!r}] must be numeric, got dtype {arr.dtype}")
        out["/".join(parts)] = arr
    return out


class _Reserve:
    """Disk space held back for closing a take on a full disk: an unlinked file kept open."""

    def __init__(self, directory: Path, nbytes: int) -> None:
        self.fd: int | None = None
        try:
            fd, name = tempfile.mkstemp(prefix=".stage-reserve-", dir=directory)
        except OSError:
            return
        os.unlink(name)
        try:
            os.posix_fallocate(fd, 0, nbytes)
        except (OSError, AttributeError):
            os.close(fd)  # no room even for the reserve: the up-front check already warned
            return
        self.fd = fd

    def release(self) -> bool:
        if self.fd is None:
            return False
        os.close(self.fd)
        self.fd = None
        return True


class TakeWriter:
    """Write one take, frame set by frame set, in SWMR mode.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` file to create.
    cameras : sequence of CameraSpec
        In rig order (the column order of the frame-set table).
    rig : dict or pydantic model, optional
        The rig, stored as JSON.
    calibration : Calibration, optional
        Stored as JSON (``Calibration.to_dict()``).
    compression : {"none", "lz4", "gzip"}
        Filter of raw frames and depth. ``lz4`` (Blosc/LZ4, needs hdf5plugin)
        keeps up with several cameras; ``gzip`` does not (see ``stage bench capture``).
    fps : float, optional
        Nominal frame rate, recorded.
    overwrite : bool
        Replace an existing file (default: refuse). The derived file of the old take
        (masks...) is removed with it.
    block : int
        Datasets grow this many frames at a time (then trimmed on close).
    attrs : dict, optional
        Extra JSON-serializable metadata (stored in ``/meta/extra``).
    expected_sets : int, optional
        Frame sets the take is planned to hold (a capture's rate x duration); when given, the
        free disk space is checked up front and a :class:`DiskFullError` names what is needed.
    arrays : mapping of str -> ndarray, optional
        Arrays recorded with the capture (e.g. ``{"cameras/cam0/plate": background}``, the
        clean plate shot before the subject enters), stored in the take itself; names as in
        :func:`~stage.store.write_array`. Everything computed later goes to the derived file.

    Raises
    ------
    DiskFullError
        Not enough free space for ``expected_sets`` (up front), or the disk filled up while
        writing (then the take is closed with every committed set first).

    Examples
    --------
    >>> with TakeWriter("take.h5", [CameraSpec("cam0", 640, 480)], fps=30) as w:  # doctest: +SKIP
    ...     w.write_set({"cam0": frame})
    """

    def __init__(
        self,
        path: str | os.PathLike,
        cameras: Sequence[CameraSpec],
        *,
        rig: Any = None,
        calibration: Any = None,
        compression: str = "none",
        fps: float | None = None,
        overwrite: bool = False,
        block: int = 32,
        attrs: Mapping[str, Any] | None = None,
        expected_sets: int | None = None,
        arrays: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        cams, ids = _check_cameras(cameras)
        filt = filter_kwargs(compression)
        _check_numbers(block, fps, expected_sets)
        p = Path(path)
        if p.exists() and not overwrite:
            raise FileExistsError(f"{p}: take already exists (use overwrite=True / --overwrite to replace it)")
        if not p.parent.exists():
            raise FileNotFoundError(f"{p.parent}: output directory does not exist")
        self.path = p
        self.cameras = cams
        self.compression = compression
        self._set_bytes = _set_bytes(cams, compression)
        # what closing a take on a full disk may still have to write: the sets in HDF5's caches
        reserve = 2 * max(c.frame_bytes() for c in cams) * len(cams) + (1 << 20)
        if expected_sets is not None:
            need = estimate_take_bytes(cams, int(expected_sets), compression=compression) + reserve
            if overwrite and p.is_file():
                need -= p.stat().st_size  # freed before writing
            check_free_space(p, need, f"a take of {int(expected_sets)} frame sets")
        self._block = int(block)
        self._col = {c.id: i for i, c in enumerate(cams)}
        self._n = {c.id: 0 for c in cams}  # committed frames per camera
        self._jpeg_end = {c.id: 0 for c in cams}
        self._n_sets = 0
        self._closed = False
        self._warned: set[str] = set()
        if overwrite:
            for old in (p, derived_path(p)):
                if old.exists():
                    old.unlink()
        self._reserve = _Reserve(p.parent, reserve)
        try:
            self._f = self._create(p, cams, ids, rig=rig, calibration=calibration, compression=compression, fps=fps,
                                   attrs=attrs, filt=filt, arrays=_check_arrays(arrays, ids))
            # datasets stay open while writing: HDF5 writes a dataset's cached chunks when the
            # dataset is flushed or closed, and only a flush of the file reports a failed write
            # (a dataset handle closed by the garbage collector would swallow it)
            self._ds = {c.id: {name: self._f["cameras"][c.id][name] for name in self._f["cameras"][c.id]} for c in cams}
            self._sets = {name: self._f["sets"][name] for name in ("commit", "frames", "time_ns")}
            self._sync = self._f["meta"]["sync_stats"]
        except BaseException as exc:
            self._reserve.release()
            if p.exists():
                p.unlink()  # nothing was committed yet
            if is_disk_full(exc):
                raise DiskFullError(f"{p}: disk full while creating the take ({format_bytes(_HEADER_BYTES)} needed)") from None
            raise

    def _create(self, p: Path, cams: list[CameraSpec], ids: list[str], *, rig, calibration, compression, fps, attrs,
                filt, arrays) -> h5py.File:
        f = h5py.File(p, "w", libver="latest")
        try:
            wall, mono = time.time_ns(), time.monotonic_ns()
            f.attrs["format"] = FORMAT
            f.attrs["software_version"] = __version__
            f.attrs["created_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(wall / 1e9))
            f.attrs["anchor_wall_ns"] = np.int64(wall)
            f.attrs["anchor_monotonic_ns"] = np.int64(mono)
            f.attrs["fps"] = float(fps) if fps is not None else float("nan")
            f.attrs["compression"] = compression
            f.attrs["cameras"] = to_json(ids)
            f.attrs["checksums"] = "fletcher32"
            meta = f.create_group("meta")
            str_dt = h5py.string_dtype()
            meta.create_dataset("rig", data=to_json(rig) if rig is not None else "null", dtype=str_dt)
            if calibration is not None:
                cal = calibration.to_dict() if hasattr(calibration, "to_dict") else dict(calibration)
                meta.create_dataset("calibration", data=to_json(cal), dtype=str_dt)
            meta.create_dataset("extra", data=to_json(dict(attrs or {})), dtype=str_dt)
            meta.create_dataset("sync_stats", shape=(0,), maxshape=(None,), dtype=np.uint8, chunks=(4096,), **_SUM)
            sets = f.create_group("sets")
            C = len(cams)
            # commit = [n_sets, closed, frames of camera 0, 1, ...]; written last for every set
            sets.create_dataset("commit", data=np.zeros(2 + C, dtype=np.int64))
            sets.create_dataset("frames", shape=(0, C), maxshape=(None, C), dtype=np.int64, chunks=(256, C), fillvalue=-1,
                                **_SUM)
            sets.create_dataset("time_ns", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(256,), **_SUM)
            grp = f.create_group("cameras")
            for c in cams:
                g = grp.create_group(c.id)
                g.attrs.update(
                    {
                        "storage": c.storage,
                        "width": int(c.width),
                        "height": int(c.height),
                        "has_depth": bool(c.depth),
                        "column": self._col[c.id],
                        "compression": compression if c.storage == "raw" else "none",
                    }
                )
                H, W = int(c.height), int(c.width)
                if c.storage == "raw":
                    g.create_dataset("image", shape=(0, H, W, 3), maxshape=(None, H, W, 3), dtype=np.uint8,
                                     chunks=(1, H, W, 3), **filt, **_SUM)
                else:
                    g.create_dataset("jpeg", shape=(0,), maxshape=(None,), dtype=np.uint8, chunks=(256 << 10,), **_SUM)
                    g.create_dataset("jpeg_offset", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,), **_SUM)
                    g.create_dataset("jpeg_length", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,), **_SUM)
                if c.depth:
                    g.create_dataset("depth", shape=(0, H, W), maxshape=(None, H, W), dtype=np.uint16, chunks=(1, H, W),
                                     **filt, **_SUM)
                for name in ("timestamp_ns", "host_timestamp_ns", "sequence", "set_index"):
                    g.create_dataset(name, shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,), **_SUM)
                g.create_dataset("valid", shape=(0,), maxshape=(None,), dtype=np.uint8, chunks=(1024,), **_SUM)
            for key, arr in arrays.items():  # HDF5 creates no object once SWMR writing has started
                f.create_dataset(key, data=arr, **({"chunks": True, **derived_filter_kwargs(), **_SUM} if arr.ndim >= 2 else {}))
            f.swmr_mode = True
            f.flush()
        except BaseException:
            _close_file(f)
            raise
        return f

    # -- context ------------------------------------------------------------
    def __enter__(self) -> "TakeWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def n_sets(self) -> int:
        return self._n_sets

    def frame_counts(self) -> dict[str, int]:
        return dict(self._n)

    # -- writing ------------------------------------------------------------
    def _grow(self, ds: h5py.Dataset, need: int) -> None:
        if ds.shape[0] < need:
            ds.resize(max(need, ds.shape[0] + self._block), axis=0)

    def _frame_valid(self, spec: CameraSpec, frame: Frame) -> bool:
        H, W = frame.image.shape[:2]
        if (W, H) != (spec.width, spec.height):
            if spec.id not in self._warned:
                log.warning(
                    "camera %s delivered %dx%d frames, the take expects %dx%d: storing them as invalid",
                    spec.id, W, H, spec.width, spec.height,
                )
                self._warned.add(spec.id)
            return False
        return True

    def write_set(self, frames: Mapping[str, Frame | None], *, time_ns: int | None = None) -> int:
        """Store one frame set and flush; return its index.

        Parameters
        ----------
        frames : mapping of camera id -> Frame or None
            Cameras absent from the mapping, or mapped to ``None``, are missing
            in this set (row -1 in the frame-set table).
        time_ns : int, optional
            Set time on the host monotonic clock (default: median host
            timestamp of its frames).

        Raises
        ------
        DiskFullError
            The disk filled up: the take is closed with every set committed before this one.
        """
        if self._closed:
            raise ValueError(f"{self.path}: the take writer is closed")
        unknown = [c for c in frames if c not in self._col]
        if unknown:
            raise ValueError(f"frames: unknown camera ids {unknown} (take cameras: {list(self._col)})")
        for c, fr in frames.items():
            if fr is not None and not isinstance(fr, Frame):
                raise ValueError(f"frames[{c!r}] must be a Frame or None, got {type(fr).__name__}")
        try:
            return self._write_set(frames, time_ns)
        except (OSError, RuntimeError, ValueError) as exc:
            if not is_disk_full(exc):
                raise
        raise self._close_on_full_disk("frame set")

    def _write_set(self, frames: Mapping[str, Frame | None], time_ns: int | None) -> int:
        f = self._f
        k = self._n_sets
        row = np.full(len(self.cameras), -1, dtype=np.int64)
        hosts = []
        for spec in self.cameras:
            fr = frames.get(spec.id)
            if fr is None:
                continue
            self._write_frame(self._ds[spec.id], spec, fr, k)
            row[self._col[spec.id]] = self._n[spec.id]
            hosts.append(int(fr.host_timestamp_ns))
        if time_ns is None:
            time_ns = int(np.median(hosts)) if hosts else 0
        sets = self._sets
        self._grow(sets["frames"], k + 1)
        sets["frames"][k] = row
        self._grow(sets["time_ns"], k + 1)
        sets["time_ns"][k] = int(time_ns)
        f.flush()  # the set's data reaches the file before the commit counter says it exists
        for spec in self.cameras:
            if row[self._col[spec.id]] >= 0:
                self._n[spec.id] += 1
        self._n_sets += 1
        self._write_commit(closed=False)
        f.flush()
        return k

    def _write_frame(self, g: dict[str, h5py.Dataset], spec: CameraSpec, fr: Frame, k: int) -> None:
        i = self._n[spec.id]
        valid = self._frame_valid(spec, fr)
        if spec.storage == "raw":
            ds = g["image"]
            self._grow(ds, i + 1)
            if valid:
                ds[i] = fr.image
        else:
            self._write_jpeg(g, spec, fr, i, valid)
        if spec.depth:
            ds = g["depth"]
            self._grow(ds, i + 1)
            if valid and fr.depth is not None:
                ds[i] = fr.depth
        for name, v in (
            ("timestamp_ns", fr.timestamp_ns),
            ("host_timestamp_ns", fr.host_timestamp_ns),
            ("sequence", fr.index),
            ("set_index", k),
            ("valid", 1 if valid else 0),
        ):
            d = g[name]
            self._grow(d, i + 1)
            d[i] = v

    def _write_jpeg(self, g: dict[str, h5py.Dataset], spec: CameraSpec, fr: Frame, i: int, valid: bool) -> None:
        data = fr.encoded
        if data is None and valid:
            data = encode_jpeg(fr.image)
            if spec.id + ":enc" not in self._warned:
                log.info("camera %s delivered decoded frames; encoding them as JPEG for storage", spec.id)
                self._warned.add(spec.id + ":enc")
        buf = np.frombuffer(data, dtype=np.uint8) if (valid and data) else np.zeros(0, np.uint8)
        off = self._jpeg_end[spec.id]
        js = g["jpeg"]
        if js.shape[0] < off + buf.size:
            js.resize(max(off + buf.size, js.shape[0] + _JPEG_BLOCK), axis=0)
        if buf.size:
            js[off : off + buf.size] = buf
        for name, v in (("jpeg_offset", off), ("jpeg_length", buf.size)):
            self._grow(g[name], i + 1)
            g[name][i] = v
        self._jpeg_end[spec.id] = off + buf.size

    def _write_commit(self, *, closed: bool) -> None:
        commit = np.array([self._n_sets, int(closed)] + [self._n[c.id] for c in self.cameras], dtype=np.int64)
        self._sets["commit"][...] = commit

    def update_sync_stats(self, stats: Any) -> None:
        """Record sync statistics (a :class:`~stage.sync.SyncStats` or its dict); rewritable."""
        if self._closed:
            raise ValueError(f"{self.path}: the take writer is closed")
        d = stats.to_dict() if hasattr(stats, "to_dict") else dict(stats)
        buf = np.frombuffer(to_json(d).encode("utf-8"), dtype=np.uint8)
        try:
            ds = self._sync
            ds.resize(buf.size, axis=0)
            ds[:] = buf
            self._f.flush()
        except (OSError, RuntimeError, ValueError) as exc:
            if not is_disk_full(exc):
                raise
            raise self._close_on_full_disk("sync statistics") from None

    def _close_on_full_disk(self, what: str) -> DiskFullError:
        """Release the reserve, close the take with its committed sets; the error to raise."""
        self._reserve.release()
        try:
            self._finish()
            state = "closed cleanly"
        except Exception as exc:  # the reserve was not enough: the SWMR take stays readable
            log.debug("closing %s on a full disk failed: %s", self.path, exc)
            state = "left open for writing; `stage info --recover` makes a clean copy"
        finally:
            self._closed = True
            _close_file(self._f)
        return DiskFullError(
            f"{self.path}: disk full while writing a {what} (about {format_bytes(self._set_bytes)} per set); "
            f"the take keeps the {self._n_sets} frame sets stored before ({state}); free space and capture again"
        )

    def _finish(self) -> None:
        for spec in self.cameras:
            n = self._n[spec.id]
            for name, ds in self._ds[spec.id].items():
                if name == "jpeg":
                    ds.resize(self._jpeg_end[spec.id], axis=0)
                elif name in RESERVED:
                    ds.resize(n, axis=0)
        self._sets["frames"].resize(self._n_sets, axis=0)
        self._sets["time_ns"].resize(self._n_sets, axis=0)
        self._write_commit(closed=True)
        self._f.flush()

    def close(self, *, sync_stats: Any = None) -> None:
        """Trim datasets to their frame counts, mark the take complete, close the file.

        Raises
        ------
        DiskFullError
            The disk filled up while closing (the take keeps its committed sets).
        """
        if self._closed:
            return
        try:
            if sync_stats is not None:
                self.update_sync_stats(sync_stats)
            if self._closed:  # update_sync_stats hit a full disk and closed the take
                return
            self._finish()
        except (OSError, RuntimeError, ValueError) as exc:
            if not is_disk_full(exc) or isinstance(exc, DiskFullError):
                raise
            raise self._close_on_full_disk("closing record") from None
        finally:
            if not self._closed:
                self._closed = True
                _close_file(self._f)
                self._reserve.release()
