"""HDF5 take store: one file per take (layout in ``docs/take-format.md``).

This is the only capture-side module that imports :mod:`h5py`. The writer
works in SWMR mode (single writer, multiple readers): every dataset is created
up front, extended as frames arrive, and the file is flushed after every frame
set, so

* a reader (``stage info``, the pipeline) can open a take while it is written;
* a writer killed mid-take loses at most the frame set in flight: readers count
  only the sets recorded in the commit counter, which is written and flushed
  after the set's frames.

Frames are stored either raw (``(N, H, W, 3) uint8``, one frame per chunk,
optionally through a fast filter) or as the camera's own JPEG bytes exactly as
they arrived (nothing is re-encoded).

Derived per-camera data (masks from keying, background plates...) goes into a
closed take through :func:`write_array` / :func:`write_masks`, and is read back
with :meth:`TakeReader.read_array` / :meth:`TakeReader.masks`. Meshes and
spines do not belong in a take.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Literal, Mapping, Sequence

import h5py
import numpy as np

try:  # registers the Blosc/LZ4 filters with HDF5 (optional extra ``capture-stage[fast]``)
    import hdf5plugin
except ImportError:  # pragma: no cover - depends on the environment
    hdf5plugin = None

from stage import __version__
from stage.frame import Frame

__all__ = [
    "FORMAT",
    "COMPRESSIONS",
    "TakeError",
    "CameraSpec",
    "TakeWriter",
    "TakeReader",
    "write_array",
    "write_masks",
    "attach_calibration",
    "recover_take",
    "have_lz4",
]

log = logging.getLogger(__name__)

FORMAT = "capture-stage/take@1"
COMPRESSIONS = ("none", "lz4", "gzip")
_JPEG_BLOCK = 4 << 20  # grow the JPEG byte stream 4 MiB at a time
_RESERVED = {
    "image",
    "jpeg",
    "jpeg_offset",
    "jpeg_length",
    "depth",
    "timestamp_ns",
    "host_timestamp_ns",
    "sequence",
    "valid",
    "set_index",
}


class TakeError(ValueError):
    """A take file that cannot be read or written; the message names the file and the problem."""


def have_lz4() -> bool:
    """True when the Blosc/LZ4 filter (``hdf5plugin``) is available."""
    return hdf5plugin is not None


def _filter_kwargs(compression: str) -> dict:
    if compression == "none":
        return {}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 1}
    if compression == "lz4":
        if hdf5plugin is None:
            raise ValueError(
                "compression='lz4' needs the optional package hdf5plugin (pip install 'capture-stage[fast]' "
                "or pip install hdf5plugin); use compression='none' instead"
            )
        # Blosc/LZ4 with bit shuffle: the only filter here that keeps up with
        # several 640x480 cameras at 30 fps and still compresses noisy frames.
        return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.BITSHUFFLE))
    raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")


@dataclass(frozen=True)
class CameraSpec:
    """What the writer needs to know about one camera before the take starts.

    Parameters
    ----------
    id : str
        Camera id (the HDF5 group name; no ``/``).
    width, height : int
        Frame size in pixels.
    storage : {"raw", "jpeg"}
        Raw BGR frames, or the camera's JPEG bytes as delivered.
    depth : bool
        The camera delivers depth images (uint16 mm, same size).
    """

    id: str
    width: int
    height: int
    storage: Literal["raw", "jpeg"] = "raw"
    depth: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id or "/" in self.id or self.id in (".", ".."):
            raise ValueError(f"camera id must be a non-empty string without '/', got {self.id!r}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera {self.id}: width and height must be positive, got {self.width}x{self.height}")
        if self.storage not in ("raw", "jpeg"):
            raise ValueError(f"camera {self.id}: storage must be 'raw' or 'jpeg', got {self.storage!r}")


def _json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=_json_default)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    if hasattr(o, "to_dict"):
        return o.to_dict()
    raise TypeError(f"not JSON-serializable: {type(o).__name__}")


# ---------------------------------------------------------------------------
# writer


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
        Replace an existing file (default: refuse).
    block : int
        Datasets grow this many frames at a time (then trimmed on close).
    attrs : dict, optional
        Extra JSON-serializable metadata (stored in ``/meta/extra``).

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
    ) -> None:
        cams = list(cameras)
        if not cams or not all(isinstance(c, CameraSpec) for c in cams):
            raise ValueError("cameras must be a non-empty sequence of CameraSpec")
        ids = [c.id for c in cams]
        if len(set(ids)) != len(ids):
            raise ValueError(f"cameras: duplicate camera ids {ids}")
        filt = _filter_kwargs(compression)
        if int(block) < 1:
            raise ValueError(f"block must be >= 1, got {block}")
        if fps is not None and not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be positive, got {fps}")
        p = Path(path)
        if p.exists() and not overwrite:
            raise FileExistsError(f"{p}: take already exists (use overwrite=True / --overwrite to replace it)")
        if not p.parent.exists():
            raise FileNotFoundError(f"{p.parent}: output directory does not exist")
        self.path = p
        self.cameras = cams
        self.compression = compression
        self._block = int(block)
        self._col = {c.id: i for i, c in enumerate(cams)}
        self._n = {c.id: 0 for c in cams}  # committed frames per camera
        self._jpeg_end = {c.id: 0 for c in cams}
        self._n_sets = 0
        self._closed = False
        self._warned: set[str] = set()

        f = h5py.File(p, "w", libver="latest")
        self._f = f
        try:
            wall, mono = time.time_ns(), time.monotonic_ns()
            f.attrs["format"] = FORMAT
            f.attrs["software_version"] = __version__
            f.attrs["created_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(wall / 1e9))
            f.attrs["anchor_wall_ns"] = np.int64(wall)
            f.attrs["anchor_monotonic_ns"] = np.int64(mono)
            f.attrs["fps"] = float(fps) if fps is not None else float("nan")
            f.attrs["compression"] = compression
            f.attrs["cameras"] = _json(ids)
            meta = f.create_group("meta")
            str_dt = h5py.string_dtype()
            meta.create_dataset("rig", data=_json(rig) if rig is not None else "null", dtype=str_dt)
            if calibration is not None:
                cal = calibration.to_dict() if hasattr(calibration, "to_dict") else dict(calibration)
                meta.create_dataset("calibration", data=_json(cal), dtype=str_dt)
            meta.create_dataset("extra", data=_json(dict(attrs or {})), dtype=str_dt)
            meta.create_dataset("sync_stats", shape=(0,), maxshape=(None,), dtype=np.uint8, chunks=(4096,))
            sets = f.create_group("sets")
            C = len(cams)
            # commit = [n_sets, closed, frames of camera 0, 1, ...]; written last for every set
            sets.create_dataset("commit", data=np.zeros(2 + C, dtype=np.int64))
            sets.create_dataset("frames", shape=(0, C), maxshape=(None, C), dtype=np.int64, chunks=(256, C), fillvalue=-1)
            sets.create_dataset("time_ns", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(256,))
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
                    g.create_dataset("image", shape=(0, H, W, 3), maxshape=(None, H, W, 3), dtype=np.uint8, chunks=(1, H, W, 3), **filt)
                else:
                    g.create_dataset("jpeg", shape=(0,), maxshape=(None,), dtype=np.uint8, chunks=(256 << 10,))
                    g.create_dataset("jpeg_offset", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
                    g.create_dataset("jpeg_length", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
                if c.depth:
                    g.create_dataset("depth", shape=(0, H, W), maxshape=(None, H, W), dtype=np.uint16, chunks=(1, H, W), **filt)
                for name in ("timestamp_ns", "host_timestamp_ns", "sequence", "set_index"):
                    g.create_dataset(name, shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
                g.create_dataset("valid", shape=(0,), maxshape=(None,), dtype=np.uint8, chunks=(1024,))
            f.swmr_mode = True
            f.flush()
        except BaseException:
            f.close()
            raise

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
        """
        if self._closed:
            raise ValueError(f"{self.path}: the take writer is closed")
        unknown = [c for c in frames if c not in self._col]
        if unknown:
            raise ValueError(f"frames: unknown camera ids {unknown} (take cameras: {list(self._col)})")
        for c, fr in frames.items():
            if fr is not None and not isinstance(fr, Frame):
                raise ValueError(f"frames[{c!r}] must be a Frame or None, got {type(fr).__name__}")
        f = self._f
        k = self._n_sets
        row = np.full(len(self.cameras), -1, dtype=np.int64)
        hosts = []
        for spec in self.cameras:
            fr = frames.get(spec.id)
            if fr is None:
                continue
            g = f["cameras"][spec.id]
            i = self._n[spec.id]
            valid = self._frame_valid(spec, fr)
            if spec.storage == "raw":
                ds = g["image"]
                self._grow(ds, i + 1)
                if valid:
                    ds[i] = fr.image
            else:
                data = fr.encoded
                if data is None and valid:
                    data = _encode_jpeg(fr.image)
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
            row[self._col[spec.id]] = i
            hosts.append(int(fr.host_timestamp_ns))
        if time_ns is None:
            time_ns = int(np.median(hosts)) if hosts else 0
        sets = f["sets"]
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

    def _write_commit(self, *, closed: bool) -> None:
        commit = np.array([self._n_sets, int(closed)] + [self._n[c.id] for c in self.cameras], dtype=np.int64)
        self._f["sets"]["commit"][...] = commit

    def update_sync_stats(self, stats: Any) -> None:
        """Record sync statistics (a :class:`~stage.sync.SyncStats` or its dict); rewritable."""
        if self._closed:
            raise ValueError(f"{self.path}: the take writer is closed")
        d = stats.to_dict() if hasattr(stats, "to_dict") else dict(stats)
        buf = np.frombuffer(_json(d).encode("utf-8"), dtype=np.uint8)
        ds = self._f["meta"]["sync_stats"]
        ds.resize(buf.size, axis=0)
        ds[:] = buf
        self._f.flush()

    def close(self, *, sync_stats: Any = None) -> None:
        """Trim datasets to their frame counts, mark the take complete, close the file."""
        if self._closed:
            return
        try:
            if sync_stats is not None:
                self.update_sync_stats(sync_stats)
            f = self._f
            for spec in self.cameras:
                g = f["cameras"][spec.id]
                n = self._n[spec.id]
                for name in g:
                    if name == "jpeg":
                        g[name].resize(self._jpeg_end[spec.id], axis=0)
                    elif name in _RESERVED:
                        g[name].resize(n, axis=0)
            f["sets"]["frames"].resize(self._n_sets, axis=0)
            f["sets"]["time_ns"].resize(self._n_sets, axis=0)
            self._write_commit(closed=True)
            f.flush()
        finally:
            self._closed = True
            self._f.close()


