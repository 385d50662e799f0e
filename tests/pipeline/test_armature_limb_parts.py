"""The armature of a template tracked with its limb/body labels, its parts cut along the spine's limb axes
(pipeline.armature_files.limb_parts, armature_results(parts="limbs"), build_armature(parts=))."""

from __future__ import annotations

import io
import json
import logging

import numpy as np
import pytest

from tests.pipeline.labelled_take import labelled_results, quadruped_take


def test_the_parts_are_the_labels_body_and_every_limb_cut_along_its_axis(tmp_path):
    from pipeline.armature_files import armature_results

    res, labels = labelled_results(tmp_path)  # a tracking of an earlier version: the labels computed again
    assert not (res / "tracked" / "labels.npy").exists()
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


def test_the_parts_follow_the_labels_the_tracking_wrote(tmp_path, caplog):
    """``tracked/labels.npy``: the labels the tracking cut its patches at, though the spine's labels of the tracked
    template are others (``stage track --template``, or the recomputation differing), are the parts' labels."""
    from pipeline.armature_files import limb_parts, load_sequence, tracked_meshes

    _, spines = labelled_results(tmp_path / "a")
    used = spines.copy()
    used[spines == 0] = -1  # limb 0 the body's
    res, _ = labelled_results(tmp_path / "b", tracked_labels=used)
    V, F, numbers = load_sequence(tracked_meshes(res))
    with caplog.at_level(logging.WARNING):
        seg = limb_parts(res, V, F, numbers)
    assert seg is not None and not caplog.records
    assert len(np.unique(seg[used == -1])) == 1  # the body, limb 0 with it, one part
    for s in np.unique(seg):
        assert len(np.unique(used[seg == s])) == 1


def test_the_armature_rounds_segments_are_the_cuts_seams(tmp_path, caplog):
    """A tracking whose kept armature round tracked with a limbs armature (``tracked/rig_segments.npy``, its digest in
    ``rig_prior``): its segments are the cuts' ``seams``; a file that is not the one track.json names is one line, and
    the cuts are made without it."""
    from pipeline.armature_files import limb_parts, load_sequence, spine_limb_axes, tracked_meshes
    from pipeline.armature_spine import reference_frame
    from pipeline.limb_segments import limb_segments
    from pipeline.spine_format import read_spine
    from pipeline.track_frames import labels_digest, write_round_segments

    res, labels = labelled_results(tmp_path)
    V, F, numbers = load_sequence(tracked_meshes(res))
    spine = read_spine(res / "spine.json")
    ref = reference_frame(spine)
    axes = spine_limb_axes(spine, labels, ref)
    plain = limb_segments(V, labels, axes, reference=ref, rho="limb", centres=True)
    rounds = np.where(labels < 0, 0, 1 + labels * 2 + (V[ref, :, 2] > np.median(V[ref, :, 2])))  # a made-up round
    prior = {}
    write_round_segments(res, rounds, prior)
    assert prior == {"segments_sha256": labels_digest(rounds)}
    report = json.loads((res / "tracked" / "track.json").read_text())
    (res / "tracked" / "track.json").write_text(json.dumps({**report, "rig_prior": {"segments_sha256": "0" * 64}}))
    with caplog.at_level(logging.WARNING):
        assert np.array_equal(limb_parts(res, V, F, numbers), plain)  # not the file track.json names: cut without
    assert "do not keep off the armature round's seams" in caplog.text and "rig_segments.npy is not the segments" in caplog.text
    job = [getattr(r, "job_message", "") for r in caplog.records if "seams" in r.getMessage()]
    assert job[0].startswith("parameters rig.parts 'limbs': the cuts do not keep off") and "parts='" not in job[0]
    (res / "tracked" / "track.json").write_text(json.dumps({**report, "rig_prior": prior}))
    seg = limb_parts(res, V, F, numbers)
    assert not np.array_equal(seg, plain)
    assert np.array_equal(seg, limb_segments(V, labels, axes, reference=ref, rho="limb", faces=F, seams=rounds,
                                             centres=True))
    assert np.array_equal(limb_parts(res, V, F, numbers), seg)
    (res / "tracked" / "track.json").write_text(json.dumps(report))  # no round: the file is not read
    assert np.array_equal(limb_parts(res, V, F, numbers), plain)


def test_a_labels_file_that_is_not_the_trackings_is_one_line(tmp_path, caplog):
    """A truncated ``tracked/labels.npy``, one of another vertex count or not the digest's: one warning naming the
    file, and the labels are computed again (the parts when they are the tracking's, else the motion's)."""
    from pipeline.armature_files import limb_parts, load_sequence, tracked_meshes

    res, labels = labelled_results(tmp_path / "a", tracked_labels=None)
    V, F, numbers = load_sequence(tracked_meshes(res))
    other = labels.copy()
    other[labels == 0] = -1
    path = res / "tracked" / "labels.npy"
    buf = io.BytesIO()
    np.save(buf, labels)
    for bad, why in ((buf.getvalue()[:100], "cannot be read"), (b"", "cannot be read"), (other, "patch_labels_sha256"),
                     (labels[:-1], "not the template's"), (labels.astype(np.int32), "not the template's")):
        if isinstance(bad, bytes):
            path.write_bytes(bad)
        else:
            np.save(path, bad)
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            assert limb_parts(res, V, F, numbers) is not None  # the spine's labels again are the tracking's
        assert len(caplog.records) == 1 and "labels.npy" in caplog.text and why in caplog.text, caplog.text
    res, _ = labelled_results(tmp_path / "b", tracked_labels=other)  # the spine's are not the tracking's
    (res / "tracked" / "labels.npy").write_bytes(buf.getvalue()[:100])
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert limb_parts(res, V, F, numbers) is None
    assert len(caplog.records) == 1 and "cannot be read" in caplog.text and "motion segmentation" in caplog.text


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
