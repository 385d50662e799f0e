"""The limb or the body of every template vertex from a take's spine and the template's shape (pipeline.template_labels)."""

from __future__ import annotations

import functools

import numpy as np
import pytest


@functools.lru_cache(maxsize=4)
def _creature_template(name: str, voxel: float = 6.0, times: tuple = (0.3,)):
    """A simulated creature's surface at ``times[0]`` (marching cubes of its exact distance), a one-junction
    spine of ``len(times)`` frames whose limb axes run from the body's centre through the creature's limb axes
    at ``times[0]``, the simulator's labels (the nearest capsule's limb, -1 the body; the spine's limb k is the
    creature's limb k) and the creature's surface vertices at every time."""
    from fake_cameras.creatures import make_creature
    from tests.pipeline.tracking_takes import pose_surface, still_spine

    poses = [make_creature(name).pose(t) for t in times]
    pose = poses[0]
    surfaces = [pose_surface(p, voxel) for p in poses]
    V, F = surfaces[0]
    spine = still_spine(pose, len(times))
    return spine, V, F, pose.limb[pose.capsule_sdf(V).argmin(1)], [S for S, _ in surfaces]


@pytest.mark.parametrize("name", ["starfish", "quadruped", "biped"])
def test_limbs_leave_the_body_where_their_section_narrows(name):
    """On the creature's own surface and limb axes, which run from the body's centre, a limb takes its own
    vertices and leaves the body to the body: the simulator's labels at 85 % of the vertices or more, the body
    at 75 % recall and 75 % precision or more. The biped's upper arms hang against its body and its hips bulge
    from it (their surface joins the body's): their sections are the body's, and only the limb's own centre
    line walked in from the cut gives them to the limb (without it the biped's body is below these bounds);
    the starfish's arm roots are wide lobes of its disc, where the simulator's capsules split the surface
    between arm and body."""
    from pipeline.template_labels import BODY, template_labels

    spine, V, F, true, _ = _creature_template(name)
    got = template_labels(spine, V, F)
    assert got.shape == (len(V),) and got.dtype == np.int64
    assert set(np.unique(got)) <= {BODY, *range(spine.K)}
    assert (got == true).mean() >= 0.85
    body, true_body = got == BODY, true == BODY
    assert (body & true_body).sum() >= 0.75 * true_body.sum()
    assert (body & true_body).sum() >= 0.75 * body.sum()
    for k in range(spine.K):  # every limb found, each one connected piece on its own limb
        assert (got == k).sum() > 0 and np.mean(true[got == k] == k) >= 0.75


def test_the_body_split_by_its_motion_gives_the_limbs_their_roots():
    """Where a limb's root is joined to the body (the biped's upper arms hanging against it, its hips), the
    body's rigid motion over the frames does not keep the root's vertices on the surfaces and the limb's
    does: with every frame's surface the labels are right at no fewer of the vertices, the body's precision
    2 points higher, its recall no more than 2 points lower (the shape alone already gives the limbs most
    of their roots, :func:`test_limbs_leave_the_body_where_their_section_narrows`)."""
    from pipeline.template_labels import template_labels

    spine, V, F, true, surfaces = _creature_template("biped", times=(0.3, 0.45, 0.6, 0.75, 0.9))
    shape = template_labels(spine, V, F)
    moving = template_labels(spine, V, F, surfaces=surfaces)
    np.testing.assert_array_equal(template_labels(spine, V, F, surfaces=surfaces[:1] * len(surfaces)), shape)

    def scores(got):
        body, true_body = got == -1, true == -1
        both = (body & true_body).sum()
        return (got == true).mean(), both / true_body.sum(), both / body.sum()

    (right0, recall0, precision0), (right, recall, precision) = scores(shape), scores(moving)
    assert right >= right0
    assert precision >= precision0 + 0.02
    assert recall >= recall0 - 0.02


def test_a_spine_file_or_results_directory_gives_the_same_labels(tmp_path):
    from pipeline.spine_format import write_spine
    from pipeline.template_labels import axis_labels, template_labels

    spine, V, F, _, _ = _creature_template("quadruped", voxel=10.0)
    write_spine(tmp_path / "spine.json", spine)
    got = template_labels(spine, V, F, reference=0)
    np.testing.assert_array_equal(template_labels(tmp_path, V, F), got)
    np.testing.assert_array_equal(template_labels(tmp_path / "spine.json", V, F), got)
    np.testing.assert_array_equal(axis_labels([spine.axes[lid][0] for lid in spine.limb_ids], V, F), got)