def _encode_jpeg(image: np.ndarray, quality: int = 95) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    if not ok:  # pragma: no cover
        raise ValueError("could not encode frame as JPEG")
    return buf.tobytes()


def _decode_jpeg(data: np.ndarray, where: str) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.ascontiguousarray(data), cv2.IMREAD_COLOR)
    if img is None:
        raise TakeError(f"{where}: stored JPEG bytes cannot be decoded (corrupt frame)")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return img


# ---------------------------------------------------------------------------
# reader


_M32 = 0xFFFFFFFF


def _rot32(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _M32


_MIX = ((0, 2, 1, 4), (1, 0, 2, 6), (2, 1, 0, 8), (0, 2, 1, 16), (1, 0, 2, 19), (2, 1, 0, 4))


def _lookup3(data: bytes) -> int:
    """Bob Jenkins' lookup3 ``hashlittle`` with seed 0: HDF5's metadata checksum."""
    n = len(data)
    a = b = c = (0xDEADBEEF + n) & _M32
    i = 0
    while n - i > 12:
        v = [
            (a + int.from_bytes(data[i : i + 4], "little")) & _M32,
            (b + int.from_bytes(data[i + 4 : i + 8], "little")) & _M32,
            (c + int.from_bytes(data[i + 8 : i + 12], "little")) & _M32,
        ]
        for x, y, z, k in _MIX:  # x -= y; x ^= rot(y, k); y += z
            v[x] = ((v[x] - v[y]) & _M32) ^ _rot32(v[y], k)
            v[y] = (v[y] + v[z]) & _M32
        a, b, c = v
        i += 12
    rest = data[i:]
    if not rest:
        return c
    rest = rest + bytes(12 - len(rest))
    a = (a + int.from_bytes(rest[0:4], "little")) & _M32
    b = (b + int.from_bytes(rest[4:8], "little")) & _M32
    c = (c + int.from_bytes(rest[8:12], "little")) & _M32
    for x, y, k in ((2, 1, 14), (0, 2, 11), (1, 0, 25), (2, 1, 16), (0, 2, 4), (1, 0, 14), (2, 1, 24)):
        v = [a, b, c]
        v[x] ^= v[y]
        v[x] = (v[x] - _rot32(v[y], k)) & _M32
        a, b, c = v
    return c


_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _clear_killed_writer_flags(path: Path) -> bool:
    """Clear the "open for writing" flag a killed non-SWMR writer left in the superblock.

    What ``h5clear -s`` does, for the one case where no reader can open the file: the flag
    says "open for write" but not "SWMR" (e.g. a process writing masks was killed), so
    neither a plain nor a SWMR reader is allowed in. Only done when no process has the file
    open (an exclusive lock is free: HDF5 locks the files it opens, and the kernel drops the
    lock of a killed process). Superblocks of version 2 and 3 only (what h5py writes).

    Returns
    -------
    bool
        True when the flag was cleared.
    """
    import fcntl

    with open(path, "r+b") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False  # a live process has it open
        try:
            for base in (0, 512, 1024, 2048, 4096, 8192):
                fh.seek(base)
                head = fh.read(12)
                if head[:8] == _SIGNATURE:
                    break
            else:
                return False
            version, size_offsets, flags = head[8], head[9], head[11]
            if version not in (2, 3) or not flags & 0x01 or flags & 0x04:
                return False
            n = 12 + 4 * size_offsets
            fh.seek(base)
            block = bytearray(fh.read(n + 4))
            if _lookup3(bytes(block[:n])) != int.from_bytes(block[n:], "little"):
                return False  # not a superblock we understand: leave it alone
            block[11] = 0
            block[n:] = _lookup3(bytes(block[:n])).to_bytes(4, "little")
            fh.seek(base)
            fh.write(block)
            fh.flush()
            os.fsync(fh.fileno())
            return True
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _open_h5(path: Path, mode: str) -> h5py.File:
    if not path.exists():
        raise FileNotFoundError(f"{path}: take not found")
    if not path.is_file():
        raise TakeError(f"{path}: not a file")
    try:
        try:
            return _open_h5_once(path, mode)
        except OSError as exc:
            msg = str(exc).lower()
            stuck = "not already open for swmr writing" in msg or (mode != "r" and "already open for write" in msg)
            if not (stuck and _clear_killed_writer_flags(path)):
                raise
            log.warning("%s: its last writer was killed while the take was open for writing; cleared the "
                        "file's open-for-write flag (like `h5clear -s`) and opened it again", path)
            return _open_h5_once(path, mode)
    except OSError as exc:
        msg = str(exc)
        if "truncated" in msg.lower():
            raise TakeError(f"{path}: truncated take file (it ends before its own end-of-data address): {msg}") from None
        if "signature" in msg.lower() or "not an hdf5" in msg.lower():
            raise TakeError(f"{path}: not an HDF5 file (corrupt, or not a take)") from None
        if "already open for write" in msg.lower():
            raise TakeError(
                f"{path}: the take was not closed cleanly (its writer was killed, or is still writing); "
                f"it can be read but not modified: make a clean copy with `stage info --recover NEW.h5 {path}`"
            ) from None
        if "already open for read-only" in msg.lower():
            raise TakeError(f"{path}: cannot modify the take while this process has it open for reading (close the TakeReader first)") from None
        raise TakeError(f"{path}: cannot open take: {msg}") from None


def _open_h5_once(path: Path, mode: str) -> h5py.File:
    if mode == "r":
        try:
            return h5py.File(path, "r")  # a closed take: HDF5 checks its end-of-file address
        except OSError as exc:
            if "already open for write" not in str(exc).lower():
                raise
        # being written, or its writer was killed: only a SWMR reader may open it
        return h5py.File(path, "r", libver="latest", swmr=True)
    return h5py.File(path, mode)


class TakeReader:
    """Read a take (also one that is being written, or whose writer was killed).

    Only frame sets recorded in the commit counter are visible; call
    :meth:`refresh` to see sets written since opening.

    Parameters
    ----------
    path : str or Path
        The take's ``.h5`` file.

    Raises
    ------
    FileNotFoundError
        No such file.
    TakeError
        Not an HDF5 file, truncated, not a capture-stage take, or a damaged layout.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._f = _open_h5(self.path, "r")
        self._swmr = bool(self._f.swmr_mode)
        try:
            fmt = self._f.attrs.get("format")
            if isinstance(fmt, bytes):
                fmt = fmt.decode()
            if fmt != FORMAT:
                raise TakeError(f"{self.path}: not a capture-stage take (format attribute {fmt!r}, expected {FORMAT!r})")
            try:
                self.cameras: list[str] = list(json.loads(self._f.attrs["cameras"]))
                self._commit_ds = self._f["sets/commit"]
                for c in self.cameras:
                    self._f["cameras"][c]
            except (KeyError, ValueError, OSError) as exc:
                raise TakeError(f"{self.path}: damaged take layout: {exc}") from None
            self._col = {c: i for i, c in enumerate(self.cameras)}
            self.refresh()
        except TakeError:
            self._f.close()
            raise
        except (OSError, KeyError, ValueError) as exc:
            self._f.close()
            raise TakeError(f"{self.path}: damaged take (cannot read its structure): {exc}") from None
        except BaseException:
            self._f.close()
            raise

    # -- lifecycle ----------------------------------------------------------
    def __enter__(self) -> "TakeReader":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    def refresh(self) -> int:
        """Re-read the commit counter (for a take still being written); return the set count."""
        try:
            return self._refresh()
        except TakeError:
            raise
        except (OSError, KeyError) as exc:
            raise TakeError(f"{self.path}: damaged take (cannot read its structure): {exc}") from None

    def _refresh(self) -> int:
        try:
            self._commit_ds.refresh()
            commit = np.asarray(self._commit_ds[()], dtype=np.int64)
        except OSError as exc:
            raise TakeError(f"{self.path}: cannot read the commit counter: {exc}") from None
        if commit.shape != (2 + len(self.cameras),):
            raise TakeError(f"{self.path}: damaged take layout: commit counter has shape {commit.shape}")
        self._n_sets = int(commit[0])
        self._complete = bool(commit[1])
        self._counts = {c: int(commit[2 + i]) for i, c in enumerate(self.cameras)}
        if self._swmr:
            for c in self.cameras:
                g = self._f["cameras"][c]
                for name in g:
                    if name in _RESERVED:
                        g[name].refresh()
            for name in ("frames", "time_ns"):
                self._f["sets"][name].refresh()
            self._f["meta/sync_stats"].refresh()
            self._check_data_end()
        # sanity: datasets must hold at least the committed rows
        for c in self.cameras:
            g = self._f["cameras"][c]
            main = g["image"] if "image" in g else g["jpeg_offset"]
            if main.shape[0] < self._counts[c]:
                raise TakeError(
                    f"{self.path}: camera {c}: commit counter says {self._counts[c]} frames but only {main.shape[0]} are stored"
                )
        if self._f["sets/frames"].shape[0] < self._n_sets:
            raise TakeError(f"{self.path}: frame-set table shorter than the commit counter")
        return self._n_sets

    def _check_data_end(self) -> None:
        """A SWMR reader does not check the file length: make sure the committed frames lie inside it."""
        size = self.path.stat().st_size
        for c in self.cameras:
            n = self._counts[c]
            if n == 0:
                continue
            g = self._f["cameras"][c]
            checks = [(g["image"], (n - 1, 0, 0, 0))] if "image" in g else []
            if "jpeg" in g:
                end = int(g["jpeg_offset"][n - 1] + g["jpeg_length"][n - 1])
                if end:
                    checks.append((g["jpeg"], ((end - 1) // g["jpeg"].chunks[0] * g["jpeg"].chunks[0],)))
            if "depth" in g:
                checks.append((g["depth"], (n - 1, 0, 0)))
            for ds, coord in checks:
                try:
                    info = ds.id.get_chunk_info_by_coord(coord)
                except (OSError, ValueError, KeyError) as exc:
                    raise TakeError(f"{self.path}: camera {c}: cannot locate frame data: {exc}") from None
                if info.byte_offset is None or info.byte_offset + info.size > size:
                    raise TakeError(
                        f"{self.path}: truncated take file: camera {c}'s frame {n - 1} lies beyond the end of the file "
                        f"({size} bytes)"
                    )

    # -- summary ------------------------------------------------------------
    def __len__(self) -> int:
        return self._n_sets

    @property
    def n_sets(self) -> int:
        return self._n_sets

    @property
    def complete(self) -> bool:
        """True when the writer closed the take (False while writing or after a crash)."""
        return self._complete

    def frame_counts(self) -> dict[str, int]:
        """Committed frames per camera."""
        return dict(self._counts)

    def n_frames(self, camera: str) -> int:
        return self._counts[self._check_camera(camera)]

    def camera_info(self, camera: str) -> dict:
        """``storage``, ``width``, ``height``, ``has_depth``, ``compression`` of one camera."""
        g = self._f["cameras"][self._check_camera(camera)]
        out = {}
        for k, v in g.attrs.items():
            out[k] = v.item() if isinstance(v, np.generic) else v
        return out

    def image_size(self, camera: str) -> tuple[int, int]:
        """(width, height) of one camera's frames."""
        info = self.camera_info(camera)
        return int(info["width"]), int(info["height"])

    @property
    def metadata(self) -> dict:
        """Root attributes: format, software_version, created_utc, anchor pair, fps, compression..."""
        out = {}
        for k, v in self._f.attrs.items():
            out[k] = v.item() if isinstance(v, np.generic) else v
        out["cameras"] = list(self.cameras)
        extra = self._read_json("meta/extra")
        if extra:
            out["extra"] = extra
        return out

    @property
    def fps(self) -> float | None:
        v = float(self._f.attrs.get("fps", float("nan")))
        return None if not np.isfinite(v) else v

    @property
    def compression(self) -> str:
        return str(self._f.attrs.get("compression", "none"))

    def _read_json(self, name: str) -> Any:
        if name not in self._f:
            return None
        try:
            raw = self._f[name][()]
            if isinstance(raw, bytes):
                raw = raw.decode("utf-8")
            return json.loads(raw)
        except (ValueError, OSError) as exc:
            raise TakeError(f"{self.path}: cannot read {name}: {exc}") from None

    @property
    def rig(self) -> dict | None:
        return self._read_json("meta/rig")

    @property
    def calibration(self):
        """The take's :class:`~calib.calibration.Calibration`, or None."""
        d = self._read_json("meta/calibration")
        if d is None:
            return None
        from calib.calibration import Calibration

        try:
            return Calibration.from_dict(d)
        except (ValueError, KeyError, TypeError) as exc:
            raise TakeError(f"{self.path}: stored calibration is invalid: {exc}") from None

    @property
    def has_calibration(self) -> bool:
        return "meta/calibration" in self._f

    @property
    def sync_stats(self) -> dict | None:
        """Sync statistics as recorded by the writer (see :class:`stage.sync.SyncStats`), or None."""
        ds = self._f["meta/sync_stats"]
        if ds.shape[0] == 0:
            return None
        try:
            return json.loads(bytes(ds[:]).decode("utf-8"))
        except (ValueError, UnicodeDecodeError):
            return None  # being rewritten by a live writer

    @property
    def size_on_disk(self) -> int:
        return self.path.stat().st_size

    # -- frames -------------------------------------------------------------
    def _check_camera(self, camera: str) -> str:
        if camera not in self._col:
            raise KeyError(f"{self.path}: no camera {camera!r} in this take (cameras: {', '.join(self.cameras)})")
        return camera

    def _check_row(self, camera: str, i: int) -> int:
        n = self._counts[self._check_camera(camera)]
        i = int(i)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"{self.path}: camera {camera}: frame {i} out of range (0..{n - 1})")
        return i

    def storage(self, camera: str) -> str:
        return str(self._f["cameras"][self._check_camera(camera)].attrs["storage"])

    def _read(self, ds: h5py.Dataset, sel: Any, what: str) -> Any:
        try:
            return ds[sel]
        except OSError as exc:
            raise TakeError(f"{self.path}: cannot read {what}: {exc}") from None

    def frame(self, camera: str, i: int) -> np.ndarray:
        """Decoded frame ``i`` (row of the camera, not set index) as (H, W, 3) uint8 BGR."""
        i = self._check_row(camera, i)
        g = self._f["cameras"][camera]
        where = f"camera {camera} frame {i}"
        if "image" in g:
            return self._read(g["image"], i, where)
        data = self.encoded(camera, i)
        if data is None:
            W, H = self.image_size(camera)
            return np.zeros((H, W, 3), np.uint8)
        return _decode_jpeg(np.frombuffer(data, np.uint8), f"{self.path}: {where}")

    def encoded(self, camera: str, i: int) -> bytes | None:
        """The JPEG bytes of frame ``i`` as the camera delivered them (None for raw storage)."""
        i = self._check_row(camera, i)
        g = self._f["cameras"][camera]
        if "jpeg" not in g:
            return None
        where = f"camera {camera} frame {i}"
        off = int(self._read(g["jpeg_offset"], i, where))
        n = int(self._read(g["jpeg_length"], i, where))
        if n == 0:
            return None
        if off + n > g["jpeg"].shape[0]:
            raise TakeError(f"{self.path}: {where}: JPEG bytes extend past the stored stream")
        return self._read(g["jpeg"], slice(off, off + n), where).tobytes()

    def depth(self, camera: str, i: int) -> np.ndarray | None:
        """(H, W) uint16 depth in mm of frame ``i``, or None for cameras without depth."""
        i = self._check_row(camera, i)
        g = self._f["cameras"][camera]
        if "depth" not in g:
            return None
        return self._read(g["depth"], i, f"camera {camera} depth {i}")

    def timestamps(self, camera: str) -> dict[str, np.ndarray]:
        """Per-frame ``timestamp_ns``, ``host_timestamp_ns``, ``sequence``, ``valid``, ``set_index``."""
        g = self._f["cameras"][self._check_camera(camera)]
        n = self._counts[camera]
        return {k: self._read(g[k], slice(0, n), f"camera {camera} {k}") for k in ("timestamp_ns", "host_timestamp_ns", "sequence", "valid", "set_index")}

    def set_table(self) -> np.ndarray:
        """(S, C) int64: row of each camera's frame in each set, -1 when missing."""
        return self._read(self._f["sets/frames"], slice(0, self._n_sets), "frame-set table")

    def set_times(self) -> np.ndarray:
        """(S,) int64 set times on the host monotonic clock."""
        return self._read(self._f["sets/time_ns"], slice(0, self._n_sets), "frame-set times")

    def set_rows(self, k: int) -> dict[str, int]:
        """Camera -> frame row in set ``k`` (-1 = missing)."""
        k = self._check_set(k)
        row = self._read(self._f["sets/frames"], k, f"frame set {k}")
        return {c: int(row[i]) for i, c in enumerate(self.cameras)}

    def _check_set(self, k: int) -> int:
        k = int(k)
        if k < 0:
            k += self._n_sets
        if not 0 <= k < self._n_sets:
            raise IndexError(f"{self.path}: frame set {k} out of range (0..{self._n_sets - 1})")
        return k

    def frame_set(self, k: int) -> dict[str, np.ndarray | None]:
        """Camera -> decoded frame of set ``k`` (None where the camera is missing)."""
        return {c: (self.frame(c, r) if r >= 0 else None) for c, r in self.set_rows(k).items()}

    def __iter__(self) -> Iterator[dict[str, np.ndarray | None]]:
        for k in range(self._n_sets):
            yield self.frame_set(k)

    @property
    def duration_s(self) -> float:
        t = self.set_times()
        return float(t[-1] - t[0]) / 1e9 if t.size > 1 else 0.0

    def measured_fps(self) -> float | None:
        """Frame sets per second from set times."""
        t = self.set_times()
        if t.size < 2 or t[-1] <= t[0]:
            return None
        return float((t.size - 1) / ((t[-1] - t[0]) / 1e9))

    # -- derived data -------------------------------------------------------
    def has_array(self, group_path: str, name: str) -> bool:
        return f"{group_path.strip('/')}/{name}" in self._f

    def read_array(self, group_path: str, name: str) -> tuple[np.ndarray, dict]:
        """A derived array and its attributes (``attrs["params"]`` decoded from JSON when present)."""
        key = f"{group_path.strip('/')}/{name}"
        if key not in self._f:
            raise KeyError(f"{self.path}: no array {key!r} in this take")
        ds = self._f[key]
        attrs = {}
        for k, v in ds.attrs.items():
            if k == "params":
                attrs[k] = json.loads(v)
            else:
                attrs[k] = v.item() if isinstance(v, np.generic) else v
        return self._read(ds, (), key), attrs

    def masks(self, camera: str) -> np.ndarray | None:
        """(N, H, W) bool masks of one camera (rows as in :meth:`frame`), or None if not keyed."""
        self._check_camera(camera)
        if not self.has_array(f"cameras/{camera}", "masks"):
            return None
        return self.read_array(f"cameras/{camera}", "masks")[0].astype(bool)

    def mask(self, camera: str, i: int) -> np.ndarray | None:
        """(H, W) bool mask of one frame row of one camera, or None if not keyed."""
        self._check_camera(camera)
        key = f"cameras/{camera}/masks"
        if key not in self._f:
            return None
        ds = self._f[key]
        i = int(i)
        if not 0 <= i < ds.shape[0]:
            raise IndexError(f"{self.path}: mask row {i} of camera {camera!r} out of range (0..{ds.shape[0] - 1})")
        return self._read(ds, i, f"mask {i} of {camera}").astype(bool)

    def mask_params(self, camera: str) -> dict | None:
        if not self.has_array(f"cameras/{camera}", "masks"):
            return None
        return self.read_array(f"cameras/{camera}", "masks")[1].get("params")

    def masks_present(self) -> list[str]:
        return [c for c in self.cameras if self.has_array(f"cameras/{c}", "masks")]


