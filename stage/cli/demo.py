"""``stage demo``: the whole job end to end on the simulated rig.

1. record a board take with the simulated cameras (real-time replay, clock offsets, jitter);
2. calibrate the rig from it (Zhang per camera, then bundle adjustment; world = the board
   lying on the floor in the first view);
3. record a creature take and write its ground truth beside it;
4. process it: keying, visual hull and surface per frame set, per-frame skeletons, tip
   correspondence and one spine (``spine.json``);
5. print the spine's accuracy against the ground truth;
6. write the rigged, animated model (GLB) and the HTML report.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from calib.camera import rotation_angle_deg
from stage.cli._args import parse_size

ORDER = 1
log = logging.getLogger("stage.demo")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="record, calibrate and process a simulated take end to end",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("demo-out"), help="output directory (default ./demo-out)")
    p.add_argument("--subject", default="starfish", choices=("starfish", "quadruped", "biped"), help="creature")
    p.add_argument("--cameras", type=int, default=12, help="simulated cameras, 4-24 (default 12)")
    p.add_argument("--frames", type=int, default=30, help="creature frames (default 30)")
    p.add_argument("--board-views", type=int, default=72, help="board views in the calibration take (default 72)")
    p.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    p.add_argument("--board", choices=("charuco", "chessboard"), default="charuco", help="calibration board")
    p.add_argument("--true-calibration", action="store_true", help="skip calibration and use the simulator's true cameras")
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--rgbd", action="store_true",
                   help="instead: the single RGB-D camera path (simulated pipe bent at 1/2: take, tracking, rig)")
    p.set_defaults(func=run)


def _capture(armature_dict: dict, path: Path, frames: int, *, calibration=None, no_progress: bool, label: str):
    from tqdm import tqdm

    from stage.capture import capture_take
    from stage.rig import parse_rig

    rig = parse_rig(armature_dict, source=f"simulated {label} rig")
    # rendering happens before the clock starts: the simulated cameras replay at the rig's fps
    from fake_cameras.device import take_for_rig

    t0 = time.perf_counter()
    cam0 = rig.cameras[0]
    take_for_rig(rig, size=(cam0.width, cam0.height), fps=rig.fps)
    log.info("%s: rendered in %.1f s", label, time.perf_counter() - t0)
    bar = tqdm(total=frames, desc=f"capture {label}", unit="set", disable=no_progress)

    def progress(p) -> None:
        bar.n = p.sets
        bar.set_postfix(fps=f"{p.fps:.1f}", drops=p.drops)
        bar.refresh()

    try:
        result = capture_take(rig, path, frames=frames, calibration=calibration, progress=progress, overwrite=True)
    finally:
        bar.close()
    return rig, result


def _calibrate(board_take: Path, board, *, world_frame: int, no_progress: bool):
    """Detect the board in every frame set of the take (as ``stage calibrate`` does), then
    Zhang per camera and one bundle adjustment; the world is the board of ``world_frame``."""
    from calib.rig import calibrate_rig
    from stage.cli.calibrate import detect_take

    detections, sizes, cameras = detect_take(board_take, board, progress=not no_progress)
    return calibrate_rig(detections, sizes, board, cameras=cameras, world="board", world_frame=world_frame)


def _calibration_errors(est, true) -> dict:
    """Pose and intrinsic errors of a calibration against the truth (same world frame)."""
    f_err, c_err, pos_err, rot_err = [], [], [], []
    for cam in true:
        e = est[cam.name]
        f_err.append(abs(e.K[0, 0] / cam.K[0, 0] - 1) * 100)
        c_err.append(float(np.linalg.norm(e.K[:2, 2] - cam.K[:2, 2])))
        pos_err.append(float(np.linalg.norm(e.center - cam.center)))
        dR = e.R @ cam.R.T
        rot_err.append(rotation_angle_deg(dR))
    return {
        "focal_error_pct_max": max(f_err),
        "principal_point_error_px_max": max(c_err),
        "centre_error_mm_max": max(pos_err),
        "rotation_error_deg_max": max(rot_err),
    }


def _transform_spine(spine: dict, R: np.ndarray, T: np.ndarray) -> dict:
    """A copy of a spine dictionary with every point mapped by ``x -> R x + T``."""

    def tf(p):
        return None if p is None else (R @ np.asarray(p, float) + T).tolist()

    out = dict(spine)
    out["frames"] = [
        {
            **fr,
            "tips": {k: tf(v) for k, v in fr["tips"].items()},
            "axes": {k: (None if v is None else [tf(q) for q in v]) for k, v in fr.get("axes", {}).items()},
        }
        for fr in spine["frames"]
    ]
    return out


def _board_calibration(args: argparse.Namespace, size, out: Path, summary: dict):
    """Record the board take, calibrate the rig from it, compare with the simulator's cameras and write
    ``calibration.toml`` and ``calibration-report.txt``; -> the calibration (``summary`` gets its figures)."""
    from calib.formats import write_calibration
    from calib.rig import group_warnings
    from fake_cameras.device import take_for_rig
    from fake_cameras.record import take_scene_frames
    from fake_cameras.rigs import simulated_rig_dict

    board_rig = simulated_rig_dict(
        args.cameras, subject=f"board-{args.board}", frames=args.board_views, size=size, name="demo-board"
    )
    board_path = out / "board.h5"
    rig, cap = _capture(board_rig, board_path, args.board_views, no_progress=args.no_progress, label="board")
    print(f"board take: {cap.sets} frame sets from {args.cameras} cameras -> {board_path}")
    views = take_for_rig(rig, size=size, fps=rig.fps)
    # the simulated board lies on the floor at the world origin in scene frame 0
    floor_sets = np.flatnonzero(take_scene_frames(board_path, views.images.shape[0]) == 0)
    if floor_sets.size == 0:
        raise ValueError("the board take missed the view of the board on the floor; record more --board-views")
    rigcal = _calibrate(board_path, views.board, world_frame=int(floor_sets[0]), no_progress=args.no_progress)
    (out / "calibration-report.txt").write_text(rigcal.report() + "\n")
    ext = rigcal.extrinsics
    calibration = rigcal.calibration
    errs = _calibration_errors(calibration, views.calibration)
    write_calibration(calibration, out / "calibration.toml", format="toml")
    geom = ext.geometry
    print(
        f"calibration: RMS {ext.rms:.3f} px; "
        f"board geometry error (corner pairs) RMS {geom.get('pairs_rms', float('nan')):.2f} mm; "
        f"vs truth: focal <= {errs['focal_error_pct_max']:.2f} %, centres <= {errs['centre_error_mm_max']:.2f} mm, "
        f"rotations <= {errs['rotation_error_deg_max']:.3f} deg -> {out / 'calibration.toml'}"
    )
    print(f"  calibration {rigcal.verdict()}")
    for w in group_warnings(rigcal.warnings):  # the report file holds them too; the terminal must show them
        print(f"  calibration warning: {w}")
    summary["calibration"] = {"rms_px": ext.rms, "geometry": geom, **errs}
    return calibration


def _take_away(results: Path, take_path: Path, summary: dict, out: Path) -> None:
    """The rigged model and the report of the processed take, and the closing lines (the last: the command that
    builds the take's armature next)."""
    from pipeline.gltf_export import export_rig
    from pipeline.report import write_report

    glb = export_rig(results)
    report = write_report(results, take=take_path)
    print(f"rigged model (glTF, opens in Blender and three.js): {glb}")
    print(f"report (open in a browser, works offline): {report}")
    if "spine_in_true_frame" in summary:
        a = summary["spine_in_true_frame"]
        print(
            f"  with the calibrated world aligned to the simulator's (camera centres, rigid): tips within 3 % in "
            f"{100 * a['tip_within_tol']:.1f} % (median {100 * a['tip_error_median']:.2f} %), limb axes "
            f"{100 * a['limb_axis_error_mean']:.2f} % of size"
        )
    print(f"demo finished in {summary['seconds']:.0f} s; everything is in {out}/ (summary.json)")
    print(f"next, the armature (segments, joints where the creature bends): stage armature {results} "
          "(tracks the template through the take first; docs/armature-format.md)")


def _accuracy(results: Path, sim, calibration, summary: dict) -> dict:
    """The spine of ``results`` against the simulator's truth (``summary["spine"]``; with a calibration
    of our own, also in the true frame: ``summary["spine_in_true_frame"]``)."""
    from fake_cameras.evaluate import evaluate_spine

    spine = json.loads((results / "spine.json").read_text())
    tips = sim.tip_array()
    axes = {name: np.stack([a[name] for a in sim.axes]) for name in sim.limb_names}
    poses = sim.poses
    acc = evaluate_spine(spine, tips, axes, list(sim.limb_names), poses=poses)
    summary["spine"] = acc
    if calibration is not None:
        # the calibrated world (the board on the floor) sits a little off the simulator's world;
        # measure the spine's shape in the true frame too, after the rigid motion that best maps
        # the calibrated camera centres onto the true ones (Arun et al. 1987)
        from pipeline.correspond import arun_alignment

        R, T, _ = arun_alignment(calibration.centers(), sim.calibration.centers())
        aligned = _transform_spine(spine, R, T)
        acc_aligned = evaluate_spine(aligned, tips, axes, list(sim.limb_names), poses=poses)
        summary["spine_in_true_frame"] = acc_aligned
    return acc


def run(args: argparse.Namespace) -> int:
    if args.rgbd:
        from stage.cli._demo_rgbd import run_rgbd

        return run_rgbd(args)
    from fake_cameras.device import take_for_rig
    from fake_cameras.record import take_scene_frames
    from fake_cameras.rigs import simulated_rig_dict
    from fake_cameras.take import write_ground_truth
    from pipeline.process import ProcessParams, process_take
    from stage.cli._pool import worker_pool
    from stage.cli._progress import StepBars
    from stage.store import attach_calibration

    size = parse_size(args.size)
    if not 4 <= args.cameras <= 24:
        raise ValueError(f"--cameras must be in 4..24, got {args.cameras}")
    if args.frames < 2:
        raise ValueError("--frames must be at least 2")
    if args.board_views < 8:
        raise ValueError("--board-views must be at least 8")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    summary: dict = {}

    # 1-2. board take and calibration
    calibration = None if args.true_calibration else _board_calibration(args, size, out, summary)

    # 3. creature take + ground truth
    creature_rig = simulated_rig_dict(args.cameras, subject=args.subject, frames=args.frames, size=size, name="demo")
    take_path = out / f"{args.subject}.h5"
    rig, cap = _capture(creature_rig, take_path, args.frames, calibration=calibration,
                        no_progress=args.no_progress, label=args.subject)
    # the ground truth in take order: frame set k shows scene frame idx[k] (k unless frames were dropped)
    idx = take_scene_frames(take_path, take_for_rig(rig, size=size, fps=rig.fps).n_frames)
    sim = take_for_rig(rig, size=size, fps=rig.fps).select(idx)
    if calibration is None:
        attach_calibration(take_path, sim.calibration)
    gt_path = write_ground_truth(sim, take_path)
    stats = cap.stats.to_dict() if hasattr(cap.stats, "to_dict") else {}
    print(
        f"creature take: {cap.sets} frame sets, {sum(cap.drops.values())} dropped frames, sync spread median "
        f"{stats.get('spread_median_ms', float('nan')):.2f} ms -> {take_path} (ground truth {gt_path.name})"
    )

    # 4. process
    results = out / f"{args.subject}-results"
    executor = worker_pool(args.workers)
    try:
        with StepBars(disable=args.no_progress) as progress:
            result = process_take(take_path, results, params=ProcessParams(), executor=executor, progress=progress)
    finally:
        if executor is not None:
            executor.shutdown(cancel_futures=True)
    print(f"processed: {result.frames} frame sets in {result.report['total_seconds']:.1f} s -> {results}")

    # 5. accuracy
    acc = _accuracy(results, sim, calibration, summary)
    summary["seconds"] = time.perf_counter() - t_start
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    print(
        f"spine accuracy vs ground truth: K = {acc['K']} (true {acc['true_limbs']}); "
        f"tips within 3 % of size ({acc['size']:.0f} mm) in {100 * acc['tip_within_tol']:.1f} % of frames "
        f"(median error {100 * acc['tip_error_median']:.2f} %); identities consistent in "
        f"{100 * acc['identity_consistent']:.1f} % of frames; limb axes off by {100 * acc['limb_axis_error_mean']:.2f} % of size "
        f"outside the body"
    )
    # 6. what users take away: a rigged, animated model and a page to look at
    _take_away(results, take_path, summary, out)
    return 0
