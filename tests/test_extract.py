"""Mesh extraction (`dmesh.extract`): the modes (upstream's, interior removal, one sheet per real-tet cluster),
the closed surface of a labelling (holes filled, fins dropped), and the visibility and depth filters."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datasets import capture as cap
from dmesh import repair, solid, wdt
from dmesh.extract import (SurfaceConfig, depth_consistent_faces, mesh_faces, surface, surface_of_mesh,
                           visible_faces)
from dmesh.recon.init import seeds_and_voronoi
from dmesh.recon.views import check_views
from common import ball_labels, check_closed, cloud_diagram, cycle

_NO_GL = cap.gl_problem()
needs_gl = pytest.mark.skipif(_NO_GL is not None, reason=f"no headless OpenGL (OSMesa/EGL): {_NO_GL}")


def _edge_counts(faces):
    e = np.sort(np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_flat_real_tet_keeps_its_larger_sheet():
    # Four real points of a bent square (two opposite corners raised unequally) form one flat tet: its
    # circumsphere leaves out the two imaginary points at z = +-2, and all four of its faces are real.
    pts = np.array([[0, 0, 0], [1, 0, 0.3], [0, 1, 0.1], [1, 1, 0], [0.5, 0.5, 2.0], [0.5, 0.5, -2.0]])
    real = np.array([1, 1, 1, 1, 0, 0], bool)
    pd = wdt.PowerDiagram.from_points(pts, None)
    assert real[pd.tets].all(1).sum() == 1
    every = pd.faces[mesh_faces(pd, real, "all")]
    assert len(every) == 4 and len(pd.faces[mesh_faces(pd, real, "no_interior")]) == 4
    sheet = pd.faces[mesh_faces(pd, real, "sheet")]
    assert len(sheet) == 2 and len(np.unique(sheet)) == 4       # two triangles covering the quad

    def area(f):
        p = pts[f]
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()

    # The quad is 0-1-3-2; its two triangulations split it along 0-3 or along 1-2.
    split_03, split_12 = np.array([[0, 1, 3], [0, 3, 2]]), np.array([[0, 1, 2], [1, 3, 2]])
    assert abs(area(split_03) - area(split_12)) > 1e-4
    larger = split_03 if area(split_03) > area(split_12) else split_12
    assert sorted(map(sorted, sheet.tolist())) == sorted(map(sorted, larger.tolist()))


def test_sheet_rule_with_real_tets_on_the_hull():
    """Real tets on the convex hull (every point real, as after image-loss steps pushed points to the box): their
    hull faces have no tet across; the one-sheet rule must still return one side of the cluster, not index
    past the points."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        pts = rng.normal(size=(40, 3))
        pts[:, 2] *= 0.05                                     # a thin slab: one flat cluster of real tets
        pd = wdt.PowerDiagram.from_points(pts, None)
        keep = mesh_faces(pd, np.ones(len(pts), bool), "sheet")
        hull = (pd.face_tets < 0).any(1)
        assert keep.any() and (keep <= hull).all()            # a side of the slab: hull faces only


def _apex_interior(pd, real):
    """Upstream's `remove_invisible` rule: faces whose two tets both have a real apex (the tet's vertex not in
    the face); hull faces never."""
    ft = pd.face_tets.astype(np.int64)
    out = ft[:, 1] >= 0
    inner = np.flatnonzero(out)
    fsum = pd.faces[inner].astype(np.int64).sum(1)
    for side in (0, 1):
        apex = pd.tets[ft[inner, side]].astype(np.int64).sum(1) - fsum
        out[inner] &= real[apex]
    return out


def test_no_interior_is_the_apex_rule_on_random_diagrams():
    """The multi-view "apex" rule (real faces minus those with two real apexes) is "no_interior"."""
    rng = np.random.default_rng(7)
    for trial in range(30):
        n = int(rng.integers(12, 80))
        pts = rng.random((n, 3))
        weights = 0.01 * rng.random(n) if trial % 2 else None
        pd = wdt.PowerDiagram.from_points(pts, weights)
        real = rng.random(n) < rng.uniform(0.3, 0.95)
        want = real[pd.faces].all(1) & ~_apex_interior(pd, real)
        assert want.any() and np.array_equal(mesh_faces(pd, real, "no_interior"), want)


def test_sheet_of_a_sampled_torus_is_closed_and_manifold():
    from datasets import normalize, sampling, synthetic

    gt, _ = normalize.normalize(synthetic.generate("torus", seed=0))
    samples, _ = sampling.sample_points(gt, 20_000, seed=0)
    pos, reals = seeds_and_voronoi(samples, 3000, np.random.default_rng(0), vertices="poles")
    pd = wdt.PowerDiagram.from_points(pos, None)
    real = reals > 0.5
    masks = {m: mesh_faces(pd, real, m) for m in ("all", "no_interior", "sheet")}
    assert (masks["sheet"] <= masks["no_interior"]).all() and (masks["no_interior"] <= masks["all"]).all()
    assert (_edge_counts(pd.faces[masks["all"]]) > 2).sum() > 100   # upstream's extraction: non-manifold
    counts = _edge_counts(pd.faces[masks["sheet"]])
    assert (counts == 2).all()                                      # closed 2-manifold ...
    n_faces = int(masks["sheet"].sum())
    assert 3000 - len(counts) + n_faces == 0                        # ... of genus 1 over all 3000 seeds


