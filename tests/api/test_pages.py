"""Viewer pages (api/routers/pages.py): 200 HTML for valid ids, 404 for unknown ones, ids validated,
read protection respected, nothing fetched from elsewhere (the pages work offline)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.routers.pages import REPORT_CACHE
from tests.api import fakework
from tests.api.conftest import AUTH, make_settings
from tests.api.fakework import make_take_file, ring_calibration

UNKNOWN_JOB = "0" * 32
# an external resource: <script src=http...>, <link href=http...>, <img src=http...>, CSS url(http...)
_EXTERNAL = re.compile(r"<(?:script|link|img|iframe|source)\b[^>]*\b(?:src|href)\s*=\s*[\"']?\s*(?:https?:)?//"
                       r"|url\(\s*[\"']?\s*(?:https?:)?//", re.I)


def _report_json(d: Path) -> None:
    d.mkdir(parents=True, exist_ok=True)
    (d / "report.json").write_text(json.dumps({
        "frames": 4, "tip_counts": [5, 4, 5, 5], "total_seconds": 1.5,
        "per_frame": [{"index": i, "status": "ok", "vertices": 100 + i, "faces": 196 + 2 * i, "watertight": True}
                      for i in range(4)],
    }))


@pytest.fixture
def app_factory(tmp_path):
    """``make(**settings) -> (TestClient, data root)``: takes ``cal`` (calibrated, masks) and ``plain``; no runner."""
    made = []

    def make(**kw):
        data = tmp_path / f"data{len(made)}"
        (data / "takes").mkdir(parents=True)
        make_take_file(data / "takes" / "cal.h5", 5, cameras=3, calibration=ring_calibration(3), masks=True)
        make_take_file(data / "takes" / "plain.h5", 2)
        app = create_app(make_settings(data, **kw), work=fakework.process_take, start_runner=False)
        c = TestClient(app, raise_server_exceptions=False)
        c.__enter__()
        made.append(c)
        return c, data

    yield make
    for c in made:
        c.__exit__(None, None, None)


@pytest.fixture
def client_data(app_factory):
    return app_factory()


def _jobs(client: TestClient, data: Path) -> dict[str, str]:
    """Jobs in every interesting state: queued, running (with progress), done (with results), failed, calibrate."""
    store = client.app.state.store
    ids = {}
    ids["queued"] = store.create(kind="process", take="cal", steps=["key"], params={}).id
    rid = store.create(kind="process", take="cal", steps=["key", "surface"], params={"salt": "<b>x</b>"}).id
    store.progress(rid, "key", 3, 5)
    store._con().execute("UPDATE jobs SET state = 'running' WHERE id = ?", (rid,))
    ids["running"] = rid
    did = store.create(kind="process", take="cal", steps=["spine"], params={}).id
    _report_json(data / "jobs" / did)
    store.finish(did, "done")
    ids["done"] = did
    fid = store.create(kind="process", take="plain", steps=["key"], params={}).id
    store.finish(fid, "failed", error="<script>alert(1)</script> went wrong")
    ids["failed"] = fid
    cid = store.create(kind="calibrate", take="cal", steps=["calibrate"], params={}).id
    store.finish(cid, "done")
    ids["calibrate"] = cid
    return ids


def _html(r) -> str:
    assert r.status_code == 200, (r.status_code, r.text[:300])
    assert r.headers["content-type"].startswith("text/html")
    text = r.text
    assert text.startswith("<!DOCTYPE html>")
    assert not _EXTERNAL.search(text), _EXTERNAL.search(text).group(0)
    return text


def _result_hrefs(client: TestClient, page: str, job_id: str) -> list[str]:
    """The links of a job's page to its result files (not the listing), each checked to answer 200."""
    hrefs = re.findall(rf'href="(/jobs/{job_id}/results/[^"]+)"', page)
    for href in hrefs:
        assert client.get(href).status_code == 200, href
    return hrefs


