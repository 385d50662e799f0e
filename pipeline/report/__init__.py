"""The HTML report of a processed take: one self-contained page that works offline.

``render_report(DIR)`` reads a results directory (``spine.json``,
``report.json``, ``meshes/frame_NNNNNN.ply``; see :mod:`pipeline.process`) and,
when a take is given (or ``report.json`` names one that exists), the take
itself, and returns a full HTML page:

* summary: frames, limbs ``K``, timings, empty frames, files;
* an interactive 3-D view: the reference frame's surface rigged to the spine
  (:mod:`pipeline.armature_spine`) and posed in every frame, with the animated
  spine, its tips and junctions (slider and play button);
* the tip count over time (Brostow et al. 2004, Fig. 7);
* per-frame surface quality (plot and table);
* silhouette consistency: per camera over the take, the IoU of its mask and the
  projected surface (``consistency.json``), the worst frames' masks beside the projection;
* the cameras: frusta, intrinsics, calibration errors (from the
  calibration's ``meta``) and how well they cover the subject;
* contact sheets of frames and masks.

plotly.js is embedded in the page (from the plotly package), images are
base64 data URIs: nothing is fetched at run time. The figure functions
(:mod:`pipeline.report.figures`) are reusable, e.g. by the API's pages.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import logging
import math
from pathlib import Path

import jinja2
import numpy as np

from pipeline.report.figures import (
    camera_coverage,
    consistency_figure,
    contact_sheet,
    decimate_mesh,
    figure_html,
    frusta_figure,
    jpeg_data_uri,
    mesh_quality_figure,
    plotly_js,
    png_data_uri,
    spine_figure,
    tip_count_figure,
)

__all__ = [
    "render_report",
    "write_report",
    "NothingToReportError",
    "take_contact_sheets",
    "camera_coverage",
    "contact_sheet",
    "decimate_mesh",
    "figure_html",
    "frusta_figure",
    "mesh_quality_figure",
    "plotly_js",
    "spine_figure",
    "tip_count_figure",
]

log = logging.getLogger(__name__)


class NothingToReportError(ValueError):
    """A results directory with neither ``spine.json`` nor ``report.json``."""


@functools.cache
def _templates() -> jinja2.Environment:
    """The report's templates (``pipeline/report/templates``), autoescaped."""
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("pipeline.report", "templates"),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
    )
    env.filters["cell"] = _cell
    return env


