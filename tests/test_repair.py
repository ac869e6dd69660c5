"""Face repairs (`dmesh.repair`): hole filling, fans split at shared vertices and edges, sheet winding."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datasets.synthetic import generate
from dmesh import repair
from common import check_closed, cycle


def test_rim_edges_count_each_face_of_an_edge_shared_by_more_than_two():
    """`rim_edge_count`: a closed tetrahedron has none; two triangles on an edge have their 4 outer edges;
    three triangles on one edge have 6 outer edges plus 3 for the shared one (split apart, each face keeps a
    rim there), where `boundary_edge_count` sees only the 6."""
    tet = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]])
    pair = np.array([[0, 1, 2], [1, 0, 3]])
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    assert [repair.rim_edge_count(f) for f in (tet, pair, fan)] == [0, 4, 9]
    assert repair.boundary_edge_count(fan) == 6


def test_fill_holes_restores_a_box():
    box = trimesh.creation.box()
    for drop in ([0], [0, 1]):  # a triangle hole and a square one
        keep = np.setdiff1d(np.arange(len(box.faces)), drop)
        fill, filled, left, crossing = repair.fill_holes(box.vertices, box.faces[keep], max_edges=8)
        assert (filled, left, crossing) == (1, 0, 0)
        mesh = check_closed(np.concatenate([box.faces[keep], fill]), box.vertices)
        assert mesh.volume == pytest.approx(1.0)
    # Too large a hole stays open.
    assert repair.fill_holes(box.vertices, box.faces[2:], max_edges=3)[1:] == (0, 1, 0)


def test_a_hole_whose_fill_would_cross_the_surface_stays_open():
    box = trimesh.creation.box()  # the top (+z) square is faces whose normals point up
    top = np.flatnonzero(box.face_normals[:, 2] > 0.5)
    keep = np.setdiff1d(np.arange(len(box.faces)), top)
    # A closed thin tetrahedron from inside the box out through the square hole.
    spike = np.array([[0.05, -0.1, 0.0], [-0.1, 0.05, 0.0], [0.1, 0.1, 0.0], [0.0, 0.0, 1.5]])
    v = np.vstack([box.vertices, spike])
    n = len(box.vertices)
    tet = n + np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]])
    faces = np.concatenate([box.faces[keep], tet])
    fill, filled, left, crossing = repair.fill_holes(v, faces, max_edges=8)
    assert (len(fill), filled, left, crossing) == (0, 0, 1, 1)
    fill, filled, left, crossing = repair.fill_holes(v, faces, max_edges=8, uncrossed=False)
    assert (len(fill), filled, left, crossing) == (2, 1, 0, 0)
    assert repair.crossing_triangles(v, fill, faces).all()
    # Faces that bound no hole but must not be crossed either (the sheets beside a closed part).
    assert repair.fill_holes(v, box.faces[keep], max_edges=8, others=tet)[1:] == (0, 1, 1)
    assert repair.fill_holes(v, box.faces[keep], max_edges=8)[1:] == (1, 0, 0)


def test_a_crossing_fill_is_made_again_without_its_crossing_triangles():
    box = trimesh.creation.box()
    top = np.flatnonzero(box.face_normals[:, 2] > 0.5)
    keep = np.setdiff1d(np.arange(len(box.faces)), top)
    v = box.vertices.copy()
    v[(v[:, 2] > 0) & (v[:, 0] * v[:, 1] < 0)] += [0, 0, 0.5]  # the hole is a saddle: two different fills
    v[(v[:, 2] > 0) & (v[:, 0] > 0) & (v[:, 1] > 0)] += [0, 0, 0.2]  # the one over the raised corners is smaller
    spike = np.array([[0.05, -0.1, 1.5], [-0.1, 0.05, 1.5], [0.1, 0.1, 1.5], [0.0, 0.0, 0.8]])  # from above,
    n = len(v)  # down through the smaller fill (height 1 at the middle) but not the other (0.6)
    v = np.vstack([v, spike])
    tet = n + np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])
    first = repair.fill_holes(v, box.faces[keep], max_edges=8)[0]
    assert repair.crossing_triangles(v, first, tet).any()
    fill, filled, left, crossing = repair.fill_holes(v, box.faces[keep], max_edges=8, others=tet)
    assert (len(fill), filled, left, crossing) == (2, 1, 0, 0)
    assert not repair.crossing_triangles(v, fill, tet).any()
    check_closed(np.concatenate([box.faces[keep], fill]), v)


def test_a_small_triangle_crossing_a_huge_face_far_from_its_centre_is_found():
    """The index keeps faces in bands of radius; a search must reach a huge face from near its corner."""
    big = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]])
    rng = np.random.default_rng(1)
    crumbs = rng.uniform(0, 50, (300, 1, 3)) + np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]) + [0, 0, 5.0]
    poke = np.array([[1.0, 1.0, -0.1], [1.05, 1.0, 0.1], [1.0, 1.05, 0.1]])  # through the big face, near a corner
    miss = poke + [0, 0, 1.0]
    v = np.vstack([big, crumbs.reshape(-1, 3), poke, miss])
    faces = np.arange(3 + 900).reshape(-1, 3)
    tris = np.arange(903, 909).reshape(-1, 3)
    assert repair.crossing_triangles(v, tris, faces).tolist() == [True, False]
    assert repair.crossing_triangles(v, tris, faces[1:]).tolist() == [False, False]


def test_triangle_crossings_match_pymeshlab():
    """Random triangle pairs, far apart from each other, half sharing one vertex: the pairs our test calls
    crossing are exactly those whose faces VCG's self-intersection filter selects."""
    pymeshlab = pytest.importorskip("pymeshlab")
    rng = np.random.default_rng(0)
    pairs, shared = 400, 200
    pts = rng.uniform(-1, 1, (pairs, 6, 3)) + 10.0 * np.arange(pairs)[:, None, None]
    ids = 6 * np.arange(pairs)[:, None] + np.array([0, 1, 2, 3, 4, 5])
    s, t = ids[:, :3].copy(), ids[:, 3:].copy()
    t[:shared, 0] = s[:shared, 0]  # share one vertex
    v = pts.reshape(-1, 3)
    ours = repair.triangles_cross(v, s, t)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=np.concatenate([s, t]).astype(np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    picked = ms.current_mesh().face_selection_array()
    assert 20 < ours[:shared].sum() and 20 < ours[shared:].sum()  # both kinds cross often enough to test
    assert np.array_equal(ours, picked[:pairs] & picked[pairs:])
    assert np.array_equal(picked[:pairs], picked[pairs:])
    # The batch version over a whole face list agrees, and a triangle never crosses itself or a neighbour.
    assert np.array_equal(repair.crossing_triangles(v, s, np.concatenate([s, t])), ours)


def test_a_long_planar_hole_gets_its_polygon_area():
    """The fill of a flat convex 400-edge loop is a triangulation of it: n - 2 distinct triangles whose areas
    add up to the polygon's (shoelace) area. (Every triangulation of a convex polygon has that area, so this
    checks validity, not minimality.)"""
    n = 400
    angle = np.sort(np.random.default_rng(0).uniform(0, 2 * np.pi, n))
    v = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)
    tris = repair.fill_loop(list(range(n)), v, set())
    assert tris.shape == (n - 2, 3) and len(np.unique(np.sort(tris, axis=1), axis=0)) == n - 2
    shoelace = 0.5 * abs(np.dot(v[:, 0], np.roll(v[:, 1], -1)) - np.dot(v[:, 1], np.roll(v[:, 0], -1)))
    area = 0.5 * np.linalg.norm(np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]]), axis=1)
    assert area.sum() == pytest.approx(shoelace, rel=1e-9)