# ---------------------------------------------------------------------------
# derived data in a closed take


def write_array(
    path: str | os.PathLike,
    group_path: str,
    name: str,
    array: np.ndarray,
    *,
    attrs: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    compress: bool = True,
    overwrite: bool = True,
) -> None:
    """Store a derived array (masks, a background plate...) inside a closed take.

    Parameters
    ----------
    path : str or Path
        The take.
    group_path : str
        Group inside the take, e.g. ``"cameras/cam00"`` or ``"derived"``;
        created if needed.
    name : str
        Dataset name; capture datasets (``image``, ``timestamp_ns``...) are reserved.
    array : ndarray
        Arrays with 3 or more dimensions are chunked one leading index per chunk.
    attrs : dict, optional
        Scalar/str attributes.
    params : dict, optional
        JSON-serializable parameters, stored as ``attrs["params"]``.
    compress : bool
        Compress (LZ4 when available, else gzip level 1).
    overwrite : bool
        Replace an existing dataset of that name.
    """
    if not isinstance(name, str) or not name or "/" in name:
        raise ValueError(f"name must be a non-empty string without '/', got {name!r}")
    if name in _RESERVED:
        raise ValueError(f"name {name!r} is reserved for captured data")
    if not isinstance(group_path, str):
        raise ValueError(f"group_path must be a string, got {type(group_path).__name__}")
    arr = np.asarray(array)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"array must be numeric or bool, got dtype {arr.dtype}")
    p = Path(path)
    # check it is a take first (clear error for a corrupt or crashed file)
    TakeReader(p).close()
    f = _open_h5(p, "r+")
    try:
        grp = f.require_group(group_path.strip("/")) if group_path.strip("/") else f
        if name in grp:
            if not overwrite:
                raise ValueError(f"{p}: {group_path}/{name} exists (overwrite=False)")
            del grp[name]
        kw: dict[str, Any] = {}
        if arr.ndim >= 2 and arr.size:
            kw["chunks"] = (1,) + arr.shape[1:] if arr.ndim >= 3 else arr.shape
            if compress:
                kw.update(_filter_kwargs("lz4") if hdf5plugin is not None else {"compression": "gzip", "compression_opts": 1})
        ds = grp.create_dataset(name, data=arr, **kw)
        if np.asarray(array).dtype == bool:
            ds.attrs["bool"] = True
        for k, v in (attrs or {}).items():
            ds.attrs[k] = v
        if params is not None:
            ds.attrs["params"] = _json(dict(params))
    finally:
        f.close()


