"""Where every surface point of a simulated creature goes: per-point ground truth for tracking.

Every capsule of a :class:`fake_cameras.creatures.Creature` moves rigidly: body capsules with
the body, limb segment ``i`` with the body, the limb's swing and its accumulated bend
(:meth:`Creature.pose`'s own capsule frames, without the tuck). :func:`capsule_frames` gives those rigid
motions at a time; :func:`surface_point_tracks` snaps points onto the surface at a first
time, assigns each to the capsule it lies on and carries it along. :func:`true_surface` meshes
the creature's exact surface on a reconstruction's grid, the per-frame surfaces a perfect
reconstruction would give: tracking on them measures the tracker apart from the surfaces
(``stage bench track --accuracy``). :func:`tracking_errors` scores a results directory's
``tracked/`` meshes against those tracks (the multi-view tracking test and the bench score alike);
:func:`invented_motion` measures the tracked surface's own non-rigid noise, the motion the
tracking invents where the body is rigid.

The limb tuck (``Creature.tuck``) bends limbs by blending joint positions, not by rotating
segments: takes with a tuck interval have no rigid per-capsule motion and are refused.
"""

from __future__ import annotations

import numpy as np

from fake_cameras.creatures import Creature

__all__ = ["capsule_frames", "surface_point_tracks", "tracking_errors", "true_surface", "invented_motion"]


def _check_creature(creature) -> None:
    if not isinstance(creature, Creature):
        raise ValueError(f"creature must be a Creature, got {type(creature).__name__}")


