"""Plotly figures and images of a processed take (reusable by the report and the API pages).

Every function takes plain data (a :class:`~calib.calibration.Calibration`, a
:class:`~pipeline.spine_format.Spine`, arrays, the ``report.json`` dict) and returns
a ``plotly.graph_objects.Figure`` or an image; nothing here reads files.
Embed a figure offline with :func:`figure_html` and :func:`plotly_js`.
"""

from __future__ import annotations

import base64
import logging
import math

import numpy as np

__all__ = [
    "consistency_figure",
    "plotly_js",
    "figure_html",
    "tip_count_figure",
    "mesh_quality_figure",
    "frusta_figure",
    "camera_coverage",
    "spine_figure",
    "armature_figure",
    "decimate_mesh",
    "contact_sheet",
    "png_data_uri",
    "jpeg_data_uri",
]

log = logging.getLogger(__name__)

_PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
            "#17becf"]


def _go():
    try:
        import plotly.graph_objects as go
    except ImportError as exc:  # pragma: no cover - plotly is a dependency
        raise ImportError("the HTML report needs plotly (pip install plotly)") from exc
    return go


def plotly_js() -> str:
    """The full plotly.js bundle shipped inside the plotly package (for an offline page)."""
    from plotly.offline import get_plotlyjs

    return get_plotlyjs()


def figure_html(fig, *, div_id: str | None = None, height: int | None = None) -> str:
    """A figure as an HTML ``<div>`` + script, *without* plotly.js (embed :func:`plotly_js` once per page)."""
    if height is not None:
        fig.update_layout(height=int(height))
    return fig.to_html(
        full_html=False,
        include_plotlyjs=False,
        div_id=div_id,
        config={"displaylogo": False, "responsive": True},
        auto_play=False,
    )


# --------------------------------------------------------------------------- 2-D plots


def tip_count_figure(tip_counts, *, K: int | None = None, frame_indices=None, fps: float | None = None):
    """Number of tips found per frame, with the take's limb count ``K`` (Brostow et al. 2004, Fig. 7).

    Parameters
    ----------
    tip_counts : (T,) sequence of int or None
        Tips ``|E_t|`` per frame (None: frame not processed / empty).
    K : int, optional
        The mode of the tip counts used for the spine (a horizontal line).
    frame_indices : (T,) int sequence, optional
    fps : float, optional
        Adds the time in seconds to the hover text.
    """
    go = _go()
    counts = [None if c is None else int(c) for c in tip_counts]
    x = list(range(len(counts))) if frame_indices is None else [int(i) for i in frame_indices]
    if len(x) != len(counts):
        raise ValueError("frame_indices must have one entry per tip count")
    fig = go.Figure()
    hover = None
    if fps:
        hover = [f"frame {i}<br>{i / fps:.2f} s<br>{c} tips" for i, c in zip(x, counts)]
    fig.add_trace(
        go.Scatter(x=x, y=counts, mode="lines+markers", line_shape="hv", name="tips found",
                   text=hover, hoverinfo="text" if hover else None, marker=dict(size=5))
    )
    if K is not None:
        fig.add_hline(y=int(K), line_dash="dash", line_color="#d62728", annotation_text=f"K = {int(K)}",
                      annotation_position="top left")
        bad = [(xi, c) for xi, c in zip(x, counts) if c is not None and c != K]
        if bad:
            fig.add_trace(go.Scatter(x=[b[0] for b in bad], y=[b[1] for b in bad], mode="markers", name="|E_t| != K",
                                     marker=dict(color="#d62728", size=8, symbol="x")))
    fig.update_layout(title="Tips per frame (Brostow et al. 2004, Fig. 7)", xaxis_title="frame",
                      yaxis_title="number of tips", yaxis=dict(dtick=1, rangemode="tozero"), height=320,
                      margin=dict(l=50, r=20, t=50, b=40))
    return fig


