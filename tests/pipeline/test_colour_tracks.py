"""Colour feature tracks of an RGB-D camera (pipeline.colour_tracks)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.camera import Camera
from pipeline.colour_tracks import colour_tracks


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
    for kw, name in (({"window": 2}, "window"), ({"levels": -1}, "levels"), ({"max_error": 0.0}, "max_error"),
                     ({"max_jump": -1.0}, "max_jump"), ({"highpass": -1.0}, "highpass")):
        with pytest.raises(ValueError, match=name):
            colour_tracks(a, a, V, np.ones(1, bool), cam, depth, **kw)
