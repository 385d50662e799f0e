"""Spines: one temporally consistent branching skeleton per take (Brostow et al. 2004).

The take-level driver:

1. per frame (in parallel): tips ``E_t`` (:mod:`pipeline.extremities`) and one
   level-set skeleton per tip (:mod:`pipeline.skeleton`) ->
   :class:`FrameSkeleton` (:func:`frame_skeleton`);
2. reduce: tip correspondence over time (:mod:`pipeline.correspond`,
   section 4.2), one tip per limb among its near-equal maxima (the one most
   consistent over the take, :func:`_settle_limb_tips`), then the skeletons re-merged with only the ``K``
   corresponded limbs (:mod:`pipeline.merge`), the most frequent topology
   imposed on every frame as the graph ``G``, and each limb resampled at one
   interval (section 4.3) -> :class:`Spine` (:func:`build_spine`);
3. :func:`write_spine` / :func:`read_spine`: the ``capture-stage/spine@1``
   JSON file (``docs/spine-format.md``).

:func:`spine_from_meshes` runs all of it on a mesh sequence.
"""

from __future__ import annotations

import json
import logging
import math
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse.csgraph import connected_components

from pipeline.correspond import NoLimbsError, correspond_tips
from pipeline.extremities import find_extremities
from pipeline.geodesic import EmptyMeshError, edge_graph, largest_component, mesh_edges, validate_mesh, vertex_areas
from pipeline.merge import MergedSkeleton, Topology, consensus_topology, merge_skeletons, skeleton_splits
from pipeline.skeleton import TipSkeleton, grow_skeleton, limb_end, limb_points

__all__ = [
    "FORMAT",
    "SpineParams",
    "FrameSkeleton",
    "Alternate",
    "frame_skeleton",
    "Spine",
    "build_spine",
    "spine_from_meshes",
    "write_spine",
    "read_spine",
    "validate_spine_dict",
    "SpineFormatError",
    "NoLimbsError",
    "EmptyMeshError",
]

log = logging.getLogger(__name__)

FORMAT = "capture-stage/spine@1"
LIMB_FRACTIONS = (0.25, 0.5, 0.75)  # points along each limb used to align skeletons over time


