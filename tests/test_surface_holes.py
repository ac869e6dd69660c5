"""The surface step's hole fills and crossing tests (`dmesh.surface.holes`, `dmesh.surface.crossings`): least-area
fills that cross nothing, the sheets' inner holes, CGAL's refine and fair, folds smoothed out of a patch."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dmesh.surface import crossings, holes, topology
from dmesh.surface.evidence import Evidence
from common import check_closed, cycle, grid_sheet


def test_fill_holes_restores_a_box():
    box = trimesh.creation.box()
    for drop in ([0], [0, 1]):  # a triangle hole and a square one
        keep = np.setdiff1d(np.arange(len(box.faces)), drop)
        fill, filled, left, crossing = holes.fill_holes(box.vertices, box.faces[keep], max_edges=8)
        assert (filled, left, crossing) == (1, 0, 0)
        mesh = check_closed(np.concatenate([box.faces[keep], fill]), box.vertices)
        assert mesh.volume == pytest.approx(1.0)
    # Too large a hole stays open.
    assert holes.fill_holes(box.vertices, box.faces[2:], max_edges=3)[1:] == (0, 1, 0)


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
    fill, filled, left, crossing = holes.fill_holes(v, faces, max_edges=8)
    assert (len(fill), filled, left, crossing) == (0, 0, 1, 1)
    fill, filled, left, crossing = holes.fill_holes(v, faces, max_edges=8, uncrossed=False)
    assert (len(fill), filled, left, crossing) == (2, 1, 0, 0)
    assert crossings.crossing_triangles(v, fill, faces).all()
    # Faces that bound no hole but must not be crossed either (the sheets beside a closed part).
    assert holes.fill_holes(v, box.faces[keep], max_edges=8, others=tet)[1:] == (0, 1, 1)
    assert holes.fill_holes(v, box.faces[keep], max_edges=8)[1:] == (1, 0, 0)


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
    first = holes.fill_holes(v, box.faces[keep], max_edges=8)[0]
    assert crossings.crossing_triangles(v, first, tet).any()
    fill, filled, left, crossing = holes.fill_holes(v, box.faces[keep], max_edges=8, others=tet)
    assert (len(fill), filled, left, crossing) == (2, 1, 0, 0)
    assert not crossings.crossing_triangles(v, fill, tet).any()
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
    assert crossings.crossing_triangles(v, tris, faces).tolist() == [True, False]
    assert crossings.crossing_triangles(v, tris, faces[1:]).tolist() == [False, False]


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
    ours = crossings.triangles_cross(v, s, t)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=np.concatenate([s, t]).astype(np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    picked = ms.current_mesh().face_selection_array()
    assert 20 < ours[:shared].sum() and 20 < ours[shared:].sum()  # both kinds cross often enough to test
    assert np.array_equal(ours, picked[:pairs] & picked[pairs:])
    assert np.array_equal(picked[:pairs], picked[pairs:])
    # The batch version over a whole face list agrees, and a triangle never crosses itself or a neighbour.
    assert np.array_equal(crossings.crossing_triangles(v, s, np.concatenate([s, t])), ours)


def test_a_long_planar_hole_gets_its_polygon_area():
    """The fill of a flat convex 400-edge loop is a triangulation of it: n - 2 distinct triangles whose areas
    add up to the polygon's (shoelace) area. (Every triangulation of a convex polygon has that area, so this
    checks validity, not minimality.)"""
    n = 400
    angle = np.sort(np.random.default_rng(0).uniform(0, 2 * np.pi, n))
    v = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)
    tris = holes.fill_loop(list(range(n)), v, set())
    assert tris.shape == (n - 2, 3) and len(np.unique(np.sort(tris, axis=1), axis=0)) == n - 2
    shoelace = 0.5 * abs(np.dot(v[:, 0], np.roll(v[:, 1], -1)) - np.dot(v[:, 1], np.roll(v[:, 0], -1)))
    area = 0.5 * np.linalg.norm(np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]]), axis=1)
    assert area.sum() == pytest.approx(shoelace, rel=1e-9)


def test_sheet_holes_are_small_inner_holes_not_rims_nor_real_holes():
    v, f = grid_sheet(12)
    centre = 5 * 12 + 5                                  # the six faces around one vertex: a 6-edge hole
    small = (f == centre).any(1)
    big = np.isin(f, [i * 12 + j for i in range(2, 4) for j in range(7, 10)]).any(1)  # a 2 x 3 vertex block
    sheet = f[~small & ~big]
    loops = topology.hole_loops(sheet)
    assert sorted(len(loop) for loop in loops) == [6, 12, 44]  # the small hole, the large one, the rim
    picked = holes.sheet_hole_loops(v, sheet, 8)
    assert [len(loop) for loop in picked] == [6]             # the large hole has more than 8 edges
    assert sorted(len(loop) for loop in holes.sheet_hole_loops(v, sheet, 48)) == [6, 12]  # never the rim
    fill, filled, _, _ = holes.fill_holes(v, sheet, 8, loops=picked)
    assert filled == 1 and len(fill) == 4
    assert sorted(len(loop) for loop in topology.hole_loops(np.concatenate([sheet, fill]))) == [12, 44]
    # A hole as large as its sheet is the shape's own (a washer): its loop is left open.
    around = np.setdiff1d(f[small], [centre])            # the hole's six corners
    ring = sheet[np.isin(sheet, around).any(1)]          # the faces at them: a band one face wide
    assert sorted(len(loop) for loop in topology.hole_loops(ring)) == [6, 12]
    assert holes.sheet_hole_loops(v, ring, 24) == []
    assert [len(loop) for loop in holes.sheet_hole_loops(v, ring, 24, max_share=1.0)] == [6]
    # A hole whose rim has an edge of `avoid` (the closed part) is not the sheet's to fill.
    ring_edge = [picked[0][0], picked[0][1]]
    assert holes.sheet_hole_loops(v, sheet, 8, avoid=np.array([[*ring_edge, 143]])) == []


def test_sampled_loops_tell_a_hole_of_the_input_from_a_gap_in_a_sampled_sheet():
    """`sampled_loops`: samples cover a grid sheet except a disk around one hole; that hole's loop is a
    hole of the input and stays out, the other, whose centre has samples around it, is sampled across. No
    samples (or fewer than two) tell nothing: every loop passes."""
    v, f = grid_sheet(12)
    gap_hole = (f == 5 * 12 + 3).any(1)                  # two 6-edge holes in the sheet
    real_hole = (f == 5 * 12 + 8).any(1)
    sheet = f[~gap_hole & ~real_hole]
    loops = holes.sheet_hole_loops(v, sheet, 8)
    centres = [v[loop].mean(0) for loop in loops]
    rng = np.random.default_rng(0)
    samples = np.c_[rng.uniform(0, 11, (20_000, 2)), np.zeros(20_000)]
    samples = samples[np.linalg.norm(samples - v[5 * 12 + 8], axis=1) > 1.0]  # no samples in the real hole
    evidence = Evidence.of_samples(samples, 8)
    sampled = holes.sampled_loops(v, loops, evidence, 8.0)
    near_real = [np.linalg.norm(c - v[5 * 12 + 8]) < 0.5 for c in centres]
    assert len(loops) == 2 and list(sampled) == [not r for r in near_real]
    assert holes.sampled_loops(v, loops, evidence, 1e6).all()      # a gap that wide counts as sampled
    assert holes.sampled_loops(v, loops, Evidence.of_samples(samples[:1], 8), 8.0).all()
    assert holes.sampled_loops(v, [], evidence, 8.0).shape == (0,)


def test_sheet_holes_beside_a_stray_vertex_stay_open():
    """A hole whose loop runs through a vertex lifted off the sheet (an outlier the mesh reached) is not
    filled: its fill would be a tent up to the stray. Lifted less than `SheetHoles.stray_off` (0.3) of its
    neighbours' spacing, or on a sheet bent too sharply to count as a surface there, the hole is filled as before."""
    v, f = grid_sheet(12)
    centre = 5 * 12 + 5
    sheet = f[~(f == centre).any(1)]                      # the 6-edge hole around vertex 65
    corner = int(np.setdiff1d(f[(f == centre).any(1)], [centre])[0])
    assert [len(loop) for loop in holes.sheet_hole_loops(v, sheet, 8)] == [6]
    spacing = 1.4                                        # about the mean distance to a grid vertex's 16 nearest
    for lift, expected in ((0.2 * spacing, [6]), (0.6 * spacing, []), (1.5, [])):
        w = v.copy()
        w[corner, 2] = lift
        assert [len(loop) for loop in holes.sheet_hole_loops(w, sheet, 8)] == expected, lift
    w = v.copy()
    w[corner, 2] = 1.5
    assert [len(loop) for loop in holes.sheet_hole_loops(w, sheet, 8, stray_off=np.inf)] == [6]
    folded = v.copy()
    folded[:, 2] = 0.8 * np.abs(folded[:, 0] - 5)        # a crease through the hole: no plane fits there
    folded[corner, 2] += 0.6 * spacing
    assert [len(loop) for loop in holes.sheet_hole_loops(folded, sheet, 8)] == [6]


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
    assert crossings.FaceIndex(folded, f).crossing(f[patch]).any()
    out, hit = crossings.untangle(folded, f, patch)
    assert not hit.any() and not crossings.FaceIndex(out, f).crossing(f).any()
    held = np.setdiff1d(np.arange(len(v)), free)
    assert np.array_equal(out[held], folded[held])
    # Nothing to untangle: the vertices come back as they were.
    same, none = crossings.untangle(v, f, patch)
    assert np.array_equal(same, v) and not none.any()