def test_invalid_input(tmp_path):
    from pipeline.template_labels import axis_labels, template_labels

    spine, V, F, _, _ = _creature_template("quadruped", voxel=10.0)
    with pytest.raises(ValueError, match="spine"):
        template_labels(object(), V, F)
    with pytest.raises(ValueError, match="spine"):
        template_labels(tmp_path / "missing", V, F)
    with pytest.raises(ValueError, match="vertices"):
        template_labels(spine, V[:, :2], F)
    with pytest.raises(ValueError, match="vertices"):
        template_labels(spine, np.where(np.arange(len(V))[:, None] == 0, np.nan, V), F)
    with pytest.raises(ValueError, match="faces"):
        template_labels(spine, V, F.astype(float))
    with pytest.raises(ValueError, match="faces"):
        template_labels(spine, V, F + len(V))
    with pytest.raises(ValueError, match="reference"):
        template_labels(spine, V, F, reference=1)
    with pytest.raises(ValueError, match="reference"):
        template_labels(spine, V, F, reference=0.5)
    with pytest.raises(ValueError, match="axes"):
        axis_labels([np.zeros((1, 3))], V, F)
    with pytest.raises(ValueError, match="axes"):
        axis_labels([np.full((3, 3), np.nan)], V, F)
    with pytest.raises(ValueError, match="faces"):
        axis_labels([np.eye(3)], V, F[:, :2])
    with pytest.raises(ValueError, match="surfaces"):
        template_labels(spine, V, F, surfaces=[V, V])
    with pytest.raises(ValueError, match="surfaces"):
        template_labels(spine, V, F, surfaces=[V[:, :2]])
    with pytest.raises(ValueError, match="frame"):
        axis_labels([spine.axes[lid][0] for lid in spine.limb_ids], V, F, surfaces=[V], frame=1)


def test_nearest_limb_and_proximal_half_against_a_loop():
    """The nearest limb of every point and a limb's proximal half, against a loop over every pair of points (exact:
    the same distances, ties broken towards the lower label as the loop does); a limb under ``min_vertices`` is
    nobody's nearest, and without any limb every point is the body's."""
    from pipeline.template_labels import BODY, nearest_limb, proximal_half

    rng = np.random.default_rng(0)
    V, X = rng.normal(size=(120, 3)), rng.normal(size=(40, 3))
    labels = rng.integers(-1, 4, size=len(V))
    labels[labels == 2] = -1  # limb 2 has no vertex
    labels[np.flatnonzero(labels == 3)[2:]] = 0  # limb 3 has two
    for min_vertices in (1, 3):
        ok = [k for k in range(4) if (labels == k).sum() >= min_vertices]
        want = [min(ok, key=lambda k: min(np.linalg.norm(x - v) for v in V[labels == k])) for x in X]
        assert np.array_equal(nearest_limb(X, V, labels, min_vertices=min_vertices), want)
    assert np.array_equal(nearest_limb(X, V, np.full(len(V), BODY)), np.full(len(X), BODY))
    body = V[labels == BODY]
    for k in range(4):
        idx = np.flatnonzero(labels == k)
        gap = np.array([min(np.linalg.norm(V[i] - b) for b in body) for i in idx])
        assert np.array_equal(proximal_half(V, labels, k), idx[gap <= np.median(gap)] if len(idx) else idx)
        assert len(idx) == 0 or 2 * len(proximal_half(V, labels, k)) >= len(idx)


