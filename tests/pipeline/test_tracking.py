"""Template tracking energy and solver (pipeline.tracking)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.sparse.linalg import spsolve

from pipeline.cholesky import CholeskySystem
from pipeline.mesh_primitives import mesh_volume, scatter_add, sum_by, summing_matrix, vertex_normals
from pipeline.tracking import (
    TemplateTracker,
    choose_gamma,
    choose_start,
    cotangent_laplacian,
    default_gate,
    start_residuals,
)
from pipeline.tracking_patches import (
    SEED_RADIUS,
    blended_align,
    blended_patches,
    farthest_seeds,
    grid_seeds,
    patch_align,
    patch_constraints,
    predict_motion,
    surface_patches,
)


def _sphere(sub=2, r=50.0):
    m = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _slow_laplacian(v, f):
    n = len(v)
    L = np.zeros((n, n))
    area = np.zeros(n)
    for tri in f:
        a = 0.5 * np.linalg.norm(np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]]))
        area[tri] += a
        for k in range(3):
            i, j, o = tri[(k + 1) % 3], tri[(k + 2) % 3], tri[k]
            e1, e2 = v[i] - v[o], v[j] - v[o]
            cot = e1 @ e2 / np.linalg.norm(np.cross(e1, e2))
            L[i, j] += cot
            L[j, i] += cot
    area *= 0.5
    L -= np.diag(L.sum(1))
    return L / (2 * area[:, None])


def test_cotangent_laplacian_matches_slow_reference():
    v, f = _sphere(1)
    v = v * np.array([1.0, 0.7, 1.3])  # not a regular mesh
    L = cotangent_laplacian(v, f).toarray()
    np.testing.assert_allclose(L, _slow_laplacian(v, f), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(L @ np.ones(len(v)), 0, atol=1e-12)
    # on a sphere of radius r the mean-curvature normal has length 2/r with the barycentric
    # cell (a third of the triangle areas); the paper's cell (half of them) scales it by 2/3
    vs, fs = _sphere(3)
    lv = cotangent_laplacian(vs, fs) @ vs
    np.testing.assert_allclose(np.linalg.norm(lv, axis=1).mean(), 2 / 50.0 * 2 / 3, rtol=0.02)


@pytest.mark.parametrize("backend", ["qdldl", "splu"])
def test_cholesky_system_matches_spsolve(backend):
    v, f = _sphere(2)
    L = cotangent_laplacian(v, f)
    K = sp.csr_matrix(L.T @ L)
    rng = np.random.default_rng(0)
    sysm = CholeskySystem(K, backend=backend)
    for _ in range(3):  # refactor with new diagonals on the same analysis
        d = rng.uniform(0.01, 0.1, len(v))
        b = rng.normal(size=(len(v), 3))
        sysm.factor(d)
        x = sysm.solve(b)
        np.testing.assert_allclose(x, spsolve((K + sp.diags(d)).tocsc(), b), rtol=1e-8, atol=1e-8)
    assert sysm.factorizations == 3


def _reference_cg(sysm, d, b, x0, rtol=1e-6, max_iter=6):
    """Preconditioned CG as the textbook writes it (precondition, then test the residual)."""
    K = sysm._K
    x = x0.copy()
    r = b - (K @ x + d[:, None] * x)
    bn = np.linalg.norm(b, axis=0)
    z = sysm.solve(r)
    p, rz = z.copy(), np.einsum("ij,ij->j", r, z)
    for _ in range(max_iter):
        if np.all(np.linalg.norm(r, axis=0) <= rtol * bn):
            return x, False
        Ap = K @ p + d[:, None] * p
        alpha = rz / np.einsum("ij,ij->j", p, Ap)
        x += p * alpha
        r -= Ap * alpha
        z = sysm.solve(r)
        rz_new = np.einsum("ij,ij->j", r, z)
        p, rz = z + p * (rz_new / rz), rz_new
    return None, True


def test_solve_near_gives_the_textbook_iterates_with_one_triangular_solve_fewer():
    v, f = _sphere(2)
    L = cotangent_laplacian(v, f)
    K = sp.csr_matrix(L.T @ L)
    rng = np.random.default_rng(1)
    d0 = rng.uniform(0.01, 0.1, len(v))
    b, x0 = rng.normal(size=(len(v), 3)), rng.normal(size=(len(v), 3))
    spread = np.random.default_rng(3).uniform(-1, 1, len(v))
    for scale, refactors in ((1e-4, False), (1e-2, False), (1.0, True)):  # near, further, too far: refactor
        a, ref = CholeskySystem(K, backend="qdldl"), CholeskySystem(K, backend="qdldl")
        a.factor(d0)
        ref.factor(d0)
        solves = []
        a.solve = lambda r, plain=a.solve, solves=solves: solves.append(1) or plain(r)
        d = d0 * np.exp(scale * spread)
        x = a.solve_near(d, b, x0)
        want, failed = _reference_cg(ref, d, b, x0)
        assert failed == refactors and a.factorizations == 1 + refactors
        if failed:
            np.testing.assert_allclose(x, spsolve((K + sp.diags(d)).tocsc(), b), rtol=1e-8, atol=1e-8)
            assert len(solves) == 1 + a.cg_iterations  # the preconditioner's 6 and the final direct solve
        else:
            assert np.array_equal(x, want)
            assert len(solves) == a.cg_iterations and a.cg_iterations >= 1


def test_summing_matrix_adds_bit_for_bit_like_bincount():
    rng = np.random.default_rng(2)
    index = rng.integers(0, 40, 2000)
    values = rng.normal(size=(2000, 6, 6)) * 10.0 ** rng.uniform(-8, 8, (2000, 1, 1))
    S = summing_matrix(index, 45)  # the last rows without any value
    assert np.array_equal(sum_by(S, values), scatter_add(index, values, 45))
    assert np.array_equal(sum_by(S, values[:, 0, 0]), scatter_add(index, values[:, 0, 0], 45))
    exact = np.zeros((45, 6, 6))
    np.add.at(exact, index, values)
    np.testing.assert_allclose(sum_by(S, values), exact, rtol=1e-12, atol=1e-12 * np.abs(values).max())


def test_gamma_and_gate_follow_the_template():
    v, f = _sphere(2, r=50.0)  # triangles ~ 97 mm^2
    assert choose_gamma(v, f) == 0.05
    assert choose_gamma(v / 10, f) == 0.005  # ~1 mm^2
    assert default_gate(v * 10) == pytest.approx(10 * np.linalg.norm(np.ptp(v * 10, 0)) / 300)
    assert default_gate(v / 100) == 10.0


def test_fit_follows_a_translated_surface_without_thinning():
    v, f = _sphere(3)
    d = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    shift = np.array([3.0, -2.0, 1.0])
    tr = TemplateTracker(v, f)
    fit = tr.fit(d.vertices + shift, d.vertex_normals, previous=v)
    # every vertex on the moved sphere (to 0.2 mm), the volume kept within 1 %
    assert np.abs(np.linalg.norm(fit.vertices - shift, axis=1) - 50.0).max() < 0.2
    assert abs(mesh_volume(fit.vertices, f) / mesh_volume(v, f) - 1) < 0.01
    assert fit.model_pairs > 0 and fit.data_pairs > 0 and fit.rounds == 15


def test_no_data_keeps_the_shape_and_components_without_data_stay():
    v, f = _sphere(2)
    v2 = v + [500.0, 0, 0]
    V = np.vstack([v, v2])
    F = np.vstack([f, f + len(v)])[:-5]  # two components, one with a hole
    tr = TemplateTracker(V, F)
    d = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    fit = tr.fit(d.vertices + [2.0, 0, 0], d.vertex_normals, previous=V)
    assert np.all(np.isfinite(fit.vertices))
    far = slice(len(v), None)
    np.testing.assert_allclose(fit.vertices[far], V[far], atol=1e-6)  # nothing pulls the second sphere
    assert np.abs(np.linalg.norm(fit.vertices[: len(v)] - [2.0, 0, 0], axis=1) - 50).mean() < 0.5
    empty = tr.fit(np.zeros((0, 3)), np.zeros((0, 3)), previous=V)
    np.testing.assert_array_equal(empty.vertices, V)


def _rotation(axis, deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def test_patch_align_places_every_patch_rigidly():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(60, 3)) * 20
    patches = np.repeat([0, 1, 2], 20)
    moves = [(_rotation([1, 2, 3], 30), [5.0, 0, 0]), (_rotation([0, 0, 1], -50), [0, 9.0, 1]), (np.eye(3), [0, 0, 2.0])]
    dst = np.concatenate([src[patches == p] @ R.T + t for p, (R, t) in enumerate(moves)])
    np.testing.assert_allclose(patch_align(src, dst, patches), dst, atol=1e-9)
    # a target that is not rigid: every patch keeps the source's shape (distances within the patch)
    noisy = dst + rng.normal(size=dst.shape)
    out = patch_align(src, noisy, patches)
    a = out[:20]
    np.testing.assert_allclose(np.linalg.norm(a[:, None] - a[None], axis=2),
                               np.linalg.norm(src[:20, None] - src[None, :20], axis=2), atol=1e-9)


def _blended_align_reference(src, dst, cover):
    """One weighted Kabsch per patch in a loop, then the weighted mean of the placements."""
    pp, vv, w = cover
    out = np.zeros_like(src)
    for p in np.unique(pp):
        m = pp == p
        i, wi = vv[m], w[m]
        cs, ct = (wi[:, None] * src[i]).sum(0) / wi.sum(), (wi[:, None] * dst[i]).sum(0) / wi.sum()
        H = ((src[i] - cs) * wi[:, None]).T @ (dst[i] - ct)
        U, _, Wt = np.linalg.svd(H)
        R = Wt.T @ np.diag([1, 1, np.sign(np.linalg.det(U @ Wt))]) @ U.T
        out[i] += wi[:, None] * ((src[i] - cs) @ R.T + ct)
    return out


def _labelled_patches_reference(v, comp, lab, size):
    """The labelled patches by a loop over parts and cells: the body one patch, a limb's cells (from its own
    corner) seeded by their first vertex."""
    out = np.empty(len(v), np.int64)
    n = 0
    for c, part in sorted({(int(a), int(b)) for a, b in zip(comp, lab)}):
        mine = np.flatnonzero((comp == c) & (lab == part))
        if part < 0:
            out[mine], n = n, n + 1
            continue
        cells = {}
        for i in mine:
            cells.setdefault(tuple(np.floor((v[i] - v[mine].min(0)) / size).astype(int)), []).append(i)
        seeds = sorted(c_[0] for c_ in cells.values())
        for i in mine:
            out[i] = n + int(np.argmin([np.linalg.norm(v[i] - v[s]) for s in seeds]))
        n += len(seeds)
    return out


def _patches_reference(v, comp, size):
    """The patches without labels by loops: per component, seeds by farthest-point sampling (the first the
    vertex farthest from the centroid, then the vertex farthest from every seed, while it is further than the
    covering radius) and every vertex with its nearest seed."""
    radius = SEED_RADIUS * size
    out = np.empty(len(v), np.int64)
    n = 0
    for c in sorted(set(comp.tolist())):
        mine = np.flatnonzero(comp == c)
        centre = v[mine].mean(0)
        seeds = [max(mine, key=lambda i: (np.sum((v[i] - centre) ** 2), -i))]
        far = {i: np.inf for i in mine}  # every vertex's distance to its nearest seed so far
        while True:
            far = {i: min(far[i], np.linalg.norm(v[i] - v[seeds[-1]])) for i in mine}
            nxt = max(mine, key=lambda i: (far[i], -i))
            if far[nxt] <= radius:
                break
            seeds.append(nxt)
        for i in mine:
            out[i] = n + int(np.argmin([np.linalg.norm(v[i] - v[s]) for s in seeds]))
        n += len(seeds)
    return out


def _same_partition(a, b):
    return len(set(zip(a.tolist(), b.tolist()))) == len(set(a.tolist())) == len(set(b.tolist()))


def test_surface_patches_follow_the_surface_not_where_it_lies():
    """The patches are seeded by farthest-point sampling on the surface: the same partition (as a loop gives)
    wherever the template lies and however it is turned; every vertex within the covering radius of its seed,
    the seeds at least that far apart. A world grid's cells moved with the template (5 patches here, 6 moved and turned)."""
    m = trimesh.creation.capsule(height=200.0, radius=20.0, count=[12, 12])
    v, f = (np.asarray(x) for x in trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=14.0))
    v = v + np.random.default_rng(0).normal(0.0, 0.5, v.shape)  # no two vertices equally far: one answer
    patch, component = surface_patches(v, f, 60.0)
    assert _same_partition(patch, _patches_reference(v, np.zeros(len(v), int), 60.0))
    moved, _ = surface_patches(v @ _rotation([1, 2, 3], 35).T + [30.0, -7.0, 12.0], f, 60.0)
    assert np.array_equal(moved, patch) and patch.max() + 1 == len(component) > 4
    seeds = farthest_seeds(v, SEED_RADIUS * 60.0)
    assert np.array_equal(np.unique(patch[seeds]), np.arange(len(seeds)))
    d = np.linalg.norm(v[:, None] - v[seeds][None], axis=2)
    assert d.min(1).max() <= SEED_RADIUS * 60.0 and np.sort(d[seeds], 1)[:, 1].min() >= SEED_RADIUS * 60.0


