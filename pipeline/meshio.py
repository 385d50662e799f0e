"""Loading mesh sequences from other systems (OBJ, PLY, OFF via trimesh).

One file per frame, sorted by name; units are whatever the files use. Only the
largest connected part of each mesh is kept (with a warning), since the spine
of a frame is the skeleton of one creature.
"""

from __future__ import annotations

import glob
import logging
import os
from pathlib import Path

import numpy as np

from pipeline.geodesic import largest_component

__all__ = ["MESH_SUFFIXES", "mesh_paths", "load_mesh"]

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".off")


def mesh_paths(pattern) -> list[Path]:
    """The mesh files of a sequence, sorted by name.

    Parameters
    ----------
    pattern : str or Path or sequence of them
        A glob (``'DIR/*.obj'``), a directory (all ``.obj/.ply/.off`` in it)
        or explicit paths.

    Raises
    ------
    FileNotFoundError
        When nothing matches.
    """
    if isinstance(pattern, (list, tuple)):
        paths = [Path(p) for p in pattern]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            raise FileNotFoundError(f"mesh files not found: {', '.join(missing[:3])}")
    else:
        p = Path(os.path.expanduser(str(pattern)))
        if p.is_dir():
            paths = [q for q in p.iterdir() if q.suffix.lower() in MESH_SUFFIXES]
        else:
            paths = [Path(q) for q in glob.glob(str(p))]
            paths = [q for q in paths if q.is_file()]
    if not paths:
        raise FileNotFoundError(f"no mesh files match {pattern!r} (expected .obj, .ply or .off)")
    bad = [q.name for q in paths if q.suffix.lower() not in MESH_SUFFIXES]
    if bad:
        raise ValueError(f"unsupported mesh format: {bad[0]} (expected .obj, .ply or .off)")
    return sorted(paths, key=lambda q: q.name)


def load_mesh(path, *, largest: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Read one triangle mesh (vertex order kept as in the file).

    Parameters
    ----------
    path : str or Path
    largest : bool
        Keep only the largest connected part (logs a warning when more are dropped).

    Returns
    -------
    vertices : (V, 3) float64 ndarray
    faces : (F, 3) int64 ndarray
        May be empty (an empty frame).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"unsupported mesh format: {path.name} (expected .obj, .ply or .off)")
    try:
        m = trimesh.load(str(path), process=False, force="mesh")
        v = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        f = np.asarray(getattr(m, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    except (ValueError, IndexError, KeyError, TypeError, AttributeError, UnicodeDecodeError, EOFError) as exc:
        raise ValueError(
            f"cannot read mesh {path}: not a valid {path.suffix.lower().lstrip('.').upper()} triangle mesh "
            f"(damaged or another format; {type(exc).__name__})"
        ) from None
    if len(v) and not np.isfinite(v).all():
        raise ValueError(f"cannot read mesh {path}: vertex coordinates are not finite (NaN or inf)")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"cannot read mesh {path}: faces refer to vertices that do not exist")
    if len(f) == 0 or not largest:
        return v, f
    n_before = len(f)
    v2, f2, _ = largest_component(v, f, warn=False)
    if len(f2) == n_before:
        return v, f  # one part: keep the file's vertex numbering
    log.warning("%s: %d faces in other connected parts dropped (kept the largest part)", path.name, n_before - len(f2))
    return v2, f2
