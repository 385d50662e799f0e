"""Process a take: keying -> visual hull and surface per frame -> spines -> ``spine.json``.

This is the worker pipeline's driver: a list of named steps (:data:`STEPS`, extended
with :func:`register_step`) run in order on one :class:`RunContext`. Per-frame work (surfaces, per-frame skeletons)
fans out over a :class:`concurrent.futures.Executor` (a local process pool by
default, a Dask ``Client.get_executor()`` on a cluster); the correspondence of tips
over time is the reduce step. Workers open the take by path themselves, so a Dask
cluster needs a shared filesystem.

Every per-frame result is persisted in the output directory as soon as it is
finished (meshes as PLY, skeletons as binary ``.npz``, written atomically by a
background thread of the task while it computes the next frame), and a second call
on the same output directory resumes from the unfinished frames: an interrupted
job re-run gives the same ``spine.json`` as an uninterrupted one.

Frames are read once: a keying task reads its camera's frames, and the masks it
returns (bit-packed) stay in this process and travel with the surface tasks of the
same run, which then never open the take (a resumed run, or a take whose masks
exceed ``steps._KEEP_MASKS_BYTES``, reads them from the take).

The package, one idea a module: :mod:`~pipeline.process.params` (the job's options),
:mod:`~pipeline.process.tasks` (the per-frame tasks the workers run),
:mod:`~pipeline.process.records` (the per-frame skeleton records), :mod:`~pipeline.process.grid`
(the subject's box and the voxel), :mod:`~pipeline.process.steps` (the step list),
:mod:`~pipeline.process.context` (what the steps share) and :mod:`~pipeline.process.driver`
(:func:`process_take`: start over or resume, run the steps, the report). The runner they share
with other steps is :mod:`pipeline.run`.

Output directory layout::

    OUT/process.json              parameters and the take it came from
    OUT/meshes/frame_000000.ply   one surface per frame set (missing: empty frame)
    OUT/frames/frame_000000.json  per-frame surface quality (or why it is empty)
    OUT/skeletons/frame_000000.npz   per-frame tips and skeletons (numpy arrays, for resuming)
    OUT/spine.json                the take's spine (capture-stage/spine@1)
    OUT/consistency.json          per camera and frame set, the IoU of its mask and the projected surface
    OUT/report.json               summary: steps, timings, per-frame quality, tip counts, how K was chosen
"""

from pipeline.process.context import Made, RunContext, TakeFacts
from pipeline.process.driver import process_take
from pipeline.process.grid import MAX_VOXELS, MIN_RESOLUTION, PIXELS_PER_VOXEL
from pipeline.process.params import ProcessError, ProcessParams, ProcessResult, TrackParams
from pipeline.process.steps import DEFAULT_STEPS, STEPS, check_job_steps, register_step
from pipeline.process.tasks import key_task, skeleton_task, surface_task, warm_task
from pipeline.run import Step

__all__ = [
    "DEFAULT_STEPS", "MAX_VOXELS", "MIN_RESOLUTION", "PIXELS_PER_VOXEL", "STEPS", "Made", "ProcessError",
    "ProcessParams", "ProcessResult", "RunContext", "Step", "TakeFacts", "TrackParams", "check_job_steps", "key_task",
    "process_take",
    "register_step", "skeleton_task", "surface_task", "warm_task",
]
