"""Viewer pages: plain server-rendered HTML that works without internet access.

* ``GET /``: index (links);
* ``GET /ui/takes``: the takes, with their cameras and frames;
* ``GET /ui/takes/{take}``: a take's cameras as frusta (when it has a calibration) and
  a few frames and masks per camera (``<img>`` tags on ``/takes/{take}/frames/...``);
* ``GET /ui/jobs``, ``GET /ui/jobs/{id}``: jobs with live progress bars (a small inline
  script polls ``/jobs`` / ``/jobs/{id}`` every second while a job is active); a job's page links the result
  files it has written (``/jobs/{id}/results/``, polled with it, and once more until it answers after the job
  ends), every frame of its per-frame folders in a collapsed list, never those its steps would write; a
  calibration job's page links its calibration (JSON, TOML, YAML) and report once made (the page is loaded again
  when the job ends);
* ``GET /ui/jobs/{id}/report``: the HTML report of a finished job
  (:func:`pipeline.report.render_report`, cached as ``DATA/jobs/<id>/report.html``).

The pages read with the same :data:`~api.deps.ReadAccess` dependency as the JSON
endpoints. Nothing is fetched from elsewhere: the only scripts are inline, and
plotly.js is embedded (:func:`pipeline.report.figures.plotly_js`) only on pages with
a figure. The pages are left out of the OpenAPI schema (they are not API).

The HTML lives in ``api/templates`` (Jinja2, autoescaped; served through FastAPI's
:class:`~fastapi.templating.Jinja2Templates`); the routes only gather what a page shows.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import threading
from pathlib import Path
from typing import Any

import jinja2
import numpy as np
from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates

from api import results
from api.deps import JobId, LibraryDep, ReadAccess, SettingsDep, StoreDep, TakeId
from api.errors import NotFoundError
from api.jobs.store import JobNotFoundError, JobRecord
from api.paths import data_relative, inside
from calib.fileio import atomic_write

__all__ = ["router", "REPORT_CACHE"]

log = logging.getLogger(__name__)

router = APIRouter(tags=["pages"], include_in_schema=False)

#: the cached report inside a job's results folder
REPORT_CACHE = "report.html"
#: frame sets shown per camera on a take's page
TAKE_PAGE_FRAMES = 3
#: cameras shown with thumbnails on a take's page
TAKE_PAGE_CAMERAS = 16
#: one report rendering at a time per server (it is CPU heavy; concurrent requests wait and reuse the cache)
_report_lock = threading.Lock()

def _when(ts: float | None) -> str:
    if ts is None:
        return "–"
    return _dt.datetime.fromtimestamp(float(ts), _dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def _templates() -> Jinja2Templates:
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("api", "templates"),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
    )
    env.filters["when"] = _when
    return Jinja2Templates(env=env)


templates = _templates()


def _page(request: Request, name: str, title: str, *, status_code: int = 200, **context: Any) -> HTMLResponse:
    """Template ``name`` (which extends ``base.html``) as a page titled ``title``; never cached."""
    return templates.TemplateResponse(request, name, {"title": title, **context}, status_code=status_code,
                                      headers={"Cache-Control": "no-store"})


def _not_found(request: Request, message: str) -> HTMLResponse:
    return _page(request, "not_found.html", "Not found", status_code=404, message=message)


def _plotly_js() -> str:
    """plotly.js, safe inside an inline ``<script>``."""
    from pipeline.report.figures import plotly_js

    return plotly_js().replace("</script", "<\\/script")


# --------------------------------------------------------------------------- index


@router.get("/", response_class=HTMLResponse)
def index(request: Request, _: ReadAccess) -> HTMLResponse:
    """Links to the viewer pages and the API."""
    return _page(request, "index.html", "capture-stage")


# --------------------------------------------------------------------------- takes


def _safe_info(library, take_id: str) -> dict[str, Any] | None:
    try:
        return library.info(take_id)
    except (NotFoundError, ValueError, OSError) as exc:
        log.warning("take %s cannot be described: %s", take_id, exc)
        return None


@router.get("/ui/takes", response_class=HTMLResponse)
def takes_page(request: Request, library: LibraryDep, _: ReadAccess) -> HTMLResponse:
    """The takes of the data root with their cameras and frame counts."""
    takes = []
    for t in library.list():
        info = _safe_info(library, t["id"])
        cams = [str(c.get("id")) for c in (info or {}).get("cameras") or []]
        takes.append({"id": t["id"], "info": info, "camera_ids": cams, "size_bytes": t["size_bytes"]})
    return _page(request, "takes.html", "Takes", takes=takes)


def _frame_sets(n: int, k: int) -> list[int]:
    if n <= 0:
        return []
    return sorted(set(np.linspace(0, n - 1, min(n, k)).round().astype(int).tolist()))


def _frusta_html(calibration: dict) -> str:
    """The cameras of a calibration (as stored in a take) as a plotly figure's HTML."""
    from calib.calibration import Calibration
    from pipeline.report.figures import figure_html, frusta_figure

    return figure_html(frusta_figure(Calibration.from_dict(calibration)), div_id="frusta")


