"""Colour feature tracks of an RGB-D camera (pipeline.colour_tracks)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.camera import Camera
from pipeline.colour_tracks import _cell_groups, _local_warps, _warped_lk, colour_tracks, ray_points


def _camera(w=160, h=120, f=150.0):
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return Camera("rgbd", K, np.zeros(5), np.eye(3), np.zeros(3), (w, h))


def _texture(w=160, h=120, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / np.ptp(img) * 200 + 25
    return img.astype(np.uint8)


def test_tracks_follow_a_textured_plane_shifted_by_a_known_sub_pixel_motion():
    """A plane at Z = 500 mm whose texture moves (2.4, -1.3) pixels: every target is the vertex
    moved by exactly that at 500 mm (dx = 500 / f pixels in mm), to 0.1 px (measured 0.06)."""
    cam = _camera()
    a = _texture()
    shift = np.array([2.4, -1.3])
    b = cv2.warpAffine(a, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (160, 120), flags=cv2.INTER_CUBIC,
                       borderMode=cv2.BORDER_REFLECT)
    Z = 500.0
    uv = np.stack(np.meshgrid(np.arange(30, 130, 7.0), np.arange(30, 90, 7.0)), -1).reshape(-1, 2)
    V = cam.unproject(uv, np.full(len(uv), Z))
    depth = np.full((120, 160), Z)
    idx, X, rays = colour_tracks(a, b, V, np.ones(len(V), bool), cam, depth)
    assert len(idx) >= 0.9 * len(V)
    expect = V[idx] + np.r_[shift * Z / 150.0, 0.0]
    assert np.abs(X - expect).max() < 0.1 * Z / 150.0
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    # a vertex not visible is not followed; a landing point without depth is dropped
    vis = np.ones(len(V), bool)
    vis[:5] = False
    hole = depth.copy()
    hole[:, :80] = 0.0
    idx2, X2, _ = colour_tracks(a, b, V, vis, cam, hole)
    assert not np.isin(np.arange(5), idx2).any()
    assert np.all(cam.project(X2)[:, 0] >= 79.0)


def test_masked_background_does_not_hold_a_thin_strip_back():
    """A 10-pixel textured strip moving 3 px over a static textured background: with the masks,
    the strip's tracks move with it (to 0.1 px)."""
    cam = _camera()
    bg = _texture(seed=1)
    fg = _texture(seed=2)
    a, b = bg.copy(), bg.copy()
    ma = np.zeros((120, 160), bool)
    ma[:, 60:70] = True
    mb = np.roll(ma, 3, axis=1)
    a[ma] = fg[ma]
    b[mb] = np.roll(fg, 3, axis=1)[mb]
    Z = 400.0
    uv = np.stack(np.meshgrid(np.arange(61.0, 69.0, 2.0), np.arange(30.0, 90.0, 5.0)), -1).reshape(-1, 2)
    V = cam.unproject(uv, np.full(len(uv), Z))
    depth = np.where(mb, Z, 0.0)
    idx, X, _ = colour_tracks(a, b, V, np.ones(len(V), bool), cam, depth, masks=(ma, mb), max_jump=1.0)
    assert len(idx) >= 0.5 * len(V)
    du = cam.project(X)[:, 0] - uv[idx, 0]
    assert np.abs(du - 3.0).max() < 0.1


def test_warped_tracks_of_a_thin_turning_strip_use_its_own_pixels_only():
    """A 12-pixel textured strip over a static textured background turns 8 degrees about the image
    centre. With the masks, the warped windows see the strip's pixels only (the background and the
    silhouette, which do not move like the texture, are out): to 0.1 px (measured 0.035; translated
    windows with the masks 0.35 px, warped windows without the masks 0.22 px)."""
    cam = _camera()
    bg, fg = _texture(seed=6), _texture(seed=7)
    M = cv2.getRotationMatrix2D((79.5, 59.5), 8.0, 1.0)
    ma = np.zeros((120, 160), bool)
    ma[20:100, 74:86] = True
    mb = cv2.warpAffine(ma.astype(np.uint8), M, (160, 120), flags=cv2.INTER_NEAREST).astype(bool)
    a, b = bg.copy(), bg.copy()
    a[ma] = fg[ma]
    b[mb] = cv2.warpAffine(fg, M, (160, 120), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)[mb]
    nx, ny = 3, 13
    uv = np.stack(np.meshgrid(np.linspace(77, 83, nx), np.linspace(30, 90, ny)), -1).reshape(-1, 2)
    Z = 400.0
    V = cam.unproject(uv, np.full(len(uv), Z))
    truth = uv @ M[:, :2].T + M[:, 2]
    predicted = cam.unproject(truth, np.full(len(uv), Z))
    depth = np.where(mb, Z, 0.0)
    idx, X, _ = colour_tracks(a, b, V, np.ones(len(V), bool), cam, depth, masks=(ma, mb), predicted=predicted,
                              faces=_grid_faces(nx, ny), max_jump=1.0)
    assert len(idx) >= 0.5 * len(V)
    err = np.linalg.norm(cam.project(X) - truth[idx], axis=1)
    assert np.median(err) < 0.1