def test_grid_seeds_equal_a_loop_over_the_cells():
    """grid_seeds against a plain loop: the first point met in every cell a seed, every point with its nearest
    seed by brute force (random points: no ties), for the points' own corner and a given one, moved or not."""
    rng = np.random.default_rng(3)
    p = rng.uniform(-40.0, 90.0, (300, 3))
    for size, offset, corner in ((25.0, 0.0, None), (25.0, 0.4, None), (17.0, 0.75, (-60.0, -50.0, -45.0))):
        lo = p.min(0) if corner is None else np.asarray(corner)
        first = {}
        for i, x in enumerate(p):
            first.setdefault(tuple(int(c) for c in np.floor((x - lo) / size + offset)), i)
        ref = np.sort(list(first.values()))
        seeds, nearest = grid_seeds(p, size, offset=offset, corner=corner)
        assert np.array_equal(seeds, ref)
        assert np.array_equal(nearest, np.linalg.norm(p[:, None] - p[ref][None], axis=2).argmin(1))


def test_surface_patches_of_a_symmetric_template_do_not_depend_on_where_it_lies():
    """An exactly symmetric template (a cylinder: many vertices equally far from its centroid, from a seed, cap
    centres equally near several seeds): equal distances go to the lowest index, so rounding under a rigid
    motion does not decide the patches."""
    m = trimesh.creation.cylinder(radius=20.0, height=120.0, sections=32)
    v, f = (np.asarray(x) for x in trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=10.0))
    patch = surface_patches(v, f, 40.0)[0]
    for k in range(6):
        moved = v @ _rotation([1, k, 3 - k], 17.0 + 29.0 * k).T + [300.0 * k, -70.0, 12.0 * k]
        assert np.array_equal(surface_patches(moved, f, 40.0)[0], patch), k