def write_masks(path: str | os.PathLike, camera: str, masks: np.ndarray, params: Mapping[str, Any] | None = None) -> None:
    """Store keying masks of one camera: (N, H, W) bool, one per frame row of that camera."""
    with TakeReader(path) as r:
        if camera not in r.cameras:
            raise ValueError(f"camera {camera!r} is not in the take (cameras: {', '.join(r.cameras)})")
        n = r.n_frames(camera)
        W, H = r.image_size(camera)
    m = np.asarray(masks)
    if m.ndim != 3 or m.shape != (n, H, W):
        raise ValueError(f"masks must have shape (N, H, W) = ({n}, {H}, {W}) for camera {camera}, got {m.shape}")
    write_array(path, f"cameras/{camera}", "masks", m.astype(bool), params=params or {})


def attach_calibration(path: str | os.PathLike, calibration: Any) -> None:
    """Store (or replace) the calibration of a closed take."""
    if not hasattr(calibration, "to_dict"):
        raise ValueError("calibration must be a Calibration")
    with TakeReader(path) as r:
        missing = [c for c in r.cameras if c not in calibration.names]
    if missing:
        log.warning("calibration has no camera named %s", ", ".join(missing))
    f = _open_h5(Path(path), "r+")
    try:
        if "meta/calibration" in f:
            del f["meta/calibration"]
        f["meta"].create_dataset("calibration", data=_json(calibration.to_dict()), dtype=h5py.string_dtype())
    finally:
        f.close()


