"""``/calibrations``: make one from a take (stored calibration or board views), list, download as JSON/TOML/YAML."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Path, Request, status
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from api import calibrations as _cal
from api.calibrations import MEDIA, CalibrationLibrary
from api.deps import CalibrationId, LibraryDep, ReadAccess, RunnerDep, StoreDep, TakeRef, WriteAccess

router = APIRouter(prefix="/calibrations", tags=["calibrations"])


async def get_calibrations(request: Request) -> CalibrationLibrary:
    return request.app.state.calibrations


def find_rig_calibrator():
    return _cal._find_rig_calibrator()


CalibrationsDep = Annotated[CalibrationLibrary, Depends(get_calibrations)]


class CalibrationCreate(BaseModel):
    """Calibrate from a take: copy its stored calibration (``take``) or solve from its board views (``board``)."""

    model_config = ConfigDict(extra="forbid")
    take: TakeRef
    source: Literal["board", "take"] = "board"
    parameters: dict[str, Any] = Field(default_factory=dict, description="source=board: api.calibrations.CalibrateParams "
                                       "(board definition required, step, min_change, world, world_frame, fix_k3, "
                                       "distortion, intrinsics, holdout, mirror)")


class CalibrationSummary(BaseModel):
    id: str
    cameras: list[str | None] = Field(default_factory=list)
    units: str | None = None
    take: str | None = None
    source: str | None = None
    created: float | None = None
    state: str = "done"
    job: str | None = None
    links: dict[str, str] = Field(default_factory=dict)


def _links(cid: str) -> dict[str, str]:
    return {f: f"/calibrations/{cid}.{f}" for f in MEDIA}


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=CalibrationSummary,
             responses={404: {"description": "unknown take / no stored calibration"},
                        503: {"description": "rig calibration not available"}})
def create_calibration(body: CalibrationCreate, library: LibraryDep, calibrations: CalibrationsDep,
                       store: StoreDep, runner: RunnerDep, _: WriteAccess, response: Response) -> CalibrationSummary:
    """Make a calibration from a take. ``source="take"`` finishes at once; ``"board"`` queues a job
    (its id is the calibration id; follow it at ``/jobs/{id}``)."""
    path = library.path(body.take)
    if body.source == "take":
        cid = calibrations.from_take(path, body.take)
        summary = next(c for c in calibrations.list() if c["id"] == cid)
        response.status_code = status.HTTP_201_CREATED
        return CalibrationSummary(**summary, links=_links(cid))
    find_rig_calibrator()  # 503 now rather than a failed job later
    try:
        params = _cal.CalibrateParams.model_validate(body.parameters)
    except ValidationError as exc:
        msgs = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'parameters'}: {e['msg']}" for e in exc.errors())
        raise HTTPException(400, f"parameters: {msgs}") from None
    rec = store.create(kind="calibrate", take=body.take, steps=("detect", "calibrate"),
                       params=params.model_dump(mode="json"))
    runner.wake()
    response.headers["Location"] = f"/jobs/{rec.id}"
    return CalibrationSummary(id=rec.id, take=body.take, source="board", state=rec.state, job=rec.id,
                              links={"job": f"/jobs/{rec.id}", **_links(rec.id)})


@router.get("", response_model=list[CalibrationSummary])
def list_calibrations(calibrations: CalibrationsDep, _: ReadAccess) -> list[CalibrationSummary]:
    """Finished calibrations."""
    return [CalibrationSummary(**c, links=_links(c["id"])) for c in calibrations.list()]


@router.get("/{cal_id}.{fmt}", response_class=Response,
            responses={200: {"content": {m: {} for m in MEDIA.values()}}, 404: {"description": "unknown id"}})
def download_calibration(cal_id: CalibrationId, fmt: Annotated[Literal["json", "toml", "yaml"], Path()],
                         calibrations: CalibrationsDep, _: ReadAccess) -> Response:
    """The calibration as JSON (ours), TOML (aniposelib) or YAML (OpenCV FileStorage)."""
    data = calibrations.export(cal_id, fmt)
    return Response(data, media_type=MEDIA[fmt],
                    headers={"Content-Disposition": f'attachment; filename="calibration-{cal_id}.{fmt}"'})


@router.delete("/{cal_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_calibration(cal_id: CalibrationId, calibrations: CalibrationsDep, _: WriteAccess) -> Response:
    """Delete a calibration."""
    calibrations.delete(cal_id)
    return Response(status_code=204)