def test_invalid_input_of_the_limb_helpers():
    from pipeline.template_labels import nearest_limb, proximal_half

    V, labels = np.eye(3), np.array([-1, 0, 0])
    with pytest.raises(ValueError, match="points"):
        nearest_limb(np.zeros((2, 2)), V, labels)
    with pytest.raises(ValueError, match="vertices"):
        nearest_limb(V, V[:, :2], labels)
    with pytest.raises(ValueError, match="labels"):
        nearest_limb(V, V, labels[:2])
    with pytest.raises(ValueError, match="labels"):
        nearest_limb(V, V, np.array([-2, 0, 0]))
    with pytest.raises(ValueError, match="labels"):
        nearest_limb(V, V, labels.astype(float))
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="min_vertices"):
            nearest_limb(V, V, labels, min_vertices=bad)
    for bad in (-1, 0.5, True):
        with pytest.raises(ValueError, match="limb"):
            proximal_half(V, labels, bad)
    with pytest.raises(ValueError, match="vertices"):
        proximal_half(np.full((3, 3), np.nan), labels, 0)
    with pytest.raises(ValueError, match="labels"):
        proximal_half(V, np.zeros(3, dtype=int), 0)


def test_the_roots_circle_and_free_side():
    """The circle fitted to a limb's section is the exact circle through points on it (to 1e-9), and the free
    side's extent is the longest circular run of rays, as a slow count of every start gives it."""
    from pipeline.template_labels import _circle, _longest_run

    rng = np.random.default_rng(0)
    th = rng.uniform(0.0, np.pi, 7)  # half a circle: the free side of a limb beside the body
    cx, cy, r = _circle(3.0 + 20.0 * np.cos(th), -2.0 + 20.0 * np.sin(th))
    np.testing.assert_allclose([cx, cy, r], [3.0, -2.0, 20.0], atol=1e-9)
    for _ in range(200):
        x = rng.random(16) < rng.uniform(0.2, 0.9)
        slow = max(next((n for n in range(16) if not x[(i + n) % 16]), 16) for i in range(16))
        assert _longest_run(x) == slow
    assert _longest_run(np.zeros(16, bool)) == 0 and _longest_run(np.ones(16, bool)) == 16


def _slow_root_tubes(V, F, labels):
    """:func:`pipeline.template_labels.root_tubes` as a loop over every limb and vertex (principal axes from the
    covariance's eigenvectors, distances one point at a time, the pieces by a walk over the edges)."""
    from pipeline.mesh_primitives import vertex_normals

    edges = sorted({tuple(sorted((int(a), int(b)))) for f in F for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))})
    step = np.median([np.linalg.norm(V[a] - V[b]) for a, b in edges])
    signed = sum(V[a] @ np.cross(V[b], V[c]) for a, b, c in F)
    N = vertex_normals(V, F) * (1.0 if signed >= 0 else -1.0)
    body = [i for i in range(len(V)) if labels[i] == -1]

    def axis_of(X):
        c = X.mean(0)
        w, U = np.linalg.eigh((X - c).T @ (X - c))
        return c, U[:, np.argmax(w)]

    def radial(x, c, a):
        return (x - c) - ((x - c) @ a) * a

    best = {}
    for k in range(int(labels.max()) + 1):
        limb = [i for i in range(len(V)) if labels[i] == k]
        if len(limb) < 3 or not body:
            continue
        c, a0 = axis_of(V[limb])
        r0 = np.median([np.linalg.norm(radial(V[i], c, a0)) for i in limb])
        root = [i for i in limb if np.linalg.norm(V[body] - V[i], axis=1).min() <= 2 * r0]
        if len(root) < 3:
            continue
        c, a = axis_of(V[root])
        if np.degrees(np.arccos(min(abs(a @ a0), 1.0))) > 45:
            continue
        nearest = [body[int(np.argmin(np.linalg.norm(V[body] - V[i], axis=1)))] for i in root]
        if (V[nearest].mean(0) - V[limb].mean(0)) @ a < 0:  # from the limb towards the body nearest the root
            a = -a
        r = np.median([np.linalg.norm(radial(V[i], c, a)) for i in root])
        reach = max((V[i] - c) @ a for i in root)
        for i in body:
            u = radial(V[i], c, a)
            d = np.linalg.norm(u)
            if 0 < (V[i] - c) @ a <= reach + r and d <= r + step and d > 0 and N[i] @ u >= np.sqrt(0.5) * d \
                    and d / r < best.get(i, (np.inf, k))[0]:
                best[i] = (d / r, k)
    out = labels.copy()
    for i, (_, k) in best.items():
        out[i] = k
    return _slow_largest_pieces(out, edges, int(labels.max()) + 1)


