"""Calibrate a whole rig from board detections: intrinsics per camera, then all together.

This is the entry point the CLI and the demo use::

    result = calibrate_rig(detections, sizes, board)
    result.calibration          # calib.Calibration, mm, world = a board pose (z up)
    print(result.report())

Steps:

1. Views. Each camera's intrinsics (Zhang) use its views thinned by novelty
   (:func:`calib.detect.select_views`) together with every view it shares with
   another camera. The bundle adjustment uses *every* frame set in which two or
   more cameras saw the board (evenly thinned only above ``max_sets``): those are
   what links the cameras.
2. Intrinsics in the bundle adjustment (``intrinsics``): ``"prior"`` refines them
   under a Gaussian prior from each camera's Zhang solve (its full covariance), so
   a parameter moves only as far as the joint data supports; ``"fixed"`` keeps the
   Zhang values; ``"free"`` refines them without a prior.
3. Honest figures (:mod:`calib.evaluate`): beside the fit on the views used, the
   reprojection and board-geometry error over every frame with a detection, a
   k-fold held-out error over frame sets (calibrate on the rest, measure on the
   fold), the per-camera projection uncertainty from the parameter covariance, the
   rotation uncertainty of every camera and camera pair in degrees (from the bundle
   adjustment's covariance, :func:`rotation_sigma`, and from the spread of the held-out
   folds' calibrations, :func:`fold_rotation_spread`), and how far each intrinsic moved
   from Zhang's in units of its standard deviation.

Detection (from images, takes or videos) is the caller's business (see
:mod:`calib.detect`); this module only takes arrays.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from calib.boards import Board, Charuco, Chessboard
from calib.bundle import INTRINSIC_NAMES, reduced_intrinsics_jacobian
from calib.calibration import Calibration
from calib.camera import rotation_angle_deg
from calib.detect import Detection, select_views
from calib.evaluate import projection_uncertainty, reprojection_errors
from calib.extrinsics import ExtrinsicsResult, calibrate_extrinsics, triangulate_board_error
from calib.fileio import plain
from calib.intrinsics import DISTORTION_MODES, CalibrationError, IntrinsicsResult, calibrate_intrinsics

__all__ = ["RigCalibration", "calibrate_rig", "resolve_flipped", "rotation_sigma", "fold_rotation_spread",
           "INTRINSICS_MODES", "MAX_SETS", "MOVE_WARN_P", "intrinsics_moved", "CORNER_WARN_PX", "FOLD_WARN_RATIO", "FOLD_WARN_DEG",
           "corner_warnings", "group_warnings"]

log = logging.getLogger(__name__)

INTRINSICS_MODES = ("prior", "fixed", "free")
MAX_SETS = 300  # frame sets in the bundle adjustment above which they are evenly thinned
# the rig's false-alarm rate for "the bundle adjustment moved a camera's intrinsics": that of one 3-sigma number
# (two-sided), shared by the cameras (intrinsics_moved)
MOVE_WARN_P = 0.0027
CORNER_WARN_PX = 2.0  # projection uncertainty at the image corners above which the report warns
FOLD_WARN_RATIO = 2.0  # folds' rotation spread over the covariance's figure above which the report warns
FOLD_WARN_DEG = 0.5  # ... when the spread is also above this


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """Result of :func:`calibrate_rig`.

    Attributes
    ----------
    calibration : Calibration
    intrinsics : dict
        Name -> :class:`~calib.intrinsics.IntrinsicsResult` (the per-camera Zhang solve).
    extrinsics : ExtrinsicsResult or None
        The bundle adjustment (None for a single camera).
    evaluation : dict
        ``all_frames`` (:func:`calib.evaluate.reprojection_errors` over every frame with a
        detection), ``geometry_all`` (board geometry error over them), ``held_out``
        (k-fold, same layout plus ``folds``), ``uncertainty`` (name -> position -> px),
        ``moved_sigma`` (name -> intrinsic -> signed move in Zhang sigmas), ``moved_test`` (name ->
        :func:`intrinsics_moved`'s joint test of those moves), ``sets``
        (frame sets used by the bundle adjustment), ``rotation_sigma_deg``
        (:func:`rotation_sigma`) and, with held-out folds, ``rotation_folds_deg``
        (:func:`fold_rotation_spread`).
    """

    calibration: Calibration
    intrinsics: dict  # name -> IntrinsicsResult
    extrinsics: ExtrinsicsResult | None
    evaluation: dict = field(default_factory=dict)
    extra_warnings: tuple[str, ...] = ()

    @property
    def warnings(self) -> list[str]:
        w = [x for r in self.intrinsics.values() for x in r.warnings]
        if self.extrinsics is not None:
            w += list(self.extrinsics.warnings)
        return w + list(self.extra_warnings)

    def held_out_rms(self) -> dict:
        """Camera name -> held-out reprojection RMS (px), NaN where not measured."""
        ho = self.evaluation.get("held_out") or {}
        return {n: v["rms"] for n, v in ho.get("per_camera", {}).items()}

    def summary(self) -> str:
        """The line a user reads first: the held-out error per camera."""
        ho = self.evaluation.get("held_out")
        if ho and ho.get("per_camera"):
            per = ", ".join(f"{n} {v['rms']:.2f}" for n, v in ho["per_camera"].items())
            return (f"held-out reprojection RMS ({ho['folds']}-fold over {ho['frames']} frame sets), px: {per}; "
                    f"all cameras {ho['rms']:.2f}")
        af = self.evaluation.get("all_frames")
        if af:
            per = ", ".join(f"{n} {v['rms']:.2f}" for n, v in af["per_camera"].items())
            return f"reprojection RMS over every detected frame (too few frame sets to hold any out), px: {per}"
        return "single camera: " + next(iter(self.intrinsics.values())).summary().splitlines()[0]

    def verdict(self) -> str:
        """One line: do the cameras and the rig's data agree (no camera's intrinsics moved beyond its own
        uncertainty, no rotation varying between held-out folds beyond what corner noise explains, no
        camera's fit far above the rest, the bundle adjustment converged), and which cameras are less certain where
        the board did not go or the views were few (every other warning)."""
        ws = self.warnings
        doubt = sorted({_camera_of(w) or "the rig" for w in ws if any(k in w for k in _DOUBT)})
        rest = sorted({_camera_of(w) or "the rig" for w in ws if not any(k in w for k in _DOUBT)})
        ho = self.evaluation.get("held_out") or {}
        fig = f"held-out reprojection {ho['rms']:.2f} px" if ho.get("rms") is not None else "no held-out figure"
        if doubt:
            return (f"verdict: check {', '.join(doubt)}: the rig's data disagree with what the cameras saw alone or "
                    f"between held-out folds ({fig}; warnings below)")
        if rest:
            return (f"verdict: consistent ({fig}); less certain where the board did not go or with few views: "
                    f"{', '.join(rest)} (warnings below)")
        return f"verdict: consistent ({fig}), no warning"

    def report(self) -> str:
        lines = [self.verdict(), self.summary(), "intrinsics (per camera, Zhang):"]
        lines += ["  " + r.summary().replace("\n", "\n  ") for r in self.intrinsics.values()]
        if self.extrinsics is not None:
            ev = self.evaluation
            lines.append(f"extrinsics (bundle adjustment of all cameras over {ev.get('sets', '?')} frame sets, "
                         f"intrinsics {ev.get('mode', '?')}):")
            lines.append("  " + self.extrinsics.report().replace("\n", "\n  "))
            af, ho = ev.get("all_frames"), ev.get("held_out")
            g = ev.get("geometry_all")
            rs, rf = ev.get("rotation_sigma_deg") or {}, ev.get("rotation_folds_deg") or {}
            ref = rs.get("reference", "?")
            lines.append("  camera        fit px   all-frames px (views)   held-out px   uncertainty px (centre / worst corner)"
                         f"   rotation deg vs {ref} (covariance / folds)")
            for name in self.calibration.names:
                fit = self.extrinsics.per_camera_rms.get(name, float("nan"))
                a = af["per_camera"][name] if af else {"rms": float("nan"), "views": 0}
                h = ho["per_camera"][name]["rms"] if ho and name in ho.get("per_camera", {}) else float("nan")
                u = ev.get("uncertainty", {}).get(name, {})
                corner = max((v for k, v in u.items() if k != "centre"), default=float("nan"))
                rot = (f"{rs.get('per_camera', {}).get(name, float('nan')):.2f} / "
                       f"{rf.get('per_camera', {}).get(name, float('nan')):.2f}")
                lines.append(f"  {name:<12} {fit:7.3f}   {a['rms']:7.3f} ({a['views']:4d})          {h:7.3f}"
                             f"       {_px(u.get('centre', float('nan')))} / {_px(corner)}"
                             f"{'':22}{'reference' if name == ref else rot}")
            if g and g.get("frames"):
                lines.append(f"  board over every detected frame ({g['frames']} frames): adjacent corners off by "
                             f"{g['neighbor_rms']:.2f} mm RMS, all corner pairs {g['pairs_rms']:.2f} mm RMS")
            moved = ev.get("moved_sigma", {})
            if moved:
                lines.append("  intrinsics moved from Zhang, in Zhang standard deviations:")
                for name, m in moved.items():
                    lines.append("    " + f"{name:<12} " + "  ".join(f"{k} {v:+.1f}" for k, v in m.items()))
        lines += [f"  warning: {w}" for w in group_warnings(list(self.extra_warnings))]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "summary": self.summary(),
            "intrinsics": {k: v.to_dict() for k, v in self.intrinsics.items()},
            "extrinsics": self.extrinsics.to_dict() if self.extrinsics is not None else None,
            "evaluation": plain({k: v for k, v in self.evaluation.items() if k != "detections"}),
            "warnings": self.warnings,
        }


def corner_warnings(uncertainty: dict) -> list[str]:
    """One warning per camera whose projection at the image corners is uncertain by more than
    :data:`CORNER_WARN_PX` (``uncertainty``: camera -> ``{"centre": px, corner: px, ...}``). It names the
    remedy as ``stage calibrate`` (``--fix-k3``) and a calibration job (``parameters.fix_k3``) both call it.

    Raises
    ------
    ValueError
        When ``uncertainty`` is not such a mapping.
    """
    if not isinstance(uncertainty, dict) or not all(isinstance(u, dict) and len(u) > 1 for u in uncertainty.values()):
        raise ValueError("uncertainty must map every camera to its pixels at the centre and the corners")
    warn = []
    for name, u in uncertainty.items():
        corner = max(v for k, v in u.items() if k != "centre")
        if corner > CORNER_WARN_PX:
            warn.append(f"camera {name}: its projection is uncertain by {_px(corner)} px (1 sigma) at the image "
                        f"corners: the lens distortion there is extrapolated from the board's views; film the board "
                        f"near the corners of {name}'s image (or fix k3 at zero for a mild lens)")
    return warn


# warnings that say the result may be wrong (the rest: less certain where the views were few)
_DOUBT = ("the rig data disagrees", "between the held-out folds", "did not converge",
          "far above the rest")
_CAMERA = re.compile(r"^camera (\S+): (.*)$", re.S)
_FIGURE = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?(?: ?(?:px|%|sigma|deg|mm)\b|%)?")


def _camera_of(w: str) -> str | None:
    m = _CAMERA.match(w)
    return m.group(1) if m else None


def _without(text: str, name: str, by: str = "") -> str:
    """``text`` with the camera's name (as a whole word) replaced by ``by``."""
    return re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", by, text)


def group_warnings(warnings: Sequence[str]) -> list[str]:
    """Each kind of per-camera warning once: ``"camera A: ..."`` messages that differ only in the camera's name
    and their figures become the first one's words followed by ``"; the same for B (figures), C (figures)"`` (the
    figures that differ from the first one's).
    Other messages are kept; the order is that of each kind's first message, repeats said once.

    Raises
    ------
    ValueError
        When ``warnings`` is not a sequence of strings.
    """
    if isinstance(warnings, str) or not isinstance(warnings, Sequence) or not all(isinstance(w, str) for w in warnings):
        raise ValueError("warnings must be a sequence of strings")
    kinds: dict[str, list[tuple[str, str]]] = {}
    for w in dict.fromkeys(warnings):
        m = _CAMERA.match(w)
        key = _FIGURE.sub("#", _without(m.group(2), m.group(1), "{camera}")) if m else w
        kinds.setdefault(key, []).append((m.group(1) if m else "", w))
    out = []
    for group in kinds.values():
        first = group[0][1]
        if len(group) > 1:
            base = _FIGURE.findall(_without(_CAMERA.match(first).group(2), group[0][0]))
            said = []
            for name, w in group[1:]:
                figs = [f for f, b in zip(_FIGURE.findall(_without(_CAMERA.match(w).group(2), name)), base) if f != b]
                said.append(f"{name} ({', '.join(figs)})" if figs else name)
            first += "; the same for " + ", ".join(said)
        out.append(first)
    return out


def _px(v: float) -> str:
    """An uncertainty for the table: beyond 100 px the linearization says only "unknown"."""
    return f"{v:.3f}" if not v > 100 else ">100"


def _intrinsic_views(dets: list[Detection], size, linking: set[int], min_change: float, min_corners: int):
    """Novelty-thinned views plus every view that links this camera to another."""
    keep = set(select_views(dets, size=size, min_corners=min_corners, min_change=min_change))
    return [d for i, d in enumerate(dets) if i in keep or (d.frame in linking and len(d) >= min_corners)]


def _thin(frames: list[int], budget: int) -> list[int]:
    if len(frames) <= budget:
        return frames
    pick = np.unique(np.round(np.linspace(0, len(frames) - 1, budget)).astype(int))
    return [frames[i] for i in pick]


def _solve(dets, sizes, board, names, *, world, world_frame, mode, fix_k3, reject_outliers, min_views, solver,
           max_intrinsic_views, min_change, max_sets, min_corners, distortion, warn=None):
    """One calibration (intrinsics, then the bundle adjustment) without the evaluation; ``warn(message)`` as each
    camera's intrinsics and then the bundle adjustment give their warnings (before a later one can fail)."""
    seen: dict[int, int] = {}
    for n in names:
        for f in {d.frame for d in dets[n]}:
            seen[f] = seen.get(f, 0) + 1
    linking = {f for f, k in seen.items() if k >= 2}
    intr: dict[str, IntrinsicsResult] = {}
    problems, bad = [], []
    own: dict[str, list[Detection]] = {}
    for n in names:
        views = own[n] = _intrinsic_views(dets[n], tuple(sizes[n]), linking, min_change, min_corners)
        try:
            intr[n] = calibrate_intrinsics(views, board, tuple(sizes[n]), name=n, fix_k3=fix_k3,
                                           reject_outliers=reject_outliers, min_views=min_views,
                                           max_views=max_intrinsic_views, distortion=distortion)
            for w in intr[n].warnings if warn is not None else ():
                warn(w)
        except CalibrationError as exc:
            if not dets[n]:
                problems.append(
                    f"camera {n}: the board was never detected; check that {n} sees the board and that the board "
                    f"file matches the print (corners = INNER corners; ChArUco squares, dictionary, legacy flag)"
                )
            else:
                problems.append(str(exc))
            bad.append(n)
    if problems:
        raise CalibrationError("; ".join(problems), cameras=bad)
    if len(names) == 1:
        return intr, None, 0
    # rejected outlier views stay out of the bundle adjustment as well
    kept = {n: [d for d in dets[n] if d.frame not in intr[n].rejected] for n in names}
    count: dict[int, int] = {}
    for n in names:
        for d in kept[n]:
            count[d.frame] = count.get(d.frame, 0) + 1
    sets = set(_thin(sorted(f for f, k in count.items() if k >= 2), max_sets))
    # a camera that never saw the board at the same time as another keeps its views: the bundle adjustment's check
    # then says so, where with none it would say the camera never saw the board
    ba = {n: [d for d in kept[n] if d.frame in sets] if any(count[d.frame] >= 2 for d in kept[n]) else kept[n]
          for n in names}
    held = np.array([[k in intr[n].held for k in INTRINSIC_NAMES] for n in names])
    prior = None
    if mode == "prior":
        prior = np.stack([intr[n].covariance if intr[n].covariance is not None else np.full((9, 9), np.nan)
                          for n in names])
    sigma = float(np.sqrt(np.mean([intr[n].rms ** 2 for n in names]) / 2.0))  # per coordinate
    if mode == "prior":
        # The prior is worth as much as the rig's own pixel noise makes the joint data worth: a first
        # solve with the intrinsics held measures that noise (sync and rolling shutter add to it).
        ext0 = calibrate_extrinsics(ba, [intr[n].camera() for n in names], board, world=world,
                                    world_frame=world_frame, optimize_intrinsics=False, solver=solver)
        if np.isfinite(ext0.meta.get("sigma_px", np.nan)):
            sigma = max(sigma, float(ext0.meta["sigma_px"]))
    # the covariance counts the corners the Zhang solves share with the frame sets once
    shared = _shared_corners(own, intr, names, board) if mode == "prior" else {}
    ext = calibrate_extrinsics(
        ba, [intr[n].camera() for n in names], board, world=world, world_frame=world_frame,
        optimize_intrinsics=mode != "fixed", solver=solver,
        fixed_intrinsics=held,  # what each camera's own calibration held, the bundle keeps
        intrinsics_prior=prior, prior_scale=max(sigma, 1e-3), **shared,
    )
    for w in ext.warnings if warn is not None else ():
        warn(w)
    return intr, ext, len(sets)


def _shared_corners(own: dict, intr: dict, names, board) -> dict:
    """``prior_jacobian`` of :func:`calib.extrinsics.calibrate_extrinsics` from each camera's own solve
    (:func:`_own_jacobian`; nothing for a camera without a covariance)."""
    return {"prior_jacobian": {n: _own_jacobian(own[n], intr[n], board) for n in names
                               if intr[n].covariance is not None}}


def _own_jacobian(views: list[Detection], result: IntrinsicsResult, board) -> dict:
    """The camera's own (Zhang) solve at its solution: frame -> (corner ids, reduced Jacobian rows (n, 2, 9)) of
    every view it kept (:func:`calib.bundle.reduced_intrinsics_jacobian`)."""
    by_frame = {int(d.frame): d for d in views}
    kept = [by_frame[int(f)] for f in result.frames]
    obj = board.object_points()
    ob = np.concatenate([np.full(len(d), i) for i, d in enumerate(kept)])
    _, J, _ = reduced_intrinsics_jacobian(ob, np.concatenate([obj[d.ids] for d in kept]),
                                          np.concatenate([d.corners for d in kept]), intrinsics=result.params,
                                          board_rvec=result.rvecs, board_tvec=result.tvecs,
                                          held=np.array([k in result.held for k in INTRINSIC_NAMES]))
    rows, at = {}, 0
    for d in kept:
        rows[int(d.frame)] = (np.asarray(d.ids), J[at : at + len(d)])
        at += len(d)
    return rows


def _unflip(dets: list[Detection], width: int) -> list[Detection]:
    """Detections made on images flipped left-right, in the coordinates of the images as delivered."""
    return [Detection(d.ids, np.column_stack([width - 1.0 - d.corners[:, 0], d.corners[:, 1]]), d.frame,
                      dict(d.meta)) for d in dets]


def _pose_spread(dets, others, board, sizes, name, min_corners) -> float:
    """How inconsistent ``name``'s pose relative to the other cameras is over their shared frames.

    Median over camera pairs of the median distance (mm) between the other camera's centre as
    seen from every shared frame and its medoid; ``inf`` without shared frames.
    """
    from calib.extrinsics import board_poses

    def poses(n, ds):
        try:
            r = calibrate_intrinsics(ds, board, tuple(sizes[n]), name=n, max_views=40, reject_outliers=False)
        except CalibrationError:
            return {}
        return board_poses(ds, board, K=r.K, dist=r.dist, min_corners=min_corners)

    mine = poses(name, dets)
    spreads = []
    for n, ds in others.items():
        theirs = poses(n, ds)
        shared = sorted(set(mine) & set(theirs))
        if len(shared) < 3:
            continue
        centres = []
        for f in shared:
            Ra, ta, _ = mine[f]
            Rb, tb, _ = theirs[f]
            R = Rb @ Ra.T
            centres.append(-R.T @ (tb - R @ ta))  # the other camera's centre in this camera's frame
        c = np.array(centres)
        med = c[np.argmin(np.linalg.norm(c[:, None] - c[None], axis=2).sum(1))]
        spreads.append(float(np.median(np.linalg.norm(c - med, axis=1))))
    return float(np.median(spreads)) if spreads else float("inf")


def resolve_flipped(detections, sizes, board, flipped, names, min_corners):
    """Decide, for cameras whose board was found only in the flipped image, which of two things happened.

    Either the camera delivers mirrored images (its model is that of the flipped image,
    ``mirror = true``), or it sees the board from behind, through the print (its model is
    that of the image as delivered). A single camera cannot tell them apart; the rig can:
    only the right one gives the same relative pose to the other cameras in every shared
    frame. Without another camera sharing frames, the mirror is assumed.

    Returns
    -------
    detections : dict
        With the flipped cameras' detections in the coordinates of their model.
    mirrored : list of str
        Cameras calibrated as mirroring.
    notes : list of str
    """
    dets = dict(detections)
    mirrored, notes = [], []
    for n in flipped:
        others = {m: dets[m] for m in names if m != n and m not in flipped}
        as_mirror = _pose_spread(dets[n], others, board, sizes, n, min_corners)
        behind = _unflip(dets[n], int(sizes[n][0]))
        as_behind = _pose_spread(behind, others, board, sizes, n, min_corners)
        if np.isfinite(as_behind) and as_behind < 0.5 * as_mirror:
            dets[n] = behind
            notes.append(f"{n}: the board is found only in the flipped image, and the rig shows that {n} sees it "
                         f"from behind, through the print (relative pose to the other cameras consistent to "
                         f"{as_behind:.0f} mm; {as_mirror:.0f} mm as a mirroring camera): calibrated as delivered, "
                         f"mirror = false")
        else:
            mirrored.append(n)
            why = (f"relative pose to the other cameras consistent to {as_mirror:.0f} mm; "
                   f"{as_behind:.0f} mm seen from behind" if np.isfinite(as_mirror) else "no other camera to tell")
            notes.append(f"{n} delivers mirrored images ({why}): calibrated on the flipped images, mirror = true")
    return dets, mirrored, notes


def _intrinsic_vector(cam) -> np.ndarray:
    """The camera's intrinsics in :data:`INTRINSIC_NAMES`' order (fx, fy, cx, cy, then the distortion), as an
    :class:`~calib.intrinsics.IntrinsicsResult`'s ``params``."""
    return np.array([cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], *cam.dist])