def _grid_faces(nx, ny):
    i = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def test_local_warps_recover_an_affine_image_motion_exactly():
    rng = np.random.default_rng(3)
    u0 = np.stack(np.meshgrid(np.arange(6.0), np.arange(5.0)), -1).reshape(-1, 2) * 4 + rng.normal(0, 0.3, (30, 2))
    A = np.array([[0.9, -0.35], [0.4, 1.1]])
    u1 = u0 @ A.T + [7.0, -2.0]
    np.testing.assert_allclose(_local_warps(u0, u1, _grid_faces(6, 5)), np.broadcast_to(A, (30, 2, 2)), atol=1e-9)
    # a flat (collinear) neighbourhood has no warp: the identity
    line = np.stack([np.arange(4.0), np.zeros(4)], 1)
    np.testing.assert_array_equal(_local_warps(line, line * 2, np.array([[0, 1, 2], [1, 2, 3]])), np.tile(np.eye(2), (4, 1, 1)))


def _turning_texture(nx, ny, x_range, y_range):
    """A plane at Z = 500 mm whose texture turns 10 degrees about the image centre and moves
    (1.5, -1) px, under an ``nx`` by ``ny`` grid of vertices over the pixel ranges; the
    prediction has the turn but not the move. -> (camera, the two images, the vertices' pixels,
    the vertices, their true pixels, the prediction, the depth image, the grid's triangles)."""
    cam = _camera()
    a = _texture(seed=4)
    M = cv2.getRotationMatrix2D((79.5, 59.5), 10.0, 1.0)
    M[:, 2] += [1.5, -1.0]
    b = cv2.warpAffine(a, M, (160, 120), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    uv = np.stack(np.meshgrid(np.linspace(*x_range, nx), np.linspace(*y_range, ny)), -1).reshape(-1, 2)
    Z = 500.0
    V = cam.unproject(uv, np.full(len(uv), Z))
    truth = uv @ M[:, :2].T + M[:, 2]
    predicted = cam.unproject(truth - [1.5, -1.0], np.full(len(uv), Z))
    return cam, a, b, uv, V, truth, predicted, np.full((120, 160), Z), _grid_faces(nx, ny)


def test_warped_windows_follow_a_turning_texture_that_translated_windows_do_not():
    """A plane at Z = 500 mm whose texture turns 10 degrees about the image centre and moves (1.5, -1)
    pixels; the prediction has the turn but not the move. The warped tracks land on the true
    pixels to 0.05 px (measured 0.007); the translated windows alone (no faces) are 0.32 px off."""
    cam, a, b, uv, V, truth, predicted, depth, F = _turning_texture(9, 6, (45, 115), (35, 85))
    errs = {}
    for name, faces in (("warped", F), ("translated", None)):
        idx, X, _ = colour_tracks(a, b, V, np.ones(len(V), bool), cam, depth, predicted=predicted, faces=faces, max_error=1.0)
        assert len(idx) >= 0.9 * len(V), name
        errs[name] = np.median(np.linalg.norm(cam.project(X) - truth[idx], axis=1))
    assert errs["warped"] < 0.05 and errs["translated"] > 2 * errs["warped"], errs


def test_warped_lk_matches_the_exact_shift_and_flags_windows_without_texture():
    a = _texture(seed=5).astype(np.float32)
    b = np.roll(a, (2, -1), axis=(0, 1))  # content moves by (-1, +2) pixels (x, y)
    p0 = np.array([[50.0, 40.0], [90.0, 70.0]])
    p, ok = _warped_lk(a, b, p0, p0, np.tile(np.eye(2), (2, 1, 1)), window=15)
    assert ok.all()
    np.testing.assert_allclose(p, p0 + [-1.0, 2.0], atol=0.02)
    _, ok = _warped_lk(np.full((60, 60), 9.0), np.full((60, 60), 9.0), p0[:1] / 2, p0[:1] / 2, np.eye(2)[None])
    assert not ok.any()


def test_invalid_input():
    cam = _camera()
    a = _texture()
    V = np.array([[0.0, 0.0, 500.0]])
    depth = np.full((120, 160), 500.0)
    with pytest.raises(ValueError, match="same shape"):
        colour_tracks(a, a[:60], V, np.ones(1, bool), cam, depth)
    with pytest.raises(ValueError, match="depth"):
        colour_tracks(a, a, V, np.ones(1, bool), cam, depth[:60])
    with pytest.raises(ValueError, match="vertices"):
        colour_tracks(a, a, V[:, :2], np.ones(1, bool), cam, depth)
    with pytest.raises(ValueError, match="previous_image and image"):
        colour_tracks(np.zeros((120, 160, 4), np.uint8), a, V, np.ones(1, bool), cam, depth)
    with pytest.raises(ValueError, match="masks"):
        colour_tracks(a, a, V, np.ones(1, bool), cam, depth, masks=(np.ones((5, 5), bool), np.ones((5, 5), bool)))
    ok = np.ones((120, 160), bool)
    with pytest.raises(ValueError, match="masks must be a pair"):
        colour_tracks(a, a, V, np.ones(1, bool), cam, depth, masks=(ok,))
    with pytest.raises(ValueError, match="predicted"):
        colour_tracks(a, a, V, np.ones(1, bool), cam, depth, predicted=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="faces"):
        colour_tracks(a, a, V, np.ones(1, bool), cam, depth, faces=np.array([[0, 1, 2]]))
    for kw, name in (({"window": 2}, "window"), ({"levels": -1}, "levels"), ({"max_error": 0.0}, "max_error"),
                     ({"max_jump": -1.0}, "max_jump"), ({"highpass": -1.0}, "highpass"), ({"cell": -1.0}, "cell")):
        with pytest.raises(ValueError, match=name):
            colour_tracks(a, a, V, np.ones(1, bool), cam, depth, **kw)


def test_ray_points_invalid_input():
    idx = np.array([0, 0, 1])
    targets = np.zeros((3, 3))
    rays = np.tile([0.0, 0.0, 1.0], (3, 1))
    ok, x = ray_points(idx[:0], targets[:0], rays[:0], 2)  # no tracks: nothing determined
    assert not ok.any() and x.shape == (2, 3)
    for args, name in (((idx, targets, rays, -1), "n must"), ((idx, targets, rays, 2.0), "n must"),
                       ((idx, targets, rays, 1), "idx must lie"), ((idx - 1, targets, rays, 2), "idx must lie"),
                       ((idx * 1.0, targets, rays, 2), "idx must be"), ((idx[:, None], targets, rays, 2), "idx must be"),
                       ((idx, targets[:2], rays, 2), "targets"), ((idx, targets + np.nan, rays, 2), "targets"),
                       ((idx, targets, rays[:, :2], 2), "rays must be a finite"), ((idx, targets, 2 * rays, 2), "unit")):
        with pytest.raises(ValueError, match=name):
            ray_points(*args)


def test_warped_tracks_with_a_prediction_one_period_off_are_rejected_or_right():
    """A periodic texture (12-pixel tiles) moved 3 pixels, with a prediction a whole period (12 px)
    too far: the forward flow locks on the wrong tile. The way back starts on its own (not at the
    track's origin), so it finds the nearer tile and the forward-backward check rejects the track:
    every kept track is within 0.5 px of the truth (it kept 20 of 20 tracks, 12 px off, when the
    way back started at the origin)."""
    cam = _camera()
    x = np.arange(160)
    tile = (128 + 80 * np.sin(2 * np.pi * x / 12.0)).astype(np.float32)
    a = np.tile(tile, (120, 1)) + 30 * np.sin(2 * np.pi * np.arange(120) / 17.0)[:, None]
    a = np.clip(a, 0, 255).astype(np.uint8)
    b = np.roll(a, 3, axis=1)
    nx, ny = 5, 4
    uv = np.stack(np.meshgrid(np.linspace(50, 100, nx), np.linspace(40, 80, ny)), -1).reshape(-1, 2)
    Z = 500.0
    V = cam.unproject(uv, np.full(len(uv), Z))
    truth = uv + [3.0, 0.0]
    predicted = cam.unproject(truth + [12.0, 0.0], np.full(len(uv), Z))
    idx, X, _ = colour_tracks(a, b, V, np.ones(len(V), bool), cam, np.full((120, 160), Z), predicted=predicted,
                              faces=_grid_faces(nx, ny), highpass=0.0, max_jump=100.0)
    err = np.linalg.norm(cam.project(X) - truth[idx], axis=1)
    assert np.all(err < 0.5), err


def test_cell_groups_match_a_loop_over_the_cells():
    """Every point in the group of its pixel cell and depth slab; each group's representative
    its member nearest the group's mean pixel (against a loop over the keys, exactly)."""
    rng = np.random.default_rng(7)
    uv = rng.uniform(0, 20, (300, 2))
    z = rng.choice([500.0, 503.0, 520.0], 300)  # 503 shares 500's 5-mm slab, 520 does not
    reps, group = _cell_groups(uv, z, 3.0, 5.0)
    keys = [(int(np.floor(u / 3.0)), int(np.floor(v / 3.0)), int(np.floor(d / 5.0))) for (u, v), d in zip(uv, z)]
    assert len(reps) == len(set(keys))
    for g, r in enumerate(reps):
        members = np.flatnonzero(group == g)
        assert {keys[i] for i in members} == {keys[r]} and r in members
        assert sum(k == keys[r] for k in keys) == len(members)
        dist = np.linalg.norm(uv[members] - uv[members].mean(axis=0), axis=1)
        assert dist[members == r][0] == dist.min()
    np.testing.assert_array_equal(_cell_groups(uv, z, 0.0, 5.0)[0], np.arange(300))


def test_shared_windows_place_every_vertex_through_its_window_model():
    """The turning, moving texture of the warped test under a grid of vertices 1.2 px apart:
    with cells of 3 px (about 6 vertices a window) every vertex lands on its true pixel as well
    as when each follows its own window, median under 0.05 px, worst under 0.2 px (measured
    0.010 / 0.035 px with a window each, 0.010 / 0.024 shared); two vertices of a cell on
    different depth slabs do not share. Within a cell the shared tracks are one window's affine model to
    1e-6 px (measured 3e-13), a window each is not (0.012 px)."""
    cam, a, b, uv, V, truth, predicted, depth, F = _turning_texture(30, 20, (60, 95), (45, 68))
    Z = 500.0
    _, group = _cell_groups(uv, np.full(len(uv), Z), 3.0, 5.0)
    for cell in (0.0, 3.0):
        idx, X, _ = colour_tracks(a, b, V, np.ones(len(V), bool), cam, depth, predicted=predicted, faces=F,
                                  max_error=1.0, cell=cell)
        assert len(idx) >= 0.9 * len(V), cell
        u = cam.project(X)
        err = np.linalg.norm(u - truth[idx], axis=1)
        assert np.median(err) < 0.05 and err.max() < 0.2, (cell, np.median(err), err.max())
        # shared: within a cell the tracks are one window's affine model exactly; a window each: not
        worst = 0.0
        for g in np.unique(group[idx]):
            m = group[idx] == g
            if m.sum() >= 4:
                A = np.c_[uv[idx][m], np.ones(m.sum())]
                fit = A @ np.linalg.lstsq(A, u[m], rcond=None)[0]
                worst = max(worst, float(np.abs(fit - u[m]).max()))
        assert (worst < 1e-6) if cell else (worst > 1e-3), (cell, worst)
    reps, _ = _cell_groups(uv, np.where(np.arange(len(uv)) % 2 == 0, Z, Z + 30.0), 3.0, 5.0)
    assert len(reps) == 2 * len(_cell_groups(uv, np.full(len(uv), Z), 3.0, 5.0)[0])
