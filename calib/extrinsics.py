"""Extrinsic calibration of a camera rig from views of one board.

1. Every camera's view of the board gives a board pose (``solvePnP``, IPPE for planes).
2. Cameras that saw the board in the same frame are linked in a co-visibility
   graph (weight: the number of shared frames); their relative pose is a robust
   average over the shared frames.
3. Relative poses are chained along the strongest (maximum-weight) spanning
   tree from a root camera (``scipy.sparse.csgraph``), giving every connected
   camera an initial pose; cameras not connected are reported by name.
4. One bundle adjustment (:func:`calib.bundle.bundle_adjust`) refines all camera
   poses (optionally intrinsics) and board poses together.
5. The world frame is a chosen board pose (origin on the board, z up, mm) or
   the first camera.

The report gives per-camera RMS reprojection errors and the triangulated
board's geometry error in millimetres (corners triangulated from all cameras,
inter-corner distances against the board's true geometry).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from calib.boards import Board, Charuco, Chessboard
from calib.bundle import bundle_adjust, rodrigues_batch
from calib.calibration import Calibration
from calib.camera import Camera, matrix_to_rodrigues, rotation_angle_deg, undistort_normalized
from calib.detect import Detection
from calib.intrinsics import CalibrationError

__all__ = [
    "ExtrinsicsResult",
    "calibrate_extrinsics",
    "board_poses",
    "covisibility",
    "spanning_tree",
    "triangulate_board_error",
    "BOARD_TO_WORLD",
]

log = logging.getLogger(__name__)

# The board frame has z into the printed face; a board lying face up defines a
# world with z up by turning it 180 degrees about its x axis.
BOARD_TO_WORLD = np.diag([1.0, -1.0, -1.0])


def _inv(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return R.T, -R.T @ t


def _compose(Ra, ta, Rb, tb):
    """(A ∘ B): x -> Ra (Rb x + tb) + ta."""
    return Ra @ Rb, Ra @ tb + ta


def board_poses(
    detections: Sequence[Detection], board: Board, *, K: np.ndarray, dist: np.ndarray, min_corners: int = 6
) -> dict[int, tuple[np.ndarray, np.ndarray, float]]:
    """Board -> camera pose of every view (``solvePnP``, IPPE then iterative refinement).

    Returns
    -------
    dict
        ``frame -> (R (3, 3), t (3,), rms px)`` for views with ``>= min_corners`` corners.
    """
    import cv2

    obj = board.object_points()
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    out: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}
    for d in detections:
        if d is None or len(d) < min_corners:
            continue
        op = obj[d.ids].reshape(-1, 1, 3)
        ip = d.corners.reshape(-1, 1, 2)
        try:
            n, rvecs, tvecs, errs = cv2.solvePnPGeneric(op, ip, K, dist, flags=cv2.SOLVEPNP_IPPE)
        except cv2.error:
            continue
        if n == 0:
            continue
        best = int(np.argmin(np.asarray(errs).ravel()))
        rvec, tvec = rvecs[best], tvecs[best]
        rvec, tvec = cv2.solvePnPRefineLM(op, ip, K, dist, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        t = tvec.ravel()
        if t[2] <= 0:
            continue
        proj, _ = cv2.projectPoints(op, rvec, tvec, K, dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - d.corners) ** 2, axis=1))))
        out[int(d.frame)] = (R, t, rms)
    return out


def covisibility(frames_per_camera: Sequence[set[int]]) -> np.ndarray:
    """(C, C) int matrix: frames in which both cameras saw the board (diagonal: own count)."""
    C = len(frames_per_camera)
    W = np.zeros((C, C), dtype=np.int64)
    for i in range(C):
        for j in range(i, C):
            W[i, j] = W[j, i] = len(frames_per_camera[i] & frames_per_camera[j])
    return W


def spanning_tree(weights: np.ndarray, root: int) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Maximum-weight spanning tree of the co-visibility graph, as parent -> child edges from ``root``.

    Returns
    -------
    edges : list of (parent, child)
        In breadth-first order from ``root`` (only the root's component).
    labels : (C,) int ndarray
        Connected component of every camera.
    """
    W = np.array(weights, dtype=np.float64)
    np.fill_diagonal(W, 0)
    C = W.shape[0]
    _, labels = connected_components(coo_matrix(W > 0), directed=False)
    iu, ju = np.nonzero(np.triu(W) > 0)
    if iu.size == 0:
        return [], labels
    top = W[iu, ju].max()
    cost = coo_matrix((top + 1.0 - W[iu, ju], (iu, ju)), shape=(C, C))
    tree = minimum_spanning_tree(cost).toarray()
    adj = (tree + tree.T) > 0
    edges: list[tuple[int, int]] = []
    seen = {root}
    queue = [root]
    while queue:
        p = queue.pop(0)
        for c in np.flatnonzero(adj[p]):
            c = int(c)
            if c not in seen:
                seen.add(c)
                edges.append((p, c))
                queue.append(c)
    return edges, labels


