"""``/takes``: list, describe, view frames and masks, import (upload or path in the data root), give a take a
calibration, delete."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Path, Request, status
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field

from api.deps import LibraryDep, ReadAccess, StoreDep, TakeId, TakeRef, WriteAccess
from api.errors import ConflictError
from api.paths import JOB_ID, TAKE_ID

router = APIRouter(prefix="/takes", tags=["takes"])

_HDF5_TYPES = ("application/x-hdf5", "application/x-hdf", "application/octet-stream")


class TakeSummary(BaseModel):
    id: str
    size_bytes: int
    modified: float | None = None


class TakeInfo(TakeSummary):
    model_config = ConfigDict(extra="allow")
    cameras: list[Any] | None = None
    frames: int | None = None
    sync: Any = None
    calibration: dict[str, Any] | None = None


class ImportPath(BaseModel):
    """Import a take file that is already inside the data root."""

    model_config = ConfigDict(extra="forbid")
    take: TakeRef
    path: Annotated[str, Field(min_length=1, max_length=1024, examples=["incoming/take1.h5"],
                               description="relative to the data root")]
    masks: Annotated[str | None, Field(min_length=1, max_length=1024, examples=["incoming/take1_masks"],
                                       description="silhouettes made elsewhere, relative to the data root: one "
                                       "folder per camera, one image per frame (non-zero = subject); stored as "
                                       "the take's masks, so processing skips keying")] = None


@router.get("", response_model=list[TakeSummary])
def list_takes(library: LibraryDep, _: ReadAccess) -> list[dict]:
    """All takes in the data root."""
    return library.list()


@router.get("/{take_id}", response_model=TakeInfo)
def take_info(take_id: TakeId, library: LibraryDep, _: ReadAccess) -> dict:
    """Cameras, frames, sync statistics and calibration of a take."""
    return library.info(take_id)


@router.get(
    "/{take_id}/frames/{index}/{camera}/{name}",
    response_class=Response,
    responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}, 404: {"description": "no such frame/camera"}},
)
def take_image(take_id: TakeId, index: Annotated[int, Path(ge=0, le=10_000_000)],
               camera: Annotated[str, Path(pattern=r"^[A-Za-z0-9_.\-]{1,64}$",
                                           description="camera id (1 to 64 letters, digits, _ . -)")],
               name: Annotated[Literal["image.png", "image.jpg", "mask.png", "mask.jpg"], Path()],
               library: LibraryDep, _: ReadAccess) -> Response:
    """Frame ``index`` of ``camera`` (``image.png|jpg``) or its mask (``mask.png|jpg``)."""
    kind, fmt = name.split(".")
    data = library.image(take_id, index, camera, kind=kind, fmt=fmt)
    return Response(data, media_type="image/png" if fmt == "png" else "image/jpeg")


@router.put(
    "/{take_id}",
    status_code=status.HTTP_201_CREATED,
    response_model=TakeSummary,
    openapi_extra={"requestBody": {
        "required": True,
        "content": {"application/x-hdf5": {"schema": {"type": "string", "format": "binary"}}},
    }},
    responses={409: {"description": "take exists"}, 413: {"description": "too large"}, 400: {"description": "not a take"},
               507: {"description": "not enough free disk space"}},
)
async def upload_take_raw(take_id: TakeId, request: Request, library: LibraryDep, _: WriteAccess) -> dict:
    """Upload a take as the raw body (an HDF5 take file, ``Content-Type: application/x-hdf5``)."""
    ctype = request.headers.get("content-type", "application/octet-stream").split(";")[0].strip().lower()
    if ctype not in _HDF5_TYPES:
        raise HTTPException(415, f"send the take as {_HDF5_TYPES[0]} (or use POST /takes with multipart/form-data)")
    length = request.headers.get("content-length", "")
    return await library.import_stream(take_id, request.stream(), expected=int(length) if length.isdigit() else None)


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=TakeSummary,
    openapi_extra={"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
        "type": "object", "required": ["take", "file"],
        "properties": {"take": {"type": "string", "pattern": TAKE_ID}, "file": {"type": "string", "format": "binary"}},
    }}}}},
    responses={409: {"description": "take exists"}, 413: {"description": "too large"}, 400: {"description": "not a take"}},
)
async def upload_take_multipart(request: Request, library: LibraryDep, _: WriteAccess) -> dict:
    """Upload a take as ``multipart/form-data`` with fields ``take`` (id) and ``file``."""
    ctype = request.headers.get("content-type", "")
    if not ctype.startswith("multipart/form-data"):
        raise HTTPException(415, "send multipart/form-data with fields 'take' and 'file' (or PUT /takes/{id} with the raw file)")
    try:
        form = await request.form(max_files=1, max_fields=4)
    except AssertionError:  # starlette asserts python-multipart is installed
        raise HTTPException(503, "multipart uploads need python-multipart; PUT /takes/{id} with the raw file instead") from None
    except ValueError as exc:
        raise HTTPException(400, f"bad multipart body: {exc}") from None
    try:
        take, upload = form.get("take"), form.get("file")
        if not isinstance(take, str) or not take:
            raise HTTPException(422, "form field 'take' (the new take's id) is required")
        if upload is None or isinstance(upload, str) or not hasattr(upload, "file"):
            raise HTTPException(422, "form field 'file' (the take file) is required")
        return library.import_file(take, upload.file)
    finally:
        await form.close()


@router.post("/import", status_code=status.HTTP_201_CREATED, response_model=TakeSummary,
             responses={404: {"description": "no such file"}, 400: {"description": "outside the data root / not a take"}})
def import_take_path(body: ImportPath, library: LibraryDep, _: WriteAccess) -> dict:
    """Import a take file from a path inside the data root (e.g. copied there by rsync)."""
    return library.import_path(body.take, body.path, masks=body.masks)


class TakeCalibration(BaseModel):
    """A calibration of the server's (``GET /calibrations``) to make a take's."""

    model_config = ConfigDict(extra="forbid")
    calibration: Annotated[str, Field(pattern=JOB_ID, description="calibration id (32 hex digits)")]


@router.put("/{take_id}/calibration", response_model=TakeInfo,
            responses={404: {"description": "no such take or calibration"},
                       409: {"description": "the calibration lacks a camera of the take / the take is being written or "
                                            "used by active jobs"}})
def put_take_calibration(take_id: TakeId, body: TakeCalibration, request: Request, library: LibraryDep,
                         store: StoreDep, _: WriteAccess) -> dict:
    """Make a calibration the take's (cut to its cameras; stored beside the recording, which is not rewritten): a
    take recorded before the rig was calibrated can then be processed."""
    library.path(take_id)
    active = store.active_for_take(take_id)
    if active:
        raise ConflictError(f"take {take_id!r} is used by active job(s) {', '.join(active)}; wait for them or cancel them")
    cal = request.app.state.calibrations.load(body.calibration)  # 404 when there is none
    return library.attach_calibration(take_id, cal)


@router.delete("/{take_id}", status_code=status.HTTP_204_NO_CONTENT, responses={409: {"description": "jobs still use it"}})
def delete_take(take_id: TakeId, library: LibraryDep, store: StoreDep, _: WriteAccess) -> Response:
    """Delete a take (refused while queued or running jobs use it)."""
    library.path(take_id)
    active = store.active_for_take(take_id)
    if active:
        raise ConflictError(f"take {take_id!r} is used by active job(s) {', '.join(active)}; cancel them first")
    library.delete(take_id)
    return Response(status_code=204)