def test_unknown_mode_is_an_error():
    pd = wdt.PowerDiagram.from_points(np.eye(4, 3) + 0.1 * np.arange(4)[:, None], None)
    with pytest.raises(ValueError, match="extraction mode"):
        mesh_faces(pd, np.ones(4, bool), "both")


# -------------------------------------------------------------------------------------- closed surfaces

def test_surface_closes_a_holed_boundary_and_drops_a_fin():
    pd = cloud_diagram(seed=2)
    inside = ball_labels(pd)
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
    config = SurfaceConfig()
    first = surface(pd, walls, config=SurfaceConfig(revote=False))
    assert first.info["inside_tets"] == 0  # the failure the second vote is for
    out = surface(pd, walls, config=config)
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
    out = surface_of_mesh(mesh, pd)
    closed = check_closed(np.asarray(out.faces), np.asarray(out.vertices))
    assert closed.volume == pytest.approx(solid.tet_volumes(pd.points, pd.tets)[inside].sum(), rel=1e-9)
    mesh.vertices[0] += 0.01
    with pytest.raises(ValueError, match="not points of the triangulation"):
        surface_of_mesh(mesh, pd)


# ---------------------------------------------------------------------------------------------- filters

@needs_gl
def test_depth_consistency_keeps_the_surface_and_drops_what_lies_inside_or_outside(sphere, sphere_views):
    vw = check_views(sphere_views)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)

    def kept(verts, tol=0.02):
        return depth_consistent_faces(verts, f, vw.world_to_camera, vw.fov_y_degrees, vw.depth, vw.mask, tol).mean()

    assert kept(v) > 0.99                       # the captured surface itself
    assert kept(0.9 * v) == 0.0                 # an inner shell: behind the surface in every view
    assert kept(1.5 * v) == 0.0                 # an outer shell: in front of it, or on background
    assert kept(0.9 * v, tol=0.2) > 0.99        # within a generous tolerance it counts as the surface


def _cube_with_centre():
    """A cube's 8 corners and its centre: 12 tets around the centre, hull = the cube's 12 triangles."""
    from dmesh.wdt import PowerDiagram

    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    pts = np.r_[corners, [[0.01, 0.02, 0.03]]]    # centre off-symmetric: a unique triangulation
    return pts, PowerDiagram.from_points(pts, None)


def _interior_naive(pd, real):
    out = np.zeros(len(pd.faces), bool)
    for f, (t0, t1) in enumerate(pd.face_tets):
        if t1 < 0:
            continue
        apexes = [set(pd.tets[t].tolist()) - set(pd.faces[f].tolist()) for t in (t0, t1)]
        assert all(len(a) == 1 for a in apexes)
        out[f] = all(real[a.pop()] for a in apexes)
    return out


def test_apex_rule_drops_faces_with_two_real_apexes():
    """The "apex" interior rule is `mesh_faces(..., "no_interior")`: real faces minus those whose two tets
    both have a real apex."""
    pts, pd = _cube_with_centre()
    assert len(pd.tets) == 12 and pd.is_hull.sum() == 12
    every = np.ones(len(pts), bool)
    assert (mesh_faces(pd, every, "no_interior") == pd.is_hull).all()   # all real: only the hull is left
    for off in (0, 5, 8):                          # one imaginary point (a corner, or the centre)
        real = every.copy()
        real[off] = False
        want = real[pd.faces].all(1) & ~_interior_naive(pd, real)
        assert (mesh_faces(pd, real, "no_interior") == want).all()