def _moved(intr: IntrinsicsResult, cam) -> dict:
    new = _intrinsic_vector(cam)
    cov = intr.covariance
    out = {}
    for i, k in enumerate(INTRINSIC_NAMES):
        sd = float(np.sqrt(cov[i, i])) if cov is not None and np.isfinite(cov[i, i]) else float("nan")
        if sd > 0:
            out[k] = float((new[i] - intr.params[i]) / sd)
    return out


def intrinsics_moved(intrinsics: Mapping, calibration: Calibration) -> tuple[dict, list[str]]:
    """Did the bundle adjustment move a camera's intrinsics further than its own calibration's uncertainty
    allows? One test per camera, for the rig a false-alarm rate of :data:`MOVE_WARN_P`.

    The move ``d`` of the camera's free intrinsics (fx, fy, cx, cy, k1, k2, p1, p2, k3 less those held) from
    its own (Zhang) solution is judged jointly, by ``chi2 = d^T C^-1 d`` with ``C`` the Zhang covariance (its full
    correlations), against the chi-square distribution with as many degrees of freedom as free intrinsics; a
    camera is named when the chance of so large a move is below ``MOVE_WARN_P / cameras`` (Bonferroni). Judging
    every number of every camera at 3 sigma instead makes about ``9 x cameras`` tests, each counting fx and fy
    (correlated near 1) apart: a rig of accurate cameras then warns often. ``C`` leaves out the bundle
    adjustment's own uncertainty, so the test errs towards silence, and a calibration the rig's data really
    contradict moves its intrinsics by many of their standard deviations.

    Parameters
    ----------
    intrinsics : mapping
        Camera name -> :class:`~calib.intrinsics.IntrinsicsResult` (each camera's own solve, with its covariance).
    calibration : Calibration
        The bundle adjustment's cameras (every name of ``intrinsics`` among them).

    Returns
    -------
    figures : dict
        Name -> ``{"chi2", "dof", "p"}`` (cameras without a covariance left out).
    warnings : list of str
        One per camera whose move is unlikely (``p < MOVE_WARN_P / cameras``).

    Raises
    ------
    ValueError
        When ``intrinsics`` is not such a mapping or names a camera ``calibration`` lacks.
    """
    from scipy.stats import chi2

    if not isinstance(intrinsics, Mapping) or not all(isinstance(r, IntrinsicsResult) for r in intrinsics.values()):
        raise ValueError("intrinsics must map camera names to IntrinsicsResult")
    if not isinstance(calibration, Calibration) or set(intrinsics) - set(calibration.names):
        raise ValueError("calibration must be a Calibration holding every camera of intrinsics")
    figures, warn = {}, []
    for name, intr in intrinsics.items():
        cov, cam = intr.covariance, calibration[name]
        if cov is None:
            continue
        d = _intrinsic_vector(cam) - intr.params
        free = np.flatnonzero(np.isfinite(np.diag(cov)) & (np.diag(cov) > 0))
        if free.size == 0:
            continue
        C = cov[np.ix_(free, free)]
        m = float(d[free] @ np.linalg.lstsq(C, d[free], rcond=None)[0])
        figures[name] = {"chi2": m, "dof": int(free.size), "p": float(chi2.sf(m, free.size))}
    for name, f in figures.items():
        if f["p"] < MOVE_WARN_P / len(figures):
            z = _moved(intrinsics[name], calibration[name])
            far = sorted(z, key=lambda k: -abs(z[k]))[:2]
            warn.append(f"camera {name}: the bundle adjustment moved its intrinsics further than its own calibration's "
                        f"uncertainty allows (" + ", ".join(f"{k} {z[k]:+.1f} sigma" for k in far) +
                        f"; together a chance of {f['p']:.1g}): the rig data disagrees with what this camera saw "
                        "alone (a moved camera, a bent board, or too few views of it)")
    return figures, warn