def _robust_relative(samples: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Medoid of a set of rigid transforms, then the mean of those close to it."""
    Rs = np.stack([s[0] for s in samples])
    ts = np.stack([s[1] for s in samples])
    if len(samples) == 1:
        return Rs[0], ts[0]
    # pairwise rotation angle and translation distance
    ang = np.radians(rotation_angle_deg(np.einsum("aji,bjk->abik", Rs, Rs)))
    dt = np.linalg.norm(ts[:, None] - ts[None], axis=2)
    scale = np.median(np.linalg.norm(ts, axis=1)) + 1e-9
    cost = np.sum(ang + dt / scale, axis=1)
    m = int(np.argmin(cost))
    close = (ang[m] < np.deg2rad(5)) & (dt[m] < 0.05 * scale)
    U, _, Vt = np.linalg.svd(Rs[close].mean(axis=0))
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    return R, np.median(ts[close], axis=0)


def _triangulate(P_norm: np.ndarray, xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Batched linear triangulation.

    P_norm : (C, 3, 4) normalized projection matrices ``[R | t]``.
    xy : (N, C, 2) undistorted normalized coordinates; valid : (N, C) bool.
    """
    A1 = xy[..., 0:1] * P_norm[None, :, 2, :] - P_norm[None, :, 0, :]
    A2 = xy[..., 1:2] * P_norm[None, :, 2, :] - P_norm[None, :, 1, :]
    A = np.concatenate([A1, A2], axis=1) * np.concatenate([valid, valid], axis=1)[..., None]
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1]
    return Xh[:, :3] / Xh[:, 3:4]


def triangulate_board_error(
    calibration: Calibration, detections: Mapping[str, Sequence[Detection]], board: Board, *, min_cameras: int = 2
) -> dict:
    """Geometry error of the board triangulated with a calibration, in the calibration's units.

    Every corner seen by ``>= min_cameras`` cameras in a frame is triangulated
    (linear, distortion removed); the distances between adjacent corners and
    between all corner pairs are compared with the board's true geometry.

    Returns
    -------
    dict
        ``neighbor_rms``, ``neighbor_max``, ``pairs_rms``, ``pairs_max`` (mm),
        ``frames`` and ``corners`` used.
    """
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    if min_cameras < 2:
        raise ValueError(f"min_cameras must be >= 2, got {min_cameras}")
    names = calibration.names
    obj = board.object_points()
    n_corners = obj.shape[0]
    by_frame: dict[int, dict[int, Detection]] = {}
    for ci, name in enumerate(names):
        for d in detections.get(name, ()):
            if d is not None:
                by_frame.setdefault(int(d.frame), {})[ci] = d
    C = len(names)
    P = np.stack([np.hstack([c.R, c.t[:, None]]) for c in calibration.cameras])
    pairs = board.neighbor_pairs()
    nb_err, all_err = [], []
    n_frames = n_pts = 0
    iu, ju = np.triu_indices(n_corners, 1)
    true_all = np.linalg.norm(obj[iu] - obj[ju], axis=1)
    true_nb = np.linalg.norm(obj[pairs[:, 0]] - obj[pairs[:, 1]], axis=1)
    for dets in by_frame.values():
        if len(dets) < min_cameras:
            continue
        xy = np.zeros((n_corners, C, 2))
        valid = np.zeros((n_corners, C), bool)
        for ci, d in dets.items():
            cam = calibration.cameras[ci]
            yd = (d.corners[:, 1] - cam.K[1, 2]) / cam.K[1, 1]
            xd = (d.corners[:, 0] - cam.K[0, 2] - cam.K[0, 1] * yd) / cam.K[0, 0]
            und = undistort_normalized(np.stack([xd, yd], axis=1), cam.dist)
            xy[d.ids, ci] = und
            valid[d.ids, ci] = True
        ok = valid.sum(axis=1) >= min_cameras
        if ok.sum() < 2:
            continue
        X = np.full((n_corners, 3), np.nan)
        X[ok] = _triangulate(P, xy[ok], valid[ok])
        n_frames += 1
        n_pts += int(ok.sum())
        m = ok[pairs[:, 0]] & ok[pairs[:, 1]]
        nb_err.append(np.linalg.norm(X[pairs[m, 0]] - X[pairs[m, 1]], axis=1) - true_nb[m])
        m = ok[iu] & ok[ju]
        all_err.append(np.linalg.norm(X[iu[m]] - X[ju[m]], axis=1) - true_all[m])
    if not n_frames:
        return {"frames": 0, "corners": 0, "neighbor_rms": float("nan"), "neighbor_max": float("nan"),
                "pairs_rms": float("nan"), "pairs_max": float("nan")}
    nb = np.concatenate(nb_err) if nb_err else np.zeros(0)
    al = np.concatenate(all_err) if all_err else np.zeros(0)

    def rms(a):
        return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")

    def mx(a):
        return float(np.max(np.abs(a))) if a.size else float("nan")

    return {"frames": n_frames, "corners": n_pts, "neighbor_rms": rms(nb), "neighbor_max": mx(nb),
            "pairs_rms": rms(al), "pairs_max": mx(al)}


