"""The per-frame skeleton records of a results directory (``OUT/skeletons/frame_NNNNNN.npz``).

A record holds one frame set's tips and skeletons (Brostow et al. 2004, 4.1) as binary arrays: a
resumed run reads them back instead of computing them again. :data:`SKELETON_FORMAT` numbers the
layout; a record of another format is recomputed (:func:`stale_skeletons`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = ["SKELETON_FORMAT", "frame_name", "frame_said", "load_skeleton", "said_fields", "skeleton_bytes",
           "skeleton_path", "skeleton_record", "skeleton_said", "stale_skeletons"]

log = logging.getLogger("pipeline.process")


def frame_name(k: int) -> str:
    """The stem of frame set ``k``'s files in a results directory (``frame_000012``)."""
    return f"frame_{k:06d}"


def said_fields(said: list[tuple[str, str | None]]) -> dict:
    """What a frame set warned of (:func:`pipeline.run.frame_warnings`) as its record keeps it: ``warnings`` (each
    message once, in the order said) and, for those said in other words in a job, ``job_warnings`` (message ->
    the job's words); ``{}`` when it said nothing. A later run that finds the frame done says them again
    (:func:`frame_said`, :func:`skeleton_said`), as a run that made it would.

    Raises
    ------
    ValueError
        ``said`` is not a list of ``(message, job's words or None)``.
    """
    if not isinstance(said, (list, tuple)) or not all(
            isinstance(x, (list, tuple)) and len(x) == 2 and isinstance(x[0], str) and isinstance(x[1], (str, type(None)))
            for x in said):
        raise ValueError(f"said must be a list of (message, job's words or None), got {said!r}")
    if not said:
        return {}
    out: dict = {"warnings": list(dict.fromkeys(m for m, _ in said))}
    job = {m: j for m, j in said if j is not None and j != m}
    if job:
        out["job_warnings"] = job
    return out


def _said_of(warnings, job_warnings) -> list[tuple[str, str | None]]:
    """The ``(message, job's words or None)`` of a record's :func:`said_fields`."""
    job = job_warnings if isinstance(job_warnings, dict) else {}
    return [(str(m), job.get(str(m))) for m in (warnings or [])]