def test_hole_loops_split_at_a_shared_vertex():
    bowtie = np.array([[0, 1, 2], [0, 3, 4]])  # two triangles that share vertex 0 only
    loops = repair.hole_loops(bowtie)
    assert sorted(sorted(loop) for loop in loops) == [[0, 1, 2], [0, 3, 4]]
    assert {cycle(loop) for loop in loops} == {(0, 2, 1), (0, 4, 3)}  # against the faces' winding
    assert repair.nonmanifold_vertices(bowtie).tolist() == [0]


def test_sheets_meeting_at_an_edge_are_split_and_folds_dropped():
    box = trimesh.creation.box()
    e = box.edges_unique[0]
    v = np.vstack([box.vertices, box.vertices[e].mean(0) + [0, 0, 3.0]])
    faces = np.concatenate([box.faces, [[e[0], e[1], len(box.vertices)]]])  # a fin on a box edge
    split, source = repair.split_fans(faces)
    assert len(repair.nonmanifold_edges(split)) == 0 and len(repair.nonmanifold_vertices(split)) == 0
    assert len(source) == len(v) + 2 and np.array_equal(v[source][split], v[faces])  # nothing moved
    assert np.array_equal(source[:len(v)], np.arange(len(v)))
    # Three faces around one edge that are joined around both its ends cannot be split: the smallest goes.
    fold = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [2, 4, 0], [3, 2, 1]])
    pts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0.2, 0.1]], float)
    keep = repair.drop_crowding(pts, fold)
    assert keep.sum() == 4 and not keep[2]