@dataclass(frozen=True, eq=False)
class ExtrinsicsResult:
    """A calibrated rig and how good it is.

    Attributes
    ----------
    calibration : Calibration
        Cameras in the world frame (mm).
    rms : float
        Reprojection RMS over all observations, px (per corner, as OpenCV).
    per_camera_rms : dict
        Camera name -> RMS px.
    per_camera_views : dict
        Camera name -> number of board views used.
    geometry : dict
        :func:`triangulate_board_error` of the result.
    board_poses : dict
        Frame -> ``(R, t)`` board -> world.
    tree : list of (str, str, int)
        Spanning-tree edges (parent, child, shared frames).
    world : str
        ``"board"`` or ``"camera"``.
    world_frame : int or None
        The frame whose board defines the world.
    warnings : tuple of str
    """

    calibration: Calibration
    rms: float
    per_camera_rms: dict
    per_camera_views: dict
    geometry: dict
    board_poses: dict
    tree: list
    world: str
    world_frame: int | None
    warnings: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "rms": self.rms,
            "per_camera_rms": dict(self.per_camera_rms),
            "per_camera_views": dict(self.per_camera_views),
            "geometry_mm": dict(self.geometry),
            "tree": [list(e) for e in self.tree],
            "world": self.world,
            "world_frame": self.world_frame,
            "warnings": list(self.warnings),
            **{k: v for k, v in self.meta.items() if k not in ("intrinsics_cov", "rotation_cov")},
        }

    def report(self) -> str:
        g = self.geometry
        lines = [
            f"rig: {len(self.calibration)} cameras, reprojection RMS {self.rms:.3f} px; "
            f"board triangulated from {g['frames']} frames: adjacent corners off by {g['neighbor_rms']:.2f} mm RMS "
            f"(max {g['neighbor_max']:.2f}), all corner pairs {g['pairs_rms']:.2f} mm RMS (max {g['pairs_max']:.2f})",
            "  camera        views   RMS px",
        ]
        for name in self.calibration.names:
            lines.append(f"  {name:<12} {self.per_camera_views[name]:6d}   {self.per_camera_rms[name]:.3f}")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _unconnected_message(names, labels, root, frames_per_camera, W) -> tuple[str, list[str]]:
    main = labels[root]
    connected = [names[i] for i in range(len(names)) if labels[i] == main]
    bad = [i for i in range(len(names)) if labels[i] != main]
    parts = []
    for i in bad:
        n = names[i]
        seen = len(frames_per_camera[i])
        if seen == 0:
            parts.append(
                f"camera {n}: the board was never detected in its images; check that {n} sees the board, that "
                "the board file matches the print (corners = INNER corners, ChArUco dictionary/legacy), and "
                "the focus and lighting"
            )
        else:
            island = [names[j] for j in range(len(names)) if labels[j] == labels[i] and j != i]
            with_ = f" (only with {', '.join(island)})" if island else ""
            parts.append(
                f"camera {n}: saw the board in {seen} view(s) but never at the same time as a camera connected "
                f"to the rest{with_}; show the board where {n} and one of {', '.join(connected[:4])}"
                f"{'...' if len(connected) > 4 else ''} see it together"
            )
    return "; ".join(parts), [names[i] for i in bad]


