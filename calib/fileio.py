"""Writing files so that a crash never leaves half of one, and numpy values in JSON.

:func:`atomic_write` writes a temporary file in the target's folder, flushes it to the disk
(``fsync``), moves it over the target (``os.replace``, atomic on POSIX) and flushes the folder,
so that after a crash or power cut the target holds either its old or its new bytes, and the new
name survives. :func:`replace_durably` does the same for a temporary file another library wrote
(OpenCV's ``FileStorage``, ``numpy.savez``, a copy). :func:`json_default` is the one
``json.dumps(default=...)`` for numpy scalars and arrays.

They live on the lowest floor (``calib``, floor 0; docs/architecture.md) so that every package
can use them, the calibration file formats included. The standard library has no atomic write
that also flushes the folder, hence these few lines.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write", "replace_durably", "fsync_dir", "json_default", "json_ready", "plain", "strict_json"]


def fsync_dir(folder: str | os.PathLike) -> None:
    """Flush a folder's entries (a new or renamed file's name) to the disk; a no-op where the
    system cannot open a folder for that."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def replace_durably(tmp: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Move the finished file ``tmp`` over ``path`` (same folder): ``tmp`` flushed to the disk, then
    ``os.replace``, then the folder flushed. Returns ``path``."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(Path(path).parent)
    return Path(path)


def atomic_write(path: str | os.PathLike, data: bytes | str, *, parents: bool = True) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` atomically and durably.

    Parameters
    ----------
    path : path
    data : bytes or str
    parents : bool, optional
        Create the folder (default); else a missing folder is a ``FileNotFoundError``.

    Returns
    -------
    Path
        ``path``.
    """
    if not isinstance(data, (bytes, bytearray, memoryview, str)):
        raise ValueError(f"data must be bytes or str, got {type(data).__name__}")
    path = Path(path)
    if parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data.encode("utf-8") if isinstance(data, str) else data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    fsync_dir(path.parent)
    return path


def json_default(o: Any) -> Any:
    """``json.dumps(..., default=json_default)``: numpy scalars as Python numbers, arrays as lists, paths
    as strings, and records as their dicts (``model_dump(mode="json")``, ``to_dict()``, a dataclass)."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    if hasattr(o, "to_dict"):
        return o.to_dict()
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return dataclasses.asdict(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def json_ready(x: Any) -> Any:
    """``x`` as JSON reads it back after ``json.dumps(x, default=json_default)``: plain dicts, lists,
    numbers and strings, records included (for a value kept or handed to another serializer)."""
    return json.loads(json.dumps(x, default=json_default))


def plain(x: Any, *, finite: bool = False) -> Any:
    """``x`` with every numpy value made a Python one, through dicts (keys as strings), lists and
    tuples (as lists): what :func:`json_default` does at ``json.dumps`` time, for a value kept.
    ``finite=True`` also makes a non-finite float ``None`` (JSON ``null``, where a format says so)."""
    if isinstance(x, dict):
        return {str(k): plain(v, finite=finite) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v, finite=finite) for v in x]
    if isinstance(x, np.ndarray):
        return plain(x.tolist(), finite=True) if finite else x.tolist()
    if isinstance(x, np.generic):
        x = x.item()
    if finite and isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def strict_json(x: Any, *, indent: int | None = 1) -> str:
    """``x`` as strict JSON text, as browsers' ``JSON.parse`` and other tools read it: numpy values plain, a
    non-finite number (a figure with nothing to measure) ``null`` rather than ``NaN``, and any other object
    through :func:`json_default` (else its ``str``)."""

    def default(o: Any) -> Any:
        try:
            return plain(json_default(o), finite=True)
        except TypeError:
            return str(o)

    return json.dumps(plain(x, finite=True), indent=indent, default=default, allow_nan=False)
