"""The offline HTML report (pipeline.report, stage report) and a real browser test of its 3-D view."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.report import (
    NothingToReportError,
    camera_coverage,
    contact_sheet,
    decimate_mesh,
    frusta_figure,
    mesh_quality_figure,
    render_report,
    spine_figure,
    take_contact_sheets,
    tip_count_figure,
    write_report,
)
from pipeline.spine_format import write_spine
from tests.browser import CHROMIUM, CHROMIUM_ARGS, sync_playwright_or_skip
from tests.pipeline.creature_truth import creature_take, surface, true_spine

FRAMES = 8
# screenshots of the browser test are kept here (CI can point STAGE_TEST_ARTIFACTS elsewhere)
ARTIFACTS = Path(os.environ.get("STAGE_TEST_ARTIFACTS", Path(__file__).resolve().parents[1] / "artifacts"))


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """A results directory as `stage process` writes it, and a tiny take (4 cameras, 160x120) with masks."""
    import trimesh

    from fake_cameras.dome import make_dome
    from fake_cameras.render import render_view
    from stage.frame import Frame
    from stage.store import CameraSpec, TakeWriter, write_masks

    d = tmp_path_factory.mktemp("results")
    _, poses = creature_take("starfish", FRAMES)
    spine = true_spine("starfish", poses, hide={"arm3": [1]})
    spine.meta["tip_counts"] = [5, 4, 5, 5, 6, 5, 5, 5]
    write_spine(d / "spine.json", spine)
    (d / "meshes").mkdir()
    per_frame = []
    for t in (3, 4):
        v, f = surface(poses[t], step=10.0)
        m = trimesh.Trimesh(v, f, process=False)
        m.export(d / "meshes" / f"frame_{t:06d}.ply")
        per_frame.append((t, m))
    quality = []
    for t in range(FRAMES):
        q = {"vertices": 1000 + t, "faces": 2000 + 2 * t, "watertight": t != 5, "bodies": 1, "area": 1e5 + t,
             "volume": 2e6, "euler": 2, "genus": 0}
        quality.append({"index": t, "status": "ok" if t != 6 else "empty", "quality": q if t != 6 else None,
                        "seconds": 0.1})
    calib = make_dome(4, size=(160, 120))
    take = d / "take.h5"
    specs = [CameraSpec(c.name, 160, 120) for c in calib.cameras]
    masks = {c.name: [] for c in calib.cameras}
    with TakeWriter(take, specs, calibration=calib, fps=30) as w:
        for k in range(3):
            frames = {}
            for c in calib.cameras:
                view = render_view(c, poses[k], rng=np.random.default_rng(k))
                frames[c.name] = Frame(view.image, c.name, k, k * 33_000_000, k * 33_000_000)
                masks[c.name].append(view.mask)
            w.write_set(frames)
    for c in calib.cameras:
        write_masks(take, c.name, np.array(masks[c.name]))
    report = {"take": str(take), "frames": FRAMES, "steps": ["key", "surface", "spine"],
              "seconds": {"surface": 1.5, "spine": 0.4}, "empty_frames": [6],
              "tip_counts": spine.meta["tip_counts"], "per_frame": quality}
    (d / "report.json").write_text(json.dumps(report))
    return d, spine, calib, take


@pytest.fixture(scope="module")
def page(results):
    d, *_ = results
    return render_report(d)


def test_report_is_offline_and_has_every_section(page, results):
    d, spine, calib, take = results
    for sid in ("summary", "view", "tips", "quality", "cameras", "sheets"):
        assert f'id="{sid}"' in page, sid
    # plotly.js is embedded, nothing is loaded from the network
    assert "Plotly" in page and len(page) > 3_000_000
    assert not re.search(r"""<script[^>]+src=""", page)
    body = page.split("</head>", 1)[1]  # the head holds plotly.js itself (URLs inside its strings)
    assert not re.search(r"""(src|href)=["']https?://""", body)
    assert "cdn.plot.ly" not in body
    # contact sheets (frames JPEG, masks PNG) as data URIs
    assert body.count("data:image/jpeg;base64,") == 1 and body.count("data:image/png;base64,") == 1
    # warnings: a non-watertight frame and an empty frame
    assert "not watertight" in page and "have no surface" in page
    for c in calib.cameras:
        assert c.name in page


