"""Per-frame skeletons of the spine pipeline (Brostow et al. 2004, sections 4.1-4.2), and its options.

:func:`frame_skeleton` finds a mesh's tips ``E_t`` (:mod:`pipeline.extremities`) and grows one
level-set skeleton per tip (:mod:`pipeline.skeleton`) -> :class:`FrameSkeleton`, with the
:class:`Alternate` tips among near-equal maxima that the take-level reduce (:mod:`pipeline.spine`)
may choose instead. :class:`SpineParams` holds the options of the whole spine pipeline: the
per-frame ones used here and the take-level ones :func:`pipeline.spine.build_spine` uses.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from pipeline.extremities import find_extremities
from pipeline.geodesic import edge_graph, largest_component, mesh_edges, validate_mesh, vertex_areas
from pipeline.merge import MergedSkeleton, Topology, consensus_topology, merge_skeletons, skeleton_splits
from pipeline.mesh_primitives import edge_components
from pipeline.skeleton import TipSkeleton, grow_skeleton, limb_points

__all__ = ["SpineParams", "FrameSkeleton", "Alternate", "frame_skeleton", "with_alternates", "LIMB_FRACTIONS"]

log = logging.getLogger(__name__)

LIMB_FRACTIONS = (0.25, 0.5, 0.75)  # points along each limb used to align skeletons over time
#: the warning of a frame whose mesh has other connected parts than its largest (dropped)
PARTS_DROPPED = "faces in other connected parts dropped (the largest part kept)"


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
        by about a patch (tests/pipeline/test_spine_fast.py bounds it), the AGD
        costs several times less. ``None``: always exact.
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


def with_alternates(frame: "FrameSkeleton", chosen: Sequence[int]) -> "FrameSkeleton":
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
    clear : (n,) bool ndarray or None
        Tips that protrude clearly (:attr:`pipeline.extremities.Extremities.clear`); ``None``
        when not known (a record written before it existed).
    """

    tips: np.ndarray
    tip_vertices: np.ndarray
    skeletons: tuple
    size: float
    n_faces: int
    limb_points: np.ndarray
    alternates: tuple = ()
    clear: np.ndarray | None = None

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
            "clear": None if self.clear is None else np.asarray(self.clear, dtype=bool).tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "FrameSkeleton":
        return cls(
            tips=np.asarray(d["tips"], dtype=np.float64).reshape(-1, 3),
            tip_vertices=np.asarray(d["tip_vertices"], dtype=np.int64),
            skeletons=tuple(TipSkeleton.from_dict(s) for s in d["skeletons"]),
            size=float(d["size"]),
            n_faces=int(d["n_faces"]),
            limb_points=np.asarray(d["limb_points"], dtype=np.float64).reshape(len(d["tips"]), -1, 3)
            if len(d["tips"]) else np.zeros((0, len(LIMB_FRACTIONS), 3)),  # (an empty frame's: no tips, no points)
            alternates=tuple(Alternate.from_dict(a) for a in d.get("alternates", ())),
            clear=None if d.get("clear") is None else np.asarray(d["clear"], dtype=bool).reshape(len(d["tips"])),
        )

    @classmethod
    def empty(cls) -> "FrameSkeleton":
        return cls(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), (), 0.0, 0, np.zeros((0, len(LIMB_FRACTIONS), 3)),
                   clear=np.zeros(0, dtype=bool))


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
    if edge_components(edges, len(v)).max() == 0:  # one part
        kept = np.arange(len(v))
    else:  # several parts (or unreferenced vertices): keep the largest part
        n_faces = len(f)
        v, f, kept = largest_component(v, f, warn=False)
        if len(f) < n_faces:  # (one wording a frame: a sequence's frames say it once, pipeline.run.frames_said)
            log.debug("%d of %d faces in other connected parts dropped", n_faces - len(f), n_faces)
            log.warning("%s", PARTS_DROPPED)
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
        clear=ext.clear.copy(),
    )