def consistency_figure(iou, cameras, *, threshold: float | None = None):
    """Silhouette consistency per camera over the take (``consistency.json``).

    Parameters
    ----------
    iou : (C, S) sequence of float or None
        Per camera and frame set, the IoU of its mask and the projected surface (None: none).
    cameras : (C,) sequence of str
    threshold : float, optional
        The level below which a camera's median is warned about (a dashed line).
    """
    go = _go()
    rows = [[None if v is None else float(v) for v in r] for r in iou]
    if len(rows) != len(cameras):
        raise ValueError("iou must have one row per camera")
    fig = go.Figure()
    for cam, r in zip(cameras, rows):
        fig.add_trace(go.Scatter(x=list(range(len(r))), y=r, mode="lines+markers", name=str(cam), marker=dict(size=4)))
    if threshold is not None:
        fig.add_hline(y=float(threshold), line_dash="dash", line_color="#d62728",
                      annotation_text=f"{float(threshold):g}", annotation_position="bottom left")
    fig.update_layout(title="Silhouette consistency: IoU of each camera's mask and the projected surface",
                      xaxis_title="frame set", yaxis_title="IoU", yaxis=dict(range=[0, 1.02]), height=340,
                      margin=dict(l=50, r=20, t=50, b=40))
    return fig


def _quality_rows(per_frame) -> list[dict]:
    rows = []
    for i, rec in enumerate(per_frame or []):
        if not isinstance(rec, dict):
            rows.append({"index": i, "status": "missing"})
            continue
        row = {"index": rec.get("index", i), "status": rec.get("status", "ok")}
        q = rec.get("quality")
        if isinstance(q, dict):
            row.update(q)
        for k, v in rec.items():
            if k not in ("quality", "index", "status") and isinstance(v, (int, float)) and not isinstance(v, bool):
                row[k] = v
        rows.append(row)
    return rows


def mesh_quality_figure(per_frame):
    """Per-frame surface quality from ``report.json["per_frame"]``: faces, area, volume, watertight, bodies.

    Parameters
    ----------
    per_frame : sequence of dict or None
        ``{"index", "status", "quality": {"vertices", "faces", "watertight", "bodies", "area", "volume", ...}}``
        (``pipeline.process``); unknown numeric fields are plotted too.
    """
    go = _go()
    from plotly.subplots import make_subplots

    rows = _quality_rows(per_frame)
    if not rows:
        raise ValueError("per_frame holds no frames")
    x = [r["index"] for r in rows]
    fig = make_subplots(rows=3, cols=1, shared_xaxes=True, vertical_spacing=0.06,
                        subplot_titles=("faces", "area / volume (relative to median)", "watertight / bodies"))

    def col(name):
        return [r.get(name) if isinstance(r.get(name), (int, float)) else None for r in rows]

    fig.add_trace(go.Scatter(x=x, y=col("faces"), name="faces", mode="lines+markers", marker=dict(size=4)), 1, 1)
    for name in ("area", "volume"):
        v = col(name)
        good = [a for a in v if a is not None and a > 0]
        med = float(np.median(good)) if good else 1.0
        fig.add_trace(go.Scatter(x=x, y=[None if a is None else a / med for a in v], name=name,
                                 mode="lines+markers", marker=dict(size=4)), 2, 1)
    wt = [None if not isinstance(r.get("watertight"), bool) else int(r["watertight"]) for r in rows]
    fig.add_trace(go.Scatter(x=x, y=wt, name="watertight", mode="markers", marker=dict(size=6)), 3, 1)
    fig.add_trace(go.Scatter(x=x, y=col("bodies"), name="bodies", mode="lines", line_shape="hv"), 3, 1)
    empty = [r["index"] for r in rows if r.get("status") not in ("ok", None)]
    for e in empty:
        fig.add_vline(x=e, line_color="#d62728", opacity=0.4)
    fig.update_layout(height=520, margin=dict(l=50, r=20, t=40, b=40), title=None)
    fig.update_xaxes(title_text="frame", row=3, col=1)
    return fig


