"""``/stage``: the running stage session (``stage serve --rig``) and its control room page ``/ui/stage``.

Reading (previews, figures, board guidance, the 3-D preview) follows ``--read-protected``;
everything that changes state (record, stop, board sessions, calibrate) needs the token.

Previews are MJPEG (``multipart/x-mixed-replace``): one stream per camera for an ``<img>``,
and ``/stage/previews.mjpg`` with every camera's parts in one response (a part's
``X-Camera`` header names its camera), which the page reads with ``fetch`` so that a dozen
cameras do not exhaust the browser's six connections per server. A stream ends when its
client goes away or the session closes; the open streams are counted in the figures.
"""

from __future__ import annotations

import asyncio
import datetime as _dt
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from api.deps import CalibrationId, LibraryDep, ReadAccess, RunnerDep, SettingsDep, StoreDep, WriteAccess
from api.errors import NotFoundError
from api.paths import TAKE_ID, check_id, inside

router = APIRouter(tags=["stage"])

BOUNDARY = "stageframe"
CameraId = Annotated[str, Path(pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="camera id of the rig")]


async def get_control(request: Request):
    room = getattr(request.app.state, "control", None)
    if room is None:
        raise NotFoundError("no stage session: start the server with stage serve --rig RIG.toml")
    return room


ControlDep = Annotated[Any, Depends(get_control)]


class RecordRequest(BaseModel):
    """Record a take from the running cameras: ``duration_s`` seconds, ``frames`` sets, or until stopped."""

    model_config = ConfigDict(extra="forbid")
    take: Annotated[str, Field(pattern=TAKE_ID, max_length=128, examples=["take1"])]
    frames: Annotated[int | None, Field(ge=1, le=10_000_000)] = None
    duration_s: Annotated[float | None, Field(gt=0, le=86400)] = None

    @model_validator(mode="after")
    def _one(self) -> "RecordRequest":
        if self.frames is not None and self.duration_s is not None:
            raise ValueError("give at most one of frames or duration_s")
        return self


class BoardRequest(BaseModel):
    """Start a board session: record the board take ``take`` while the board is detected live."""

    model_config = ConfigDict(extra="forbid")
    take: Annotated[str | None, Field(pattern=TAKE_ID, max_length=128)] = None
    min_views: Annotated[int, Field(ge=1, le=1000)] = 8
    min_shared: Annotated[int, Field(ge=1, le=1000)] = 3


class CalibrateRequest(BaseModel):
    """Calibrate the board take: ``holdout`` folds for the held-out errors (0 or >= 2), the board
    detected in every ``step``-th frame set."""

    model_config = ConfigDict(extra="forbid")
    holdout: Annotated[int, Field(ge=0, le=20)] = 5
    step: Annotated[int, Field(ge=1, le=1000)] = 1

    @model_validator(mode="after")
    def _folds(self) -> "CalibrateRequest":
        if self.holdout == 1:
            raise ValueError("holdout must be 0 (none) or >= 2 folds")
        return self


def _start(room, settings, take: str, **kw: Any) -> dict[str, Any]:
    from stage.session import RecordingBusyError

    check_id(take, pattern=TAKE_ID, name="take")
    out = inside(settings.takes_dir, f"{take}.h5")
    try:
        return room.session.start_recording(out, take=take, **kw)
    except RecordingBusyError as exc:
        raise HTTPException(409, str(exc)) from None
    except FileExistsError as exc:
        raise HTTPException(409, str(exc)) from None


# --------------------------------------------------------------------------- figures


@router.get("/stage", response_model=dict[str, Any], responses={404: {"description": "no stage session"}})
def stage_figures(room: ControlDep, _: ReadAccess) -> dict[str, Any]:
    """Live figures: per camera state, delivered fps, drops, exposure/gain, USB load; sync spread of
    the last sets; disk free and minutes left; the take being recorded; preview streams and latency."""
    return room.figures()


@router.post("/stage/record", status_code=status.HTTP_202_ACCEPTED, response_model=dict[str, Any],
             responses={409: {"description": "a take is being recorded / the take exists"}})