class SpineParams(BaseModel):
    """Options of the spine pipeline (all scale-free; defaults follow the paper).

    Attributes
    ----------
    n_base : int
        Base points for the average geodesic distance (Hilaga et al.).
    min_protrusion : float
        Tip threshold: a tip must protrude by this fraction of ``sqrt(area)``.
    n_bins : int
        Level-set bins per skeleton (paper: "usually 100").
    min_bin_edges : float
        Bins are never thinner than this many mean edge lengths.
    area_weighted : bool
        Weight ring points by vertex area (uniform on a regular mesh).
    reference_span : int
        One correspondence reference frame per this many frames.
    max_permutations : int
        Exhaustive tip-mapping search up to this many candidates per frame.
    gate : float
        Drop a tip farther than this x the RMS tip radius from its limb's
        position in the aligned neighbouring frame.
    samples : int
        Resampling interval = (median total spine length) / ``samples``.
    agd_proxy : int or None
        Meshes of more than ``3 * agd_proxy`` vertices get their average
        geodesic distance on a proxy of about this many surface patches
        (:func:`pipeline.geodesic.proxy_average_geodesic_distance`): tips move
        by about a patch (<= 3 % of ``sqrt(area)``, tested), the AGD costs
        ~5x less. ``None``: always exact.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    n_base: int = Field(24, ge=2, le=1000)
    min_protrusion: float = Field(0.1, gt=0, lt=10)
    n_bins: int = Field(100, ge=2, le=10000)
    min_bin_edges: float = Field(1.0, ge=0)
    area_weighted: bool = True
    reference_span: int = Field(150, ge=1)
    max_permutations: int = Field(40320, ge=1)
    gate: float = Field(1.0, gt=0)
    samples: int = Field(100, ge=2)
    agd_proxy: int | None = Field(8000, ge=100)


# --------------------------------------------------------------------------- per frame


@dataclass(frozen=True)
class Alternate:
    """Another near-equal maximum of one tip's limb, ready to stand in for the tip.

    Attributes
    ----------
    tip : int
        Index of the tip it may replace.
    point : (3,) float ndarray
    vertex : int
        Vertex id in the input mesh numbering.
    skeleton : TipSkeleton
        Grown from it (``seed == tip``; its ``tip_nodes`` with it in the tip's place).
    limb_points : (m, 3) float ndarray
    rings : (n,) int ndarray
        Its ring in each tip's skeleton (``-1`` unreached).
    alt_rings : (a,) int ndarray
        Every alternate's ring in its own skeleton.
    """

    tip: int
    point: np.ndarray
    vertex: int
    skeleton: TipSkeleton
    limb_points: np.ndarray
    rings: np.ndarray
    alt_rings: np.ndarray

    def to_dict(self) -> dict:
        return {"tip": int(self.tip), "point": np.asarray(self.point).tolist(), "vertex": int(self.vertex),
                "skeleton": self.skeleton.to_dict(), "limb_points": np.asarray(self.limb_points).tolist(),
                "rings": np.asarray(self.rings).tolist(), "alt_rings": np.asarray(self.alt_rings).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Alternate":
        return cls(tip=int(d["tip"]), point=np.asarray(d["point"], dtype=np.float64).reshape(3),
                   vertex=int(d["vertex"]), skeleton=TipSkeleton.from_dict(d["skeleton"]),
                   limb_points=np.asarray(d["limb_points"], dtype=np.float64).reshape(-1, 3),
                   rings=np.asarray(d["rings"], dtype=np.int64), alt_rings=np.asarray(d["alt_rings"], dtype=np.int64))


def _stand_in(frame: "FrameSkeleton", chosen: Sequence[int]) -> "FrameSkeleton":
    """``frame`` with the alternates ``chosen`` (indices into ``frame.alternates``, one per tip at most)
    in their tips' places: tips, skeletons, the rings every skeleton records for them, and every tip's
    limb points (a tip's limb ends where its paths to the other tips part, so it moves with them)."""
    alts = [frame.alternates[c] for c in chosen]
    if len({a.tip for a in alts}) != len(alts):
        raise ValueError("chosen must hold at most one alternate per tip")
    by_tip = dict(zip((a.tip for a in alts), chosen))
    tips, tv = frame.tips.copy(), frame.tip_vertices.copy()
    skels = []
    for j, s in enumerate(frame.skeletons):
        own = frame.alternates[by_tip[j]] if j in by_tip else None
        # rings of the (new) tips in this skeleton: the base rings, or the alternate's own record
        tn = own.skeleton.tip_nodes.copy() if own is not None else s.tip_nodes.copy()
        for i, c in by_tip.items():
            if i != j:
                tn[i] = own.alt_rings[c] if own is not None else frame.alternates[c].rings[j]
        skels.append(replace(own.skeleton if own is not None else s, tip_nodes=tn))
    for a in alts:
        tips[a.tip], tv[a.tip] = a.point, a.vertex
    lp = np.array([limb_points(s, tips[j], LIMB_FRACTIONS) for j, s in enumerate(skels)]).reshape(frame.limb_points.shape)
    return replace(frame, tips=tips, tip_vertices=tv, skeletons=tuple(skels), limb_points=lp, alternates=())


@dataclass(frozen=True)
class FrameSkeleton:
    """Everything the reduce step needs from one frame.

    Attributes
    ----------
    tips : (n, 3) float ndarray
        Tip positions ``E_t``.
    tip_vertices : (n,) int ndarray
        Tip vertex ids in the *input* mesh numbering.
    skeletons : tuple of TipSkeleton
        One per tip (``skeletons[i].seed == i``).
    size : float
        ``sqrt(surface area)`` of the kept part.
    n_faces : int
        Faces of the kept part (0 = empty frame).
    limb_points : (n, m, 3) float ndarray
        Points along each tip's own limb (:func:`pipeline.skeleton.limb_points`),
        aligned with the tips when tracking correspondence.
    alternates : tuple of Alternate
        The near-equal maxima of the tips' limbs
        (:attr:`pipeline.extremities.Extremities.alternates`), each with the
        skeleton grown from it; :func:`build_spine` picks one per limb and take.
    """

    tips: np.ndarray
    tip_vertices: np.ndarray
    skeletons: tuple
    size: float
    n_faces: int
    limb_points: np.ndarray
    alternates: tuple = ()

    @property
    def n_tips(self) -> int:
        return len(self.tips)

    def topology(self) -> Topology:
        """Exploratory topology over all tips (majority consensus, section 4.1)."""
        n = self.n_tips
        if n == 0:
            raise ValueError("frame has no tips")
        return consensus_topology([skeleton_splits(s) for s in self.skeletons], n)

    def merged(self) -> MergedSkeleton:
        """The frame's merged exploratory skeleton (all tips, section 4.1)."""
        if self.n_tips == 0:
            raise ValueError("frame has no tips")
        return merge_skeletons(self.skeletons, self.tips)

    def to_dict(self) -> dict:
        return {
            "tips": self.tips.tolist(),
            "tip_vertices": self.tip_vertices.tolist(),
            "skeletons": [s.to_dict() for s in self.skeletons],
            "size": float(self.size),
            "n_faces": int(self.n_faces),
            "limb_points": self.limb_points.tolist(),
            "alternates": [a.to_dict() for a in self.alternates],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "FrameSkeleton":
        return cls(
            tips=np.asarray(d["tips"], dtype=np.float64).reshape(-1, 3),
            tip_vertices=np.asarray(d["tip_vertices"], dtype=np.int64),
            skeletons=tuple(TipSkeleton.from_dict(s) for s in d["skeletons"]),
            size=float(d["size"]),
            n_faces=int(d["n_faces"]),
            limb_points=np.asarray(d["limb_points"], dtype=np.float64).reshape(len(d["tips"]), -1, 3),
            alternates=tuple(Alternate.from_dict(a) for a in d.get("alternates", ())),
        )

    @classmethod
    def empty(cls) -> "FrameSkeleton":
        return cls(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), (), 0.0, 0, np.zeros((0, len(LIMB_FRACTIONS), 3)))


def _alternate_skeletons(grow: Callable, v: np.ndarray, kept: np.ndarray, alt: list, every: np.ndarray,
                         grown: list) -> tuple:
    """One :class:`Alternate` per ``(tip, vertex)`` of ``alt``: its skeleton grown with it in its
    tip's place (``grow(seed_vertex, tips=, seed=)``), the rings of every alternate in it, and its
    ring in each tip's skeleton (``grown``, grown with all of ``every``: the ``n`` tips, then the
    alternates). ``kept`` maps the kept part's vertices to the input mesh's."""
    n = len(every) - len(alt)
    alternates = []
    for j, (i, a) in enumerate(alt):
        own = every.copy()
        own[i] = a
        s = grow(a, tips=own, seed=i)
        alt_rings, s = s.tip_nodes[n:], replace(s, tip_nodes=s.tip_nodes[:n])
        alternates.append(Alternate(tip=i, point=v[a].copy(), vertex=int(kept[a]), skeleton=s,
                                    limb_points=limb_points(s, v[a], LIMB_FRACTIONS),
                                    rings=np.asarray([g.tip_nodes[n + j] for g in grown], dtype=np.int64),
                                    alt_rings=alt_rings))
    return tuple(alternates)


def frame_skeleton(vertices, faces, *, params: SpineParams | None = None) -> FrameSkeleton:
    """Tips and per-tip level-set skeletons of one surface (Brostow et al. 2004, 4.1).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
        A triangle mesh; only its largest connected part is used (warning
        logged). Non-manifold meshes are fine. An empty mesh (no faces) gives
        an empty :class:`FrameSkeleton`; a blob with nothing protruding
        gives one with no tips.
    params : SpineParams, optional

    Returns
    -------
    FrameSkeleton
    """
    params = params or SpineParams()
    if not isinstance(params, SpineParams):
        raise ValueError(f"params must be a SpineParams, got {type(params).__name__}")
    v, f = validate_mesh(vertices, faces, allow_empty=True)
    if len(f) == 0:
        log.warning("empty frame (no faces)")
        return FrameSkeleton.empty()
    edges = mesh_edges(f)
    n_comp, _ = connected_components(
        sp.csr_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(len(v), len(v))),
        directed=False,
    )
    if n_comp == 1:
        kept = np.arange(len(v))
    else:  # several parts (or unreferenced vertices): keep the largest part
        v, f, kept = largest_component(v, f, warn=True)
        edges = mesh_edges(f)
    graph = edge_graph(v, edges)
    areas = vertex_areas(v, f)
    size = float(np.sqrt(areas.sum()))
    if size <= 0:
        log.warning("degenerate frame (zero surface area)")
        return FrameSkeleton.empty()
    ext = find_extremities(
        v,
        f,
        n_base=params.n_base,
        min_protrusion=params.min_protrusion,
        agd_proxy=params.agd_proxy,
        graph=graph,
        edges=edges,
    )
    mean_edge = float(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1).mean())
    weights = areas if params.area_weighted else None
    grow = partial(grow_skeleton, v, edges, graph, n_bins=params.n_bins, min_bin_width=params.min_bin_edges * mean_edge,
                   weights=weights)
    alt = [(i, int(a)) for i, alts in enumerate(ext.alternates) for a in alts]
    n = len(ext.vertices)
    # every skeleton also records the alternates' rings (tip_nodes beyond n), so an alternate can stand in later
    every = np.concatenate([ext.vertices, np.asarray([a for _, a in alt], dtype=np.int64)])
    grown = [grow(int(tv), tips=every, seed=i) for i, tv in enumerate(ext.vertices)]
    skels = tuple(replace(s, tip_nodes=s.tip_nodes[:n]) for s in grown)
    lp = np.array([limb_points(s, ext.points[i], LIMB_FRACTIONS) for i, s in enumerate(skels)]).reshape(
        len(skels), len(LIMB_FRACTIONS), 3
    )
    alternates = _alternate_skeletons(grow, v, kept, alt, every, grown)
    return FrameSkeleton(
        tips=ext.points.copy(),
        tip_vertices=kept[ext.vertices],
        skeletons=skels,
        size=size,
        n_faces=len(f),
        limb_points=lp,
        alternates=alternates,
    )


