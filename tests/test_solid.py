"""Tet labellings and their boundary (`dmesh.solid`): closed and outward, recovered by walks, pinches repaired.

References are independent of the code under test: a tet labelling built by hand (the mesh volume must
equal the labelled tets' volume; the boundary of a tet set is exact).
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dmesh import solid
from dmesh.surface import topology
from common import ball_labels, check_closed, cloud_diagram, cycle


def test_boundary_of_a_hand_built_labelling_is_closed_and_outward():
    pd = cloud_diagram()
    inside = ball_labels(pd)
    ids = np.flatnonzero(solid.boundary_mask(pd, inside))
    faces = solid.oriented_boundary(pd, inside, ids)
    mesh = check_closed(faces, pd.points)
    # Outward: the enclosed volume is the labelled tets' volume (positive); the complement's boundary is the
    # same faces wound inward.
    expected = solid.tet_volumes(pd.points, pd.tets)[inside].sum()
    assert mesh.volume == pytest.approx(expected, rel=1e-9)
    inverted = solid.oriented_boundary(pd, ~inside, ids)
    assert trimesh.Trimesh(pd.points, inverted, process=False).volume == pytest.approx(-expected, rel=1e-9)


def test_walks_recover_the_labelling_from_its_boundary_alone():
    pd = cloud_diagram(seed=1)
    inside = ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    dirs = solid.directions(5)
    # The boundary of any tet set is crossed an odd number of times exactly on the way out of the set.
    assert np.array_equal(solid.walk_votes(pd, walls, dirs) > 0.5, inside)
    # Winding: walls signed by outward normals, or all inward (the absolute value is used).
    ids = np.flatnonzero(walls)
    faces = solid.oriented_boundary(pd, inside, ids)
    sign = np.zeros(len(pd.faces))  # +1 where the outward winding is the sorted triple's (up to rotation)
    sign[ids] = np.where([cycle(f) == tuple(s) for f, s in zip(faces.tolist(), pd.faces[ids].tolist())], 1.0, -1.0)
    assert np.array_equal(solid.walk_votes(pd, walls, dirs, sign) > 0.5, inside)
    assert np.array_equal(solid.walk_votes(pd, walls, dirs, -sign) > 0.5, inside)


@pytest.mark.parametrize("shared", [2, 1], ids=["edge", "vertex"])
def test_pinched_tets_are_separated(shared):
    """Two tets that touch only at an edge (or a vertex): their boundary is pinched there until repaired."""
    pd = cloud_diagram(n=300, seed=3)
    tets = pd.tets.astype(np.int64)
    a = int(np.argmax(solid.tet_volumes(pd.points, pd.tets)))
    common = np.array([len(np.intersect1d(tets[a], t)) for t in tets])
    b = int(np.flatnonzero(common == shared)[0])
    inside = np.zeros(len(tets), bool)
    inside[[a, b]] = True
    faces = pd.faces[solid.boundary_mask(pd, inside)].astype(np.int64)
    assert len(topology.nonmanifold_vertices(faces)) > 0
    fixed, flipped = solid.repair_pinches(pd, inside)
    assert flipped > 0
    check_closed(solid.oriented_boundary(pd, fixed, np.flatnonzero(solid.boundary_mask(pd, fixed))), pd.points)


def test_large_lids_are_the_pieces_whose_rim_is_longer_than_a_fillable_hole():
    """Of a closed boundary cut into walls and lids, the lid pieces kept are those with more than `min_rim`
    rim edges (counted against an independent count: the boundary edges of the walls around each piece)."""
    pd = cloud_diagram(n=1500, seed=3)
    inside = ball_labels(pd)
    faces = solid.oriented_boundary(pd, inside, np.flatnonzero(solid.boundary_mask(pd, inside)))
    centre = pd.points[faces].mean(1)
    cap = centre[:, 2] > 0.3  # a large cap
    one = np.flatnonzero((centre[:, 2] < -0.2) & (np.abs(centre[:, 0]) < 0.15))[:1]  # one face, far from it
    lid = cap.copy()
    lid[one] = True
    walls, lids = faces[~lid], faces[lid]
    cap_rim = topology.boundary_edge_count(faces[cap])
    assert cap_rim > 3 and len(one) == 1
    keep = solid.large_lids(walls, lids, min_rim=3)
    assert np.array_equal(keep, cap[lid])  # the cap (rim > 3) but not the single face (rim 3)
    assert not solid.large_lids(walls, lids, min_rim=cap_rim).any()
    assert solid.large_lids(walls, lids, min_rim=cap_rim - 1).sum() == cap.sum()
