"""The control room as a lab user meets it, in a real browser over an in-process server (``LiveServer``):
what a take recorded from the page stores and says (its calibration, its disconnected cameras), a camera
that goes away while previewed, the live 3-D preview's capture volume, and the page's labels."""

from __future__ import annotations

import dataclasses
import os
import re
import threading
import time

import cv2
import numpy as np
import pytest

from calib.calibration import Calibration
from fake_cameras.device import take_for_rig
from stage.drivers.base import CameraDisconnectedError
from stage.session import StageSession
from stage.store import TakeReader
from tests.api.liveserver import TOKEN, LiveServer
from tests.browser import CHROMIUM, CHROMIUM_ARGS, LOW_CONTRAST, UNNAMED, artifacts_dir, sync_playwright_or_skip
from tests.polling import wait_until
from tests.stage.paced import PacedCamera, make_drivers, rig_for

pytestmark = [pytest.mark.slow]
try:
    import pytest_timeout  # noqa: F401

    pytestmark.append(pytest.mark.timeout(120))
except ImportError:
    pass


#: a simulated rig's cameras named as a lab names them, not in the simulator's order: (id, simulated index)
ROUND = (("north", 3), ("east", 1), ("south", 0), ("west", 2))


def _sim_rig(cams, *, subject: str = "starfish", frames: int = 10, volume: dict | None = None):
    """A simulated rig (fake_cameras) of small cameras ``(id, index)`` and its FakeCamera drivers."""
    from fake_cameras import device as fake
    from stage.rig import parse_rig

    rig = parse_rig({"name": "sim", "fps": 30, "simulation": {"subject": subject, "n_cameras": 4, "frames": frames},
                     **({"volume": volume} if volume else {}),
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
            # once a calibration job is made from it, it is a board take: its missing calibration is no alarm
            srv.app.state.store.create(kind="calibrate", take="plain", steps=("detect", "calibrate"), params={})
            page.wait_for_function("() => document.querySelector('#take-list tr[data-take=\"plain\"]').cells[4]"
                                   ".textContent === 'none: a board take'", timeout=10_000)
            board_kind = page.get_attribute('#take-list tr[data-take="plain"] td:nth-child(5)', "class")
        finally:
            browser.close()
    assert not errors, errors
    assert said.startswith("takes are recorded without a calibration") and "bad" in bad, (said, bad)
    assert row[4] == "none: cannot be processed" and not enabled, row
    assert board_kind == "muted", board_kind
    with TakeReader(srv.takes / "plain.h5") as t:
        assert t.calibration is None


def _wait_class(page, cam: str, cls: str, timeout: float = 15_000) -> None:
    page.wait_for_function("([c, k]) => document.querySelector('.tile[data-cam=\"' + c + '\"]').classList.contains(k)",
                           arg=[cam, cls], timeout=timeout)


def test_a_camera_that_goes_away_while_previewed_is_greyed_and_its_take_flagged(tmp_path):
    """A camera unplugged while the page shows it: its tile keeps the last picture greyed, saying it is the
    last one before it went away (a frozen frame must not pass for a live one); the other tiles stay live.
    A take recorded then leads its line with the problem, in amber, not in the green of a good take."""
    sync_playwright = sync_playwright_or_skip()
    rig, drivers = _sim_rig(ROUND)
    art = artifacts_dir(tmp_path, "control")
    with LiveServer(tmp_path, StageSession(rig, tmp_path / "data" / "takes", drivers=drivers)) as srv, \
            sync_playwright() as p:
        browser, page, errors = _open(p, srv.url)
        try:
            page.wait_for_function("() => CAMERAS.every((c) => (window.__stage.parts[c] || 0) >= 2)", timeout=20_000)
            page.wait_for_function("() => !document.querySelector('.tile.stale')", timeout=10_000)
            drivers["east"].unplug()
            _wait_class(page, "east", "gone")
            _wait_class(page, "east", "stale")
            note = page.text_content('.tile[data-cam="east"] [data-role="stale"]')
            shown = page.is_visible('.tile[data-cam="east"] [data-role="stale"]')
            grey = page.evaluate("() => getComputedStyle(document.querySelector('.tile[data-cam=\"east\"] img')).filter")
            live = page.evaluate("() => Array.from(document.querySelectorAll('.tile:not(.stale)')).map((t) => t.dataset.cam)")
            page.wait_for_function("() => document.getElementById('cams-msg').textContent !== ''", timeout=10_000)
            top = page.text_content("#cams-msg")
            _record(page, "gap", 1.0)
            msg = page.text_content("#rec-msg")
            kind = page.get_attribute("#rec-msg", "class")
            page.screenshot(path=str(art / "camera_gone.png"), full_page=True)
            # the page's rule for a finished take: the first and last sets may miss a camera (cut by start and
            # stop), more than those is a problem
            fine = page.evaluate("() => window.__stage.takeProblems({sets: 30, sync: {sets_complete: 28, cameras: {}}})")
            short = page.evaluate("() => window.__stage.takeProblems({sets: 30, sync: {sets_complete: 27, cameras: {}}})")
            # the take's page says the same: its sets' completeness and the camera missing from them
            page.goto(srv.url + "/ui/takes/gap", wait_until="load")
            summary = {tr.locator("th").text_content(): tr.locator("td").text_content()
                       for tr in page.locator("#summary table").first.locator("tr").all()}
            missing = {c: (page.text_content(f'#take-cameras tr[data-cam="{c}"] td:nth-child(5)'),
                           page.get_attribute(f'#take-cameras tr[data-cam="{c}"] td:nth-child(5)', "class"))
                       for c, _ in ROUND}
        finally:
            browser.close()
    assert not errors, errors
    assert note == "last picture before it went away" and shown, note
    assert "grayscale(1)" in grey, grey
    assert sorted(live) == ["north", "south", "west"], live
    assert top == "1 of 4 cameras not running: east disconnected (camera 'east': simulated USB unplug)", top
    assert msg.startswith("take gap has problems: east disconnected"), msg
    assert "warn" in kind and "good" not in kind, kind
    assert fine == [] and short == ["3 of 30 frame sets incomplete"], (fine, short)
    with TakeReader(srv.takes / "gap.h5") as t:
        st = t.sync_stats
    assert summary["complete frame sets"] == f"{st['sets_complete']} of {st['sets']}", summary
    assert summary["sync spread (ms)"] == f"{st['spread_median_ms']:.2f} median, {st['spread_max_ms']:.2f} max", summary
    assert missing["east"] == (str(st["cameras"]["east"]["missing"]), "err") and st["cameras"]["east"]["missing"] > 0, missing
    # the others as the take's file says (a loaded machine may make one miss a set): red only where not zero
    assert all(missing[c] == (str(st["cameras"][c]["missing"]), "err" if st["cameras"][c]["missing"] else None)
               for c in ("north", "south", "west")), missing


class _StallingCamera(PacedCamera):
    """A paced camera that stops delivering after ``after`` frames without an error (a hung driver), until
    ``release`` is set: then it says it went away."""

    def __init__(self, *args, after: int, release, **kw) -> None:
        super().__init__(*args, **kw)
        self.after, self.release = after, release

    def grab(self):
        if self.k >= self.after:
            self.release.wait()
            raise CameraDisconnectedError(f"camera {self.camera_id}: released")
        return super().grab()


def test_a_picture_that_stops_changing_says_so(tmp_path):
    """A camera whose driver hangs (no frame, no error: the session still calls it running) and nothing is
    recorded: its tile greys its last picture and counts the seconds since it changed."""
    sync_playwright = sync_playwright_or_skip()
    ids = ["a", "b"]
    drivers = make_drivers(ids, fps=30.0)
    release = threading.Event()
    drivers["b"] = _StallingCamera("b", 1, 30.0, after=45, release=release, start=drivers["a"].start)
    try:
        with LiveServer(tmp_path, StageSession(rig_for(ids, fps=30.0), tmp_path / "data" / "takes",
                                               drivers=drivers)) as srv, sync_playwright() as p:
            browser, page, errors = _open(p, srv.url)
            try:
                _wait_class(page, "b", "stale", timeout=20_000)
                page.wait_for_function("() => /no new picture for \\d+ s/.test("
                                       "document.querySelector('.tile[data-cam=\"b\"] [data-role=\"stale\"]').textContent)",
                                       timeout=10_000)
                state = page.text_content('.tile[data-cam="b"] [data-role="state"]')
                a_stale = page.evaluate("() => document.querySelector('.tile[data-cam=\"a\"]').classList.contains('stale')")
            finally:
                browser.close()
            release.set()
    finally:
        release.set()
    assert not errors, errors
    assert state == "running" and not a_stale, (state, a_stale)


def test_the_live_view_says_when_the_subject_reaches_the_volume_s_edge(tmp_path):
    """The biped (over half a metre tall) in a capture volume 250 mm high: the live 3-D view draws the volume
    and says in one line that the subject reaches its top, whose outside is not reconstructed; the floor it
    stands on is not named."""
    from api.live3d import Live3D

    sync_playwright = sync_playwright_or_skip()
    rig, drivers = _sim_rig(ROUND, subject="biped", frames=4,
                            volume={"center": [0.0, 0.0, 125.0], "size": [750.0, 750.0, 250.0]})
    art = artifacts_dir(tmp_path, "control")
    with LiveServer(tmp_path, StageSession(rig, tmp_path / "data" / "takes", drivers=drivers)) as srv, \
            sync_playwright() as p:
        srv.room.live3d = Live3D(srv.room, resolution=32).start()
        browser, page, errors = _open(p, srv.url)
        try:
            page.wait_for_function("() => window.__stage.lastLive3d && window.__stage.lastLive3d.state === 'ok'",
                                   timeout=60_000)
            page.wait_for_function("() => document.getElementById('live3d-edge').textContent !== ''", timeout=10_000)
            line = page.text_content("#live3d-edge")
            edges = page.get_attribute("#live3d-edge", "data-edges").split(",")
            kind = page.get_attribute("#live3d-edge", "class")
            box_note = page.is_visible("#live3d-box")
            page.locator("#view3d").scroll_into_view_if_needed()
            page.screenshot(path=str(art / "live3d_edge.png"), full_page=True)
            # a calibration that lacks one of the rig's cameras: the hull is carved without it, and the view says so
            cal = drivers["north"].calibration
            srv.room.use_calibration(Calibration(cameras=tuple(c for c in cal if c.name != "west")), "a calibration")
            page.wait_for_function("() => document.getElementById('live3d-info').textContent.includes('a calibration;')",
                                   timeout=60_000)
            info = page.text_content("#live3d-info")
        finally:
            browser.close()
    assert not errors, errors
    assert "z max" in edges and "z min" not in edges, edges
    assert line.startswith("the subject reaches the capture volume's ") and "z max" in line, line
    assert line.endswith("what is outside the volume is not reconstructed") and "warn" in kind, (line, kind)
    assert info.endswith("; a calibration; carved without west (not in the calibration)"), info
    # in the rig's words: what it shows, how old, how often renewed (no "updates/s shown (computed)")
    assert re.match(r"frame set \d+, \d+\.\d s ago: \d+ voxels \(\d+ mm cubes\) in the hull(, a skeleton of \d+ segments)?; "
                    r"the view is renewed \d+\.\d times a second, each taking \d+\.\d\d s to build; a calibration;", info), info
    assert box_note  # (said only while a hull is drawn)


def test_disk_state_warns_under_ten_minutes_and_calls_two_almost_full():
    from api.control import DISK_FULL_MINUTES, DISK_LOW_MINUTES, disk_state

    assert (DISK_LOW_MINUTES, DISK_FULL_MINUTES) == (10.0, 2.0)
    assert disk_state({"minutes_left": None}) == {"level": None, "message": None}
    assert disk_state({"minutes_left": 10.0})["level"] is None
    low = disk_state({"minutes_left": 9.6})
    assert low == {"level": "low", "message": "disk low: 10 min of recording left at the rig's data rate"}
    assert disk_state({"minutes_left": 2.0})["level"] == "low"
    full = disk_state({"minutes_left": 1.94})
    assert full["level"] == "full" and full["message"].startswith("disk almost full: 1.9 min of recording left")


def test_invalid_input():
    from api.control import disk_state

    with pytest.raises(ValueError, match="disk"):
        disk_state([1.0])


def test_a_disk_running_out_is_said_at_the_top(tmp_path):
    """The takes' disk with 6, then 1 minute of recording left: the top line says so, amber then red."""
    sync_playwright = sync_playwright_or_skip()
    ids = ["a", "b"]
    with LiveServer(tmp_path, StageSession(rig_for(ids), tmp_path / "data" / "takes", drivers=make_drivers(ids))) as srv, \
            sync_playwright() as p:
        session = srv.room.session
        rate = session.disk()["rate_mb_s"]
        said = []
        browser, page, errors = _open(p, srv.url)
        try:
            for minutes in (6.0, 1.0):
                session.disk = lambda m=minutes: {"free_bytes": m * 60 * rate * 1e6, "minutes_left": m, "rate_mb_s": rate}
                page.wait_for_function("(m) => document.getElementById('minutes-left').textContent === String(m)",
                                       arg=int(minutes), timeout=10_000)
                page.wait_for_timeout(100)
                said.append((page.text_content("#disk-msg"), page.get_attribute("#disk-msg", "class")))
        finally:
            browser.close()
    assert not errors, errors
    assert said[0] == ("disk low: 6 min of recording left at the rig's data rate", "msg warn"), said
    assert said[1][0].startswith("disk almost full: 1.0 min of recording left") and said[1][1] == "msg bad", said


def test_the_page_reads_without_the_eyes_and_says_when_the_server_is_gone(tmp_path):
    """With a board (every section shown): no text under 4.5:1 contrast, every control and picture named, the
    controls reached by Tab in the order they are read; when the figures stop coming one red line says so
    with the time of the last ones, and it goes when they come back."""
    from calib.boards import parse_board

    sync_playwright = sync_playwright_or_skip()
    ids = ["a", "b"]
    with LiveServer(tmp_path, StageSession(rig_for(ids), tmp_path / "data" / "takes", drivers=make_drivers(ids))) as srv, \
            sync_playwright() as p:
        srv.room.board = parse_board({"type": "charuco", "squares": [7, 5], "square_mm": 70.0, "marker_mm": 52.0,
                                          "dictionary": "DICT_4X4_50"})
        browser, page, errors = _open(p, srv.url)
        try:
            _record(page, "seen", 0.5)  # the take list's row and its button too
            _take_row(page, "seen")
            low = page.evaluate(LOW_CONTRAST)
            unnamed = page.evaluate(UNNAMED)
            page.focus("#token")
            order = []
            for _ in range(12):
                page.keyboard.press("Tab")
                order.append(page.evaluate("() => document.activeElement.id"))
            page.route("**/stage", lambda route: route.abort())
            page.wait_for_function("() => document.getElementById('conn-msg').textContent !== ''", timeout=10_000)
            gone = page.text_content("#conn-msg")
            shown = page.is_visible("#conn-msg")
            page.unroute("**/stage")
            page.wait_for_function("() => document.getElementById('conn-msg').textContent === ''", timeout=10_000)
            hidden = not page.is_visible("#conn-msg")
        finally:
            browser.close()
    assert not errors, errors
    assert low == {}, low
    assert unnamed == [], unnamed
    # (stop is disabled while nothing is recorded: Tab passes it)
    assert order[:9] == ["take-name", "take-seconds", "record", "mask", "min-views", "min-shared", "board-start",
                         "holdout", "cal-step"], order
    assert gone.startswith("the server does not answer (") and "the figures and pictures are from " in gone, gone
    assert shown and hidden


def _reference_figures(img: np.ndarray) -> dict:
    """image_figures by hand: BT.601 luma, the 4-neighbour Laplacian with mirrored borders, percentages by counting;
    level and clipped share over every (W // 320)-th pixel, the sharpness over the central half's middle 256 square."""
    luma = np.round(img[..., 2] * 0.299 + img[..., 1] * 0.587 + img[..., 0] * 0.114)
    h, w = luma.shape
    k = max(1, w // 320)
    ch, cw = min(h - 2 * (h // 4), 256), min(w - 2 * (w // 4), 256)
    c = luma[(h - ch) // 2: (h - ch) // 2 + ch, (w - cw) // 2: (w - cw) // 2 + cw]
    p = np.pad(c, 1, mode="reflect")
    lap = p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * p[1:-1, 1:-1]
    sub = img[::k, ::k]
    clipped = sum(1 for row in sub for px in row if max(px) >= 250) / (sub.shape[0] * sub.shape[1]) * 100
    return {"level": float(np.median(luma[::k, ::k])), "clipped_pct": clipped, "sharpness": float(lap.var())}


def test_image_figures_against_a_count_by_hand():
    from api.control import image_figures

    rng = np.random.default_rng(3)
    for shape in ((40, 60, 3), (700, 1000, 3)):  # all pixels; every 3rd pixel and a 256 square of the centre
        img = rng.integers(0, 256, shape).astype(np.uint8)
        got, ref = image_figures(img), _reference_figures(img)
        assert got["level"] == pytest.approx(ref["level"], abs=1.0)  # cv2 rounds the luma its own way
        assert got["clipped_pct"] == pytest.approx(ref["clipped_pct"], abs=1e-9)
        assert got["sharpness"] == pytest.approx(ref["sharpness"], rel=0.02)
    flat = np.full((40, 60, 3), 120, np.uint8)
    assert image_figures(flat) == {"level": 120.0, "clipped_pct": 0.0, "sharpness": 0.0, "exposure": None}
    half = flat.copy()
    half[:, :30] = 255
    assert image_figures(half)["clipped_pct"] == 50.0 and image_figures(half)["exposure"] == "overexposed"
    assert image_figures(np.full((8, 8, 3), 20, np.uint8))["exposure"] == "dark"
    sharp = np.kron((np.indices((10, 15)).sum(0) % 2) * 200 + 20, np.ones((4, 4))).astype(np.uint8)[..., None].repeat(3, 2)
    blurred = cv2.GaussianBlur(sharp, (9, 9), 3)
    assert image_figures(blurred)["sharpness"] < image_figures(sharp)["sharpness"] / 4


def test_image_figures_invalid_input():
    from api.control import image_figures

    for bad in (np.zeros((10, 10), np.uint8), np.zeros((10, 10, 3), np.float32), np.zeros((2, 10, 3), np.uint8)):
        with pytest.raises(ValueError, match="image"):
            image_figures(bad)


class _FixedCamera(PacedCamera):
    """A paced camera that shows one fixed picture."""

    def __init__(self, *args, image: np.ndarray, **kw) -> None:
        super().__init__(*args, **kw)
        self.image = image

    def grab(self):
        return dataclasses.replace(super().grab(), image=self.image)


def test_a_tile_shows_what_its_picture_says_of_exposure_and_focus(tmp_path):
    """Two cameras whose drivers report no exposure: one sees a well-lit grey, the other a picture half burnt
    out. Each tile shows the picture's own level, clipped share and sharpness, and the second says OVEREXPOSED
    in amber."""
    sync_playwright = sync_playwright_or_skip()
    from tests.stage.paced import H, W

    grey = np.full((H, W, 3), 120, np.uint8)
    burnt = grey.copy()
    burnt[:, : W // 2] = 255
    ids = ["ok", "burnt"]
    start: dict = {}
    drivers = {c: _FixedCamera(c, i, 30.0, image=img, start=start) for i, (c, img) in enumerate(zip(ids, (grey, burnt)))}
    with LiveServer(tmp_path, StageSession(rig_for(ids, fps=30.0), tmp_path / "data" / "takes", drivers=drivers)) as srv, \
            sync_playwright() as p:
        browser, page, errors = _open(p, srv.url)
        try:
            page.wait_for_function("() => !document.querySelector('.tile[data-cam=\"burnt\"] [data-role=\"image\"]')"
                                   ".textContent.startsWith('level –')", timeout=15_000)
            said = {c: page.text_content(f'.tile[data-cam="{c}"] [data-role="image"]') for c in ids}
            kind = {c: page.get_attribute(f'.tile[data-cam="{c}"] [data-role="image"]', "class") for c in ids}
        finally:
            browser.close()
    assert not errors, errors
    assert said["ok"] == "level 120 · clipped 0.0 % · sharpness 0" and kind["ok"] == "muted", said
    assert said["burnt"].startswith("OVEREXPOSED: level ") and "clipped 50.0 %" in said["burnt"], said
    assert kind["burnt"] == "warn", kind


def test_a_job_is_cancelled_from_its_page_and_a_failed_one_says_why_in_the_list(tmp_path):
    """The job page of a queued job has a cancel button (refused without the token, said in one line; with the
    token the job is cancelled and the button goes); the jobs list gives a failed job's first line of error
    beside its state, when it fails while the list is open and when the list is loaded after."""
    sync_playwright = sync_playwright_or_skip()
    ids = ["a", "b"]
    with LiveServer(tmp_path, StageSession(rig_for(ids), tmp_path / "data" / "takes", drivers=make_drivers(ids))) as srv, \
            sync_playwright() as p:
        store = srv.app.state.store
        queued = store.create(kind="process", take="t1", steps=["key"], params={}).id
        failing = store.create(kind="process", take="t2", steps=["key"], params={}).id
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        errors: list[str] = []
        try:
            page = browser.new_page()
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(srv.url + f"/ui/jobs/{queued}", wait_until="load")
            page.click("#cancel")
            page.wait_for_function("() => document.getElementById('cancel-msg').textContent !== ''", timeout=10_000)
            refused = page.text_content("#cancel-msg")
            page.fill("#token", TOKEN)
            page.click("#cancel")
            page.wait_for_function("() => document.getElementById('state').textContent === 'cancelled'", timeout=10_000)
            box_hidden = not page.is_visible("#cancel-box")
            page.goto(srv.url + "/ui/jobs", wait_until="load")
            store.finish(failing, "failed", error="DATA/takes/t2.h5: the take has no calibration\nTraceback ...")
            sel = f'tr[data-job="{failing}"] .why'
            page.wait_for_function("(s) => document.querySelector(s).textContent !== ''", arg=sel, timeout=10_000)
            live_why = page.text_content(sel)
            page.reload(wait_until="load")
            loaded_why = page.text_content(sel)
            cancelled_why = page.text_content(f'tr[data-job="{queued}"] .why')
        finally:
            browser.close()
    assert not errors, errors
    assert refused.startswith("not cancelled (401): enter the API token."), refused
    assert box_hidden and store.get(queued).state == "cancelled"
    assert live_why == loaded_why == "DATA/takes/t2.h5: the take has no calibration", (live_why, loaded_why)
    assert cancelled_why == ""


def test_the_recorder_refuses_a_bad_name_before_asking_and_says_a_refusal_plainly(tmp_path):
    """A take name with a space is refused on the page, in words; a refusal of the server's checks (422) reads
    "field: message", not JSON; stop is disabled while no take runs."""
    sync_playwright = sync_playwright_or_skip()
    ids = ["a", "b"]
    with LiveServer(tmp_path, StageSession(rig_for(ids), tmp_path / "data" / "takes", drivers=make_drivers(ids))) as srv, \
            sync_playwright() as p:
        browser, page, errors = _open(p, srv.url)
        requests: list[str] = []
        page.on("request", lambda q: requests.append(q.url) if q.url.endswith("/stage/record") else None)
        try:
            page.wait_for_function("() => document.getElementById('rec-state').textContent.startsWith('idle')",
                                   timeout=10_000)
            idle = (page.is_enabled("#record"), page.is_enabled("#stop"))
            spread = page.text_content("#spread")
            page.fill("#take-name", "my take")
            page.click("#record")
            bad_name = page.text_content("#rec-msg")
            asked = list(requests)
            page.fill("#take-name", "long")
            page.fill("#take-seconds", "100000")
            page.click("#record")
            page.wait_for_function("() => document.getElementById('rec-msg').textContent.includes('422')", timeout=10_000)
            refused = page.text_content("#rec-msg")
            page.fill("#take-seconds", "2")
            page.click("#record")
            page.wait_for_function("() => document.getElementById('rec-state').textContent.startsWith('recording')",
                                   timeout=10_000)
            recording = (page.is_enabled("#record"), page.is_enabled("#stop"))
            banner = page.evaluate("() => [document.getElementById('recorder').classList.contains('recording'), "
                                   "getComputedStyle(document.getElementById('recorder')).borderLeftWidth]")
            page.click("#stop")
            page.wait_for_function("() => document.getElementById('rec-state').textContent.startsWith('done')",
                                   timeout=15_000)
            done = (page.is_enabled("#record"), page.is_enabled("#stop"))
            banner_after = page.evaluate("() => document.getElementById('recorder').classList.contains('recording')")
        finally:
            browser.close()
    assert not errors, errors
    assert idle == (True, False) and recording == (True, True) and done == (True, False), (idle, recording, done)
    assert banner == [True, "8px"] and not banner_after, (banner, banner_after)  # the recorder says it, across the room
    assert bad_name.startswith("not recording: a take name is letters, digits") and asked == [], (bad_name, asked)
    assert spread.endswith(" (sets group within 8.3 ms)"), spread  # half the 60 fps rig's period
    assert refused.startswith("not recording: (422) duration_s: ") and "[{" not in refused, refused


def test_a_take_is_processed_from_the_take_list_and_its_job_followed_there(tmp_path):
    """"process" queues the take's job and the control room stays open: the take's row follows its newest job
    (state, the page's link), then says a failure's first line, or links the report when it is done."""
    sync_playwright = sync_playwright_or_skip()
    rig, drivers = _sim_rig(ROUND)
    with LiveServer(tmp_path, StageSession(rig, tmp_path / "data" / "takes", drivers=drivers)) as srv, \
            sync_playwright() as p:
        store = srv.app.state.store
        browser, page, errors = _open(p, srv.url)
        cell = 'document.querySelector(\'#take-list tr[data-take="{}"] td.job\').textContent'
        try:
            for name in ("one", "two"):
                _record(page, name, 0.5)
                _take_row(page, name)
            jobs = {}
            for name in ("one", "two"):
                page.click(f'#take-list tr[data-take="{name}"] button')
                page.wait_for_function(f"() => {cell.format(name)}.startsWith('process ')", timeout=10_000)
                jobs[name] = store.list(take=name)[0].id
            queued = page.evaluate(f"() => {cell.format('one')}")
            url = page.url
            # its steps report as they run: the row names the first entry not finished, in run order (not by name),
            # with its step (the surface step's box)
            for name, done, total in (("key", 8, 8), ("box", 2, 4), ("surface", 0, 4)):
                store.progress(jobs["one"], name, done, total, of_step="key" if name == "key" else "surface")
            page.wait_for_function(f"() => {cell.format('one')}.includes('step ')", timeout=10_000)
            at_work = page.evaluate(f"() => {cell.format('one')}")
            store.finish(jobs["one"], "failed", error="DATA/takes/one.h5: the surface is empty\nmore lines")
            store.finish(jobs["two"], "done")
            page.wait_for_function(f"() => {cell.format('one')}.includes('failed')", timeout=10_000)
            page.wait_for_function(f"() => {cell.format('two')}.includes('report')", timeout=10_000)
            failed = page.evaluate(f"() => {cell.format('one')}")
            link = page.get_attribute('#take-list tr[data-take="two"] td.job a[href$="/report"]', "href")
            job_link = page.get_attribute('#take-list tr[data-take="one"] td.job a', "href")
        finally:
            browser.close()
    assert not errors, errors
    assert url.endswith("/ui/stage")
    assert queued == f"process {jobs['one'][:8]} queued 0/0", queued
    assert at_work == f"process {jobs['one'][:8]} queued 10/16 · step surface: box 2/4", at_work
    assert failed == f"process {jobs['one'][:8]} failedDATA/takes/one.h5: the surface is empty", failed
    assert link == f"/ui/jobs/{jobs['two']}/report" and job_link == f"/ui/jobs/{jobs['one']}", (link, job_link)


def test_the_stage_link_of_a_server_without_cameras_says_how_to_start_one(tmp_path):
    """``stage serve`` without a rig: the navigation's "stage" opens a page (not JSON) that says how to start
    a stage session."""
    from tests.api.served import Server

    sync_playwright = sync_playwright_or_skip()
    (tmp_path / "data").mkdir()
    srv = Server(tmp_path / "data", workers=1).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
            try:
                page = browser.new_page()
                page.goto(srv.url + "/", wait_until="load")
                with page.expect_navigation():
                    page.click("nav >> text=stage")
                status = page.evaluate("() => performance.getEntriesByType('navigation')[0].responseStatus")
                said = page.text_content("section")
                kind = page.evaluate("() => document.contentType")
            finally:
                browser.close()
    finally:
        srv.cleanup()
    assert kind == "text/html" and status == 404, (kind, status)
    assert said.startswith("No stage session: this server was started without cameras.") and "--rig" in said, said


def test_a_take_recorded_before_the_calibration_is_given_it_from_the_take_list(tmp_path):
    """A take recorded without a calibration, then a calibration made on the server: the take's row offers the
    newest one; pressed, the take has it (cut to its cameras, in order), the row says yes and "process" is enabled.
    The API refuses a calibration lacking one of the take's cameras (409, naming it) and an unknown one (404)."""
    import httpx

    from tests.stage.frames import calibration

    sync_playwright = sync_playwright_or_skip()
    ids = ["a", "b"]
    with LiveServer(tmp_path, StageSession(rig_for(ids), tmp_path / "data" / "takes", drivers=make_drivers(ids))) as srv, \
            sync_playwright() as p:
        lib = srv.app.state.calibrations
        browser, page, errors = _open(p, srv.url)
        try:
            _record(page, "early", 0.5)
            assert _take_row(page, "early")[4] == "none: cannot be processed"
            short = lib.save(calibration(["a"]))
            made = calibration(["b", "x", "a"])  # more cameras than the take, in another order
            cid = lib.save(made)
            old = time.time() - 60  # the newest is the one offered: made, not short
            os.utime(srv.app.state.settings.calibrations_dir / f"{short}.json", (old, old))
            auth = {"Authorization": f"Bearer {TOKEN}"}
            lacking = httpx.put(srv.url + "/takes/early/calibration", json={"calibration": short}, headers=auth, timeout=10)
            unknown = httpx.put(srv.url + "/takes/early/calibration", json={"calibration": "0" * 32}, headers=auth,
                                timeout=10)
            page.reload(wait_until="load")  # (the token stays: the tab keeps it)
            page.wait_for_selector('#take-list tr[data-take="early"] button.use-cal', timeout=10_000)
            offer = page.text_content('#take-list tr[data-take="early"] button.use-cal')
            page.click('#take-list tr[data-take="early"] button.use-cal')
            page.wait_for_function("() => { const r = document.querySelector('#take-list tr[data-take=\"early\"]');"
                                   " return r && r.cells[4].textContent === 'yes'; }", timeout=10_000)
            enabled = page.locator('#take-list tr[data-take="early"] button').first.is_enabled()
            said = page.text_content("#rec-msg")
        finally:
            browser.close()
    assert not errors, errors
    assert lacking.status_code == 409 and "no camera b of take 'early'" in lacking.json()["detail"], lacking.text
    assert unknown.status_code == 404, unknown.text
    assert offer == f"use calibration {cid[:8]}" and enabled, offer
    assert said == f"take early now has calibration {cid[:8]}", said
    with TakeReader(srv.takes / "early.h5") as t:
        cal = t.calibration
    assert cal.names == ["a", "b"]
    for n in ("a", "b"):
        np.testing.assert_array_equal(cal[n].t, made[n].t)


def test_a_rig_capture_through_the_session_holds_the_calibration_too(tmp_path):
    """``POST /rig/capture`` on a server with a stage session records from its cameras and stores the same
    calibration as the control room's record (it stored none)."""
    import httpx

    rig, drivers = _sim_rig(ROUND)
    with LiveServer(tmp_path, StageSession(rig, tmp_path / "data" / "takes", drivers=drivers)) as srv:
        r = httpx.post(srv.url + "/rig/capture", json={"take": "viarig", "frames": 5},
                       headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
        assert r.status_code == 202, r.text
        wait_until(lambda: httpx.get(srv.url + "/rig/capture", timeout=10).json()["state"] == "done", timeout=20.0,
                   poll=0.1, what="the capture")
    true = take_for_rig(rig, size=(160, 120), fps=30.0).calibration
    with TakeReader(srv.takes / "viarig.h5") as t:
        cal = t.calibration
    assert cal is not None and cal.names == [cid for cid, _ in ROUND]
    for cid, index in ROUND:
        np.testing.assert_array_equal(cal[cid].R, true.cameras[index].R)


def test_capture_manager_invalid_input(tmp_path):
    from api.rigctl import CaptureManager

    with pytest.raises(ValueError, match="take_calibration"):
        CaptureManager(tmp_path / "rig.toml", tmp_path, take_calibration=3)


#: tiles a and c say their sync, b's dropped count reads 10
_SYNC_SHOWN = """() => { const t = (c, r) => document.querySelector('figure[data-cam="' + c + '"] [data-role="' + r + '"]');
  return ['a', 'c'].every((c) => t(c, 'sync') && t(c, 'sync').textContent.startsWith('sync: ')) &&
         t('b', 'dropped').textContent.startsWith('10 '); }"""


def test_each_tile_says_how_late_its_camera_is_and_what_it_just_dropped(tmp_path, monkeypatch):
    """Three paced cameras, c exposing 4 ms after a and b, b dropping ten frames a second in: c's tile says
    "4.0 ms late" (muted: a lateness within the grouping is no loss), a's "on time"; b's dropped count is amber
    with the frames of the recent window (made a minute here, so that a browser slow to start on a busy machine
    still sees the drops as recent); nobody is missing from the sets."""
    import stage.session

    monkeypatch.setattr(stage.session, "RECENT_DROPS_S", 60.0)
    sync_playwright = sync_playwright_or_skip()
    ids = ["a", "b", "c"]
    t0 = time.monotonic_ns() + 300_000_000
    drivers = {c: PacedCamera(c, i, 60.0, offset_ns=i * 1_234_567_891, jitter_ms=0.1, seed=i,
                              start={"t0": t0 + (4_000_000 if c == "c" else 0)}, drop=range(60, 70) if c == "b" else ())
               for i, c in enumerate(ids)}
    with LiveServer(tmp_path, StageSession(rig_for(ids), tmp_path / "data" / "takes", drivers=drivers)) as srv, \
            sync_playwright() as p:
        browser, page, errors = _open(p, srv.url)
        try:
            page.wait_for_function(_SYNC_SHOWN, timeout=10_000)
            page.wait_for_timeout(1500)  # the median over a full window of sets
            sync = {c: (page.text_content(f'figure[data-cam="{c}"] [data-role="sync"]'),
                        page.get_attribute(f'figure[data-cam="{c}"] [data-role="sync"]', "class")) for c in ids}
            dropped = [(page.text_content(f'figure[data-cam="{c}"] [data-role="dropped"]'),
                        page.get_attribute(f'figure[data-cam="{c}"] [data-role="dropped"]', "class")) for c in ids]
        finally:
            browser.close()
    assert not errors, errors
    late = sync["c"][0]
    assert late.startswith("sync: ") and late.endswith(" ms late"), sync
    assert abs(float(late.split()[1]) - 4.0) <= 0.5, sync
    assert sync["a"][0].startswith("sync: on time") or " ms early" in sync["a"][0], sync
    assert all(cls == "muted" for _, cls in sync.values()), sync
    assert dropped[1] == ("10 (10 in the last 60 s)", "warn"), dropped
    assert dropped[0] == ("0", "") and dropped[2] == ("0", ""), dropped


def test_sync_offsets_against_the_median_of_each_set():
    """Offsets counted by hand: each camera against the median of its set, the median over its sets."""
    from stage.session import sync_offsets

    ms = 1_000_000
    sets = [{"a": 10 * ms, "b": 9 * ms, "c": 13 * ms}, {"a": 19 * ms, "c": 22 * ms}, {"b": 5 * ms}]
    out = sync_offsets(sets, cameras=["a", "b", "c", "d"])
    # set 1: median 10 -> a 0, b -1, c +3; set 2: median 20.5 -> a -1.5, c +1.5; set 3: one camera, no offset
    assert out["a"] == {"offset_ms": pytest.approx(-0.75), "missing": 1}
    assert out["b"] == {"offset_ms": pytest.approx(-1.0), "missing": 1}
    assert out["c"] == {"offset_ms": pytest.approx(2.25), "missing": 1}
    assert out["d"] == {"offset_ms": None, "missing": 3}
    assert sync_offsets([], cameras=["a"]) == {"a": {"offset_ms": None, "missing": 0}}


def test_sync_offsets_invalid_input():
    from stage.session import sync_offsets

    with pytest.raises(ValueError, match="cameras"):
        sync_offsets([], cameras="a")
    with pytest.raises(ValueError, match="sets"):
        sync_offsets([[1, 2]], cameras=["a"])
