"""Output surfaces: oriented (outward on closed parts), watertight and 2-manifold where the input is closed.

References are independent of the code under test: a tet labelling built by hand (the mesh volume must
equal the labelled tets' volume; the boundary of a tet set is exact), meshes with known volume, and the
GT's own face normals at the closest point.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datasets.normalize import normalize
from datasets.sampling import sample_points
from datasets.synthetic import generate
from dmesh import repair, solid
from dmesh.extract import SurfaceConfig, surface, surface_of_mesh
from dmesh.recon.mesh_to_dmesh import _orient
from dmesh.recon.pointcloud import PointCloudConfig, reconstruct
from dmesh.wdt import PowerDiagram


def _cloud_diagram(n: int = 500, seed: int = 0) -> PowerDiagram:
    rng = np.random.default_rng(seed)
    return PowerDiagram.from_points(rng.uniform(-1, 1, (n, 3)), None)


def _ball_labels(pd: PowerDiagram, radius: float = 0.6) -> np.ndarray:
    """Tets whose centroid lies in the ball, made pinch-free (so their boundary is a closed 2-manifold)."""
    inside = np.linalg.norm(pd.points[pd.tets.astype(np.int64)].mean(1), axis=1) < radius
    return solid.repair_pinches(pd, inside)[0]


def _oriented_fraction(mesh: trimesh.Trimesh, gt: trimesh.Trimesh) -> float:
    """Area fraction of `mesh` whose normal agrees with the normal of the GT face closest to its centroid."""
    _, _, tri = trimesh.proximity.closest_point(gt, mesh.triangles_center)
    agree = np.einsum("ij,ij->i", mesh.face_normals, gt.face_normals[tri]) > 0
    return float((mesh.area_faces * agree).sum() / mesh.area_faces.sum())


def _cycle(face) -> tuple:
    """A face's vertex cycle, rotated to start at its smallest id (equal for equal windings)."""
    k = int(np.argmin(face))
    return tuple(face[k:]) + tuple(face[:k])


