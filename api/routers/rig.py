"""``/rig``: cameras and their state, start/stop a capture, a live preview per camera."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, status
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, model_validator

from api.deps import CaptureDep, ReadAccess, TakeRef, WriteAccess

router = APIRouter(prefix="/rig", tags=["rig"])


class CaptureRequest(BaseModel):
    """Capture ``frames`` frame sets or ``duration_s`` seconds into a new take."""

    model_config = ConfigDict(extra="forbid")
    take: TakeRef
    frames: Annotated[int | None, Field(ge=1, le=10_000_000)] = None
    duration_s: Annotated[float | None, Field(gt=0, le=86400)] = None

    @model_validator(mode="after")
    def _one(self) -> "CaptureRequest":
        if (self.frames is None) == (self.duration_s is None):
            raise ValueError("give exactly one of frames or duration_s")
        return self


@router.get("", response_model=dict[str, Any], responses={503: {"description": "no rig file"}})
def get_rig(capture: CaptureDep, _: ReadAccess) -> dict[str, Any]:
    """The rig: name, fps, volume, cameras (with their state) and the current capture."""
    return capture.describe()


@router.get("/capture", response_model=dict[str, Any])
def capture_status(capture: CaptureDep, _: ReadAccess) -> dict[str, Any]:
    """State of the current (or last) capture."""
    return capture.status()


@router.post("/capture", status_code=status.HTTP_202_ACCEPTED, response_model=dict[str, Any],
             responses={409: {"description": "a capture is running / take exists"}, 503: {"description": "no rig"}})
def start_capture(body: CaptureRequest, capture: CaptureDep, _: WriteAccess) -> dict[str, Any]:
    """Start capturing into take ``take`` in the background; follow it with ``GET /rig/capture``."""
    return capture.start(take=body.take, frames=body.frames, duration_s=body.duration_s)


@router.post("/capture/stop", response_model=dict[str, Any], responses={409: {"description": "no capture running"}})
def stop_capture(capture: CaptureDep, _: WriteAccess) -> dict[str, Any]:
    """Stop the running capture; the take keeps the frames written so far."""
    return capture.stop()


@router.get("/cameras/{camera_id}/preview.jpg", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}}}, 404: {"description": "no such camera"}})
def preview(camera_id: Annotated[str, Path(pattern=r"^[A-Za-z0-9_.\-]{1,64}$",
                                           description="camera id (1 to 64 letters, digits, _ . -)")],
            capture: CaptureDep, _: ReadAccess,
            quality: Annotated[int, Query(ge=10, le=100)] = 80) -> Response:
    """A JPEG grabbed now from one camera."""
    return Response(capture.preview(camera_id, quality=quality), media_type="image/jpeg",
                    headers={"Cache-Control": "no-store"})
