"""``/jobs``: submit processing, follow its progress (polling or Server-Sent Events), cancel, fetch results."""

from __future__ import annotations

import asyncio
import re
import shutil
from typing import Annotated, Any, AsyncIterator, Literal

from fastapi import APIRouter, Depends, Header, HTTPException, Path, Query, Request, status
from fastapi.responses import FileResponse, Response
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import BaseModel, ConfigDict, Field

from api import results
from api.deps import JobId, LibraryDep, ReadAccess, RunnerDep, SettingsDep, StoreDep, TakeQuery, TakeRef, WriteAccess
from api.jobs.store import TERMINAL, JobRecord
from api.paths import inside

router = APIRouter(prefix="/jobs", tags=["jobs"])


class JobCreate(BaseModel):
    """A processing job: which take, which steps, which parameters."""

    model_config = ConfigDict(extra="forbid")
    take: TakeRef
    steps: Annotated[list[str] | None, Field(max_length=16, examples=[["key", "surface", "spine"]])] = None
    parameters: dict[str, Any] = Field(default_factory=dict, description="pipeline.process.ProcessParams fields")


class JobStatus(JobRecord):
    """A job's status: its record and where to follow it."""

    links: dict[str, str] = Field(default_factory=dict)


def _status(rec: JobRecord) -> JobStatus:
    links = {"self": f"/jobs/{rec.id}", "events": f"/jobs/{rec.id}/events"}
    if rec.kind == "process":
        links["results"] = f"/jobs/{rec.id}/results/"
    return JobStatus(**rec.to_dict(), links=links)


async def existing_job(job_id: JobId, store: StoreDep) -> JobRecord:
    return store.get(job_id)


Job = Annotated[JobRecord, Depends(existing_job)]


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=JobStatus,
             responses={400: {"description": "bad steps or parameters"}, 404: {"description": "unknown take"},
                        503: {"description": "processing not available"}})
def create_job(body: JobCreate, _: WriteAccess, store: StoreDep, runner: RunnerDep, library: LibraryDep,
               response: Response) -> JobStatus:
    """Queue a job that processes ``take`` through ``steps``; returns at once (202) with its id."""
    library.path(body.take)  # 404 if the take does not exist
    spec = runner.work_spec()
    steps, params = spec.validate(body.steps, body.parameters)
    _check_rest_frame(steps, params, body.take, library)
    rec = store.create(kind="process", take=body.take, steps=steps, params=params)
    runner.wake()
    response.headers["Location"] = f"/jobs/{rec.id}"
    return _status(rec)


def _check_rest_frame(steps: tuple[str, ...], params: dict, take: str, library) -> None:
    """A job whose rig's rest frame (``parameters.rig.reference``, a position among the tracked frames) is past the
    take's frame sets is refused when submitted, not after its surfaces and tracking: ValueError (400). A position
    within them can still be past the frame sets that get a surface (the rig step says so then)."""
    reference = (params.get("rig") or {}).get("reference") if "rig" in steps and isinstance(params, dict) else None
    if not isinstance(reference, int):
        return
    n = int(library.info(take).get("frames") or 0)
    if reference >= n:
        raise ValueError(f"parameters: rig.reference must be a position within 0..{n - 1} (take {take!r} has {n} "
                         f"frame sets, the most frames a tracking has), got {reference}")


@router.get("", response_model=list[JobStatus])
def list_jobs(store: StoreDep, _: ReadAccess,
              state: Literal["queued", "running", "done", "failed", "cancelled"] | None = None,
              take: TakeQuery = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0) -> list[JobStatus]:
    """Jobs, newest first."""
    return [_status(r) for r in store.list(state=state, take=take, limit=limit, offset=offset)]


@router.get("/{job_id}", response_model=JobStatus)
async def get_job(_: ReadAccess, job: Job) -> JobStatus:
    """Status of one job: state, progress per step, attempts, error (poll this, or follow ``/events``)."""
    return _status(job)


@router.post("/{job_id}/cancel", response_model=JobStatus, responses={409: {"description": "already finished"}})
def cancel_job(_: WriteAccess, job: Job, store: StoreDep, runner: RunnerDep) -> JobStatus:
    """Cancel a queued job at once, or ask a running one to stop."""
    rec = store.request_cancel(job.id)
    runner.wake()
    return _status(rec)


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, responses={409: {"description": "still active"}})
def delete_job(_: WriteAccess, job: Job, store: StoreDep, settings: SettingsDep) -> Response:
    """Forget a finished job and delete its results."""
    store.delete(job.id)
    out = inside(settings.jobs_dir, job.id)
    shutil.rmtree(out, ignore_errors=True)
    return Response(status_code=204)


@router.get("/{job_id}/events", response_class=EventSourceResponse,
            responses={200: {"description": "text/event-stream of `progress` events (id = frames done) and a final `end`"}})
