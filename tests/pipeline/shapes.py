"""Small test meshes several test files share: a capsule with roughly uniform edges, a capsule whose
top forks into two near-equal bumps, and a bar hinged at its middle over a take."""

from __future__ import annotations

import numpy as np
import trimesh


def capsule(height=3.0):
    """A capsule with roughly uniform edges (trimesh's has only end rings on the cylinder)."""
    m = trimesh.creation.capsule(height=height, radius=0.5, count=[16, 16])
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=0.2)
    return trimesh.Trimesh(v, f)


def forked_capsule(heights=(0.45, 0.43), b_offset=(0.0, 0.0)):
    """A capsule whose top end forks into two bumps of near-equal height (by default 0.45 and
    0.43 of its radius-0.5 body; bump A at x = 0.28, bump B at x = -0.28 moved by ``b_offset``
    in x, y): one limb ending in two near-equal maxima, like a horse's nose and ears."""
    m = capsule()
    v = np.asarray(m.vertices).copy()
    top = v[:, 2] > 1.4
    for (cx, cy), a in (((0.28, 0.0), heights[0]), ((-0.28 + b_offset[0], b_offset[1]), heights[1])):
        v[:, 2] += a * top * np.exp(-((v[:, 0] - cx) ** 2 + (v[:, 1] - cy) ** 2) / 0.12**2)
    return v, np.asarray(m.faces)


def two_bars(T=12):
    """A bar hinged at its middle (the origin); the right half turns by up to 60 degrees (mm)."""
    m = trimesh.creation.box(extents=(200, 20, 20))
    for _ in range(4):
        m = m.subdivide()
    v0 = np.asarray(m.vertices)
    right = v0[:, 0] > 0
    frames = []
    for ang in np.linspace(0, np.pi / 3, T):
        c, s = np.cos(ang), np.sin(ang)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        v = v0.copy()
        v[right] = v0[right] @ R.T
        frames.append(v)
    return np.asarray(frames), np.asarray(m.faces), right