def test_report_3d_view_animates_the_spine_over_the_take(results):
    d, spine, *_ = results
    from pipeline.armature_spine import rigged_model

    v, f = surface(creature_take("starfish", FRAMES)[1][4], step=12.0)
    model = rigged_model(spine, v, f, reference=4)
    fig = spine_figure(spine, model=model)
    assert len(fig.frames) == FRAMES
    # the surface is posed per frame, the tips follow the spine, a null limb is left out
    for t in (0, 7):
        mesh, lines, tips, _ = fig.frames[t].data
        np.testing.assert_allclose(np.c_[mesh.x, mesh.y, mesh.z], model.deform(t), atol=1e-3)  # float32
        assert len(tips.x) == spine.K
    assert len(fig.frames[1].data[2].x) == spine.K - 1
    assert fig.layout.sliders[0].steps[-1].label == str(FRAMES - 1)
    assert len(spine_figure(spine, max_frames=3).frames) == 3


def test_tip_count_and_quality_figures():
    fig = tip_count_figure([5, 4, None, 5, 6], K=5)
    assert list(fig.data[0].y) == [5, 4, None, 5, 6]
    assert list(fig.data[1].x) == [1, 4]  # frames whose count differs from K
    q = mesh_quality_figure([{"index": 0, "status": "ok", "quality": {"faces": 10, "area": 2.0, "watertight": True}},
                             {"index": 1, "status": "empty"}])
    assert list(q.data[0].y) == [10, None]


def test_frusta_and_coverage(results):
    _, spine, calib, _ = results
    pts = spine.axes["arm0"][0]
    fig = frusta_figure(calib, points=pts)
    assert list(fig.data[1].text) == list(calib.names)
    cov = camera_coverage(calib, pts)
    assert set(cov["per_camera"]) == set(calib.names)
    # slow reference: project point by point
    for c in calib.cameras:
        seen = [bool(c.in_image(c.project(p[None]))[0]) for p in pts]
        assert cov["per_camera"][c.name] == pytest.approx(np.mean(seen))
    behind = camera_coverage(calib, calib.cameras[0].center[None] + 1e6)
    assert behind["seen_by_2"] == 0.0


def test_contact_sheets_and_decimation(results):
    from stage.store import TakeReader

    _, _, calib, take = results
    with TakeReader(take) as r:
        s = take_contact_sheets(r, n_frames=2, thumb_width=80)
    assert s["sets"] == [0, 2] and s["cameras"] == list(calib.names)
    assert s["frames"].shape == (2 * 62 + 2, 4 * 82 + 2, 3)
    assert s["masks"].max() == 255
    sheet = contact_sheet([np.zeros((10, 20, 3), np.uint8), None, np.ones((10, 20), bool)], columns=2, thumb_width=20)
    assert sheet.shape == (2 * 12 + 2, 2 * 22 + 2, 3)
    v, f = surface(creature_take("starfish", 1)[1][0], step=8.0)
    v2, f2 = decimate_mesh(v, f, max_faces=1500)
    assert len(f2) <= 1500 and f2.max() < len(v2)
    # decimated vertices stay near the surface they came from
    assert np.abs(creature_take("starfish", 1)[1][0].sdf(v2)).mean() < 5.0


def test_cli_report_writes_the_page(results, tmp_path, capsys):
    from stage.cli import main

    d, *_ = results
    out = tmp_path / "r.html"
    assert main(["report", str(d), "--out", str(out), "--max-frames", "4"]) == 0
    assert out.is_file() and "plotly" in out.read_text()[:5_000_000].lower()
    assert str(out) in capsys.readouterr().out


def test_report_without_take_or_calibration(results, tmp_path):
    d, *_ = results
    only = tmp_path / "only_spine"
    only.mkdir()
    shutil.copy(d / "spine.json", only / "spine.json")
    html = render_report(only)
    assert 'id="view"' in html and 'id="sheets"' not in html and 'id="cameras"' not in html
    assert "the spine alone" in html


def test_process_warnings_reach_the_page(results, tmp_path):
    d, *_ = results
    only = tmp_path / "warned"
    only.mkdir()
    shutil.copy(d / "spine.json", only / "spine.json")
    (only / "report.json").write_text(json.dumps({"frames": 3, "warnings": ["all 16 cameras sit <above> the subject"]}))
    html = render_report(only)
    assert 'class="warn">&#9888; all 16 cameras sit &lt;above&gt; the subject' in html