def test_labelled_patches_never_span_two_parts_and_match_a_per_part_reference():
    """With the template's labels every component's body is one patch and every limb is cut on a grid from
    its own corner (the same partition as a loop)."""
    a = trimesh.creation.capsule(height=200.0, radius=20.0, count=[12, 12])
    av, af = trimesh.remesh.subdivide_to_size(a.vertices, a.faces, max_edge=14.0)
    b = trimesh.creation.capsule(height=90.0, radius=15.0, count=[8, 8])
    v = np.concatenate([av, b.vertices + [100.0, 0, 0]])
    f = np.concatenate([af, b.faces + len(av)])
    comp = np.repeat([0, 1], [len(av), len(b.vertices)])
    # component 0: body below z = -5, limb 0 above; component 1: limb 1 and a body end
    lab = np.where(comp == 0, np.where(v[:, 2] > -5, 0, -1), np.where(v[:, 2] > -40, 1, -1))
    patch, component = surface_patches(v, f, 60.0, labels=lab)
    ref = _labelled_patches_reference(v, comp, lab, 60.0)
    pairs = set(zip(patch.tolist(), ref.tolist()))  # the same partition (up to the patches' numbers)
    assert len(pairs) == len(set(patch.tolist())) == len(set(ref.tolist())) == patch.max() + 1 == len(component)
    for p in range(patch.max() + 1):
        assert len(set(lab[patch == p])) == 1 and set(comp[patch == p]) == {component[p]}
    assert [len(set(patch[(comp == c) & (lab < 0)])) for c in (0, 1)] == [1, 1]
    # a grid of the whole template would leave fragments of a few vertices where a part just enters a cell;
    # the parts' own do not
    assert len(set(patch[lab == 0])) == 3 and np.bincount(patch).min() >= 30
    # no labels, or every vertex the body: one patch per component
    assert np.array_equal(surface_patches(v, f, 1e4)[0], surface_patches(v, f, 60.0, labels=np.full(len(v), -1))[0])


