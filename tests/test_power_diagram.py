"""The power diagram built from a WDT: orthocentres, dual edges, adjacency lists."""
from __future__ import annotations

import numpy as np
import pytest

from dmesh import wdt
from dmesh.reference import wdt as ref
from conftest import spacing_weights


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