# --------------------------------------------------------------------------- cameras


def _frustum(cam, depth: float) -> np.ndarray:
    """(5, 3) camera centre and the 4 image corners at camera depth ``depth``."""
    w, h = cam.size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]], dtype=np.float64)
    pts = cam.unproject(corners, np.full(4, depth))
    return np.vstack([cam.center[None], pts])


def frusta_figure(calibration, *, depth: float | None = None, points=None, volume=None):
    """Camera frusta in 3-D (named), optionally with subject points and a capture volume box.

    Parameters
    ----------
    calibration : calib.calibration.Calibration
    depth : float, optional
        Frustum length (default: 40 % of the mean camera distance to the cameras' centroid... or to ``points``).
    points : (N, 3) float ndarray, optional
        E.g. the spine's joints; drawn as markers.
    volume : (center (3,), size (3,)), optional
        An axis-aligned box.
    """
    go = _go()
    cams = list(calibration.cameras)
    if not cams:
        raise ValueError("calibration has no cameras")
    centres = np.array([c.center for c in cams])
    target = np.asarray(points, float).reshape(-1, 3).mean(0) if points is not None and len(points) else centres.mean(0)
    if depth is None:
        depth = 0.25 * float(np.mean(np.linalg.norm(centres - target, axis=1))) or 1.0
    fig = go.Figure()
    xs, ys, zs = [], [], []
    for c in cams:
        F = _frustum(c, depth)
        for a, b in ((0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)):
            xs += [F[a, 0], F[b, 0], None]
            ys += [F[a, 1], F[b, 1], None]
            zs += [F[a, 2], F[b, 2], None]
    fig.add_trace(go.Scatter3d(x=xs, y=ys, z=zs, mode="lines", line=dict(color="#1f77b4", width=3), name="frusta",
                               hoverinfo="skip"))
    fig.add_trace(go.Scatter3d(x=centres[:, 0], y=centres[:, 1], z=centres[:, 2], mode="markers+text",
                               text=[c.name for c in cams], textposition="top center",
                               marker=dict(size=4, color="#1f77b4"), name="cameras"))
    if points is not None and len(points):
        P = np.asarray(points, float).reshape(-1, 3)
        fig.add_trace(go.Scatter3d(x=P[:, 0], y=P[:, 1], z=P[:, 2], mode="markers",
                                   marker=dict(size=2, color="#d62728"), name="subject"))
    if volume is not None:
        c, s = (np.asarray(a, float) for a in volume)
        lo, hi = c - s / 2, c + s / 2
        bx, by, bz = [], [], []
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        for i in range(8):
            for j in range(i + 1, 8):
                if np.sum(corners[i] != corners[j]) == 1:
                    bx += [corners[i, 0], corners[j, 0], None]
                    by += [corners[i, 1], corners[j, 1], None]
                    bz += [corners[i, 2], corners[j, 2], None]
        fig.add_trace(go.Scatter3d(x=bx, y=by, z=bz, mode="lines", line=dict(color="#7f7f7f", width=2),
                                   name="volume", hoverinfo="skip"))
    fig.update_layout(scene=dict(aspectmode="data"), height=520, margin=dict(l=0, r=0, t=30, b=0),
                      title="Cameras")
    return fig


