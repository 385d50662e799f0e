"""Result files of a job (``DATA/jobs/<job>/``): listing and safe lookup, PLY -> GLB conversion.

What :func:`pipeline.process.process_take` writes: ``spine.json``, ``report.json``,
``meshes/frame_NNNNNN.ply``; the ``track`` step ``tracked/NNNNNN.ply``, ``tracked/track.json`` (what the tracking
did: its options, reference frame, the armature round kept), ``tracked/labels.npy`` (a tracking with the
template's labels) and ``tracked/rig_segments.npy`` (the segments of the limbs armature its kept armature round
tracked with); the ``rig`` step
``rig/rig.json``, ``rig/rig.glb``, ``rig/rig.bvh``, ``rig/segments.npy`` and ``rig/posed/NNNNNN.ply``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from api.errors import NotFoundError, UnavailableError
from api.paths import JOB_ID, check_id, confined, confined_entries, inside

__all__ = ["RESULT_STEPS", "listing", "result_file", "mesh", "spine_glb", "rig_glb", "ply_to_glb", "frame_file",
           "rig_file", "tracked_file"]

_MESH = re.compile(r"^(?:frame_)?([0-9]{1,6})\.(ply|glb)$")
_FRAME = re.compile(r"^([0-9]{6})\.ply$")  # tracked/ and rig/posed/: exactly six digits
#: the files of ``rig/`` served as they are, and their media types
RIG_FILES = {"rig.json": "application/json", "rig.glb": "model/gltf-binary", "rig.bvh": "text/plain",
             "segments.npy": "application/octet-stream"}
#: the files of ``tracked/`` beside its frames, served as they are, and their media types
TRACKED_FILES = {"track.json": "application/json", "labels.npy": "application/octet-stream",
                 "rig_segments.npy": "application/octet-stream"}
#: why a file of :data:`TRACKED_FILES` is absent when the tracking ran
_NO_TRACKED_FILE = {"labels.npy": "the tracking used no labels",
                    "rig_segments.npy": "the tracking kept no armature round with the limbs' parts"}
#: folders of per-frame meshes in the template's vertex order
FRAME_FOLDERS = {"tracked": ("tracked",), "posed": ("rig", "posed")}
#: the steps whose results are in a job's folder, in the pipeline's order (``key`` writes the take's masks, beside
#: the take): ``surface`` ``meshes/``, ``spine`` ``spine.json``, ``track`` ``tracked/``, ``rig`` ``rig/``
RESULT_STEPS = ("surface", "spine", "track", "rig")


def _job_dir(jobs_dir: Path, job_id: str) -> Path:
    check_id(job_id, pattern=JOB_ID, name="job id")
    return inside(jobs_dir, job_id)


def listing(jobs_dir: Path, job_id: str) -> dict[str, Any]:
    """What a job's folder holds now.

    Parameters
    ----------
    jobs_dir : Path
        The folder of the jobs' folders.
    job_id : str
        The job (a 32-hex id).

    Returns
    -------
    dict
        ``files`` (the named files written, e.g. ``spine.json``, ``rig/rig.glb``), ``links`` (a URL for each of
        them, and for ``spine.glb`` and ``spine_rig.glb`` once ``spine.json`` is written), ``meshes``, ``tracked``,
        ``posed`` (frame indices of ``meshes/``, ``tracked/``, ``rig/posed/``, with ``mesh_url`` and, when there are
        any, ``tracked_url``, ``posed_url``: ``{index:06d}`` marks the frame), ``rig`` (the summary of
        ``rig/rig.json``, once written) and ``written_by``: the steps of :data:`RESULT_STEPS` whose files are there,
        in the pipeline's order. Nothing that is not there is linked.

    Raises
    ------
    ValueError
        When ``job_id`` is not a job id.
    """
    d = _job_dir(jobs_dir, job_id)
    files = [n for n in ("spine.json", "report.json") if (d / n).is_file() and confined(d / n, d)]
    meshes = []
    for p in confined_entries(d / "meshes", "frame_*.ply", root=d):
        m = _MESH.match(p.name)
        if m:
            meshes.append(int(m.group(1)))
    links = {n: f"/jobs/{job_id}/results/{n}" for n in files}
    if "spine.json" in files:
        links["spine.glb"] = f"/jobs/{job_id}/results/spine.glb"
        links["spine_rig.glb"] = f"/jobs/{job_id}/results/spine_rig.glb"
    out = {"files": files, "meshes": meshes, "mesh_url": f"/jobs/{job_id}/results/meshes/frame_{{index:06d}}.ply",
           "links": links}
    for key, parts in FRAME_FOLDERS.items():
        idx = [int(m.group(1)) for p in confined_entries(d.joinpath(*parts), "*.ply", root=d) if (m := _FRAME.match(p.name))]
        out[key] = idx
        if idx:
            out[f"{key}_url"] = f"/jobs/{job_id}/results/{'/'.join(parts)}/{{index:06d}}.ply"
    tracked = [f"tracked/{n}" for n in TRACKED_FILES if (d / "tracked" / n).is_file() and confined(d / "tracked" / n, d)]
    rig = [f"rig/{n}" for n in RIG_FILES if (d / "rig" / n).is_file() and confined(d / "rig" / n, d)]
    out["files"] = files + tracked + rig
    links.update({n: f"/jobs/{job_id}/results/{n}" for n in tracked + rig})
    wrote = {"surface": bool(meshes), "spine": "spine.json" in files, "track": bool(out["tracked"] or tracked),
             "rig": bool(out["posed"] or rig)}
    out["written_by"] = [step for step in RESULT_STEPS if wrote[step]]
    if "rig/rig.json" in rig:
        from pipeline.armature_files import armature_summary

        out["rig"] = armature_summary(d / "rig" / "rig.json")
    return out


def frame_file(jobs_dir: Path, job_id: str, folder: str, name: str) -> Path:
    """A per-frame mesh of ``tracked/`` or ``rig/posed/`` (``folder``: ``tracked`` or ``posed``), ``NNNNNN.ply``.

    Raises
    ------
    NotFoundError
        When the frame has no such mesh (yet).
    """
    if folder not in FRAME_FOLDERS:
        raise ValueError(f"folder must be one of {', '.join(FRAME_FOLDERS)}, got {folder!r}")
    if _FRAME.match(name) is None:
        raise ValueError(f"mesh name {name!r} must look like 000003.ply")
    p = inside(_job_dir(jobs_dir, job_id), *FRAME_FOLDERS[folder], name)
    if not p.is_file():
        raise NotFoundError(f"no {'/'.join(FRAME_FOLDERS[folder])}/{name} (yet)")
    return p


def rig_file(jobs_dir: Path, job_id: str, name: str) -> tuple[Path, str]:
    """``rig/<name>`` of a job (``rig.json``, ``rig.glb``, ``rig.bvh``, ``segments.npy``) and its media type."""
    if name not in RIG_FILES:
        raise ValueError(f"unknown rig file {name!r} (one of {', '.join(RIG_FILES)})")
    p = inside(_job_dir(jobs_dir, job_id), "rig", name)
    if not p.is_file():
        raise NotFoundError(f"rig/{name} is not available (yet): the job's steps did not include the rig, or it has not run")
    return p, RIG_FILES[name]


def tracked_file(jobs_dir: Path, job_id: str, name: str) -> tuple[Path, str]:
    """``tracked/<name>`` of a job (``track.json``, ``labels.npy``, ``rig_segments.npy``) and its media type.

    Raises
    ------
    NotFoundError
        When the job has no such file (yet): no ``track`` step, a tracking without the template's labels, or
        without an armature round with the limbs' parts.
    """
    if name not in TRACKED_FILES:
        raise ValueError(f"unknown tracking file {name!r} (one of {', '.join(TRACKED_FILES)})")
    p = inside(_job_dir(jobs_dir, job_id), "tracked", name)
    if not p.is_file():
        why = _NO_TRACKED_FILE.get(name, "the job's steps did not include the track step")
        raise NotFoundError(f"tracked/{name} is not available (yet): {why}, or it has not run")
    return p, TRACKED_FILES[name]


def result_file(jobs_dir: Path, job_id: str, name: str) -> Path | None:
    """Path of ``spine.json`` / ``report.json`` when it exists."""
    if name not in ("spine.json", "report.json"):
        raise ValueError(f"unknown result {name!r}")
    p = inside(_job_dir(jobs_dir, job_id), name)
    return p if p.is_file() else None


def ply_to_glb(path: Path) -> bytes:
    """A PLY mesh as binary glTF."""
    import trimesh

    mesh = trimesh.load(path, file_type="ply", force="mesh", process=False)
    return trimesh.Scene(mesh).export(file_type="glb")


def mesh(jobs_dir: Path, job_id: str, name: str) -> tuple[Path | bytes, str]:
    """The mesh of one frame: ``(path, media type)`` for PLY, ``(bytes, media type)`` for GLB.

    Raises
    ------
    NotFoundError
        When the frame has no mesh (yet).
    """
    m = _MESH.match(name)
    if m is None:
        raise ValueError(f"mesh name {name!r} must look like frame_000003.ply or 3.glb")
    index, ext = int(m.group(1)), m.group(2)
    p = inside(_job_dir(jobs_dir, job_id), "meshes", f"frame_{index:06d}.ply")
    if not p.is_file():
        raise NotFoundError(f"no mesh for frame {index} (yet)")
    if ext == "ply":
        return p, "application/octet-stream"
    return ply_to_glb(p), "model/gltf-binary"


def spine_glb(jobs_dir: Path, job_id: str) -> bytes:
    """The spines of all frames as binary glTF (one tube mesh per frame's spine, as a scene node)."""
    import json

    p = inside(_job_dir(jobs_dir, job_id), "spine.json")
    if not p.is_file():
        raise NotFoundError("spine.json is not available (yet)")
    data = json.loads(p.read_text(encoding="utf-8"))
    if isinstance(data, dict) and str(data.get("format", "")).startswith("capture-stage/spine"):
        from pipeline.gltf_export import spine_to_glb  # the animated spine (tubes along the bones)

        return spine_to_glb(data)
    return _generic_spine_glb(data)


def rig_glb(jobs_dir: Path, job_id: str) -> Path:
    """``spine_rig.glb``: the reference frame's mesh rigged to the spine (made on first request)."""
    d = _job_dir(jobs_dir, job_id)
    out = inside(d, "spine_rig.glb")
    if out.is_file():
        return out
    if not inside(d, "spine.json").is_file():
        raise NotFoundError("spine.json is not available (yet)")
    mdir = d / "meshes"
    if mdir.exists() and (not confined(mdir, d) or len(confined_entries(mdir, "*", root=d)) != len(list(mdir.iterdir()))):
        raise NotFoundError("the meshes of this job are not available (a mesh file points outside the data root)")
    from pipeline.gltf_export import export_rig

    export_rig(d, out=out)
    return out


def _polylines(data: Any) -> list[tuple[int, list]]:
    """(frame, polyline) pairs from a spine.json: frames[*].limbs[*].points or frames[*].edges/nodes."""
    out: list[tuple[int, list]] = []
    frames = data.get("frames", []) if isinstance(data, dict) else []
    for fi, fr in enumerate(frames):
        if not isinstance(fr, dict):
            continue
        idx = int(fr.get("index", fi))
        for key in ("limbs", "branches", "paths"):
            for limb in fr.get(key, []) or []:
                pts = limb.get("points") if isinstance(limb, dict) else limb
                if isinstance(pts, list) and len(pts) >= 2:
                    out.append((idx, pts))
        nodes, edges = fr.get("nodes"), fr.get("edges")
        if isinstance(nodes, list) and isinstance(edges, list):
            for e in edges:
                try:
                    out.append((idx, [nodes[int(e[0])], nodes[int(e[1])]]))
                except (IndexError, TypeError, ValueError, KeyError):
                    continue
    return out


def _generic_spine_glb(data: Any) -> bytes:
    import numpy as np
    import trimesh

    lines = _polylines(data)
    if not lines:
        raise UnavailableError("spine.json has no polylines this server knows how to export as GLB")
    scene = trimesh.Scene()
    by_frame: dict[int, list] = {}
    for idx, pts in lines:
        by_frame.setdefault(idx, []).append(np.asarray(pts, dtype=float)[:, :3])
    for idx, polys in sorted(by_frame.items()):
        segs = np.concatenate([np.stack([p[:-1], p[1:]], axis=1) for p in polys])
        scale = float(np.ptp(np.concatenate(polys), axis=0).max() or 1.0)
        tubes = []
        for a, b in segs:
            if np.linalg.norm(b - a) <= 0:
                continue
            tubes.append(trimesh.creation.cylinder(radius=scale * 0.01, segment=np.stack([a, b]), sections=8))
        if tubes:
            scene.add_geometry(trimesh.util.concatenate(tubes), node_name=f"frame_{idx:06d}")
    return scene.export(file_type="glb")
