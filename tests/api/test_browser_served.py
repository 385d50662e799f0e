"""A real browser on a real server: ``python -m stage serve`` processes a small simulated take over HTTP;
headless Chromium (Playwright, Debian's chromium) follows the job's live progress page, then opens the
report and the take's page from the server, waits for the plotly 3-D views and checks they are not blank;
a second job, over a take whose masks failed in some frame sets, which then fails (its rig's rest frame is past
the surfaces), lists on its page the warnings said before it failed. Each job's page links only the result files
the job wrote (each answers 200), every frame of its surfaces in a collapsed list, the failed one saying which of
its steps wrote nothing; each job's steps are one table, every step with the progress entries it reports under it,
laid out live by a page opened while the job was queued as the server lays it out; the done job's page, whose
results' listing fails twice once the job is done, says so and asks again until it has the finished job's links.

Screenshots are kept under ``$STAGE_TEST_ARTIFACTS`` (else the test's tmp dir); the path is printed.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import httpx
import pytest

from fake_cameras.record import record_take
from fake_cameras.take import simulate_take
from tests.api.served import AUTH, Server
from tests.browser import CHROMIUM, CHROMIUM_ARGS, LOW_CONTRAST, UNNAMED, not_blank, sync_playwright_or_skip
from tests.pipeline.hull_scenes import FAILED_MASKS_SAID, take_with_failed_masks

pytestmark = [pytest.mark.slow]
try:  # pytest-timeout is in the [test] extra
    import pytest_timeout  # noqa: F401

    pytestmark.append(pytest.mark.timeout(120))
except ImportError:
    pass

CAMERAS, FRAMES, SIZE = 5, 6, (320, 240)

# the plotly figure in div `id` has drawn its WebGL scene
_GL_READY = ("(id) => { const g = document.getElementById(id);"
             " return !!(g && g._fullLayout && g.querySelector('.gl-container canvas')); }")


def _artifacts(tmp_path: Path) -> Path:
    env = os.environ.get("STAGE_TEST_ARTIFACTS")
    d = Path(env) / "browser_served" if env else tmp_path / "artifacts"
    d.mkdir(parents=True, exist_ok=True)
    return d


def _take(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return record_take(simulate_take("starfish", n_cameras=CAMERAS, frames=FRAMES, size=SIZE, seed=0), path)


# the job page's steps table: (step, progress entry or None for a step's own row) per row
_STEP_ROWS = ("() => Array.from(document.querySelectorAll('#steps tbody tr'))"
              ".map(e => [e.closest('tbody').dataset.group, e.dataset.step || null])")


def _served_step_rows(url: str) -> list[list]:
    """The steps table of a job's page as the server renders it now (as _STEP_ROWS reads it)."""
    page = httpx.get(url, timeout=30).text
    table = page.split('<table id="steps"', 1)[1].split("</table>", 1)[0]
    return [[group, entry or None] for group, body in re.findall(r'<tbody data-group="([^"]*)">(.*?)</tbody>', table, re.S)
            for entry in re.findall(r'<tr class="(?:step|part)"(?: data-step="([^"]*)")?>', body)]


def _result_links(page, url: str) -> dict[str, int]:
    """The results a job's page links (its listing's files, every frame of its meshes), each with the status
    the server answers it with."""
    hrefs = page.eval_on_selector_all("#results a, #frames a", "els => els.map(e => e.getAttribute('href'))")
    return {h: httpx.get(url + h, timeout=60).status_code for h in hrefs}