def _cell(v) -> str:
    """A table cell's text: ``–`` for missing or non-finite, ``yes``/``no``, 4 significant digits."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}" if math.isfinite(v) else "–"
    return str(v)


def _scalars(d: dict, prefix: str = "") -> dict:
    """Flatten the scalar leaves of a nested dict (``a.b``)."""
    out = {}
    for k, v in (d or {}).items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_scalars(v, key + "."))
        elif isinstance(v, (int, float, str, bool)) or v is None:
            out[key] = v
    return out


# --------------------------------------------------------------------------- take images


def take_contact_sheets(reader, *, n_frames: int = 4, max_cameras: int = 12, thumb_width: int = 160) -> dict:
    """Contact sheets of a take: some frame sets (rows) x cameras (columns), images and masks.

    Parameters
    ----------
    reader : stage.store.TakeReader
    n_frames : int
        Frame sets shown, evenly spread over the take.
    max_cameras : int
    thumb_width : int

    Returns
    -------
    dict
        ``frames``: (H, W, 3) BGR sheet; ``masks``: sheet or None when the take
        has no masks; ``sets``: the frame-set numbers; ``cameras``: the camera ids.
    """
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    n = len(reader)
    if n == 0:
        raise ValueError(f"{reader.path}: the take has no frame sets")
    sets = sorted(set(np.linspace(0, n - 1, min(n, int(n_frames))).round().astype(int).tolist()))
    cams = list(reader.cameras)[: int(max_cameras)]
    with_masks = [c for c in cams if c in reader.masks_present()]
    masks = {c: reader.masks(c) for c in with_masks}
    imgs, mimgs, labels = [], [], []
    for k in sets:
        rows = reader.set_rows(k)
        for c in cams:
            r = rows[c]
            imgs.append(reader.frame(c, r) if r >= 0 else None)
            m = masks.get(c)
            mimgs.append(m[r] if (m is not None and r >= 0 and r < len(m)) else None)
            labels.append(f"{c} #{k}")
    frames = contact_sheet(imgs, columns=len(cams), labels=labels, thumb_width=thumb_width)
    msheet = contact_sheet(mimgs, columns=len(cams), labels=labels, thumb_width=thumb_width) if masks else None
    return {"frames": frames, "masks": msheet, "sets": sets, "cameras": cams}


# --------------------------------------------------------------------------- page


def _load_json(p: Path):
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{p}: cannot read ({exc})") from None


def _rigged_view_model(spine, d: Path, *, max_faces: int):
    """A small rigged surface for the 3-D view (None when no mesh of a complete frame exists)."""
    from pipeline.armature_spine import reference_frame, rigged_model
    from pipeline.gltf_export import find_frame_mesh
    from pipeline.meshio import load_mesh

    try:
        best = reference_frame(spine)
    except ValueError as exc:
        log.warning("no rest pose for the 3-D view: %s", exc)
        return None, None
    fi = [int(x) for x in spine.frame_indices]
    for t in sorted(range(len(fi)), key=lambda t: abs(t - best)):
        p = find_frame_mesh(d, fi[t])
        if p is None:
            continue
        try:
            reference_frame(spine, prefer=t)
        except ValueError:
            continue
        v, f = load_mesh(p)
        if len(f) == 0:
            continue
        v, f = decimate_mesh(v, f, max_faces=max_faces)
        try:
            return rigged_model(spine, v, f, reference=t), None
        except ValueError as exc:  # fall back to the static surface
            log.warning("could not rig the surface for the 3-D view: %s", exc)
            return None, (v, f)
    return None, None


def render_report(results_dir, *, take=None, max_frames: int = 120, view_faces: int = 5000,
                  contact_frames: int = 4) -> str:
    """A full, self-contained HTML page about a processed take.

    Parameters
    ----------
    results_dir : str or Path
        Output directory of ``stage process`` (``spine.json``, ``report.json``, ``meshes/``).
    take : str or Path, optional
        The take (``.h5``) for contact sheets and its calibration. Default:
        the take named in ``report.json``, when that file exists.
    max_frames : int
        Animation keys of the 3-D view.
    view_faces : int
        Faces of the surface shown in the 3-D view (decimated for the page's size).
    contact_frames : int
        Frame sets in the contact sheets.

    Returns
    -------
    str
        The HTML page (plotly.js embedded; no network access needed), rendered
        from ``pipeline/report/templates/report.html``.

    Raises
    ------
    FileNotFoundError
        ``results_dir`` or ``take`` does not exist.
    NothingToReportError
        Neither ``spine.json`` nor ``report.json`` in ``results_dir``.
    """
    d = Path(results_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"results directory not found: {d}")
    if int(max_frames) < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    if int(view_faces) < 4:
        raise ValueError(f"view_faces must be >= 4, got {view_faces}")
    if take is not None and not Path(take).is_file():
        raise FileNotFoundError(f"take not found: {take}")
    spine, report = _read_results(d)
    if take is None and isinstance(report, dict) and isinstance(report.get("take"), str):
        if Path(report["take"]).is_file():
            take = report["take"]

    warnings: list[str] = []
    calibration, sheets = _read_take(take, d, contact_frames=int(contact_frames))
    sections = [
        _summary_section(d, spine, report, take, warnings),
        _view_section(d, spine, max_frames=int(max_frames), view_faces=int(view_faces))
        if spine is not None else None,
        _tips_section(spine, report),
        _armature_section(d, max_frames=int(max_frames), warnings=warnings),
        _quality_section(report, warnings),
        _consistency_section(d, take, calibration, warnings),
        _cameras_section(calibration, spine, warnings) if calibration is not None else None,
        _sheets_section(sheets) if sheets is not None else None,
    ]
    title = f"capture-stage report: {d.resolve().name}"
    return _templates().get_template("report.html").render(
        title=title,
        where=str(d.resolve()),
        stamp=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        plotly_js=plotly_js().replace("</script", "<\\/script"),
        sections=[s for s in sections if s is not None],
        warnings=warnings,
    )


# --------------------------------------------------------------------------- sections
# Each returns the data one block of the template shows (``id`` picks the block), or None.


def _read_results(d: Path):
    """``(spine or None, report.json or None)`` of a results directory."""
    has_spine = (d / "spine.json").is_file()
    report = _load_json(d / "report.json") if (d / "report.json").is_file() else None
    if not has_spine and report is None:
        raise NothingToReportError(f"{d} has neither spine.json nor report.json: run `stage process` first")
    spine = None
    if has_spine:
        from pipeline.spine_format import read_spine

        spine = read_spine(d / "spine.json")
    return spine, report


def _read_take(take, d: Path, *, contact_frames: int):
    """``(calibration or None, contact sheets or None)``: from the take, else ``calibration.json``."""
    calibration = sheets = None
    if take is not None:
        from stage.store import TakeReader

        with TakeReader(take) as reader:
            calibration = reader.calibration
            sheets = take_contact_sheets(reader, n_frames=contact_frames)
    if calibration is None and (d / "calibration.json").is_file():
        from calib.calibration import Calibration

        calibration = Calibration.from_dict(_load_json(d / "calibration.json"))
    return calibration, sheets


def _summary_section(d: Path, spine, report, take, warnings: list[str]) -> dict:
    rows = []
    if spine is not None:
        rows += [["frames", spine.frame_count], ["limbs K", spine.K], ["junctions", len(spine.junction_ids)],
                 ["fps", spine.fps], ["units", spine.units]]
        refs = spine.meta.get("references")
        if refs:
            rows.append(["reference frames", ", ".join(str(int(spine.frame_indices[r])) for r in refs
                                                        if 0 <= r < spine.frame_count)])
    if isinstance(report, dict):
        for k in ("frames", "total_seconds"):
            if k in report and not (spine is not None and k == "frames"):
                rows.append([k.replace("_", " "), report[k]])
        if report.get("empty_frames"):
            rows.append(["empty frames", ", ".join(str(x) for x in report["empty_frames"][:50])])
            warnings.append(f"{len(report['empty_frames'])} frame(s) have no surface")
        if report.get("damaged_sets"):  # the warnings say which camera's frames
            rows.append(["skipped frame sets (damaged)", ", ".join(str(x) for x in report["damaged_sets"][:50])])
        warnings.extend(str(w) for w in report.get("warnings") or [])  # e.g. the blind side under the subject
        if (report.get("grid") or {}).get("box"):
            rows.append(["subject box", _box_choice(report["grid"]["box"])])
        if (report.get("grid") or {}).get("voxel"):
            rows.append(["voxel", _grid_choice(report["grid"])])
        for k, v in (report.get("seconds") or {}).items():
            rows.append([f"seconds: {k}", v])
    if spine is not None and spine.meta.get("count_rule", "mode") not in ("mode", "given"):
        rows.append(["limb count", spine.meta["count_rule"]])
    files = [n for n in ("spine.json", "report.json", "spine_rig.glb", "spine.glb") if (d / n).is_file()]
    n_meshes = len(list((d / "meshes").glob("frame_*.ply"))) if (d / "meshes").is_dir() else 0
    rows.append(["files", ", ".join(files + ([f"meshes/ ({n_meshes})"] if n_meshes else []))])
    if take is not None:
        rows.append(["take", str(take)])
    return {"id": "summary", "title": "Summary", "rows": rows}


def _box_choice(b: dict) -> str:
    """The subject's box and why (``report.json`` ``grid.box``)."""
    size = " x ".join(f"{x:.4g}" for x in b.get("size", []))
    return f"{size}: {b.get('why', '')}"


def _grid_choice(g: dict) -> str:
    """The processing grid's voxel and why it is that size (``report.json`` ``grid``)."""
    head = f"{g['voxel']:.3g} ({' x '.join(str(n) for n in g.get('shape', []))} voxels)"
    if g.get("source") == "rig":
        return (f"{head}: {g['pixels_per_voxel']:g} x the median pixel footprint at the subject "
                f"({g['pixel_footprint']:.3g} over {g['cameras_seeing_subject']} cameras), limited by {g['limited_by']}")
    return f"{head}: resolution {g.get('resolution')}, as given"  # stage process's or a job's: no option named


def _view_section(d: Path, spine, *, max_frames: int, view_faces: int) -> dict:
    model, static = _rigged_view_model(spine, d, max_faces=view_faces)
    fig = spine_figure(spine, model=model, mesh=static, max_frames=max_frames)
    if model is not None:
        note = ("The reference frame's surface is rigged to the spine (bone heat weights) and posed in every "
                "frame by linear blend skinning.")
    elif static is None:
        note = "No surface mesh of a complete frame: the spine alone."
    else:
        note = "The reference frame's surface (static)."
    return {"id": "view", "title": "3-D view: surface and animated spine", "note": note,
            "figure": figure_html(fig, div_id="spine-view")}


def _tips_section(spine, report) -> dict | None:
    counts = None
    if spine is not None and spine.meta.get("tip_counts"):
        counts = spine.meta["tip_counts"]
    elif isinstance(report, dict) and report.get("tip_counts"):
        counts = report["tip_counts"]
    if not counts:
        return None
    K = spine.K if spine is not None else None
    fi = spine.frame_indices if spine is not None and len(spine.frame_indices) == len(counts) else None
    fig = tip_count_figure(counts, K=K, frame_indices=fi, fps=spine.fps if spine is not None else None)
    unseen = None
    if spine is not None:
        unseen = [[lid, int(np.sum(~np.all(np.isfinite(spine.tips[:, k]), axis=1)))]
                  for k, lid in enumerate(spine.limb_ids)]
    return {"id": "tips", "title": "Tips over time", "figure": figure_html(fig, div_id="tip-counts"),
            "K": K, "n": len(counts), "off": sum(1 for c in counts if c is not None and K is not None and c != K),
            "unseen": unseen}


def _armature_section(d: Path, *, max_frames: int, warnings: list[str]) -> dict | None:
    """The armature of ``DIR/rig/`` (``stage armature``): segments on the surface, joints over the take."""
    from pipeline.report.figures import armature_figure

    r = d / "rig"
    if not ((r / "rig.json").is_file() and (r / "segments.npy").is_file()):
        return None
    try:
        from pipeline.meshio import load_mesh

        doc = _load_json(r / "rig.json")
        labels = np.load(r / "segments.npy")
        ref = doc["reference_frame"]
        v, f = load_mesh(r / "posed" / f"{int(ref):06d}.ply", largest=False)
        names = [j["name"] for j in doc["joints"]]
        idx = {n: i for i, n in enumerate(names)}
        parents = np.array([idx[j["parent"]] if j["parent"] is not None else -1 for j in doc["joints"]])
        P = np.array([[fr["joints"][n] if fr["joints"][n] is not None else [np.nan] * 3 for n in names]
                      for fr in doc["frames"]], dtype=float)
        # the parts' source: the motion segmentation, or the limbs (stage armature --parts limbs)
        segment = "limb segment" if doc.get("segmentation", {}).get("source") == "limbs" else "motion segment"
        fig = armature_figure(v, f, labels, P, parents, [j["kind"] for j in doc["joints"]],
                         frame_indices=[fr["index"] for fr in doc["frames"]], fps=float(doc["fps"]),
                         max_frames=max_frames, segment=segment)
    except (OSError, KeyError, ValueError, TypeError) as exc:
        warnings.append(f"rig/ could not be shown: {exc}")
        return None
    err = doc.get("fit", {}).get("mean_vertex_error")
    note = (f"Mean vertex error of the fitted model {err:.3g} {doc.get('units', '')}." if err is not None else "")
    return {"id": "rig", "title": f"Armature: {segment}s and joints", "note": note, "parts": f"{segment}s",
            "figure": figure_html(fig, div_id="rig-view")}


def _quality_section(report, warnings: list[str]) -> dict | None:
    per_frame = report.get("per_frame") if isinstance(report, dict) else None
    if not per_frame:
        return None
    from pipeline.report.figures import _quality_rows

    fig = mesh_quality_figure(per_frame)
    rows = _quality_rows(per_frame)
    cols = ["index", "status"] + [c for c in ("vertices", "faces", "watertight", "bodies", "genus", "area",
                                               "volume", "seconds") if any(c in r for r in rows)]
    not_tight = sum(1 for r in rows if r.get("watertight") is False)
    if not_tight:
        warnings.append(f"{not_tight} surface(s) are not watertight")
    return {"id": "quality", "title": "Surface quality per frame", "figure": figure_html(fig, div_id="mesh-quality"),
            "columns": cols, "rows": [[r.get(c) for c in cols] for r in rows]}


#: Worst (camera, frame set) pairs of the silhouette consistency shown as images.
_WORST_SHOWN = 4


def _worst_pairs(iou: list, cameras: list, n: int) -> list[tuple[str, int, float]]:
    """The ``n`` lowest IoUs as (camera, frame set, IoU), at most one per camera first."""
    cells = sorted((v, c, k) for c, row in enumerate(iou) for k, v in enumerate(row) if v is not None)
    picked, cams = [], set()
    for v, c, k in cells:  # the worst frame of each camera, worst cameras first
        if c not in cams:
            picked.append((cameras[c], k, v))
            cams.add(c)
    return picked[:n]


def _reprojection_sheet(d: Path, take, calibration, pairs: list) -> np.ndarray | None:
    """Rows of (mask, projected surface, overlay) for the given (camera, frame set, IoU)."""
    from pipeline.consistency import mesh_silhouette
    from pipeline.gltf_export import find_frame_mesh
    from pipeline.meshio import load_mesh
    from stage.store import TakeReader

    images, labels = [], []
    with TakeReader(take) as reader:
        for cam, k, v in pairs:
            row = reader.set_rows(k).get(cam, -1)
            path = find_frame_mesh(d, k)
            if row < 0 or path is None or cam not in calibration.names or cam not in reader.masks_present():
                continue
            mask = reader.mask(cam, row)
            mv, mf = load_mesh(path, largest=False)
            proj = mesh_silhouette(mv, mf, calibration[cam])
            overlay = np.zeros(mask.shape + (3,), np.uint8)
            overlay[mask & proj] = (255, 255, 255)
            overlay[mask & ~proj] = (60, 60, 255)  # BGR: red, the mask alone
            overlay[proj & ~mask] = (255, 160, 40)  # blue, the surface alone
            images += [mask, proj, overlay]
            labels += [f"{cam} #{k} mask", "projected surface", f"IoU {v:.2f}"]
    if not images:
        return None
    return contact_sheet(images, columns=3, labels=labels, thumb_width=240)


def _consistency_section(d: Path, take, calibration, warnings: list[str]) -> dict | None:
    """``consistency.json``: IoU per camera over the take, medians, the worst frames as images."""
    if not (d / "consistency.json").is_file():
        return None
    doc = _load_json(d / "consistency.json")
    try:
        cameras, iou, median = list(doc["cameras"]), doc["iou"], doc["median"]
        fig = consistency_figure(iou, cameras, threshold=doc.get("threshold"))
    except (KeyError, TypeError, ValueError) as exc:
        warnings.append(f"consistency.json could not be shown: {exc}")
        return None
    rows = [[c, median.get(c), "below" if c in (doc.get("low") or []) else ""] for c in cameras]
    sheet_uri = None
    pairs = _worst_pairs(iou, cameras, _WORST_SHOWN)
    if take is not None and calibration is not None and pairs:
        try:
            sheet = _reprojection_sheet(d, take, calibration, pairs)
        except (OSError, ValueError, KeyError) as exc:
            warnings.append(f"the worst frames' reprojections could not be drawn: {exc}")
            sheet = None
        sheet_uri = png_data_uri(sheet) if sheet is not None else None
    return {"id": "consistency", "title": "Silhouette consistency", "figure": figure_html(fig, div_id="consistency"),
            "rows": rows, "threshold": doc.get("threshold"), "worst_uri": sheet_uri,
            "worst": [f"{c} #{k}" for c, k, _ in pairs]}


def _cameras_section(calibration, spine, warnings: list[str]) -> dict:
    pts = None
    if spine is not None:
        pts = np.concatenate([a.reshape(-1, 3) for a in spine.axes.values()])
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if not len(pts):
            pts = None
    fig = frusta_figure(calibration, points=pts[:: max(1, len(pts) // 3000)] if pts is not None else None)
    cov = camera_coverage(calibration, pts) if pts is not None else None
    extra_keys = sorted({k for c in calibration.cameras for k, v in _scalars(c.meta).items()
                         if isinstance(v, (int, float)) and not isinstance(v, bool)})[:6]
    header = ["camera", "size", "fx", "fy", "cx", "cy", "|dist|"] + extra_keys + (["sees subject"] if cov is not None else [])
    rows = []
    for c in calibration.cameras:
        cm = _scalars(c.meta)
        row = [c.name, f"{c.size[0]}x{c.size[1]}", c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2],
               float(np.linalg.norm(c.dist))]
        row += [cm.get(k) for k in extra_keys]
        if cov is not None:
            row.append(f"{cov['per_camera'][c.name]:.0%}")
        rows.append(row)
    coverage = None
    if cov is not None:
        coverage = {"seen_by_2": cov["seen_by_2"], "median_views": int(np.median(cov["views"]))}
        if cov["seen_by_2"] < 0.95:
            warnings.append(f"only {cov['seen_by_2']:.0%} of the spine points are seen by >= 2 cameras")
    meta_rows = [[k, v] for k, v in _scalars(calibration.meta).items() if not k.startswith("board.")][:20]
    return {"id": "cameras", "title": "Cameras and calibration", "figure": figure_html(fig, div_id="frusta"),
            "header": header, "rows": rows, "coverage": coverage, "meta_rows": meta_rows}


def _sheets_section(sheets: dict) -> dict:
    return {"id": "sheets", "title": "Contact sheets", "sets": sheets["sets"], "cameras": sheets["cameras"],
            "frames_uri": jpeg_data_uri(sheets["frames"]),
            "masks_uri": png_data_uri(sheets["masks"]) if sheets["masks"] is not None else None}

def write_report(results_dir, *, take=None, out=None, **kwargs) -> Path:
    """Write :func:`render_report` to ``out`` (default ``results_dir/report.html``); returns the path."""
    page = render_report(results_dir, take=take, **kwargs)
    target = Path(out) if out is not None else Path(results_dir) / "report.html"
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_suffix(target.suffix + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(target)
    return target