def rotation_sigma(calibration: Calibration, rotation_cov: np.ndarray | None, reference: str | None) -> dict:
    """1-sigma uncertainty (deg) of every camera's rotation relative to ``reference`` and of every
    pair's relative rotation, from the bundle adjustment's covariance.

    The figure is the RMS of the rotation angle error, ``sqrt(trace(S))`` of the 3 x 3 covariance
    ``S`` of the small rotation. For a pair, ``d_ab = d_a - R_a R_b^T d_b`` (left perturbations).
    It assumes independent corner noise of the measured size; errors shared by whole views (a
    board that moved between the cameras' exposures) make it optimistic, see
    :func:`fold_rotation_spread` for the figure the data themselves give.

    Returns
    -------
    dict
        ``reference``, ``per_camera`` (name -> deg, 0 for the reference), ``pairs``
        (``"a - b"`` -> deg); empty without a covariance.
    """
    if rotation_cov is None or reference is None:
        return {}
    cams = calibration.cameras
    rc = np.asarray(rotation_cov, dtype=np.float64)
    per = {c.name: float(np.degrees(np.sqrt(max(np.trace(rc[i, i]), 0.0)))) for i, c in enumerate(cams)}
    pairs = {}
    for a in range(len(cams)):
        for b in range(a + 1, len(cams)):
            R = cams[a].R @ cams[b].R.T
            S = rc[a, a] + R @ rc[b, b] @ R.T - rc[a, b] @ R.T - R @ rc[b, a]
            pairs[f"{cams[a].name} - {cams[b].name}"] = float(np.degrees(np.sqrt(max(np.trace(S), 0.0))))
    return {"reference": reference, "per_camera": per, "pairs": pairs}


