"""``stage bench calib``: rig calibration speed and accuracy on the simulated dome, or (``--real DIR``)
on real footage in caliscope's layout against that program's calibration.

Synthetic board views (true projections through ``fake_cameras.dome.make_dome``
cameras plus Gaussian noise) -> per-camera intrinsics -> one bundle adjustment;
errors against the true cameras after the best rigid alignment.

Side by side, aniposelib's ``CameraGroup.calibrate_rows`` runs on the same
corners. It is a benchmark-only extra, never a runtime dependency: it declares
opencv-contrib-python (the GUI build, which would replace our headless OpenCV 5)
and needs numba, pandas, toml and jax, so it lives in its own virtual environment
and runs in a subprocess (``_anipose_worker.py``): corners go in as an npz, the
calibrated cameras come back as JSON (aniposelib's TOML layout), and both
calibrations are scored here against the same ground truth. Setup, once::

    python3.11 -m venv ~/.cache/capture-stage/anipose-venv
    ~/.cache/capture-stage/anipose-venv/bin/pip install --no-deps aniposelib
    ~/.cache/capture-stage/anipose-venv/bin/pip install opencv-contrib-python-headless numba pandas scipy toml tqdm jax

(``--anipose-python PATH`` or ``$CAPTURE_STAGE_ANIPOSE_PYTHON`` point elsewhere.)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from calib.camera import rotation_angle_deg

NAME = "calib"
HELP = "intrinsics + bundle adjustment for a simulated 12-camera dome (vs aniposelib if installed)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--real", type=Path, metavar="DIR",
                   help="instead: real footage in caliscope's layout (DIR/extrinsic/<camera>.mp4, DIR/charuco.toml, "
                   "DIR/camera_array.toml): held-out error per camera, ours and the reference calibration's on the "
                   "same detections, focal and distance differences, seconds")
    p.add_argument("--distortion", choices=("prior", "full", "auto"), default="prior",
                   help="each camera's distortion model, as stage calibrate --distortion (default prior)")
    p.add_argument("--cameras", type=int, default=12)
    p.add_argument("--views", type=int, default=60)
    p.add_argument("--noise", type=float, default=0.3, help="corner noise sigma, px (default 0.3)")
    p.add_argument("--board", choices=("chessboard", "charuco"), default="chessboard")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--scipy", action="store_true", help="also run the bundle adjustment with scipy least_squares")
    p.add_argument("--anipose-python", metavar="PATH", default=None,
                   help="python of an isolated virtual environment with aniposelib, run in a subprocess on the "
                        "same corners (default: $CAPTURE_STAGE_ANIPOSE_PYTHON, else "
                        "~/.cache/capture-stage/anipose-venv/bin/python if it exists; else the column is skipped "
                        "and the one-line setup command is printed)")
    p.add_argument("--no-anipose", action="store_true", help="skip the aniposelib column")
    p.add_argument("--draws", type=int, default=0, metavar="N",
                   help="instead: how honest the reported uncertainties are over N noise draws (seeds SEED..SEED+N-1, "
                        "calibrate_rig defaults): per intrinsic the RMS of (estimate - truth) / reported sigma, the "
                        "chi-square of each camera's intrinsics and of its rotation relative to the reference "
                        "against their covariances, over their degrees of freedom (all 1 when honest)")
    p.add_argument("--anipose-timeout", type=float, default=1800.0, metavar="S",
                   help="give up on aniposelib after S seconds (default 1800)")


def _errors(est, truth) -> dict:
    A = np.concatenate([est.centers()] + [np.stack([c.center + 300 * c.R[k] for c in est]) for k in range(3)])
    B = np.concatenate([truth.centers()] + [np.stack([c.center + 300 * c.R[k] for c in truth]) for k in range(3)])
    ma, mb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ma).T @ (B - mb))
    R = Vt.T @ np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    t = mb - R @ ma
    f, pp, cen, ang = [], [], [], []
    for e, g in zip(est, truth):
        f.append(100 * abs(e.K[0, 0] / g.K[0, 0] - 1))
        pp.append(float(np.abs(e.K[:2, 2] - g.K[:2, 2]).max()))
        cen.append(float(np.linalg.norm(R @ e.center + t - g.center)))
        dR = (e.R @ R.T) @ g.R.T
        ang.append(rotation_angle_deg(dR))
    return {"focal_%": f, "pp_px": pp, "centre_mm": cen, "rot_deg": ang}


def _line(name: str, secs: float, err: dict, extra: str = "") -> str:
    def mm(v):
        return f"{np.median(v):6.3f} / {np.max(v):6.3f}"

    return (f"{name:<22} {secs:7.2f} s   focal % {mm(err['focal_%'])}   pp px {mm(err['pp_px'])}   "
            f"centre mm {mm(err['centre_mm'])}   rot deg {mm(err['rot_deg'])}  {extra}")


ANIPOSE_VENV = Path("~/.cache/capture-stage/anipose-venv").expanduser()
ANIPOSE_SETUP = (
    "python3.11 -m venv ~/.cache/capture-stage/anipose-venv && "
    "~/.cache/capture-stage/anipose-venv/bin/pip install --no-deps aniposelib && "
    "~/.cache/capture-stage/anipose-venv/bin/pip install opencv-contrib-python-headless numba pandas scipy toml "
    "tqdm jax"
)


def _anipose_python(arg: str | None) -> Path | None:
    """The interpreter of aniposelib's isolated environment: ``--anipose-python``, else
    ``$CAPTURE_STAGE_ANIPOSE_PYTHON``, else the default venv; None when there is none."""
    if arg:
        path = Path(arg).expanduser()
        if not path.is_file():
            raise ValueError(f"--anipose-python: no such interpreter: {path}")
        return path
    env = os.environ.get("CAPTURE_STAGE_ANIPOSE_PYTHON")
    if env:
        path = Path(env).expanduser()
        if not path.is_file():
            raise ValueError(f"CAPTURE_STAGE_ANIPOSE_PYTHON: no such interpreter: {path}")
        return path
    path = ANIPOSE_VENV / "bin" / "python"
    return path if path.is_file() else None


def _write_corners(path: Path, dets, truth, board) -> None:
    """The detected corners, per camera, as the worker's input npz."""
    if board.type == "chessboard":
        b = {"type": "chessboard", "corners": list(board.corners), "square_mm": board.square_mm}
    else:
        bits, size = (int(v) for v in re.match(r"DICT_(\d+)X\d+_(\d+)$", board.dictionary).groups())
        b = {"type": "charuco", "squares": list(board.squares), "square_mm": board.square_mm,
             "marker_mm": board.marker_mm, "marker_bits": bits, "dict_size": size}
    arrays = {"names": np.array(truth.names), "sizes": np.array([c.size for c in truth], dtype=np.int64),
              "board": np.array(json.dumps(b))}
    for i, c in enumerate(truth):
        ds = list(dets[c.name])
        arrays[f"corners_{i}"] = np.concatenate([d.corners for d in ds]).astype(np.float64).reshape(-1, 2)
        arrays[f"ids_{i}"] = np.concatenate([d.ids for d in ds]).astype(np.int64).ravel()
        arrays[f"view_{i}"] = np.concatenate([np.full(len(d.ids), k) for k, d in enumerate(ds)]).astype(np.int64)
        arrays[f"frame_{i}"] = np.array([d.frame for d in ds], dtype=np.int64)
    np.savez(path, **arrays)


