"""``stage bench calib``: rig calibration speed and accuracy on the simulated dome.

Synthetic board views (true projections through ``fake_cameras.dome.make_dome``
cameras plus Gaussian noise) -> per-camera intrinsics -> one bundle adjustment;
errors against the true cameras after the best rigid alignment. When
aniposelib is importable, its ``CameraGroup.calibrate_rows`` runs on the same
corners (a benchmark-only extra; it needs numba, toml and jax, and declares
opencv-contrib-python, which would replace the headless OpenCV 5 build — install
it in a separate virtual environment).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

NAME = "calib"
HELP = "intrinsics + bundle adjustment for a simulated 12-camera dome (vs aniposelib if installed)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cameras", type=int, default=12)
    p.add_argument("--views", type=int, default=60)
    p.add_argument("--noise", type=float, default=0.3, help="corner noise sigma, px (default 0.3)")
    p.add_argument("--board", choices=("chessboard", "charuco"), default="chessboard")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--scipy", action="store_true", help="also run the bundle adjustment with scipy least_squares")


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
        ang.append(float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))))
    return {"focal_%": f, "pp_px": pp, "centre_mm": cen, "rot_deg": ang}


def _line(name: str, secs: float, err: dict, extra: str = "") -> str:
    def mm(v):
        return f"{np.median(v):6.3f} / {np.max(v):6.3f}"

    return (f"{name:<22} {secs:7.2f} s   focal % {mm(err['focal_%'])}   pp px {mm(err['pp_px'])}   "
            f"centre mm {mm(err['centre_mm'])}   rot deg {mm(err['rot_deg'])}  {extra}")


def _aniposelib(dets, truth, board, sizes):
    try:
        import aniposelib.boards as ab
        from aniposelib.cameras import CameraGroup
    except Exception as exc:  # noqa: BLE001 - any import failure means "not available"
        return None, f"{type(exc).__name__}: {exc}"
    if board.type == "chessboard":
        ab_board = ab.Checkerboard(board.corners[0], board.corners[1], square_length=board.square_mm)
    else:
        ab_board = ab.CharucoBoard(board.squares[0], board.squares[1], square_length=board.square_mm,
                                   marker_length=board.marker_mm, marker_bits=4, dict_size=100)
    rows = []
    for c in truth:
        r = []
        for d in dets[c.name]:
            r.append({"framenum": (0, d.frame), "corners": d.corners.reshape(-1, 1, 2).astype(np.float32),
                      "ids": d.ids.reshape(-1, 1)})
        rows.append(r)
    cg = CameraGroup.from_names(truth.names)
    for cam, c in zip(cg.cameras, truth):
        cam.set_size(sizes[c.name])
    t = time.perf_counter()
    cg.calibrate_rows(rows, ab_board, init_intrinsics=True, init_extrinsics=True, verbose=False)
    secs = time.perf_counter() - t
    from calib.formats import calibration_from_aniposelib

    d = {f"cam_{i}": cam.get_dict() for i, cam in enumerate(cg.cameras)}
    return (calibration_from_aniposelib(d), secs), None


def run(args: argparse.Namespace) -> int:
    import logging

    from calib.boards import Charuco, Chessboard
    from calib.extrinsics import calibrate_extrinsics
    from calib.intrinsics import calibrate_intrinsics
    from calib.synthetic import random_board_poses, synthetic_detections

    try:
        from fake_cameras.dome import make_dome
    except ImportError as exc:
        raise ValueError(f"fake_cameras.dome is needed for this benchmark: {exc}") from None
    logging.getLogger("calib").setLevel(logging.ERROR)
    truth = make_dome(args.cameras)
    board = Chessboard((11, 8), 50.0) if args.board == "chessboard" else Charuco((12, 9), 50.0, 37.0,
                                                                                  dictionary="DICT_4X4_100")
    sizes = {c.name: c.size for c in truth}
    dist = float(np.median(np.linalg.norm(truth.centers() - truth.centers().mean(0), axis=1)))
    poses = random_board_poses(truth, board, args.views, seed=args.seed, spread=0.25 * dist)
    dets = synthetic_detections(truth, board, poses, noise_px=args.noise, seed=args.seed + 1)
    n_obs = sum(len(d) for v in dets.values() for d in v)
    print(f"{args.cameras} cameras x {args.views} board poses ({board.type}, {board.n_corners} corners), "
          f"noise {args.noise} px: {sum(len(v) for v in dets.values())} camera views, {n_obs} corners")
    print("errors: median / max over cameras, after the best rigid alignment to the true rig")
    t0 = time.perf_counter()
    intr = [calibrate_intrinsics(dets[c.name], board, c.size, name=c.name, max_views=40) for c in truth]
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
                    f"RMS {res.rms:.3f} px, board {g['neighbor_rms']:.2f} mm, BA {t_ba:.2f} s"))
    out, why = _aniposelib(dets, truth, board, sizes)
    if out is None:
        print(f"{'aniposelib':<22} not available ({why}); it is a benchmark-only extra: install it in a separate "
              "virtual environment (pip install aniposelib: needs numba, jax, toml, pandas and pulls "
              "opencv-contrib-python)")
    else:
        calib, secs = out
        print(_line("aniposelib", secs, _errors(calib, truth)))
    return 0