def test_labelled_patches_let_a_limb_bend_where_one_rigid_patch_cannot():
    """A capsule's upper half turned 20 degrees about its middle: the tracker's one rigid patch over it cannot
    bend (mean error over 3 mm); labelled at the bend (the lower half the body), the same patch size leaves
    the body one patch and the limb another, and the fit follows (under 1.5 mm; measured 5.88 and 0.91 mm)."""
    m = trimesh.creation.capsule(height=200.0, radius=20.0, count=[8, 8])
    v, f = (np.asarray(x) for x in trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=20.0))
    d, df = (np.asarray(x) for x in trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=10.0))
    R = _rotation([1, 0, 0], 20)
    truth, d = v.copy(), d.copy()
    truth[v[:, 2] > 0] = v[v[:, 2] > 0] @ R.T
    d[d[:, 2] > 0] = d[d[:, 2] > 0] @ R.T
    err = {}
    for name, labels in (("none", None), ("bend", np.where(v[:, 2] > 0, 0, -1))):
        tr = TemplateTracker(v, f, patch_size=1000.0, patch_labels=labels)
        fit = tr.fit(d, vertex_normals(d, df), previous=v)
        err[name] = np.linalg.norm(fit.vertices - truth, axis=1).mean()
        assert tr.patches.max() + 1 == (1 if labels is None else 2)
    assert err["bend"] < 1.5 and err["none"] > 3.0, err


def test_blended_patches_overlap_and_blended_align_is_rigid_where_the_target_is():
    m = trimesh.creation.capsule(height=200.0, radius=20.0, count=[24, 24])
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=8.0)
    pp, vv, w = cover = blended_patches(v, f, 60.0)
    np.testing.assert_allclose(np.bincount(vv, weights=w, minlength=len(v)), 1.0)
    # the patches overlap: across every boundary of the partition both vertices are in both patches
    part = surface_patches(v, f, 60.0)[0]
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = e[part[e[:, 0]] != part[e[:, 1]]]
    covered = set(zip(pp.tolist(), vv.tolist()))
    assert len(e) and all((part[j], i) in covered and (part[i], j) in covered for i, j in e)
    R, t = _rotation([1, 2, 3], 40), np.array([5.0, -3.0, 8.0])
    np.testing.assert_allclose(blended_align(v, v @ R.T + t, cover), v @ R.T + t, atol=1e-9)
    # a bent target: the same as a slow reference (loop over patches)
    bent = v.copy()
    top = v[:, 2] > 0
    bent[top] = v[top] @ _rotation([1, 0, 0], 30).T
    noisy = bent + np.random.default_rng(1).normal(0, 0.5, v.shape)
    np.testing.assert_allclose(blended_align(v, noisy, cover), _blended_align_reference(v, noisy, cover), atol=1e-8)


def _blended_align_by_bincount(S, T, cover):
    """:func:`blended_align` summing by bincount (``scatter_add``) in every call: the sums the kept
    summing matrices must give bit for bit."""
    pp, vv, w = cover
    n_p = int(pp.max()) + 1
    sw = np.maximum(np.bincount(pp, weights=w, minlength=n_p), 1e-300)[:, None]
    cs = scatter_add(pp, w[:, None] * S[vv], n_p) / sw
    ct = scatter_add(pp, w[:, None] * T[vv], n_p) / sw
    a = S[vv] - cs[pp]
    H = scatter_add(pp, (w[:, None] * a)[:, :, None] * (T[vv] - ct[pp])[:, None, :], n_p)
    U, _, Wt = np.linalg.svd(H)
    D = np.ones((n_p, 3))
    D[:, 2] = np.sign(np.linalg.det(np.einsum("pij,pjk->pik", U, Wt)))
    R = np.einsum("pji,pj,pkj->pik", Wt, D, U)
    return scatter_add(vv, w[:, None] * (np.einsum("kij,kj->ki", R[pp], a) + ct[pp]), len(S))


def test_the_trackers_blended_align_keeps_its_sums_and_gives_the_same_bits():
    """The previous-shape prior's placement with the cover's summing matrices and patch weights
    built once per take (every round of every frame used to rebuild them by bincount): the same
    placement bit for bit, with and without the kept sums."""
    from pipeline.tracking_patches import _blended_align

    m = trimesh.creation.capsule(height=200.0, radius=20.0, count=[24, 24])
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=8.0)
    tr = TemplateTracker(v, f, prior="previous", align_size=60.0)
    rng = np.random.default_rng(3)
    for _ in range(3):
        S, T = v + rng.normal(0, 1.0, v.shape), v @ _rotation([1, 2, 0], 10).T + rng.normal(0, 1.0, v.shape)
        ref = _blended_align_by_bincount(S, T, tr.align_cover)
        assert np.array_equal(_blended_align(S, T, tr.align_cover, tr._cover_sums), ref)
        assert np.array_equal(blended_align(S, T, tr.align_cover), ref)
    assert TemplateTracker(v, f)._cover_sums is None  # only the previous-shape prior uses them


