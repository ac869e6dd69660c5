"""The weighted Delaunay triangulation (`dmesh.wdt`) against independent oracles, and its power diagram:
orthocentres, dual edges, adjacency lists."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from dmesh import wdt
from dmesh.reference import wdt as ref
from common import spacing_weights

needs_gudhi = pytest.mark.skipif(importlib.util.find_spec("gudhi") is None,
                                 reason="gudhi is the independent WDT oracle (test extra)")


@needs_gudhi
@pytest.mark.parametrize("n", [5, 50, 1000, 20000])
@pytest.mark.parametrize("weighted", [True, False])
def test_tets_match_independent_oracles(rng, n, weighted):
    p = rng.random((n, 3))
    w = spacing_weights(rng, n) if weighted else np.zeros(n)
    ours = ref.canonical_tets(wdt.regular_triangulation(p, w))
    assert len(ours) > 0
    np.testing.assert_array_equal(ours, ref.canonical_tets(ref.gudhi_tets(p, w)))
    if n >= 10:  # Qhull needs at least 5 points; random input is in general position
        np.testing.assert_array_equal(ours, ref.canonical_tets(ref.lifted_hull_tets(p, w)))


@pytest.mark.parametrize("parallel", [False, True])
def test_parallel_insertion_gives_the_same_tets(rng, parallel):
    n = 30000
    p = rng.random((n, 3))
    w = spacing_weights(rng, n)
    seq = ref.canonical_tets(wdt.regular_triangulation(p, w, parallel=False))
    tri = wdt.triangulate(p, w, parallel=parallel)
    np.testing.assert_array_equal(ref.canonical_tets(tri.tets), seq)


@needs_gudhi
def test_large_weights_hide_points_and_match_oracle(rng):
    n = 2000
    p = rng.random((n, 3))
    w = np.where(rng.random(n) < 0.5, 0.01, 0.0)  # weights >> spacing^2: many hidden points
    tets = wdt.regular_triangulation(p, w)
    np.testing.assert_array_equal(ref.canonical_tets(tets), ref.canonical_tets(ref.gudhi_tets(p, w)))
    pd = wdt.PowerDiagram(p, w, tets)
    assert pd.hidden.sum() > 100
    assert not np.isin(np.flatnonzero(pd.hidden), tets).any()


@pytest.mark.parametrize("n", [8, 30, 120])
def test_empty_power_sphere_brute_force(rng, n):
    p = rng.random((n, 3))
    w = spacing_weights(rng, n, scale=0.5)
    tets = wdt.regular_triangulation(p, w)
    assert not ref.empty_power_sphere_violations(p, w, tets).any()


def test_empty_power_sphere_check_catches_a_wrong_tet():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.2, 0.2, 0.2]], dtype=float)
    w = np.zeros(5)
    assert ref.empty_power_sphere_violations(p, w, np.array([[0, 1, 2, 3]]))[0]
    assert not ref.empty_power_sphere_violations(p, w, wdt.regular_triangulation(p, w)).any()


def test_hull_volume_is_covered(rng):
    from scipy.spatial import ConvexHull

    p = rng.random((500, 3))
    tets = wdt.regular_triangulation(p, None)
    a, b, c, d = (p[tets[:, k]] for k in range(4))
    vol = np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0
    assert (vol > 0).all(), "tets are positively oriented"
    assert vol.sum() == pytest.approx(ConvexHull(p).volume, rel=1e-9)


@pytest.mark.parametrize("kind", ["random", "grid"])
def test_output_order_does_not_depend_on_the_insertion(rng, kind):
    """Byte-identical tets and neighbours from sequential and TBB insertion, run after run (the order is
    canonical), also on a grid, whose cospherical points the symbolic perturbation decides."""
    if kind == "random":
        p = rng.random((30000, 3))
        w = spacing_weights(rng, len(p))
    else:
        g = np.linspace(0.0, 1.0, 32)
        p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        w = np.zeros(len(p))
    seq = wdt.triangulate(p, w, parallel=False)
    np.testing.assert_array_equal(seq.tets[:, 0], seq.tets.min(1))  # smallest id first
    key = seq.tets.astype(np.int64) @ (len(p) ** np.arange(3, -1, -1, dtype=np.int64))
    assert (np.diff(key) > 0).all()                                    # rows ascending
    for _ in range(3):
        par = wdt.triangulate(p, w, parallel=True)
        np.testing.assert_array_equal(par.tets, seq.tets)
        np.testing.assert_array_equal(par.neighbors, seq.neighbors)


def test_automatic_mode_inserts_sequentially_on_a_one_thread_budget(rng):
    """torch.get_num_threads() is the thread budget of the kernels (a sweep's runner sets it per run): at 1,
    the automatic mode does not start TBB's threads, and the tets are the same."""
    import torch

    p = rng.random((30000, 3))  # above native.PARALLEL_THRESHOLD
    w = spacing_weights(rng, len(p))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = wdt.triangulate(p, w)
    finally:
        torch.set_num_threads(before)
    assert not one.parallel
    np.testing.assert_array_equal(one.tets, wdt.triangulate(p, w, parallel=True).tets)


def test_grid_gives_six_tets_per_cube_and_no_flat_ones():
    g = np.linspace(0.0, 1.0, 20)
    p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    tets = wdt.regular_triangulation(p, np.zeros(len(p)))
    assert len(tets) == 6 * 19**3 == 41154
    a, b, c, d = (p[tets[:, k]] for k in range(4))
    vol = np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0
    assert vol.min() > 1e-8
    assert vol.sum() == pytest.approx(1.0)


def test_hidden_points_are_in_no_tet():
    g = np.linspace(0.0, 1.0, 8)
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    h = g[1] - g[0]
    centres = grid[(grid < 1.0 - 1e-9).all(1)] + h / 2
    p = np.concatenate([grid, centres])
    w = np.concatenate([np.full(len(grid), h * h), np.zeros(len(centres))])
    tets = wdt.regular_triangulation(p, w)
    used = np.unique(tets)
    assert np.array_equal(used, np.arange(len(grid))), "cube centres are hidden by the heavy grid"
    pd = wdt.PowerDiagram(p, w, tets)
    np.testing.assert_array_equal(pd.hidden, np.arange(len(p)) >= len(grid))


@pytest.mark.parametrize("heavier_copy", [False, True])
def test_duplicates_merge_and_the_first_index_survives(rng, heavier_copy):
    p = rng.random((300, 3))
    dup_src = rng.choice(300, 40, replace=False)
    p = np.concatenate([p, p[dup_src]])
    w = np.zeros(len(p))
    if heavier_copy:
        w[300:] = 1e-4  # the contract keeps the first index even when a later copy is heavier
    tri = wdt.triangulate(p, w)
    used = np.unique(tri.tets)
    assert not np.isin(np.arange(300, 340), used).any()
    assert np.isin(dup_src, used).all()
    np.testing.assert_array_equal(tri.duplicate_of[300:], dup_src)
    assert (tri.duplicate_of[:300] == -1).all()
    # Same triangulation as with the copies removed.
    np.testing.assert_array_equal(ref.canonical_tets(tri.tets),
                                  ref.canonical_tets(wdt.regular_triangulation(p[:300], w[:300])))


@pytest.mark.parametrize(
    "points, weights, message",
    [
        (np.zeros((3, 3)), np.zeros(3), "at least 4 distinct points"),
        (np.repeat(np.eye(3)[:1], 10, 0), np.zeros(10), "at least 4 distinct points"),
        (np.c_[np.random.default_rng(0).random((50, 2)), np.full(50, 0.5)], np.zeros(50), "not affinely independent"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan]]), np.zeros(4), "finite"),
        (np.eye(4)[:, :3], np.array([0, 0, np.inf, 0]), "finite"),
        (np.zeros((5, 2)), np.zeros(5), r"shape \(N, 3\)"),
        (np.random.default_rng(0).random((6, 3)), np.zeros(5), r"shape \(6,\)"),
    ],
)
def test_degenerate_input_raises_clear_errors(points, weights, message):
    with pytest.raises(ValueError, match=message):
        wdt.regular_triangulation(points, weights)


