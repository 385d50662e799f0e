"""A calibration job's page in headless Chromium (Playwright, Debian's chromium), served in-process by uvicorn with
the job runner on: the page follows the running job, then, once it is done, shows what it made, its calibration in
each format and its report, each answering 200 (the calibrator stands in: it waits for the page before it
returns)."""

from __future__ import annotations

import threading
import time

import httpx
import pytest

from tests.api.conftest import AUTH, make_settings
from tests.api.fakework import make_take_file, small_calibration
from tests.browser import CHROMIUM, CHROMIUM_ARGS, sync_playwright_or_skip

pytestmark = [pytest.mark.slow]

BOARD = {"type": "chessboard", "corners": [7, 6], "square_mm": 100.0}


def test_a_calibration_jobs_page_shows_what_it_made_once_it_is_done(tmp_path, monkeypatch):
    import uvicorn

    import api.calibrations as mod
    from api.app import create_app
    from tests.api.served import free_port

    sync_playwright = sync_playwright_or_skip()
    go = threading.Event()

    def calibrator(take, *, params, progress=None, cancel=None):
        progress("calibrate", 0, 1)
        assert go.wait(60), "the page never asked"
        progress("calibrate", 1, 1)
        return small_calibration(2)

    monkeypatch.setattr(mod, "_find_rig_calibrator", lambda: calibrator)
    data = tmp_path / "data"
    (data / "takes").mkdir(parents=True)
    make_take_file(data / "takes" / "b.h5", 2)
    app = create_app(make_settings(data), start_runner=True)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    errors: list[str] = []
    try:
        t0 = time.monotonic()
        while not server.started:
            assert time.monotonic() - t0 < 20, "the server did not start"
            time.sleep(0.05)
        r = httpx.post(f"{url}/calibrations", json={"take": "b", "parameters": {"board": BOARD}}, headers=AUTH,
                       timeout=30)
        assert r.status_code == 202, r.text
        cid = r.json()["job"]
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
            try:
                page = browser.new_page()
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(f"{url}/ui/jobs/{cid}", wait_until="load", timeout=30_000)
                before = page.text_content("#calibration")
                go.set()
                page.wait_for_selector("#calibration a[href$='.yaml']", timeout=30_000)  # (after the page's reload)
                state = page.text_content("#state")
                hrefs = page.eval_on_selector_all("#calibration a", "els => els.map(e => e.getAttribute('href'))")
            finally:
                browser.close()
        answers = {h: httpx.get(url + h, timeout=30).status_code for h in hrefs}
    finally:
        go.set()
        server.should_exit = True
        thread.join(30)
    assert not errors, errors
    assert before.split() == ["Calibration:", "none", "yet"], before
    assert state == "done"
    assert hrefs == [f"/calibrations/{cid}.{f}" for f in ("json", "toml", "yaml")] + [
        f"/jobs/{cid}/results/report.json"], hrefs
    assert set(answers.values()) == {200}, answers