# --------------------------------------------------------------------------- take


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
            "meta": _jsonable(self.meta),
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


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    return x


def resample_polyline(poly: np.ndarray, n: int) -> np.ndarray:
    """Uniform arc-length resampling of a polyline (K, 3) to ``n`` points."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(poly[:1], n, axis=0)
    q = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(q, s, poly[:, k]) for k in range(3)], axis=1)


def _polyline_length(poly) -> float:
    return float(np.linalg.norm(np.diff(poly, axis=0), axis=1).sum()) if poly is not None and len(poly) > 1 else 0.0


def _check_build_args(frames, fps, units, frame_indices) -> tuple[list, np.ndarray]:
    """The frames as a list and the take frame numbers; ValueError naming a bad parameter."""
    frames = list(frames)
    if not frames:
        raise ValueError("frames must hold at least one FrameSkeleton")
    if not all(isinstance(f, FrameSkeleton) for f in frames):
        raise ValueError("frames must be FrameSkeleton objects")
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be > 0, got {fps}")
    if not isinstance(units, str) or not units:
        raise ValueError("units must be a non-empty string")
    T = len(frames)
    idx = np.arange(T) if frame_indices is None else np.asarray(frame_indices, dtype=np.int64)
    if idx.shape != (T,):
        raise ValueError(f"frame_indices must have {T} entries")
    if all(f.n_tips == 0 for f in frames):
        raise NoLimbsError("no limb tips in any frame: nothing protrudes from the surfaces")
    return frames, idx


def _imposed_topology(frames, A: np.ndarray, K: int) -> tuple[Topology, Counter]:
    """Topology of every complete frame over the K limbs; the most frequent one (4.3)."""
    tops: list[Topology | None] = []
    for t, fr in enumerate(frames):
        sel = A[t]
        if np.all(sel >= 0):
            sk = [s for s in fr.skeletons if s.seed in set(sel.tolist())]
            tops.append(consensus_topology([skeleton_splits(s, sel) for s in sk], K))
        else:
            tops.append(None)
    counted = Counter(tp.splits for tp in tops if tp is not None)
    if counted:
        G = Topology.from_splits(K, counted.most_common(1)[0][0])
    else:  # no complete frame: majority over the partial frames' skeletons
        G = Topology.from_splits(K, [])
    return G, counted


def _junction_hints(merged, t: int, jpos: np.ndarray) -> np.ndarray:
    """Positions from the nearest frame for the junctions frame ``t`` could not realise."""
    m = merged[t]
    J = jpos.shape[1]
    hints = np.full((J, 3), np.nan)
    for j in range(J):
        if np.isfinite(m.junctions[j]).all():
            continue
        ok = np.flatnonzero(np.all(np.isfinite(jpos[:, j]), axis=1))
        if len(ok):
            hints[j] = jpos[ok[np.argmin(np.abs(ok - t))], j]
    return hints


def _realise_topology(frames, A: np.ndarray, G: Topology) -> list[MergedSkeleton | None]:
    """G realised in every frame; junctions not realisable get hints from the nearest frame."""
    T, J = len(frames), G.n_junctions
    merged: list[MergedSkeleton | None] = [None] * T
    for t, fr in enumerate(frames):
        if fr.n_tips and np.any(A[t] >= 0):
            merged[t] = merge_skeletons(fr.skeletons, fr.tips, tips=A[t], topology=G)
    jpos = np.full((T, J, 3), np.nan)
    for t, m in enumerate(merged):
        if m is not None:
            jpos[t] = m.junctions
    for t, m in enumerate(merged):
        if m is None or np.all(np.isfinite(m.junctions)):
            continue
        hints = _junction_hints(merged, t, jpos)
        if np.isfinite(hints).any():
            fr = frames[t]
            merged[t] = merge_skeletons(fr.skeletons, fr.tips, tips=A[t], topology=G, junction_hints=hints)
    return merged


def _graph_ids_for(G: Topology, K: int) -> tuple[list[str], list[str], dict]:
    """Limb and junction ids and the parent of each."""
    J = G.n_junctions
    limb_ids = [f"limb{k}" for k in range(K)]
    junction_ids = [f"j{j}" for j in range(J)]
    parents: dict = {"j0": None}
    for j in range(1, J):
        parents[junction_ids[j]] = junction_ids[G.junction_parent[j]]
    for k in range(K):
        parents[limb_ids[k]] = junction_ids[G.tip_parent[k]]
    return limb_ids, junction_ids, parents


def _frame_polylines(merged, limb_ids, junction_ids):
    """Tips, junctions and the axis polyline of every limb and inner junction, per frame."""
    T, K, J = len(merged), len(limb_ids), len(junction_ids)
    tips = np.full((T, K, 3), np.nan)
    juncs = np.full((T, J, 3), np.nan)
    polys: dict[str, list] = {name: [None] * T for name in limb_ids + junction_ids[1:]}
    for t, m in enumerate(merged):
        if m is None:
            continue
        tips[t] = m.tips
        juncs[t] = m.junctions
        for k in range(K):
            polys[limb_ids[k]][t] = m.tip_axes[k]
        for j in range(1, J):
            polys[junction_ids[j]][t] = m.junction_axes[j]
    return tips, juncs, polys


def _resample_axes(polys: dict, T: int, samples: int) -> tuple[dict, float]:
    """Every axis resampled at one interval (the median total length over ``samples``)."""
    lengths = {name: [_polyline_length(p) for p in ps if p is not None] for name, ps in polys.items()}
    totals = []
    for t in range(T):
        tot = [_polyline_length(polys[name][t]) for name in polys if polys[name][t] is not None]
        if len(tot) == len(polys):
            totals.append(sum(tot))
    total = float(np.median(totals)) if totals else float(sum(np.median(v) for v in lengths.values() if v))
    interval = total / samples if total > 0 else 1.0
    axes = {}
    for name, ps in polys.items():
        L = float(np.median(lengths[name])) if lengths[name] else 0.0
        n = max(2, int(round(L / interval)) + 1)
        a = np.full((T, n, 3), np.nan)
        for t, p in enumerate(ps):
            if p is not None and len(p) >= 1:
                a[t] = resample_polyline(p, n)
        axes[name] = a
    return axes, interval


def _limb_candidates(frames, A: np.ndarray, k: int) -> dict[int, list]:
    """Frame -> ``[(alternate index or -1 for the tip, position relative to the limb)]`` of limb ``k``.

    Relative to one base shared by all the limb's candidates of the frame, the limb's junction with
    the body (:func:`pipeline.skeleton.limb_end` in the tip's skeleton), so that the creature's
    travel does not count. (A point along the tip's own limb would move with the candidate
    ranked highest, exactly on the frames where the ranking flips.)"""
    out = {}
    for t, fr in enumerate(frames):
        i = int(A[t, k])
        if i < 0:
            continue
        s = fr.skeletons[i]
        base = s.nodes[limb_end(s)]
        out[t] = [(-1, fr.tips[i] - base)] + [(c, a.point - base) for c, a in enumerate(fr.alternates) if a.tip == i]
    return out


def _candidate_tracks(cands: dict[int, list], gates: dict[int, float]) -> dict[tuple[int, int], int]:
    """Track id of every ``(frame, candidate slot)``: each seen frame's candidates linked one to one
    (Hungarian on distance) to the previous seen frame's, a link no longer than the frame's gate."""
    from scipy.optimize import linear_sum_assignment

    track: dict[tuple[int, int], int] = {}
    n_tracks, prev = 0, None
    for t in sorted(cands):
        here = cands[t]
        if prev is not None:
            P = np.array([q for _, q in cands[prev]])
            Q = np.array([q for _, q in here])
            D = np.linalg.norm(P[:, None] - Q[None], axis=2)
            for r, c in zip(*linear_sum_assignment(D)):
                if D[r, c] <= gates[t]:
                    track[(t, int(c))] = track[(prev, int(r))]
        for c in range(len(here)):
            if (t, c) not in track:
                track[(t, c)] = n_tracks
                n_tracks += 1
        prev = t
    return track


def _track_spread(cands: dict[int, list], track: dict[tuple[int, int], int]) -> dict[int, float]:
    """RMS distance of each track's relative positions to their mean."""
    pts: dict[int, list] = {}
    for (t, c), tr in track.items():
        pts.setdefault(tr, []).append(cands[t][c][1])
    return {tr: float(np.sqrt(np.mean(np.sum((np.array(p) - np.mean(p, axis=0)) ** 2, axis=1)))) for tr, p in pts.items()}


def _settle_limb_tips(frames, A: np.ndarray, params: SpineParams) -> tuple[list, dict]:
    """One tip per limb over the take where a limb ends in several near-equal maxima.

    A frame's tip is the highest of its limb's near-equal maxima (Brostow's AGD), and which one
    that is follows the surface's small errors (a horse's nose or an ear). Over the take the
    candidates are linked frame to frame (in the limb's own position, within the protrusion
    threshold ``h``: any two candidates of a frame lie at least ``h`` apart along the surface,
    geodesically; in space they may be closer) and, of the tracks
    seen in the most frames, the one whose position in the limb's frame is the most consistent
    over the take (least RMS distance to its mean) is the limb's tip (Brostow's spine is one
    over time); where it is seen, it stands in for the frame's tip. Limbs without alternates
    are left as they are.

    Returns the frames and, per limb index, the frames where an alternate stood in.
    """
    if not any(fr.alternates for fr in frames):
        return frames, {}
    chosen: list[list[int]] = [[] for _ in frames]
    settled = {}
    for k in range(A.shape[1]):
        cands = _limb_candidates(frames, A, k)
        if all(len(c) == 1 for c in cands.values()):
            continue
        gates = {t: params.min_protrusion * frames[t].size for t in cands}
        track = _candidate_tracks(cands, gates)
        seen = Counter(track.values())
        spread = _track_spread(cands, track)
        best = min(seen, key=lambda tr: (-seen[tr], spread[tr], tr))
        swaps = [(t, cands[t][c][0]) for (t, c), tr in track.items() if tr == best and cands[t][c][0] >= 0]
        for t, alt in swaps:
            chosen[t].append(alt)
        settled[f"limb{k}"] = sorted(t for t, _ in swaps)
    frames = [_stand_in(fr, chosen[t]) if chosen[t] else fr for t, fr in enumerate(frames)]
    return frames, settled


def build_spine(
    frames: Sequence[FrameSkeleton],
    *,
    fps: float = 30.0,
    units: str = "mm",
    params: SpineParams | None = None,
    frame_indices=None,
) -> Spine:
    """The reduce step: correspondence (4.2) and one imposed graph (4.3).

    Parameters
    ----------
    frames : sequence of FrameSkeleton
        In take order.
    fps : float
    units : str
    params : SpineParams, optional
    frame_indices : (T,) int array-like, optional
        Take frame numbers (default ``0..T-1``).

    Returns
    -------
    Spine

    Raises
    ------
    NoLimbsError
        When no frame has a tip.
    """
    params = params or SpineParams()
    frames, idx = _check_build_args(frames, fps, units, frame_indices)
    corr = correspond_tips(
        [f.tips for f in frames],
        features=[f.limb_points for f in frames],
        reference_span=params.reference_span,
        max_permutations=params.max_permutations,
        gate=params.gate,
    )
    frames, settled = _settle_limb_tips(frames, corr.assignment, params)
    G, counted = _imposed_topology(frames, corr.assignment, corr.K)
    merged = _realise_topology(frames, corr.assignment, G)
    limb_ids, junction_ids, parents = _graph_ids_for(G, corr.K)
    tips, juncs, polys = _frame_polylines(merged, limb_ids, junction_ids)
    axes, interval = _resample_axes(polys, len(frames), params.samples)
    meta = {
        "K": corr.K,
        "references": [int(r) for r in corr.references],
        "count_rule": corr.count_rule,
        "topology_splits": [int(s) for s in G.splits],
        "topology_frames": int(counted.get(G.splits, 0)),
        "tip_counts": [f.n_tips for f in frames],
        "sample_interval": interval,
        "tip_alternates": settled,
        "method": "Brostow et al. 2004",
    }
    return Spine(
        units=units,
        fps=float(fps),
        frame_indices=idx,
        limb_ids=limb_ids,
        junction_ids=junction_ids,
        parents=parents,
        tips=tips,
        junctions=juncs,
        axes=axes,
        meta=meta,
    )


# --------------------------------------------------------------------------- driver


def _frame_task(item, params_dict: dict) -> dict:
    """Top-level (picklable) per-frame work: load if needed, skeletonize, serialise."""
    params = SpineParams(**params_dict)
    if isinstance(item, (str, Path)):
        from pipeline.meshio import load_mesh

        v, f = load_mesh(item)
    else:
        v, f = item
    return frame_skeleton(v, f, params=params).to_dict()


def spine_from_meshes(
    meshes,
    *,
    fps: float = 30.0,
    units: str = "mm",
    workers: int = 2,
    progress: bool | Callable[[Iterable], Iterable] = False,
    params: SpineParams | None = None,
) -> Spine:
    """Spine of a mesh sequence: per-frame skeletons in parallel, then the reduce step.

    Parameters
    ----------
    meshes : str, Path, sequence of paths, or sequence of (vertices, faces)
        A glob such as ``'DIR/*.obj'`` or a directory (files sorted by name),
        explicit files (OBJ, PLY, OFF), or in-memory meshes; one per frame,
        in take order.
    fps : float
    units : str
        The meshes' units (written to the spine as given).
    workers : int
        Processes for the per-frame work (``<= 1``: in this process).
    progress : bool or callable
        ``True`` shows a tqdm bar; a callable wraps the frame iterator.
    params : SpineParams, optional

    Returns
    -------
    Spine
    """
    from pipeline.meshio import mesh_paths

    params = params or SpineParams()
    if not isinstance(params, SpineParams):
        raise ValueError(f"params must be a SpineParams, got {type(params).__name__}")
    if isinstance(meshes, (str, Path)):
        items: list = list(mesh_paths(meshes))
    else:
        items = list(meshes)
        if items and isinstance(items[0], (str, Path)):
            items = list(mesh_paths(items))
    if not items:
        raise ValueError("meshes must hold at least one frame")
    if int(workers) < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    pd = params.model_dump()
    wrap = progress if callable(progress) else None
    if progress is True:
        from tqdm import tqdm

        def wrap(it):
            return tqdm(it, total=len(items), desc="skeletons", unit="frame")

    if int(workers) <= 1 or len(items) == 1:
        it = (_frame_task(x, pd) for x in items)
        results = list(wrap(it) if wrap else it)
    else:
        with ProcessPoolExecutor(max_workers=int(workers)) as ex:
            it = ex.map(_frame_task, items, [pd] * len(items), chunksize=1)
            results = list(wrap(it) if wrap else it)
    frames = [FrameSkeleton.from_dict(r) for r in results]
    return build_spine(frames, fps=fps, units=units, params=params)


# --------------------------------------------------------------------------- file


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
