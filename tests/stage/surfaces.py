"""Random surfaces written as a results directory's PLY meshes, for the benches' `--copies` tests."""

from __future__ import annotations

import numpy as np


def random_surfaces(folder, name: str, *, T: int = 3, V: int) -> np.ndarray:
    """``T`` surfaces of ``V`` vertices drawn from N(0, 100 mm) (``default_rng(0)``), one face each, written to
    ``folder`` (made) as ``name.format(t)``; -> their vertices, (T, V, 3)."""
    from pipeline.results import ply_bytes

    folder.mkdir(parents=True)
    verts = np.random.default_rng(0).normal(scale=100.0, size=(T, V, 3))
    for t in range(T):
        (folder / name.format(t)).write_bytes(ply_bytes(verts[t], np.array([[0, 1, 2]])))
    return verts
