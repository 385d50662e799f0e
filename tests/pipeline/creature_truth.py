"""Ground-truth meshes and spines of the simulated creatures, for the rig/export tests.

Meshes come from marching cubes on the creature's exact signed distance
(``Pose.sdf``); spines from the true limb axes (``Pose.axes``), so these tests
do not depend on the reconstruction or the spine stage.
"""

from __future__ import annotations

import functools

import numpy as np

from fake_cameras.creatures import make_creature
from pipeline.spine_format import Spine

FPS = 30.0

# junctions of the ground-truth graph: name -> (parent junction, limbs attached there)
GRAPHS = {
    "starfish": {"j0": (None, ["arm0", "arm1", "arm2", "arm3", "arm4"])},
    "quadruped": {
        "j0": (None, []),
        "j1": ("j0", ["leg_fl", "leg_fr", "head"]),
        "j2": ("j0", ["leg_hl", "leg_hr", "tail"]),
    },
}


def surface(pose, *, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes mesh (V, 3), (F, 3) of a pose's zero level set at grid ``step`` mm."""
    from skimage.measure import marching_cubes

    lo, hi = pose.bounds()
    lo = lo - 2 * step
    hi = hi + 2 * step
    n = np.ceil((hi - lo) / step).astype(int) + 1
    axes = [lo[k] + step * np.arange(n[k]) for k in range(3)]
    vol = pose.grid_sdf(axes)
    v, f, _, _ = marching_cubes(vol, 0.0, spacing=(step, step, step))
    return v + lo, f.astype(np.int64)


def _resample(poly, n):
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    q = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(q, s, poly[:, k]) for k in range(3)], axis=1)


@functools.lru_cache(maxsize=8)
def creature_take(name: str, frames: int, *, seed: int = 0):
    """(creature, poses) of ``frames`` frames at :data:`FPS`."""
    c = make_creature(name, seed=seed)
    return c, tuple(c.pose(t / FPS) for t in range(frames))


def true_spine(name: str, poses, *, points: int = 16, hide: dict | None = None) -> Spine:
    """A :class:`Spine` from the true axes: junctions at the mean attach point of their limbs.

    ``hide`` maps a limb id to frame positions where it is null.
    """
    graph = GRAPHS[name]
    limbs = [lb for _, (_, ls) in graph.items() for lb in ls]
    juncs = list(graph)
    parents = {j: graph[j][0] for j in juncs}
    for j, (_, ls) in graph.items():
        for lb in ls:
            parents[lb] = j
    T = len(poses)
    jpos = np.zeros((T, len(juncs), 3))
    for t, p in enumerate(poses):
        for i, j in enumerate(juncs):
            ls = graph[j][1] or limbs
            jpos[t, i] = np.mean([p.axes[lb][0] for lb in ls], axis=0)
    tips = np.array([[p.tips[lb] for lb in limbs] for p in poses])
    axes = {}
    for lb in limbs:
        ji = juncs.index(parents[lb])
        axes[lb] = np.array([_resample(np.vstack([jpos[t, ji], p.axes[lb]]), points) for t, p in enumerate(poses)])
    for i, j in enumerate(juncs):
        if parents[j] is not None:
            pi = juncs.index(parents[j])
            axes[j] = np.array([_resample(np.vstack([jpos[t, pi], jpos[t, i]]), 4) for t in range(T)])
    for lb, ts in (hide or {}).items():
        k = limbs.index(lb)
        for t in ts:
            tips[t, k] = np.nan
            axes[lb][t] = np.nan
    return Spine(
        units="mm",
        fps=FPS,
        frame_indices=np.arange(T),
        limb_ids=limbs,
        junction_ids=juncs,
        parents=parents,
        tips=tips,
        junctions=jpos,
        axes=axes,
        meta={"K": len(limbs), "references": [T // 2], "tip_counts": [len(limbs)] * T},
    )


def creature_size(pose) -> float:
    """Size of a creature: the diagonal of its bounding box (mm)."""
    lo, hi = pose.bounds()
    return float(np.linalg.norm(hi - lo))
