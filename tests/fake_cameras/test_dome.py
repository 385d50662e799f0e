import numpy as np
import pytest

from fake_cameras.dome import look_at, make_dome
from stage.rig import Volume


@pytest.mark.parametrize("n", [4, 7, 12, 24])
def test_every_camera_sees_the_whole_volume(n):
    vol = Volume()
    cal = make_dome(n, size=(320, 240), volume=vol)
    assert len(cal) == n
    assert cal.names == [f"cam{i:02d}" for i in range(n)]
    lo, hi = (np.asarray(b) for b in vol.bounds)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for cam in cal:
        pix, z = cam.project(corners, return_depth=True)
        assert np.all(z > 0)
        assert np.all(cam.in_image(pix)), cam
        # the volume fills most of the frame in at least one image direction
        ext = (pix.max(0) - pix.min(0)) / np.asarray(cam.size)
        assert ext.max() > 0.65
        # camera outside the volume, above the floor
        c = cam.center
        assert c[2] > 0 and np.any((c < lo) | (c > hi))


def test_cameras_differ_and_distortion_is_mild():
    cal = make_dome(12)
    f = np.array([c.K[0, 0] for c in cal])
    assert len(np.unique(np.round(f, 6))) == 12
    d = np.array([c.dist for c in cal])
    assert np.all(np.abs(d[:, :2]) <= [0.05, 0.02]) and np.all(np.abs(d[:, 2:4]) <= 0.001)
    assert np.any(d[:, 0] != 0)
    assert np.all(make_dome(12, distortion=False)[3].dist == 0)
    # at least two elevations: some cameras look down steeply, some nearly level
    elev = np.array([np.degrees(np.arcsin((c.center[2] - 375) / np.linalg.norm(c.center - [0, 0, 375]))) for c in cal])
    assert elev.min() < 20 and elev.max() > 50


def test_deterministic_by_seed():
    assert make_dome(6, seed=3) == make_dome(6, seed=3)
    assert make_dome(6, seed=3) != make_dome(6, seed=4)


def test_look_at_points_the_optical_axis_at_the_target():
    c, tgt = np.array([1000.0, 200.0, 800.0]), np.array([0.0, 0.0, 375.0])
    R = look_at(c, tgt)
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
    fwd = (tgt - c) / np.linalg.norm(tgt - c)
    assert np.allclose(R[2], fwd)
    assert R[1] @ [0, 0, 1] < 0  # image y points down in the world


def test_invalid_input():
    with pytest.raises(ValueError, match="n_cameras"):
        make_dome(3)
    with pytest.raises(ValueError, match="n_cameras"):
        make_dome(25)
    with pytest.raises(ValueError, match="n_cameras"):
        make_dome(4.5)
    with pytest.raises(ValueError, match="size"):
        make_dome(4, size=(0, 480))
    with pytest.raises(ValueError, match="size"):
        make_dome(4, size="big")
    with pytest.raises(ValueError, match="volume"):
        make_dome(4, volume=(0, 0, 0))
    with pytest.raises(ValueError):
        look_at([0, 0, 0], [0, 0, 0])
