"""What the steps of one :func:`pipeline.process.process_take` call share.

A :class:`RunContext` is the runner's side of the run (:class:`pipeline.run.Run`) and three
groups of the process's own: the job (``params``, the ``steps`` asked for, and what they imply:
``need_key``, ``damaged``), the take (:class:`TakeFacts`, read once when the run opens) and what
the steps made for later steps and the report (:class:`Made`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from calib.fileio import atomic_write, json_default
from pipeline.process.params import ProcessParams
from pipeline.process.records import frame_name
from pipeline.run import Run, chunks, finished_before, frames_said, frames_said_before

log = logging.getLogger("pipeline.process")

__all__ = ["Made", "RunContext", "TakeFacts"]


@dataclass(frozen=True, kw_only=True)
class TakeFacts:
    """The take a run processes, as read when the run opens."""

    path: Path
    calibration: object  # calib.Calibration of ``cameras``, in their order
    cameras: list[str]
    n_sets: int  # frame sets
    fps: float
    rig: dict  # the rig file's contents stored with the take
    all_depth: bool = False  # every camera records depth
    set_table: np.ndarray | None = None  # (S, C) frame row of every camera in every set


@dataclass(kw_only=True)
class Made:
    """What the steps of this run made for later steps and for the report."""

    key_choice: dict = field(default_factory=dict)  # the keying mode and layers of this run, and why
    keyed: dict | None = field(default_factory=dict)  # camera -> (bit-packed masks, width, valid) keyed in this run
    grid_choice: dict = field(default_factory=dict)  # the grid and why
    consistency: dict = field(default_factory=dict)  # per camera median silhouette IoU, and those below the threshold
    skeletons: dict[int, object] = field(default_factory=dict)  # frame -> FrameSkeleton (None: none), as computed
    tip_counts: list[int | None] = field(default_factory=list)  # per frame set
    limb_count: dict = field(default_factory=dict)  # the spine's K and the rule that chose it
    spine_path: Path | None = None


@dataclass(kw_only=True)
class RunContext(Run):
    """The runner's side of the run (:class:`pipeline.run.Run`: results directory, executor,
    progress, cancel, timings, warnings), the job, the take's facts and what the steps made."""

    # the job: what it asks for and what that implies
    params: ProcessParams
    steps: tuple[str, ...] = ()
    need_key: bool  # the key step runs (asked to key again, or a camera has no masks)
    damaged: dict = field(default_factory=dict)  # skip_damaged: {"sets", "frames" per camera, "summary"} skipped
    take: TakeFacts
    made: Made = field(default_factory=Made)

    @property
    def skipped_sets(self) -> frozenset[int]:
        """Frame sets holding a damaged frame, skipped by this run (``skip_damaged``)."""
        return frozenset(self.damaged.get("sets", ()))

    def run_frames(self, step: str, task: Callable[..., list[dict]], done_dir: str, *, suffix: str = ".json",
                   chunk_args: Callable[[list[int]], dict] | None = None,
                   said_before: Callable[[int], list[tuple[str, str | None]]] | None = None) -> None:
        """Run a per-frame ``task`` on every frame set without a result in ``OUT/done_dir``
        (the one runner all per-frame steps share: chunks, executor, progress, cancel);
        ``chunk_args(frames)`` adds keywords per chunk (e.g. its masks). What the frames warned of (a result's
        ``said``, :func:`pipeline.run.frame_warnings`) is said once per kind of message, with the count of frame
        sets and the first of them (:func:`pipeline.run.frames_said`), as ``"{step}: ..."``, in the warnings; when a
        task fails or the run is cancelled, before the error goes on, those of the failed task's frames
        (:func:`pipeline.run.frames_said_before`) and of every task that finished (:func:`pipeline.run.finished_before`):
        each frame set whose result is written has its warnings said, and counts in the step's progress.
        ``said_before(k)``: what frame set ``k``, done by an earlier run (a resumed job, a command run again), said
        then, from its record: said with this run's, so that the warnings (``report.json``'s) are those of one run
        that made every frame set."""
        n_sets = self.take.n_sets
        todo = [k for k in range(n_sets) if not (self.out / done_dir / f"{frame_name(k)}{suffix}").exists()]
        done = n_sets - len(todo)
        self.report_progress(step, done, n_sets)
        tasks = [partial(task, ch, **(chunk_args(ch) if chunk_args else {})) for ch in chunks(todo, self.params.chunk)]
        said: dict[int, list] = {}
        if said_before is not None:
            for k in sorted(set(range(n_sets)) - set(todo)):
                if kept := said_before(k):
                    said[k] = [tuple(x) for x in kept]
        try:
            for finished in self.map_tasks(tasks):
                done += len(finished)
                for rec in finished:
                    if "skeleton" in rec:
                        self.made.skeletons[rec["index"]] = rec.pop("skeleton")
                    if rec.get("said"):
                        said[rec["index"]] = [tuple(x) for x in rec["said"]]
                    rec.pop("said", None)
                self.report_progress(step, done, n_sets)
        except Exception as exc:  # (stopped: the tasks that finished count, and what their frames, a failed one's too, said)
            if finished := finished_before(exc):
                done += sum(len(f) for f in finished)
                self.report_progress(step, done, n_sets)
            for rec in (r for f in finished for r in f):
                if rec.get("said"):
                    said.setdefault(rec["index"], [tuple(x) for x in rec["said"]])
            for k, kept in frames_said_before(exc).items():
                said.setdefault(k, kept)
            raise
        finally:  # (a cancelled or failed run says what its finished frames warned of too)
            for msg, job_message in frames_said(step, said):
                self.warn(msg, job_message=job_message)

    def warn(self, msg: str, *, job_message: str | None = None) -> None:
        """Log ``msg`` as a warning and keep it for the report and the job (``warnings``), said as ``job_message``
        there when given (a message naming a command line option names the job's parameter instead)."""
        log.warning("%s", msg)
        self.keep_warning(msg if job_message is None else job_message)

    def add_to_record(self, **items) -> None:
        """Add what a step decided (e.g. the grid and why) to ``process.json``."""
        path = self.out / "process.json"
        atomic_write(path, json.dumps({**json.loads(path.read_text()), **items}, indent=2, default=json_default))