def test_index_and_takes(client_data):
    client, _ = client_data
    page = _html(client.get("/"))
    for link in ("/ui/takes", "/ui/jobs", "/docs"):
        assert f'href="{link}"' in page
    page = _html(client.get("/ui/takes"))
    assert 'href="/ui/takes/cal"' in page and 'href="/ui/takes/plain"' in page
    assert "cam00, cam01, cam02" in page
    assert "Plotly" not in page  # no figure, no plotly.js


def test_take_page_with_calibration(client_data):
    client, _ = client_data
    page = _html(client.get("/ui/takes/cal"))
    assert 'id="frusta"' in page and "Plotly.newPlot" in page
    assert "cam02" in page and page.count("<script") >= 2
    srcs = re.findall(r'<img[^>]*src="([^"]+)"', page)
    # 3 frame sets x 3 cameras, images and masks
    assert len([s for s in srcs if s.endswith("/image.jpg")]) == 9
    assert len([s for s in srcs if s.endswith("/mask.png")]) == 9
    for s in srcs:
        assert s.startswith("/takes/cal/frames/")
        r = client.get(s)
        assert r.status_code == 200 and r.headers["content-type"].startswith("image/"), s


def test_take_page_without_calibration(client_data):
    client, _ = client_data
    page = _html(client.get("/ui/takes/plain"))
    assert "has no calibration" in page and "Plotly" not in page
    srcs = re.findall(r'<img[^>]*src="([^"]+)"', page)
    assert srcs and not [s for s in srcs if "mask" in s]  # no masks in this take


