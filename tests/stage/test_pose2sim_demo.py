"""The Pose2Sim demo (real lab footage, no backdrop, a Qualisys calibration) through the product's
defaults: ``stage import --calibration Calib.qca.txt`` then keying as the footage decides.

Quick form for the suite: frames a quarter of their size on import (``--scale 0.25``), every
frame of the take (a plate from the take needs the whole of it). The full-size run's figures
are in docs/keying.md. What is checked: the footage's default is a plate from the take; the
person is keyed in every camera; and the calibration by projection: the four cameras' silhouette
cones meet in one standing person on the treadmill platform (the largest piece of the hull of
the keyed masks) sits where the README says the person stands in every frame set sampled, and
the hull stands on the platform and reaches a person's height. Then the product's defaults
after keying: the subject's box (:func:`pipeline.subject_box.find_subject_box`) finds the person
in every sampled frame set and is a fraction of the cameras' shared view, and the surface step's
hull (:func:`pipeline.silhouette_refine.subject_hull`) is the person, nearly all in one piece.

The issue's targets on this footage with defaults -- the hull one piece in 95 % of the frame sets,
median silhouette consistency >= 0.85 in every camera, K = 5 -- need the whole ``stage process``
(minutes, not a suite test); what it reaches is in docs/keying.md with the command.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pipeline.hull import EmptyHullError, HullCarver
from pipeline.silhouette_refine import subject_hull
from pipeline.subject_box import find_subject_box
from pipeline.volume import grid_from_volume, volume_from_cameras
from stage.importer import import_take
from stage.keying.params import PLATE_CLOSE_RELATIVE
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
    frames = range(0, 100, 10)
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

    # the subject's box from every 10th frame set (the product searches all): the person in every
    # one, the box holds where the README says the person stands and is at most half the cameras'
    # shared view along every axis (measured 3.2 x 1.9 x 2.8 m of 8.8 x 6.5 x 6.9 m; before the
    # box counted the cameras that find a cube, it was the whole shared view)
    shared = np.asarray(volume_from_cameras(calib), float).reshape(2, 3)
    sets = range(0, 100, 10)
    sb = find_subject_box([[m[k] for m in masks] for k in sets], calib, shared)
    assert sb.stats["with_subject"] == len(sets), sb.stats
    assert np.all(sb.bounds[0] <= person[0]) and np.all(person[1] <= sb.bounds[1]), sb.bounds
    assert np.all(sb.bounds[1] - sb.bounds[0] <= 0.5 * (shared[1] - shared[0])), (sb.bounds, shared)
    # the surface step's hull on a grid of 64 voxels over the box: the largest piece is the person
    # in every sampled set and holds at least 90 % of the hull's voxels in each (the figures: docs/keying.md);
    # silhouette parts the person does not explain are dropped
    grid = grid_from_volume(sb.bounds, 64)
    carver = HullCarver(calib, grid)
    shares = []
    for f in sets:
        # as stage process carves plate-keyed masks: one camera's miss bridged in the keyer's gaps
        sh = subject_hull([m[f] for m in masks], carver, margin=1, bridge_gaps=PLATE_CLOSE_RELATIVE)
        lab, _ = ndimage.label(sh.occupancy, structure=np.ones((3, 3, 3), bool))
        count = np.bincount(lab.ravel())[1:]
        pts = grid.lo + (np.argwhere(lab == np.argmax(count) + 1) + 0.5) * grid.voxel
        centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
        assert np.all(centre >= person[0] - 300) and np.all(centre <= person[1] + 300), (f, centre)
        shares.append(count.max() / count.sum())
    assert np.median(shares) >= 0.95 and min(shares) >= 0.9, np.round(shares, 3)