def test_prediction_repeats_a_rigid_motion_and_drops_what_the_data_cannot_see():
    m = trimesh.creation.cylinder(radius=15.0, height=200.0, sections=24)
    m = m.subdivide().subdivide()
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    patches, _ = surface_patches(v, f, 1000.0)  # one patch
    R = _rotation([1, 0, 0], 4.0)
    step = np.array([0.0, 2.0, 3.0])  # 3 mm along the cylinder's own axis (z): invisible point-to-plane
    c = v.mean(0)
    before = v
    previous = (v - c) @ R.T + c + step
    exact = (previous - c - step) @ R.T + c + 2 * step
    np.testing.assert_allclose(predict_motion(previous, before, f, patches, smoothing=0), exact, atol=1e-6)
    # the cylinder's side: point-to-plane pairs constrain neither sliding along z nor twist about z
    side = np.abs(v[:, 2]) < 99.0
    Q = patch_constraints(previous, np.flatnonzero(side), vertex_normals(previous, f)[side], patches)
    assert np.linalg.matrix_rank(Q[0], tol=1e-6) == 4
    pred = predict_motion(previous, before, f, patches, constrained=Q, smoothing=0)
    axis = R @ [0, 0, 1.0]
    moved = pred - previous
    assert abs((moved.mean(0)) @ axis) < 0.1  # no slide along the (tilted) axis
    assert np.linalg.norm(moved.mean(0)) > 1.0  # the visible part of the step is kept


def test_vertex_normals_point_outwards():
    v, f = _sphere(2)
    n = vertex_normals(v, f)
    np.testing.assert_allclose(np.einsum("ij,ij->i", n, v / 50.0), 1.0, atol=0.01)


def test_vertex_normals_with_the_trackers_corner_sums_are_the_same_bit_for_bit():
    v, f = _sphere(2)
    tr = TemplateTracker(v, f)
    moved = v * [1.0, 1.3, 0.8] + 5.0
    normals = vertex_normals(moved, f, corners=tr.corner_sum)
    assert np.array_equal(normals, vertex_normals(moved, f))
    # an independent reference: area-weighted face normals summed per corner by np.add.at, normalised
    a, b, c = (moved[f[:, i]] for i in range(3))
    slow = np.zeros_like(moved)
    for i in range(3):
        np.add.at(slow, f[:, i], np.cross(b - a, c - a))
    # measured: at most 2.2e-16 apart (unit normals)
    np.testing.assert_allclose(normals, slow / np.linalg.norm(slow, axis=1, keepdims=True), rtol=0, atol=1e-12)
    for bad in (tr.corner_sum[:-1], tr.corner_sum.toarray(), "corners"):
        with pytest.raises(ValueError, match="corners"):
            vertex_normals(moved, f, corners=bad)


def test_invalid_input():
    v, f = _sphere(1)
    with pytest.raises(ValueError, match="vertices"):
        TemplateTracker(v[:, :2], f)
    with pytest.raises(ValueError, match="faces"):
        TemplateTracker(v, f + 1000)
    with pytest.raises(ValueError, match="gamma"):
        TemplateTracker(v, f, gamma=-1)
    with pytest.raises(ValueError, match="gate"):
        TemplateTracker(v, f, gate=0)
    with pytest.raises(ValueError, match="rounds"):
        TemplateTracker(v, f, rounds=0)
    with pytest.raises(ValueError, match="prior"):
        TemplateTracker(v, f, prior="next")
    with pytest.raises(ValueError, match="align_size"):
        TemplateTracker(v, f, prior="previous", align_size=-1.0)
    for blend in ("no", 1, None):
        with pytest.raises(ValueError, match="blend"):
            TemplateTracker(v, f, prior="previous", blend=blend)
    for labels in (np.zeros(len(v) - 1, int), np.zeros(len(v)), np.full(len(v), -2)):
        with pytest.raises(ValueError, match="patch_labels"):
            TemplateTracker(v, f, patch_labels=labels)
    with pytest.raises(ValueError, match="labels"):
        surface_patches(v, f, 10.0, labels=np.zeros((len(v), 2), int))
    for size in (0.0, -1.0, float("nan"), float("inf"), True, "10"):
        with pytest.raises(ValueError, match="size"):
            surface_patches(v, f, size)
        with pytest.raises(ValueError, match="patch_size"):
            TemplateTracker(v, f, patch_size=size)
    with pytest.raises(ValueError, match="vertices"):
        surface_patches(v[:, :2], f, 10.0)
    with pytest.raises(ValueError, match="faces"):
        surface_patches(v, f[:, :2], 10.0)
    for pts, radius, msg in ((v[:, :2], 5.0, "points"), (np.zeros((0, 3)), 5.0, "points"), (v, 0.0, "radius"),
                             (v, float("nan"), "radius"), (v, True, "radius"), (v, "5", "radius")):
        with pytest.raises(ValueError, match=msg):
            farthest_seeds(pts, radius)
    for kwargs, msg in (({"points": v[:, :2]}, "points"), ({"points": np.zeros((0, 3))}, "points"),
                        ({"points": np.r_[v, [[np.nan, 0, 0]]]}, "points"), ({"size": 0.0}, "size"),
                        ({"size": float("inf")}, "size"), ({"size": True}, "size"), ({"offset": float("nan")}, "offset"),
                        ({"offset": "0.5"}, "offset"), ({"corner": [0.0, 0.0]}, "corner"),
                        ({"corner": [np.inf, 0, 0]}, "corner")):
        args = {"points": v, "size": 10.0, **kwargs}
        with pytest.raises(ValueError, match=msg):
            grid_seeds(args.pop("points"), args.pop("size"), **args)
    tr = TemplateTracker(v, f)
    with pytest.raises(ValueError, match="points and normals"):
        tr.fit(np.zeros((5, 3)), np.zeros((4, 3)), previous=v)
    with pytest.raises(ValueError, match="previous"):
        tr.fit(np.zeros((5, 3)), np.zeros((5, 3)), previous=v[:3])
    with pytest.raises(ValueError, match="backend"):
        CholeskySystem(sp.eye(3), backend="magic")
    with pytest.raises(ValueError, match="tracks"):
        tr.fit(v, vertex_normals(v, f), previous=v, tracks=(np.array([0, 1]), np.zeros((3, 3))))
    with pytest.raises(ValueError, match="tracks"):
        tr.fit(v, vertex_normals(v, f), previous=v, tracks=(np.array([len(v)]), np.zeros((1, 3))))