def test_jobs_pages(client_data):
    client, data = client_data
    ids = _jobs(client, data)
    page = _html(client.get("/ui/jobs"))
    for jid in ids.values():
        assert f'data-job="{jid}"' in page
    # every job's bar has a name a screen reader says (each row's own)
    bars = re.findall(r"<progress[^>]*>", page)
    assert len(bars) == len(ids) and all(f'aria-label="job {jid[:8]}&#39;s progress"' in page for jid in ids.values())
    assert f'href="/ui/jobs/{ids["done"]}/report"' in page
    assert f'href="/ui/jobs/{ids["queued"]}/report"' not in page
    assert "setTimeout(poll, 1000)" in page and "fetch('/jobs?limit=" in page

    page = _html(client.get(f"/ui/jobs/{ids['running']}"))
    assert '<progress id="bar-all" aria-label="the job&#39;s progress" max="5" value="3">' in page
    assert "/results/spine" not in page  # a job without the spine step has no spine to download
    assert 'data-step="key"' in page and "fetch('/jobs/' + JOB_ID" in page
    assert f'const JOB_ID = "{ids["running"]}"' in page
    assert "&lt;b&gt;x&lt;/b&gt;" in page and "<b>x</b>" not in page  # parameters escaped
    assert f'id="report" href="/ui/jobs/{ids["running"]}/report" hidden' in page
    page = _html(client.get(f"/ui/jobs/{ids['failed']}"))
    assert "&lt;script&gt;alert(1)&lt;/script&gt; went wrong" in page and "<script>alert(1)" not in page
    page = _html(client.get(f"/ui/jobs/{ids['done']}"))
    assert f'id="report" href="/ui/jobs/{ids["done"]}/report">' in page
    # what the job wrote (its report.json), not what its spine step would have written (spine.json: 404)
    assert _result_hrefs(client, page, ids["done"]) == [f"/jobs/{ids['done']}/results/report.json"]
    assert '<p id="unwritten" class="err" hidden></p>' in page
    # (a failed job's key step writes the take's masks, not its folder's)
    assert '<p id="unwritten" class="err" hidden></p>' in _html(client.get(f"/ui/jobs/{ids['failed']}"))
    # a job that failed after its surfaces: every one of them linked, in a collapsed list saying how many (frame set
    # 1 has none: no link), its track and rig steps said to have written nothing (their files, 404, not linked)
    store = client.app.state.store
    rig = store.create(kind="process", take="cal", steps=["surface", "track", "rig"], params={}).id
    (data / "jobs" / rig / "meshes").mkdir(parents=True)
    for i in (0, 2, 3):
        (data / "jobs" / rig / "meshes" / f"frame_00000{i}.ply").write_bytes(b"ply\n")
    store.finish(rig, "failed", error="stopped")
    page = _html(client.get(f"/ui/jobs/{rig}"))
    meshes = [f"/jobs/{rig}/results/meshes/frame_00000{i}.ply" for i in (0, 2, 3)]
    assert _result_hrefs(client, page, rig) == meshes
    assert ('<details data-key="meshes" data-frames="0,2,3"><summary>surface meshes (3 frame sets)</summary>'
            f'<p class="frames"><a href="{meshes[0]}" title="frame set 0">0</a> ') in page
    assert client.get(f"/jobs/{rig}/results/rig/rig.glb").status_code == 404
    assert '<p id="unwritten" class="err">The job failed: the track and rig steps wrote nothing.</p>' in page
    assert client.get(f"/jobs/{rig}/results/").json()["written_by"] == ["surface"]
    # once the armature's files are there (docs/armature-format.md), they are linked, and no step is said unwritten
    (data / "jobs" / rig / "rig").mkdir()
    for name in ("rig.glb", "rig.bvh"):
        (data / "jobs" / rig / "rig" / name).write_bytes(b"x")
    (data / "jobs" / rig / "tracked").mkdir()
    (data / "jobs" / rig / "tracked" / "000000.ply").write_bytes(b"ply\n")
    page = _html(client.get(f"/ui/jobs/{rig}"))
    assert _result_hrefs(client, page, rig) == [f"/jobs/{rig}/results/{n}" for n in (
        "rig/rig.glb", "rig/rig.bvh")] + meshes + [f"/jobs/{rig}/results/tracked/000000.ply"]
    assert "<summary>tracked meshes (1 frame set)</summary>" in page
    assert '<a href="/jobs/{rig}/results/rig/rig.glb">rig/rig.glb</a>'.format(rig=rig) in page
    assert '<p id="unwritten" class="err" hidden></p>' in page
    assert client.get(f"/jobs/{rig}/results/").json()["written_by"] == ["surface", "track", "rig"]
    # a cancelled job that had written nothing; one step said alone
    for steps, said in ((["surface", "spine"], "The job was cancelled: the surface and spine steps wrote nothing."),
                        (["rig"], "The job was cancelled: the rig step wrote nothing.")):
        jid = store.create(kind="process", take="cal", steps=steps, params={}).id
        store.finish(jid, "cancelled")
        page = _html(client.get(f"/ui/jobs/{jid}"))
        assert _result_hrefs(client, page, jid) == [] and f'<p id="unwritten" class="err">{said}</p>' in page
    # the page's own status endpoint exists and says what the script reads
    st = client.get(f"/jobs/{ids['running']}").json()
    assert st["done"] == 3 and st["total"] == 5 and st["progress"]["key"] == {"done": 3, "total": 5, "step": "key"}


def _step_rows(page: str) -> list[tuple[str, str | None, str]]:
    """The job page's steps table: ``(group, entry, what its progress cell says)`` per row, in order; ``entry``
    None for a step's own row that is not an entry's."""
    table = page.split('<table id="steps"', 1)[1].split("</table>", 1)[0]
    rows = []
    for group, body in re.findall(r'<tbody data-group="([^"]*)">(.*?)</tbody>', table, re.S):
        for entry, cell in re.findall(r'<tr class="(?:step|part)"(?: data-step="([^"]*)")?><th [^>]*>[^<]*</th>'
                                      r'<td[^>]*>(.*?)</td></tr>', body, re.S):
            rows.append((group, entry or None, re.sub(r"<[^>]+>", "", cell).strip()))
    return rows


