"""The armature of a template tracked with its limb/body labels, its parts cut along the spine's limb axes
(pipeline.armature_files.limb_parts, armature_results(parts="limbs"), build_armature(parts=))."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from tests.pipeline.labelled_take import labelled_results, quadruped_take


def test_the_parts_are_the_labels_body_and_every_limb_cut_along_its_axis(tmp_path):
    from pipeline.armature_files import armature_results

    res, labels = labelled_results(tmp_path)
    rig = armature_results(res, parts="limbs")
    seg = rig.segmentation
    assert seg.source == "limbs"
    assert json.loads((res / "rig" / "rig.json").read_text())["segmentation"]["source"] == "limbs"
    assert len(np.unique(seg.labels[labels == -1])) == 1  # the body one part
    for s in range(seg.n_segments):  # no part spans two labels
        assert len(np.unique(labels[seg.labels == s])) == 1
    assert seg.n_segments > len(np.unique(labels))  # the legs bend: some limb is cut
    assert np.array_equal(np.bincount(seg.labels), np.sort(np.bincount(seg.labels))[::-1])  # by decreasing size


def test_without_the_trackings_labels_the_parts_come_from_the_motion(tmp_path, caplog):
    from pipeline.armature_files import limb_parts, load_sequence, tracked_meshes

    res, _ = labelled_results(tmp_path, labels_digest=False)
    V, F, numbers = load_sequence(tracked_meshes(res))
    with caplog.at_level(logging.WARNING):
        assert limb_parts(res, V, F, numbers) is None
    assert "not the ones the template was tracked with" in caplog.text
    (res / "tracked" / "track.json").write_text(json.dumps({"reference_frame": 0, "patch_labels": None}))
    with caplog.at_level(logging.WARNING):
        assert limb_parts(res, V, F, numbers) is None
    assert "stage track --labels" in caplog.text


def test_the_limb_axes_are_the_spines_at_its_frame():
    """``spine_limb_axes``: every limb's finite axis points at the frame, a stand-in for a limb the labels leave
    empty; a limb of the labels without an axis there is one ValueError."""
    from dataclasses import replace

    from pipeline.armature_files import spine_limb_axes

    _, _, spine = quadruped_take()
    labels = np.r_[np.full(8, -1), np.arange(spine.K)]
    axes = spine_limb_axes(spine, labels, 2)
    assert len(axes) == spine.K and all(np.array_equal(a, spine.axes[lid][2]) for a, lid in zip(axes, spine.limb_ids))
    lid = spine.limb_ids[1]
    unseen = {**spine.axes, lid: spine.axes[lid].copy()}
    unseen[lid][2, 1:] = np.nan  # one point left at frame 2
    unseen = replace(spine, axes=unseen)
    assert np.array_equal(spine_limb_axes(unseen, labels[labels != 1], 2)[1], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="no axis at the spine's frame 2"):
        spine_limb_axes(unseen, labels, 2)
    with pytest.raises(ValueError, match="no axis"):
        spine_limb_axes(spine, np.r_[labels, spine.K], 2)


def test_invalid_input(tmp_path):
    from pipeline.armature import build_armature
    from pipeline.armature_files import armature_results

    res, labels = labelled_results(tmp_path)
    for parts in ("bones", labels):
        with pytest.raises(ValueError, match="parts"):
            armature_results(res, parts=parts)
    tracks, F, _ = quadruped_take()
    with pytest.raises(ValueError, match="parts"):
        build_armature(tracks, F, parts=labels[:-1] + 1)
    with pytest.raises(ValueError, match="parts"):
        build_armature(tracks, F, parts=labels)  # the body's -1
    with pytest.raises(ValueError, match="parts: 'motion'"):
        build_armature(tracks, F, parts=[labels + 1, "motion"])