def _check_inputs(detections, cameras, board, world: str, min_corners: int):
    """ValueError naming the bad parameter of :func:`calibrate_extrinsics`; the cameras and their names."""
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    cams = list(cameras)
    if len(cams) < 2:
        raise ValueError(f"cameras: need at least 2 cameras for extrinsics, got {len(cams)}")
    for c in cams:
        if not isinstance(c, Camera):
            raise ValueError(f"cameras must hold Camera objects, got {type(c).__name__}")
    names = [c.name for c in cams]
    if not isinstance(detections, Mapping):
        raise ValueError("detections must map camera names to sequences of Detection")
    unknown = sorted(set(detections) - set(names))
    if unknown:
        raise ValueError(f"detections: unknown camera name(s) {unknown} (cameras: {names})")
    if world not in ("board", "camera"):
        raise ValueError(f"world must be 'board' or 'camera', got {world!r}")
    if min_corners < 4:
        raise ValueError(f"min_corners must be >= 4, got {min_corners}")
    if isinstance(board, Chessboard) and sum(board.corners) % 2 == 0:
        log.warning(
            "board %dx%d: a chessboard with cols + rows even is 180-degree symmetric, so cameras may number its "
            "corners differently; use e.g. 9 x 6 inner corners or a ChArUco board", *board.corners
        )
    return cams, names


def _chain(edges, root: int, poses, frames_per_camera, names):
    """Camera poses ``T_c<-root`` chained along the spanning tree from the shared views of each edge."""
    T: dict[int, tuple[np.ndarray, np.ndarray]] = {root: (np.eye(3), np.zeros(3))}
    tree_report = []
    for p, c in edges:
        shared = sorted(frames_per_camera[p] & frames_per_camera[c])
        samples = []
        for f in shared:
            Rp, tp, _ = poses[p][f]
            Rc, tc, _ = poses[c][f]
            samples.append(_compose(Rc, tc, *_inv(Rp, tp)))  # T_c<-p
        Rcp, tcp = _robust_relative(samples)
        T[c] = _compose(Rcp, tcp, *T[p])
        tree_report.append((names[p], names[c], len(shared)))

    return T, tree_report


def _warnings(res, per_rms: dict, per_views: dict) -> list[str]:
    """What a user should know about the bundle adjustment."""
    warnings = []
    if not res.success:
        warnings.append(f"bundle adjustment did not converge: {res.message}")
    med = float(np.median(list(per_rms.values())))
    for n, v in per_rms.items():
        if v > 3 * med and v > 1.0:
            warnings.append(f"camera {n}: reprojection RMS {v:.2f} px is far above the rest (median {med:.2f}); "
                            "check its focus, motion blur and that it did not move during calibration")
    for n, v in per_views.items():
        if v < 3:
            warnings.append(f"camera {n}: only {v} shared board view(s); its pose rests on little data")
    return warnings


def _world_from_root(world, world_frame, use_frames, frame_cams, corners_count, frame_index, Rc_all, Rb_all, res):
    """``T_world<-root`` and the world frame (None with ``world="camera"``)."""
    if world == "camera":
        Rw, tw = Rc_all[0], res.cam_tvec[0]  # T_cam0<-root: world = first camera
        W_from_root = (Rw, tw)
        wf = None
    else:
        if world_frame is None:
            wf = max(use_frames, key=lambda f: (len(frame_cams[f]), sum(corners_count.get((k, f), 0)
                                                                       for k in frame_cams[f])))
        else:
            wf = int(world_frame)
            if wf not in frame_index:
                raise CalibrationError(f"world_frame {wf}: no camera saw the board in that frame; pick another frame")
        i = frame_index[wf]
        # X_root = Rb X_board + tb ; X_world = F X_board  =>  T_world<-root = F T_board<-root
        Rbr, tbr = _inv(Rb_all[i], res.board_tvec[i])
        W_from_root = (BOARD_TO_WORLD @ Rbr, BOARD_TO_WORLD @ tbr)
    return W_from_root, wf


