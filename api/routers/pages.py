"""Viewer pages: plain server-rendered HTML that works without internet access.

* ``GET /``: index (links);
* ``GET /ui/takes``: the takes, with their cameras and frames;
* ``GET /ui/takes/{take}``: a take's cameras as frusta (when it has a calibration) and
  a few frames and masks per camera (``<img>`` tags on ``/takes/{take}/frames/...``);
* ``GET /ui/jobs``, ``GET /ui/jobs/{id}``: jobs with live progress bars (a small inline
  script polls ``/jobs`` / ``/jobs/{id}`` every second while a job is active);
* ``GET /ui/jobs/{id}/report``: the HTML report of a finished job
  (:func:`stage.report.render_report`, cached as ``DATA/jobs/<id>/report.html``).

The pages read with the same :data:`~api.deps.ReadAccess` dependency as the JSON
endpoints. Nothing is fetched from elsewhere: the only scripts are inline, and
plotly.js is embedded (:func:`stage.report.figures.plotly_js`) only on pages with
a figure. The pages are left out of the OpenAPI schema (they are not API).
"""

from __future__ import annotations

import datetime as _dt
import html
import json
import logging
import os
import threading
import uuid
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import APIRouter
from fastapi.responses import HTMLResponse

from api.deps import JobId, LibraryDep, ReadAccess, SettingsDep, StoreDep, TakeId
from api.errors import NotFoundError
from api.jobs.store import JobNotFoundError, JobRecord
from api.paths import inside

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

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;color:#222;background:#fafafa}
header{background:#263238;color:#fff;padding:12px 24px} header h1{margin:0;font-size:20px}
header a{color:#b3e5fc} nav{padding:6px 24px;background:#eceff1;font-size:14px} nav a{margin-right:14px;color:#1565c0}
section{background:#fff;margin:14px 24px;padding:10px 18px;border-radius:6px;box-shadow:0 1px 3px rgba(0,0,0,.12)}
h2{font-size:17px;margin:8px 0} table{border-collapse:collapse;font-size:13px;margin:6px 0}
td,th{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top} th{background:#f5f5f5}
.muted{color:#777;font-size:13px} .err{color:#b71c1c;white-space:pre-wrap}
progress{width:180px;height:14px;vertical-align:middle}
.state-done{color:#2e7d32} .state-failed{color:#b71c1c} .state-cancelled{color:#777} .state-running{color:#1565c0}
.thumbs{display:flex;flex-wrap:wrap;gap:6px} .thumbs figure{margin:0;font-size:12px;text-align:center}
.thumbs img{width:160px;height:auto;border:1px solid #ccc;display:block;background:#eee}
"""


# --------------------------------------------------------------------------- helpers


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _when(ts: float | None) -> str:
    if ts is None:
        return "–"
    return _dt.datetime.fromtimestamp(float(ts), _dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def _page(title: str, body: str, *, head: str = "", status_code: int = 200) -> HTMLResponse:
    """A full page: header, navigation, ``body``; ``head`` goes into ``<head>`` (inline scripts only)."""
    page = (
        "<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>{_e(title)} · capture-stage</title><style>{_CSS}</style>{head}</head><body>"
        f"<header><h1>{_e(title)}</h1></header>"
        "<nav><a href=\"/\">home</a><a href=\"/ui/takes\">takes</a><a href=\"/ui/jobs\">jobs</a>"
        "<a href=\"/docs\">API docs</a></nav>"
        f"{body}</body></html>"
    )
    return HTMLResponse(page, status_code=status_code, headers={"Cache-Control": "no-store"})


def _not_found(message: str) -> HTMLResponse:
    return _page("Not found", f"<section><p>{_e(message)}</p></section>", status_code=404)


def _plotly_head() -> str:
    from stage.report.figures import plotly_js

    return "<script type=\"text/javascript\">" + plotly_js().replace("</script", "<\\/script") + "</script>"


def _script(js: str) -> str:
    return "<script>" + js.replace("</script", "<\\/script") + "</script>"


def _json_js(value: Any) -> str:
    """A JSON value safe inside an inline ``<script>``."""
    return json.dumps(value).replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


# --------------------------------------------------------------------------- index


@router.get("/", response_class=HTMLResponse)
def index(_: ReadAccess) -> HTMLResponse:
    """Links to the viewer pages and the API."""
    body = (
        "<section><h2>capture-stage</h2><ul>"
        "<li><a href=\"/ui/takes\">Takes</a>: cameras, frames and masks, calibration frusta</li>"
        "<li><a href=\"/ui/jobs\">Jobs</a>: live progress and reports</li>"
        "<li><a href=\"/docs\">API documentation</a> (OpenAPI) · <a href=\"/health\">health</a></li>"
        "</ul></section>"
    )
    return _page("capture-stage", body)


# --------------------------------------------------------------------------- takes


def _safe_info(library, take_id: str) -> dict[str, Any] | None:
    try:
        return library.info(take_id)
    except (NotFoundError, ValueError, OSError) as exc:
        log.warning("take %s cannot be described: %s", take_id, exc)
        return None


@router.get("/ui/takes", response_class=HTMLResponse)
def takes_page(library: LibraryDep, _: ReadAccess) -> HTMLResponse:
    """The takes of the data root with their cameras and frame counts."""
    rows = []
    for t in library.list():
        info = _safe_info(library, t["id"])
        if info is None:
            rows.append(f"<tr><td><a href=\"/ui/takes/{_e(t['id'])}\">{_e(t['id'])}</a></td>"
                        f"<td colspan=\"4\" class=\"err\">not a readable take</td></tr>")
            continue
        cams = [c.get("id") for c in info.get("cameras") or []]
        rows.append(
            f"<tr><td><a href=\"/ui/takes/{_e(t['id'])}\">{_e(t['id'])}</a></td>"
            f"<td>{len(cams)}: {_e(', '.join(map(str, cams)))}</td><td>{_e(info.get('frames'))}</td>"
            f"<td>{'yes' if info.get('calibration') else 'no'}</td>"
            f"<td>{len(info.get('masks') or [])}</td><td>{t['size_bytes'] / 1e6:.1f} MB</td></tr>"
        )
    if rows:
        body = ("<section><table><tr><th>take</th><th>cameras</th><th>frames</th><th>calibrated</th>"
                "<th>cameras with masks</th><th>size</th></tr>" + "".join(rows) + "</table></section>")
    else:
        body = "<section><p class=\"muted\">No takes yet: capture one or import it (<code>PUT /takes/{id}</code>).</p></section>"
    return _page("Takes", body)


def _frame_sets(n: int, k: int) -> list[int]:
    if n <= 0:
        return []
    return sorted(set(np.linspace(0, n - 1, min(n, k)).round().astype(int).tolist()))


@router.get("/ui/takes/{take_id}", response_class=HTMLResponse)
def take_page(take_id: TakeId, library: LibraryDep, store: StoreDep, _: ReadAccess) -> HTMLResponse:
    """One take: its cameras as frusta (when calibrated), and a few frames and masks per camera."""
    try:
        info = library.info(take_id)
    except NotFoundError as exc:
        return _not_found(str(exc))
    cams = info.get("cameras") or []
    masks = set(info.get("masks") or [])
    n = int(info.get("frames") or 0)
    rows = [["frames (sets)", n], ["fps", info.get("fps")], ["duration (s)", info.get("duration_s")],
            ["complete", info.get("complete")], ["compression", info.get("compression")]]
    summary = "<table>" + "".join(f"<tr><th>{_e(k)}</th><td>{_e('–' if v is None else v)}</td></tr>"
                                  for k, v in rows) + "</table>"
    cam_rows = "".join(f"<tr><td>{_e(c.get('id'))}</td><td>{_e(c.get('frames'))}</td>"
                       f"<td>{_e(c.get('width', ''))}x{_e(c.get('height', ''))}</td>"
                       f"<td>{'yes' if c.get('id') in masks else 'no'}</td></tr>" for c in cams)
    summary += ("<table><tr><th>camera</th><th>frames</th><th>size</th><th>masks</th></tr>" + cam_rows + "</table>")
    sections = [f"<section id=\"summary\"><h2>Take {_e(take_id)}</h2>{summary}</section>"]

    head = ""
    if info.get("calibration"):
        from calib.calibration import Calibration
        from stage.report.figures import figure_html, frusta_figure

        try:
            cal = Calibration.from_dict(info["calibration"])
            fig = frusta_figure(cal)
            sections.append("<section id=\"cameras\"><h2>Cameras (calibration)</h2>"
                            "<p class=\"muted\">Drag to rotate, scroll to zoom.</p>"
                            + figure_html(fig, div_id="frusta") + "</section>")
            head = _plotly_head()
        except (ValueError, KeyError, TypeError) as exc:
            sections.append(f"<section id=\"cameras\"><h2>Cameras</h2><p class=\"err\">the calibration cannot be "
                            f"shown: {_e(exc)}</p></section>")
    else:
        sections.append("<section id=\"cameras\"><h2>Cameras</h2><p class=\"muted\">The take has no calibration.</p></section>")

    sets = _frame_sets(n, TAKE_PAGE_FRAMES)
    thumbs = []
    for c in cams[:TAKE_PAGE_CAMERAS]:
        cid = str(c.get("id"))
        figs = []
        for k in sets:
            base = f"/takes/{_e(take_id)}/frames/{k}/{_e(cid)}"
            figs.append(f"<figure><img loading=\"lazy\" src=\"{base}/image.jpg\" alt=\"{_e(cid)} frame {k}\">"
                        f"<figcaption>frame {k}</figcaption></figure>")
            if cid in masks:
                figs.append(f"<figure><img loading=\"lazy\" src=\"{base}/mask.png\" alt=\"{_e(cid)} mask {k}\">"
                            f"<figcaption>mask {k}</figcaption></figure>")
        thumbs.append(f"<h3>{_e(cid)}</h3><div class=\"thumbs\">{''.join(figs)}</div>")
    more = (f"<p class=\"muted\">{len(cams) - TAKE_PAGE_CAMERAS} more camera(s) not shown.</p>"
            if len(cams) > TAKE_PAGE_CAMERAS else "")
    sections.append(f"<section id=\"frames\"><h2>Frames and masks</h2>"
                    f"<p class=\"muted\">Frame sets {', '.join(map(str, sets)) or '–'}.</p>{''.join(thumbs)}{more}</section>")

    jobs = store.list(take=take_id, limit=20)
    if jobs:
        sections.append("<section id=\"jobs\"><h2>Jobs on this take</h2>" + _jobs_table(jobs) + "</section>")
    return _page(f"Take {take_id}", "".join(sections), head=head)


# --------------------------------------------------------------------------- jobs


def _bar(done: int, total: int, *, attr: str = "") -> str:
    total = max(int(total or 0), 0)
    return (f"<progress {attr} max=\"{max(total, 1)}\" value=\"{min(int(done or 0), max(total, 1))}\"></progress> "
            f"<span class=\"count\">{int(done or 0)}/{total}</span>")


def _jobs_table(jobs: list[JobRecord]) -> str:
    rows = []
    for j in jobs:
        report = (f"<a href=\"/ui/jobs/{j.id}/report\">report</a>" if j.kind == "process" and j.state == "done" else "")
        rows.append(
            f"<tr data-job=\"{j.id}\"><td><a href=\"/ui/jobs/{j.id}\">{j.id[:8]}</a></td><td>{_e(j.kind)}</td>"
            f"<td><a href=\"/ui/takes/{_e(j.take)}\">{_e(j.take)}</a></td>"
            f"<td class=\"state state-{_e(j.state)}\">{_e(j.state)}</td>"
            f"<td class=\"bar\">{_bar(j.done, j.total)}</td><td>{_when(j.created)}</td>"
            f"<td class=\"report\">{report}</td></tr>"
        )
    return ("<table id=\"jobs\"><tr><th>job</th><th>kind</th><th>take</th><th>state</th><th>progress</th>"
            "<th>created</th><th></th></tr>" + "".join(rows) + "</table>")


# polls /jobs every second while a listed job is active, updating states and bars
_JOBS_JS = """
(function(){
  const TERMINAL = ["done", "failed", "cancelled"];
  function update(jobs){
    let active = false;
    for (const j of jobs){
      const tr = document.querySelector('tr[data-job="' + j.id + '"]');
      if (!tr) continue;
      const st = tr.querySelector('.state');
      st.textContent = j.state; st.className = 'state state-' + j.state;
      const bar = tr.querySelector('progress');
      bar.max = Math.max(j.total, 1); bar.value = Math.min(j.done, bar.max);
      tr.querySelector('.count').textContent = j.done + '/' + j.total;
      if (j.state === 'done' && j.kind === 'process'){
        const r = tr.querySelector('.report');
        if (!r.firstChild){ const a = document.createElement('a'); a.href = '/ui/jobs/' + j.id + '/report';
                            a.textContent = 'report'; r.appendChild(a); }
      }
      if (!TERMINAL.includes(j.state)) active = true;
    }
    return active;
  }
  async function poll(){
    try {
      const r = await fetch('/jobs?limit=' + LIMIT, {headers: {'Accept': 'application/json'}});
      if (r.ok && !update(await r.json())) return;
    } catch (e) {}
    setTimeout(poll, 1000);
  }
  if (document.querySelector('tr[data-job]')) setTimeout(poll, 1000);
})();
"""


@router.get("/ui/jobs", response_class=HTMLResponse)
def jobs_page(store: StoreDep, _: ReadAccess) -> HTMLResponse:
    """All jobs (newest first) with live progress."""
    limit = 200
    jobs = store.list(limit=limit)
    if not jobs:
        body = "<section><p class=\"muted\">No jobs yet (<code>POST /jobs</code>).</p></section>"
        return _page("Jobs", body)
    body = ("<section>" + _jobs_table(jobs) + "</section>"
            + _script(f"const LIMIT = {limit};" + _JOBS_JS))
    return _page("Jobs", body)


# follows one job: polls /jobs/{id} every second until it is finished
_JOB_JS = """
(function(){
  const TERMINAL = ["done", "failed", "cancelled"];
  function render(j){
    const st = document.getElementById('state');
    st.textContent = j.state + (j.cancel_requested && !TERMINAL.includes(j.state) ? ' (cancel requested)' : '');
    st.className = 'state state-' + j.state;
    const all = document.getElementById('bar-all');
    all.max = Math.max(j.total, 1); all.value = Math.min(j.done, all.max);
    document.getElementById('count-all').textContent = j.done + '/' + j.total;
    const tbody = document.getElementById('steps');
    for (const [step, p] of Object.entries(j.progress || {})){
      let tr = tbody.querySelector('tr[data-step="' + CSS.escape(step) + '"]');
      if (!tr){
        tr = document.createElement('tr'); tr.dataset.step = step;
        const td0 = document.createElement('td'); td0.textContent = step;
        const td1 = document.createElement('td'); const bar = document.createElement('progress');
        const sp = document.createElement('span'); sp.className = 'count';
        td1.appendChild(bar); td1.appendChild(document.createTextNode(' ')); td1.appendChild(sp);
        tr.appendChild(td0); tr.appendChild(td1); tbody.appendChild(tr);
      }
      const bar = tr.querySelector('progress');
      bar.max = Math.max(p.total, 1); bar.value = Math.min(p.done, bar.max);
      tr.querySelector('.count').textContent = p.done + '/' + p.total;
    }
    document.getElementById('attempts').textContent = j.attempts;
    for (const k of ['started', 'finished'])
      if (j[k]) document.getElementById(k).textContent = new Date(j[k] * 1000).toISOString().slice(0, 19).replace('T', ' ') + ' UTC';
    const err = document.getElementById('error');
    err.textContent = j.error || '';
    if (j.state === 'done' && j.kind === 'process') document.getElementById('report').hidden = false;
    return !TERMINAL.includes(j.state);
  }
  async function poll(){
    try {
      const r = await fetch('/jobs/' + JOB_ID, {headers: {'Accept': 'application/json'}});
      if (r.ok && !render(await r.json())) return;
    } catch (e) {}
    setTimeout(poll, 1000);
  }
  if (!TERMINAL.includes(INITIAL_STATE)) setTimeout(poll, 1000);
})();
"""


@router.get("/ui/jobs/{job_id}", response_class=HTMLResponse)
def job_page(job_id: JobId, store: StoreDep, _: ReadAccess) -> HTMLResponse:
    """One job: state, progress per step (live), error, links to its results and report."""
    try:
        j = store.get(job_id)
    except JobNotFoundError as exc:
        return _not_found(str(exc))
    steps = "".join(f"<tr data-step=\"{_e(s)}\"><td>{_e(s)}</td><td>{_bar(p.get('done', 0), p.get('total', 0))}</td></tr>"
                    for s, p in (j.progress or {}).items())
    rows = [("kind", _e(j.kind)), ("take", f"<a href=\"/ui/takes/{_e(j.take)}\">{_e(j.take)}</a>"),
            ("steps", _e(", ".join(j.steps))),
            ("state", f"<span id=\"state\" class=\"state state-{_e(j.state)}\">{_e(j.state)}</span>"),
            ("progress", _bar(j.done, j.total, attr="id=\"bar-all\"").replace("class=\"count\"", "class=\"count\" id=\"count-all\"")),
            ("attempts", f"<span id=\"attempts\">{j.attempts}</span>"),
            ("created", _when(j.created)), ("started", f"<span id=\"started\">{_when(j.started)}</span>"),
            ("finished", f"<span id=\"finished\">{_when(j.finished)}</span>"),
            ("parameters", _e(json.dumps(j.params)) if j.params else "–")]
    table = "<table>" + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"
    links = (f"<p><a id=\"report\" href=\"/ui/jobs/{j.id}/report\"{'' if j.state == 'done' else ' hidden'}>"
             f"open the report</a></p>" if j.kind == "process" else "")
    if j.kind == "process":
        links += (f"<p class=\"muted\">Results: <a href=\"/jobs/{j.id}/results/\">listing</a> · "
                  f"<a href=\"/jobs/{j.id}/results/spine.json\">spine.json</a> · "
                  f"<a href=\"/jobs/{j.id}/results/spine_rig.glb\">spine_rig.glb</a> · "
                  f"<a href=\"/jobs/{j.id}/events\">progress events</a></p>")
    body = (f"<section><h2>Job {j.id}</h2>{table}"
            f"<h3>Steps</h3><table><tbody id=\"steps\">{steps}</tbody></table>"
            f"<p id=\"error\" class=\"err\">{_e(j.error or '')}</p>{links}</section>"
            + _script(f"const JOB_ID = {_json_js(j.id)}; const INITIAL_STATE = {_json_js(j.state)};" + _JOB_JS))
    return _page(f"Job {j.id[:8]}", body)


def _report_html(job: JobRecord, job_dir: Path, take: Path | None) -> str:
    """The cached report of a finished job, (re)rendered when missing or older than its inputs."""
    from stage.report import render_report

    cache = job_dir / REPORT_CACHE
    inputs = [p for p in (job_dir / "spine.json", job_dir / "report.json") if p.is_file()]
    newest = max((p.stat().st_mtime for p in inputs), default=0.0)
    with _report_lock:
        if cache.is_file() and cache.stat().st_mtime >= newest:
            return cache.read_text(encoding="utf-8")
        page = render_report(job_dir, take=take)
        tmp = job_dir / f".{REPORT_CACHE}.{uuid.uuid4().hex}.part"
        try:
            tmp.write_text(page, encoding="utf-8")
            os.replace(tmp, cache)
        finally:
            tmp.unlink(missing_ok=True)
        return page


@router.get("/ui/jobs/{job_id}/report", response_class=HTMLResponse)
def job_report(job_id: JobId, store: StoreDep, library: LibraryDep, settings: SettingsDep,
               _: ReadAccess) -> HTMLResponse:
    """The HTML report of a finished processing job (plotly.js embedded; cached in the job's folder)."""
    from stage.report import NothingToReportError

    try:
        j = store.get(job_id)
    except JobNotFoundError as exc:
        return _not_found(str(exc))
    if j.kind != "process":
        return _not_found(f"job {j.id} is a {j.kind} job: it has no report")
    if j.state != "done":
        return _not_found(f"job {j.id} is {j.state}: the report exists once it is done")
    job_dir = inside(settings.jobs_dir, j.id)
    if not job_dir.is_dir():
        return _not_found(f"job {j.id} has no results")
    try:
        take = library.path(j.take)
    except (NotFoundError, ValueError):
        take = None  # deleted since: a report without contact sheets
    try:
        page = _report_html(j, job_dir, take)
    except NothingToReportError:
        return _not_found(f"job {j.id} has no spine.json or report.json")
    return HTMLResponse(page, headers={"Cache-Control": "no-cache"})