def test_split_copies_move_apart_into_their_own_faces():
    from datasets.meshes import merge_vertices

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0.5]], float)
    bowtie = np.array([[0, 1, 2], [0, 3, 4]])                     # two triangles that share vertex 0 only
    faces, source = repair.split_fans(bowtie, len(v))
    at = v[source]
    moved = repair.separate_copies(at, faces, source, ratio=0.1)
    copies = np.flatnonzero(source == 0)
    assert len(copies) == 2
    for c in copies:                                              # 10 % of the way to its own face's centroid
        centroid = at[faces[(faces == c).any(1)][0]].mean(0)
        np.testing.assert_allclose(moved[c], 0.9 * at[c] + 0.1 * centroid)
    rest = np.setdiff1d(np.arange(len(source)), copies)
    assert np.array_equal(moved[rest], at[rest])
    # Merged by position (a file read back), the copies on one point make the pinch again; moved, they do not.
    assert len(repair.nonmanifold_vertices(merge_vertices(at, faces)[1])) == 1
    assert len(repair.nonmanifold_vertices(merge_vertices(moved, faces)[1])) == 0
    assert np.array_equal(repair.separate_copies(v, bowtie, np.arange(len(v))), v)  # no copies: nothing moves
    with pytest.raises(ValueError, match="ratio"):
        repair.separate_copies(at, faces, source, ratio=1.0)


def test_surface_keeps_every_face_of_a_branch_and_moves_its_copies_apart():
    """Three sheet faces on one edge: each keeps its face, with its own copies of the edge's vertices, moved
    into it, so that read back with vertices merged by position the edge is not a branch."""
    from datasets.meshes import merge_vertices
    from dmesh import wdt
    from dmesh.extract import SurfaceConfig, _surface_mesh

    # A flat strip of two faces on edge 0-1 (z = 0) and a fin standing up from that edge.
    pts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0.1, 1.0],
                    [3, 3, 3], [-3, 3, -3], [3, -3, -3], [-3, -3, 3]], float)
    pd = wdt.PowerDiagram.from_points(pts, None)
    wanted = {(0, 1, 2), (0, 1, 3), (0, 1, 4)}
    walls = np.array([tuple(sorted(f)) in wanted for f in pd.faces.tolist()])
    assert walls.sum() == 3
    mesh = _surface_mesh(pd, walls, None, SurfaceConfig(max_crumb=0))
    assert len(mesh.faces) == 3 and mesh.metadata["surface"]["split_vertices"] == 4   # 2 more copies of 0 and 1
    merged = merge_vertices(mesh.vertices, mesh.faces)[1]
    assert len(repair.nonmanifold_edges(merged)) == 0 and len(repair.nonmanifold_vertices(merged)) == 0
    # Only the copies moved, each by 5 % of the way to its face's centroid (far less than an edge).
    moved = np.linalg.norm(mesh.vertices - pts[np.argmin(((mesh.vertices[:, None] - pts) ** 2).sum(2), 1)], axis=1)
    assert (moved[moved > 0] < 0.05).all() and (moved > 0).sum() == 6


def test_an_orientable_sheet_turns_whole_whatever_its_vectors_say():
    """Directions towards cameras on a sheet seen from both sides point up on one half and down on the other:
    face by face they would split the sheet's winding. A sheet that can be wound consistently turns whole, to
    the side most of its area agrees with, with input normals (turn_faces) or without."""
    from eval.metrics import topology

    grid = trimesh.creation.box(extents=(2.0, 2.0, 0.0)).subdivide().subdivide()   # a flat square, doubled
    top = grid.faces[grid.face_normals[:, 2] > 0]
    sheet = trimesh.Trimesh(grid.vertices, top).subdivide()
    v, f = np.asarray(sheet.vertices), np.asarray(sheet.faces)
    centres = v[f].mean(1)
    towards = np.where((centres[:, 0] < 0.4)[:, None], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])  # 70 % up
    for turn_faces in (True, False):
        out = repair.orient_sheets(v, f, (centres, towards), turn_faces=turn_faces)
        assert topology(v, out)["inconsistent_winding_edges"] == 0
        assert (trimesh.Trimesh(v, out, process=False).face_normals[:, 2] > 0).all()


def test_a_non_orientable_sheet_puts_its_seam_where_its_normals_turn():
    """A Mobius strip has no consistent winding; with turn_faces its faces turn one by one to their normals,
    so the one seam lies where the given normals flip, not where the spanning tree happened to close."""
    strip = generate("mobius")
    v, f = np.asarray(strip.vertices), np.asarray(strip.faces)
    normals = trimesh.Trimesh(v, f, process=False).face_normals
    rng = np.random.default_rng(0)
    scrambled = f.copy()
    turned = rng.random(len(f)) < 0.5
    scrambled[turned] = scrambled[turned][:, ::-1]
    flip, comp, n = repair.winding_components(scrambled)
    assert n == 1 and repair.seam_components(np.where(flip[:, None], scrambled[:, ::-1], scrambled), comp, n)[0]
    out = repair.orient_sheets(v, scrambled, (v[f].mean(1), normals), k=1)
    agree = np.einsum("ij,ij->i", trimesh.Trimesh(v, out, process=False).face_normals, normals)
    assert (agree > 0).all()
    whole = repair.orient_sheets(v, scrambled, (v[f].mean(1), normals), k=1, turn_faces=False)
    assert (np.einsum("ij,ij->i", trimesh.Trimesh(v, whole, process=False).face_normals, normals) < 0).any()


