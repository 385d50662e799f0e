"""The spine of a take and its file, ``capture-stage/spine@1`` (docs/spine-format.md).

:class:`Spine` is one fixed graph (limbs, junctions, parents) and its pose in every frame;
:func:`write_spine` / :func:`read_spine` write and read it as JSON, and
:func:`validate_spine_dict` checks a parsed file (:class:`SpineFormatError` naming the place).
Non-finite values are written as ``null`` (an unseen tip, junction or axis): part of the format.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.fileio import plain

__all__ = ["FORMAT", "Spine", "write_spine", "read_spine", "validate_spine_dict", "SpineFormatError"]

FORMAT = "capture-stage/spine@1"


@dataclass
class Spine:
    """One spine for a take: a fixed graph and its pose in every frame.

    Attributes
    ----------
    units : str
    fps : float
    frame_indices : (T,) int ndarray
    limb_ids : list of str
        One per limb tip (``limb0``, ...), in correspondence order.
    junction_ids : list of str
    parents : dict of str to str or None
        Parent junction of every limb and junction (the root junction: None).
    tips : (T, K, 3) float ndarray
        nan where a limb was not seen.
    junctions : (T, J, 3) float ndarray
    axes : dict of str to (T, n, 3) float ndarray
        For every limb and every non-root junction, the polyline from its
        parent junction to it, resampled to ``n`` points (nan rows = unseen).
    meta : dict
        ``K``, reference frames, topology splits, tip counts, ...
    """

    units: str
    fps: float
    frame_indices: np.ndarray
    limb_ids: list
    junction_ids: list
    parents: dict
    tips: np.ndarray
    junctions: np.ndarray
    axes: dict
    meta: dict = field(default_factory=dict)

    @property
    def K(self) -> int:
        return len(self.limb_ids)

    @property
    def frame_count(self) -> int:
        return len(self.frame_indices)

    @property
    def root(self) -> str:
        return next(k for k, p in self.parents.items() if p is None)

    def to_dict(self) -> dict:
        def pt(x):
            return [float(c) for c in x] if np.all(np.isfinite(x)) else None

        frames = []
        for t, idx in enumerate(self.frame_indices):
            frames.append(
                {
                    "index": int(idx),
                    "tips": {lid: pt(self.tips[t, k]) for k, lid in enumerate(self.limb_ids)},
                    "junctions": {jid: pt(self.junctions[t, j]) for j, jid in enumerate(self.junction_ids)},
                    "axes": {
                        name: (a[t].tolist() if np.all(np.isfinite(a[t])) else None) for name, a in self.axes.items()
                    },
                }
            )
        return {
            "format": FORMAT,
            "units": self.units,
            "fps": float(self.fps),
            "frame_count": self.frame_count,
            "graph": {
                "limbs": list(self.limb_ids),
                "junctions": list(self.junction_ids),
                "root": self.root,
                "parents": dict(self.parents),
            },
            "frames": frames,
            "meta": plain(self.meta, finite=True),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Spine":
        validate_spine_dict(d)
        g = d["graph"]
        limbs, juncs = list(g["limbs"]), list(g["junctions"])
        frames = d["frames"]
        T = len(frames)

        def arr(x, n=3):
            return np.full(n, np.nan) if x is None else np.asarray(x, dtype=np.float64)

        tips = np.array([[arr(fr["tips"][k]) for k in limbs] for fr in frames]).reshape(T, len(limbs), 3)
        jun = np.array([[arr(fr.get("junctions", {}).get(j)) for j in juncs] for fr in frames]).reshape(
            T, len(juncs), 3
        )
        axes = {}
        names = [n for n in limbs + juncs if g["parents"][n] is not None]
        for name in names:
            n = max((len(fr["axes"][name]) for fr in frames if fr["axes"].get(name) is not None), default=0)
            a = np.full((T, n, 3), np.nan)
            for t, fr in enumerate(frames):
                if fr["axes"].get(name) is not None:
                    a[t] = np.asarray(fr["axes"][name], dtype=np.float64)
            axes[name] = a
        return cls(
            units=d["units"],
            fps=float(d["fps"]),
            frame_indices=np.array([fr["index"] for fr in frames], dtype=np.int64),
            limb_ids=limbs,
            junction_ids=juncs,
            parents=dict(g["parents"]),
            tips=tips,
            junctions=jun,
            axes=axes,
            meta=dict(d.get("meta", {})),
        )


class SpineFormatError(ValueError):
    """A spine file that does not follow ``capture-stage/spine@1``."""


def _check_point(x, where):
    if x is None:
        return
    if not (isinstance(x, list) and len(x) == 3 and all(isinstance(c, (int, float)) for c in x)):
        raise SpineFormatError(f"{where}: expected [x, y, z] or null")
    if not all(math.isfinite(c) for c in x):
        raise SpineFormatError(f"{where}: coordinates must be finite")


def _check_header(d) -> None:
    if not isinstance(d, dict):
        raise SpineFormatError("spine must be a JSON object")
    if d.get("format") != FORMAT:
        raise SpineFormatError(f"format must be {FORMAT!r}, got {d.get('format')!r}")
    for k in ("units", "fps", "frame_count", "graph", "frames"):
        if k not in d:
            raise SpineFormatError(f"missing key {k!r}")
    if not isinstance(d["units"], str):
        raise SpineFormatError("units must be a string")
    if not (isinstance(d["fps"], (int, float)) and d["fps"] > 0):
        raise SpineFormatError("fps must be a positive number")


def _check_graph(g) -> tuple[list, list, dict]:
    """Limbs, junctions and parents of a valid graph: unique ids, one root junction, a tree."""
    if not isinstance(g, dict) or not all(k in g for k in ("limbs", "junctions", "parents")):
        raise SpineFormatError("graph must have limbs, junctions and parents")
    limbs, juncs, parents = g["limbs"], g["junctions"], g["parents"]
    names = list(limbs) + list(juncs)
    if len(set(names)) != len(names) or not all(isinstance(n, str) for n in names):
        raise SpineFormatError("limb and junction ids must be unique strings")
    if set(parents) != set(names):
        raise SpineFormatError("parents must name the parent of every limb and junction")
    roots = [n for n, p in parents.items() if p is None]
    if len(roots) != 1 or roots[0] not in juncs:
        raise SpineFormatError("exactly one junction must be the root (parent null)")
    for n, p in parents.items():
        if p is not None and p not in juncs:
            raise SpineFormatError(f"parent of {n!r} must be a junction, got {p!r}")
    for n in names:  # acyclic
        seen, x = set(), n
        while x is not None:
            if x in seen:
                raise SpineFormatError(f"parents form a cycle through {x!r}")
            seen.add(x)
            x = parents[x]
    return limbs, juncs, parents


def _check_axes(fr: dict, w: str, parents: dict) -> None:
    for k, a in fr["axes"].items():
        if k not in parents or parents[k] is None:
            raise SpineFormatError(f"{w}.axes: unknown limb {k!r}")
        if a is None:
            continue
        if not isinstance(a, list) or len(a) < 2:
            raise SpineFormatError(f"{w}.axes.{k}: expected a polyline of >= 2 points or null")
        for j, p in enumerate(a):
            _check_point(p, f"{w}.axes.{k}[{j}]")
            if p is None:
                raise SpineFormatError(f"{w}.axes.{k}[{j}]: null point inside a polyline")


def _check_frame(fr, w: str, last, limbs, juncs, parents) -> int:
    """One frame entry; returns its index."""
    if not isinstance(fr, dict) or "index" not in fr or "tips" not in fr or "axes" not in fr:
        raise SpineFormatError(f"{w}: needs index, tips and axes")
    if not isinstance(fr["index"], int) or (last is not None and fr["index"] <= last):
        raise SpineFormatError(f"{w}: index must be an integer increasing with the take order")
    if set(fr["tips"]) != set(limbs):
        raise SpineFormatError(f"{w}: tips must have one entry per limb")
    for k, x in fr["tips"].items():
        _check_point(x, f"{w}.tips.{k}")
    for k, x in fr.get("junctions", {}).items():
        if k not in juncs:
            raise SpineFormatError(f"{w}.junctions: unknown junction {k!r}")
        _check_point(x, f"{w}.junctions.{k}")
    _check_axes(fr, w, parents)
    for k in limbs:
        if (fr["tips"][k] is None) != (fr["axes"].get(k) is None) and fr["axes"].get(k) is not None:
            raise SpineFormatError(f"{w}: limb {k!r} has an axis but no tip")
    return fr["index"]


def validate_spine_dict(d) -> None:
    """Check a parsed spine file; raises :class:`SpineFormatError` naming the first problem."""
    _check_header(d)
    limbs, juncs, parents = _check_graph(d["graph"])
    frames = d["frames"]
    if not isinstance(frames, list) or len(frames) != d["frame_count"]:
        raise SpineFormatError("frames must be a list of frame_count entries")
    last = None
    for i, fr in enumerate(frames):
        last = _check_frame(fr, f"frames[{i}]", last, limbs, juncs, parents)


def write_spine(path, spine: Spine) -> Path:
    """Write ``spine.json`` (``capture-stage/spine@1``); returns the path."""
    if not isinstance(spine, Spine):
        raise ValueError(f"spine must be a Spine, got {type(spine).__name__}")
    d = spine.to_dict()
    validate_spine_dict(d)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(d, separators=(",", ":"), allow_nan=False))
    tmp.replace(path)
    return path


def read_spine(path) -> Spine:
    """Read and validate a ``spine.json``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"spine file not found: {path}")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SpineFormatError(f"{path}: not JSON ({exc})") from exc
    return Spine.from_dict(d)
