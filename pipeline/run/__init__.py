"""The runner every step over a results directory shares.

A *step* (:class:`Step`) is a named function of a run; a :class:`StepList` keeps a pipeline's steps in order (a
plug-in adds one with :meth:`StepList.register`). A :class:`Run` is what the steps of one call share from the runner:
the results directory, the executor their per-frame tasks fan out over (:meth:`Run.map_tasks`: results as they finish,
cancellation between tasks, the workers' CPU seconds), progress, and the timings the report gives (wall and CPU
seconds per step and per part of a step). :func:`submit_aside` runs one task on the executor while this process works
on (tracking's and carving's second half of a take), with its CPU seconds and a broken pool said once; what a task's
``pipeline`` and ``stage`` loggers warn of in a worker process is said again in the thread that takes its result (a
failed task's before its error), so that a job's warnings and a command's terminal have it; what they warn of while a
task works on one frame set is kept for the frame (:func:`frame_warnings`) and said once per kind of message with the
frame sets that said it (:func:`frames_said`); what every part of a run would say again (its rounds) is said once in
it (:func:`once_per_run`, :func:`warn_once`). :class:`BackgroundWriter` writes a task's files in order on a thread of
their own (atomic and durable, :func:`calib.fileio.atomic_write`) while the task computes on.
:mod:`pipeline.run.settings` holds the start-over rule: a step writes its settings and the digests of what it read
before its results; a later run with other settings makes them again.

The steps themselves live with their pipeline: :mod:`pipeline.process` (key, refine, surface,
spine, track, rig over a take).
"""

from pipeline.run.context import (
    Aside,
    Clock,
    Run,
    chunks,
    finished_before,
    forking_pool,
    frame_warnings,
    frames_said,
    frames_said_before,
    once_per_run,
    pool_size,
    submit_aside,
    submitted_by,
    warn_once,
)
from pipeline.run.settings import array_digest, changed_settings, file_digest, read_settings
from pipeline.run.steps import Step, StepList
from pipeline.run.writer import BackgroundWriter

__all__ = ["Aside", "BackgroundWriter", "Clock", "Run", "Step", "StepList", "array_digest", "changed_settings", "chunks",
           "file_digest", "finished_before", "forking_pool", "frame_warnings", "frames_said", "frames_said_before", "once_per_run",
           "pool_size", "read_settings", "submit_aside", "submitted_by", "warn_once"]