def record(body: RecordRequest, room: ControlDep, settings: SettingsDep, _: WriteAccess) -> dict[str, Any]:
    """Record a take from the running cameras (one at a time: a second request gets 409). The take stores the
    calibration the live 3-D preview uses (``GET /stage``: ``take_calibration`` says which, or why none)."""
    cal, _said = room.take_calibration()
    return _start(room, settings, body.take, frames=body.frames, duration_s=body.duration_s, calibration=cal)


@router.post("/stage/stop", response_model=dict[str, Any], responses={409: {"description": "nothing is recorded"}})
async def stop(room: ControlDep, _: WriteAccess) -> dict[str, Any]:
    """Stop the take being recorded; it keeps what was written."""
    from stage.session import NoRecordingError

    try:
        return await run_in_threadpool(room.session.stop_recording)
    except NoRecordingError as exc:
        raise HTTPException(409, str(exc)) from None


# --------------------------------------------------------------------------- previews


def _part(cid: str, seq: int, jpg: bytes) -> bytes:
    head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nX-Camera: {cid}\r\nX-Seq: {seq}\r\n"
            f"Content-Length: {len(jpg)}\r\n\r\n").encode()
    return head + jpg + b"\r\n"


async def _stream(request: Request, room, cams: list[str], mask: bool):
    """Parts for ``cams`` at the preview rate, each camera's new frames only, until the client leaves."""
    period = 1.0 / room.preview_fps
    last = {c: -1 for c in cams}
    room.stream_opened()
    try:
        while not (room.session.closed or room.closing.is_set()):
            t0 = asyncio.get_running_loop().time()
            for cid in cams:
                seq, jpg, grab_ns = await run_in_threadpool(room.preview, cid, mask=mask)
                if jpg is None or seq == last[cid]:
                    continue
                last[cid] = seq
                yield _part(cid, seq, jpg)
                room.sent(grab_ns)
            await asyncio.sleep(max(0.0, period - (asyncio.get_running_loop().time() - t0)))
    finally:
        room.stream_closed()


@router.get("/stage/previews.mjpg", response_class=StreamingResponse,
            responses={200: {"content": {f"multipart/x-mixed-replace; boundary={BOUNDARY}": {}}}})
def previews(request: Request, room: ControlDep, _: ReadAccess,
             mask: Annotated[bool, Query(description="tint the backdrop mask in")] = False) -> StreamingResponse:
    """Every camera's preview in one MJPEG stream (a part's ``X-Camera`` header names its camera)."""
    return StreamingResponse(_stream(request, room, list(room.session.ids), mask),
                             media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                             headers={"Cache-Control": "no-store"})


@router.get("/stage/cameras/{camera_id}/preview.mjpg", response_class=StreamingResponse,
            responses={200: {"content": {f"multipart/x-mixed-replace; boundary={BOUNDARY}": {}}},
                       404: {"description": "no such camera"}})
def camera_preview_stream(request: Request, camera_id: CameraId, room: ControlDep, _: ReadAccess,
                          mask: bool = False) -> StreamingResponse:
    """One camera's live preview as MJPEG (for an ``<img>``)."""
    if camera_id not in room.session.ids:
        raise HTTPException(404, f"no camera {camera_id!r} in the rig")
    return StreamingResponse(_stream(request, room, [camera_id], mask),
                             media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                             headers={"Cache-Control": "no-store"})


@router.get("/stage/cameras/{camera_id}/preview.jpg", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}}}, 404: {"description": "no such camera / no frame yet"}})
def camera_preview(camera_id: CameraId, room: ControlDep, _: ReadAccess, mask: bool = False) -> Response:
    """The latest frame of one running camera as a JPEG."""
    if camera_id not in room.session.ids:
        raise HTTPException(404, f"no camera {camera_id!r} in the rig")
    seq, jpg, _ = room.preview(camera_id, mask=mask)
    if jpg is None:
        raise HTTPException(404, f"camera {camera_id!r} has delivered no frame yet")
    return Response(jpg, media_type="image/jpeg", headers={"Cache-Control": "no-store", "X-Seq": str(seq)})


# --------------------------------------------------------------------------- board session


@router.get("/stage/board", response_model=dict[str, Any])
def board_status(room: ControlDep, _: ReadAccess) -> dict[str, Any]:
    """The board session: views per camera, shared views per pair, coverage maps, enough or not."""
    if room.board_session is None:
        return {"running": False, "board": None if room.board is None else room.board.to_dict(),
                "message": "no board session" if room.board is not None else
                "no calibration board: start stage serve with --board BOARD.toml"}
    return room.board_session.status()