def test_blended_patches_and_blended_align_invalid_input():
    v, f = _sphere(1)
    for size in (0, -5.0, float("nan"), float("inf"), "20", None, True):
        with pytest.raises(ValueError, match="size"):
            blended_patches(v, f, size)
    with pytest.raises(ValueError, match="vertices"):
        blended_patches(v[:, :2], f, 20.0)
    with pytest.raises(ValueError, match="faces"):
        blended_patches(v, f + len(v), 20.0)
    pp, vv, w = cover = blended_patches(v, f, 20.0)
    for src, dst, msg in ((v[:, :2], v[:, :2], "source"), (v, v[:-1], "target"), (v, v.T, "target"),
                          (np.zeros((0, 3)), np.zeros((0, 3)), "source"), (v, v + np.nan, "finite")):
        with pytest.raises(ValueError, match=msg):
            blended_align(src, dst, cover)
    for bad in ((pp, vv), [pp, vv, w, w], (pp, vv[:-1], w), (pp, vv, w[:, None]), (pp[:0], vv[:0], w[:0]),
                (pp, vv.astype(float), w), (pp - 1, vv, w), (pp, vv + 1, w), (pp, vv - 1, w),
                (pp, vv, -w), (pp, vv, w * np.nan)):
        with pytest.raises(ValueError, match="cover"):
            blended_align(v, v, bad)
    # a cover of a bigger surface indexes vertices this one does not have
    with pytest.raises(ValueError, match="cover's vertex"):
        blended_align(v[:10], v[:10], cover)
    np.testing.assert_allclose(blended_align(v, v + [1.0, 2.0, 3.0], list(cover)), v + [1.0, 2.0, 3.0], atol=1e-9)


def test_previous_prior_builds_only_the_placement_it_uses():
    v, f = _sphere(1)
    tr = TemplateTracker(v, f, prior="previous")
    assert tr.blend and tr.align_cover is not None and tr.align_patches is None and tr._align_sum is None
    tr = TemplateTracker(v, f, prior="previous", blend=np.False_)
    assert tr.align_cover is None and tr.align_patches is not None and tr._align_sum is not None
    tr = TemplateTracker(v, f)  # prior="round": neither
    assert tr.align_cover is None and tr.align_patches is None


def test_prediction_follows_motion_faster_than_the_gate():
    """A box sliding 1.5 gates a frame along its long side: lost from the previous frame, kept in
    reach from the prediction (its top and sides do not see the slide, so the prediction leaves
    it out there and the box lags, measured 23 mm after five frames against 60 mm)."""
    m = trimesh.creation.box(extents=(120.0, 80.0, 60.0))
    v, f = np.asarray(m.subdivide().subdivide().subdivide().vertices), np.asarray(m.subdivide().subdivide().subdivide().faces)
    d = m.subdivide().subdivide().subdivide().subdivide()
    tr = TemplateTracker(v, f, gate=10.0)
    step = np.array([15.0, 0.0, 0.0])
    errs = {}
    for predict in (False, True):
        prev, before, seen = v.copy(), None, None
        for k in range(1, 6):
            truth = step * (k - 0.5) if k > 1 else step * 0.5  # a slow first step (within the gate), then fast
            init = predict_motion(prev, before, f, tr.patches, constrained=seen) if predict and before is not None else None
            fit = tr.fit(d.vertices + truth, d.vertex_normals, previous=prev, init=init)
            before, prev, seen = prev, fit.vertices, fit.constrained
        errs[predict] = np.linalg.norm(prev - (v + truth), axis=1).mean()
    assert errs[True] < 0.5 * errs[False], errs
    assert errs[False] > 3 * np.linalg.norm(step), errs  # left behind


