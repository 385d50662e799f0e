"""Spines: one temporally consistent branching skeleton per take (Brostow et al. 2004).

Arrays in, a spine out (the per-frame skeletons are computed by the caller: :mod:`pipeline.process`
over a take, :mod:`pipeline.spine_meshes` over a mesh sequence):

1. per frame: tips ``E_t`` (:mod:`pipeline.extremities`) and one
   level-set skeleton per tip (:mod:`pipeline.skeleton`) ->
   :class:`~pipeline.frame_skeleton.FrameSkeleton` (:func:`~pipeline.frame_skeleton.frame_skeleton`);
2. reduce: tip correspondence over time (:mod:`pipeline.correspond`,
   section 4.2), one tip per limb among its near-equal maxima (the one most
   consistent over the take, :func:`_settle_limb_tips`), then the skeletons re-merged with only the ``K``
   corresponded limbs (:mod:`pipeline.merge`), the most frequent topology
   imposed on every frame as the graph ``G``, and each limb resampled at one
   interval (section 4.3) -> :class:`~pipeline.spine_format.Spine` (:func:`build_spine`);
3. the ``capture-stage/spine@1`` JSON file: :mod:`pipeline.spine_format`
   (``docs/spine-format.md``).

:func:`pipeline.spine_meshes.spine_from_meshes` runs all of it on a mesh sequence.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from pipeline.correspond import NoLimbsError, correspond_tips
from pipeline.frame_skeleton import FrameSkeleton, SpineParams, with_alternates
from pipeline.merge import MergedSkeleton, Topology, consensus_topology, merge_skeletons, skeleton_splits
from pipeline.skeleton import limb_end
from pipeline.spine_format import Spine

__all__ = ["build_spine", "resample_polyline"]

log = logging.getLogger(__name__)


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
    frames = [with_alternates(fr, chosen[t]) if chosen[t] else fr for t, fr in enumerate(frames)]
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
        clear=None if any(f.clear is None for f in frames) else [f.clear for f in frames],
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