def test_job_page_lists_each_step_with_its_progress_entries(client_data):
    """One list of steps: each step the job asked for (or ran) with the progress entries the pipeline announced
    for it indented under it (a step whose one entry is itself, one row; its own row the sum of its entries), a
    step asked that reported nothing said so; an entry kept without its step (an older record's) is a step of its
    own. The page's layout key is the one job.js computes from the job's record."""
    client, _ = client_data
    store = client.app.state.store
    jid = store.create(kind="process", take="cal", steps=["key", "surface", "track", "rig"], params={}).id
    for name, step, done, total in (("key", "key", 15, 15), ("box", "surface", 5, 5), ("surface", "surface", 4, 5),
                                    ("refine", "refine", 5, 5), ("track", "track", 5, 5),
                                    ("track with the rig round 1", "track", 2, 5)):
        store.progress(jid, name, done, total, of_step=step)
    store.finish(jid, "failed", error="rig: stopped")
    page = _html(client.get(f"/ui/jobs/{jid}"))
    assert _step_rows(page) == [
        ("key", "key", "15/15"),
        ("surface", None, "9/10"), ("surface", "box", "5/5"), ("surface", "surface", "4/5"),
        ("refine", "refine", "5/5"),  # (ran for the key step, asked or not)
        ("track", None, "7/10"), ("track", "track", "5/5"), ("track", "track with the rig round 1", "2/5"),
        ("rig", None, "no progress reported")]
    assert "<th>steps</th>" not in page  # (the steps are said once, in the table)
    assert '<th scope="col">step</th><th scope="col">progress</th>' in page
    assert '<th scope="rowgroup">track</th><td><progress aria-label="the track step" max="10" value="7">' in page
    assert '<th scope="row">box</th><td><progress aria-label="box (surface step)" max="5" value="5">' in page
    key = json.dumps([[n, e["step"]] for n, e in client.get(f"/jobs/{jid}").json()["progress"].items()],
                     separators=(",", ":"))
    assert f'data-key="{key.replace(chr(34), "&#34;")}"' in page
    # a queued job: its steps asked, none reported yet; an entry without its step, a step of its own
    qid = store.create(kind="process", take="cal", steps=["surface", "spine"], params={}).id
    assert _step_rows(_html(client.get(f"/ui/jobs/{qid}"))) == [("surface", None, "no progress reported"),
                                                                 ("spine", None, "no progress reported")]
    store._con().execute("UPDATE jobs SET progress = ? WHERE id = ?",
                         (json.dumps({"box": {"done": 1, "total": 2}, "spine": {"done": 0, "total": 1, "step": "spine"}}),
                          qid))
    assert _step_rows(_html(client.get(f"/ui/jobs/{qid}"))) == [
        ("surface", None, "no progress reported"), ("box", "box", "1/2"), ("spine", "spine", "0/1")]


def test_take_page_lists_its_jobs(client_data):
    client, data = client_data
    ids = _jobs(client, data)
    page = _html(client.get("/ui/takes/cal"))
    assert f'href="/ui/jobs/{ids["done"]}"' in page and f'data-job="{ids["failed"]}"' not in page


def test_report_is_rendered_and_cached(client_data):
    client, data = client_data
    ids = _jobs(client, data)
    url = f"/ui/jobs/{ids['done']}/report"
    page = _html(client.get(url))
    assert 'id="tip-counts"' in page and "Plotly.newPlot" in page
    assert "frusta" in page  # the take (with its calibration) was found for the report
    assert str(data) not in page and str(data.resolve()) not in page  # the server's paths: DATA/...
    cache = data / "jobs" / ids["done"] / REPORT_CACHE
    assert cache.read_text(encoding="utf-8") == page
    # served from the cache while the results do not change ...
    cache.write_text(page.replace("</body>", "<!-- cached --></body>"), encoding="utf-8")
    assert "<!-- cached -->" in _html(client.get(url))
    # ... and rendered again when they do
    rep = data / "jobs" / ids["done"] / "report.json"
    import os

    st = cache.stat()
    os.utime(rep, (st.st_mtime + 5, st.st_mtime + 5))
    assert "<!-- cached -->" not in _html(client.get(url))