def test_tracker_prediction_builds_its_matrices_once_and_predicts_the_same_bits():
    """``TemplateTracker.predict`` (averaging matrix and patch sums kept for the take) equals
    :func:`predict_motion` building them in the call, bit for bit, frame after frame; one ring of
    the averaging is each vertex's mean over itself and its neighbours (slow reference)."""
    m = trimesh.creation.box(extents=(120.0, 80.0, 60.0)).subdivide().subdivide()
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    tr = TemplateTracker(v, f, gate=10.0, patch_size=60.0)
    ring = [{i} for i in range(len(v))]
    for a, b, c in f:
        ring[a] |= {b, c}
        ring[b] |= {a, c}
        ring[c] |= {a, b}
    x = np.random.default_rng(2).normal(size=(len(v), 3))
    slow = np.array([x[sorted(r)].mean(0) for r in ring])
    np.testing.assert_allclose(tr.smoother @ x, slow, rtol=0, atol=1e-14)
    assert tr.smoother is tr.smoother and tr.patch_sum.shape == (int(tr.patches.max()) + 1, len(v))
    prev, before, seen = v.copy(), None, None
    for k in range(1, 5):
        moved = (v - v.mean(0)) @ _rotation([0, 1, 1], 2.0 * k).T + v.mean(0) + [3.0 * k, 0.0, 0.0]
        init = None
        if before is not None:
            init = tr.predict(prev, before, constrained=seen)
            assert np.array_equal(init, predict_motion(prev, before, f, tr.patches, constrained=seen))
        fit = tr.fit(moved, vertex_normals(moved, f), previous=prev, init=init)
        before, prev, seen = prev, fit.vertices, fit.constrained
    with pytest.raises(ValueError, match="smoother"):
        predict_motion(prev, before, f, tr.patches, smoother=tr.smoother[:-1])
    with pytest.raises(ValueError, match="patch_sum"):
        predict_motion(prev, before, f, tr.patches, patch_sum=tr.patch_sum[:, :-1])
    for bad in (tr.smoother.toarray(), "smoother"):  # not a sparse matrix: a ValueError naming it, not AttributeError
        with pytest.raises(ValueError, match="smoother"):
            predict_motion(prev, before, f, tr.patches, smoother=bad)
    with pytest.raises(ValueError, match="patch_sum"):
        predict_motion(prev, before, f, tr.patches, patch_sum=[[1.0]])


def _rotz(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("with_rays", [False, True])
def test_feature_tracks_see_a_cylinders_twist_which_depth_pairs_do_not(with_rays):
    """A cylinder turned 3 degrees about its own axis: its surface is unchanged, so depth pairs keep
    it where it was; tracks of a third of its side vertices give most of the turn of its side (exact:
    R @ v). The flat ends have no tracks and their turn is invisible to their pairs: an end turns only
    where a rigid patch holds it together with tracked side, which depends on where the patches fall,
    so the side is what is scored."""
    m = trimesh.creation.cylinder(radius=20.0, height=120.0, sections=48)
    m = m.subdivide().subdivide()
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    R = _rotz(3.0)
    truth = v @ R.T
    d = trimesh.Trimesh(truth, f, process=False)
    tr = TemplateTracker(v, f)
    plain = tr.fit(d.vertices, d.vertex_normals, previous=v)
    side = np.flatnonzero(np.abs(v[:, 2]) < 50.0)[::3]
    rays = np.tile([0.0, 1.0, 0.0], (len(side), 1))  # a camera looking along +y
    tracks = (side, truth[side], rays) if with_rays else (side, truth[side])
    fit = tr.fit(d.vertices, d.vertex_normals, previous=v, tracks=tracks)
    on = np.abs(v[:, 2]) < 59.0  # the side
    moved = np.linalg.norm(truth - v, axis=1)[on].mean()  # 1 mm at the radius
    assert np.linalg.norm(plain.vertices - truth, axis=1)[on].mean() > 0.8 * moved  # depth alone: the turn is lost
    # measured 0.001 of the turn left (one frame)
    assert np.linalg.norm(fit.vertices - truth, axis=1)[on].mean() < 0.5 * moved


def _slow_start_residuals(V, vn, X, N, patches, gate):
    """Per patch: every vertex's and every data point's gated distance, one at a time."""
    total = np.zeros(patches.max() + 1)
    count = np.zeros(patches.max() + 1)
    for i in range(len(V)):
        d = np.linalg.norm(X - V[i], axis=1)
        j = int(np.argmin(d))
        total[patches[i]] += d[j] if d[j] < gate and vn[i] @ N[j] >= np.cos(np.pi / 4) else gate
        count[patches[i]] += 1
    for j in range(len(X)):
        d = np.linalg.norm(V - X[j], axis=1)
        i = int(np.argmin(d))
        total[patches[i]] += d[i] if d[i] < gate and vn[i] @ N[j] >= np.cos(np.pi / 4) else gate
        count[patches[i]] += 1
    return total / np.maximum(count, 1)


def _half_moved(v, f, shift):
    """The sphere's x > 0 half moved by ``shift`` (the data of a start that only fits one half)."""
    moved = v.copy()
    moved[v[:, 0] > 0] += shift
    return moved


def test_start_residuals_match_a_slow_reference():
    v, f = _sphere(2)
    patches, _ = surface_patches(v, f, 40.0)
    data = _half_moved(v, f, [8.0, 0.0, 0.0]) + 0.3
    X, N = data[::2], vertex_normals(data, f)[::2]
    got = start_residuals(v, X, N, f, patches, gate=10.0)
    want = _slow_start_residuals(v, vertex_normals(v, f), X, N, patches, 10.0)
    # measured: at most 8.9e-16 apart (2.2e-16 relative; residuals 1.87..10 mm)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert got.max() > 2 * got.min()  # the moved half's patches further than the others
    assert np.allclose(start_residuals(v, np.zeros((0, 3)), np.zeros((0, 3)), f, patches, gate=10.0), 10.0)


def test_choose_start_takes_per_patch_the_start_the_data_explain():
    """Data: a sphere whose x > 0 half moved 30 mm (three gates); the unmoved start explains the other half,
    the moved one this half: each patch takes its own, exactly without smoothing, in between with it."""
    v, f = _sphere(3, r=60.0)
    patches, _ = surface_patches(v, f, 30.0)
    shift = np.array([30.0, 0.0, 0.0])
    data = _half_moved(v, f, shift)
    a, b = v, v + shift
    X, N = data, vertex_normals(data, f)
    start, chosen = choose_start([a, b], X, N, f, patches, gate=10.0, smoothing=0)
    cx = scatter_add(patches, v, patches.max() + 1)[:, 0] / np.bincount(patches)
    clear = np.abs(cx) > 15.0  # patches wholly on one side of the cut
    assert np.array_equal(chosen[clear], (cx[clear] > 0).astype(int))
    assert np.array_equal(start, np.where((chosen[patches] == 1)[:, None], b, a))
    smooth, _ = choose_start([a, b], X, N, f, patches, gate=10.0)
    # a vertex more than `smoothing` rings from every patch that chose otherwise keeps its own start
    # (3 rings: this sphere is about 13 rings from the cut to a pole)
    import scipy.sparse as sp

    ring = sp.csr_matrix((np.ones(6 * len(f)), (np.r_[f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]],
                                                np.r_[f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])),
                         shape=(len(v), len(v))) + sp.eye(len(v))
    own = chosen[patches]
    far = np.ones(len(v), bool)
    for c in (0, 1):
        reach = (own != c).astype(float)
        for _ in range(3):
            reach = ring @ reach
        far[own == c] = reach[own == c] == 0
    assert far[own == 0].sum() > 50 and far[own == 1].sum() > 50  # both sides have such interiors
    smooth3, _ = choose_start([a, b], X, N, f, patches, gate=10.0, smoothing=3)
    np.testing.assert_allclose(smooth3[far], np.where((own[far] == 1)[:, None], b[far], a[far]), rtol=0, atol=1e-12)
    assert not np.allclose(smooth3[~far], np.where((own[~far] == 1)[:, None], b[~far], a[~far]), atol=1e-6)
    w = (smooth - a)[:, 0] / 30.0  # the blend weight of the moved start, 0..1
    assert np.all((w >= -1e-12) & (w <= 1 + 1e-12)) and np.any((w > 1e-6) & (w < 1 - 1e-6))
    assert w[v[:, 0] > 30].min() > 0.5 > w[v[:, 0] < -30].max()  # each side mostly its own start
    one, only = choose_start([a], X, N, f, patches, gate=10.0)
    assert np.array_equal(one, a) and not only.any()
    # within reach (the half moved by less than the gate) the first start stays, whatever the residuals say
    near = _half_moved(v, f, [6.0, 0.0, 0.0])
    kept, none = choose_start([a, v + [6.0, 0.0, 0.0]], near, vertex_normals(near, f), f, patches, gate=10.0)
    assert np.array_equal(kept, a) and not none.any()