def test_sheet_winding_follows_the_normals_or_the_volume():
    box = trimesh.creation.box()
    scrambled = box.faces.copy()
    scrambled[::2] = scrambled[::2, ::-1]
    out = repair.orient_sheets(box.vertices, scrambled)
    assert trimesh.Trimesh(box.vertices, out, process=False).volume == pytest.approx(1.0)
    centres, normals = box.triangles_center, box.face_normals
    inward = repair.orient_sheets(box.vertices, scrambled, (centres, -normals))
    assert trimesh.Trimesh(box.vertices, inward, process=False).volume == pytest.approx(-1.0)
    # Faces without a shared edge: each is its own component and faces its normal.
    lone = repair.orient_sheets(box.vertices, scrambled[[0, 5]], (centres[[0, 5]], normals[[0, 5]]))
    assert (np.einsum("ij,ij->i", trimesh.Trimesh(box.vertices, lone, process=False).face_normals,
                      normals[[0, 5]]) > 0).all()
    # A Mobius strip cannot be wound consistently: one seam is left, nothing fails.
    strip = generate("mobius")
    flip, comp, n = repair.winding_components(np.asarray(strip.faces))
    assert n == 1 and 0 < flip.sum() < len(strip.faces)


def test_orientation_is_consistent():
    import trimesh

    box = trimesh.creation.box()
    faces = box.faces.copy()
    faces[::2] = faces[::2, ::-1]                       # scramble the winding of every other face
    mesh = trimesh.Trimesh(box.vertices, faces, process=False)
    repair.orient_faces(mesh)
    assert mesh.is_winding_consistent and mesh.volume > 0


def test_crumbs_are_a_sheet_part_made_only_of_small_edge_connected_pieces():
    sheet = trimesh.creation.box().faces  # 12 faces, one piece: a real sheet
    stray = np.array([[20, 21, 22]])  # a lone triangle
    pair = np.array([[30, 31, 32], [31, 32, 33]])  # two triangles sharing an edge
    touching = np.array([[0, 40, 41]])  # shares only a vertex with the box: a piece of its own
    small = np.concatenate([stray, pair, touching])
    assert repair.crumbs(small, 2).all()
    assert not repair.crumbs(small, 1).any()  # the pair is larger than 1 face: a real sheet part
    # Beside a real sheet, small pieces may be parts of it: none is a crumb.
    assert not repair.crumbs(np.concatenate([sheet, small]), 2).any()
    assert repair.crumbs(np.concatenate([sheet, small]), 12).all()
    assert not repair.crumbs(small, 0).any()
    assert repair.crumbs(np.zeros((0, 3), np.int64), 4).shape == (0,)


def test_surface_drops_stray_sheet_triangles_so_a_closed_part_stays_watertight():
    from dmesh import wdt
    from dmesh.extract import SurfaceConfig, surface

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(400, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    inner = 0.3 * rng.normal(size=(40, 3))
    pd = wdt.PowerDiagram.from_points(np.concatenate([pts, inner]), None)
    hull = pd.is_hull
    walls = hull.copy()
    inner_faces = np.flatnonzero((pd.faces >= len(pts)).all(1))  # faces among the interior points only
    walls[inner_faces[:1]] = True  # one stray triangle inside the ball
    # max_crumb: pieces this small go when all are; max_debris: a sheet part this small a fraction of the faces
    # goes whatever its pieces' sizes (one stray face among about 800 is 1/800 of them). The stray triangle can
    # lie within an edge length of the sphere; the test of pieces lying on the surface (`stacked`) is off here.
    for max_crumb, max_debris, expect_stray in ((4, 0.0, False), (0, 0.0, True), (0, 1e-3, True), (0, 0.01, False)):
        out = surface(pd, walls, config=SurfaceConfig(max_crumb=max_crumb, max_debris=max_debris, stacked=0.0))
        mesh = trimesh.Trimesh(pd.points[out.vertices], out.faces, process=False)
        assert ((len(out.faces) == int(hull.sum()) + 1) == expect_stray
                and out.info["crumbs_dropped"] == (not expect_stray))
        assert mesh.split(only_watertight=False)[0].is_watertight


def test_keep_flattest_drops_the_fin_across_a_flat_pair():
    from dmesh.repair import keep_flattest

    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.0], [0.2, 0.8, -0.3]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4], [2, 0, 5]])    # a flat square split on edge 0-2, two fins
    keep = keep_flattest(v, f)
    assert keep.tolist() == [True, True, False, False]
    assert keep_flattest(v, f[:2]).all()                           # a manifold mesh keeps every face