def recover_take(src: str | os.PathLike, dst: str | os.PathLike, *, overwrite: bool = False) -> int:
    """Copy the committed part of a take (e.g. one whose writer was killed) into a clean, closed take.

    Returns the number of frame sets copied.
    """
    src, dst = Path(src), Path(dst)
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst}: exists (use overwrite)")
    if dst.resolve() == src.resolve():
        raise ValueError("dst must differ from src")
    with TakeReader(src) as r:
        counts = r.frame_counts()
        n_sets = r.n_sets
        fin = r._f
        jpeg_end = {}
        for c in r.cameras:
            g = fin["cameras"][c]
            n = counts[c]
            jpeg_end[c] = int(g["jpeg_offset"][n - 1] + g["jpeg_length"][n - 1]) if ("jpeg" in g and n) else 0
        with h5py.File(dst, "w", libver="latest") as out:
            for k, v in fin.attrs.items():
                out.attrs[k] = v
            for name in ("meta", "sets", "cameras"):
                fin.copy(fin[name], out, name)
            out["sets/frames"].resize(n_sets, axis=0)
            out["sets/time_ns"].resize(n_sets, axis=0)
            out["sets/commit"][...] = np.array([n_sets, 1] + [counts[c] for c in r.cameras], dtype=np.int64)
            for c in r.cameras:
                g = out["cameras"][c]
                for name in g:
                    if name == "jpeg":
                        g[name].resize(jpeg_end[c], axis=0)
                    elif name in _RESERVED:
                        g[name].resize(counts[c], axis=0)
    return n_sets