def calibrate_extrinsics(
    detections: Mapping[str, Sequence[Detection]],
    cameras: Sequence[Camera],
    board: Board,
    *,
    world: str = "board",
    world_frame: int | None = None,
    optimize_intrinsics: bool = True,
    fixed_intrinsics: tuple[str, ...] | np.ndarray = (),
    loss: str = "soft_l1",
    f_scale: float = 1.0,
    min_corners: int = 6,
    max_nfev: int | None = None,
    solver: str = "lm",
    intrinsics_prior: np.ndarray | None = None,
    prior_scale: float = 1.0,
    prior_jacobian: Mapping[str, Mapping[int, tuple[np.ndarray, np.ndarray]]] | None = None,
) -> ExtrinsicsResult:
    """Calibrate the poses of all cameras together (and refine their intrinsics).

    Parameters
    ----------
    detections : mapping str -> sequence of Detection
        Board detections per camera name; ``Detection.frame`` identifies the
        moment, so detections with the same frame saw the same board pose.
    cameras : sequence of Camera
        Intrinsics of every camera (poses are ignored), in rig order.
    board : Chessboard or Charuco
    world : {"board", "camera"}
        World frame: a board pose (origin on the board, z up out of the printed
        face turned upwards, i.e. the board lying face up on the floor gives z up)
        or the first camera.
    world_frame : int, optional
        Frame whose board pose defines the world (default: the frame seen by
        the most cameras).
    optimize_intrinsics : bool
        Refine intrinsics in the bundle adjustment too.
    fixed_intrinsics : tuple of str or (C, 9) bool ndarray
        Intrinsics the bundle adjustment keeps as given (``calib.bundle.INTRINSIC_NAMES``),
        e.g. ``("k3",)`` for cameras calibrated with ``fix_k3``, or per camera (True: held).
    loss, f_scale : str, float
        Robust loss of the bundle adjustment and its inlier scale (px).
    min_corners : int
        Views with fewer corners are ignored.
    solver : {"lm", "scipy"}
        See :func:`calib.bundle.bundle_adjust`.
    intrinsics_prior : (C, 9, 9) float ndarray, optional
        Covariance of a Gaussian prior on every camera's intrinsics, centred on the
        given cameras' (``prior_cov`` of :func:`calib.bundle.bundle_adjust`).
    prior_scale : float
        Pixel noise the prior is expressed in (px per coordinate).
    prior_jacobian : mapping str -> mapping int -> (ids (n,) int ndarray, rows (n, 2, 9) float ndarray), optional
        With ``intrinsics_prior`` from each camera's own solve on some of the same views: per camera and frame,
        the corners that solve used and its reduced Jacobian rows there
        (:func:`calib.bundle.reduced_intrinsics_jacobian`), so that the covariance counts the corners both
        solves used once (``prior_jacobian`` of :func:`calib.bundle.bundle_adjust`; the estimate is the same).

    Returns
    -------
    ExtrinsicsResult
        ``meta["intrinsics_cov"]``: (C, 9, 9) covariance of the refined intrinsics;
        ``meta["rotation_cov"]``: (C, C, 3, 3) joint covariance of the camera rotations (rad^2,
        :func:`calib.bundle.bundle_adjust`), relative to ``meta["reference"]``, the camera held
        fixed in the adjustment (the covariance of relative rotations does not depend on it).

    Raises
    ------
    CalibrationError
        A camera could not be connected to the others (names every such camera,
        why, and what to do) or ``world_frame`` saw no board.
    """
    cams, names = _check_inputs(detections, cameras, board, world, min_corners)
    C = len(cams)

    # 1. per-view board poses
    poses = [board_poses(detections.get(c.name, ()), board, K=c.K, dist=c.dist, min_corners=min_corners)
             for c in cams]
    frames_per_camera = [set(p) for p in poses]
    # 2. co-visibility graph and spanning tree
    root, edges = _spanning_tree_or_raise(frames_per_camera, names)
    # 3. chain relative poses along the tree (T_c<-root), board poses in the root frame
    T, tree_report = _chain(edges, root, poses, frames_per_camera, names)
    views = _views(cams, detections, frames_per_camera, min_cams=1 if optimize_intrinsics else 2)
    board_rvec, board_tvec = _boards_in_root(views, poses, T)
    obs_cam, obs_board, obs_points, obs_uv = _observation_arrays(cams, detections, views.frame_index, poses,
                                                                 board.object_points())
    intr0 = np.array([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *c.dist] for c in cams])
    cam_rvec = np.stack([matrix_to_rodrigues(T[ci][0]) for ci in range(C)])
    cam_tvec = np.stack([T[ci][1] for ci in range(C)])
    shared = {}
    if prior_jacobian is not None:
        shared["prior_jacobian"] = _aligned_prior_jacobian(cams, detections, views.frame_index, poses, prior_jacobian)

    # 4. bundle adjustment
    res = bundle_adjust(
        obs_cam, obs_board, obs_points, obs_uv,
        intrinsics=intr0, cam_rvec=cam_rvec, cam_tvec=cam_tvec, board_rvec=board_rvec, board_tvec=board_tvec,
        reference=root, optimize_intrinsics=optimize_intrinsics,
        fixed_intrinsics=fixed_intrinsics if isinstance(fixed_intrinsics, np.ndarray) else tuple(fixed_intrinsics),
        loss=loss, f_scale=f_scale, max_nfev=max_nfev,
        solver=solver, prior_cov=intrinsics_prior, prior_scale=prior_scale, covariance=True, **shared,
    )
    Rc_all = rodrigues_batch(res.cam_rvec)
    Rb_all = rodrigues_batch(res.board_rvec)

    # 5. world frame
    W_from_root, wf = _world_from_root(world, world_frame, views.use_frames, views.frame_cams, views.corners_count,
                                       views.frame_index, Rc_all, Rb_all, res)
    out_cams, board_world = _in_world(cams, res, Rc_all, Rb_all, W_from_root, views.frame_index)
    return _rig_result(res, out_cams, names, obs_cam, frames_per_camera, views, detections, board, world=world,
                       world_frame=wf, board_world=board_world, tree_report=tree_report, reference=names[root])


