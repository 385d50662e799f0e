"""Silhouette consistency (pipeline.consistency): the projection of a surface against the exact
silhouette, and ``stage process`` naming the one camera whose masks are corrupted."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import trimesh

from fake_cameras.record import record_take
from fake_cameras.take import simulate_take
from pipeline.consistency import mesh_silhouette, silhouette_consistency, silhouette_iou
from tests.pipeline.simrig import dome, look_at


def _sphere_hits(cam, centre, radius) -> np.ndarray:
    """Exact silhouette of a sphere: pixel-centre rays that meet it (lens distortion included)."""
    w, h = cam.size
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    o, d = cam.rays(np.stack([u.ravel(), v.ravel()], axis=1).astype(float))
    oc = o - np.asarray(centre, float)
    b = d @ oc
    disc = b * b - (d * d).sum(axis=1) * (oc @ oc - radius**2)
    return ((disc >= 0) & (b < 0)).reshape(h, w)


@pytest.mark.parametrize("distortion", [(0, 0, 0, 0, 0), (-0.08, 0.02, 0.0005, -0.0003, 0.0)])
def test_projection_of_a_sphere_is_its_silhouette(distortion):
    """An icosphere (5120 faces, radius 300 mm, 2 m away, about 90 px across) projected by
    :func:`mesh_silhouette` against the exact silhouette of the sphere: IoU at least 0.97 (the
    icosphere's flat faces lie inside the sphere), and the same with the faces turned the other
    way (a closed surface's back faces cover its projection too)."""
    cam = look_at("c", (0, -2000, 300), (0, 0, 300), size=(320, 240), dist=distortion)
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=300.0)
    v = mesh.vertices + [0.0, 0.0, 300.0]
    exact = _sphere_hits(cam, (0, 0, 300), 300.0)
    sil = mesh_silhouette(v, mesh.faces, cam)
    assert silhouette_iou(exact, sil) >= 0.97
    assert silhouette_iou(exact, mesh_silhouette(v, mesh.faces[:, ::-1], cam)) >= 0.97
    assert sil.sum() <= exact.sum() and not (sil & ~exact).any()  # inscribed: never more than the sphere


def test_iou_is_the_formula():
    rng = np.random.default_rng(0)
    a, b = rng.random((40, 50)) < 0.3, rng.random((40, 50)) < 0.4
    assert silhouette_iou(a, b) == pytest.approx((a & b).sum() / (a | b).sum())
    assert np.isnan(silhouette_iou(np.zeros((3, 3), bool), np.zeros((3, 3), bool)))
    cal = dome(4, size=(160, 120))
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=200.0)
    v = mesh.vertices + [0.0, 0.0, 300.0]
    masks = [mesh_silhouette(v, mesh.faces, c) for c in cal]
    masks[1] = None
    iou = silhouette_consistency(v, mesh.faces, masks, cal)
    assert np.isnan(iou[1]) and np.allclose(iou[[0, 2, 3]], 1.0)


def _fill_reference(out: np.ndarray, tri: np.ndarray) -> None:
    """Slow reference of the raster: every pixel centre of each triangle's bounding box tested
    against its three edges (edges included), one triangle at a time."""
    h, w = out.shape
    for k in range(tri.shape[1]):
        t = tri[:, k]
        lo = np.maximum(np.ceil(t.min(axis=0)), 0).astype(int)
        hi = np.minimum(np.floor(t.max(axis=0)), [w - 1, h - 1]).astype(int)
        if (hi < lo).any():
            continue
        py, px = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
        inside = np.ones(px.shape, bool)
        for i, j in ((0, 1), (1, 2), (2, 0)):
            (ax, ay), (bx, by) = t[i], t[j]
            inside &= (bx - ax) * (py - ay) - (by - ay) * (px - ax) <= 0
        out[py[inside], px[inside]] = 1


def test_the_raster_is_exact_on_pixel_centres_and_windows():
    """The run-per-row raster against the slow per-pixel reference, on random clockwise
    triangles up to 40 px (within the exact raster's size range), half of them with vertices on
    half-pixel positions (pixel centres on edges and corners) and horizontal edges: the same
    pixels, on the whole image and on a window of it (tolerance: none)."""
    from pipeline.consistency import _fill

    rng = np.random.default_rng(0)
    for trial in range(12):
        tri = rng.uniform(-10, 110, (1, 200, 2)) + rng.uniform(-20, 20, (3, 200, 2))
        if trial % 2:
            tri = np.round(tri * 2) / 2
        if trial % 3 == 0:
            tri[1, :, 1] = tri[0, :, 1]
        d1, d2 = tri[1] - tri[0], tri[2] - tri[0]
        area = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
        tri = np.where((area > 0)[None, :, None], tri[::-1], tri)[:, area != 0]
        whole, ref = np.zeros((90, 100), np.uint8), np.zeros((90, 100), np.uint8)
        _fill(whole, tri)
        _fill_reference(ref, tri)
        assert np.array_equal(whole, ref), trial
        window = np.zeros((40, 50), np.uint8)
        _fill(window, tri, origin=(30, 20))
        assert np.array_equal(window, ref[20:60, 30:80]), trial