def test_closed_crumbs_are_tiny_closed_pieces_beside_a_larger_one():
    """One tet's boundary and a two-face pillow beside a sphere go; the sphere alone, a tiny open piece and
    a mesh made only of tiny closed pieces stay."""
    ball = trimesh.creation.icosphere(subdivisions=1)
    n = len(ball.vertices)
    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]) + n
    pillow = np.array([[0, 1, 2], [0, 2, 1]]) + n + 4
    lone = np.array([[0, 1, 2]]) + n + 7
    faces = np.concatenate([ball.faces, tet, pillow, lone])
    crumbs = repair.closed_crumbs(faces, 4)
    assert crumbs.sum() == 6 and crumbs[len(ball.faces):len(ball.faces) + 6].all()
    assert not repair.closed_crumbs(ball.faces, 4).any()
    assert not repair.closed_crumbs(tet, 4).any()           # nothing larger beside it: it is the mesh
    assert not repair.closed_crumbs(faces, 0).any()


def test_refine_and_fair_restores_a_flattened_cap_of_a_sphere():
    """CGAL's refine and fair over a cap of a sphere pressed flat: the cap comes back towards the sphere
    (the reference: the unit sphere itself), the other vertices and faces stay as they were, and the mesh
    stays a closed 2-manifold of the sphere's genus."""
    from dmesh import native

    sphere = trimesh.creation.icosphere(3)
    v, f = np.asarray(sphere.vertices, dtype=np.float64), np.asarray(sphere.faces, dtype=np.int64)
    patch = v[f].mean(1)[:, 2] > 0.6
    inner = np.setdiff1d(np.unique(f[patch]), np.unique(f[~patch]))  # vertices with only cap faces around
    pressed = v.copy()
    pressed[inner, 2] = 0.6
    out_v, out_f, out_patch, solved = native.refine_and_fair(pressed, f, patch, density=4.0, continuity=1)
    assert solved and len(out_v) > len(v) and out_patch.sum() > patch.sum()
    moved = np.r_[inner, np.arange(len(v), len(out_v))]
    before = np.abs(np.linalg.norm(pressed[inner], axis=1) - 1.0).mean()
    after = np.abs(np.linalg.norm(out_v[moved], axis=1) - 1.0).mean()
    assert after < 0.25 * before, (before, after)
    held = np.setdiff1d(np.arange(len(v)), inner)
    assert np.array_equal(out_v[held], pressed[held])
    assert {cycle(t) for t in f[~patch].tolist()} <= {cycle(t) for t in out_f[~out_patch].tolist()}
    mesh = check_closed(out_f, out_v)
    assert mesh.euler_number == 2
    # `hold`: the pressed vertices stay; only the new ones move, and still towards the sphere
    kept_v, kept_f, kept_patch, solved = native.refine_and_fair(pressed, f, patch, density=4.0, continuity=1,
                                                                hold=np.isin(np.arange(len(v)), inner))
    assert solved and np.array_equal(kept_v[:len(v)], pressed) and len(kept_v) > len(v)
    new = kept_v[len(v):]
    risen = new[:, 2] > 0.6 + 1e-9  # the new vertices over the pressed cap rise off its plane
    assert risen.mean() > 0.5
    check_closed(kept_f, kept_v)


def test_long_faces_are_long_against_the_median_edge():
    grid = trimesh.creation.box(extents=(1, 1, 1)).subdivide().subdivide()
    v, f = np.asarray(grid.vertices, dtype=np.float64), np.asarray(grid.faces, dtype=np.int64)
    stretched = v.copy()
    stretched[0] = stretched[0] * 9.0  # one corner pulled far out: its faces' edges grow
    at = np.isin(f, [0]).any(1)
    assert repair.long_faces(v, f, 2.0).sum() == 0
    assert np.array_equal(repair.long_faces(stretched, f, 4.0), at)
    assert repair.long_faces(v, f[:0], 4.0).shape == (0,)


def test_refine_and_fair_rejects_what_is_not_an_oriented_manifold():
    from dmesh import native

    sphere = trimesh.creation.icosphere(1)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    flipped = f.copy()
    flipped[0] = flipped[0, ::-1]  # one face wound against its neighbours
    with pytest.raises(ValueError, match="2-manifold"):
        native.refine_and_fair(v, flipped, np.zeros(len(f), bool))
    with pytest.raises(ValueError, match="patch has"):
        native.refine_and_fair(v, f, np.zeros(3, bool))
    with pytest.raises(ValueError, match="continuity"):
        native.refine_and_fair(v, f, np.zeros(len(f), bool), continuity=3)
    with pytest.raises(ValueError, match="hold has"):
        native.refine_and_fair(v, f, np.zeros(len(f), bool), hold=np.zeros(2, bool))