def _aniposelib(python: Path, dets, truth, board, *, timeout: float):
    """Run ``CameraGroup.calibrate_rows`` in aniposelib's own environment on the same corners.

    Returns ``((calibration, seconds, own_error, versions), None)`` or ``(None, reason)``.
    """
    from calib.formats import calibration_from_aniposelib

    worker = Path(__file__).with_name("_anipose_worker.py")
    with tempfile.TemporaryDirectory(prefix="bench-calib-anipose-") as tmp:
        src, dst = Path(tmp) / "corners.npz", Path(tmp) / "cameras.json"
        _write_corners(src, dets, truth, board)
        try:
            proc = subprocess.run([str(python), "-I", str(worker), str(src), str(dst)], cwd=tmp,
                                  capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return None, f"{python} did not finish within {timeout:.0f} s"
        if not dst.is_file():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            return None, f"{python} exited with {proc.returncode}: {' | '.join(tail)}"
        out = json.loads(dst.read_text())
    if "failed" in out:
        return None, f"aniposelib failed: {out['failed']}"
    calib = calibration_from_aniposelib(out["cameras"])
    return (calib, float(out["seconds"]), float(out["error"]), out.get("versions", {})), None


def _refit_rms(calib, dets, board) -> float:
    """Reprojection RMS (px) of a calibration with its cameras held fixed: every board pose
    is re-fitted (6 DOF, all cameras that see it, linear loss) — the same yardstick for
    any calibration, whatever board poses its own solver ended with."""
    from scipy.optimize import least_squares

    from calib.camera import matrix_to_rodrigues, project_points, rodrigues_to_matrix

    obj = board.object_points()
    by_frame: dict[int, list] = {}
    for c in calib:
        for d in dets[c.name]:
            by_frame.setdefault(d.frame, []).append((c, d))
    sq, n = 0.0, 0
    for views in by_frame.values():
        c0, d0 = max(views, key=lambda v: len(v[1].ids))
        ok, rv, tv = cv2.solvePnP(obj[d0.ids], d0.corners.astype(np.float64), c0.K, c0.dist)
        if not ok:
            continue
        Rb = c0.R.T @ rodrigues_to_matrix(rv.ravel())  # board -> world
        tb = c0.R.T @ (tv.ravel() - c0.t)
        x0 = np.concatenate([matrix_to_rodrigues(Rb), tb])

        def resid(x, views=views):
            R = rodrigues_to_matrix(x[:3])
            out = []
            for c, d in views:
                X = obj[d.ids] @ R.T + x[3:]
                out.append((project_points(X, K=c.K, dist=c.dist, R=c.R, t=c.t) - d.corners).ravel())
            return np.concatenate(out)

        r = least_squares(resid, x0, method="lm").fun
        sq += float(r @ r)
        n += r.size // 2
    return float(np.sqrt(sq / max(n, 1)))


def run_real(root: Path, *, distortion: str = "prior") -> int:
    """Default ``stage calibrate`` on caliscope-layout footage against its reference calibration."""
    import itertools

    from calib.boards import load_board
    from calib.evaluate import reprojection_errors
    from calib.formats import in_units, read_calibration
    from calib.rig import calibrate_rig
    from stage.cli.calibrate import detect_images

    for need in ("extrinsic", "charuco.toml", "camera_array.toml"):
        if not (root / need).exists():
            raise FileNotFoundError(f"--real {root}: no {need} (caliscope layout: extrinsic/<camera>.mp4, "
                                    "charuco.toml, camera_array.toml)")
    board = load_board(root / "charuco.toml")
    ref = in_units(read_calibration(root / "camera_array.toml"), "mm")
    t0 = time.perf_counter()
    dets, sizes, flipped, notes = detect_images(root / "extrinsic", board, progress=False)
    t_det = time.perf_counter() - t0
    t1 = time.perf_counter()
    res = calibrate_rig(dets, sizes, board, cameras=list(sizes), flipped=flipped, holdout_folds=5,
                        distortion=distortion)
    t_cal = time.perf_counter() - t1
    for n in notes + res.evaluation["flipped"]:
        print(f"note: {n}")
    cal = res.calibration
    names = [n for n in cal.names if n in ref.names]
    theirs = reprojection_errors(_subset(ref, names), {n: res.evaluation["detections"][n] for n in names},
                                 board)["per_camera"]
    ours_all = res.evaluation["all_frames"]["per_camera"]
    print(f"{root}: {len(cal)} cameras; detection {t_det:.1f} s, calibration + 5-fold held-out {t_cal:.1f} s")
    print("camera      held-out px  all-frames px | reference px (same detections) | focal fx, fy %")
    for n in names:
        c, r = cal[n], ref[n]
        print(f"{n:<10} {res.held_out_rms()[n]:10.3f} {ours_all[n]['rms']:13.3f}  | {theirs[n]['rms']:12.3f}"
              f"                   | {100 * (c.K[0, 0] / r.K[0, 0] - 1):+6.2f} {100 * (c.K[1, 1] / r.K[1, 1] - 1):+6.2f}")
    cov = res.evaluation.get("rotation_sigma_deg", {}).get("pairs", {})
    folds = (res.evaluation.get("rotation_folds_deg") or {}).get("pairs", {})
    print("pair              distance %   relative rotation deg | our 1-sigma deg: covariance  folds")
    for a, b in itertools.combinations(names, 2):
        do = np.linalg.norm(cal[a].center - cal[b].center)
        dr = np.linalg.norm(ref[a].center - ref[b].center)
        rot = rotation_angle_deg((cal[a].R @ cal[b].R.T).T @ (ref[a].R @ ref[b].R.T))
        key = f"{a} - {b}"
        print(f"{key:<17} {100 * (do / dr - 1):+9.2f}   {rot:8.2f}              | "
              f"{cov.get(key, float('nan')):20.2f} {folds.get(key, float('nan')):6.2f}")
    dropped = {n: r.dropped for n, r in res.intrinsics.items() if r.dropped}
    if dropped:
        print("distortion held at 0 (not supported by the views): "
              + "; ".join(f"{n} {', '.join(d)}" for n, d in dropped.items()))
    print("held-out: 5-fold over frame sets (calibrate on the rest, board pose re-fitted on the fold); the "
          "reference calibration saw all frames, so its figure is in-sample. 1-sigma of our relative rotations: "
          "from the bundle adjustment's covariance, and the grouped jackknife of the 5 fold calibrations")
    return 0


def _board(name: str):
    from calib.boards import Charuco, Chessboard

    return Chessboard((11, 8), 50.0) if name == "chessboard" else Charuco((12, 9), 50.0, 37.0, dictionary="DICT_4X4_100")


def run_draws(args: argparse.Namespace, truth) -> int:
    """``--draws N``: the reported uncertainties against the errors they describe, over N noise draws."""
    from scipy.spatial.transform import Rotation

    from calib.bundle import INTRINSIC_NAMES
    from calib.calibration import Calibration
    from calib.intrinsics import CalibrationError
    from calib.rig import calibrate_rig, intrinsics_moved
    from calib.synthetic import random_board_poses, synthetic_detections

    board = _board(args.board)
    dist = float(np.median(np.linalg.norm(truth.centers() - truth.centers().mean(0), axis=1)))
    true = {c.name: np.array([c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *c.dist]) for c in truth}
    zz, zb, cz, cb, cr, dof, skipped = [], [], [], [], [], [], 0
    moved, rigs_warned, named = [], 0, 0
    for k in range(args.draws):
        poses = random_board_poses(truth, board, args.views, seed=args.seed + k, spread=0.25 * dist)
        dets = synthetic_detections(truth, board, poses, noise_px=args.noise, seed=args.seed + k + 10_000)
        try:
            res = calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names,
                                distortion=args.distortion)
        except CalibrationError:  # a camera the draw's board poses left with too few views
            skipped += 1
            continue
        meta = res.extrinsics.meta
        figures, warned = intrinsics_moved(res.intrinsics, res.calibration)
        moved += [f["chi2"] / f["dof"] for f in figures.values()]
        rigs_warned += bool(warned)
        ref = res.calibration[meta["reference"]]
        for i, cam in enumerate(res.calibration.cameras):
            zhang = res.intrinsics[cam.name]
            free = np.isfinite(np.diag(zhang.covariance))
            for est, cov, z, chi in ((zhang.params, zhang.covariance, zz, cz),
                                     (np.array([cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], *cam.dist]),
                                      meta["intrinsics_cov"][i], zb, cb)):
                d, C = (est - true[cam.name])[free], cov[np.ix_(free, free)]
                z.append(np.where(free, est - true[cam.name], np.nan) / np.sqrt(np.abs(np.diag(cov))))
                chi.append(float(d @ np.linalg.solve(C, d)))
            dof.append(int(free.sum()))
            K = cam.K.copy()
            K[0, 0], K[1, 1] = 1.02 * K[0, 0], 1.02 * K[1, 1]  # the focal length 2 % longer
            wrong = cam.replace(K=K)
            wrong_cal = Calibration(tuple(wrong if c.name == cam.name else c for c in res.calibration.cameras))
            named += any(w.startswith(f"camera {cam.name}:") for w in intrinsics_moved(res.intrinsics, wrong_cal)[1])
            if cam.name != ref.name:
                rel = (cam.R @ ref.R.T) @ (truth[cam.name].R @ truth[ref.name].R.T).T
                r = Rotation.from_matrix(rel).as_rotvec()
                cr.append(float(r @ np.linalg.solve(meta["rotation_cov"][i, i], r)))
    print(f"{args.draws} draws x {len(truth)} cameras x {args.views} board poses ({board.type}), noise {args.noise} px, "
          f"--distortion {args.distortion}: (estimate - truth) / reported sigma, RMS over cameras and draws (1 when "
          "the sigmas are honest)" + (f"; {skipped} draws skipped (a camera with too few views)" if skipped else ""))
    print("  " + " " * 22 + "".join(f"{n:>7}" for n in INTRINSIC_NAMES) + "   chi2 / dof")
    for name, z, chi in (("own calibration (Zhang)", zz, cz), ("rig (bundle adjustment)", zb, cb)):
        rms = np.sqrt(np.nanmean(np.square(z), axis=0))
        print(f"  {name:<22}" + "".join(f"{v:7.2f}" for v in rms) + f"   {np.sum(chi) / np.sum(dof):6.2f}")
    print(f"  rotation relative to the reference camera: chi2 / 3 {np.mean(cr) / 3:.2f} ({len(cr)} cameras)")
    print(f"  the rig's move from each camera's own intrinsics (intrinsics_moved): chi2 / dof {np.mean(moved):.2f}; "
          f"rigs warned {rigs_warned} of {args.draws - skipped}; a focal length 2 % off named on {named} of "
          f"{len(moved)} cameras")
    return 0


