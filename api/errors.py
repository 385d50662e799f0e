"""Errors as JSON: ``{"detail": "clear message"}`` with the right status, never a stack trace.

Library code raises plain domain errors (``ValueError`` subclasses, ``KeyError``
subclasses); the handlers here map them to HTTP statuses. Routes may raise
``HTTPException`` themselves.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from api.jobs.runner import WorkUnavailableError
from api.jobs.store import JobNotFoundError, JobStateError
from api.paths import InvalidIdError, OutsideDataRootError

__all__ = ["NotFoundError", "ConflictError", "UploadTooLargeError", "UnavailableError", "install_handlers"]

log = logging.getLogger(__name__)


class NotFoundError(LookupError):
    """A take, camera, frame, calibration or result that does not exist (404)."""


class ConflictError(RuntimeError):
    """The resource is busy or already exists (409)."""


class UploadTooLargeError(ValueError):
    """An upload larger than ``max_upload_bytes`` (413)."""


class UnavailableError(RuntimeError):
    """A feature that needs a missing component (503): no rig file, no driver, no processing module."""


def _scrub(request: Request, message: str) -> str:
    """Never show the server's own paths: the data root becomes ``DATA``."""
    settings = getattr(request.app.state, "settings", None)
    if settings is not None:
        message = message.replace(str(settings.data), "DATA")
    return message


def _json(status: int, message: str, headers: dict | None = None, request: Request | None = None) -> JSONResponse:
    if request is not None:
        message = _scrub(request, message)
    return JSONResponse({"detail": message}, status_code=status, headers=headers)


def _path_field(dependant, name: str):
    """The ``FieldInfo`` of path parameter ``name`` of a route's dependant or of its dependencies' (``JobId`` is a
    dependency's); None when it has none."""
    if dependant is None:
        return None
    for p in dependant.path_params:
        if p.name == name:
            return p.field_info
    for sub in dependant.dependencies:
        if (found := _path_field(sub, name)) is not None:
            return found
    return None


def _path_said(request: Request, error: dict, shown: dict) -> str:
    """A path parameter's validation error in words: one that does not match its pattern is said as what the
    parameter is (its description: ``'xyz' is not a job id (32 hex digits)``) or what it looks like (its examples:
    ``'zero.ply' does not look like any of 'frame_000000.ply', '3.glb'``); any other error, or a parameter with neither,
    as pydantic says it."""
    if shown.get("type") != "string_pattern_mismatch" or len(shown["loc"]) < 2:
        return shown["msg"]
    field = _path_field(getattr(request.scope.get("route"), "dependant", None), str(shown["loc"][1]))
    value = _scrub(request, repr(str(error.get("input", ""))))
    if field is not None and field.description:
        return f"{value} is not a {field.description}"
    if field is not None and field.examples:
        names = list(map(repr, field.examples))
        return f"{value} does not look like {names[0] if len(names) == 1 else 'any of ' + ', '.join(names)}"
    return shown["msg"]


def install_handlers(app: FastAPI) -> None:
    """Register the exception handlers on ``app``."""

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        return _json(exc.status_code, str(exc.detail), getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        # the body the OpenAPI schema promises (HTTPValidationError): detail = [{loc, msg, type}]
        detail = []
        for e in exc.errors():
            loc = [p if isinstance(p, (str, int)) else str(p) for p in e.get("loc", ())]
            msg = _scrub(request, str(e.get("msg", "invalid")))
            detail.append({"loc": loc, "msg": msg, "type": str(e.get("type", "value_error"))})
        # a malformed id in the URL (e.g. a path traversal attempt) is a bad request, not an unprocessable body,
        # whatever the body (the URL names nothing, so the body is not judged); its message says what the parameter
        # is, not the regular expression it failed
        in_path = [(e, d) for e, d in zip(exc.errors(), detail) if d["loc"][:1] == ["path"]]
        if in_path:
            msg = "; ".join(f"{'.'.join(str(p) for p in d['loc'])}: {_path_said(request, e, d)}" for e, d in in_path)
            return JSONResponse({"detail": msg, "errors": [d for _, d in in_path]}, status_code=400)
        return JSONResponse({"detail": detail}, status_code=422)

    @app.exception_handler(InvalidIdError)
    @app.exception_handler(OutsideDataRootError)
    async def _bad_id(request: Request, exc: Exception) -> JSONResponse:
        return _json(400, str(exc), request=request)

    @app.exception_handler(UploadTooLargeError)
    async def _too_large(request: Request, exc: Exception) -> JSONResponse:
        return _json(413, str(exc), request=request)

    @app.exception_handler(JobNotFoundError)
    @app.exception_handler(NotFoundError)
    @app.exception_handler(FileNotFoundError)
    async def _not_found(request: Request, exc: Exception) -> JSONResponse:
        msg = str(exc) if not isinstance(exc, FileNotFoundError) else "not found"
        return _json(404, msg, request=request)

    @app.exception_handler(JobStateError)
    @app.exception_handler(ConflictError)
    async def _conflict(request: Request, exc: Exception) -> JSONResponse:
        return _json(409, str(exc), request=request)

    @app.exception_handler(WorkUnavailableError)
    @app.exception_handler(UnavailableError)
    async def _unavailable(request: Request, exc: Exception) -> JSONResponse:
        return _json(503, str(exc), request=request)

    from stage.drivers.base import CameraError
    from stage.rig import RigError

    @app.exception_handler(RigError)
    async def _rig(request: Request, exc: Exception) -> JSONResponse:
        return _json(503, f"the rig file is not usable: {exc}", request=request)

    @app.exception_handler(CameraError)
    async def _camera(request: Request, exc: Exception) -> JSONResponse:
        return _json(503, f"camera error: {exc}", request=request)

    from stage.store.space import DiskFullError

    @app.exception_handler(DiskFullError)
    async def _disk_full(request: Request, exc: Exception) -> JSONResponse:
        return _json(507, str(exc), request=request)

    @app.exception_handler(ValueError)
    async def _value(request: Request, exc: ValueError) -> JSONResponse:
        return _json(400, str(exc), request=request)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
        return _json(500, f"internal server error ({type(exc).__name__})", request=request)