def test_browser_on_served_pages(tmp_path):
    sync_playwright = sync_playwright_or_skip()  # skips with the reason when chromium or playwright is missing
    t0 = time.monotonic()
    data = tmp_path / "data"
    _take(data / "takes" / "sim.h5")
    take_with_failed_masks(data / "takes" / "failed.h5")
    art = _artifacts(tmp_path)
    srv = Server(data).start()
    try:
        r = httpx.post(f"{srv.url}/jobs", json={"take": "sim"}, headers=AUTH, timeout=30)
        assert r.status_code == 202, r.text
        jid = r.json()["id"]
        r = httpx.post(f"{srv.url}/jobs", json={"take": "failed", "steps": ["surface", "track", "rig"],
                                                "parameters": {"resolution": 32, "rig": {"reference": 5}}},
                       headers=AUTH, timeout=30)
        assert r.status_code == 202, r.text
        failed = r.json()["id"]
        errors: list[str] = []
        requests: list[str] = []
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
            try:
                page = browser.new_page(viewport={"width": 1200, "height": 900})
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.on("request", lambda q: requests.append(q.url))
                unlisted = [2]  # the listing fails twice once the job is done (the poll that sees it done, the next)

                def listing(route):
                    if unlisted[0] and httpx.get(f"{srv.url}/jobs/{jid}", timeout=10).json()["state"] == "done":
                        unlisted[0] -= 1
                        route.fulfill(status=503, body="busy")
                    else:
                        route.continue_()

                page.route(f"**/jobs/{jid}/results/", listing)
                # the job page follows the job live until it is done, then shows the report link
                page.goto(f"{srv.url}/ui/jobs/{jid}", wait_until="load", timeout=30_000)
                initial = page.text_content("#state")
                # the second job's page, opened while it waits for the first: job.js lays out its steps as they come
                live = browser.new_page(viewport={"width": 1200, "height": 900})
                live.on("pageerror", lambda e: errors.append(str(e)))
                live.goto(f"{srv.url}/ui/jobs/{failed}", wait_until="load", timeout=30_000)
                live_initial, live_rows0 = live.text_content("#state"), live.evaluate(_STEP_ROWS)
                page.evaluate("() => { window.__seen = []; new MutationObserver(() => window.__seen.push("
                              "document.getElementById('count-all').textContent)).observe("
                              "document.getElementById('count-all'), {childList: true, characterData: true, subtree: true});"
                              " window.__unlisted = []; const e = document.getElementById('results-error');"
                              " new MutationObserver(() => { if (!e.hidden) window.__unlisted.push(e.textContent); })"
                              ".observe(e, {attributes: true, childList: true, characterData: true, subtree: true}); }")
                page.wait_for_function("() => document.getElementById('state').textContent === 'done'",
                                       timeout=60_000)
                # the page asks again until the listing answers: the finished job's links, the message gone
                page.wait_for_function("() => document.getElementById('results-error').hidden"
                                       " && !!document.querySelector('#results a[href$=\"/report.json\"]')",
                                       timeout=20_000)
                unlisted_said = page.evaluate("() => window.__unlisted")
                frames_open = page.eval_on_selector_all("#frames details", "els => els.map(e => e.open)")
                frames_said = page.eval_on_selector_all("#frames summary", "els => els.map(e => e.textContent)")
                assert page.is_visible("#report"), "the report link did not appear"
                counts = page.text_content("#count-all")
                rows = page.evaluate(_STEP_ROWS)
                done, total = (int(x) for x in counts.split("/"))
                assert done == total > 0, counts
                if initial != "done":  # the script updated the page while the job ran
                    assert page.evaluate("() => window.__seen.length") > 0
                assert "UTC" in page.text_content("#finished")
                page.screenshot(path=str(art / "job_page.png"), full_page=True)
                done_links = _result_links(page, srv.url)
                st = httpx.get(f"{srv.url}/jobs/{jid}", timeout=10).json()
                assert st["state"] == "done", f"{st}\n{srv.logtext()}"

                # the report, rendered by the server
                page.click("#report")
                page.wait_for_url(f"**/ui/jobs/{jid}/report", timeout=60_000)
                page.wait_for_function(_GL_READY, arg="spine-view", timeout=60_000)
                page.wait_for_timeout(1000)  # let WebGL draw
                view = page.locator("#spine-view")
                view.scroll_into_view_if_needed()
                report_png = view.screenshot(path=str(art / "report_3d_view.png"))

                # the take's page: the cameras as frusta, frames and masks from the server
                page.goto(f"{srv.url}/ui/takes/sim", wait_until="networkidle", timeout=30_000)
                page.wait_for_function(_GL_READY, arg="frusta", timeout=30_000)
                page.wait_for_timeout(1000)
                frusta = page.locator("#frusta")
                frusta.scroll_into_view_if_needed()
                frusta_png = frusta.screenshot(path=str(art / "take_frusta.png"))
                n_cams = page.evaluate("() => document.getElementById('frusta').data[1].text.length")
                # the thumbnails load lazily: bring each into view, then wait for all of them
                page.evaluate("() => { for (const i of document.images) i.scrollIntoView(); }")
                page.wait_for_function("() => Array.from(document.images).every(i => i.complete)", timeout=30_000)
                loaded = page.evaluate("() => Array.from(document.images).map(i => i.naturalWidth)")
                page.screenshot(path=str(art / "take_page.png"), full_page=True)

                # the second job's live page, once it failed: its steps laid out as the server lays them out
                live.wait_for_function("() => document.getElementById('state').textContent === 'failed'",
                                       timeout=60_000)
                served_rows = _served_step_rows(f"{srv.url}/ui/jobs/{failed}")
                live.wait_for_function(f"(want) => JSON.stringify(({_STEP_ROWS})()) === want",
                                       arg=json.dumps(served_rows, separators=(",", ":")), timeout=20_000)
                live_rows = live.evaluate(_STEP_ROWS)
                # the table reads as the other pages: AA contrast, every bar named
                live_low, live_unnamed = live.evaluate(LOW_CONTRAST), live.evaluate(UNNAMED)
                bar_names = live.eval_on_selector_all("#steps progress", "els => els.map(e => e.getAttribute('aria-label'))")
                live.screenshot(path=str(art / "failed_job_live_page.png"), full_page=True)

                # a job whose frames warned, then failed: its page lists the warnings said before it failed (its
                # worker processes carved the frames), with its error
                page.goto(f"{srv.url}/ui/jobs/{failed}", wait_until="load", timeout=30_000)
                page.wait_for_function("() => document.getElementById('state').textContent === 'failed'",
                                       timeout=60_000)
                shown = page.eval_on_selector_all("#warning-list li", "els => els.map(e => e.textContent)")
                shown_count, shown_visible = page.text_content("#nwarn"), page.is_visible("#warnings")
                shown_error = page.text_content("#error")
                failed_links = _result_links(page, srv.url)
                failed_frames = page.eval_on_selector_all("#frames summary", "els => els.map(e => e.textContent)")
                unwritten, unwritten_visible = page.text_content("#unwritten"), page.is_visible("#unwritten")
                page.screenshot(path=str(art / "failed_job_page.png"), full_page=True)
                st = httpx.get(f"{srv.url}/jobs/{failed}", timeout=10).json()
            finally:
                browser.close()
    finally:
        srv.cleanup()
    print(f"\nscreenshots of the served pages: {art} ({time.monotonic() - t0:.1f} s; the second job's live page opened"
          f" {live_initial})")
    assert not errors, errors
    assert all(u.startswith((srv.url + "/", "data:", "about:", "blob:")) for u in requests), \
        [u for u in requests if not u.startswith(srv.url)]
    not_blank(report_png, "report 3-D view")
    not_blank(frusta_png, "take frusta")
    assert n_cams == CAMERAS
    assert len(loaded) == 3 * CAMERAS * 2 and all(w == SIZE[0] for w in loaded), loaded  # frames and masks
    # the failed masks' job: each kind of warning once, with its frame sets, on its page as in its record, and the
    # error that stopped it after them
    assert st["state"] == "failed" and st["result"] is None, st
    assert shown_error == st["error"] and "rig.reference" in shown_error, shown_error
    warned = st["warnings"]
    assert [w for w in warned if "silhouette consistency" not in w] == FAILED_MASKS_SAID, warned
    assert shown == warned and shown_count == str(len(warned)) and shown_visible
    # each job's page links the files it wrote, each there (200), as the job's page followed it: the done job its
    # spine's and surfaces', the failed one its surfaces alone, saying its track and rig steps wrote nothing
    assert set(done_links.values()) == {200}, done_links
    assert {h.rsplit("/results/", 1)[1] for h in done_links} == {
        "spine.json", "report.json", "spine.glb", "spine_rig.glb"} | {
        f"meshes/frame_{k:06d}.ply" for k in range(FRAMES)}, done_links
    # the steps' order, as they run, each step's entries under it (the key step's one entry is its row; the refine
    # step, which the key step brings, reported nothing: keying without its graphcut layer)
    assert rows == [["key", "key"], ["refine", None], ["surface", None], ["surface", "box"], ["surface", "surface"],
                    ["spine", None], ["spine", "skeleton"], ["spine", "spine"]], rows
    # the failed job's steps asked, each with what it reported, the rig step's parts announced before it failed
    assert list(dict.fromkeys(g for g, _ in live_rows)) == ["surface", "track", "rig"], live_rows
    assert [e for g, e in live_rows if g == "rig"] == [None, "rig segmentation", "rig skeleton", "rig fit",
                                                       "rig write"], live_rows
    assert ["track", "track"] in live_rows and live_rows == served_rows, (live_rows, served_rows)
    assert not live_low and not live_unnamed, (live_low, live_unnamed)
    assert bar_names[:3] == ["the surface step", "box (surface step)", "surface (surface step)"], bar_names
    if live_initial == "queued":  # (laid out by job.js as the job ran: the server's first page had no entries)
        assert live_rows0 == [["surface", None], ["track", None], ["rig", None]], live_rows0
    assert frames_said == [f"surface meshes ({FRAMES} frame sets)"] and frames_open == [False], (frames_said,
                                                                                             frames_open)
    if initial != "done":  # the listing failed on the poll that saw the job done: said, then asked again
        assert unlisted[0] == 0 and unlisted_said and all(
            t.startswith("The list of results could not be read (HTTP 503)") for t in unlisted_said), unlisted_said
    assert set(failed_links.values()) == {200} and failed_links, failed_links
    assert all("/results/meshes/frame_" in h for h in failed_links), failed_links
    assert failed_frames == [f"surface meshes ({len(failed_links)} frame sets)"], failed_frames
    assert unwritten == "The job failed: the track and rig steps wrote nothing." and unwritten_visible, unwritten