def test_untangle_smooths_a_fold_out_of_a_patch_and_moves_nothing_else():
    sphere = trimesh.creation.icosphere(2)
    v, f = np.asarray(sphere.vertices, dtype=np.float64), np.asarray(sphere.faces, dtype=np.int64)
    patch = v[f].mean(1)[:, 2] > 0.5
    free = np.setdiff1d(np.unique(f[patch]), np.unique(f[~patch]))
    folded = v.copy()
    folded[free[0]] = [0.05, 0.05, -1.5]  # one cap vertex pulled out through the far side: its faces cross it
    assert repair.FaceIndex(folded, f).crossing(f[patch]).any()
    out, hit = repair.untangle(folded, f, patch)
    assert not hit.any() and not repair.FaceIndex(out, f).crossing(f).any()
    held = np.setdiff1d(np.arange(len(v)), free)
    assert np.array_equal(out[held], folded[held])
    # Nothing to untangle: the vertices come back as they were.
    same, none = repair.untangle(v, f, patch)
    assert np.array_equal(same, v) and not none.any()


def _grid(n: int, z: float = 0.0, offset=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """An n x n vertex grid of unit spacing in the plane z, two triangles per square, wound upward."""
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.stack([x.ravel() + offset[0], y.ravel() + offset[1], np.full(n * n, z)], 1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b, c, d = (i * n + j).ravel(), ((i + 1) * n + j).ravel(), ((i + 1) * n + j + 1).ravel(), (i * n + j + 1).ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_stacked_pieces_are_small_pieces_lying_on_a_larger_surface():
    v, f = _grid(12)
    extra = np.array([[3.2, 3.3, 0.1], [4.1, 3.4, -0.1], [3.6, 4.2, 0.05],    # a triangle in the grid's band
                      [3.2, 3.3, 3.0], [4.1, 3.4, 3.0], [3.6, 4.2, 3.0],      # one three edges above it
                      [6.0, 6.0, 0.2]])                                        # apex of a fin on a grid edge
    v = np.concatenate([v, extra])
    n = 144
    near, far = [n, n + 1, n + 2], [n + 3, n + 4, n + 5]
    fin = [5 * 12 + 5, 6 * 12 + 6, n + 6]              # on the diagonal edge of square (5, 5): non-manifold there
    sv, sf = _grid(3, offset=(30.0, 0.0))                # a separate 8-face sheet far away
    v = np.concatenate([v, sv])
    faces = np.concatenate([f, [near, far, fin], sf + len(v) - len(sv)])
    flagged = repair.stacked_pieces(v, faces)
    expect = np.zeros(len(faces), bool)
    expect[len(f)] = expect[len(f) + 2] = True         # the one in the band and the fin (cut off at its edge)
    assert flagged.tolist() == expect.tolist()
    assert not repair.stacked_pieces(v, faces, tol=0).any()
    # A triangle just above another surface given as `others` (e.g. the closed part) lies on it too.
    alone = np.array([near, far])
    assert repair.stacked_pieces(v, alone, others=f).tolist() == [True, False]
    # A triangle in a hole of the grid lies beside its faces, not over them: it covers what they do not.
    centre = 8 * 12 + 8
    holed = f[~(f == centre).any(1)]
    w = np.concatenate([v[:144], [[7.8, 7.8, 0.05], [8.3, 7.9, 0.0], [8.0, 8.3, -0.05]]])
    plug = np.array([[144, 145, 146]])
    assert not repair.stacked_pieces(w, np.concatenate([holed, plug]))[-1]
    # Pieces of one size never absorb each other: two triangles lying on one another both stay.
    w = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.01], [1, 0, 0.01], [0, 1, 0.01]], float)
    assert not repair.stacked_pieces(w, np.array([[0, 1, 2], [3, 4, 5]])).any()