def test_native_validates_shapes_itself():
    from dmesh import _native

    with pytest.raises(ValueError, match="weights must have shape"):
        _native.regular_triangulation(np.zeros((5, 3)), np.zeros(4), -1)
    with pytest.raises(TypeError):  # noconvert: float32 is refused rather than copied silently
        _native.regular_triangulation(np.zeros((5, 3), np.float32), np.zeros(5), -1)


def test_torch_input_is_accepted(rng):
    import torch

    p = torch.rand(100, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float32)
    tets = wdt.regular_triangulation(p, torch.zeros(100))
    assert tets.dtype == np.int32 and tets.shape[1] == 4


# ---------------------------------------------------------------------------------------- power diagram

@pytest.fixture(params=[60, 3000])
def diagram(request, rng):
    n = request.param
    p = rng.random((n, 3))
    w = spacing_weights(rng, n, scale=0.3)
    return wdt.PowerDiagram.from_points(p, w)


def test_orthocentres_have_equal_power_to_their_four_points(diagram):
    c = diagram.orthocentres
    pts = diagram.points[diagram.tets]
    pw = ((c[:, None, :] - pts) ** 2).sum(-1) - diagram.weights[diagram.tets]
    spread = pw.max(1) - pw.min(1)
    assert spread.max() < 1e-9 * (1 + np.abs(pw).max())
    np.testing.assert_allclose(c, ref.orthocentres(diagram.points, diagram.weights, diagram.tets),
                               rtol=0, atol=1e-9)


