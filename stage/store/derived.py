"""Derived data of a take (masks, background plates, an attached calibration), beside the take.

A take is written once: nothing after capture or import opens the capture file for writing.
Everything computed from it later goes to ``TAKE.derived.h5`` next to ``TAKE.h5``, with the
take's layout (``cameras/<id>/<name>``, ``meta/calibration``), and :class:`~stage.store.TakeReader`
presents it as if it were part of the take.

Every update is atomic: the new derived file is built in memory (the arrays kept from the old
one plus the new one), written to a temporary file in the same directory with plain file I/O,
flushed to disk and renamed over the old file. A crash, a kill or a full disk at any point leaves the old derived file (and the
take, which is never opened for writing) as they were; a reader that has the old file open
keeps reading it. Updates of takes in one directory are serialized with an exclusive ``flock``
on the directory, so two jobs keying one take at once both land their arrays; readers never wait.
The derived file records which take it belongs to (the take's creation stamp): a derived file
left from an older take of the same name is ignored.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import logging
import os
import threading
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import h5py
import numpy as np

from stage.store._format import DERIVED_FORMAT, RESERVED, TakeError, attr_value, derived_filter_kwargs, to_json
from stage.store.space import check_free_space, format_bytes, raise_disk_full

__all__ = ["derived_path", "open_derived", "write_array", "write_arrays", "write_masks", "attach_calibration"]

log = logging.getLogger("stage.store")

DERIVED_SUFFIX = ".derived.h5"
_MARGIN = 64 << 10  # metadata of a derived file, generously


def derived_path(take: str | os.PathLike) -> Path:
    """``dir/TAKE.h5`` -> ``dir/TAKE.derived.h5``."""
    p = Path(take)
    stem = p.name[: -len(".h5")] if p.name.endswith(".h5") else p.name
    return p.with_name(stem + DERIVED_SUFFIX)


def open_derived(path: Path, identity: Mapping[str, Any]) -> h5py.File | None:
    """Open a derived file for reading; None (with a warning) when it belongs to another take or is unreadable."""
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        log.warning("%s: cannot read the derived data (%s); ignoring it", path, exc)
        return None
    if not _belongs(f, identity):
        log.warning("%s: derived data of an older take of the same name; ignoring it", path)
        f.close()
        return None
    return f


def _belongs(f: h5py.File, identity: Mapping[str, Any]) -> bool:
    if attr_value(f.attrs.get("format")) not in (DERIVED_FORMAT, DERIVED_FORMAT.encode()):
        return False
    return all(attr_value(f.attrs.get("take_" + k)) == v for k, v in identity.items())


_thread_lock = threading.Lock()


@contextlib.contextmanager
def _directory_lock(directory: Path) -> Iterator[None]:
    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # drops the lock


def _copy_except(src: h5py.Group, dst: h5py.Group, skip: str, prefix: str = "") -> None:
    for name, obj in src.items():
        full = prefix + name
        if full == skip:
            continue
        if isinstance(obj, h5py.Group):
            _copy_except(obj, dst.require_group(name), skip, full + "/")
        else:
            src.copy(obj, dst, name)


def _update(take: Path, key: str, put: Callable[[h5py.File], None], *, nbytes: int, what: str) -> None:
    """Replace the derived file of ``take`` by a copy in which ``put`` wrote ``key``."""
    from stage.store.reader import TakeReader

    with TakeReader(take) as r:
        if not r.complete:
            raise TakeError(
                f"{take}: the take was not closed cleanly (its writer was killed, or is still writing); "
                f"make a clean copy with `stage info --recover NEW.h5 {take}` first"
            )
        identity = r._identity()
    dp = derived_path(take)
    tmp = dp.with_name(f".{dp.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with _thread_lock, _directory_lock(dp.parent):
        old = open_derived(dp, identity) if dp.exists() else None
        need = (dp.stat().st_size if old is not None else 0) + nbytes + _MARGIN
        try:
            with raise_disk_full(dp, what, need, detail="the take and its earlier derived data are unchanged"):
                check_free_space(dp, need, what)
                # built in memory, then written with plain file I/O: a full disk fails that write
                # cleanly, never HDF5's own flush of a half-written file
                buf = io.BytesIO()
                with h5py.File(buf, "w") as out:
                    out.attrs["format"] = DERIVED_FORMAT
                    out.attrs["take"] = take.name
                    for k, v in identity.items():
                        out.attrs["take_" + k] = v
                    if old is not None:
                        _copy_except(old, out, key)
                    put(out)
                with open(tmp, "wb") as fh:
                    fh.write(buf.getbuffer())
                    fh.flush()
                    os.fsync(fh.fileno())
                del buf
                os.replace(tmp, dp)
                _fsync_dir(dp.parent)
        finally:
            if old is not None:
                old.close()
            if tmp.exists():
                tmp.unlink()


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - some filesystems refuse
        pass
    finally:
        os.close(fd)


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
    """Store a derived array (masks, a background plate...) of a closed take, in its derived file.

    Parameters
    ----------
    path : str or Path
        The take (its ``TAKE.derived.h5`` is written, never the take).
    group_path : str
        Group, e.g. ``"cameras/cam00"`` or ``"derived"``; created if needed.
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
        Replace an existing array of that name.

    Raises
    ------
    DiskFullError
        Not enough space (the take and the old derived file stay as they were).
    TakeError
        Not a take, or a take whose writer did not close it.
    """
    if not isinstance(name, str) or not name or "/" in name:
        raise ValueError(f"name must be a non-empty string without '/', got {name!r}")
    if name in RESERVED:
        raise ValueError(f"name {name!r} is reserved for captured data")
    if not isinstance(group_path, str):
        raise ValueError(f"group_path must be a string, got {type(group_path).__name__}")
    group = group_path.strip("/")
    if group.split("/")[0] == "meta":
        raise ValueError("group_path 'meta' is reserved for the take's metadata")
    arr = np.asarray(array)
    is_bool = arr.dtype == bool
    if is_bool:
        arr = arr.astype(np.uint8)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"array must be numeric or bool, got dtype {arr.dtype}")
    p = Path(path)
    key = f"{group}/{name}" if group else name
    if not overwrite:
        from stage.store.reader import TakeReader

        with TakeReader(p) as r:
            if r._derived_file() is not None and key in r._derived_file():
                raise ValueError(f"{p}: {key} exists (overwrite=False)")

    def put(out: h5py.File) -> None:
        grp = out.require_group(group) if group else out
        kw: dict[str, Any] = {}
        if arr.ndim >= 2 and arr.size:
            kw["chunks"] = (1,) + arr.shape[1:] if arr.ndim >= 3 else arr.shape
            if compress:
                kw.update(derived_filter_kwargs())
            kw["fletcher32"] = True  # a damaged chunk is an error on read, not wrong masks
        ds = grp.create_dataset(name, data=arr, **kw)
        if is_bool:
            ds.attrs["bool"] = True
        for k, v in (attrs or {}).items():
            ds.attrs[k] = v
        if params is not None:
            ds.attrs["params"] = to_json(dict(params))

    # compressed masks take a small fraction of their bytes; the estimate only guards the obvious
    expect = arr.nbytes if not compress else arr.nbytes // (16 if is_bool else 2)
    _update(p, key, put, nbytes=expect, what=f"{key} of {p.name} ({format_bytes(expect)})")


def write_masks(path: str | os.PathLike, camera: str, masks: np.ndarray, params: Mapping[str, Any] | None = None) -> None:
    """Store keying masks of one camera: (N, H, W) bool, one per frame row of that camera."""
    from stage.store.reader import TakeReader

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
    """Store (or replace) the calibration of a closed take (in its derived file; readers prefer it)."""
    from stage.store.reader import TakeReader

    if not hasattr(calibration, "to_dict"):
        raise ValueError("calibration must be a Calibration")
    with TakeReader(path) as r:
        missing = [c for c in r.cameras if c not in calibration.names]
    if missing:
        log.warning("calibration has no camera named %s", ", ".join(missing))
    text = to_json(calibration.to_dict())

    def put(out: h5py.File) -> None:
        out.require_group("meta").create_dataset("calibration", data=text, dtype=h5py.string_dtype())

    _update(Path(path), "meta/calibration", put, nbytes=len(text), what=f"the calibration of {Path(path).name}")


def write_arrays(path: str | os.PathLike, arrays: Sequence[tuple[str, str, np.ndarray, Mapping[str, Any] | None]]) -> None:
    """Store several derived arrays in one update of the derived file (one copy, one flush).

    ``arrays`` holds ``(group_path, name, array, params)`` as :func:`write_array` takes them
    (compressed, arrays of 3 or more dimensions chunked one leading index per chunk; existing
    arrays of those names replaced). Keying every camera of a take stores its masks this way:
    one update instead of two per camera, each of which copies the derived file.
    """
    items = []
    for group_path, name, array, params in arrays:
        if not isinstance(name, str) or not name or "/" in name or name in RESERVED:
            raise ValueError(f"name must be a non-reserved string without '/', got {name!r}")
        group = str(group_path).strip("/")
        if group.split("/")[0] == "meta":
            raise ValueError("group_path 'meta' is reserved for the take's metadata")
        arr = np.asarray(array)
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"array must be numeric or bool, got dtype {arr.dtype}")
        items.append((group, name, arr, params))
    if not items:
        return

    def put(out: h5py.File) -> None:
        for group, name, arr, params in items:
            grp = out.require_group(group) if group else out
            if name in grp:
                del grp[name]
            kw: dict[str, Any] = {}
            if arr.ndim >= 2 and arr.size:
                kw = {"chunks": (1,) + arr.shape[1:] if arr.ndim >= 3 else arr.shape, **derived_filter_kwargs(),
                      "fletcher32": True}
            ds = grp.create_dataset(name, data=arr.view(np.uint8) if arr.dtype == bool else arr, **kw)  # no copy
            if arr.dtype == bool:
                ds.attrs["bool"] = True
            if params is not None:
                ds.attrs["params"] = to_json(dict(params))

    p = Path(path)
    expect = sum(a.nbytes // (16 if a.dtype == bool else 2) for _, _, a, _ in items)
    first = f"{items[0][0]}/{items[0][1]}"
    _update(p, first, put, nbytes=expect, what=f"{len(items)} arrays of {p.name} ({format_bytes(expect)})")
