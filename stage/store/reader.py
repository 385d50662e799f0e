"""Read a take: frames, timestamps, metadata, and the derived data beside it.

A closed take is opened as a plain HDF5 reader (HDF5 checks its end-of-file address); a take
that is being written, or whose writer was killed, as a SWMR reader. Only frame sets recorded in
the commit counter are visible. Any number of readers (threads or processes) may read one take
at once: nothing here opens a take for writing.

Masks and other derived per-camera arrays are read from the derived file beside the take
(:mod:`stage.store.derived`), reopened whenever a writer replaced it; takes written by older
versions, which kept masks inside the capture file, are read where their masks are.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from stage.store._format import FORMAT, RESERVED, TakeError, attr_value
from stage.store.derived import derived_path, open_derived
from stage.store.h5repair import open_h5
from stage.store.jpeg import decode_jpeg

# waits (s) before reading again a chunk that failed to read on a take still being written
_LIVE_RETRIES = (0.01, 0.03, 0.1, 0.3)

__all__ = ["TakeReader"]

log = logging.getLogger("stage.store")

_PER_FRAME = ("timestamp_ns", "host_timestamp_ns", "sequence", "valid", "set_index")


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
        self._f = open_h5(self.path, "r")
        self._derived_path = derived_path(self.path)
        self._derived: h5py.File | None = None
        self._derived_key: tuple | None = None
        self._swmr = bool(self._f.swmr_mode)
        self._complete = False  # until the commit counter is read: a live take's reads are tried again
        try:
            fmt = self._f.attrs.get("format")
            if isinstance(fmt, bytes):
                fmt = fmt.decode()
            if fmt != FORMAT:
                raise TakeError(f"{self.path}: not a capture-stage take (format attribute {fmt!r}, expected {FORMAT!r})")
            self._check_headers()
            try:
                self.cameras: list[str] = list(json.loads(self._f.attrs["cameras"]))
                self._commit_ds = self._f["sets/commit"]
                for c in self.cameras:
                    self._check_layout(c)
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

    def _check_headers(self) -> None:
        """Open every object of the take once: a damaged object header (flipped bytes in the
        file's metadata) is one :class:`TakeError` naming it here, not a ``KeyError`` later."""
        todo, where = [self._f], "/"
        try:
            while todo:
                group = todo.pop()
                where = group.name
                for key in list(group.keys()):
                    where = f"{group.name.rstrip('/')}/{key}"
                    obj = group[key]
                    if isinstance(obj, h5py.Group):
                        todo.append(obj)
        except (KeyError, OSError, ValueError, RuntimeError) as exc:
            why = str(exc).strip("'\"")
            raise TakeError(f"{self.path}: damaged take: the header of {where} cannot be read ({why})") from None

    def _check_layout(self, camera: str) -> None:
        g = self._f["cameras"][camera]
        if not isinstance(g, h5py.Group):
            raise KeyError(f"cameras/{camera} is not a group")
        need = list(_PER_FRAME) + (["image"] if g.attrs.get("storage") == "raw" else ["jpeg", "jpeg_offset", "jpeg_length"])
        missing = [n for n in need if not isinstance(g.get(n), h5py.Dataset)]
        if missing:
            raise KeyError(f"camera {camera} has no dataset {', '.join(missing)}")
        for k in ("width", "height", "storage"):
            if k not in g.attrs:
                raise KeyError(f"camera {camera} has no attribute {k!r}")

    # -- lifecycle ----------------------------------------------------------
    def __enter__(self) -> "TakeReader":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        if self._derived is not None:
            self._derived.close()
            self._derived = None
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
        except OSError as exc:
            raise TakeError(f"{self.path}: cannot read the commit counter: {exc}") from None
        commit = np.asarray(self._read(self._commit_ds, (), "the commit counter"), dtype=np.int64)
        if commit.shape != (2 + len(self.cameras),):
            raise TakeError(f"{self.path}: damaged take layout: commit counter has shape {commit.shape}")
        self._n_sets = int(commit[0])
        self._complete = bool(commit[1])
        self._counts = {c: int(commit[2 + i]) for i, c in enumerate(self.cameras)}
        if self._swmr:
            for c in self.cameras:
                g = self._f["cameras"][c]
                for name in g:
                    if name in RESERVED:
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
                # (the offsets' chunk is rewritten in place while the writer runs: read as every live read)
                end = int(self._read(g["jpeg_offset"], n - 1, f"camera {c}'s frame offsets")
                          + self._read(g["jpeg_length"], n - 1, f"camera {c}'s frame lengths"))
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
            out[k] = attr_value(v)
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
            out[k] = attr_value(v)
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
        ds = self._dataset(name)
        if ds is None:
            return None
        try:
            raw = ds[()]
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
        """The take's :class:`~calib.calibration.Calibration` (an attached one first), or None."""
        d = self._read_json("meta/calibration")
        if d is None:
            return None
        from calib.calibration import Calibration

        try:
            return Calibration.from_dict(d)
        except (ValueError, KeyError, TypeError) as exc:
            raise TakeError(f"{self.path}: stored calibration is invalid: {exc}") from None

    @property
    def checksums(self) -> bool:
        """True when every chunk of frame data carries a checksum (takes written before they
        were added have none: damage inside their frames cannot be detected)."""
        for c in self.cameras:
            g = self._f["cameras"][c]
            if any(name in g and not g[name].fletcher32 for name in ("image", "jpeg", "depth")):
                return False
        return True

    @property
    def has_calibration(self) -> bool:
        return self._dataset("meta/calibration") is not None

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
        """``ds[sel]``; a read error is a :class:`TakeError` naming ``what``.

        A take still being written shares chunks between committed and new records (the JPEG
        stream, the offsets, the set table): the writer rewrites such a chunk in place, and a
        read that meets the rewrite sees a mix of old and new bytes, which fails the chunk's
        checksum although the committed records are intact. On a live take a failed read is
        therefore tried again after a short wait (``_LIVE_RETRIES``); damage that persists is
        reported as on a closed take.
        """
        for wait in _LIVE_RETRIES if self._swmr and not self._complete else ():
            try:
                return ds[sel]
            except OSError:
                time.sleep(wait)
                ds.refresh()
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
        return decode_jpeg(np.frombuffer(data, np.uint8), f"{self.path}: {where}")

    def frames(self, camera: str, start: int, stop: int) -> np.ndarray:
        """Decoded frames ``start:stop`` (rows of the camera) as (N, H, W, 3) uint8 BGR; one
        read of the file for raw storage, where :meth:`frame` per row pays h5py's per-call cost."""
        n = self._counts[self._check_camera(camera)]
        start, stop = int(start), int(stop)
        if not 0 <= start <= stop <= n:
            raise IndexError(f"{self.path}: camera {camera}: frames {start}:{stop} out of range (0..{n})")
        g = self._f["cameras"][camera]
        if "image" in g:
            return self._read(g["image"], slice(start, stop), f"camera {camera} frames {start}:{stop}")
        W, H = self.image_size(camera)
        out = np.empty((stop - start, H, W, 3), np.uint8)
        for j, i in enumerate(range(start, stop)):
            out[j] = self.frame(camera, i)
        return out

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
        return {k: self._read(g[k], slice(0, n), f"camera {camera} {k}") for k in _PER_FRAME}

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
    def _derived_file(self) -> h5py.File | None:
        """The derived file beside the take, opened again when it was replaced since."""
        try:
            st = self._derived_path.stat()
        except OSError:
            st = None
        key = None if st is None else (st.st_ino, st.st_mtime_ns, st.st_size)
        if key != self._derived_key:
            if self._derived is not None:
                self._derived.close()
            self._derived, self._derived_key = None, key
            if st is not None and self._derived_beside_take():
                self._derived = open_derived(self._derived_path, self._identity())
        return self._derived

    def _derived_beside_take(self) -> bool:
        """A derived file that is a link to another directory is not this take's (never followed)."""
        if self._derived_path.resolve().parent == self.path.resolve().parent:
            return True
        log.warning("%s links outside the take's directory; its derived data is ignored", self._derived_path)
        return False

    def _identity(self) -> dict:
        return {k: attr_value(self._f.attrs[k]) for k in ("created_utc", "anchor_wall_ns") if k in self._f.attrs}

    def _dataset(self, key: str) -> h5py.Dataset | None:
        """``key`` from the derived file, else from the take itself (takes of the older layout)."""
        key = key.strip("/")
        d = self._derived_file()
        if d is not None and key in d:
            return d[key]
        if key in self._f and isinstance(self._f[key], h5py.Dataset) and key.rsplit("/", 1)[-1] not in RESERVED:
            return self._f[key]
        return None

    @property
    def derived_path(self) -> Path:
        """The file that holds this take's masks and other derived data (may not exist yet)."""
        return self._derived_path

    def has_array(self, group_path: str, name: str) -> bool:
        return self._dataset(f"{group_path.strip('/')}/{name}") is not None

    def read_array(self, group_path: str, name: str) -> tuple[np.ndarray, dict]:
        """A derived array and its attributes (``attrs["params"]`` decoded from JSON when present)."""
        key = f"{group_path.strip('/')}/{name}"
        ds = self._dataset(key)
        if ds is None:
            raise KeyError(f"{self.path}: no array {key!r} in this take")
        attrs = {}
        for k, v in ds.attrs.items():
            if k == "params":
                try:
                    attrs[k] = json.loads(v)
                except ValueError as exc:
                    raise TakeError(f"{self.path}: parameters of {key} are not JSON: {exc}") from None
            else:
                attrs[k] = attr_value(v)
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
        ds = self._dataset(f"cameras/{camera}/masks")
        if ds is None:
            return None
        i = int(i)
        if not 0 <= i < ds.shape[0]:
            raise IndexError(f"{self.path}: mask row {i} of camera {camera!r} out of range (0..{ds.shape[0] - 1})")
        return self._read(ds, i, f"mask {i} of {camera}").astype(bool)

    def mask_params(self, camera: str) -> dict | None:
        """The parameters stored with one camera's masks (the keyer's), None if not keyed; the
        masks themselves are not read."""
        key = f"cameras/{camera}/masks"
        ds = self._dataset(key)
        if ds is None:
            return None
        v = ds.attrs.get("params")
        if v is None:
            return None
        try:
            return json.loads(v)
        except ValueError as exc:
            raise TakeError(f"{self.path}: parameters of {key} are not JSON: {exc}") from None

    def masks_present(self) -> list[str]:
        return [c for c in self.cameras if self.has_array(f"cameras/{c}", "masks")]
