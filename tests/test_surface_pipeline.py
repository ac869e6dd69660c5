"""The surface step as a whole (`dmesh.surface.run`, `surface_mesh`): holes closed by fills and lids, fins and stray
triangles dropped, a sheet over a solid set aside, spans faired, branches split and their copies moved apart."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dmesh import solid, wdt
from dmesh.surface import SurfaceConfig, run, surface_mesh, surface_of_wdt_mesh
from dmesh.surface.crossings import FaceIndex
from dmesh.surface.topology import boundary_edge_count, edge_table, nonmanifold_edges, nonmanifold_vertices
from common import ball_labels, check_closed, cloud_diagram, cycle

#: The stages up to the geometry: `run`'s faces still index the triangulation's points (no copy moved, no lid
#: refined), so they compare with its own faces.
TOPOLOGY = ("copies", "fair")


def _config(**overrides) -> SurfaceConfig:
    """`SurfaceConfig` with dotted overrides ("lids.max_hole": 8 as lids__max_hole=8) and the geometry skipped."""
    skip = overrides.pop("skip", TOPOLOGY)
    return SurfaceConfig(skip=skip).with_overrides({k.replace("__", "."): v for k, v in overrides.items()})


def test_surface_closes_a_holed_boundary_and_drops_a_fin():
    pd = cloud_diagram(seed=2)
    inside = ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    truth = solid.oriented_boundary(pd, inside, np.flatnonzero(walls))
    holed = walls.copy()
    holed[np.flatnonzero(walls)[0]] = False  # a one-triangle hole
    # A fin: a face outside the ball that shares an edge with the surface.
    edges = {tuple(e) for e in np.sort(edge_table(truth)[0], axis=1).tolist()}
    fin = next(i for i in np.flatnonzero(~walls)
               if any(tuple(sorted(e)) in edges for e in np.sort(edge_table(pd.faces[i:i + 1])[0], 1).tolist()))
    holed[fin] = True
    out = run(pd, holed, config=_config(vote__directions=9))
    assert out.info["holes_filled"] == 1 and out.info["fins_dropped"] == 1 and out.info["sheet_faces"] == 0
    check_closed(out.faces, pd.points)
    # The filled surface is the original one, wound the same way.
    assert {cycle(f) for f in out.faces.tolist()} == {cycle(f) for f in truth.tolist()}


@pytest.mark.parametrize("holed", [False, True], ids=["closed", "holed"])
def test_a_sheet_over_a_solid_does_not_hollow_it(holed):
    """A ball under a wide cap (a mushroom's stalk under its cap): walks from the ball that pass through the
    cap cross two walls, so the first vote calls the whole ball outside; with the cap set aside the second
    vote recovers it exactly (and, with a one-triangle hole in the ball, fills that hole)."""
    pd = cloud_diagram(n=4000, seed=5)
    centroid = pd.points[pd.tets.astype(np.int64)].mean(1)
    ball = solid.repair_pinches(pd, np.linalg.norm(centroid - [0.0, -0.2, 0.0], axis=1) < 0.35)[0]
    big = solid.repair_pinches(pd, np.linalg.norm(centroid, axis=1) < 0.85)[0]
    cap = solid.boundary_mask(pd, big) & (pd.points[pd.faces.astype(np.int64)].mean(1)[:, 1] > 0.0)
    truth = solid.boundary_mask(pd, ball)
    walls = truth | cap
    if holed:
        walls[np.flatnonzero(truth)[0]] = False
    first = run(pd, walls, config=_config(skip=TOPOLOGY + ("revote",)))
    assert first.info["inside_tets"] == 0  # the failure the second vote is for
    out = run(pd, walls, config=_config())
    assert out.info["sheets_set_aside"] == cap.sum() and out.info["inside_tets"] == ball.sum()
    assert out.info["holes_filled"] == int(holed)
    closed = out.faces[:out.closed]
    check_closed(closed, pd.points[out.vertices])
    expected = solid.oriented_boundary(pd, ball, np.flatnonzero(truth))
    assert {cycle(out.vertices[f]) for f in closed.tolist()} == {cycle(f) for f in expected.tolist()}
    assert len(out.faces) - out.closed == cap.sum()  # the cap stays, as a sheet


def test_surface_of_a_renumbered_mesh_and_a_foreign_one():
    pd = cloud_diagram(seed=4)
    inside = ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    mesh = trimesh.Trimesh(pd.points, pd.faces[walls], process=False)
    mesh.remove_unreferenced_vertices()
    out = surface_of_wdt_mesh(mesh, pd)
    closed = check_closed(np.asarray(out.faces), np.asarray(out.vertices))
    assert closed.volume == pytest.approx(solid.tet_volumes(pd.points, pd.tets)[inside].sum(), rel=1e-9)
    mesh.vertices[0] += 0.01
    with pytest.raises(ValueError, match="not points of the triangulation"):
        surface_of_wdt_mesh(mesh, pd)


def test_surface_closes_a_large_hole_with_the_inside_tets_boundary():
    """A ball's boundary with a cap of walls missing (a part a scanner did not see): too large a hole for a
    fill over its rim, so the inside tets' own boundary closes it: a closed surface that keeps the walls and
    about the ball's volume (the walks that leave through the hole call a few tets under it outside, so the
    lid need not be the missing cap face for face); its mesh, lid refined and faired, is watertight. Without
    lids the hole stays open."""
    pd = cloud_diagram(n=3000, seed=4)
    inside = ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    truth = solid.oriented_boundary(pd, inside, np.flatnonzero(walls))
    centre = pd.points[pd.faces.astype(np.int64)].mean(1)
    cap = walls & (centre[:, 2] > 0.35)
    holed = walls & ~cap
    small = {"revote.min_faces": 8, "lids.max_hole": 8, "fills.max_hole": 8}
    config = SurfaceConfig().with_overrides(small)
    out = run(pd, holed, config=config.with_overrides({"skip": TOPOLOGY}))
    assert out.info["lids"] == 1 and out.info["lid_faces"] > 0 and out.info["holes_left"] == 0
    assert out.lid.sum() == out.info["lid_faces"] and not out.lid[out.closed:].any()
    mesh = check_closed(out.faces, pd.points[out.vertices])
    kept = {cycle(out.vertices[f]) for f in out.faces[~out.lid].tolist()}
    walls_kept = [cycle(f) in kept for f in truth.tolist() if cycle(f) not in
                  {cycle(g) for g in solid.oriented_boundary(pd, inside, np.flatnonzero(cap)).tolist()}]
    assert np.mean(walls_kept) > 0.95
    ball = trimesh.Trimesh(pd.points, truth, process=False).volume
    assert mesh.volume == pytest.approx(ball, rel=0.1)
    bare = run(pd, holed, config=config.with_overrides({"skip": TOPOLOGY + ("lids",)}))
    assert bare.info["holes_left"] >= 1 and boundary_edge_count(bare.faces) > 8

    faired = surface_mesh(pd, holed, config=config)
    info = faired.metadata["surface"]
    assert info["lids_faired"] and info["lid_vertices_added"] > 0
    check_closed(np.asarray(faired.faces), np.asarray(faired.vertices))
    # the fair stage skipped: the lids stay faces of the triangulation, the surface's faces as they are
    flat = surface_mesh(pd, holed, config=config.with_overrides({"skip": ["fair"]}))
    assert "lids_faired" not in flat.metadata["surface"] and len(flat.faces) == len(out.faces)
    check_closed(np.asarray(flat.faces), np.asarray(flat.vertices))
    assert len(faired.vertices) == len(flat.vertices) + info["lid_vertices_added"]
    with pytest.raises(ValueError, match="fair.continuity"):
        config.with_overrides({"fair.continuity": 3})


def test_a_stretch_the_samples_missed_is_faired_between_them():
    """Samples of a sphere with a cap left unsampled (what a scanner did not see): the Delaunay faces across the
    cap are a flat lid of long faces, no hole. With `spans` (the default) they are refined and faired like a lid
    over a hole: the cap rises back towards the sphere, the surface stays watertight, and no sample moves.
    With `spans=0` the faces stay flat."""
    n = 1500
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    samples = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    samples = samples[samples[:, 2] < 0.75]
    corners = 1.5 * np.array([[x, y, w] for x in (-1, 1) for y in (-1, 1) for w in (-1, 1)], float)
    pd = wdt.PowerDiagram.from_points(np.concatenate([samples, corners]), None)
    inside = (pd.tets < len(samples)).all(1)  # the samples' hull
    walls = solid.boundary_mask(pd, inside)
    flat = surface_mesh(pd, walls, config=SurfaceConfig().with_overrides({"spans.ratio": 0.0}))
    assert flat.metadata["surface"]["span_faces"] == 0 and np.asarray(flat.vertices)[:, 2].max() < 0.76
    faired = surface_mesh(pd, walls)
    info = faired.metadata["surface"]
    assert info["span_faces"] > 0 and info["lids_faired"] and info["lid_vertices_added"] > 0
    v = np.asarray(faired.vertices)
    check_closed(np.asarray(faired.faces), v)
    assert v[:, 2].max() > 0.85  # a sphere's cap, not a plane: the top of the unit sphere is 1
    old = v[:len(v) - info["lid_vertices_added"]]
    assert np.abs(np.linalg.norm(old, axis=1) - 1.0).max() < 1e-9  # every sample stays on the sphere
    with pytest.raises(ValueError, match="spans.ratio"):
        SurfaceConfig().with_overrides({"spans.ratio": -1.0})


@pytest.mark.parametrize("height,dropped", [(0.7, True), (1.5, False)])
@pytest.mark.parametrize("as_span", [False, True])
def test_a_lid_whose_fair_form_crosses_a_sheet_is_dropped(height, dropped, as_span):
    """A pressed sphere cap as the lid and a square sheet above it: faired, the cap rises towards the sphere.
    Through a sheet at z = 0.7 it would cross it, so the lid is dropped (its hole open again) and the sheet
    kept; a sheet at z = 1.5 leaves the faired lid in place. The cap as a span (faces of the surface across an
    unsampled stretch, not a lid; its corners held): a sheet tilted through it is crossed whatever the fairing
    does, so the span leaves the fairing and its faces stay as they were (the surface stays closed); under the
    sheet at z = 1.5 only new vertices are added and moved."""
    from dmesh.surface.finish import fair_patches

    sphere = trimesh.creation.icosphere(3)
    v, f = np.asarray(sphere.vertices, dtype=np.float64), np.asarray(sphere.faces, dtype=np.int64)
    lid = v[f].mean(1)[:, 2] > 0.6
    inner = np.setdiff1d(np.unique(f[lid]), np.unique(f[~lid]))
    v[inner, 2] = 0.6
    square = np.array([[-0.5, -0.5, height], [0.5, -0.5, height], [0.5, 0.5, height], [-0.5, 0.5, height]])
    if as_span and dropped:  # its corners held, a span barely rises: a sheet tilted through the pressed cap
        square[:, 2] = 0.5 + 0.3 * square[:, 0]
    sheet = len(v) + np.array([[0, 1, 2], [0, 2, 3]])
    vertices = np.concatenate([v, square])
    faces = np.concatenate([f, sheet])
    none = np.zeros(len(f), bool)
    out_v, refined, keep, counts = fair_patches(vertices, f, sheet, none if as_span else lid, lid if as_span else none)
    closed = refined[keep]
    out_f = np.concatenate([closed, sheet])
    assert counts["lids_dropped"] == int(dropped)
    if dropped and as_span:
        assert np.array_equal(out_v, vertices) and np.array_equal(closed, f)
        assert counts["lid_faces_dropped"] == 0
    elif as_span:
        assert np.array_equal(out_v[:len(vertices)], vertices) and len(out_v) > len(vertices)
        check_closed(closed, out_v)
    elif dropped:
        assert np.array_equal(out_v, vertices) and len(closed) == (~lid).sum()
        assert counts["lid_faces_dropped"] == lid.sum() and boundary_edge_count(closed) > 0
    else:
        assert len(out_v) > len(vertices) and counts["lid_vertices_added"] > 0
        check_closed(closed, out_v)
        assert not FaceIndex(out_v, out_f).crossing(out_f).any()


def test_surface_keeps_every_face_of_a_branch_and_moves_its_copies_apart():
    """Three sheet faces on one edge: each keeps its face, with its own copies of the edge's vertices, moved
    into it, so that read back with vertices merged by position the edge is not a branch."""
    from datasets.meshes import merge_vertices

    # A flat strip of two faces on edge 0-1 (z = 0) and a fin standing up from that edge.
    pts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0.1, 1.0],
                    [3, 3, 3], [-3, 3, -3], [3, -3, -3], [-3, -3, 3]], float)
    pd = wdt.PowerDiagram.from_points(pts, None)
    wanted = {(0, 1, 2), (0, 1, 3), (0, 1, 4)}
    walls = np.array([tuple(sorted(f)) in wanted for f in pd.faces.tolist()])
    assert walls.sum() == 3
    mesh = surface_mesh(pd, walls, config=_config(crumbs__max_faces=0, closed_crumbs__max_faces=0, skip=()))
    assert len(mesh.faces) == 3 and mesh.metadata["surface"]["split_vertices"] == 4   # 2 more copies of 0 and 1
    merged = merge_vertices(mesh.vertices, mesh.faces)[1]
    assert len(nonmanifold_edges(merged)) == 0 and len(nonmanifold_vertices(merged)) == 0
    # Only the copies moved, each by 5 % of the way to its face's centroid (far less than an edge).
    moved = np.linalg.norm(mesh.vertices - pts[np.argmin(((mesh.vertices[:, None] - pts) ** 2).sum(2), 1)], axis=1)
    assert (moved[moved > 0] < 0.05).all() and (moved > 0).sum() == 6


def test_surface_drops_stray_sheet_triangles_so_a_closed_part_stays_watertight():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(400, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    inner = 0.3 * rng.normal(size=(40, 3))
    pd = wdt.PowerDiagram.from_points(np.concatenate([pts, inner]), None)
    hull = pd.is_hull
    walls = hull.copy()
    inner_faces = np.flatnonzero((pd.faces >= len(pts)).all(1))  # faces among the interior points only
    walls[inner_faces[:1]] = True  # one stray triangle inside the ball
    # crumbs.max_faces: pieces this small go when all are; crumbs.max_debris: a sheet part this small a fraction of
    # the faces goes whatever its pieces' sizes (one stray face among about 800 is 1/800 of them). The stray
    # triangle can lie within an edge length of the sphere; the stacked stage is skipped here.
    for max_crumb, max_debris, expect_stray in ((4, 0.0, False), (0, 0.0, True), (0, 1e-3, True), (0, 0.01, False)):
        out = run(pd, walls, config=_config(crumbs__max_faces=max_crumb, closed_crumbs__max_faces=max_crumb,
                                            crumbs__max_debris=max_debris, skip=TOPOLOGY + ("stacked",)))
        mesh = trimesh.Trimesh(pd.points[out.vertices], out.faces, process=False)
        assert ((len(out.faces) == int(hull.sum()) + 1) == expect_stray
                and out.info["crumbs_dropped"] == (not expect_stray))
        assert mesh.split(only_watertight=False)[0].is_watertight
