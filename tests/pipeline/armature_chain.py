"""A straight chain of parts bound to a ring of vertices each: a small articulated model for the
armature fit's and the armature tracking's tests."""

from __future__ import annotations

import numpy as np

from pipeline.armature_fit import ArticulatedModel
from pipeline.armature_skeleton import ArticulatedSkeleton


def chain_model(parts: int = 40, per: int = 6) -> ArticulatedModel:
    """A straight chain of ``parts`` parts 10 apart (the finest segmentations give chains of tens of
    parts), ``per`` vertices on a ring around every part, each bound to its part alone."""
    J = parts + 1
    rest = np.c_[np.arange(J) * 10.0, np.zeros(J), np.zeros(J)]
    sk = ArticulatedSkeleton(names=("root", *(f"joint{i}" for i in range(1, parts)), "aux0"),
                             parents=np.arange(J) - 1, rest=rest,
                             articulation=np.r_[False, np.ones(parts - 1, bool), False], segment_pairs=(None,) * J,
                             part=np.r_[np.arange(parts), parts - 1], part_joint=np.arange(parts),
                             part_parent=np.arange(parts) - 1, bones=np.c_[np.arange(parts), np.arange(1, J)])
    angles = np.linspace(0, 2 * np.pi, per, endpoint=False)
    ring = 3.0 * np.c_[np.zeros(per), np.cos(angles), np.sin(angles)]
    v = np.concatenate([rest[p] + ring + [5.0, 0.0, 0.0] for p in range(parts)])
    return ArticulatedModel(v, np.zeros((0, 3), int), sk, np.repeat(np.arange(parts), per)[:, None], np.ones((len(v), 1)))