def _spanning_tree_or_raise(frames_per_camera: list[set[int]], names: list[str]) -> tuple[int, list]:
    """The root camera (most shared views) and the strongest spanning tree's edges of the co-visibility
    graph; CalibrationError naming every camera that cannot be connected."""
    W = covisibility(frames_per_camera)
    strength = W.sum(axis=1) - np.diag(W)
    root = int(np.argmax(strength))
    edges, labels = spanning_tree(W, root)
    if len(set(labels.tolist())) > 1 or any(not f for f in frames_per_camera):
        msg, bad = _unconnected_message(names, labels, root, frames_per_camera, W)
        raise CalibrationError(f"could not connect every camera: {msg}", cameras=bad)
    return root, edges


@dataclass(frozen=True)
class _Views:
    """Which camera saw the board in which frame."""

    corners_count: dict  # (camera index, frame) -> corners detected
    frame_cams: dict  # frame -> indices of the cameras with a board pose in it
    use_frames: list  # frames seen by enough cameras, in order (the adjustment's board poses)
    frame_index: dict  # frame -> its board pose's index in the adjustment


def _views(cams, detections, frames_per_camera, *, min_cams: int) -> _Views:
    """The frames the adjustment uses: those with a board pose in at least ``min_cams`` cameras."""
    corners_count = {}
    for ci, c in enumerate(cams):
        for d in detections.get(c.name, ()):
            if d is not None:
                corners_count[(ci, int(d.frame))] = len(d)
    all_frames = sorted(set().union(*frames_per_camera))
    frame_cams = {f: [ci for ci in range(len(cams)) if f in frames_per_camera[ci]] for f in all_frames}
    use_frames = [f for f in all_frames if len(frame_cams[f]) >= min_cams]
    return _Views(corners_count, frame_cams, use_frames, {f: i for i, f in enumerate(use_frames)})