def test_stacked_pieces_keep_a_part_the_input_sampled_a_few_spacings_off():
    """On a coarse mesh (unit edges) a triangle half an edge over a larger surface is within its edge length and
    flagged. With the input's samples (spacing 0.05) the length is at most `STACKED_SPACINGS` of their
    spacings: the triangle the samples cover on its own, 10 spacings off, stays (an eye in its socket), and one
    in the band of the surface is still a stray copy."""
    v, f = _grid(12)
    band = [[3.2, 3.3, 0.02], [4.1, 3.4, -0.02], [3.6, 4.2, 0.01]]
    eye = [[6.2, 6.3, 0.5], [7.1, 6.4, 0.5], [6.6, 7.2, 0.5]]
    v = np.concatenate([v, band, eye])
    faces = np.concatenate([f, [[144, 145, 146], [147, 148, 149]]])
    assert repair.stacked_pieces(v, faces)[-2:].tolist() == [True, True]
    x, y = np.meshgrid(np.arange(0.0, 11.0, 0.05), np.arange(0.0, 11.0, 0.05), indexing="ij")
    plane = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    bary = np.random.default_rng(0).dirichlet(np.ones(3), 400)
    samples = np.concatenate([plane, bary @ np.array(eye)])
    assert repair.sample_spacing(samples) == pytest.approx(0.05)
    assert repair.stacked_pieces(v, faces, samples=samples)[-2:].tolist() == [True, False]


def test_sheet_holes_are_small_inner_holes_not_rims_nor_real_holes():
    v, f = _grid(12)
    centre = 5 * 12 + 5                                  # the six faces around one vertex: a 6-edge hole
    small = (f == centre).any(1)
    big = np.isin(f, [i * 12 + j for i in range(2, 4) for j in range(7, 10)]).any(1)  # a 2 x 3 vertex block
    sheet = f[~small & ~big]
    loops = repair.hole_loops(sheet)
    assert sorted(len(loop) for loop in loops) == [6, 12, 44]  # the small hole, the large one, the rim
    picked = repair.sheet_holes(v, sheet, 8)
    assert [len(loop) for loop in picked] == [6]             # the large hole has more than 8 edges
    assert sorted(len(loop) for loop in repair.sheet_holes(v, sheet, 48)) == [6, 12]  # never the rim
    fill, filled, _, _ = repair.fill_holes(v, sheet, 8, loops=picked)
    assert filled == 1 and len(fill) == 4
    assert sorted(len(loop) for loop in repair.hole_loops(np.concatenate([sheet, fill]))) == [12, 44]
    # A hole as large as its sheet is the shape's own (a washer): its loop is left open.
    around = np.setdiff1d(f[small], [centre])            # the hole's six corners
    ring = sheet[np.isin(sheet, around).any(1)]          # the faces at them: a band one face wide
    assert sorted(len(loop) for loop in repair.hole_loops(ring)) == [6, 12]
    assert repair.sheet_holes(v, ring, 24) == []
    assert [len(loop) for loop in repair.sheet_holes(v, ring, 24, max_share=1.0)] == [6]
    # A hole whose rim has an edge of `avoid` (the closed part) is not the sheet's to fill.
    ring_edge = [picked[0][0], picked[0][1]]
    assert repair.sheet_holes(v, sheet, 8, avoid=np.array([[*ring_edge, 143]])) == []


def test_sampled_loops_tell_a_hole_of_the_input_from_a_gap_in_a_sampled_sheet():
    """`sampled_loops`: samples cover a grid sheet except a disk around one hole; that hole's loop is a
    hole of the input and stays out, the other, whose centre has samples around it, is sampled across. No
    samples (or fewer than two) tell nothing: every loop passes."""
    v, f = _grid(12)
    gap_hole = (f == 5 * 12 + 3).any(1)                  # two 6-edge holes in the sheet
    real_hole = (f == 5 * 12 + 8).any(1)
    sheet = f[~gap_hole & ~real_hole]
    loops = repair.sheet_holes(v, sheet, 8)
    centres = [v[loop].mean(0) for loop in loops]
    rng = np.random.default_rng(0)
    samples = np.c_[rng.uniform(0, 11, (20_000, 2)), np.zeros(20_000)]
    samples = samples[np.linalg.norm(samples - v[5 * 12 + 8], axis=1) > 1.0]  # no samples in the real hole
    sampled = repair.sampled_loops(v, loops, samples, 8.0)
    near_real = [np.linalg.norm(c - v[5 * 12 + 8]) < 0.5 for c in centres]
    assert len(loops) == 2 and list(sampled) == [not r for r in near_real]
    assert repair.sampled_loops(v, loops, samples, 1e6).all()      # a gap that wide counts as sampled
    assert repair.sampled_loops(v, loops, samples[:1], 8.0).all()
    assert repair.sampled_loops(v, [], samples, 8.0).shape == (0,)