@router.post("/stage/board/start", status_code=status.HTTP_202_ACCEPTED, response_model=dict[str, Any],
             responses={409: {"description": "a take is being recorded"}, 400: {"description": "no board"}})
def board_start(body: BoardRequest, room: ControlDep, settings: SettingsDep, _: WriteAccess) -> dict[str, Any]:
    """Start recording the board take and detecting the board live on every camera."""
    if room.board is None:
        raise HTTPException(400, "no calibration board: start stage serve with --board BOARD.toml")
    take = body.take or "board-" + _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S")
    _start(room, settings, take)
    bs = room.start_board(min_views=body.min_views, min_shared=body.min_shared)
    bs.take = take
    return bs.status()


@router.post("/stage/board/calibrate", status_code=status.HTTP_202_ACCEPTED, response_model=dict[str, Any],
             responses={409: {"description": "no board session"}})
async def board_calibrate(body: CalibrateRequest, room: ControlDep, store: StoreDep, runner: RunnerDep,
                          library: LibraryDep, _: WriteAccess) -> dict[str, Any]:
    """Stop the board take and queue its calibration job (follow it at ``/jobs/{id}``; its
    ``report.json`` holds every warning and the held-out errors)."""
    from api.calibrations import CalibrateParams
    from stage.session import NoRecordingError

    bs = room.board_session
    if bs is None or bs.take is None:
        raise HTTPException(409, "no board session: start one first")
    bs.stop()
    try:
        await run_in_threadpool(room.session.stop_recording)
    except NoRecordingError:
        pass  # it ended on its own
    library.path(bs.take)  # 404 when the take is not there
    params = CalibrateParams(board=room.board.to_dict(), holdout=body.holdout, step=body.step)
    rec = store.create(kind="calibrate", take=bs.take, steps=("detect", "calibrate"),
                       params=params.model_dump(mode="json"))
    runner.wake()
    bs.job = rec.id
    return {"job": rec.id, "take": bs.take, "links": {"job": f"/jobs/{rec.id}",
                                                      "report": f"/jobs/{rec.id}/results/report.json"}}


# --------------------------------------------------------------------------- 3-D preview


@router.put("/stage/calibration/{cal_id}", response_model=dict[str, Any],
            responses={409: {"description": "the calibration has none of the rig's cameras"}})
def choose_calibration(cal_id: CalibrationId, room: ControlDep, request: Request, _: WriteAccess) -> dict[str, Any]:
    """Make calibration ``cal_id`` the live 3-D preview's (its worker starts again with it). A
    board session's calibration becomes the preview's by itself once its job is done."""
    cal = request.app.state.calibrations.load(cal_id)  # 404 when there is none
    if not set(cal.names) & set(room.session.ids):
        raise HTTPException(409, f"calibration {cal_id} has none of the rig's cameras ({', '.join(room.session.ids)})")
    room.use_calibration(cal, f"calibration {cal_id}")
    return {"calibration": room.calibration_source, "version": room.calibration_version}


@router.get("/stage/live3d", response_model=dict[str, Any])
def live3d(room: ControlDep, _: ReadAccess) -> dict[str, Any]:
    """The latest coarse hull (surface voxel centres, world units) and spine segments."""
    if room.live3d is None:
        return {"state": "off", "message": "the 3-D preview is off"}
    return room.live3d.latest()


# --------------------------------------------------------------------------- page


@router.get("/ui/stage", response_class=HTMLResponse, include_in_schema=False)
def stage_page(request: Request, _: ReadAccess) -> HTMLResponse:
    """The control room: a tile per camera, record/stop, board session, 3-D preview, takes; without a stage
    session, a page that says how to start one (the navigation links here from every page)."""
    from api.routers.pages import _not_found, _page

    room = getattr(request.app.state, "control", None)
    if room is None:
        return _not_found(request, "No stage session: this server was started without cameras. Start it with "
                                   "stage serve --rig RIG.toml (docs/control-room.md) to see and record them here.")
    rig = room.session.rig
    return _page(request, "stage.html", f"Stage · {rig.name}", cameras=list(room.session.ids),
                 has_board=room.board is not None, fps=rig.fps)