def camera_coverage(calibration, points) -> dict:
    """How well the cameras see some subject points (e.g. every spine joint of every frame).

    Parameters
    ----------
    calibration : calib.calibration.Calibration
    points : (N, 3) float ndarray
        Finite world points.

    Returns
    -------
    dict
        ``per_camera``: camera -> fraction of the points in its image (in front of it);
        ``views``: (N,) int number of cameras seeing each point;
        ``seen_by_2``: fraction of the points seen by at least 2 cameras.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) == 0:
        raise ValueError("points must hold at least one finite point")
    views = np.zeros(len(P), dtype=np.int64)
    per = {}
    for c in calibration.cameras:
        pix, z = c.project(P, return_depth=True)
        ok = (np.asarray(z) > 0) & c.in_image(pix)
        per[c.name] = float(ok.mean())
        views += ok
    return {"per_camera": per, "views": views, "seen_by_2": float((views >= 2).mean())}


# --------------------------------------------------------------------------- 3-D spine view


def decimate_mesh(vertices, faces, *, max_faces: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Vertex-clustering decimation (for display): at most ``max_faces`` faces.

    Vertices are merged per grid cell *and* per normal direction (6 buckets),
    so the two sides of a part thinner than a cell (a horse's leg) stay apart.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    max_faces : int

    Returns
    -------
    vertices : (V', 3) float ndarray
    faces : (F', 3) int ndarray
        Degenerate and duplicate faces removed; unused vertices dropped.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError("vertices must be (V, 3) and faces (F, 3)")
    if int(max_faces) < 4:
        raise ValueError(f"max_faces must be >= 4, got {max_faces}")
    if len(f) <= max_faces:
        return v, f
    lo = v.min(0)
    ext = float(np.linalg.norm(v.max(0) - lo))
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    cell = math.sqrt(2.0 * area / max_faces)  # about one face pair per cell face
    # vertex normals, bucketed by their dominant signed axis: the two sides of a thin part never merge
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    ax = np.abs(vn).argmax(1)
    bucket = 2 * ax + (vn[np.arange(len(v)), ax] < 0)
    for _ in range(30):
        key = np.c_[np.floor((v - lo) / cell).astype(np.int64), bucket]
        _, inv = np.unique(key, axis=0, return_inverse=True)
        inv = inv.ravel()
        nf = inv[f]
        keep = (nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 0] != nf[:, 2])
        nf = nf[keep]
        nf = nf[np.unique(np.sort(nf, axis=1), axis=0, return_index=True)[1]]
        if len(nf) <= max_faces or cell > ext:
            break
        cell *= 1.25
    nv = np.zeros((inv.max() + 1, 3))
    cnt = np.bincount(inv)
    np.add.at(nv, inv, v)
    nv /= np.maximum(cnt, 1)[:, None]
    used = np.unique(nf)
    remap = -np.ones(len(nv), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return nv[used], remap[nf]


def _bone_lines(positions: np.ndarray, parents: np.ndarray) -> tuple[list, list, list]:
    xs, ys, zs = [], [], []
    for j, p in enumerate(parents):
        if p < 0:
            continue
        a, b = positions[p], positions[j]
        xs += [a[0], b[0], None]
        ys += [a[1], b[1], None]
        zs += [a[2], b[2], None]
    return xs, ys, zs


def _spine_lines(spine, t: int) -> tuple[list, list, list]:
    xs, ys, zs = [], [], []
    for a in spine.axes.values():
        p = a[t]
        if not np.all(np.isfinite(p)):
            continue
        xs += list(p[:, 0]) + [None]
        ys += list(p[:, 1]) + [None]
        zs += list(p[:, 2]) + [None]
    return xs, ys, zs


def _fixed_scene(spine, keys, surf_v, model) -> dict:
    """Fixed axes over the whole take (the view does not jump between frames), equal scale."""
    pts = [a[keys].reshape(-1, 3) for a in spine.axes.values()] + [spine.tips[keys].reshape(-1, 3)]
    if surf_v is not None:
        pts.append(surf_v)
    P = np.concatenate(pts)
    P = P[np.all(np.isfinite(P), axis=1)]
    if model is not None:
        P = np.concatenate([P, model.deform(int(keys[0])), model.deform(int(keys[-1]))])
    lo, hi = (P.min(0), P.max(0)) if len(P) else (np.zeros(3), np.ones(3))
    pad = 0.08 * float(np.max(hi - lo) or 1.0)
    lo, hi = lo - pad, hi + pad
    span = hi - lo
    return dict(
        xaxis=dict(range=[lo[0], hi[0]], title="x"),
        yaxis=dict(range=[lo[1], hi[1]], title="y"),
        zaxis=dict(range=[lo[2], hi[2]], title="z"),
        aspectmode="manual",
        aspectratio=dict(x=span[0] / span.max(), y=span[1] / span.max(), z=span[2] / span.max()),
    )


def _animation_controls(frame_indices, keys, step_ms: int) -> dict:
    """A play/pause button and a frame slider over the animation keys (plotly layout entries)."""
    fi = frame_indices
    return dict(
        updatemenus=[dict(
            type="buttons", showactive=False, x=0.02, y=0.02, xanchor="left", yanchor="bottom",
            buttons=[
                dict(label="Play", method="animate",
                     args=[None, dict(frame=dict(duration=step_ms, redraw=True), fromcurrent=True,
                                      transition=dict(duration=0))]),
                dict(label="Pause", method="animate",
                     args=[[None], dict(frame=dict(duration=0, redraw=False), mode="immediate")]),
            ])],
        sliders=[dict(
            active=0, x=0.12, len=0.86, y=0.02, yanchor="bottom", currentvalue=dict(prefix="frame "),
            steps=[dict(method="animate", label=str(int(fi[t])),
                        args=[[str(int(fi[t]))], dict(mode="immediate", frame=dict(duration=0, redraw=True),
                                                      transition=dict(duration=0))]) for t in keys])],
    )


def spine_figure(spine, *, mesh=None, model=None, max_frames: int = 120, title: str | None = None):
    """Interactive 3-D view: the spine animated over the take (slider and play button), with the surface.

    Parameters
    ----------
    spine : pipeline.spine_format.Spine
    mesh : (vertices (V, 3), faces (F, 3)), optional
        A static surface (e.g. the reference frame's mesh), drawn semi-transparent.
    model : pipeline.armature_spine.RiggedModel, optional
        A rigged surface: posed in every frame by linear blend skinning (wins over ``mesh``).
    max_frames : int
        Animation keys (frames are subsampled evenly above this).
    title : str, optional
    """
    go = _go()
    T = spine.frame_count
    if T == 0:
        raise ValueError("spine has no frames")
    if int(max_frames) < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    keys = np.unique(np.linspace(0, T - 1, min(T, int(max_frames))).round().astype(int))
    limb_ids = list(spine.limb_ids)
    colors = [_PALETTE[k % len(_PALETTE)] for k in range(len(limb_ids))]

    surf_v = surf_f = None
    if model is not None:
        surf_v, surf_f = model.vertices, model.faces
    elif mesh is not None:
        surf_v, surf_f = (np.asarray(a) for a in mesh)

    def traces(t: int, first: bool = False) -> list:
        out = []
        if surf_v is not None:
            V = (model.deform(t) if model is not None else surf_v).astype(np.float32)
            if first:
                out.append(go.Mesh3d(x=V[:, 0], y=V[:, 1], z=V[:, 2], i=surf_f[:, 0].astype(np.int32),
                                     j=surf_f[:, 1].astype(np.int32), k=surf_f[:, 2].astype(np.int32),
                                     color="#d9c3a5", opacity=0.55, name="surface", flatshading=False,
                                     lighting=dict(ambient=0.6, diffuse=0.6), hoverinfo="skip", showlegend=True))
            else:  # animation frames update the coordinates only (faces stay those of the first trace)
                out.append(go.Mesh3d(x=V[:, 0], y=V[:, 1], z=V[:, 2]))
        xs, ys, zs = _spine_lines(spine, t)
        out.append(go.Scatter3d(x=xs, y=ys, z=zs, mode="lines", line=dict(color="#222222", width=6), name="spine",
                                hoverinfo="skip"))
        tips = spine.tips[t]
        ok = np.all(np.isfinite(tips), axis=1)
        out.append(go.Scatter3d(
            x=tips[ok, 0], y=tips[ok, 1], z=tips[ok, 2], mode="markers+text",
            text=[lid for lid, o in zip(limb_ids, ok) if o], textposition="top center",
            marker=dict(size=6, color=[c for c, o in zip(colors, ok) if o]), name="tips"))
        J = spine.junctions[t] if spine.junctions.size else np.zeros((0, 3))
        okj = np.all(np.isfinite(J), axis=1) if len(J) else np.zeros(0, bool)
        out.append(go.Scatter3d(x=J[okj, 0], y=J[okj, 1], z=J[okj, 2], mode="markers",
                                marker=dict(size=5, color="#9467bd", symbol="diamond"), name="junctions"))
        return out

    scene = _fixed_scene(spine, keys, surf_v, model)
    fi = spine.frame_indices
    frames = [go.Frame(data=traces(int(t)), name=str(int(fi[t]))) for t in keys]
    fig = go.Figure(data=traces(int(keys[0]), first=True), frames=frames)
    step_ms = max(1, int(round(1000.0 / spine.fps * max(1, (T - 1) / max(1, len(keys) - 1)))))
    fig.update_layout(
        title=title or f"Spine: {len(limb_ids)} limbs, {T} frames",
        scene=scene,
        height=620,
        margin=dict(l=0, r=0, t=40, b=0),
        uirevision="spine",
        **_animation_controls(fi, keys, step_ms),
    )
    return fig


def armature_figure(vertices, faces, labels, joints, parents, kinds, *, frame_indices=None, fps: float = 30.0,
                    max_frames: int = 120, max_faces: int = 20000, segment: str = "motion segment"):
    """The armature: the rest surface coloured by segment, the joints animated over the take.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    labels : (V,) int ndarray
        Motion segment of every vertex.
    joints : (T, J, 3) float ndarray
        Joint positions per frame.
    parents : (J,) int ndarray
    kinds : sequence of str
        ``root``, ``joint`` (articulation) or ``aux`` per joint.
    frame_indices : (T,) int array_like, optional
    fps : float
    max_frames : int
        Animation keys (evenly subsampled above this).
    max_faces : int
        Faces drawn at most (an even subset of them above this).
    segment : str
        What a segment is, in the title: ``"motion segment"`` (the motion segmentation's) or ``"limb segment"``
        (parts from the limbs, rig.json's ``segmentation.source``).
    """
    from pipeline.armature import counted

    go = _go()
    v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces, dtype=np.int64)
    lab = np.asarray(labels, dtype=np.int64)
    P = np.asarray(joints, dtype=np.float64)
    par = np.asarray(parents, dtype=np.int64)
    if P.ndim != 3 or P.shape[2] != 3 or len(P) == 0:
        raise ValueError(f"joints must have shape (T, J, 3) with T > 0, got {P.shape}")
    if lab.shape != (len(v),):
        raise ValueError(f"labels must have shape ({len(v)},), got {lab.shape}")
    T = len(P)
    fi = np.arange(T) if frame_indices is None else np.asarray(frame_indices)
    keys = np.unique(np.linspace(0, T - 1, min(T, int(max_frames))).round().astype(int))
    if len(f) > max_faces:
        f = f[np.linspace(0, len(f) - 1, int(max_faces)).round().astype(int)]
    colors = [_PALETTE[int(k) % len(_PALETTE)] for k in lab]
    art = np.array([k == "joint" for k in kinds])

    def joint_traces(t: int) -> list:
        xs, ys, zs = _bone_lines(P[t], par)
        return [
            go.Scatter3d(x=xs, y=ys, z=zs, mode="lines", line=dict(color="#222222", width=6), name="bones",
                         hoverinfo="skip"),
            go.Scatter3d(x=P[t, art, 0], y=P[t, art, 1], z=P[t, art, 2], mode="markers",
                         marker=dict(size=7, color="#d62728"), name="articulations"),
            go.Scatter3d(x=P[t, ~art, 0], y=P[t, ~art, 1], z=P[t, ~art, 2], mode="markers",
                         marker=dict(size=4, color="#555555"), name="auxiliary joints"),
        ]

    surface = go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2], vertexcolor=colors,
                        opacity=0.5, name=f"{int(lab.max()) + 1} segments", hoverinfo="skip", showlegend=True)
    frames = [go.Frame(data=joint_traces(int(t)), traces=[1, 2, 3], name=str(int(fi[t]))) for t in keys]
    fig = go.Figure(data=[surface] + joint_traces(int(keys[0])), frames=frames)
    step_ms = max(1, int(round(1000.0 / fps * max(1, (T - 1) / max(1, len(keys) - 1)))))
    fig.update_layout(
        title=f"Armature: {counted(int(lab.max()) + 1, segment)}, {counted(int(art.sum()), 'articulation')}, "
              f"{counted(len(par), 'joint')}",
        scene=dict(aspectmode="data"), height=620, margin=dict(l=0, r=0, t=40, b=0), uirevision="rig",
        **_animation_controls(fi, keys, step_ms),
    )
    return fig


# --------------------------------------------------------------------------- images


def contact_sheet(images, *, columns: int, labels=None, thumb_width: int = 160, pad: int = 2) -> np.ndarray:
    """Thumbnails in a grid.

    Parameters
    ----------
    images : sequence of (H, W, 3) uint8 BGR or (H, W) bool/uint8 ndarray or None
        None leaves a grey cell.
    columns : int
    labels : sequence of str, optional
        Drawn in each cell's corner.
    thumb_width : int

    Returns
    -------
    (H', W', 3) uint8 ndarray (BGR)
    """
    import cv2

    imgs = list(images)
    if not imgs:
        raise ValueError("images must hold at least one image")
    if int(columns) < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    if int(thumb_width) < 8:
        raise ValueError(f"thumb_width must be >= 8, got {thumb_width}")
    first = next((i for i in imgs if i is not None), None)
    aspect = first.shape[0] / first.shape[1] if first is not None else 0.75
    tw, th = int(thumb_width), max(1, int(round(thumb_width * aspect)))
    rows = math.ceil(len(imgs) / columns)
    sheet = np.full((rows * (th + pad) + pad, columns * (tw + pad) + pad, 3), 40, np.uint8)
    for n, im in enumerate(imgs):
        r, c = divmod(n, columns)
        y, x = pad + r * (th + pad), pad + c * (tw + pad)
        if im is None:
            cell = np.full((th, tw, 3), 90, np.uint8)
        else:
            a = np.asarray(im)
            if a.dtype == bool:
                a = a.astype(np.uint8) * 255
            if a.ndim == 2:
                a = np.repeat(a[..., None], 3, axis=2)
            cell = cv2.resize(a.astype(np.uint8), (tw, th), interpolation=cv2.INTER_AREA)
        sheet[y : y + th, x : x + tw] = cell
        if labels is not None and n < len(labels) and labels[n]:
            cv2.putText(sheet, str(labels[n]), (x + 3, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 2,
                        cv2.LINE_AA)
            cv2.putText(sheet, str(labels[n]), (x + 3, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1,
                        cv2.LINE_AA)
    return sheet


def png_data_uri(image: np.ndarray) -> str:
    """``data:image/png;base64,...`` of a BGR or grey image."""
    import cv2

    ok, buf = cv2.imencode(".png", np.asarray(image))
    if not ok:
        raise ValueError("cannot encode the image as PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def jpeg_data_uri(image: np.ndarray, *, quality: int = 85) -> str:
    """``data:image/jpeg;base64,...`` of a BGR image."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.asarray(image), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("cannot encode the image as JPEG")
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii")