def _slow_largest_pieces(out, edges, K):
    """Every limb's vertices outside its largest piece (a walk over the edges) given to the body."""
    near = {i: [] for i in range(len(out))}
    for a, b in edges:
        near[a].append(b)
        near[b].append(a)
    final = out.copy()
    for k in range(K):
        pieces, seen = [], set()
        for s in np.flatnonzero(out == k):
            if s in seen:
                continue
            piece, todo = [], [s]
            seen.add(s)
            while todo:
                i = todo.pop()
                piece.append(i)
                for j in near[i]:
                    if out[j] == k and j not in seen:
                        seen.add(j)
                        todo.append(j)
            pieces.append(piece)
        for piece in pieces:
            if len(piece) < max(map(len, pieces)):
                final[piece] = -1
    return final


@pytest.mark.parametrize("name", ["biped", "quadruped"])
def test_root_tubes_against_a_loop(name):
    """The limbs' root tubes give back body vertices as a loop over every limb and vertex does (exact), on the
    creature's surface with its own labels and with every limb vertex within two voxels of the body given to
    the body (a root the surface merged into it); there they give back at least 10 vertices and only limb
    vertices; the same whichever way the triangles wind; a limb's vertex is never taken."""
    from scipy.spatial import cKDTree

    from pipeline.template_labels import BODY, root_tubes

    _, V, F, true, _ = _creature_template(name, voxel=10.0)
    gap = cKDTree(V[true == BODY]).query(V)[0]
    merged = np.where((true >= 0) & (gap <= 20.0), BODY, true)
    for labels in (true, merged):
        got = root_tubes(V, F, labels)
        np.testing.assert_array_equal(got, _slow_root_tubes(V, F, labels))
        np.testing.assert_array_equal(root_tubes(V, F[:, ::-1], labels), got)
        assert np.array_equal(got[labels >= 0], labels[labels >= 0])
    given = got != merged
    assert given.sum() >= 10 and np.array_equal(got[given], true[given])


def _gives_back_two_rings(V, F, labels, expected):
    """``root_tubes`` gives ``expected``, two rings of 16 vertices more on the limb than ``labels``, whichever way
    the triangles wind."""
    from pipeline.template_labels import root_tubes

    assert (expected != labels).sum() == 2 * 16
    np.testing.assert_array_equal(root_tubes(V, F, labels), expected)
    np.testing.assert_array_equal(root_tubes(V, F[:, ::-1], labels), expected)


def _revolved(profile, sections: int = 16):
    """A closed surface of revolution about the x axis: one ring of ``sections`` vertices for each (x, radius) of
    ``profile`` (in order), a vertex on the axis closing each end; (vertices, faces, the ring's x and radius of every
    vertex)."""
    t = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    rings = np.array(profile, dtype=float)
    V = np.concatenate([np.c_[np.full(sections, x), r * np.cos(t), r * np.sin(t)] for x, r in rings]
                       + [[[rings[0, 0], 0.0, 0.0], [rings[-1, 0], 0.0, 0.0]]])
    F = []
    for j in range(len(rings) - 1):
        for i in range(sections):
            p, q = j * sections + i, j * sections + (i + 1) % sections
            F += [[p, q, q + sections], [p, q + sections, p + sections]]
    first, last, top = len(rings) * sections, len(rings) * sections + 1, (len(rings) - 1) * sections
    for i in range(sections):
        F += [[first, (i + 1) % sections, i], [last, top + i, top + (i + 1) % sections]]
    ring = np.concatenate([np.repeat(rings, sections, axis=0), [[rings[0, 0], 0.0], [rings[-1, 0], 0.0]]])
    return V, np.array(F), ring[:, 0], ring[:, 1]


#: The body: a cylinder of radius 10 along x from -20 to its end face at x = 0 (rings 10, 7 and 4 on the face).
_BODY_PROFILE = [(x, 10.0) for x in np.arange(-20.0, 0.5, 2.0)] + [(0.0, 7.0), (0.0, 4.0)]