def test_unknown_ids_are_404(client_data):
    client, data = client_data
    ids = _jobs(client, data)
    for url in ("/ui/takes/nope", f"/ui/jobs/{UNKNOWN_JOB}", f"/ui/jobs/{UNKNOWN_JOB}/report",
                f"/ui/jobs/{ids['queued']}/report", f"/ui/jobs/{ids['running']}/report",
                f"/ui/jobs/{ids['failed']}/report", f"/ui/jobs/{ids['calibrate']}/report"):
        r = client.get(url)
        assert r.status_code == 404, (url, r.status_code)
        assert r.headers["content-type"].startswith("text/html") and "Not found" in r.text, url
    # a done job whose results folder has vanished
    import shutil

    shutil.rmtree(data / "jobs" / ids["done"])
    assert client.get(f"/ui/jobs/{ids['done']}/report").status_code == 404


@pytest.mark.parametrize("url", [
    "/ui/takes/..%2F..%2Fetc%2Fpasswd", "/ui/takes/%2E%2E", "/ui/takes/.hidden", "/ui/takes/a%00b",
    "/ui/takes/" + "a" * 200, "/ui/jobs/..%2Fjobs.sqlite", "/ui/jobs/ABCDEF0123456789ABCDEF0123456789",
    "/ui/jobs/not-a-job/report", "/ui/jobs/%2E%2E%2F%2E%2E/report", "/ui/takes/../../etc/passwd",
])
def test_path_traversal_is_rejected(client_data, url):
    client, _ = client_data
    r = client.get(url)
    assert r.status_code in (400, 404), (url, r.status_code)
    assert "root:" not in r.text and "SQLite" not in r.text


def test_read_protection(app_factory):
    client, data = app_factory(read_protected=True)
    ids = _jobs(client, data)
    urls = ["/", "/ui/takes", "/ui/takes/cal", "/ui/jobs", f"/ui/jobs/{ids['done']}", f"/ui/jobs/{ids['done']}/report"]
    for url in urls:
        assert client.get(url).status_code == 401, url
        assert client.get(url, headers={"Authorization": "Bearer wrong"}).status_code == 403, url
        assert client.get(url, headers=AUTH).status_code == 200, url
    # open reading (the default): no token needed
    client, _ = app_factory()
    assert client.get("/ui/takes").status_code == 200


def test_pages_are_not_in_the_openapi_schema(client_data):
    client, _ = client_data
    paths = client.get("/openapi.json").json()["paths"]
    assert not [p for p in paths if p == "/" or p.startswith("/ui")]


def test_a_calibration_jobs_page_links_what_it_made(client_data):
    """A calibration job's page links its calibration in each format once it is saved (its id is the job's) and its
    report.json once written, each answering 200; before, and for a job that made none, it says so and links
    nothing; a running one's page loads itself again when the job ends (job.js)."""
    from api.calibrations import CalibrationLibrary
    from tests.api.fakework import small_calibration

    client, data = client_data
    store, settings = client.app.state.store, client.app.state.settings
    cid = store.create(kind="calibrate", take="cal", steps=["calibrate"], params={}).id
    store._con().execute("UPDATE jobs SET state = 'running' WHERE id = ?", (cid,))
    page = _html(client.get(f"/ui/jobs/{cid}"))
    assert '<span id="no-calibration">none yet</span>' in page and "location.reload()" in page
    assert not re.findall(r'href="(/calibrations/[^"]+)"', page)
    store.finish(cid, "failed", error="could not connect every camera")
    assert '<span id="no-calibration">none</span>' in _html(client.get(f"/ui/jobs/{cid}"))
    CalibrationLibrary(settings.calibrations_dir).save(small_calibration(2), cid)
    (data / "jobs" / cid).mkdir(parents=True)
    (data / "jobs" / cid / "report.json").write_text("{}")
    page = _html(client.get(f"/ui/jobs/{cid}"))
    hrefs = re.findall(r'<a href="(/calibrations/[^"]+|/jobs/[^"]+/results/[^"]+)">', page)
    assert hrefs == [f"/calibrations/{cid}.{f}" for f in ("json", "toml", "yaml")] + [
        f"/jobs/{cid}/results/report.json"], hrefs
    assert all(client.get(h).status_code == 200 for h in hrefs) and 'id="no-calibration"' not in page
