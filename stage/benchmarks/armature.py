"""``stage bench armature``: seconds for motion segmentation, skeleton and fit (Tzionas & Gall 2016, section 4).

``stage bench rig`` is its old name, kept as an alias for one release.

Subjects: the simulated quadruped posed along its kinematic tree
(:func:`fake_cameras.mesh_motion.mesh_sequence`) at two mesh resolutions (about
6k and 50k vertices) and two lengths (60 and 500 frames). Targets on a 2-core
machine: segmentation (1000 samples) under 10 s for 50k vertices x 500 frames;
fit under 20 ms a frame.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from stage.benchmarks import COPY_SIGMA, check_copies, check_sigma, move_meshes, seeds_option, spread_cell

NAME = "armature"
ALIASES = ("rig",)  # the old name, kept for one release
HELP = ("seconds for segmentation, skeleton and per-frame fit on ~6k/50k vertices, 60/500 frames "
        "(`stage bench rig`: the old name, kept for one release)")

#: marching-cubes cell (mm) of the quadruped for about 6k and 50k vertices
VOXELS = {"6k": 7.0, "50k": 2.5}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sizes", default="6k,50k", help="mesh sizes to run (default 6k,50k)")
    p.add_argument("--frames", default="60,500", help="sequence lengths to segment (default 60,500)")
    p.add_argument("--fit-frames", type=int, default=20, help="frames timed for the fit (default 20)")
    p.add_argument("--samples", type=int, default=1000, help="sampled vertices (default 1000)")
    p.add_argument("--accuracy", action="store_true",
                   help="instead of the timings: where the rig goes wrong, stage by stage, on the cow, the pipe and "
                   "the simulated creatures (segments against the true rigid parts, joints on the true segments, "
                   "the rig against the true articulations), then simulated takes through process, track and armature "
                   "(tens of minutes)")
    p.add_argument("--takes", default="starfish,quadruped,biped",
                   help="with --accuracy: the simulated takes through process, track and armature (default "
                   "starfish,quadruped,biped; 'none' for none)")
    p.add_argument("--take-frames", type=int, default=30, help="with --accuracy: frames of each take (default 30)")
    p.add_argument("--take-seeds", default="3", help="with --accuracy: the simulator's seeds of each take (default 3)")
    p.add_argument("--parts", choices=("motion", "limbs"), default="motion",
                   help="with --accuracy: the takes' armature parts: 'motion' (default) as `stage track` then `stage "
                   "armature` with their defaults; 'limbs' as `stage track --labels` then `stage armature --parts limbs`")
    p.add_argument("--labels", action="store_true",
                   help="with --accuracy: the takes tracked with the template's limb/body labels (as `stage track "
                   "--labels`; --parts limbs implies it)")
    p.add_argument("--colour", action="store_true",
                   help="with --accuracy: the takes tracked with the colour tracks (as `stage track --colour`)")
    p.add_argument("--armature-rounds", type=_rounds, default=None, metavar="ROUNDS",
                   help="with --accuracy: the takes tracked again with this many rounds of the armature mode, or "
                   "'auto' (as `stage track --armature-rounds`; default: `stage track`'s, one round; 0: the tracking "
                   "alone)")
    p.add_argument("--armature-parts", choices=("motion", "limbs"), default="motion",
                   help="with --accuracy, --armature-rounds and the labels: where every round's armature gets its "
                   "parts, 'motion' (default) or 'limbs' (as `stage track --armature-parts`)")
    p.add_argument("--copies", type=int, default=0, metavar="N",
                   help="with --accuracy: every take's armature also built on N copies of its tracking, every vertex "
                   f"moved by N(0, {1000 * COPY_SIGMA:g} um) (a tracking re-run elsewhere differs by about as much), and "
                   "the spread of their recall / precision printed (default 0)")
    p.add_argument("--skinned", default="2",
                   help="with --accuracy: the creatures' posed sequences also skinned, vertices blending the parts' "
                   "motions over these widths (%% of the size; default 2; 'none' for none)")


def run(args: argparse.Namespace) -> int:
    if getattr(args, "accuracy", False):
        takes, frames, seeds, parts, widths, tracking = _accuracy_options(args)
        copies = check_copies(getattr(args, "copies", 0), name="--copies")
        accuracy(skinned=widths)
        take_accuracy(takes, frames=frames, seeds=seeds, parts=parts, copies=copies, **tracking)
        return 0
    _refuse_accuracy_options(args)
    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    lengths = [int(x) for x in args.frames.split(",") if x.strip()]
    bad = [s for s in sizes if s not in VOXELS]
    if bad:
        raise ValueError(f"--sizes: unknown size {bad[0]!r} (choose from {', '.join(VOXELS)})")
    print(f"{'vertices':>9} {'frames':>7} {'segment s':>10} {'cpu s':>6} {'dt':>4} {'k':>4} {'segments':>9} "
          f"{'skeleton s':>11} {'cpu s':>6} {'fit ms/frame':>13} {'cpu ms':>7}")
    for size in sizes:
        for T in lengths:
            _timing_row(size, T, samples=args.samples, fit_frames=int(args.fit_frames))
    return 0


def _refuse_accuracy_options(args: argparse.Namespace) -> None:
    """Without ``--accuracy``, an option whose help begins "with --accuracy" that is not at its default is refused
    (the timings would ignore it): ValueError naming it."""
    p = argparse.ArgumentParser()
    add_arguments(p)
    for action in p._actions:
        if (action.help or "").startswith("with --accuracy") and hasattr(args, action.dest) \
                and getattr(args, action.dest) != action.default:
            raise ValueError(f"{action.option_strings[0]} needs --accuracy (the timings do not use it)")


def _accuracy_options(args: argparse.Namespace):
    """``--accuracy``'s options checked before any work, each error naming its option: -> (takes, take frames,
    seeds, parts, skinning widths as fractions of the size, the takes' tracking as keywords of
    :func:`take_armature`)."""
    takes = [t.strip() for t in str(getattr(args, "takes", "none")).split(",") if t.strip() not in ("", "none")]
    bad = [t for t in takes if t not in ("starfish", "quadruped", "biped")]
    if bad:
        raise ValueError(f"--takes: unknown creature {bad[0]!r} (choose from starfish, quadruped, biped)")
    if int(getattr(args, "take_frames", 30)) < 2:
        raise ValueError(f"--take-frames must be >= 2, got {args.take_frames}")
    parts = str(getattr(args, "parts", "motion"))
    seeds = seeds_option(getattr(args, "take_seeds", "3"))
    skinned = str(getattr(args, "skinned", "none")).strip()
    try:
        widths = [] if skinned == "none" else [float(x) / 100 for x in skinned.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--skinned must be widths in % of the size (e.g. 1,2,3) or 'none', got {skinned!r}") from None
    if any(not 0 < w < 1 for w in widths):
        raise ValueError(f"--skinned widths must be within (0, 100) %, got {skinned!r}")
    tracking = dict(labels=bool(getattr(args, "labels", False)), colour=bool(getattr(args, "colour", False)),
                    armature_rounds=getattr(args, "armature_rounds", None),
                    armature_parts=str(getattr(args, "armature_parts", "motion")))
    _check_tracking(parts=parts, **tracking, name=lambda p: "--" + p.replace("_", "-"))
    return takes, int(getattr(args, "take_frames", 30)), tuple(seeds), parts, tuple(widths), tracking


def _rounds(text: str):
    """``--armature-rounds``: a count or ``auto``, as ``stage track`` takes it."""
    return text if text == "auto" else int(text)


def _check_tracking(*, parts: str, labels: bool, colour: bool, armature_rounds, armature_parts: str,
                    name=lambda p: p) -> None:
    """The tracking options of :func:`take_armature`, or a ValueError that starts with the parameter's name
    (``name`` spells it: the bench's options are the same rules under their command-line names)."""
    if parts not in ("motion", "limbs"):
        raise ValueError(f"{name('parts')} must be 'motion' or 'limbs', got {parts!r}")
    if armature_rounds is not None and armature_rounds != "auto" and (
            isinstance(armature_rounds, bool) or not isinstance(armature_rounds, int) or armature_rounds < 0):
        raise ValueError(f"{name('armature_rounds')} must be an integer >= 0 or 'auto', got {armature_rounds!r}")
    if armature_rounds is None:  # the track step's default
        from pipeline.process.params import TrackParams

        armature_rounds = TrackParams.model_fields["armature_rounds"].default
    if armature_parts not in ("motion", "limbs"):
        raise ValueError(f"{name('armature_parts')} must be 'motion' or 'limbs', got {armature_parts!r}")
    if armature_parts == "limbs" and not (armature_rounds and (labels or parts == "limbs")):
        raise ValueError(f"{name('armature_parts')} 'limbs' needs {name('armature_rounds')} (>= 1 or 'auto') and the "
                         f"template's labels ({name('labels')} or {name('parts')} 'limbs'): its parts are the labels' "
                         "body and limbs")


def _timing_row(size: str, T: int, *, samples: int, fit_frames: int) -> None:
    """One row of the timings: the quadruped of ``size`` over ``T`` frames segmented, its skeleton and model
    built, and ``fit_frames`` of its frames fitted; wall and CPU seconds of each."""
    from fake_cameras.mesh_motion import mesh_sequence
    from pipeline.armature_fit import articulated_model, fit_sequence
    from pipeline.armature_skeleton import articulated_skeleton
    from pipeline.motion_segmentation import motion_segmentation

    ms = mesh_sequence("quadruped", frames=T, voxel=VOXELS[size], dtype=np.float32)
    V = ms.vertices
    t0, c0 = time.perf_counter(), time.process_time()
    seg = motion_segmentation(V, ms.faces, n_samples=samples, lambda_thr=0.98)
    t_seg, c_seg = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    sk = articulated_skeleton(np.asarray(V[0], dtype=np.float64), ms.faces, seg.labels, motion=V, reference=0)
    model = articulated_model(np.asarray(V[0], dtype=np.float64), ms.faces, sk)
    t_sk, c_sk = time.perf_counter() - t0, time.process_time() - c0
    n_fit = min(fit_frames, T)
    t0, c0 = time.perf_counter(), time.process_time()
    fit_sequence(model, np.asarray(V[:n_fit], dtype=np.float64))
    t_fit, c_fit = (time.perf_counter() - t0) / n_fit * 1e3, (time.process_time() - c0) / n_fit * 1e3
    print(f"{V.shape[1]:>9} {T:>7} {t_seg:>10.2f} {c_seg:>6.2f} {seg.interval:>4} {seg.k:>4} {seg.n_segments:>9} "
          f"{t_sk:>11.2f} {c_sk:>6.2f} {t_fit:>13.1f} {c_fit:>7.1f}", flush=True)


# --------------------------------------------------------------------------- where it goes wrong, stage by stage


def _truth_cow(root):
    """The cow's 7 poses, its rigging skeleton and the true part of every vertex (the bone whose rigid
    motion, estimated from the vertices nearest to it, best predicts the vertex over the poses)."""
    from pipeline.armature_files import load_sequence
    from pipeline.armature_score import articulation_bends
    from pipeline.rigid_parts import rigid_motions

    d = root / "cow_poses"
    V, F, _ = load_sequence(sorted(d.glob("cow-*.obj")))
    sk = np.load(d / "skeleton.npz")
    J, par = np.asarray(sk["joints"], dtype=np.float64), np.asarray(sk["parents"], dtype=np.int64)
    bones = [(int(par[c]), c) for c in range(len(par)) if par[c] >= 0]
    # start: the nearest bone (median over the poses of the distance to the bone's segment)
    dist = []
    for p, c in bones:
        a, b = J[:, p][:, None], J[:, c][:, None]
        ab = b - a
        u = np.clip(((V - a) * ab).sum(2) / np.maximum((ab * ab).sum(2), 1e-12), 0.0, 1.0)
        dist.append(np.median(np.linalg.norm(V - (a + u[..., None] * ab), axis=2), axis=0))
    lab = np.argmin(np.stack(dist, 1), 1)
    for _ in range(3):
        err = []
        for k in range(len(bones)):
            ids = np.flatnonzero(lab == k)
            R, t = rigid_motions(V[:, ids]) if len(ids) >= 3 else (np.tile(np.eye(3), (len(V), 1, 1)), np.zeros((len(V), 3)))
            err.append(np.linalg.norm(np.einsum("tij,vj->tvi", R, V[0]) + t[:, None] - V, axis=2).mean(0))
        lab = np.argmin(np.stack(err, 1), 1)
    art = np.array([par[j] >= 0 and (par == j).any() for j in range(len(par))])
    bend = articulation_bends(J, par)
    # a bone's part joins its parent bone's across a joint that does not bend (for this child bone)
    child_of = {c: i for i, (_, c) in enumerate(bones)}
    part_parent = np.array([child_of.get(p, -1) for p, _ in bones])
    part_bends = np.zeros(len(bones), bool)
    for i, (p, c) in enumerate(bones):
        q = par[p]
        if q >= 0:
            a, b = J[:, p] - J[:, q], J[:, c] - J[:, p]
            ang = np.degrees(np.arccos(np.clip((a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1), -1, 1)))
            part_bends[i] = ang.max() - ang.min() >= 10.0
    # true articulations where the rig's bones meet: the nine with a parent and a child; the root joins four
    # bones and is where the front legs turn, so a found joint there is not wrong
    hub = art | (np.bincount(par[par >= 0], minlength=len(par)) >= 2)
    return dict(V=V, F=F, joints=J, articulates=hub, bending=art & (bend >= 10.0), part=lab,
                part_parent=part_parent, part_bends=part_bends, units="mm", fps=30.0, lambda_thr=0.7)


def _truth_pipe(root):
    d = np.load(root / "tzionas_pipe" / "pipe.npz")
    V = np.asarray(d["vertices"], dtype=np.float64)
    J = np.asarray(d["joints"], dtype=np.float64)
    art = np.array([False, True, False])
    return dict(V=V, F=d["faces"], joints=J, articulates=art, bending=art, part=np.asarray(d["bone_of_vertex"]),
                part_parent=np.array([-1, 0]), part_bends=np.array([False, True]), units="mm", fps=30.0, lambda_thr=0.7)


def _parts(raw, creature, names, articulates):
    """True parts from every vertex's capsule id (-1 body, limb * 16 + segment): the part index of every
    vertex, every part's parent part and whether it bends against its parent (any joint between them
    does)."""
    ids = sorted({int(p) for p in np.unique(raw)})
    index = {p: i for i, p in enumerate(ids)}
    part = np.array([index[int(p)] for p in raw])
    parent, bends = np.full(len(ids), -1), np.zeros(len(ids), bool)
    for p in ids:
        if p < 0:
            continue
        li, i = divmod(p, 16)
        up = next((q for q in range(p - 1, li * 16 - 1, -1) if q in index), -1)  # the nearest part above with vertices
        parent[index[p]] = index.get(up, -1)
        # every joint between the part above and this one (a capsule with no vertex of its own, such as a
        # neck hidden between the body and the head, leaves two): the part bends when any of them does
        first = up % 16 + 1 if up >= li * 16 else 0
        bends[index[p]] = any(bool(articulates[list(names).index(f"{creature.limbs[li].name}.{k}")])
                              for k in range(first, i + 1))
    return part, parent, bends


def _truth_creature(name, frames=40):
    from fake_cameras.creatures import make_creature
    from fake_cameras.mesh_motion import mesh_sequence

    ms = mesh_sequence(name, frames=frames)
    cr = make_creature(name)
    part, parent, bends = _parts(ms.part, cr, ms.joint_names, ms.articulates)
    return dict(V=ms.vertices, F=ms.faces, joints=ms.joints, articulates=np.ones(len(ms.joint_names), bool),
                bending=np.asarray(ms.articulates, bool), part=part, part_parent=parent, part_bends=bends,
                units="mm", fps=30.0, lambda_thr=0.98)


def _truth_skinned(name, sigma: float, frames=40):
    """The creature's posed sequence skinned (motion the segmentation was not made on): every vertex moved
    by a blend of the true parts' rigid motions, weights ``exp(-d_p / s)`` over its rest distance ``d_p`` to
    each part beyond the nearest one's, cut at ``4 s``, normalised; ``s`` = ``sigma`` of the size."""
    from scipy.spatial import cKDTree

    from pipeline.rigid_parts import rigid_motions

    tr = _truth_creature(name, frames)
    V = np.asarray(tr["V"], dtype=np.float64)
    X = V[0]
    parts = np.unique(tr["part"])
    D = np.stack([cKDTree(X[tr["part"] == p]).query(X)[0] for p in parts], 1)
    D -= D.min(1, keepdims=True)
    s = float(sigma) * float(np.linalg.norm(np.ptp(X, axis=0)))
    W = np.where(D <= 4 * s, np.exp(-D / s), 0.0)
    W /= W.sum(1, keepdims=True)
    out = np.zeros_like(V)
    for k, p in enumerate(parts):
        R, t = rigid_motions(V[:, tr["part"] == p])
        out += W[None, :, k, None] * (np.einsum("tij,vj->tvi", R, X) + t[:, None])
    return dict(tr, V=out)


def _truth_take(sim, rig, vertices, faces, reference: int):
    """The truth of a simulated take's armature: the creature's joints at the tracked frames' times and the
    true part of every tracked template vertex (the capsule nearest to it at the tracking's reference
    frame ``reference``, a frame number, where the template is the surface)."""
    from fake_cameras.mesh_motion import true_joints

    cr = sim.creature
    times = np.asarray(sim.times)[rig.frame_indices]
    names, J, bending = true_joints(cr, times)
    at = int(np.flatnonzero(rig.frame_indices == reference)[0])
    cap = cr.pose(float(times[at])).capsule_sdf(np.asarray(vertices[at])).argmin(1)
    seg_ids = np.array([li * 16 + i for li, lb in enumerate(cr.limbs) for i in range(len(lb.lengths))])
    nb = len(cr.body)
    raw = np.full(len(cap), -1)
    limb = (cap >= nb) & (cap < nb + len(seg_ids))  # body capsules first, then the limbs' segments in order
    raw[limb] = seg_ids[cap[limb] - nb]
    part, parent, bends = _parts(raw, cr, names, bending)
    return dict(V=vertices, F=faces, joints=J, articulates=np.ones(len(names), bool), bending=bending, part=part,
                part_parent=parent, part_bends=bends)


def _placements(tr, labels, ref):
    """Joints on the true segments: the paper's (boundary centroid on the curve skeleton) and ours
    (the centre of rotation where it is determined), each fitted and scored."""
    from pipeline.armature_fit import articulated_model, fit_sequence
    from pipeline.armature_score import articulation_scores
    from pipeline.armature_skeleton import articulated_skeleton, curve_skeleton

    V, F = tr["V"], tr["F"]
    rest = np.asarray(V[ref], dtype=np.float64)
    cs = curve_skeleton(rest, F)
    size = float(np.linalg.norm(np.ptp(rest, axis=0)))
    out = {}
    for key, refine in (("paper", False), ("pivot", True)):
        sk = articulated_skeleton(rest, F, labels, cs, motion=V, reference=ref, refine_joints=refine,
                                  whole_crossing_paths=True)
        fit = fit_sequence(articulated_model(rest, F, sk), np.asarray(V, dtype=np.float64))
        out[key] = articulation_scores(fit.joints[:, sk.articulation], tr["joints"], size=size,
                                       articulates=tr["articulates"], bending=tr["bending"])
    return out


def accuracy(names=("cow", "pipe", "starfish", "quadruped", "biped"), skinned=(0.02,)) -> None:
    """Per stage: the segmentation against the true rigid parts, the joints placed on the true segments
    (the paper's placement and the centre of rotation), and the whole rig against the true articulations;
    then the creatures skinned with blends of ``skinned`` (fractions of the size, :func:`_truth_skinned`)."""
    from pipeline.armature import build_armature
    from pipeline.armature_score import articulation_scores, bending_parts, segment_agreement
    from stage.benchmarks._data import SHARED_DATA

    print(f"{'subject':12} {'V':>6} {'T':>4} {'bend':>4} | {'segs':>4} {'true':>4} {'purity':>6} {'compl':>6} | "
          f"{'true segs: paper R/P/err%':>26} {'pivot R/P/err%':>18} | {'rig: R':>6} {'P':>5} {'err%':>5} {'vert%':>5} "
          f"{'s':>5}")
    creatures = [n for n in names if n not in ("cow", "pipe")]
    for name in [*names, *(f"{n}~{100 * sg:g}%" for sg in skinned for n in creatures)]:
        if name in ("cow", "pipe"):
            if not (SHARED_DATA / ("cow_poses" if name == "cow" else "tzionas_pipe")).is_dir():
                print(f"{name:12} skipped: {SHARED_DATA} is absent")
                continue
            tr = (_truth_cow if name == "cow" else _truth_pipe)(SHARED_DATA)
        elif "~" in name:  # skinned: blends of the true parts' motions, sigma in % of the size
            tr = _truth_skinned(name.split("~")[0], float(name.split("~")[1][:-1]) / 100)
        else:
            tr = _truth_creature(name)
        t0 = time.perf_counter()
        rig = build_armature(tr["V"], tr["F"], units=tr["units"], fps=tr["fps"], lambda_thr=tr["lambda_thr"],
                             whole_crossing_paths=True)  # as ``stage armature --meshes``
        secs = time.perf_counter() - t0
        truth = bending_parts(tr["part"], tr["part_parent"], tr["part_bends"])
        pur, comp = segment_agreement(rig.segmentation.labels, truth)
        pl = _placements(tr, truth, rig.reference)
        sc = articulation_scores(rig.fit.joints[:, rig.skeleton.articulation], tr["joints"], size=rig.size,
                                 articulates=tr["articulates"], bending=tr["bending"])

        def rpe(s):
            return f"{s['recall']:.2f}/{s['precision']:.2f}/{100 * s['error']:.1f}"

        print(f"{name:12} {tr['V'].shape[1]:>6} {len(tr['V']):>4} {sc['bending']:>4} | {rig.segmentation.n_segments:>4} "
              f"{int(truth.max()) + 1:>4} {pur:>6.2f} {comp:>6.2f} | {rpe(pl['paper']):>26} {rpe(pl['pivot']):>18} | "
              f"{sc['recall']:>6.2f} {sc['precision']:>5.2f} {100 * sc['error']:>5.1f} "
              f"{100 * rig.fit.errors.mean() / rig.size:>5.2f} {secs:>5.1f}", flush=True)


def take_armature(name: str, root, *, frames: int = 30, n_cameras: int = 8, size=(640, 480), seed: int = 3,
                  fps: float = 30.0, parts: str = "motion", labels: bool = False, colour: bool = False,
                  armature_rounds=None, armature_parts: str = "motion"):
    """A simulated take of ``name`` through ``process``, ``track`` and ``armature`` with their defaults, in
    ``root``; -> (take, results directory, rig, seconds per step). ``parts="limbs"``: tracked with the template's
    limb/body labels (``stage track --labels``) and the armature's parts from them (``stage armature --parts
    limbs``).

    The tracking's options as ``stage track RESULTS_DIR`` takes them: ``labels`` (``--labels``, implied by
    ``parts="limbs"``), ``colour`` (``--colour``), ``armature_rounds`` (``--armature-rounds``: the take tracked
    again with this many rounds of :func:`pipeline.track_armature.track_with_armature`; None: the track step's
    default, :class:`pipeline.process.TrackParams`) and ``armature_parts``
    (``--armature-parts``; ``"limbs"`` needs ``armature_rounds`` and the labels)."""
    _check_tracking(parts=parts, labels=labels, colour=colour, armature_rounds=armature_rounds,
                    armature_parts=armature_parts)
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.armature_files import armature_results
    from pipeline.process import process_take

    root = Path(root)
    secs = {}
    t0 = time.perf_counter()
    sim = simulate_take(name, n_cameras=n_cameras, frames=frames, size=tuple(size), seed=seed, fps=fps)
    res = root / "results"
    process_take(record_take(sim, root / f"{name}.h5"), res, executor=None)
    secs["process"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    labels = labels or parts == "limbs"
    track = {key: True for key, on in (("labels", labels), ("colour", colour)) if on}
    if armature_rounds is not None:
        track["armature_rounds"] = armature_rounds
    if armature_parts != "motion":
        track["armature_parts"] = armature_parts
    process_take(root / f"{name}.h5", res, steps=("track",), executor=None, **({"params": {"track": track}} if track else {}))
    secs["track"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rig = armature_results(res, parts="limbs") if parts == "limbs" else armature_results(res)
    secs["rig"] = time.perf_counter() - t0
    return sim, res, rig, secs


def take_scores(sim, res, rig) -> dict:
    """The rig of a simulated take against the creature's joints at the take's times (recall over the
    joints whose parts turn against each other by 10 degrees or more), and the tracking it was built
    on: distance of the tracked vertices from their true points and the motion the tracking invents
    where the body is rigid (voxels, mean over vertices, worst frame)."""
    import json

    from fake_cameras.surface_motion import invented_motion, tracking_errors
    from pipeline.armature_files import load_sequence, tracked_meshes
    from pipeline.armature_score import articulation_scores, bending_parts, segment_agreement

    V, F, _ = load_sequence(tracked_meshes(res))
    reference = int(json.loads((Path(res) / "tracked" / "track.json").read_text())["reference_frame"])
    tr = _truth_take(sim, rig, V, F, reference)
    J, bending = tr["joints"], tr["bending"]
    sc = articulation_scores(rig.fit.joints[:, rig.skeleton.articulation], J, size=rig.size, bending=bending)
    truth = bending_parts(tr["part"], tr["part_parent"], tr["part_bends"])
    sc["purity"], sc["completeness"] = segment_agreement(rig.segmentation.labels, truth)
    sc["true_parts"] = int(truth.max()) + 1
    sc["placements"] = _placements(tr, truth, rig.reference)
    err, _, _ = tracking_errors(sim.creature, sim.times, res)
    sc["track_error"] = float(err.mean(axis=1).max())
    sc["invented"] = float(np.max(invented_motion(sim.creature, sim.times, res)))
    sc["joints"] = len(bending)
    sc["noise"] = segmentation_noise(V, F, truth)
    sc["true_tracks"] = true_track_scores(sim, rig, V, F, tr, reference)
    return sc


def segmentation_noise(vertices, faces, parts, *, n_samples: int = 1000) -> dict:
    """How much the motion segmentation's distances see where the body is rigid: eqs. 8-9 of Tzionas & Gall
    2016 (:func:`pipeline.trajectory_distances.trajectory_distances`, the segmentation's samples, interval and
    reference millimetres) between samples of one true part and of two, and the eigenvalues below the
    small-motion threshold.

    Parameters
    ----------
    vertices : (T, V, 3) float ndarray
    faces : (F, 3) int ndarray
    parts : (V,) int ndarray
        True part of every vertex (parts joined across joints that do not bend,
        :func:`pipeline.armature_score.bending_parts`).
    n_samples : int

    Returns
    -------
    dict
        ``dv_within``, ``dv_across``: median ``d^v`` (reference mm) over the sample pairs of one part and of two
        parts; ``dn_within``, ``dn_across``: the same of ``d^n`` (degrees); ``below_small_motion``: eigenvalues of
        the normalised Laplacian below :data:`pipeline.motion_segmentation.SMALL_MOTION_THR` (at most
        ``max_clusters`` + 1 = 65 are computed).
    """
    from pipeline.mesh_primitives import vertex_normals
    from pipeline.motion_segmentation import (
        REFERENCE_SIZE,
        SMALL_MOTION_THR,
        check_sequence,
        interval_length,
        sample_vertices,
        spectral_clusters,
        subject_size,
    )
    from pipeline.trajectory_distances import trajectory_distances

    v, f = check_sequence(vertices, faces)
    parts = np.asarray(parts)
    if parts.shape != (v.shape[1],):
        raise ValueError(f"parts must have one entry per vertex ({v.shape[1]}), got shape {parts.shape}")
    if v.shape[0] < 2:
        raise ValueError("vertices: one frame has no motion to measure")
    to_ref = REFERENCE_SIZE / subject_size(v)
    s = sample_vertices(v[0], n_samples)
    dt = interval_length(v[:, s], to_reference=to_ref)
    normals = np.stack([vertex_normals(np.asarray(x, dtype=np.float64), f)[s] for x in v])
    dv, dn = trajectory_distances(v[:, s], normals, interval=dt)
    lam = 0.1 * to_ref  # the segmentation's affinity (lambda = 0.1 per reference mm)
    _, eig, _ = spectral_clusters(np.exp(-lam * (dv * (dn + 1.0)).astype(np.float64)), lambda_thr=SMALL_MOTION_THR,
                                  restarts=1)
    iu = np.triu_indices(len(s), 1)
    same = (parts[s][:, None] == parts[s][None])[iu]

    def med(x, m):
        return float(np.median(x[iu][m])) if m.any() else float("nan")

    return {"dv_within": med(dv * to_ref, same), "dv_across": med(dv * to_ref, ~same),
            "dn_within": med(np.degrees(dn), same), "dn_across": med(np.degrees(dn), ~same),
            "below_small_motion": int((eig < SMALL_MOTION_THR).sum())}


def true_track_scores(sim, rig, vertices, faces, truth: dict, reference: int) -> dict:
    """The armature built, as ``stage armature RESULTS_DIR`` builds it (but with every bone that leaves the mesh split,
    ``whole_crossing_paths`` off), on the simulator's *true* tracks of the
    same template vertices (every vertex carried by the capsule it lies on at the tracking's reference frame
    ``reference``, a frame number, :func:`fake_cameras.surface_motion.surface_point_tracks`), scored as the
    tracked one (``truth``: :func:`_truth_take`): what the
    segmentation and the joints reach when the tracking is exact."""
    from fake_cameras.surface_motion import surface_point_tracks
    from pipeline.armature import build_armature
    from pipeline.armature_score import articulation_scores, bending_parts, segment_agreement
    from pipeline.motion_segmentation import MIN_GAP

    times = np.asarray(sim.times)[rig.frame_indices]
    at = int(np.flatnonzero(rig.frame_indices == reference)[0])
    V = surface_point_tracks(sim.creature, np.asarray(vertices[at], dtype=np.float64), [times[at], *times])[1:]
    arm = build_armature(V, faces, frame_indices=rig.frame_indices, peel_parts=False, min_gap=MIN_GAP)
    sc = articulation_scores(arm.fit.joints[:, arm.skeleton.articulation], truth["joints"], size=arm.size,
                             bending=truth["bending"])
    parts = bending_parts(truth["part"], truth["part_parent"], truth["part_bends"])
    sc["purity"], sc["completeness"] = segment_agreement(arm.segmentation.labels, parts)
    sc["segments"], sc["lambda_thr"] = arm.segmentation.n_segments, arm.segmentation.lambda_thr
    sc["vertex_error"] = float(arm.fit.errors.mean() / arm.size)
    sc["noise"] = segmentation_noise(V, faces, parts)
    return sc


def take_accuracy(names, *, frames: int = 30, seeds=(3,), parts: str = "motion", labels: bool = False,
                  colour: bool = False, armature_rounds=None, armature_parts: str = "motion", copies: int = 0) -> None:
    """Simulated takes (8 cameras, 640x480, each of ``seeds``) through process, track and armature, scored
    (``parts``, ``labels``, ``colour``, ``armature_rounds``, ``armature_parts``: as :func:`take_armature`); with
    ``copies``, each take's armature also on that many moved copies of its tracking (:func:`copies_scores`)."""
    import tempfile

    tracking = dict(labels=labels, colour=colour, armature_rounds=armature_rounds, armature_parts=armature_parts)
    _check_tracking(parts=parts, **tracking)
    copies = check_copies(copies)
    if not names:
        return
    flags = [f"--{key.replace('_', '-')}" + ("" if value is True else f" {value}") for key, value in tracking.items()
             if (value or (key == "armature_rounds" and value is not None))
             and not (key == "armature_parts" and value == "motion")]
    if parts != "motion" or flags:
        how = " ".join(["--labels" if parts == "limbs" and "--labels" not in flags else "", *flags]).strip()
        print(f"\nthe takes tracked as `stage track {how}`".rstrip() + f", the armature's parts --parts {parts}")
    print(f"\n{'take':12} {'T':>3} {'track vx':>8} {'invent vx':>9} | {'segs':>4} {'true':>4} {'purity':>6} {'compl':>6} | "
          f"{'true segs: paper R/P/err%':>26} {'pivot R/P/err%':>18} | {'arts':>4} {'bend':>4} {'R':>5} {'P':>5} "
          f"{'err%':>5} {'vert%':>5} | {'process s':>9} {'track s':>7} {'rig s':>5}")
    for seed in seeds:
        for name in names:
            with tempfile.TemporaryDirectory(prefix=f"bench-rig-{name}-") as tmp:
                sim, res, rig, secs = take_armature(name, tmp, frames=frames, seed=int(seed), parts=parts, **tracking)
                sc = take_scores(sim, res, rig)
                spread = copies_scores(sim, res, rig, copies=copies, parts=parts) if copies else None
            print(take_row(f"{name} s{seed}", frames, rig, sc, secs), flush=True)
            if spread:
                print(copies_row(sc, spread), flush=True)


def copies_scores(sim, res, rig, *, copies: int, parts: str = "motion", sigma: float = COPY_SIGMA) -> list[dict]:
    """The armature of moved copies of a take's tracking, built and scored as the take's own.

    Every copy is the results directory ``res`` with its tracked template's vertices moved by N(0, ``sigma``) mm
    per coordinate (seeds 1..``copies``); its armature is built by :func:`pipeline.armature_files.armature_results`
    (``parts`` as :func:`take_armature` takes it) and scored against the creature's joints as :func:`take_scores`
    scores ``rig``, the armature of the tracking itself.

    Returns
    -------
    list of dict
        One per copy: ``recall``, ``precision``, ``segments`` and ``same`` (True when its segmentation is
        ``rig``'s, up to the segments' numbering).
    """
    import json
    import shutil
    import tempfile

    from pipeline.armature_files import armature_results, load_sequence, tracked_meshes
    from pipeline.armature_score import articulation_scores

    copies = check_copies(copies)
    check_sigma(sigma)
    if parts not in ("motion", "limbs"):
        raise ValueError(f"parts must be 'motion' or 'limbs', got {parts!r}")
    res = Path(res)
    reference = int(json.loads((res / "tracked" / "track.json").read_text())["reference_frame"])
    out = []
    for seed in range(1, copies + 1):
        with tempfile.TemporaryDirectory(prefix="bench-rig-copy-") as tmp:
            copy = Path(tmp) / "results"
            copy.mkdir()
            for entry in res.iterdir():
                if entry.name not in ("tracked", "rig"):
                    (copy / entry.name).symlink_to(entry.resolve())
            shutil.copytree(res / "tracked", copy / "tracked")
            move_meshes(sorted((copy / "tracked").glob("*.ply")), seed=seed, sigma=sigma)
            moved = armature_results(copy, parts="limbs") if parts == "limbs" else armature_results(copy)
            V, F, _ = load_sequence(tracked_meshes(copy))
        tr = _truth_take(sim, moved, V, F, reference)
        sc = articulation_scores(moved.fit.joints[:, moved.skeleton.articulation], tr["joints"], size=moved.size,
                                 bending=tr["bending"])
        out.append({"recall": sc["recall"], "precision": sc["precision"], "segments": moved.segmentation.n_segments,
                    "same": _same_partition(rig.segmentation.labels, moved.segmentation.labels)})
    return out


def copies_row(sc: dict, spread: list[dict]) -> str:
    """The line under a take's row: its recall / precision with those of its moved copies, mean (least..most)."""
    def stat(key):
        return spread_cell([sc[key], *(c[key] for c in spread)], 2)

    segs = [c["segments"] for c in spread]
    return (f"{'  copies':12} the tracking and {len(spread)} copies moved by {1000 * COPY_SIGMA:g} um: recall "
            f"{stat('recall')}, precision {stat('precision')}; segments {min(segs)}..{max(segs)}, the tracking's "
            f"segmentation in {sum(c['same'] for c in spread)} of {len(spread)}")


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two labellings of the same vertices make the same segments (whatever their numbers)."""
    pairs = np.unique(np.stack([np.asarray(a), np.asarray(b)], 1), axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


def take_row(name: str, frames: int, rig, sc: dict, secs: dict) -> str:
    """One line of :func:`take_accuracy`'s table."""
    def rpe(s):
        return f"{s['recall']:.2f}/{s['precision']:.2f}/{100 * s['error']:.1f}"

    pl, tt = sc["placements"], sc["true_tracks"]
    return (f"{name:12} {frames:>3} {sc['track_error']:>8.2f} {sc['invented']:>9.2f} | {rig.segmentation.n_segments:>4} "
            f"{sc['true_parts']:>4} {sc['purity']:>6.2f} {sc['completeness']:>6.2f} | {rpe(pl['paper']):>26} "
            f"{rpe(pl['pivot']):>18} | {sc['found']:>4} {sc['bending']:>4} {sc['recall']:>5.2f} {sc['precision']:>5.2f} "
            f"{100 * sc['error']:>5.1f} {100 * rig.fit.errors.mean() / rig.size:>5.2f} | {secs.get('process', 0):>9.0f} "
            f"{secs.get('track', 0):>7.0f} {secs.get('rig', 0):>5.0f}\n"
            f"{'  true':12} {'':>3} {'tracks':>8} {'thr ' + format(tt['lambda_thr'], '.2f'):>9} | {tt['segments']:>4} "
            f"{sc['true_parts']:>4} "
            f"{tt['purity']:>6.2f} {tt['completeness']:>6.2f} | {'':>26} {'':>18} | {tt['found']:>4} {tt['bending']:>4} "
            f"{tt['recall']:>5.2f} {tt['precision']:>5.2f} {100 * tt['error']:>5.1f} {100 * tt['vertex_error']:>5.2f} |\n"
            f"{'  noise':12} {_noise(sc['noise'], tt['noise'])}")


def _noise(tracked: dict, true: dict) -> str:
    """The segmentation's distances within one part and across two (:func:`segmentation_noise`), tracked / true."""
    def two(key, fmt):
        return f"{format(tracked[key], fmt)}/{format(true[key], fmt)}"

    return (f"tracked/true: d^v within {two('dv_within', '.1f')} across {two('dv_across', '.1f')} ref mm; "
            f"d^n within {two('dn_within', '.0f')} across {two('dn_across', '.0f')} deg; "
            f"eigenvalues below 0.98 {tracked['below_small_motion']}/{true['below_small_motion']}")