def test_root_tubes_on_a_club_limb_out_of_a_body():
    """Exact sets by the geometry. A neck of radius 1.25 (rings 0.5 apart) leaves the body's end face and the body
    holds it up to x = 3; then a club of radius 5 from x = 14 to 34, so the limb's radius (the median distance to
    its axis) is 5. The root is the neck within two limb radii (10) of the body, its rings at x = 3.5 .. 13; the tube
    runs along the neck into the body (towards -x), its radius the neck's, and reaches one radius past the root's
    end at 3.5: the neck's rings at x = 3 and 2.5, which the body holds, go to the limb; the ring at 2 (1.5 past) and
    the end face (its normals along the tube, not away from it) stay the body's. Either winding gives the same."""
    from pipeline.template_labels import BODY

    neck = [(x, 1.25) for x in np.arange(0.0, 14.25, 0.5)]
    club = [(x, 5.0) for x in np.arange(14.0, 34.25, 0.5)]
    V, F, x, r = _revolved(_BODY_PROFILE + neck + club)
    on_limb = (x > 0) | ((x == 0) & (r == 1.25))
    labels = np.where(on_limb & (x > 3.0), 0, BODY)
    expected = np.where(on_limb & (x >= 2.5), 0, BODY)
    _gives_back_two_rings(V, F, labels, expected)


def test_root_tubes_where_the_root_is_all_of_the_limb():
    """A neck of radius 1.25 (rings 0.5 apart, x = 0 .. 8) stands in a sleeve of the body whose inner wall, radius
    2.1, runs from the sleeve's floor at x = 0 to its rim at x = 10; the body holds the neck up to x = 1. Every
    neck vertex lies within two limb radii (2.5) of the body, so the root is all of the limb and has the limb's
    centroid. The body nearest the root (the wall beside it, the held rings below it) lies towards -x: the tube
    runs that way and gives back the held rings at x = 1 and 0.5, within one radius of the root's end at 1.5; the
    wall (its normals point at the axis) and the floor stay the body's. Either winding gives the same."""
    from pipeline.template_labels import BODY

    neck = [(x, 1.25) for x in np.arange(0.0, 8.25, 0.5)]
    sleeve = [(x, 10.0) for x in np.arange(-20.0, 10.5, 2.0)] + [(10.0, 7.0), (10.0, 4.0)] \
        + [(x, 2.1) for x in np.arange(10.0, -0.25, -0.5)]
    V, F, x, r = _revolved(sleeve + neck)
    on_neck = np.arange(len(V)) >= len(V) - (len(neck) * 16 + 1)  # its rings and the vertex closing it
    labels = np.where(on_neck & (x > 1.0), 0, BODY)
    expected = np.where(on_neck & (x >= 0.5), 0, BODY)
    _gives_back_two_rings(V, F, labels, expected)


def test_a_root_as_wide_as_it_is_long_has_no_tube():
    """A limb of radius 4 (rings 0.5 apart) out of the body's end face, held by the body up to x = 1: its root (the
    limb within two of its radii of the body, x = 1.5 .. 9) spreads more across the limb (radius 4) than along it
    (length 7.5), so its principal axis lies across the limb's (90 degrees): no tube, nothing given back."""
    from pipeline.template_labels import BODY, _root_tube, root_tubes

    V, F, x, r = _revolved(_BODY_PROFILE[:-1] + [(x, 4.0) for x in np.arange(0.0, 30.25, 0.5)])
    labels = np.where(((x > 0) | (r == 4.0)) & (x > 1.0), 0, BODY)
    assert _root_tube(V, labels, 0) is None
    np.testing.assert_array_equal(root_tubes(V, F, labels), labels)


def test_invalid_input_of_root_tubes():
    from pipeline.template_labels import root_tubes

    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    labels = np.array([-1, -1, 0, 0])
    assert root_tubes(V, F, labels).tolist() == labels.tolist()  # a limb of 2 vertices has no tube
    with pytest.raises(ValueError, match="vertices"):
        root_tubes(V[:, :2], F, labels)
    with pytest.raises(ValueError, match="faces"):
        root_tubes(V, F + 4, labels)
    with pytest.raises(ValueError, match="non-zero length"):  # every edge of length zero
        root_tubes(np.zeros_like(V), F, labels)
    for bad in (labels[:3], labels - 1, labels.astype(float)):
        with pytest.raises(ValueError, match="labels"):
            root_tubes(V, F, bad)