def capsule_frames(creature: Creature, time_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Rigid frame of every capsule of ``creature.pose(time_s)``, in the pose's capsule order.

    Returns
    -------
    R : (M, 3, 3) float ndarray
    o : (M, 3) float ndarray
        A point with local coordinates ``q`` in capsule ``k``'s frame is at ``R[k] @ q + o[k]``.
    """
    _check_creature(creature)
    if creature.tuck is not None:
        raise ValueError("creature: a take with a tuck interval has no rigid per-capsule motion")
    t = float(time_s)
    pos, Rb = creature._body_transform(t)
    limbs = {lb.name: creature._limb_frames(lb, t) for lb in creature.limbs}
    spur = creature.spur is not None and creature._weight(t, creature.spur, 0.0) > 0
    return creature._capsule_frames({k: v[0] for k, v in limbs.items()}, {k: v[1] for k, v in limbs.items()}, Rb, pos,
                                    spur)


def _snap(pose, points: np.ndarray, h: float = 0.05) -> np.ndarray:
    """Points moved onto the surface along the distance gradient (two Newton steps)."""
    x = np.asarray(points, dtype=np.float64).copy()
    for _ in range(2):
        d = pose.sdf(x)
        g = np.stack([(pose.sdf(x + h * e) - pose.sdf(x - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
        x -= d[:, None] * g
    return x


def surface_point_tracks(creature: Creature, points, times) -> np.ndarray:
    """Carry points through time with the creature's capsules.

    Parameters
    ----------
    creature : Creature
    points : (N, 3) float ndarray
        Points near the surface at ``times[0]`` (e.g. a reconstructed mesh's vertices); each
        is first snapped onto the true surface.
    times : (F,) float ndarray
        Seconds.

    Returns
    -------
    (F, N, 3) float ndarray
        Every point's true surface position at every time.
    """
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    pose0 = creature.pose(times[0])
    x0 = _snap(pose0, pts)
    cap = pose0.capsule_sdf(x0).argmin(axis=1)
    R0, o0 = capsule_frames(creature, times[0])
    local = np.einsum("nji,nj->ni", R0[cap], x0 - o0[cap])
    out = np.empty((len(times), len(pts), 3))
    for f, t in enumerate(times):
        R, o = capsule_frames(creature, t)
        out[f] = np.einsum("nij,nj->ni", R[cap], local) + o[cap]
    return out


def true_surface(creature: Creature, time_s: float, grid, *, taubin_iterations: int = 10):
    """The creature's exact surface at ``time_s``, meshed on ``grid`` as the reconstruction meshes.

    Marching cubes of :meth:`Pose.sdf` sampled on the voxel centres of ``grid``, cleaned and
    smoothed by :func:`pipeline.surface.surface_from_field` (the same cleanup as the hull's
    surfaces), so that it differs from a reconstructed surface only by what the reconstruction
    gets wrong.

    Parameters
    ----------
    creature : Creature
    time_s : float
        Seconds.
    grid : pipeline.volume.Grid
        The reconstruction's grid (``grid.json`` of ``stage process``).
    taubin_iterations : int, optional
        As in :func:`pipeline.surface.clean_mesh`.

    Returns
    -------
    trimesh.Trimesh
        World units (mm), outward normals.
    """
    from pipeline.surface import surface_from_field
    from pipeline.volume import Grid

    _check_creature(creature)
    if not isinstance(grid, Grid):
        raise ValueError(f"grid must be a pipeline.volume.Grid, got {type(grid).__name__}")
    t = float(time_s)
    if not np.isfinite(t):
        raise ValueError(f"time_s must be finite, got {time_s!r}")
    field = creature.pose(t).sdf(grid.centers()).reshape(grid.shape)
    return surface_from_field(field, grid, level=0.0, inside="below", taubin_iterations=taubin_iterations)


def tracking_errors(creature: Creature, times, results_dir, *, frames: int | None = None):
    """Every tracked vertex of a results directory against the true surface point it started on.

    The template (``tracked/track.json``: ``template``, ``reference_frame``) is snapped onto the
    true surface at the reference frame's time and carried along (:func:`surface_point_tracks`);
    each frame's ``tracked/NNNNNN.ply`` is compared with it vertex by vertex.

    Parameters
    ----------
    creature : Creature
        The take's creature (``SimulatedTake.creature``).
    times : (F,) float ndarray
        The take's frame times, seconds (``SimulatedTake.times``).
    results_dir : path
        A ``stage process`` results directory after ``stage track`` (``grid.json``, ``tracked/``).
    frames : int, optional
        Frames scored, from the first (default: all of ``times``).

    Returns
    -------
    errors : (frames, V) float ndarray
        Distance of every tracked vertex to its true point, voxels (``grid.json``).
    volumes : (frames,) float ndarray
        Every tracked frame's volume over the template's.
    report : dict
        ``tracked/track.json``.
    """
    import json
    from pathlib import Path

    from pipeline.mesh_primitives import mesh_volume
    from pipeline.meshio import load_mesh

    _check_creature(creature)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    n = len(times) if frames is None else frames
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= len(times):
        raise ValueError(f"frames must be an integer in 1..{len(times)} (the times given), got {frames!r}")
    res = Path(results_dir)
    track_json, grid_json = res / "tracked" / "track.json", res / "grid.json"
    if not (track_json.is_file() and grid_json.is_file()):
        raise ValueError(f"results_dir {res} has no tracked/track.json or grid.json (run `stage track` on it first)")
    rep = json.loads(track_json.read_text())
    voxel = float(json.loads(grid_json.read_text())["voxel"])
    V0, F0 = load_mesh(rep["template"], largest=True)
    ref = int(rep["reference_frame"])
    truth = surface_point_tracks(creature, V0, [times[ref], *times[:n]])[1:]
    v0 = mesh_volume(V0, F0)
    errors, volumes = np.empty((n, len(V0))), np.empty(n)
    for k in range(n):
        v, f = load_mesh(res / "tracked" / f"{k:06d}.ply", largest=False)
        if v.shape != V0.shape or not np.array_equal(f, F0):
            raise ValueError(f"results_dir {res}: tracked/{k:06d}.ply is not the template's mesh "
                             f"({len(v)} vertices, {len(f)} faces against {len(V0)} and {len(F0)})")
        errors[k] = np.linalg.norm(v - truth[k], axis=1) / voxel
        volumes[k] = mesh_volume(v, f) / v0
    return errors, volumes, rep


def _kabsch_residual(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Distances left after the best rigid motion of points ``A`` onto ``B`` (Kabsch)."""
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return np.linalg.norm((A - ca) @ R.T + cb - B, axis=1)


def invented_motion(creature: Creature, times, results_dir, *, frames: int | None = None,
                    min_vertices: int = 20) -> np.ndarray:
    """The motion the tracking invents where the body is rigid: its non-rigid noise.

    Every template vertex is assigned to the capsule it lies on at the reference frame (the
    template snapped onto the true surface, as :func:`tracking_errors` does), leaving out the
    vertices within one voxel of a second capsule (at a joint the true part is ambiguous). A
    capsule moves rigidly, so on every frame its tracked vertices should be their reference-frame
    positions moved by one rigid motion: what is left after the best one (Kabsch) is invented.

    Parameters
    ----------
    creature : Creature
    times : (F,) float ndarray
    results_dir : path
        A results directory after ``stage track``.
    frames : int, optional
        Frames scored, from the first (default: all of ``times``).
    min_vertices : int
        Capsules with fewer vertices are left out.

    Returns
    -------
    (frames,) float ndarray
        Per frame, the mean distance left over the scored vertices, voxels (0 at the reference frame).
    """
    import json
    from pathlib import Path

    from pipeline.meshio import load_mesh

    _check_creature(creature)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    n = len(times) if frames is None else frames
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= len(times):
        raise ValueError(f"frames must be an integer in 1..{len(times)} (the times given), got {frames!r}")
    if isinstance(min_vertices, bool) or not isinstance(min_vertices, (int, np.integer)) or min_vertices < 3:
        raise ValueError(f"min_vertices must be an integer >= 3, got {min_vertices!r}")
    res = Path(results_dir)
    try:
        rep = json.loads((res / "tracked" / "track.json").read_text())
        voxel = float(json.loads((res / "grid.json").read_text())["voxel"])
        ref = int(rep["reference_frame"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"results_dir {res}: no readable tracked/track.json or grid.json ({exc})") from None
    V0, _ = load_mesh(res / "tracked" / f"{ref:06d}.ply", largest=False)
    pose = creature.pose(times[ref])
    sd = pose.capsule_sdf(_snap(pose, V0))
    d, cap = np.sort(sd, axis=1), sd.argmin(axis=1)
    keep = d[:, 1] - d[:, 0] > voxel
    groups = [np.flatnonzero(keep & (cap == c)) for c in np.unique(cap)]
    groups = [g for g in groups if len(g) >= min_vertices]
    out = np.empty(n)
    for k in range(n):
        v, _ = load_mesh(res / "tracked" / f"{k:06d}.ply", largest=False)
        if v.shape != V0.shape:
            raise ValueError(f"results_dir {res}: tracked/{k:06d}.ply has {len(v)} vertices, the template {len(V0)}")
        left = np.concatenate([_kabsch_residual(V0[g], v[g]) for g in groups])
        out[k] = left.mean() / voxel
    return out