def fold_rotation_spread(calibrations: Sequence[Calibration], names: Sequence[str], reference: str | None) -> dict:
    """Grouped-jackknife 1-sigma (deg) of the rotations, from the held-out folds' calibrations.

    Each fold calibrated on all frame sets but one group; the spread of the k results,
    ``sqrt((k - 1) / k * sum |log(R_i mean(R)^T)|^2)`` (Efron & Tibshirani 1993, ch. 11),
    estimates the uncertainty of the calibration on all frame sets, whatever the errors
    (shared by views, intrinsics), as far as k folds can tell.

    Returns
    -------
    dict
        ``per_camera`` (relative to ``reference``), ``pairs`` as :func:`rotation_sigma`, and
        ``folds``; empty with fewer than 3 folds.
    """
    k = len(calibrations)
    if k < 3:
        return {}

    def spread(rots: list[np.ndarray]) -> float:
        U, _, Vt = np.linalg.svd(np.sum(rots, axis=0))
        mean = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        dev = np.radians(rotation_angle_deg(np.stack(rots) @ mean.T))
        return float(np.degrees(np.sqrt((k - 1) / k * np.sum(dev**2))))

    def rel(c: Calibration, a: str, b: str) -> np.ndarray:
        return c[a].R @ c[b].R.T

    out: dict = {"folds": k, "per_camera": {}, "pairs": {}}
    if reference is not None:
        out["reference"] = reference
        out["per_camera"] = {n: spread([rel(c, n, reference) for c in calibrations]) for n in names}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            out["pairs"][f"{a} - {b}"] = spread([rel(c, a, b) for c in calibrations])
    return out