def test_consistency_on_windows_equals_the_whole_image():
    """:func:`silhouette_consistency` works on the window around each mask and projection; the
    same IoU (exactly) as the projection over the whole image against the whole mask grown by
    the margin, with specks of noise far from the subject and a camera whose mask is empty."""
    import cv2

    cal = dome(6, size=(200, 150))
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=180.0)
    rng = np.random.default_rng(3)
    v = mesh.vertices * [1.0, 0.6, 2.0] + [20.0, -10.0, 400.0] + rng.normal(0, 4, mesh.vertices.shape)
    masks = []
    for c in cal:
        m = mesh_silhouette(v * [1.05, 1.0, 0.97], mesh.faces, c)
        m[rng.random(m.shape) < 0.001] = True
        masks.append(m)
    masks[4] = np.zeros_like(masks[4])
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    expected = [silhouette_iou(cv2.dilate(m.view(np.uint8), disk).view(bool), mesh_silhouette(v, mesh.faces, c))
                for m, c in zip(masks, cal)]
    got = silhouette_consistency(v, mesh.faces, masks, cal, margin=1)
    assert np.array_equal(got, np.array(expected)) and got[4] == 0.0


def test_invalid_input():
    cal = dome(2, size=(160, 120))
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=200.0)
    with pytest.raises(ValueError, match="camera"):
        mesh_silhouette(mesh.vertices, mesh.faces, "cam")
    with pytest.raises(ValueError, match="vertices"):
        mesh_silhouette(mesh.vertices[:, :2], mesh.faces, cal[0])
    with pytest.raises(ValueError, match="faces"):
        mesh_silhouette(mesh.vertices, mesh.faces + 1000, cal[0])
    with pytest.raises(ValueError, match="faces"):
        mesh_silhouette(mesh.vertices, mesh.faces.astype(float), cal[0])
    with pytest.raises(ValueError, match="shape"):
        silhouette_iou(np.zeros((3, 3)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="calibration"):
        silhouette_consistency(mesh.vertices, mesh.faces, [None, None], "cal")
    with pytest.raises(ValueError, match="one mask per camera"):
        silhouette_consistency(mesh.vertices, mesh.faces, [None], cal)
    with pytest.raises(ValueError, match="margin"):
        silhouette_consistency(mesh.vertices, mesh.faces, [None, None], cal, margin=-1)
    with pytest.raises(ValueError, match="cam01"):
        silhouette_consistency(mesh.vertices, mesh.faces, [None, np.zeros((5, 5), bool)], cal)


def test_process_names_the_camera_with_corrupted_masks(tmp_path, caplog, capsys):
    """Eight cameras, true silhouettes, except that camera 2's keyer kept a wall: a block of
    foreground over the left third of its image in every frame. The subject the other cameras
    see does not explain that block: it is dropped before carving
    (:func:`pipeline.silhouette_refine.subject_hull`), and ``stage process`` names camera 2 -- and
    only it -- for the share of its silhouette dropped; ``consistency.json`` holds every camera's
    IoU per frame set (of the silhouettes the hull was carved from) and the dropped shares,
    ``report.json`` the medians, and the report plots them with the worst frames."""
    from pipeline.report import render_report

    def grow(m):
        m[:, 40:200, :100] = True

    sim, path, out = _processed_with_one_camera_edited(tmp_path, caplog, 2, grow, n_cameras=8, frames=3,
                                                        size=(320, 240), seed=2)
    names = list(sim.calibration.names)
    doc = json.loads((out / "consistency.json").read_text())
    assert doc["cameras"] == names and len(doc["iou"]) == 8 and all(len(r) == 3 for r in doc["iou"])
    assert doc["low"] == [] and doc["dropping"] == [names[2]]
    assert doc["dropped"][names[2]] > 0.2 and max(d for n, d in doc["dropped"].items() if n != names[2]) == 0.0
    assert min(doc["median"].values()) >= 0.85
    said = [r.getMessage() for r in caplog.records if "silhouette consistency" in r.getMessage()]
    assert len(said) == 1 and names[2] in said[0]
    printed = capsys.readouterr().out
    assert "silhouette consistency" in printed and "subject box" in printed
    report = json.loads((out / "report.json").read_text())
    assert report["consistency"]["dropping"] == [names[2]]
    assert any(names[2] in w for w in report["warnings"])
    page = render_report(out, take=path)
    assert 'id="consistency"' in page and "Worst frames" in page


def test_process_names_the_camera_whose_masks_miss_part_of_the_subject(tmp_path, caplog):
    """Six cameras, true silhouettes, except that camera 4's miss the upper half of the subject in
    every frame (a keyer that lost the torso). That camera carves the half from the hull for
    every camera, so the others' IoU drops and its own does not; the hull carved without it
    explains the others' silhouettes better (:func:`pipeline.consistency.leave_one_out_gain`), and
    ``stage process`` names camera 4 -- and only it -- as missing part of the subject."""

    def lose_the_upper_half(m):
        for f in range(len(m)):
            rows = np.flatnonzero(m[f].any(axis=1))
            m[f, : rows[len(rows) // 2]] = False

    sim, _, out = _processed_with_one_camera_edited(tmp_path, caplog, 4, lose_the_upper_half, n_cameras=6, frames=2,
                                                    size=(240, 180), seed=3)
    names = list(sim.calibration.names)
    doc = json.loads((out / "consistency.json").read_text())
    assert doc["misses"] == [names[4]], doc["missing"]
    # measured: camera 4 +0.048, the others -0.004 .. +0.001 (mean over the other cameras' IoU)
    assert doc["missing"][names[4]] > 0.03 and max(v for n, v in doc["missing"].items() if n != names[4]) < 0.01
    said = [r.getMessage() for r in caplog.records if "miss part of the subject" in r.getMessage()]
    assert len(said) == 1 and names[4] in said[0]


def _processed_with_one_camera_edited(tmp_path, caplog, camera: int, edit, **take):
    """A simulated starfish take (``take``: :func:`simulate_take`'s keywords) with true masks, camera
    ``camera``'s edited in place by ``edit(masks)``, processed to the surface with warnings caught:
    -> (the simulation, the take's path, the results directory)."""
    from stage.cli import main
    from stage.store import write_masks

    sim = simulate_take("starfish", **take)
    path = record_take(sim, tmp_path / "take.h5")
    for c, name in enumerate(sim.calibration.names):
        m = sim.masks[:, c].copy()
        if c == camera:
            edit(m)
        write_masks(path, name, m, params={"source": "ground truth"})
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING, logger="pipeline.process"):
        assert main(["process", str(path), "--out", str(out), "--until", "surface", "--workers", "0",
                     "--no-progress"]) == 0
    return sim, path, out


def test_leave_one_out_invalid_input():
    from pipeline.consistency import leave_one_out_gain
    from pipeline.hull import HullCarver
    from pipeline.volume import grid_from_volume

    cal = dome(3, size=(80, 60))
    carver = HullCarver(cal, grid_from_volume(np.array([[-300.0, -300.0, 0.0], [300.0, 300.0, 600.0]]), 16))
    with pytest.raises(ValueError, match="one mask per camera"):
        leave_one_out_gain([None], carver)
    assert np.isnan(leave_one_out_gain([np.zeros((60, 80), bool)] * 3, carver)).all()  # nothing to carve


def test_poor_sets_are_those_whose_median_over_the_cameras_is_low():
    """The median over the cameras of every frame set (NaN skipped, a set with none NaN), against the threshold."""
    from pipeline.consistency import poor_sets

    iou = np.array([[0.9, 0.5, np.nan, 0.79, 0.95],
                    [0.8, 0.4, np.nan, 0.81, np.nan],
                    [0.2, 0.9, np.nan, 0.70, np.nan]])
    sets, median = poor_sets(iou)
    assert sets == [1, 3]  # 0.5 and 0.79 below 0.8; set 0's median 0.8 is not; set 2 has none
    np.testing.assert_allclose(median, [0.8, 0.5, np.nan, 0.79, 0.95], equal_nan=True)
    assert poor_sets(iou, threshold=0.6)[0] == [1]


def test_walls_reached_are_the_volumes_sides_that_cut_the_subject_for_a_while():
    """A box cut by the volume at x = -375, x = 375 and the floor z = 0, inside it along y. Frame sets 0 and 4
    reach the x walls (0 and 1 the low one), every set the floor: the floor is left out, y (inside the volume)
    is no wall even where a surface reaches the box's side, and only the sets judged are named."""
    from pipeline.consistency import walls_reached

    box = [[-375.0, -100.0, 0.0], [375.0, 150.0, 400.0]]
    volume = [[-375.0, -375.0, 0.0], [375.0, 375.0, 750.0]]
    bounds = np.array([[[-376.0, -50, 2], [-200, 100, 300]],
                       [[-370.0, -50, 3], [100, 149, 300]],
                       [[-200.0, -99, 1], [200, 100, 300]],
                       [[np.nan] * 3, [np.nan] * 3],  # no surface
                       [[250.0, -50, 0], [375, 100, 300]]])
    assert walls_reached(bounds, box, volume, sets=[0, 4], tol=10.0) == {"x = -375": [0], "x = 375": [4]}
    assert walls_reached(bounds, box, volume, sets=[2], tol=10.0) == {}  # y: the box ends inside the volume
    # a box inside the volume everywhere: no wall
    assert walls_reached(bounds, box, [[-500.0, -375, -10], [500, 375, 750]], sets=[0, 4], tol=10.0) == {}


def test_poor_sets_and_walls_invalid_input():
    from pipeline.consistency import poor_sets, walls_reached

    for bad in (np.zeros(3), np.full((2, 2), 1.5), np.full((2, 2), np.inf)):
        with pytest.raises(ValueError, match="iou"):
            poor_sets(bad)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="threshold"):
            poor_sets(np.ones((2, 2)), threshold=bad)
    b, box = np.zeros((2, 2, 3)), np.array([[0.0] * 3, [1.0] * 3])
    with pytest.raises(ValueError, match="bounds"):
        walls_reached(np.zeros((2, 3)), box, box, sets=[0], tol=1.0)
    with pytest.raises(ValueError, match="box"):
        walls_reached(b, np.zeros(3), box, sets=[0], tol=1.0)
    with pytest.raises(ValueError, match="volume"):
        walls_reached(b, box, [[0, 0, 0], [1, 1, np.nan]], sets=[0], tol=1.0)
    with pytest.raises(ValueError, match="sets"):
        walls_reached(b, box, box, sets=[2], tol=1.0)
    for bad in (0.0, -1.0, float("nan"), True):
        with pytest.raises(ValueError, match="tol"):
            walls_reached(b, box, box, sets=[0], tol=bad)


def test_process_says_the_frame_sets_a_capture_volume_cuts_the_subject_in(tmp_path):
    """The quadruped walks 900 mm along x through the rig's 750 mm capture volume in 4 frame sets: in the first
    and the last its front or back is beyond the volume's wall and the surfaces are cut flat there; every camera's
    median over the take hides where. ``stage process`` names those frame sets and the walls (the floor it stands
    on left out)."""
    from pipeline.process import process_take

    sim = simulate_take("quadruped", n_cameras=6, frames=4, size=(240, 180), seed=7, travel=(900.0, 0.0))
    run = process_take(record_take(sim, tmp_path / "t.h5"), tmp_path / "r", steps=("key", "surface"), executor=None)
    said = [w for w in run.report["warnings"] if "the surface explains little" in w]
    assert len(said) == 1, run.report["warnings"]
    assert said[0].startswith("frame sets 0, 3: ") and "wall at x = -375 (frame set 0), x = 375 (frame set 3)" in said[0]
    assert "z = " not in said[0] and "give a volume that holds it" in said[0]


def test_a_camera_is_judged_without_the_frame_sets_the_capture_volumes_walls_explain(tmp_path, monkeypatch):
    """Frame sets where the walls cut the subject are said once by their own warning; the per-camera warning judges a
    camera on the others: cam1, poor only in the three walled sets of five, is not named; cam2, poor in every set, is
    (with its median over the two others)."""
    from types import SimpleNamespace

    import pipeline.process.steps as steps
    from pipeline.process.records import frame_name

    iou = {"cam0": [0.95] * 5, "cam1": [0.5, 0.5, 0.5, 0.95, 0.95], "cam2": [0.6, 0.6, 0.6, 0.55, 0.55]}
    (tmp_path / "frames").mkdir()
    for k in range(5):
        (tmp_path / "frames" / f"{frame_name(k)}.json").write_text(
            json.dumps({"consistency": {c: v[k] for c, v in iou.items()}}))
    said = []
    ctx = SimpleNamespace(take=SimpleNamespace(cameras=list(iou), n_sets=5), out=tmp_path, warn=said.append,
                          made=SimpleNamespace())
    monkeypatch.setattr(steps, "_name_poor_sets", lambda ctx, iou: {0, 1, 2})
    monkeypatch.setattr(steps, "_name_missing", lambda ctx, iou, doc: None)
    steps._write_consistency(ctx)
    assert [w.split(":")[0] for w in said] == ["camera cam2"] and "consistency 0.55 " in said[0], said
    doc = json.loads((tmp_path / "consistency.json").read_text())
    assert doc["walled_sets"] == [0, 1, 2] and doc["low"] == ["cam2"] and doc["median"]["cam1"] == 0.5
