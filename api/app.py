"""The FastAPI application: ``create_app(settings) -> FastAPI`` (OpenAPI UI at ``/docs``).

The app owns, on ``app.state``: the settings, the :class:`~api.jobs.store.JobStore`,
the :class:`~api.jobs.runner.JobRunner` (started and stopped with the app), the
take and calibration libraries and the capture manager.
"""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from typing import Any, Callable

from fastapi import FastAPI
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.calibrations import CalibrationLibrary, calibrate_take_work
from api.errors import UploadTooLargeError, install_handlers
from api.jobs.runner import JobRunner
from api.jobs.store import JobStore
from api.library import TakeLibrary
from api.openapi import declare_responses
from api.paths import upload_path
from api.rigctl import CaptureManager
from api.routers import calibrations, jobs, pages, rig, takes
from api.routers import control as control_routes
from api.settings import Settings

__all__ = ["create_app"]

log = logging.getLogger(__name__)

#: request bodies other than take uploads are small JSON documents
SMALL_BODY = 1 << 20


class BodySizeLimit:
    """Refuse request bodies over the limit, counting bytes as they arrive (Content-Length may lie or be absent)."""

    def __init__(self, app: ASGIApp, *, max_upload_bytes: int) -> None:
        self.app = app
        self.max_upload_bytes = max_upload_bytes

    def _limit(self, scope: Scope) -> int:
        """The upload limit for the two routes that take a take file (``POST /takes``, ``PUT
        /takes/{id}``); every other body is a small JSON document (``POST /takes/import`` too)."""
        path, method = scope.get("path", "").rstrip("/"), scope.get("method", "")
        if (method == "POST" and path == "/takes") or (method == "PUT" and upload_path(path)):
            return self.max_upload_bytes
        return SMALL_BODY

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self._limit(scope)
        for k, v in scope.get("headers", []):
            if k == b"content-length":
                try:
                    n = int(v)
                except ValueError:
                    n = 0
                if n > limit:
                    from fastapi.responses import JSONResponse

                    await JSONResponse({"detail": f"request body larger than the limit of {limit} bytes"},
                                       status_code=413)(scope, receive, send)
                    return
        seen = 0
        too_large = False
        replied = False

        async def limited() -> Message:
            nonlocal seen, too_large
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > limit:
                    too_large = True
                    raise UploadTooLargeError(f"request body larger than the limit of {limit} bytes")
            return msg

        async def reply(message: Message) -> None:
            # a body that grew past the limit (chunked, no Content-Length) is a 413 whatever the
            # route made of the aborted read (FastAPI answers 400 "error parsing the body")
            nonlocal replied
            if too_large:
                if not replied and message["type"] == "http.response.start":
                    replied = True
                    from fastapi.responses import JSONResponse

                    await JSONResponse({"detail": f"request body larger than the limit of {limit} bytes"},
                                       status_code=413)(scope, receive, send)
                return
            await send(message)

        try:
            await self.app(scope, limited, reply)
        except UploadTooLargeError:
            if replied:
                return
            from fastapi.responses import JSONResponse

            await JSONResponse({"detail": f"request body larger than the limit of {limit} bytes"},
                               status_code=413)(scope, receive, send)


def create_app(settings: Settings | None = None, *, work: str | Callable[..., Any] | None = None,
               executor: Any = None, start_runner: bool = True, driver_factory: Any = None,
               control: Any = None) -> FastAPI:
    """Build the API application.

    Parameters
    ----------
    settings : Settings, optional
        Default: from the environment (``STAGE_*``).
    work : str or callable, optional
        Override of ``settings.work`` (the job work function; test hook).
    executor : ExecutorHandle or callable, optional
        Override of the executor (default: local pool, or Dask per settings).
    start_runner : bool
        Run jobs in this process (default). ``False`` only queues them.
    driver_factory : callable, optional
        ``(camera_config, rig) -> CameraDriver`` instead of :func:`stage.drivers.open_driver` (test hook).
    control : api.control.ControlRoom, optional
        The running stage session's control room (``/stage``, ``/ui/stage``); the app closes it
        and its session at shutdown. Captures of ``/rig/capture`` then record from the session.
    """
    settings = settings if settings is not None else Settings()
    settings.ensure_dirs()
    store = JobStore(settings.db_path)
    runner = JobRunner(
        store,
        takes_dir=settings.takes_dir,
        jobs_dir=settings.jobs_dir,
        work=work if work is not None else settings.work,
        executor=executor,
        dask=settings.dask,
        workers=settings.workers,
        heartbeat_s=settings.heartbeat_s,
        stale_after_s=settings.stale_after_s,
        max_attempts=settings.max_attempts,
        max_concurrent=settings.max_concurrent_jobs,
        poll_s=settings.poll_s,
        handlers={"calibrate": calibrate_take_work(settings.calibrations_dir)},
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.library.remove_stale_uploads()  # a killed server's unfinished uploads
        if start_runner:
            runner.start()
        try:
            yield
        finally:
            capture = app.state.capture
            if capture.busy:  # close the take cleanly
                capture.stop()
                capture.wait(30)
            if control is not None:  # a take being recorded is closed cleanly, then the cameras
                control.close()
                control.session.close()
            runner.stop()
            store.close()

    from stage import __version__

    app = FastAPI(
        title="capture-stage",
        version=__version__,
        description="Drive the capture rig, manage takes and calibrations, and turn takes into spines. "
        "Endpoints that change anything need `Authorization: Bearer <token>`.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.store = store
    app.state.runner = runner
    app.state.library = TakeLibrary(settings.takes_dir, max_upload_bytes=settings.max_upload_bytes, data_root=settings.data)
    app.state.calibrations = CalibrationLibrary(settings.calibrations_dir)
    app.state.capture = CaptureManager(settings.rig_path, settings.takes_dir, driver_factory=driver_factory,
                                       session=None if control is None else control.session,
                                       take_calibration=None if control is None else control.take_calibration)
    app.state.control = control
    if control is not None and control.calibrations is None:  # the 3-D preview finds the calibrations made here
        control.calibrations = app.state.calibrations
    install_handlers(app)
    app.add_middleware(BodySizeLimit, max_upload_bytes=settings.max_upload_bytes)
    for r in (rig.router, takes.router, calibrations.router, jobs.router, pages.router, control_routes.router):
        app.include_router(r)

    declare_responses(app, (rig.router, takes.router, calibrations.router, jobs.router, control_routes.router),
                      read_protected=settings.read_protected)

    @app.get("/health", tags=["meta"])
    def health() -> dict[str, Any]:
        """Liveness: version and where jobs run."""
        return {"status": "ok", "version": __version__, "executor": "dask" if settings.dask else "local",
                "runner": bool(runner._thread and runner._thread.is_alive())}

    return app
