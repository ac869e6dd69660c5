"""The surface step's combinatorics (`dmesh.surface.topology`) and winding (`dmesh.surface.winding`): rim edges,
hole loops, fans split at shared vertices and edges and their copies moved apart, sheets wound and turned."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datasets.synthetic import generate
from dmesh.surface import finish, topology, winding
from common import cycle


def test_rim_edges_count_each_face_of_an_edge_shared_by_more_than_two():
    """`rim_edge_count`: a closed tetrahedron has none; two triangles on an edge have their 4 outer edges;
    three triangles on one edge have 6 outer edges plus 3 for the shared one (split apart, each face keeps a
    rim there), where `boundary_edge_count` sees only the 6."""
    tet = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]])
    pair = np.array([[0, 1, 2], [1, 0, 3]])
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    assert [topology.rim_edge_count(f) for f in (tet, pair, fan)] == [0, 4, 9]
    assert topology.boundary_edge_count(fan) == 6


def test_hole_loops_split_at_a_shared_vertex():
    bowtie = np.array([[0, 1, 2], [0, 3, 4]])  # two triangles that share vertex 0 only
    loops = topology.hole_loops(bowtie)
    assert sorted(sorted(loop) for loop in loops) == [[0, 1, 2], [0, 3, 4]]
    assert {cycle(loop) for loop in loops} == {(0, 2, 1), (0, 4, 3)}  # against the faces' winding
    assert topology.nonmanifold_vertices(bowtie).tolist() == [0]


def test_sheets_meeting_at_an_edge_are_split_and_folds_dropped():
    box = trimesh.creation.box()
    e = box.edges_unique[0]
    v = np.vstack([box.vertices, box.vertices[e].mean(0) + [0, 0, 3.0]])
    faces = np.concatenate([box.faces, [[e[0], e[1], len(box.vertices)]]])  # a fin on a box edge
    split, source = topology.split_at_fans(faces)
    assert len(topology.nonmanifold_edges(split)) == 0 and len(topology.nonmanifold_vertices(split)) == 0
    assert len(source) == len(v) + 2 and np.array_equal(v[source][split], v[faces])  # nothing moved
    assert np.array_equal(source[:len(v)], np.arange(len(v)))
    # Three faces around one edge that are joined around both its ends cannot be split: the smallest goes.
    fold = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [2, 4, 0], [3, 2, 1]])
    pts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0.2, 0.1]], float)
    keep = finish.drop_crowding(pts, fold)
    assert keep.sum() == 4 and not keep[2]


def test_split_copies_move_apart_into_their_own_faces():
    from datasets.meshes import merge_vertices

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0.5]], float)
    bowtie = np.array([[0, 1, 2], [0, 3, 4]])                     # two triangles that share vertex 0 only
    faces, source = topology.split_at_fans(bowtie, len(v))
    at = v[source]
    moved = finish.separate_copies(at, faces, source, ratio=0.1)
    copies = np.flatnonzero(source == 0)
    assert len(copies) == 2
    for c in copies:                                              # 10 % of the way to its own face's centroid
        centroid = at[faces[(faces == c).any(1)][0]].mean(0)
        np.testing.assert_allclose(moved[c], 0.9 * at[c] + 0.1 * centroid)
    rest = np.setdiff1d(np.arange(len(source)), copies)
    assert np.array_equal(moved[rest], at[rest])
    # Merged by position (a file read back), the copies on one point make the pinch again; moved, they do not.
    assert len(topology.nonmanifold_vertices(merge_vertices(at, faces)[1])) == 1
    assert len(topology.nonmanifold_vertices(merge_vertices(moved, faces)[1])) == 0
    assert np.array_equal(finish.separate_copies(v, bowtie, np.arange(len(v))), v)  # no copies: nothing moves
    with pytest.raises(ValueError, match="ratio"):
        finish.separate_copies(at, faces, source, ratio=1.0)


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
        out = winding.orient_sheets(v, f, (centres, towards), turn_faces=turn_faces)
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
    flip, comp, n = topology.winding_components(scrambled)
    assert n == 1 and topology.seam_components(np.where(flip[:, None], scrambled[:, ::-1], scrambled), comp, n)[0]
    out = winding.orient_sheets(v, scrambled, (v[f].mean(1), normals), k=1)
    agree = np.einsum("ij,ij->i", trimesh.Trimesh(v, out, process=False).face_normals, normals)
    assert (agree > 0).all()
    whole = winding.orient_sheets(v, scrambled, (v[f].mean(1), normals), k=1, turn_faces=False)
    assert (np.einsum("ij,ij->i", trimesh.Trimesh(v, whole, process=False).face_normals, normals) < 0).any()


def test_sheet_winding_follows_the_normals_or_the_volume():
    box = trimesh.creation.box()
    scrambled = box.faces.copy()
    scrambled[::2] = scrambled[::2, ::-1]
    out = winding.orient_sheets(box.vertices, scrambled)
    assert trimesh.Trimesh(box.vertices, out, process=False).volume == pytest.approx(1.0)
    centres, normals = box.triangles_center, box.face_normals
    inward = winding.orient_sheets(box.vertices, scrambled, (centres, -normals))
    assert trimesh.Trimesh(box.vertices, inward, process=False).volume == pytest.approx(-1.0)
    # Faces without a shared edge: each is its own component and faces its normal.
    lone = winding.orient_sheets(box.vertices, scrambled[[0, 5]], (centres[[0, 5]], normals[[0, 5]]))
    assert (np.einsum("ij,ij->i", trimesh.Trimesh(box.vertices, lone, process=False).face_normals,
                      normals[[0, 5]]) > 0).all()
    # A Mobius strip cannot be wound consistently: one seam is left, nothing fails.
    strip = generate("mobius")
    flip, comp, n = topology.winding_components(np.asarray(strip.faces))
    assert n == 1 and 0 < flip.sum() < len(strip.faces)


def test_orientation_is_consistent():
    import trimesh

    box = trimesh.creation.box()
    faces = box.faces.copy()
    faces[::2] = faces[::2, ::-1]                       # scramble the winding of every other face
    mesh = trimesh.Trimesh(box.vertices, faces, process=False)
    winding.orient_faces(mesh)
    assert mesh.is_winding_consistent and mesh.volume > 0
