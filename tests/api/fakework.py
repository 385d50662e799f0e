"""A tiny deterministic stand-in for :func:`pipeline.process.process_take` (same contract), for unit tests.

It reads the frame count from a minimal take file (``attrs["frames"]``, see
:func:`make_take_file`), fans frames out on the executor, persists one result per
frame as it finishes, resumes from the unfinished frames when called again on the
same ``out``, and writes ``spine.json`` only when every frame is done (as the real
correspondence step does).
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import os
import threading
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

STEPS = ("key", "surface", "spine")


class ProcessParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    delay_s: float = Field(default=0.0, ge=0, le=5)
    salt: str = "x"


class BadTakeError(ValueError):
    pass


def make_take_file(path: Path, frames: int = 6, *, cameras: int = 2, size: tuple[int, int] = (32, 24),
                   calibration=None, masks: bool = False) -> Path:
    """A small real take (written by stage.store): ``cameras`` cameras of noise images, optional masks."""
    from stage.frame import Frame
    from stage.store import CameraSpec, TakeWriter, write_masks

    w, h = size
    ids = [f"cam{i:02d}" for i in range(cameras)]
    rng = np.random.default_rng(frames)
    with TakeWriter(path, [CameraSpec(c, w, h) for c in ids], fps=30.0, calibration=calibration) as tw:
        for k in range(frames):
            t = 1_000_000_000 + k * 33_333_333
            tw.write_set({c: Frame(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), c, k, t, t) for c in ids}, time_ns=t)
    if masks:
        for c in ids:
            m = np.zeros((frames, h, w), bool)
            m[:, h // 4: 3 * h // 4, w // 4: 3 * w // 4] = True
            write_masks(path, c, m)
    return path


def write_legacy_masks(path: Path, camera: str, masks: np.ndarray) -> None:
    """Masks inside the take file itself, as takes written by older versions of the store hold them."""
    import h5py

    with h5py.File(path, "r+") as f:
        ds = f[f"cameras/{camera}"].create_dataset("masks", data=np.asarray(masks, np.uint8))
        ds.attrs["bool"] = True
        ds.attrs["params"] = "{}"


def _frame(step: str, index: int, salt: str, delay_s: float) -> str:
    if delay_s:
        time.sleep(delay_s)
    return hashlib.sha256(f"{step}:{index}:{salt}".encode()).hexdigest()[:16]


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + f".{os.getpid()}.{threading.get_ident()}.part")
    tmp.write_text(text)
    os.replace(tmp, path)


_PLY = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 4
property list uchar int vertex_indices
end_header
0 0 0
{s} 0 0
0 {s} 0
0 0 {s}
3 0 2 1
3 0 1 3
3 0 3 2
3 1 2 3
"""


def process_take(take: str | Path, out: str | Path, *, steps: Sequence[str] = STEPS,
                 params: ProcessParams | None = None, executor: cf.Executor | None = None,
                 progress: Callable[[str, int, int], None] | None = None,
                 cancel: threading.Event | None = None) -> dict:
    params = params or ProcessParams()
    take, out = Path(take), Path(out)
    from stage.store import TakeReader

    try:
        with TakeReader(take) as r:
            n = len(r)
    except (OSError, ValueError) as exc:
        raise BadTakeError(f"take: not readable ({exc})") from None
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "meshes").mkdir(parents=True, exist_ok=True)
    ex = executor or cf.ThreadPoolExecutor(1)
    for step in steps:
        if step == "spine":
            continue  # correspondence: once all per-frame steps are done
        done_files = {i for i in range(n) if (out / "frames" / f"{step}_{i:06d}.txt").is_file()}
        if progress:
            progress(step, len(done_files), n)
        todo = [i for i in range(n) if i not in done_files]
        futs = {}
        for i in todo:
            futs[ex.submit(_frame, step, i, params.salt, params.delay_s)] = i
        count = len(done_files)
        for fut in cf.as_completed(futs):
            i = futs[fut]
            _write_atomic(out / "frames" / f"{step}_{i:06d}.txt", fut.result())
            if step == "surface":
                _write_atomic(out / "meshes" / f"frame_{i:06d}.ply", _PLY.format(s=1 + i))
            count += 1
            if progress:
                progress(step, count, n)
            if cancel is not None and cancel.is_set():
                for f in futs:
                    f.cancel()
                return {"cancelled": True}
    if "spine" in steps:
        vals = {}
        for i in range(n):
            vals[i] = "".join((out / "frames" / f"{s}_{i:06d}.txt").read_text() for s in steps
                              if s != "spine" and (out / "frames" / f"{s}_{i:06d}.txt").is_file())
        spine = {"frames": [{"index": i, "value": vals[i], "limbs": [{"points": [[0, 0, 0], [i + 1, 1, 2], [2, i, 3]]}]}
                            for i in range(n)]}
        _write_atomic(out / "spine.json", json.dumps(spine, sort_keys=True))
        if progress:
            progress("spine", n, n)
    _write_atomic(out / "report.json", json.dumps({"frames": n, "steps": list(steps)}))
    return {"frames": n}


def small_calibration(n: int = 2):
    """``n`` 32x24 pinhole cameras side by side, 100 mm apart, looking along +z."""
    from calib.calibration import Calibration
    from calib.camera import Camera

    cams = []
    for i in range(n):
        K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
        cams.append(Camera(f"cam{i:02d}", K, np.zeros(5), np.eye(3), np.array([i * 100.0, 0, 1000]), size=(32, 24)))
    return Calibration(tuple(cams))


def ring_calibration(n: int = 3):
    """``n`` 32x24 pinhole cameras on a ring of 1000 mm around the origin, looking at it."""
    from calib.calibration import Calibration
    from calib.camera import Camera

    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
        K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
        cams.append(Camera(f"cam{i:02d}", K, np.zeros(5), R, np.array([0, 0, 1000.0]), size=(32, 24)))
    return Calibration(tuple(cams))