def test_sheet_holes_beside_a_stray_vertex_stay_open():
    """A hole whose loop runs through a vertex lifted off the sheet (an outlier the mesh reached) is not
    filled: its fill would be a tent up to the stray. Lifted less than `STRAY_OFF` of its neighbours' spacing,
    or on a sheet bent too sharply to count as a surface there, the hole is filled as before."""
    v, f = _grid(12)
    centre = 5 * 12 + 5
    sheet = f[~(f == centre).any(1)]                      # the 6-edge hole around vertex 65
    corner = int(np.setdiff1d(f[(f == centre).any(1)], [centre])[0])
    assert [len(loop) for loop in repair.sheet_holes(v, sheet, 8)] == [6]
    spacing = 1.4                                        # about the mean distance to a grid vertex's 16 nearest
    for lift, expected in ((0.2 * spacing, [6]), (0.6 * spacing, []), (1.5, [])):
        w = v.copy()
        w[corner, 2] = lift
        assert [len(loop) for loop in repair.sheet_holes(w, sheet, 8)] == expected, lift
    w = v.copy()
    w[corner, 2] = 1.5
    assert [len(loop) for loop in repair.sheet_holes(w, sheet, 8, stray_off=np.inf)] == [6]
    folded = v.copy()
    folded[:, 2] = 0.8 * np.abs(folded[:, 0] - 5)        # a crease through the hole: no plane fits there
    folded[corner, 2] += 0.6 * spacing
    assert [len(loop) for loop in repair.sheet_holes(folded, sheet, 8)] == [6]


def test_floating_crumbs_are_small_pieces_far_from_every_larger_one(monkeypatch):
    """Beside a real sheet, a crumb within an edge or two of it stays (a thin part that did not join up); one
    several edge lengths from every larger piece and from `others`, off the plane of the surface nearest it, is a
    triangle among stray points; one as far but in that plane is a fragment of the surface (a scanner's sparse
    stretch) and stays."""
    v, f = _grid(12)                                      # unit edges; median edge length 1
    tri = np.array([[0.0, 0.0, 0.0], [0.8, 0.0, 0.0], [0.0, 0.8, 0.0]])
    near = tri + [12.0, 5.0, 0.0]                         # 1 unit past the grid's rim
    far = tri + [5.0, 5.0, 9.0]                           # 9 units above it
    by_others = tri + [30.0, 0.0, 3.0]                    # far from the grid and off its plane, beside `others`
    in_plane = tri + [20.0, 5.0, 0.0]                     # 9 units past the rim, in the grid's plane
    tilted = in_plane + [0.0, 0.0, 2.0]                   # as far, 2 units off that plane
    w = np.concatenate([v, near, far, by_others, in_plane, tilted, by_others[:1] + [0.0, 0.0, 1.0]])
    n = len(v)
    faces = np.concatenate([f, n + np.arange(15).reshape(5, 3)])
    others = np.array([[n + 15, n + 15, n + 15]])
    flag = repair.floating_crumbs(w, faces, 4, others)
    assert not flag[: len(f)].any()
    assert flag[len(f):].tolist() == [False, True, False, False, True]
    assert repair.floating_crumbs(w, faces, 4).tolist()[len(f):] == [False, True, True, False, True]
    monkeypatch.setattr(repair, "FLOATING_BESIDE", -1.0)  # no crumb counts as beside: the fragment goes too
    assert repair.floating_crumbs(w, faces, 4).tolist()[len(f):] == [False, True, True, True, True]
    assert not repair.floating_crumbs(w, faces, 4, gap=20.0).any()
    assert not repair.floating_crumbs(w, faces[len(f):], 4).any()  # only crumbs: `crumbs` decides


def test_larger_pieces_float_apart_when_farther_than_their_extent(monkeypatch):
    """Stray points far off a surface join into pieces of a few long faces: one farther from every larger piece
    than its own extent goes, and the crumb beside it with it (pieces are decided largest first); a piece as
    far but larger than its distance (a fragment of a sparsely seen stretch) stays."""
    v, f = _grid(12)                                      # unit edges, 242 faces
    s, sf = _grid(3)                                      # 8 faces, bounding-box diagonal 2.8
    tri = np.array([[0.0, 0.0, 0.0], [0.8, 0.0, 0.0], [0.0, 0.8, 0.0]])
    parts = [(v, f), (s + [4.0, 4.0, 9.0], sf), (s * 4.0 + [0.0, 0.0, -9.0], sf),
             (tri + [7.0, 4.0, 9.0], np.array([[0, 1, 2]]))]  # 9 above the grid, 1 beside the small piece
    w = np.concatenate([p for p, _ in parts])
    start = np.cumsum([0] + [len(p) for p, _ in parts])
    faces = np.concatenate([q + o for (_, q), o in zip(parts, start)])
    piece = np.repeat(np.arange(4), [len(q) for _, q in parts])
    flag = repair.floating_crumbs(w, faces, 4)
    assert [bool(flag[piece == i].all()) for i in range(4)] == [False, True, False, True]
    assert all(flag[piece == i].all() or not flag[piece == i].any() for i in range(4))
    monkeypatch.setattr(repair, "FLOATING_MAX_FACES", 0)   # crumbs only: the small piece anchors the crumb
    assert not repair.floating_crumbs(w, faces, 4).any()
