"""Mesh extraction modes (`dmesh.extract`): upstream's, interior removal, and one sheet per real-tet cluster."""
from __future__ import annotations

import numpy as np
import pytest

from dmesh import wdt
from dmesh.extract import mesh_faces
from dmesh.recon.init import poles, seeds_and_voronoi


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


def test_poles_lie_off_the_surface_on_both_sides():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(400, 3))
    sphere = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.99, 1.01, (400, 1))
    corners = 3.0 * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    pd = wdt.PowerDiagram.from_points(np.concatenate([sphere, corners]), None)
    ids = poles(pd, len(sphere))
    r = np.linalg.norm(pd.orthocentres[ids], axis=1)
    r_all = np.linalg.norm(pd.orthocentres, axis=1)
    # Inner poles sit near the centre (the medial axis of a sphere), outer ones far outside. Few hug the
    # surface (measured: 0.4 % of the poles against 3.3 % of all Voronoi vertices), which is what keeps
    # them from punching holes into the first mesh.
    assert (r < 0.5).any() and (r > 1.3).any()
    assert (np.abs(r - 1) < 0.1).mean() < 0.25 * (np.abs(r_all - 1) < 0.1).mean()
    assert len(ids) <= 2 * len(sphere)


def test_unknown_mode_is_an_error():
    pd = wdt.PowerDiagram.from_points(np.eye(4, 3) + 0.1 * np.arange(4)[:, None], None)
    with pytest.raises(ValueError, match="extraction mode"):
        mesh_faces(pd, np.ones(4, bool), "both")


def test_carving_removes_faces_spanning_holes():
    from scipy.spatial import cKDTree

    from datasets import normalize, sampling, synthetic
    from dmesh.recon.init import carve_far_faces

    gt, _ = normalize.normalize(synthetic.generate("wavy_sheet", seed=0))   # an open sheet with 3 holes
    data, _ = sampling.sample_points(gt, 20_000, seed=0)
    pos, reals = seeds_and_voronoi(data, 4000, np.random.default_rng(0), vertices="poles")

    def far_area(p, r):
        pd = wdt.PowerDiagram.from_points(p, None)
        f = pd.faces[mesh_faces(pd, r > 0.5, "sheet")]
        d = cKDTree(data).query(p[f].mean(1))[0]
        area = 0.5 * np.linalg.norm(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]), axis=1)
        return area[d > 0.05].sum(), len(f)

    before, n_before = far_area(pos, reals)
    pos2, reals2, added = carve_far_faces(pos, reals, data)
    after, n_after = far_area(pos2, reals2)
    assert before > 0.01 and added > 0                # the holes are spanned at first ...
    assert after == 0.0 and n_after > 0.95 * n_before  # ... and only those faces go
    assert (reals2[len(reals):] == 0).all() and np.array_equal(pos2[:len(pos)], pos)