def _boards_in_root(views: _Views, poses, T) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3) rotation and translation vectors ``T_root<-board`` of every used frame, each from the
    camera that saw the most of its corners."""
    B_R, B_t = [], []
    for f in views.use_frames:
        ci = max(views.frame_cams[f], key=lambda k: views.corners_count.get((k, f), 0))
        Rcb, tcb, _ = poses[ci][f]
        B = _compose(*_inv(*T[ci]), Rcb, tcb)  # T_root<-board
        B_R.append(B[0])
        B_t.append(B[1])
    return np.stack([matrix_to_rodrigues(R) for R in B_R]), np.stack(B_t)


def _used_detections(cams, detections, frame_index, poses):
    """``(camera index, camera, detection)`` of every detection the adjustment uses, in its order."""
    for ci, c in enumerate(cams):
        for d in detections.get(c.name, ()):
            if d is not None and int(d.frame) in frame_index and int(d.frame) in poses[ci]:
                yield ci, c, d


def _observation_arrays(cams, detections, frame_index, poses, obj):
    """Camera index, board-pose index, board point and pixel of every corner the adjustment uses."""
    oc, ob, op, ouv = [], [], [], []
    for ci, _, d in _used_detections(cams, detections, frame_index, poses):
        n = len(d)
        oc.append(np.full(n, ci))
        ob.append(np.full(n, frame_index[int(d.frame)]))
        op.append(obj[d.ids])
        ouv.append(d.corners)
    return np.concatenate(oc), np.concatenate(ob), np.concatenate(op), np.concatenate(ouv)


def _aligned_prior_jacobian(cams, detections, frame_index, poses, prior_jacobian) -> np.ndarray:
    """(M, 2, 9) the prior solve's reduced Jacobian row at every corner of :func:`_observation_arrays`, in its
    order (zero where that solve did not use the corner)."""
    out = []
    for _, c, d in _used_detections(cams, detections, frame_index, poses):
        rows = np.zeros((len(d), 2, 9))
        mine = prior_jacobian.get(c.name, {})
        if int(d.frame) in mine:
            ids, J = mine[int(d.frame)]
            where = {int(i): k for k, i in enumerate(np.asarray(ids).ravel())}
            for k, i in enumerate(np.asarray(d.ids).ravel()):
                if int(i) in where:
                    rows[k] = J[where[int(i)]]
        out.append(rows)
    return np.concatenate(out)


def _in_world(cams, res, Rc_all, Rb_all, W_from_root, frame_index) -> tuple[list[Camera], dict]:
    """The adjusted cameras and board poses in the world frame."""
    root_from_world = _inv(*W_from_root)
    out_cams = []
    for ci, c in enumerate(cams):
        fx, fy, cx, cy, *dist = res.intrinsics[ci]
        K = np.array([[fx, c.K[0, 1], cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        R, t = _compose(Rc_all[ci], res.cam_tvec[ci], *root_from_world)
        out_cams.append(Camera(c.name, K=K, dist=np.array(dist), R=R, t=t, size=c.size, meta=dict(c.meta)))
    board_world = {}
    for f, i in frame_index.items():
        board_world[f] = _compose(*W_from_root, Rb_all[i], res.board_tvec[i])
    return out_cams, board_world


def _rig_result(res, out_cams, names, obs_cam, frames_per_camera, views: _Views, detections, board, *, world: str,
                world_frame, board_world: dict, tree_report: list, reference: str) -> ExtrinsicsResult:
    """The calibration with its report: per-camera errors, the triangulated board's geometry, warnings."""
    C = len(names)
    r2 = np.sum(res.residuals**2, axis=1)
    per_rms = {names[ci]: float(np.sqrt(np.mean(r2[obs_cam == ci]))) if np.any(obs_cam == ci) else float("nan")
               for ci in range(C)}
    per_views = {names[ci]: int(len(frames_per_camera[ci] & set(views.use_frames))) for ci in range(C)}
    calib = Calibration(cameras=tuple(out_cams), units="mm",
                        meta={"method": "capture-stage bundle adjustment", "board": board.to_dict(),
                              "rms_px": float(np.sqrt(np.mean(r2))), "world": world,
                              **({"world_frame": world_frame} if world_frame is not None else {})})
    geometry = triangulate_board_error(calib, detections, board)
    warnings = _warnings(res, per_rms, per_views)
    for w in warnings:
        log.debug(w)  # in the result's warnings / report
    return ExtrinsicsResult(
        calibration=calib, rms=float(np.sqrt(np.mean(r2))), per_camera_rms=per_rms, per_camera_views=per_views,
        geometry=geometry, board_poses=board_world, tree=tree_report, world=world, world_frame=world_frame,
        warnings=tuple(warnings), meta={"bundle": {"nfev": res.nfev, "message": res.message,
                                                    "observations": int(obs_cam.size)},
                                        "intrinsics_cov": res.intrinsics_cov, "sigma_px": res.sigma_px,
                                        "rotation_cov": res.rotation_cov, "reference": reference},
    )