def test_invalid_input(tmp_path, results):
    d, spine, calib, take = results
    with pytest.raises(FileNotFoundError, match="results directory"):
        render_report(tmp_path / "nope")
    with pytest.raises(NothingToReportError, match="stage process"):
        render_report(tmp_path)
    with pytest.raises(FileNotFoundError, match="take"):
        render_report(d, take=tmp_path / "missing.h5")
    with pytest.raises(ValueError, match="max_frames"):
        render_report(d, max_frames=0)
    with pytest.raises(ValueError, match="max_frames"):
        spine_figure(spine, max_frames=0)
    with pytest.raises(ValueError, match="frame_indices"):
        tip_count_figure([1, 2], frame_indices=[0])
    with pytest.raises(ValueError, match="per_frame"):
        mesh_quality_figure([])
    with pytest.raises(ValueError, match="points"):
        camera_coverage(calib, np.full((2, 3), np.nan))
    with pytest.raises(ValueError, match="columns"):
        contact_sheet([np.zeros((4, 4, 3), np.uint8)], columns=0)
    with pytest.raises(ValueError, match="max_faces"):
        decimate_mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), max_faces=1)
    (tmp_path / "report.json").write_text("{not json")
    with pytest.raises(ValueError, match="cannot read"):
        write_report(tmp_path)


# ----------------------------------------------------------------------------- real browser


@pytest.mark.slow
def test_browser_renders_the_3d_view(results):
    """Headless Chromium opens the report (file://), waits for the plotly 3-D view and checks it is not blank."""
    sync_playwright = sync_playwright_or_skip()
    d, *_ = results
    path = write_report(d, max_frames=8)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shot = ARTIFACTS / "report_3d_view.png"
    errors: list[str] = []
    requests: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.on("request", lambda r: requests.append(r.url))
            page.goto(path.resolve().as_uri(), wait_until="load", timeout=60_000)
            page.wait_for_function(
                "() => { const g = document.getElementById('spine-view');"
                " return g && g._fullLayout && g.querySelector('.gl-container canvas') !== null; }",
                timeout=60_000,
            )
            page.wait_for_timeout(1500)  # let WebGL draw
            view = page.locator("#spine-view")
            view.scroll_into_view_if_needed()
            png = view.screenshot(path=str(shot))
            n_frames = page.evaluate("() => document.getElementById('spine-view')._transitionData._frames.length")
            # step the animation to the last frame: the picture must change
            page.evaluate(
                "() => Plotly.animate('spine-view', ['%d'], {frame: {duration: 0, redraw: true},"
                " transition: {duration: 0}, mode: 'immediate'})" % (FRAMES - 1)
            )
            page.wait_for_timeout(1500)
            png_last = view.screenshot(path=str(ARTIFACTS / "report_3d_view_last.png"))
        finally:
            browser.close()
    print(f"screenshots of the 3-D view: {shot} and {ARTIFACTS / 'report_3d_view_last.png'}")
    assert not errors, errors
    assert all(u.startswith(("file:", "data:", "about:", "blob:")) for u in requests), requests
    assert n_frames == FRAMES
    import cv2

    img, last = (cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR).astype(int) for b in (png, png_last))
    assert img.shape == last.shape and img.shape[0] > 200
    # not blank: many distinct colours, and the surface's warm colour (#d9c3a5; the plotly scene is blue-grey)
    assert len(np.unique(img.reshape(-1, 3) // 8, axis=0)) > 100
    warm = ((img[..., 2] - img[..., 0]) > 15).mean()
    assert warm > 0.005, f"no surface drawn (warm pixel fraction {warm:.4f})"
    # animated: the creature moved between the first and the last frame
    changed = (np.abs(img - last).max(axis=2) > 40).mean()
    assert changed > 0.002, f"the view did not change when stepping the animation ({changed:.4f})"


def test_grid_choice_reaches_the_page(results, tmp_path):
    """The voxel `stage process` chose from the rig, and why, is on the page."""
    d, *_ = results
    only = tmp_path / "grid"
    only.mkdir()
    shutil.copy(d / "spine.json", only / "spine.json")
    grid = {"source": "rig", "resolution": 115, "pixel_footprint": 2.94, "cameras_seeing_subject": 10,
            "pixels_per_voxel": 2.0, "limited_by": "pixel footprint", "voxel": 5.86, "shape": [115, 55, 75]}
    (only / "report.json").write_text(json.dumps({"frames": 3, "grid": grid}))
    html = render_report(only)
    assert "5.86 (115 x 55 x 75 voxels): 2 x the median pixel footprint at the subject (2.94 over 10 cameras)" in html
    # a resolution given (stage process --resolution, a job's parameters.resolution): said without an option
    grid = {"source": "resolution option", "resolution": 32, "voxel": 17.6, "shape": [32, 32, 16]}
    (only / "report.json").write_text(json.dumps({"frames": 3, "grid": grid}))
    assert "17.6 (32 x 32 x 16 voxels): resolution 32, as given" in render_report(only)