def _sync_rows(sync: dict[str, Any]) -> list[tuple[str, Any]]:
    """A take's sync statistics as its page's summary rows (none for a take without them)."""
    if not sync:
        return []
    med, mx = sync.get("spread_median_ms"), sync.get("spread_max_ms")
    return [("complete frame sets", f"{sync.get('sets_complete')} of {sync.get('sets')}"),
            ("sync spread (ms)", "–" if med is None else f"{med:.2f} median, {mx:.2f} max")]


@router.get("/ui/takes/{take_id}", response_class=HTMLResponse)
def take_page(request: Request, take_id: TakeId, library: LibraryDep, store: StoreDep,
              _: ReadAccess) -> HTMLResponse:
    """One take: its cameras as frusta (when calibrated), and a few frames and masks per camera."""
    try:
        info = library.info(take_id)
    except NotFoundError as exc:
        return _not_found(request, str(exc))
    cams = info.get("cameras") or []
    n = int(info.get("frames") or 0)
    sync = info.get("sync") or {}
    frusta = calibration_error = None
    if info.get("calibration"):
        try:
            frusta = _frusta_html(info["calibration"])
        except (ValueError, KeyError, TypeError) as exc:
            calibration_error = str(exc)
    extra = {"plotly_js": _plotly_js()} if frusta is not None else {}
    return _page(
        request, "take.html", f"Take {take_id}", **extra,
        take_id=take_id,
        summary=[("frames (sets)", n), ("fps", info.get("fps")), ("duration (s)", info.get("duration_s")),
                 ("complete", info.get("complete")), ("compression", info.get("compression")), *_sync_rows(sync)],
        sync_cameras=sync.get("cameras") or {},
        cameras=cams,
        masks=set(info.get("masks") or []),
        frusta=frusta,
        calibration_error=calibration_error,
        sets=_frame_sets(n, TAKE_PAGE_FRAMES),
        thumb_cameras=[str(c.get("id")) for c in cams[:TAKE_PAGE_CAMERAS]],
        hidden_cameras=len(cams) - TAKE_PAGE_CAMERAS,
        jobs=store.list(take=take_id, limit=20),
    )


# --------------------------------------------------------------------------- jobs


@router.get("/ui/jobs", response_class=HTMLResponse)
def jobs_page(request: Request, store: StoreDep, _: ReadAccess) -> HTMLResponse:
    """All jobs (newest first) with live progress."""
    limit = 200
    return _page(request, "jobs.html", "Jobs", jobs=store.list(limit=limit), limit=limit)


@router.get("/ui/jobs/{job_id}", response_class=HTMLResponse)
def job_page(request: Request, job_id: JobId, store: StoreDep, settings: SettingsDep, _: ReadAccess) -> HTMLResponse:
    """One job: state, its steps each with its progress entries under it (live: :func:`step_groups`), error, links
    to the results it has written (live: the page asks ``/jobs/{id}/results/`` as the job runs) and its report."""
    try:
        j = store.get(job_id)
    except JobNotFoundError as exc:
        return _not_found(request, str(exc))
    written = results.listing(settings.jobs_dir, j.id) if j.kind == "process" else None
    return _page(request, "job.html", f"Job {j.id[:8]}", job=j,
                 calibration_links=_calibration_links(j, settings) if j.kind == "calibrate" else [],
                 result_links=list(written["links"].items()) if written else [],
                 frame_lists=_frame_lists(written) if written else [],
                 unwritten=_unwritten(j, written) if written else "",
                 result_steps=results.RESULT_STEPS, frame_links=_FRAME_LINKS,
                 step_groups=step_groups(j), steps_key=steps_key(j.progress),
                 parameters=json.dumps(j.params) if j.params else "–")


def step_groups(job: JobRecord) -> list[tuple[str, list[tuple[str, dict]]]]:
    """The job's steps, each with its progress entries ``(name, entry)`` as the job's record says whose they are
    (an entry's ``step``, the pipeline's announcement; an entry without one is a step of its own), in the order
    they were first reported; a step the job asked for that reported nothing has no entries, after the step
    asked before it. The job's page lists them so, one table."""
    groups: dict[str, list[tuple[str, dict]]] = {}
    for name, entry in (job.progress or {}).items():
        groups.setdefault(entry.get("step") or name, []).append((name, entry))
    order = list(groups)
    for i, step in enumerate(job.steps):
        if step not in groups:
            before = [s for s in job.steps[:i] if s in order]
            order.insert(order.index(before[-1]) + 1 if before else 0, step)
            groups[step] = []
    return [(step, groups[step]) for step in order]