def test_visible_faces_are_the_hull_of_an_opaque_solid():
    from dmesh.render import Camera

    pts, pd = _cube_with_centre()
    cams = Camera.from_views(cap.camera_rig(8, distance=3.0)[0], resolution=32)
    seen = visible_faces(pts, pd, np.ones(len(pd.faces), bool), cams)
    assert (seen == pd.is_hull).all()
    few = np.zeros(len(pd.faces), bool)
    few[np.flatnonzero(~pd.is_hull)[:3]] = True    # inner faces alone are visible through the empty hull
    assert (visible_faces(pts, pd, few, cams) <= few).all() and visible_faces(pts, pd, few, cams).any()


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
    config = SurfaceConfig(max_hole=8)
    out = surface(pd, holed, config=config)
    assert out.info["lids"] == 1 and out.info["lid_faces"] > 0 and out.info["holes_left"] == 0
    assert out.lid.sum() == out.info["lid_faces"] and not out.lid[out.closed:].any()
    mesh = check_closed(out.faces, pd.points[out.vertices])
    kept = {cycle(out.vertices[f]) for f in out.faces[~out.lid].tolist()}
    walls_kept = [cycle(f) in kept for f in truth.tolist() if cycle(f) not in
                  {cycle(g) for g in solid.oriented_boundary(pd, inside, np.flatnonzero(cap)).tolist()}]
    assert np.mean(walls_kept) > 0.95
    ball = trimesh.Trimesh(pd.points, truth, process=False).volume
    assert mesh.volume == pytest.approx(ball, rel=0.1)
    bare = surface(pd, holed, config=SurfaceConfig(max_hole=8, lids=False))
    assert bare.info["holes_left"] >= 1 and repair.boundary_edge_count(bare.faces) > 8

    walls_mesh = trimesh.Trimesh(pd.points, pd.faces[holed], process=False)
    faired = surface_of_mesh(walls_mesh, pd, config=config)
    info = faired.metadata["surface"]
    assert info["lids_faired"] and info["lid_vertices_added"] > 0
    check_closed(np.asarray(faired.faces), np.asarray(faired.vertices))
    # `fairing=-1`: the lids stay faces of the triangulation, the surface's faces as they are
    flat = surface_of_mesh(walls_mesh, pd, config=SurfaceConfig(max_hole=8, fairing=-1))
    assert "lids_faired" not in flat.metadata["surface"] and len(flat.faces) == len(out.faces)
    check_closed(np.asarray(flat.faces), np.asarray(flat.vertices))
    assert len(faired.vertices) == len(flat.vertices) + info["lid_vertices_added"]
    with pytest.raises(ValueError, match="fairing"):
        SurfaceConfig(fairing=3)



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
    mesh = trimesh.Trimesh(pd.points, pd.faces[walls], process=False)
    flat = surface_of_mesh(mesh, pd, config=SurfaceConfig(spans=0.0))
    assert flat.metadata["surface"]["span_faces"] == 0 and np.asarray(flat.vertices)[:, 2].max() < 0.76
    faired = surface_of_mesh(mesh, pd)
    info = faired.metadata["surface"]
    assert info["span_faces"] > 0 and info["lids_faired"] and info["lid_vertices_added"] > 0
    v = np.asarray(faired.vertices)
    check_closed(np.asarray(faired.faces), v)
    assert v[:, 2].max() > 0.85  # a sphere's cap, not a plane: the top of the unit sphere is 1
    old = v[:len(v) - info["lid_vertices_added"]]
    assert np.abs(np.linalg.norm(old, axis=1) - 1.0).max() < 1e-9  # every sample stays on the sphere
    with pytest.raises(ValueError, match="spans"):
        SurfaceConfig(spans=-1.0)


@pytest.mark.parametrize("height,dropped", [(0.7, True), (1.5, False)])
@pytest.mark.parametrize("as_span", [False, True])
def test_a_lid_whose_fair_form_crosses_a_sheet_is_dropped(height, dropped, as_span):
    """A pressed sphere cap as the lid and a square sheet above it: faired, the cap rises towards the sphere.
    Through a sheet at z = 0.7 it would cross it, so the lid is dropped (its hole open again) and the sheet
    kept; a sheet at z = 1.5 leaves the faired lid in place. The cap as a span (faces of the surface across an
    unsampled stretch, not a lid; its corners held): a sheet tilted through it is crossed whatever the fairing
    does, so the span leaves the fairing and its faces stay as they were (the surface stays closed); under the
    sheet at z = 1.5 only new vertices are added and moved."""
    from dmesh.extract import Surface, _fair_lids

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
    flags = np.r_[lid, False, False]
    none = np.zeros(len(flags), bool)
    info = {"lids": 0, "lid_faces": 0} if as_span else {"lids": 1, "lid_faces": int(lid.sum())}
    result = Surface(faces, np.arange(len(vertices)), len(f), info, none if as_span else flags,
                     flags if as_span else none)
    out_v, out_f = _fair_lids(vertices, faces, result, 1)
    assert result.info["lids_dropped"] == int(dropped)
    assert {cycle(t) for t in sheet.tolist()} <= {cycle(t) for t in out_f.tolist()}  # the sheet stays
    closed = out_f[~np.isin(out_f, sheet).all(1)]
    if dropped and as_span:
        assert np.array_equal(out_v, vertices) and np.array_equal(closed, f)
        assert result.info["lid_faces"] == 0
    elif as_span:
        assert np.array_equal(out_v[:len(vertices)], vertices) and len(out_v) > len(vertices)
        check_closed(closed, out_v)
    elif dropped:
        assert np.array_equal(out_v, vertices) and len(closed) == (~lid).sum()
        assert result.info["lid_faces"] == 0 and repair.boundary_edge_count(closed) > 0
    else:
        assert len(out_v) > len(vertices) and result.info["lid_vertices_added"] > 0
        check_closed(closed, out_v)
        assert not repair.FaceIndex(out_v, out_f).crossing(out_f).any()