async def job_events(_: ReadAccess, job: Job, request: Request, store: StoreDep, settings: SettingsDep,
                     last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None,
                     ) -> AsyncIterator[ServerSentEvent]:
    """Progress as Server-Sent Events.

    Every ``progress`` event has ``id`` = frames done (summed over steps); a client
    that reconnects with ``Last-Event-ID`` gets only the events after it. The stream
    ends with one ``end`` event carrying the final status. Poll ``GET /jobs/{id}``
    when SSE is not an option.
    """
    try:
        last = int(last_event_id) if last_event_id not in (None, "") else -1
    except ValueError:
        last = -1
    yield ServerSentEvent(event="status", data=_status(job).model_dump(mode="json"), retry=1000)
    poll = settings.poll_s
    while True:
        for seq, data in await asyncio.to_thread(store.events, job.id, after=last):
            last = seq
            yield ServerSentEvent(event="progress", id=str(seq), data=data)
        rec = await asyncio.to_thread(store.get, job.id)
        if rec.state in TERMINAL:
            # drain events written between the two reads
            for seq, data in await asyncio.to_thread(store.events, job.id, after=last):
                last = seq
                yield ServerSentEvent(event="progress", id=str(seq), data=data)
            yield ServerSentEvent(event="end", id=str(max(last, rec.done)), data=_status(rec).model_dump(mode="json"))
            return
        if await request.is_disconnected():
            return
        await asyncio.sleep(poll)


# -- results --------------------------------------------------------------------------------------

#: the names these routes serve: a wrong one is a 400 naming them ("Input should be 'spine.json', ..."), not a pattern
ResultName = Annotated[Literal["spine.json", "report.json", "spine.glb", "spine_rig.glb"], Path()]
MeshName = Annotated[str, Path(pattern=r"^(frame_)?[0-9]{1,6}\.(ply|glb)$", examples=["frame_000000.ply", "3.glb"])]


@router.get("/{job_id}/results/", response_model=dict[str, Any])
def list_results(_: ReadAccess, job: Job, settings: SettingsDep) -> dict[str, Any]:
    """The result files of a job, those written so far (and only those): ``files`` with their ``links``, the
    frames of ``meshes``, ``tracked`` and ``posed``, and ``written_by``, the steps whose results are there (a
    failed job's step that wrote nothing is not among them)."""
    return results.listing(settings.jobs_dir, job.id)


@router.get("/{job_id}/results/meshes/{name}", response_class=FileResponse,
            responses={200: {"content": {"model/gltf-binary": {}, "application/octet-stream": {}}}})
def get_mesh(_: ReadAccess, job: Job, name: MeshName, settings: SettingsDep) -> Response:
    """One frame's surface mesh as PLY (as written) or GLB (converted): ``frame_000003.ply`` or ``3.glb``."""
    path, media = results.mesh(settings.jobs_dir, job.id, name)
    if isinstance(path, bytes):
        return Response(path, media_type=media)
    return FileResponse(path, media_type=media, filename=path.name)


FrameName = Annotated[str, Path(pattern=r"^[0-9]{6}\.ply$", examples=["000003.ply"])]
TrackedName = Annotated[str, Path(pattern=rf"^([0-9]{{6}}\.ply|{'|'.join(map(re.escape, results.TRACKED_FILES))})$",
                                  examples=["000003.ply", *results.TRACKED_FILES])]
RigName = Annotated[Literal[tuple(results.RIG_FILES)], Path()]


@router.get("/{job_id}/results/tracked/{name}", response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}, "application/json": {}}}})
def get_tracked(_: ReadAccess, job: Job, name: TrackedName, settings: SettingsDep) -> Response:
    """What the ``track`` step wrote: one frame of the tracked template, ``000003.ply`` (the template's vertex
    order); ``track.json``, what the tracking did (its options, reference frame, the armature round kept);
    ``labels.npy``, the template's limb/body labels of a tracking with them; ``rig_segments.npy``, the segments of
    the limbs armature its kept armature round tracked with."""
    if name in results.TRACKED_FILES:
        path, media = results.tracked_file(settings.jobs_dir, job.id, name)
        return FileResponse(path, media_type=media, filename=name)
    path = results.frame_file(settings.jobs_dir, job.id, "tracked", name)
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.get("/{job_id}/results/rig/posed/{name}", response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}}}})
def get_posed(_: ReadAccess, job: Job, name: FrameName, settings: SettingsDep) -> Response:
    """One frame of the fitted articulated model (the ``rig`` step): ``000003.ply``."""
    path = results.frame_file(settings.jobs_dir, job.id, "posed", name)
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.get("/{job_id}/results/rig/{name}", response_class=FileResponse,
            responses={200: {"content": {"application/json": {}, "model/gltf-binary": {}, "text/plain": {},
                                         "application/octet-stream": {}}}})
def get_rig_file(_: ReadAccess, job: Job, name: RigName, settings: SettingsDep) -> Response:
    """The armature of the ``rig`` step: ``rig.json``, ``rig.glb``, ``rig.bvh`` or ``segments.npy``."""
    path, media = results.rig_file(settings.jobs_dir, job.id, name)
    return FileResponse(path, media_type=media, filename=name)


@router.get("/{job_id}/results/{name}", response_class=FileResponse,
            responses={200: {"content": {"application/json": {}, "model/gltf-binary": {}}}})
def get_result(_: ReadAccess, job: Job, name: ResultName, settings: SettingsDep) -> Response:
    """``spine.json``, ``report.json``, the animated spine as ``spine.glb``, or the reference mesh
    rigged to the spine as ``spine_rig.glb``."""
    if name == "spine_rig.glb":
        return FileResponse(results.rig_glb(settings.jobs_dir, job.id), media_type="model/gltf-binary",
                            filename="spine_rig.glb")
    if name == "spine.glb":
        return Response(results.spine_glb(settings.jobs_dir, job.id), media_type="model/gltf-binary")
    path = results.result_file(settings.jobs_dir, job.id, name)
    if path is None:
        raise HTTPException(404, f"{name} is not available (job is {job.state})")
    return FileResponse(path, media_type="application/json", filename=name)
