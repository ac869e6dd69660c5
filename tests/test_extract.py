"""Mesh extraction (`dmesh.extract`): the modes (upstream's, interior removal, one sheet per real-tet cluster), the
raw-faces mesh of a DMesh, and the visibility and depth filters. The surface step made of these faces:
tests/test_surface_*.py."""
from __future__ import annotations

import numpy as np
import pytest

from datasets import capture as cap
from dmesh import wdt
from dmesh.extract import depth_consistent_faces, mesh_faces, visible_faces
from dmesh.recon.init import seeds_and_voronoi
from dmesh.recon.views import check_views

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


def test_a_dmesh_gives_its_raw_faces_or_their_surface_through_one_argument():
    """`DMesh.extract_mesh`: without `surface`, its mesh faces as sorted triples (`dmesh.extract.extract`); with a
    `SurfaceConfig`, the surface step made of the same faces (`dmesh.surface.surface_mesh`): here, sampled from
    a sphere, a closed outward mesh, its counts in the metadata."""
    from datasets import normalize, sampling, synthetic
    from dmesh.extract import extract
    from dmesh.model import DMesh
    from dmesh.surface import SurfaceConfig, surface_mesh

    gt, _ = normalize.normalize(synthetic.generate("sphere", seed=0))
    samples, _ = sampling.sample_points(gt, 4000, seed=0)
    pos, reals = seeds_and_voronoi(samples, 800, np.random.default_rng(0), vertices="poles")
    dm = DMesh(pos, np.ones(len(pos)), reals)
    raw = dm.extract_mesh(mode="sheet")
    assert np.array_equal(np.asarray(raw.faces), np.sort(raw.faces, axis=1)) and "surface" not in raw.metadata
    assert np.array_equal(raw.faces, extract(dm, mode="sheet").faces)
    pd = dm.power_diagram()
    made = dm.extract_mesh(mode="sheet", surface=SurfaceConfig(), pd=pd)
    same = surface_mesh(pd, mesh_faces(pd, reals > 0.5, "sheet"))
    assert np.array_equal(made.faces, same.faces) and np.array_equal(made.vertices, same.vertices)
    assert len(made.faces) == len(raw.faces) and made.is_watertight and made.volume > 0
    assert made.metadata["surface"]["closed_faces"] == len(raw.faces)


def test_unknown_mode_is_an_error():
    pd = wdt.PowerDiagram.from_points(np.eye(4, 3) + 0.1 * np.arange(4)[:, None], None)
    with pytest.raises(ValueError, match="extraction mode"):
        mesh_faces(pd, np.ones(4, bool), "both")


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