def _check_frame_set(k) -> None:
    """``ValueError`` naming ``k`` unless it is an integer (a frame set)."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise ValueError(f"k must be an integer (a frame set), got {k!r}")


def frame_said(out: Path, k: int) -> list[tuple[str, str | None]]:
    """What frame set ``k`` warned of when its surface was made, as its record ``OUT/frames/frame_NNNNNN.json`` keeps
    it (:func:`said_fields`); none when it has no record or an unreadable one.

    Raises
    ------
    ValueError
        ``k`` is not an integer.
    """
    _check_frame_set(k)
    import json

    try:
        rec = json.loads((Path(out) / "frames" / f"{frame_name(k)}.json").read_text())
    except (OSError, ValueError):
        return []
    return _said_of(rec.get("warnings"), rec.get("job_warnings")) if isinstance(rec, dict) else []


def skeleton_said(out: Path, k: int) -> list[tuple[str, str | None]]:
    """What frame set ``k`` warned of when the skeleton step made its record (:func:`skeleton_bytes` of a record with
    ``said``); none when it has none (one made by the surface step keeps its warnings in the frame's record).

    Raises
    ------
    ValueError
        ``k`` is not an integer.
    """
    _check_frame_set(k)
    try:
        with np.load(skeleton_path(out, k), allow_pickle=False) as z:
            if "warnings" not in z:
                return []
            job = dict(zip(z["warnings"].tolist(), z["job_warnings"].tolist())) if "job_warnings" in z else {}
            return _said_of(z["warnings"].tolist(), {m: j for m, j in job.items() if j})
    except (OSError, ValueError, KeyError):
        return []


def skeleton_path(out: Path, k: int) -> Path:
    """Where frame set ``k``'s skeleton record goes in the results directory ``out``."""
    return Path(out) / "skeletons" / f"{frame_name(k)}.npz"


def skeleton_record(k: int, mesh, params, *, bodies: int | None = None) -> dict:
    """Per-frame tips and skeletons (Brostow et al. 2004, 4.1) of one frame's surface
    (``None``: an empty frame): ``{"index", "status", "skeleton"}`` (a :class:`FrameSkeleton`,
    ``None`` unless ``ok``) or ``reason``. The mesh is taken as
    :func:`pipeline.meshio.load_mesh` reads it back (its largest connected part); with
    ``bodies == 1`` (the surface's quality counted its pieces) it is that part already."""
    from pipeline.frame_skeleton import frame_skeleton
    from pipeline.geodesic import largest_component

    if mesh is None:
        return {"index": int(k), "status": "empty", "skeleton": None}
    v, f = np.asarray(mesh[0], np.float64), np.asarray(mesh[1], np.int64)
    if bodies != 1:
        v2, f2, _ = largest_component(v, f, warn=False)
        if len(f2) != len(f):
            v, f = v2, f2
    try:
        return {"index": int(k), "status": "ok", "skeleton": frame_skeleton(v, f, params=params)}
    except ValueError as exc:
        log.warning("no skeleton: %s", exc)  # (a per-frame task names the frame set: pipeline.run.frame_warnings)
        return {"index": int(k), "status": "failed", "reason": str(exc), "skeleton": None}


_TIP_FIELDS = ("seed", "nodes", "parent", "cost", "frame", "count", "level", "tip_nodes")
_ALT_FIELDS = ("tip", "point", "vertex", "limb_points", "rings", "alt_rings")  # pipeline.frame_skeleton.Alternate
# format of a ``skeletons/`` record; 2: with the alternates; 3: with the clear tips. A record of another
# format (or none: written before alternates existed, which reads as "no alternates") is recomputed on a resume.
SKELETON_FORMAT = 3


def skeleton_bytes(rec: dict) -> bytes:
    """A ``skeletons/`` record as an uncompressed ``.npz`` (binary arrays: exact, and a
    fraction of the time JSON takes for the ~10^4 floats of a frame's skeletons)."""
    import io

    arrays: dict[str, np.ndarray] = {"format": np.int64(SKELETON_FORMAT), "index": np.int64(rec["index"]),
                                     "status": np.str_(rec["status"]), "reason": np.str_(rec.get("reason", ""))}
    sk = rec.get("skeleton")
    if sk is not None:
        arrays.update(tips=sk.tips, tip_vertices=sk.tip_vertices, size=np.float64(sk.size), n_faces=np.int64(sk.n_faces),
                      limb_points=sk.limb_points, n_skeletons=np.int64(len(sk.skeletons)))
        if sk.clear is not None:
            arrays["clear"] = np.asarray(sk.clear, dtype=bool)
        for i, tip in enumerate(sk.skeletons):
            arrays.update({f"skeleton{i}.{name}": np.asarray(getattr(tip, name)) for name in _TIP_FIELDS})
        arrays["n_alternates"] = np.int64(len(sk.alternates))
        for j, alt in enumerate(sk.alternates):
            arrays.update({f"alternate{j}.{name}": np.asarray(getattr(alt, name)) for name in _ALT_FIELDS})
            arrays.update({f"alternate{j}.skeleton.{name}": np.asarray(getattr(alt.skeleton, name)) for name in _TIP_FIELDS})
    if fields := said_fields(rec.get("said") or []):  # (what the frame warned of, said again by a later run)
        job = fields.get("job_warnings", {})
        arrays.update(warnings=np.array(fields["warnings"], dtype=np.str_),
                      job_warnings=np.array([job.get(m, "") for m in fields["warnings"]], dtype=np.str_))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def load_skeleton(path: Path) -> dict:
    """A record written by :func:`skeleton_bytes`."""
    from pipeline.frame_skeleton import FrameSkeleton

    with np.load(path, allow_pickle=False) as z:
        rec = {"index": int(z["index"]), "status": str(z["status"]), "skeleton": None}
        if str(z["reason"]):
            rec["reason"] = str(z["reason"])
        if "tips" in z:
            d = {name: z[name] for name in ("tips", "tip_vertices", "size", "n_faces", "limb_points")}
            d["skeletons"] = [{name: z[f"skeleton{i}.{name}"] for name in _TIP_FIELDS} for i in range(int(z["n_skeletons"]))]
            n_alt = int(z["n_alternates"]) if "n_alternates" in z else 0  # an older record (see stale_skeletons)
            d["alternates"] = [{**{name: z[f"alternate{j}.{name}"] for name in _ALT_FIELDS},
                                "skeleton": {name: z[f"alternate{j}.skeleton.{name}"] for name in _TIP_FIELDS}}
                               for j in range(n_alt)]
            d["clear"] = z["clear"] if "clear" in z else None  # an older record: not known
            rec["skeleton"] = FrameSkeleton.from_dict(d)
    return rec


def stale_skeletons(out: Path, n: int) -> list[int]:
    """Remove the ``skeletons/`` records of the first ``n`` frame sets written in another format
    than :data:`SKELETON_FORMAT` (or unreadable), so the skeleton step recomputes them; their
    frame indices. Reads only each archive's directory and one scalar."""
    import zipfile

    stale = []
    for k in range(n):
        path = out / "skeletons" / f"{frame_name(k)}.npz"
        if not path.exists():
            continue
        try:
            with np.load(path, allow_pickle=False) as z:
                current = "format" in z and int(z["format"]) == SKELETON_FORMAT
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):  # EOFError: an empty or cut file
            current = False
        if not current:
            path.unlink()
            stale.append(k)
    if stale:
        log.info("%d skeleton records of an older format are recomputed", len(stale))
    return stale

