"""A template tracked with its limb/body labels, shared by the tests of ``armature_results(parts="limbs")`` and
``stage armature --parts limbs``: the simulated quadruped carried through five times, its spine and track.json."""

from __future__ import annotations

import functools
import hashlib
import json

import numpy as np


@functools.lru_cache(maxsize=1)
def quadruped_take(voxel: float = 12.0, times: tuple = (0.2, 0.35, 0.5, 0.65, 0.8)):
    """The simulated quadruped's surface at the middle time (marching cubes of its exact distance, the spine's
    rest frame) carried through ``times`` by its capsules (a tracked template), and a one-junction spine of
    those frames whose limb axes run from the body's centre through the creature's limb axes at that time."""
    from fake_cameras.creatures import make_creature
    from fake_cameras.surface_motion import surface_point_tracks
    from tests.pipeline.tracking_takes import pose_surface, still_spine

    creature = make_creature("quadruped")
    mid = len(times) // 2
    V, F = pose_surface(creature.pose(times[mid]), voxel)
    order = [mid, *range(mid), *range(mid + 1, len(times))]
    tracks = np.empty((len(times), len(V), 3))
    tracks[order] = surface_point_tracks(creature, V, np.asarray(times)[order])
    spine = still_spine(creature.pose(times[mid]), len(times))
    return tracks, F, spine


def labelled_results(tmp_path, *, labels_digest=True, tracked_labels=None):
    """A results directory: the tracked template (tracked/NNNNNN.ply), its track.json (tracked with the spine's
    labels, their digest right or not) and spine.json; -> (the directory, the spine's labels of the template).
    ``tracked_labels``: the labels the tracking wrote (``tracked/labels.npy``, their digest in track.json), or
    None: a tracking of an earlier version, which wrote none."""
    from pipeline.armature_spine import reference_frame
    from pipeline.results import ply_bytes
    from pipeline.spine_format import write_spine
    from pipeline.template_labels import template_labels
    from pipeline.track_frames import write_labels

    tracks, F, spine = quadruped_take()
    res = tmp_path / "results"
    (res / "tracked").mkdir(parents=True)
    for t, v in enumerate(tracks):
        (res / "tracked" / f"{t:06d}.ply").write_bytes(ply_bytes(v, F))
    write_spine(res / "spine.json", spine)
    ref = reference_frame(spine)
    labels = np.asarray(template_labels(spine, tracks[ref], F, reference=ref), dtype=np.int64)
    used = labels if tracked_labels is None else np.asarray(tracked_labels, dtype=np.int64)
    digest = hashlib.sha256(used.tobytes()).hexdigest() if labels_digest else "0" * 64
    if tracked_labels is not None:
        write_labels(res, used)
    (res / "tracked" / "track.json").write_text(json.dumps({"reference_frame": ref, "patch_labels": "spine",
                                                            "patch_labels_sha256": digest}))
    return res, labels