def _check_closed(faces: np.ndarray, points: np.ndarray) -> trimesh.Trimesh:
    mesh = trimesh.Trimesh(points, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert len(repair.nonmanifold_edges(faces)) == 0 and len(repair.nonmanifold_vertices(faces)) == 0
    return mesh


# ------------------------------------------------------------------------------------------ tet labelling

def test_boundary_of_a_hand_built_labelling_is_closed_and_outward():
    pd = _cloud_diagram()
    inside = _ball_labels(pd)
    ids = np.flatnonzero(solid.boundary_mask(pd, inside))
    faces = solid.oriented_boundary(pd, inside, ids)
    mesh = _check_closed(faces, pd.points)
    # Outward: the enclosed volume is the labelled tets' volume (positive); the complement's boundary is the
    # same faces wound inward.
    expected = solid.tet_volumes(pd.points, pd.tets)[inside].sum()
    assert mesh.volume == pytest.approx(expected, rel=1e-9)
    inverted = solid.oriented_boundary(pd, ~inside, ids)
    assert trimesh.Trimesh(pd.points, inverted, process=False).volume == pytest.approx(-expected, rel=1e-9)


def test_walks_recover_the_labelling_from_its_boundary_alone():
    pd = _cloud_diagram(seed=1)
    inside = _ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    dirs = solid.directions(5)
    # The boundary of any tet set is crossed an odd number of times exactly on the way out of the set.
    assert np.array_equal(solid.walk_votes(pd, walls, dirs) > 0.5, inside)
    # Winding: walls signed by outward normals, or all inward (the absolute value is used).
    ids = np.flatnonzero(walls)
    faces = solid.oriented_boundary(pd, inside, ids)
    sign = np.zeros(len(pd.faces))  # +1 where the outward winding is the sorted triple's (up to rotation)
    sign[ids] = np.where([_cycle(f) == tuple(s) for f, s in zip(faces.tolist(), pd.faces[ids].tolist())], 1.0, -1.0)
    assert np.array_equal(solid.walk_votes(pd, walls, dirs, sign) > 0.5, inside)
    assert np.array_equal(solid.walk_votes(pd, walls, dirs, -sign) > 0.5, inside)


def test_surface_closes_a_holed_boundary_and_drops_a_fin():
    pd = _cloud_diagram(seed=2)
    inside = _ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    truth = solid.oriented_boundary(pd, inside, np.flatnonzero(walls))
    holed = walls.copy()
    holed[np.flatnonzero(walls)[0]] = False  # a one-triangle hole
    # A fin: a face outside the ball that shares an edge with the surface.
    edges = {tuple(e) for e in np.sort(repair.edge_table(truth)[0], axis=1).tolist()}
    fin = next(i for i in np.flatnonzero(~walls)
               if any(tuple(sorted(e)) in edges for e in np.sort(repair.edge_table(pd.faces[i:i + 1])[0], 1).tolist()))
    holed[fin] = True
    out = surface(pd, holed, config=SurfaceConfig(directions=9))
    assert out.info["holes_filled"] == 1 and out.info["fins_dropped"] == 1 and out.info["sheet_faces"] == 0
    _check_closed(out.faces, pd.points)
    # The filled surface is the original one, wound the same way.
    assert {_cycle(f) for f in out.faces.tolist()} == {_cycle(f) for f in truth.tolist()}


@pytest.mark.parametrize("shared", [2, 1], ids=["edge", "vertex"])
def test_pinched_tets_are_separated(shared):
    """Two tets that touch only at an edge (or a vertex): their boundary is pinched there until repaired."""
    pd = _cloud_diagram(n=300, seed=3)
    tets = pd.tets.astype(np.int64)
    a = int(np.argmax(solid.tet_volumes(pd.points, pd.tets)))
    common = np.array([len(np.intersect1d(tets[a], t)) for t in tets])
    b = int(np.flatnonzero(common == shared)[0])
    inside = np.zeros(len(tets), bool)
    inside[[a, b]] = True
    faces = pd.faces[solid.boundary_mask(pd, inside)].astype(np.int64)
    assert len(repair.nonmanifold_vertices(faces)) > 0
    fixed, flipped = solid.repair_pinches(pd, inside)
    assert flipped > 0
    _check_closed(solid.oriented_boundary(pd, fixed, np.flatnonzero(solid.boundary_mask(pd, fixed))), pd.points)


def test_surface_of_a_renumbered_mesh_and_a_foreign_one():
    pd = _cloud_diagram(seed=4)
    inside = _ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    mesh = trimesh.Trimesh(pd.points, pd.faces[walls], process=False)
    mesh.remove_unreferenced_vertices()
    out = surface_of_mesh(mesh, pd)
    closed = _check_closed(np.asarray(out.faces), np.asarray(out.vertices))
    assert closed.volume == pytest.approx(solid.tet_volumes(pd.points, pd.tets)[inside].sum(), rel=1e-9)
    mesh.vertices[0] += 0.01
    with pytest.raises(ValueError, match="not points of the triangulation"):
        surface_of_mesh(mesh, pd)


# ------------------------------------------------------------------------------------------ face repairs

def test_fill_holes_restores_a_box():
    box = trimesh.creation.box()
    for drop in ([0], [0, 1]):  # a triangle hole and a square one
        keep = np.setdiff1d(np.arange(len(box.faces)), drop)
        fill, filled, left = repair.fill_holes(box.vertices, box.faces[keep], max_edges=8)
        assert (filled, left) == (1, 0)
        mesh = _check_closed(np.concatenate([box.faces[keep], fill]), box.vertices)
        assert mesh.volume == pytest.approx(1.0)
    # Too large a hole stays open.
    assert repair.fill_holes(box.vertices, box.faces[2:], max_edges=3)[1:] == (0, 1)


def test_hole_loops_split_at_a_shared_vertex():
    bowtie = np.array([[0, 1, 2], [0, 3, 4]])  # two triangles that share vertex 0 only
    loops = repair.hole_loops(bowtie)
    assert sorted(sorted(loop) for loop in loops) == [[0, 1, 2], [0, 3, 4]]
    assert {_cycle(loop) for loop in loops} == {(0, 2, 1), (0, 4, 3)}  # against the faces' winding
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


# ------------------------------------------------------------------------------------------ reconstructions

def _tiny_cloud(name: str, normals: bool):
    gt = normalize(generate(name))[0]
    pts, nrm = sample_points(gt, 3000, 0)
    # No optimisation step: the output is the extraction of the initial DMesh (what this file tests).
    res = reconstruct(pts, nrm if normals else None, PointCloudConfig.tiny(steps_phase1=0, steps_phase2=0))
    return gt, res


@pytest.mark.parametrize("name", ["sphere", "torus"])
def test_closed_clouds_give_watertight_outward_meshes(name):
    gt, res = _tiny_cloud(name, normals=False)
    _check_closed(np.asarray(res.mesh.faces), np.asarray(res.mesh.vertices))
    assert res.mesh.volume > 0 and _oriented_fraction(res.mesh, gt) >= 0.99
    assert res.info["surface"]["vote"] == "parity"


@pytest.mark.parametrize("name", ["disc", "bowl"])
def test_open_clouds_face_their_normals(name):
    gt, res = _tiny_cloud(name, normals=True)
    faces = np.asarray(res.mesh.faces)
    assert len(repair.nonmanifold_edges(faces)) == 0 and res.mesh.is_winding_consistent
    assert _oriented_fraction(res.mesh, gt) >= 0.99
    # Without normals the side of an open sheet is unknown, but the winding is still consistent.
    _, bare = _tiny_cloud(name, normals=False)
    assert bare.mesh.is_winding_consistent and len(repair.nonmanifold_edges(np.asarray(bare.mesh.faces))) == 0


def test_mesh_to_dmesh_output_is_wound_outward_even_for_an_inside_out_input():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    v = sphere.vertices * 0.8
    sorted_faces = np.sort(sphere.faces, axis=1)  # what the WDT gives
    for given in (sphere.faces, sphere.faces[:, ::-1]):  # outward and inside-out input windings
        out = _orient(v, np.ones(len(v)), sorted_faces, v, given)
        mesh = _check_closed(out, v)
        assert mesh.volume > 0
    # An open cap keeps the input's winding, whichever it is.
    cap = sphere.faces[sphere.triangles_center[:, 2] > 0.3]
    for given in (cap, cap[:, ::-1]):
        out = _orient(v, np.ones(len(v)), np.sort(given, axis=1), v, given)
        assert {_cycle(f) for f in out.tolist()} == {_cycle(f) for f in given.tolist()}