def test_choose_start_invalid_input():
    v, f = _sphere(1)
    patches, _ = surface_patches(v, f, 40.0)
    n = vertex_normals(v, f)
    with pytest.raises(ValueError, match="candidates"):
        choose_start([], v, n, f, patches, gate=10.0)
    with pytest.raises(ValueError, match="candidates"):
        choose_start([v, v[:5]], v, n, f, patches, gate=10.0)
    with pytest.raises(ValueError, match="smoothing"):
        choose_start([v], v, n, f, patches, gate=10.0, smoothing=-1)
    with pytest.raises(ValueError, match="out_of_reach"):
        choose_start([v], v, n, f, patches, gate=10.0, out_of_reach=1.5)
    with pytest.raises(ValueError, match="points and normals"):
        start_residuals(v, v, n[:3], f, patches, gate=10.0)
    with pytest.raises(ValueError, match="start"):
        start_residuals(v[:, :2], v, n, f, patches, gate=10.0)
    with pytest.raises(ValueError, match="patches"):
        start_residuals(v, v, n, f, patches[:3], gate=10.0)
    with pytest.raises(ValueError, match="gate"):
        start_residuals(v, v, n, f, patches, gate=0.0)
    import scipy.sparse as sp

    from pipeline.tracking import TemplateTracker

    tr = TemplateTracker(v, f, gate=10.0)
    for bad in (True, float("nan"), float("inf"), -1.0, "10", None):  # gate: a finite positive real, not a bool
        for call in (lambda g: start_residuals(v, v, n, f, patches, gate=g),
                     lambda g: choose_start([v], v, n, f, patches, gate=g)):  # one candidate: checked all the same
            with pytest.raises(ValueError, match="gate"):
                call(bad)
    assert start_residuals(v, v, n, f, patches, gate=np.float32(10.0)).shape == (patches.max() + 1,)
    for bad in (tr.smoother.toarray(), sp.eye(len(v) - 1, format="csr")):  # dense, or the wrong shape
        with pytest.raises(ValueError, match="smoother must be a sparse matrix of shape"):
            choose_start([v, v + 1.0], v, n, f, patches, gate=10.0, smoother=bad)
        with pytest.raises(ValueError, match="smoother"):
            choose_start([v], v, n, f, patches, gate=10.0, smoother=bad)
    for bad in (tr.corner_sum.toarray(), tr.corner_sum[:, :-3]):
        with pytest.raises(ValueError, match="corners must be a sparse matrix of shape"):
            start_residuals(v, v, n, f, patches, gate=10.0, corners=bad)
        with pytest.raises(ValueError, match="corners"):
            choose_start([v], v, n, f, patches, gate=10.0, corners=bad)
    for bad in (f[:, :2], f + len(v), f.astype(float)):
        with pytest.raises(ValueError, match="faces"):
            start_residuals(v, v, n, bad, patches, gate=10.0)
    with pytest.raises(ValueError, match="patches"):  # one candidate: checked all the same
        choose_start([v], v, n, f, patches[:3], gate=10.0)
    with pytest.raises(ValueError, match="points and normals"):
        choose_start([v], v, n[:3], f, patches, gate=10.0)
    with pytest.raises(ValueError, match="out_of_reach"):
        choose_start([v], v, n, f, patches, gate=10.0, out_of_reach=True)
