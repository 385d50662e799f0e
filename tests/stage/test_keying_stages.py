"""Silhouettes where the backdrop does not fill the view, on simulated stages with ground truth.

Footage is imported without a rig file (image folders and a calibration, as another rig's
footage arrives; the capture volume given as ``stage process --volume`` does), so the keying
mode and layers are the footage's own default
(:func:`stage.keying.take.choose_key_mode`): a green floor before textured walls gives chroma
with the volume and graph-cut layers, a stage without any backdrop a plate from the take.
Tolerances: mask IoU >= 0.95 in every camera (pooled over the frames); the hull from the keyed
masks within one voxel of the hull from the true masks (every voxel of each lies within one
voxel of the other), on a grid of 64 voxels along the subject's longest side.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from calib.formats import write_calibration
from fake_cameras.dome import make_dome
from fake_cameras.take import simulate_take, stage_backdrop
from pipeline.hull import HullCarver
from pipeline.process import process_take
from pipeline.volume import grid_from_volume
from stage.importer import import_take
from stage.keying import iou
from stage.rig import Volume
from stage.store import TakeReader

FRAMES = 16
N_CAMERAS = 6
SIZE = (400, 300)


def _travel_direction(calib) -> float:
    """A walking direction no camera looks along (a plate from the take needs the subject to
    leave every pixel for most of the take)."""
    az = np.arctan2(calib.centers()[:, 1], calib.centers()[:, 0])
    cand = np.linspace(0, np.pi, 181)
    score = [np.min(np.abs(np.angle(np.exp(2j * (a - az))))) for a in cand]
    return float(cand[int(np.argmax(score))])


def _stage(kind: str, tmp_path):
    vol = Volume(center=(0.0, 0.0, 500.0), size=(2400.0, 2400.0, 1000.0))
    calib = make_dome(N_CAMERAS, size=SIZE, volume=vol, seed=2, distortion=True)
    a = _travel_direction(calib)
    sim = simulate_take("biped", calibration=calib, frames=FRAMES, backdrop=stage_backdrop(kind, calibration=calib,
                        volume=vol), seed=2, volume=vol, scale=1.6, travel=(1800 * np.cos(a), 1800 * np.sin(a)),
                        workers=1)
    footage = tmp_path / "footage"
    for c, name in enumerate(calib.names):
        (footage / name).mkdir(parents=True)
        for f in range(FRAMES):
            cv2.imwrite(str(footage / name / f"{f:03d}.png"), sim.images[f, c])
    cal = write_calibration(calib, tmp_path / "calibration.json")
    take = import_take(footage, cal, tmp_path / "t.h5").path
    return sim, take


def _check_masks_and_hull(sim, take):
    with TakeReader(take) as r:
        keyed = np.stack([r.masks(c) for c in sim.calibration.names], axis=1)  # (F, C, H, W)
    for c, name in enumerate(sim.calibration.names):
        inter = (keyed[:, c] & sim.masks[:, c]).sum()
        union = (keyed[:, c] | sim.masks[:, c]).sum()
        assert inter / union >= 0.95, (name, inter / union, [round(iou(keyed[f, c], sim.masks[f, c]), 3)
                                                             for f in range(FRAMES)])
    for f in (0, FRAMES // 2, FRAMES - 1):
        truth = _subject_box(sim, f)
        grid = grid_from_volume(truth, 64)
        carver = HullCarver(sim.calibration, grid)
        a = carver.carve(list(keyed[f]), margin=1).occupancy
        b = carver.carve(list(sim.masks[f]), margin=1).occupancy
        ball = np.ones((3, 3, 3), bool)
        assert not (a & ~binary_dilation(b, ball)).any(), f"frame {f}: keyed hull beyond one voxel of the true one"
        assert not (b & ~binary_dilation(a, ball)).any(), f"frame {f}: true hull beyond one voxel of the keyed one"


def _subject_box(sim, f) -> np.ndarray:
    """The subject's box from its capsules (radii included), padded by 20 %."""
    pose = sim.poses[f]
    r = np.maximum(pose.r0, pose.r1)[:, None]
    lo = np.minimum(pose.p0 - r, pose.p1 - r).min(axis=0)
    hi = np.maximum(pose.p0 + r, pose.p1 + r).max(axis=0)
    pad = 0.2 * (hi - lo).max()
    return np.array([lo - pad, hi + pad])


@pytest.mark.parametrize("kind, mode, layers", [("floor", "chroma", ["volume", "graphcut"]), ("none", "plate", [])])
def test_partial_backdrop_stage_keys_to_the_true_masks(tmp_path, kind, mode, layers):
    sim, take = _stage(kind, tmp_path)
    out = tmp_path / "out"
    lo, hi = sim.volume.bounds
    # the stage's capture volume, as `stage process --volume` gives it for footage without a rig file
    process_take(take, out, steps=("key",), params={"volume": (*lo, *hi)})
    record = json.loads((out / "process.json").read_text())
    assert record["key"]["mode"] == mode and record["key"]["layers"] == layers, record["key"]
    if "graphcut" in layers:
        assert record["refine"]["masks"] == FRAMES * N_CAMERAS
    _check_masks_and_hull(sim, take)