def _subset(calib, names):
    from calib.calibration import Calibration

    return Calibration(tuple(calib[n] for n in names), units=calib.units, meta=dict(calib.meta))


def run(args: argparse.Namespace) -> int:
    import logging

    if args.real is not None:
        logging.getLogger("calib").setLevel(logging.ERROR)
        return run_real(args.real, distortion=args.distortion)
    if args.draws < 0:
        raise ValueError(f"--draws must be >= 0, got {args.draws}")

    from calib.extrinsics import calibrate_extrinsics
    from calib.intrinsics import calibrate_intrinsics
    from calib.synthetic import random_board_poses, synthetic_detections

    try:
        from fake_cameras.dome import make_dome
    except ImportError as exc:
        raise ValueError(f"fake_cameras.dome is needed for this benchmark: {exc}") from None
    logging.getLogger("calib").setLevel(logging.ERROR)
    if args.draws:
        return run_draws(args, make_dome(args.cameras))
    python = None if args.no_anipose else _anipose_python(args.anipose_python)  # fail early on a bad path
    truth = make_dome(args.cameras)
    board = _board(args.board)
    dist = float(np.median(np.linalg.norm(truth.centers() - truth.centers().mean(0), axis=1)))
    poses = random_board_poses(truth, board, args.views, seed=args.seed, spread=0.25 * dist)
    dets = synthetic_detections(truth, board, poses, noise_px=args.noise, seed=args.seed + 1)
    n_obs = sum(len(d) for v in dets.values() for d in v)
    print(f"{args.cameras} cameras x {args.views} board poses ({board.type}, {board.n_corners} corners), "
          f"noise {args.noise} px: {sum(len(v) for v in dets.values())} camera views, {n_obs} corners")
    print("errors: median / max over cameras, after the best rigid alignment to the true rig")
    t0 = time.perf_counter()
    intr = [calibrate_intrinsics(dets[c.name], board, c.size, name=c.name, max_views=40,
                                 distortion=args.distortion) for c in truth]
    t_intr = time.perf_counter() - t0
    f = [100 * abs(r.K[0, 0] / c.K[0, 0] - 1) for r, c in zip(intr, truth)]
    pp = [float(np.abs(r.K[:2, 2] - c.K[:2, 2]).max()) for r, c in zip(intr, truth)]
    print(f"{'intrinsics only (Zhang)':<22} {t_intr:7.2f} s   focal % {np.median(f):6.3f} / {np.max(f):6.3f}   "
          f"pp px {np.median(pp):6.3f} / {np.max(pp):6.3f}   (per camera, <= 40 views each; no poses)")
    for solver in ("lm", "scipy") if args.scipy else ("lm",):
        t1 = time.perf_counter()
        res = calibrate_extrinsics(dets, [r.camera() for r in intr], board, world="camera", solver=solver)
        t_ba = time.perf_counter() - t1
        g = res.geometry
        print(_line(f"capture-stage ({solver})", t_intr + t_ba, _errors(res.calibration, truth),
                    f"RMS {_refit_rms(res.calibration, dets, board):.3f} px (BA {res.rms:.3f} px), "
                    f"board {g['neighbor_rms']:.2f} mm, BA {t_ba:.2f} s"))
    from calib.rig import calibrate_rig

    t2 = time.perf_counter()
    rig = calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names, world="camera",
                        distortion=args.distortion)
    t_rig = time.perf_counter() - t2
    g = rig.extrinsics.geometry
    print(_line("capture-stage rig", t_rig, _errors(rig.calibration, truth),
                f"RMS {_refit_rms(rig.calibration, dets, board):.3f} px, board {g['neighbor_rms']:.2f} mm "
                f"(calibrate_rig defaults: intrinsics under the Zhang prior)"))
    if args.no_anipose:
        return 0
    if python is None:
        print(f"{'aniposelib':<22} skipped: no isolated aniposelib environment. It is a benchmark-only extra "
              "(it declares opencv-contrib-python, which must not replace our headless OpenCV 5), so set it up "
              f"once in its own venv:\n    {ANIPOSE_SETUP}\n  or pass --anipose-python PATH")
        return 0
    print(f"aniposelib: running CameraGroup.calibrate_rows in {python} (subprocess, same corners) ...", flush=True)
    out, why = _aniposelib(python, dets, truth, board, timeout=args.anipose_timeout)
    if out is None:
        print(f"{'aniposelib':<22} not available ({why}); setup:\n    {ANIPOSE_SETUP}")
        return 0
    calib, secs, own_err, versions = out
    print(_line("aniposelib", secs, _errors(calib, truth),
                f"RMS {_refit_rms(calib, dets, board):.3f} px (its own error {own_err:.3f} px)"))
    print("  aniposelib " + ", ".join(f"{k} {v}" for k, v in versions.items())
          + "; seconds = calibrate_rows only (no process start-up or imports)")
    print("RMS: all corners, cameras held fixed, every board pose re-fitted (same yardstick for both)")
    return 0
