"""The Pose2Sim demo (real lab footage, no backdrop, a Qualisys calibration) through the product's
defaults: ``stage import --calibration Calib.qca.txt`` then keying as the footage decides.

Quick form for the suite: frames a quarter of their size on import (``--scale 0.25``), every
frame of the take (a plate from the take needs the whole of it). The full-size run's figures
are in docs/keying.md. What is checked: the footage's default is a plate from the take; the
person is keyed in every camera; and the calibration by projection: the four cameras' silhouette
cones meet in one standing person on the treadmill platform (the largest piece of the hull of
the keyed masks) sits where the README says the person stands in every frame set sampled, and
the hull stands on the platform and reaches a person's height.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pipeline.hull import EmptyHullError, HullCarver
from pipeline.volume import grid_from_volume
from stage.importer import import_take
from stage.keying.take import key_take
from stage.store import TakeReader
from tests.conftest import shared_dataset


def test_pose2sim_demo_keys_with_a_plate_from_the_take_and_the_cones_meet(tmp_path):
    root = shared_dataset("pose2sim_demo")
    take = import_take(root, root / "Calib.qca.txt", tmp_path / "demo.h5", scale=0.25).path
    summary = key_take(take)
    assert summary["mode"] == "plate" and summary["layers"] == [], summary
    with TakeReader(take) as r:
        calib = r.calibration
        masks = [r.masks(c) for c in r.cameras]
        assert r.cameras == ["cam01", "cam02", "cam03", "cam04"] and len(r) == 100
    for c, m in zip(calib.names, masks):
        share = m.mean(axis=(1, 2))
        assert np.mean((share > 0.005) & (share < 0.3)) >= 0.95, (c, np.round(share, 3))
    # the cones meet where the README says the person stands (x -1.55..-0.45 m, y -0.90..0.40 m,
    # z 0..1.70 m): carved on a grid of 64 voxels over that place grown by half a metre, the
    # largest piece's centre lies in the person's box (grown by 0.3 m) in every sampled frame set,
    # and over the take the hull stands on the platform (its lowest voxel within two of z = 0) and
    # reaches 1.4-2.2 m up
    person = np.array([[-1550.0, -900.0, 0.0], [-450.0, 400.0, 1700.0]])
    grid = grid_from_volume(person + [[-500.0, -500.0, 0.0], [500.0, 500.0, 500.0]], 64)
    carver = HullCarver(calib, grid)
    frames = range(0, 100, 5)
    lows, highs = [], []
    for f in frames:
        try:
            occ = carver.carve([m[f] for m in masks], margin=1).occupancy
        except EmptyHullError:
            raise AssertionError(f"frame set {f}: the four cones do not meet") from None
        lab, _ = ndimage.label(occ)
        big = np.argmax(np.bincount(lab.ravel())[1:]) + 1
        pts = grid.lo + (np.argwhere(lab == big) + 0.5) * grid.voxel
        centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
        assert np.all(centre >= person[0] - 300) and np.all(centre <= person[1] + 300), (f, centre)
        z = grid.lo[2] + (np.argwhere(occ)[:, 2] + 0.5) * grid.voxel
        lows.append(z.min())
        highs.append(z.max())
    assert min(lows) <= 2.5 * grid.voxel and 1400 <= max(highs) <= 2200, (min(lows), max(highs))
