"""The settings of a step's results and the start-over rule.

A step that writes results into a folder writes its settings there first (``process.json``,
``tracked/track.json``, ``carved/carve.json``): what it ran with, and digests of what it read.
A later run with the same settings keeps the results and does only what is missing; a run with
other settings removes them first (*starts over*) and says what changed. The settings are
written before any result, so a killed run's results keep theirs.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Collection
from pathlib import Path

import numpy as np

__all__ = ["array_digest", "changed_settings", "file_digest", "read_settings"]


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def array_digest(vertices: np.ndarray, faces: np.ndarray) -> str:
    """SHA-256 (hex) of a mesh's vertices and faces, as float64 and int64 (the same mesh read from
    another file format has the same digest)."""
    v = np.ascontiguousarray(vertices, np.float64).tobytes()
    return hashlib.sha256(v + np.ascontiguousarray(faces, np.int64).tobytes()).hexdigest()


def read_settings(path: str | Path) -> dict | None:
    """An earlier run's settings file, or None when there is none or it cannot be read (a run
    then starts over: nothing says its results are of these settings)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def changed_settings(old: dict, new: dict, *, results: Collection[str] = (),
                     was: Callable[[dict, str, object], object] | None = None) -> list[str]:
    """The keys of ``new`` whose value differs from ``old``'s, in ``new``'s order.

    Parameters
    ----------
    old, new : dict
        An earlier run's settings (as read back) and this run's.
    results : collection of str
        Keys that are results, not settings (a resumed run may differ in them).
    was : callable, optional
        ``was(old, key, new_value)``: the earlier value of ``key``; a step whose settings gained a
        key reads an earlier file without it as what that run did. Default ``old.get(key)``.
    """
    def before(k):
        return was(old, k, new[k]) if was is not None else old.get(k)

    return [k for k in new if k not in results and before(k) != new[k]]
