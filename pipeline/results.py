"""Results store: per-frame meshes beside the take, never inside it.

The capture file stays as recorded; everything computed from it goes to a directory::

    DIR/
      meshes/frame_000123.ply  binary PLY (what MeshLab, Blender, trimesh and the API serve)
      export/frame_000123.glb  on request (export), also .ply

The take's ``report.json`` (steps, timings, per-frame quality) in the same directory belongs
to :func:`pipeline.process.process_take`, which writes it.

Plain files and numpy only (no HDF5 here: only the ``stage.store`` package touches HDF5). Every write
goes to a temporary file in the same directory and is moved into place with ``os.replace``,
so a killed process leaves either the old file or the new one, never half a file.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from calib.fileio import atomic_write as atomic_write_bytes  # the project's one atomic write (fsyncs the folder too)

__all__ = ["ResultsStore", "atomic_write_bytes", "ply_bytes"]

_FRAME_RE = re.compile(r"^frame_(\d{6,})\.ply$")
_EXPORT_FORMATS = ("ply", "glb")


def ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """Binary little-endian PLY with double-precision vertices (exact round trip).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    """
    v = np.ascontiguousarray(vertices, dtype="<f8")
    f = np.asarray(faces)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment capture-stage\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    rec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"] = 3
    rec["i"] = f
    return header + v.tobytes() + rec.tobytes()


def _check_frame(frame: Any) -> int:
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or frame < 0:
        raise ValueError(f"frame must be a non-negative integer, got {frame!r}")
    return int(frame)


class ResultsStore:
    """A directory of per-frame results for one processed take.

    Parameters
    ----------
    path : str or Path
        The results directory (created on first write). Keep it beside the take, e.g.
        ``takes/walk.h5`` -> ``takes/walk.results/``.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        if not isinstance(path, (str, os.PathLike)) or str(path) == "":
            raise ValueError(f"path must be a directory path, got {path!r}")
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"path {str(self.path)!r} exists and is not a directory")

    # -- layout ---------------------------------------------------------------------------------
    @property
    def mesh_dir(self) -> Path:
        return self.path / "meshes"

    def mesh_path(self, frame: int) -> Path:
        return self.mesh_dir / f"frame_{_check_frame(frame):06d}.ply"

    # -- meshes ---------------------------------------------------------------------------------
    def write_mesh(self, frame: int, mesh) -> Path:
        """Store the mesh of ``frame`` (replaces any previous one).

        Parameters
        ----------
        frame : int
        mesh : trimesh.Trimesh, or a pair ``(vertices (V, 3), faces (F, 3))``
        """
        frame = _check_frame(frame)
        if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            v, f = mesh.vertices, mesh.faces
        elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
            v, f = mesh
        else:
            raise ValueError("mesh must be a trimesh.Trimesh or a (vertices, faces) pair")
        v = np.asarray(v, dtype=np.float64)
        f = np.asarray(f)
        if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
            raise ValueError(f"mesh vertices must be finite (V, 3), got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"mesh faces must be integer (F, 3), got shape {f.shape} dtype {f.dtype}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError("mesh faces index vertices that do not exist")
        return atomic_write_bytes(self.mesh_path(frame), ply_bytes(v, f))

    def read_mesh(self, frame: int):
        """The stored mesh of ``frame`` as a ``trimesh.Trimesh``.

        Raises
        ------
        KeyError
            No mesh stored for that frame.
        """
        import trimesh

        p = self.mesh_path(frame)
        if not p.is_file():
            raise KeyError(f"no mesh for frame {frame} in {self.path}")
        return trimesh.load(p, file_type="ply", process=False, force="mesh")

    def frames(self) -> list[int]:
        """Frames that have a mesh, sorted."""
        if not self.mesh_dir.is_dir():
            return []
        out = []
        for p in self.mesh_dir.iterdir():
            m = _FRAME_RE.match(p.name)
            if m:
                out.append(int(m.group(1)))
        return sorted(out)

    def export(self, frame: int, fmt: str = "ply", path: str | os.PathLike | None = None) -> Path:
        """Export the mesh of ``frame`` to PLY (binary) or GLB.

        Parameters
        ----------
        frame : int
        fmt : {"ply", "glb"}
        path : str or Path, optional
            Destination; default ``DIR/export/frame_000123.<fmt>``.

        Returns
        -------
        Path
            The written file.
        """
        if fmt not in _EXPORT_FORMATS:
            raise ValueError(f"fmt must be one of {_EXPORT_FORMATS}, got {fmt!r}")
        mesh = self.read_mesh(frame)
        data = mesh.export(file_type=fmt)
        if isinstance(data, str):
            data = data.encode()
        dest = Path(path) if path is not None else self.path / "export" / f"frame_{int(frame):06d}.{fmt}"
        return atomic_write_bytes(dest, data)

    def __repr__(self) -> str:
        return f"ResultsStore({str(self.path)!r})"