def test_faces_are_unique_sorted_and_each_tet_face_is_listed(diagram):
    f = diagram.faces
    assert (f[:, 0] < f[:, 1]).all() and (f[:, 1] < f[:, 2]).all()
    assert len(np.unique(f, axis=0)) == len(f)
    for k in range(4):
        face_of = diagram.faces[diagram.tet_faces[:, k]]
        expect = np.sort(np.delete(diagram.tets, k, axis=1), axis=1)
        np.testing.assert_array_equal(face_of, expect)
    # Interior faces have 2 tets, hull faces 1; every tet side is accounted for once.
    assert 2 * (~diagram.is_hull).sum() + diagram.is_hull.sum() == 4 * len(diagram.tets)


def test_hull_faces_match_the_convex_hull(diagram):
    from scipy.spatial import ConvexHull

    hull = np.sort(ConvexHull(diagram.points[~diagram.hidden]).simplices, axis=1)
    used = np.flatnonzero(~diagram.hidden)
    hull = np.sort(used[hull], axis=1)
    ours = diagram.faces[diagram.is_hull]
    assert {tuple(r) for r in hull} == {tuple(r) for r in ours}


def test_hull_rays_point_away_from_their_tet(diagram):
    hull = np.flatnonzero(diagram.is_hull)
    d = diagram.ray_dirs[hull]
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    tets = diagram.tets[diagram.face_tets[hull, 0]]
    apex = np.array([np.setdiff1d(t, f)[0] for t, f in zip(tets, diagram.faces[hull])])
    a = diagram.points[diagram.faces[hull, 0]]
    assert (np.einsum("ij,ij->i", d, diagram.points[apex] - a) < 0).all()
    # Perpendicular to the face.
    b = diagram.points[diagram.faces[hull, 1]]
    c = diagram.points[diagram.faces[hull, 2]]
    assert np.abs(np.einsum("ij,ij->i", d, b - a)).max() < 1e-9
    assert np.abs(np.einsum("ij,ij->i", d, c - a)).max() < 1e-9
    assert (diagram.ray_dirs[~diagram.is_hull] == 0).all()


def test_dual_edges_are_equidistant_in_power_from_the_face_vertices(diagram):
    start, end = diagram.dual_edges(ray_length=2.0)
    for x in (start, end, 0.5 * (start + end)):
        pts = diagram.points[diagram.faces]
        pw = ((x[:, None, :] - pts) ** 2).sum(-1) - diagram.weights[diagram.faces]
        assert (pw.max(1) - pw.min(1)).max() < 1e-8 * (1 + np.abs(pw).max())


def test_point_adjacency_lists(diagram):
    n = diagram.num_points
    for i in range(0, n, max(1, n // 25)):
        tets = diagram.point_tets.row(i)
        np.testing.assert_array_equal(tets, np.flatnonzero((diagram.tets == i).any(1)))
        faces = diagram.point_faces.row(i)
        np.testing.assert_array_equal(faces, np.flatnonzero((diagram.faces == i).any(1)))
        nbrs = diagram.point_neighbors.row(i)
        expect = np.setdiff1d(np.unique(diagram.tets[tets]), [i])
        np.testing.assert_array_equal(nbrs, expect)


def test_adjacency_from_tets_alone_matches_cgal(diagram):
    from dmesh import native

    tri = wdt.triangulate(diagram.points, diagram.weights)
    np.testing.assert_array_equal(native.tet_neighbors(tri.tets), tri.neighbors)


def test_face_ids_lookup(diagram):
    f = diagram.faces
    ids = diagram.face_ids(f[::7][:, ::-1])  # any vertex order
    np.testing.assert_array_equal(ids, np.arange(0, len(f), 7))
    assert diagram.face_ids([[0, 0, 1]])[0] == -1


def test_bad_tets_raise(rng):
    p = rng.random((10, 3))
    with pytest.raises(ValueError, match="tets must index points"):
        wdt.PowerDiagram(p, None, np.array([[0, 1, 2, 99]]))
    with pytest.raises(ValueError, match="tets must have shape"):
        wdt.PowerDiagram(p, None, np.array([[0, 1, 2]]))