def _held_out(dets, sizes, board, names, folds: int, solve_kw: dict) -> dict | None:
    """k-fold over frame sets (frame set i in fold i mod k): calibrate on the rest, measure on the fold."""
    frames = sorted({d.frame for n in names for d in dets[n]})
    k = min(int(folds), len(frames) // 2)
    if k < 2:
        return None
    blocks = [np.array(frames[i::k]) for i in range(k)]
    sq = {n: 0.0 for n in names}
    cnt = {n: 0 for n in names}
    views = {n: 0 for n in names}
    failed, fold_calibs = [], []
    for i, block in enumerate(blocks):
        out = set(block.tolist())
        rest = {n: [d for d in dets[n] if d.frame not in out] for n in names}
        try:  # the world frame is a gauge: any will do, and the chosen one may be in the fold
            _, ext, _ = _solve(rest, sizes, board, names, **{**solve_kw, "world_frame": None})
        except CalibrationError as exc:
            failed.append(f"fold {i + 1} of {k}: {exc}")
            continue
        fold_calibs.append(ext.calibration)
        ev = reprojection_errors(ext.calibration, {n: [d for d in dets[n] if d.frame in out] for n in names},
                                 board)
        for n, v in ev["per_camera"].items():
            sq[n] += v["sum_sq"]
            cnt[n] += v["corners"]
            views[n] += v["views"]
    if len(failed) == k:
        return None
    per = {n: {"rms": float(np.sqrt(sq[n] / cnt[n])) if cnt[n] else float("nan"), "corners": cnt[n],
               "views": views[n], "sum_sq": sq[n]} for n in names}
    tot = sum(cnt.values())
    return {"per_camera": per, "rms": float(np.sqrt(sum(sq.values()) / tot)) if tot else float("nan"),
            "folds": k, "frames": len(frames), "failed_folds": failed, "calibrations": fold_calibs}


def _shared_error_warnings(cov: dict, folds: dict) -> list[str]:
    """Cameras whose rotation varies between the folds far more than independent corner errors explain."""
    out = []
    for name, f in (folds.get("per_camera") or {}).items():
        c = (cov.get("per_camera") or {}).get(name, float("nan"))
        if name != cov.get("reference") and f > FOLD_WARN_DEG and f > FOLD_WARN_RATIO * c:
            out.append(f"camera {name}: its rotation relative to {cov['reference']} varies by {f:.2f} deg (1 sigma) "
                       f"between the held-out folds, {f / c:.1f} times what independent corner errors explain: errors "
                       f"shared by whole views dominate (a board that moved between the cameras' exposures, cameras "
                       f"not synchronised, a bending board), so trust the folds' figure; hold the board still in each "
                       f"pose, or synchronise the cameras")
    return out


def _evaluate(calib, dets, sizes, board, names, intr, ext, intrinsics, holdout_folds, solve_kw):
    """The figures of the module docstring (step 3) and the warnings they give."""
    ev: dict = {"mode": intrinsics}
    ev["all_frames"] = reprojection_errors(calib, dets, board)
    ev["geometry_all"] = triangulate_board_error(calib, dets, board)
    icov = ext.meta.get("intrinsics_cov")
    ev["uncertainty"] = {}
    for ci, cam in enumerate(calib.cameras):
        cov = icov[ci] if icov is not None and intrinsics != "fixed" else intr[cam.name].covariance
        if cov is not None:
            ev["uncertainty"][cam.name] = projection_uncertainty(cam, cov)
    ev["moved_sigma"] = {} if intrinsics == "fixed" else {c.name: _moved(intr[c.name], c) for c in calib.cameras}
    ev["rotation_sigma_deg"] = rotation_sigma(calib, ext.meta.get("rotation_cov"), ext.meta.get("reference"))
    warn = []
    if intrinsics != "fixed":
        ev["moved_test"], warn = intrinsics_moved(intr, calib)
    warn += corner_warnings(ev["uncertainty"])
    ev["held_out"] = _held_out(dets, sizes, board, names, holdout_folds, solve_kw) if holdout_folds else None
    if ev["held_out"] is not None:
        warn += [f"held-out {f}" for f in ev["held_out"]["failed_folds"]]
        ref = ev["rotation_sigma_deg"].get("reference")
        ev["rotation_folds_deg"] = fold_rotation_spread(ev["held_out"].pop("calibrations"), names, ref)
        warn += _shared_error_warnings(ev["rotation_sigma_deg"], ev["rotation_folds_deg"])
    for w in warn:
        log.debug(w)  # in the result's warnings / report
    return ev, warn


def _check(detections, sizes, board, cameras, intrinsics, max_sets, holdout_folds, min_change, mirrored, flipped):
    """Validate :func:`calibrate_rig`'s arguments; the camera names in rig order."""
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    if not isinstance(detections, Mapping) or not isinstance(sizes, Mapping):
        raise ValueError("detections and sizes must be mappings keyed by camera name")
    if intrinsics not in INTRINSICS_MODES:
        raise ValueError(f"intrinsics must be one of {INTRINSICS_MODES}, got {intrinsics!r}")
    if not (isinstance(max_sets, (int, np.integer)) and max_sets >= 2):
        raise ValueError(f"max_sets must be an integer >= 2, got {max_sets!r}")
    if not (isinstance(holdout_folds, (int, np.integer)) and (holdout_folds == 0 or holdout_folds >= 2)):
        raise ValueError(f"holdout_folds must be 0 or an integer >= 2, got {holdout_folds!r}")
    if not (np.isfinite(min_change) and min_change >= 0):
        raise ValueError(f"min_change must be >= 0, got {min_change!r}")
    names = list(cameras) if cameras is not None else list(sizes)
    if not names:
        raise ValueError("cameras: no cameras to calibrate")
    missing = [n for n in names if n not in sizes]
    if missing:
        raise ValueError(f"sizes: no image size for camera(s) {missing}")
    for what, given in (("mirrored", mirrored), ("flipped", flipped)):
        unknown = sorted(set(given) - set(names))
        if unknown:
            raise ValueError(f"{what}: unknown camera(s) {unknown}")
    return names


def calibrate_rig(
    detections: Mapping[str, Sequence[Detection]],
    sizes: Mapping[str, tuple[int, int]],
    board: Board,
    *,
    cameras: Sequence[str] | None = None,
    world: str = "board",
    world_frame: int | None = None,
    intrinsics: str = "prior",
    optimize_intrinsics: bool | None = None,
    fix_k3: bool = False,
    reject_outliers: bool = True,
    min_views: int = 4,
    solver: str = "lm",
    max_intrinsic_views: int | None = 40,
    min_change: float = 0.02,
    max_sets: int = MAX_SETS,
    holdout_folds: int = 0,
    mirrored: Sequence[str] = (),
    flipped: Sequence[str] = (),
    distortion: str = "prior",
    warn: Callable[[str], None] | None = None,
) -> RigCalibration:
    """Intrinsics of every camera (:func:`calib.intrinsics.calibrate_intrinsics`), then
    one bundle adjustment of the rig (:func:`calib.extrinsics.calibrate_extrinsics`),
    then the evaluation (module docstring).

    Parameters
    ----------
    detections : mapping str -> sequence of Detection
        Per camera, every detection (no need to thin them: this function selects);
        equal ``frame`` numbers mean the same moment.
    sizes : mapping str -> (int, int)
        Image ``(width, height)`` per camera.
    board : Chessboard or Charuco
    cameras : sequence of str, optional
        Rig order (default: the order of ``sizes``).
    world, world_frame, solver
        See :func:`calib.extrinsics.calibrate_extrinsics`.
    intrinsics : {"prior", "fixed", "free"}
        How the bundle adjustment treats the intrinsics (module docstring).
    optimize_intrinsics : bool, optional
        Older spelling: ``False`` means ``intrinsics="fixed"``, ``True`` keeps ``intrinsics``.
    fix_k3, reject_outliers, min_views
        See :func:`calib.intrinsics.calibrate_intrinsics`.
    distortion : {"prior", "full", "auto"}
        Each camera's distortion model (:func:`calib.intrinsics.calibrate_intrinsics`):
        ``"prior"`` (default) fits all five coefficients under a weak zero-mean prior on
        ``p1, p2, k3`` (its posterior covariance is then the bundle adjustment's prior);
        ``"full"`` keeps all five coefficients without a prior; ``"auto"`` holds ``p1, p2`` and / or ``k3``
        at zero where the camera's own views do not support them, and the bundle adjustment
        keeps what each camera held (docs/calibration.md: steadier principal points on
        narrow-coverage footage, at the price of small real terms on a well-covered rig).
    max_intrinsic_views : int or None
        Views per camera for its Zhang solve (evenly spaced).
    min_change : float
        Novelty threshold of the intrinsic views (:func:`calib.detect.select_views`).
    max_sets : int
        Frame sets seen by two or more cameras above which the bundle adjustment thins them evenly.
    holdout_folds : int
        Folds of the held-out error (0: none, the default here; ``stage calibrate`` uses 5).
        Each fold is a whole calibration, so this multiplies the time by ``1 + holdout_folds``.
    mirrored : sequence of str
        Cameras known to deliver mirrored images (their detections made on the flipped
        images); marked ``meta["mirror"] = True`` in the calibration.
    flipped : sequence of str
        Cameras whose board was found only in the flipped image (detections made on it):
        :func:`resolve_flipped` decides whether each mirrors or sees the board from behind.
    warn : callable, optional
        ``warn(message)`` as each of the result's warnings (:attr:`RigCalibration.warnings`, in their order) is
        known: each camera's once its intrinsics are solved, the bundle adjustment's, then the evaluation's. A
        caller keeps those said before the calibration fails (a later camera, the bundle adjustment), which no
        result holds.

    Returns
    -------
    RigCalibration
        With a single camera only the intrinsics (camera at the origin).

    Raises
    ------
    CalibrationError
        Naming every camera that has too few views or cannot be connected, with
        what to do. Nothing is written anywhere.
    """
    if warn is not None and not callable(warn):
        raise ValueError(f"warn must be a callable taking a message, or None, got {type(warn).__name__}")
    if optimize_intrinsics is False:
        intrinsics = "fixed"
    names = _check(detections, sizes, board, cameras, intrinsics, max_sets, holdout_folds, min_change,
                   mirrored, flipped)
    from calib.detect import default_min_corners

    min_corners = default_min_corners(board)
    dets = {n: sorted((d for d in detections.get(n, ()) if d is not None), key=lambda d: d.frame) for n in names}
    flip_notes: list[str] = []
    if flipped:
        dets, more, flip_notes = resolve_flipped(dets, sizes, board, list(flipped), names, min_corners)
        mirrored = list(mirrored) + more
    if distortion not in DISTORTION_MODES:
        raise ValueError(f"distortion must be one of {DISTORTION_MODES}, got {distortion!r}")
    solve_kw = dict(world=world, world_frame=world_frame, mode=intrinsics, fix_k3=fix_k3, distortion=distortion,
                    reject_outliers=reject_outliers, min_views=min_views, solver=solver,
                    max_intrinsic_views=max_intrinsic_views, min_change=min_change, max_sets=max_sets,
                    min_corners=min_corners)
    intr, ext, n_sets = _solve(dets, sizes, board, names, **solve_kw, warn=warn)
    mirror = set(mirrored)

    def mark(cam):
        return cam.replace(meta={**cam.meta, "mirror": True}) if cam.name in mirror else cam

    if ext is None:
        cam = mark(intr[names[0]].camera())
        meta = {"method": "intrinsics only", "rms_px": intr[names[0]].rms}
        return RigCalibration(Calibration((cam,), units="mm", meta=meta), intr, None,
                              {"mode": intrinsics, "sets": 0, "flipped": flip_notes, "mirrored": sorted(mirror),
                               "detections": dets})
    calib = Calibration(tuple(mark(c) for c in ext.calibration.cameras), units="mm", meta=dict(ext.calibration.meta))
    ev, evaluated = _evaluate(calib, dets, sizes, board, names, intr, ext, intrinsics, holdout_folds, solve_kw)
    for w in evaluated if warn is not None else ():
        warn(w)
    ev.update({"sets": n_sets, "flipped": flip_notes, "mirrored": sorted(mirror), "detections": dets})
    meta = dict(calib.meta)
    meta["per_camera_rms_px"] = dict(ext.per_camera_rms)
    meta["board_geometry_error_mm"] = {k: v for k, v in ext.geometry.items() if np.isfinite(v)}
    meta["intrinsics"] = intrinsics
    if ev["held_out"] is not None:
        meta["held_out_rms_px"] = {n: v["rms"] for n, v in ev["held_out"]["per_camera"].items()}
    meta["all_frames_rms_px"] = {n: v["rms"] for n, v in ev["all_frames"]["per_camera"].items()}
    calib = Calibration(calib.cameras, units="mm", meta=meta)
    return RigCalibration(calib, intr, ext, ev, tuple(evaluated))
