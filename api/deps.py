"""Dependencies of the routes, as ``Annotated`` aliases.

* :data:`SettingsDep`, :data:`StoreDep`, :data:`RunnerDep`, :data:`LibraryDep`, :data:`CaptureDep`:
  the app's singletons (on ``app.state``);
* :data:`WriteAccess`: the bearer token, required by everything that changes anything;
* :data:`ReadAccess`: the token when ``read_protected`` is set, else nothing;
* :data:`TakeId`, :data:`JobId`, :data:`CalibrationId`: validated path parameters; :data:`TakeRef`
  (a body field) and :data:`TakeQuery` (a query parameter) hold take ids under the same rule
  (:func:`api.paths.check_take_id`).
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import AfterValidator, Field

from api.jobs.runner import JobRunner
from api.jobs.store import JobStore
from api.paths import JOB_ID, TAKE_ID, take_id_rule
from api.settings import Settings

__all__ = [
    "SettingsDep",
    "StoreDep",
    "RunnerDep",
    "LibraryDep",
    "CaptureDep",
    "WriteAccess",
    "ReadAccess",
    "TakeId",
    "TakeRef",
    "TakeQuery",
    "JobId",
    "CalibrationId",
]

_bearer = HTTPBearer(auto_error=False, description="API token (settings `api_token` or env STAGE_API_TOKEN)")


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_store(request: Request) -> JobStore:
    return request.app.state.store


async def get_runner(request: Request) -> JobRunner:
    return request.app.state.runner


async def get_library(request: Request):
    return request.app.state.library


async def get_capture(request: Request):
    return request.app.state.capture


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
RunnerDep = Annotated[JobRunner, Depends(get_runner)]
LibraryDep = Annotated["TakeLibrary", Depends(get_library)]  # noqa: F821 (api.library.TakeLibrary)
CaptureDep = Annotated["CaptureManager", Depends(get_capture)]  # noqa: F821 (api.rigctl.CaptureManager)

_Creds = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def _check_token(settings: Settings, creds: HTTPAuthorizationCredentials | None) -> None:
    token = settings.api_token.get_secret_value() if settings.api_token is not None else None
    if not token:
        if settings.allow_anonymous_writes:
            return
        raise HTTPException(403, "this server has no API token configured (set STAGE_API_TOKEN); changes are refused")
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise HTTPException(401, "missing API token: send 'Authorization: Bearer <token>'",
                            headers={"WWW-Authenticate": "Bearer"})
    if not hmac.compare_digest(creds.credentials.encode(), token.encode()):
        raise HTTPException(403, "wrong API token")


async def require_write(settings: SettingsDep, creds: _Creds) -> None:
    """Every endpoint that changes anything depends on this."""
    _check_token(settings, creds)


async def require_read(settings: SettingsDep, creds: _Creds) -> None:
    """Reading endpoints: open unless ``read_protected``."""
    if settings.read_protected:
        _check_token(settings, creds)


WriteAccess = Annotated[None, Depends(require_write)]
ReadAccess = Annotated[None, Depends(require_read)]

_TAKE_DOC = "take id (letters, digits, _ . -; not ending in .derived, .gt, .template, .part, .tmp)"
TakeId = Annotated[str, Path(pattern=TAKE_ID, max_length=128, description=_TAKE_DOC, examples=["take1"]),
                   AfterValidator(take_id_rule)]
TakeRef = Annotated[str, Field(pattern=TAKE_ID, max_length=128, description=_TAKE_DOC, examples=["take1"]),
                    AfterValidator(take_id_rule)]
TakeQuery = Annotated[str | None, Query(pattern=TAKE_ID, max_length=128, description=_TAKE_DOC),
                      AfterValidator(lambda v: v if v is None else take_id_rule(v))]
JobId = Annotated[str, Path(pattern=JOB_ID, description="job id (32 hex digits)")]
CalibrationId = Annotated[str, Path(pattern=JOB_ID, description="calibration id (32 hex digits)")]
