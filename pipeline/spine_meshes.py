"""The spine of a mesh sequence on disk or in memory (``stage spines``, ``stage process --meshes``).

The per-frame skeletons (:func:`pipeline.frame_skeleton.frame_skeleton`) fan out over an
executor the caller owns (``stage spines --workers`` makes a process pool); the take-level
reduce is :func:`pipeline.spine.build_spine`, arrays in, a spine out.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from concurrent.futures import Executor
from pathlib import Path

from pipeline.frame_skeleton import PARTS_DROPPED, FrameSkeleton, SpineParams, frame_skeleton
from pipeline.run import frame_warnings, frames_said
from pipeline.spine import build_spine
from pipeline.spine_format import Spine

__all__ = ["spine_from_meshes", "frame_task"]

log = logging.getLogger(__name__)


def frame_task(item, params_dict: dict) -> dict:
    """One frame's skeleton, serialised (picklable, for a worker): a mesh file is loaded there, its largest
    connected part kept (:func:`pipeline.meshio.load_mesh`; the others dropped with a warning that names no frame,
    the file and the faces dropped at DEBUG)."""
    params = SpineParams(**params_dict)
    if isinstance(item, (str, Path)):
        from pipeline.geodesic import largest_component
        from pipeline.meshio import load_mesh

        v, f = load_mesh(item, largest=False)
        v2, f2, _ = largest_component(v, f, warn=False) if len(f) else (v, f, None)
        if len(f2) != len(f):  # (one part: the file's vertex numbering kept, as load_mesh keeps it)
            log.debug("%s: %d faces in other connected parts dropped", Path(item).name, len(f) - len(f2))
            log.warning("%s", PARTS_DROPPED)
            v, f = v2, f2
    else:
        v, f = item
    return frame_skeleton(v, f, params=params).to_dict()


def _frame_said(item, params_dict: dict, frame: int) -> tuple[dict, list]:
    """:func:`frame_task` and what frame ``frame`` warned of (:func:`pipeline.run.frame_warnings`), for the
    caller to say once per kind."""
    with frame_warnings(frame) as said:
        out = frame_task(item, params_dict)
    return out, said


def spine_from_meshes(
    meshes,
    *,
    fps: float = 30.0,
    units: str = "mm",
    executor: Executor | None = None,
    progress: bool | Callable[[Iterable], Iterable] = False,
    params: SpineParams | None = None,
) -> Spine:
    """Spine of a mesh sequence: per-frame skeletons (on ``executor`` when given), then the reduce step.

    Parameters
    ----------
    meshes : str, Path, sequence of paths, or sequence of (vertices, faces)
        A glob such as ``'DIR/*.obj'`` or a directory (files sorted by name),
        explicit files (OBJ, PLY, OFF), or in-memory meshes; one per frame,
        in take order.
    fps : float
    units : str
        The meshes' units (written to the spine as given).
    executor : concurrent.futures.Executor, optional
        Runs the per-frame work (a process pool: :func:`frame_task` is its task); without
        one, or for a single frame, it runs in this process. The spine is the same either way.
    progress : bool or callable
        ``True`` shows a tqdm bar; a callable wraps the frame iterator.
    params : SpineParams, optional

    Returns
    -------
    Spine
    """
    from pipeline.meshio import mesh_paths

    params = params or SpineParams()
    if not isinstance(params, SpineParams):
        raise ValueError(f"params must be a SpineParams, got {type(params).__name__}")
    if executor is not None and not isinstance(executor, Executor):
        raise ValueError(f"executor must be a concurrent.futures.Executor, got {type(executor).__name__}")
    if isinstance(meshes, (str, Path)):
        items: list = list(mesh_paths(meshes))
    else:
        items = list(meshes)
        if items and isinstance(items[0], (str, Path)):
            items = list(mesh_paths(items))
    if not items:
        raise ValueError("meshes must hold at least one frame")
    pd = params.model_dump()
    wrap = progress if callable(progress) else None
    if progress is True:
        from tqdm import tqdm

        def wrap(it):
            return tqdm(it, total=len(items), desc="skeletons", unit="frame")

    if executor is None or len(items) == 1:
        it = (_frame_said(x, pd, k) for k, x in enumerate(items))
    else:
        it = executor.map(_frame_said, items, [pd] * len(items), range(len(items)), chunksize=1)
    results = list(wrap(it) if wrap else it)
    for msg, _ in frames_said("skeletons", {k: said for k, (_, said) in enumerate(results) if said}, unit="frame"):
        log.warning("%s", msg)
    frames = [FrameSkeleton.from_dict(r) for r, _ in results]
    return build_spine(frames, fps=fps, units=units, params=params)
