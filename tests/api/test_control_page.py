"""The control room as a lab user meets it, in a real browser over an in-process server (``LiveServer``):
what a take recorded from the page stores and says (its calibration, its disconnected cameras), a camera
that goes away while previewed, the live 3-D preview's capture volume, and the page's labels."""

from __future__ import annotations

import numpy as np
import pytest

from fake_cameras.device import take_for_rig
from stage.session import StageSession
from stage.store import TakeReader
from tests.api.liveserver import TOKEN, LiveServer
from tests.browser import CHROMIUM, CHROMIUM_ARGS, artifacts_dir, sync_playwright_or_skip
from tests.stage.paced import make_drivers, rig_for

pytestmark = [pytest.mark.slow]
try:
    import pytest_timeout  # noqa: F401

    pytestmark.append(pytest.mark.timeout(120))
except ImportError:
    pass


#: a simulated rig's cameras named as a lab names them, not in the simulator's order: (id, simulated index)
ROUND = (("north", 3), ("east", 1), ("south", 0), ("west", 2))


def _sim_rig(cams, *, subject: str = "starfish", frames: int = 10):
    """A simulated rig (fake_cameras) of small cameras ``(id, index)`` and its FakeCamera drivers."""
    from fake_cameras import device as fake
    from stage.rig import parse_rig

    rig = parse_rig({"name": "sim", "fps": 30, "simulation": {"subject": subject, "n_cameras": 4, "frames": frames},
                     "cameras": [{"id": cid, "driver": "fake", "index": i, "width": 160, "height": 120}
                                 for cid, i in cams]})
    return rig, {c.id: fake.FakeCamera(c, rig) for c in rig.cameras}


def _open(p, url: str):
    browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url + "/ui/stage", wait_until="load", timeout=30_000)
    page.fill("#token", TOKEN)
    page.dispatch_event("#token", "change")
    return browser, page, errors


def _record(page, name: str, seconds: float) -> None:
    page.fill("#take-name", name)
    page.fill("#take-seconds", str(seconds))
    page.click("#record")
    page.wait_for_function("(n) => document.getElementById('rec-state').textContent.startsWith('done (' + n + ')')",
                           arg=name, timeout=20_000)


def _take_row(page, name: str) -> list[str]:
    """The take list's cells of take ``name`` once its calibration cell is filled in."""
    sel = f'#take-list tr[data-take="{name}"]'
    page.wait_for_function("(s) => { const r = document.querySelector(s); return r && r.cells[4].textContent !== '…'; }",
                           arg=sel, timeout=15_000)
    return [td.text_content() for td in page.locator(sel + " td").all()]


def test_a_take_recorded_from_the_page_holds_the_calibration(tmp_path):
    """A take recorded in the control room stores the calibration the 3-D preview uses (here the simulated
    rig's own), so that it can be processed; the page says which before recording, and the take list says
    a take without one cannot be processed (its button is disabled) rather than failing a job later."""
    sync_playwright = sync_playwright_or_skip()
    rig, drivers = _sim_rig(ROUND)
    art = artifacts_dir(tmp_path, "control")
    with LiveServer(tmp_path, StageSession(rig, tmp_path / "data" / "takes", drivers=drivers)) as srv, \
            sync_playwright() as p:
        browser, page, errors = _open(p, srv.url)
        try:
            page.wait_for_function("() => document.getElementById('take-cal').textContent !== ''", timeout=15_000)
            said = page.text_content("#take-cal")
            _record(page, "calibrated", 1.0)
            row = _take_row(page, "calibrated")
            enabled = page.locator('#take-list tr[data-take="calibrated"] button').is_enabled()
            page.screenshot(path=str(art / "take_calibrated.png"), full_page=True)
        finally:
            browser.close()
    assert not errors, errors
    assert said == "takes are recorded with the cameras' own calibration", said
    assert row[4] == "yes" and enabled, row
    true = take_for_rig(rig, size=(160, 120), fps=30.0).calibration  # the simulated cameras by index
    with TakeReader(srv.takes / "calibrated.h5") as t:
        cal = t.calibration
        assert cal is not None and cal.names == [cid for cid, _ in ROUND]
        for cid, index in ROUND:
            for key in ("K", "dist", "R", "t"):
                np.testing.assert_allclose(getattr(cal[cid], key), getattr(true.cameras[index], key), atol=1e-9)

    ids = ["a", "b"]  # cameras that know no calibration: the take has none, and the page says so twice
    with LiveServer(tmp_path / "plain", StageSession(rig_for(ids), tmp_path / "plain" / "data" / "takes",
                                                     drivers=make_drivers(ids))) as srv, sync_playwright() as p:
        browser, page, errors = _open(p, srv.url)
        try:
            page.wait_for_function("() => document.getElementById('take-cal').textContent !== ''", timeout=15_000)
            said = page.text_content("#take-cal")
            bad = page.get_attribute("#take-cal", "class")
            _record(page, "plain", 0.5)
            row = _take_row(page, "plain")
            enabled = page.locator('#take-list tr[data-take="plain"] button').is_enabled()
        finally:
            browser.close()
    assert not errors, errors
    assert said.startswith("takes are recorded without a calibration") and "bad" in bad, (said, bad)
    assert row[4] == "none: cannot be processed" and not enabled, row
    with TakeReader(srv.takes / "plain.h5") as t:
        assert t.calibration is None