def steps_key(progress: dict) -> str:
    """The progress entries and their steps, as job.js says them (``JSON.stringify``): the page's steps table is
    laid out again (asked from the server) when the job's differ from those it was laid out for."""
    return json.dumps([[name, e.get("step") or name] for name, e in (progress or {}).items()], separators=(",", ":"))


#: a job's per-frame results on its page: the listing's frames, the key of their URL, what the list is called
_FRAME_LINKS = (("meshes", "mesh_url", "surface meshes"), ("tracked", "tracked_url", "tracked meshes"),
                ("posed", "posed_url", "posed meshes"))


def _frame_lists(written: dict[str, Any]) -> list[tuple[str, str, list[tuple[int, str]]]]:
    """Per folder of per-frame results a job has written (its listing, :func:`api.results.listing`), in the order
    of :data:`_FRAME_LINKS`: its key, what its list says (``"surface meshes (6 frame sets)"``) and ``(frame set,
    url)`` of every frame in it. The page shows each as a collapsed list of every frame (job.js makes the same from
    the listing as the job runs)."""
    out = []
    for key, url, text in _FRAME_LINKS:
        if frames := written.get(key):
            said = f"{text} ({len(frames)} frame set{'s' if len(frames) != 1 else ''})"
            out.append((key, said, [(k, written[url].format(index=k)) for k in frames]))
    return out


def _calibration_links(job: JobRecord, settings) -> list[tuple[str, str]]:
    """``(text, url)`` of what a calibration job has made: its calibration in each format once it is saved (the
    calibration's id is the job's), and its ``report.json`` once written; nothing that is not there (a failed job's,
    a calibration deleted since)."""
    from api.calibrations import FORMATS, CalibrationLibrary

    links = []
    if CalibrationLibrary(settings.calibrations_dir).exists(job.id):
        links += [(f"calibration.{f}", f"/calibrations/{job.id}.{f}") for f in FORMATS]
    if results.result_file(settings.jobs_dir, job.id, "report.json") is not None:
        links.append(("report.json", f"/jobs/{job.id}/results/report.json"))
    return links


def _unwritten(job: JobRecord, written: dict[str, Any]) -> str:
    """What a failed or cancelled job's page says of its steps that wrote nothing (job.js says it alike)."""
    steps = [s for s in job.steps if s in results.RESULT_STEPS and s not in written["written_by"]]
    if job.state not in ("failed", "cancelled") or not steps:
        return ""
    named = steps[0] if len(steps) == 1 else ", ".join(steps[:-1]) + " and " + steps[-1]
    return (f"The job {'failed' if job.state == 'failed' else 'was cancelled'}: "
            f"the {named} step{'s' if len(steps) > 1 else ''} wrote nothing.")


def _report_html(job: JobRecord, job_dir: Path, take: Path | None, data_root: Path) -> str:
    """The cached report of a finished job, (re)rendered when missing or older than its inputs;
    paths in it are relative to the data root (``DATA/...``), never the server's own."""
    from pipeline.report import render_report

    cache = job_dir / REPORT_CACHE
    inputs = [p for p in (job_dir / "spine.json", job_dir / "report.json") if p.is_file()]
    newest = max((p.stat().st_mtime for p in inputs), default=0.0)
    with _report_lock:
        if cache.is_file() and cache.stat().st_mtime >= newest:
            return cache.read_text(encoding="utf-8")
        page = data_relative(render_report(job_dir, take=take), data_root)
        atomic_write(cache, page)
        return page


@router.get("/ui/jobs/{job_id}/report", response_class=HTMLResponse)
def job_report(request: Request, job_id: JobId, store: StoreDep, library: LibraryDep, settings: SettingsDep,
               _: ReadAccess) -> HTMLResponse:
    """The HTML report of a finished processing job (plotly.js embedded; cached in the job's folder)."""
    from pipeline.report import NothingToReportError

    try:
        j = store.get(job_id)
    except JobNotFoundError as exc:
        return _not_found(request, str(exc))
    if j.kind != "process":
        return _not_found(request, f"job {j.id} is a {j.kind} job: it has no report")
    if j.state != "done":
        return _not_found(request, f"job {j.id} is {j.state}: the report exists once it is done")
    job_dir = inside(settings.jobs_dir, j.id)
    if not job_dir.is_dir():
        return _not_found(request, f"job {j.id} has no results")
    try:
        take = library.path(j.take)
    except (NotFoundError, ValueError):
        take = None  # deleted since: a report without contact sheets
    try:
        page = _report_html(j, job_dir, take, settings.data)
    except NothingToReportError:
        return _not_found(request, f"job {j.id} has no spine.json or report.json")
    return HTMLResponse(page, headers={"Cache-Control": "no-cache"})
