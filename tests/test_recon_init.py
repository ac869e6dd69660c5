"""The initial DMesh (`dmesh.recon.init`): Voronoi poles off the surface, carving faces that span holes."""
from __future__ import annotations

import numpy as np
import pytest

from dmesh import wdt
from dmesh.extract import mesh_faces
from dmesh.recon.init import poles, seeds_and_voronoi


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


def test_statistical_inliers_drop_stray_points_and_keep_the_surface():
    """Uniform stray points in the bounding cube of a dense sphere sample are dropped; the sample stays."""
    from dmesh.recon.init import statistical_inliers

    rng = np.random.default_rng(0)
    surface = rng.normal(size=(20_000, 3))
    surface /= np.linalg.norm(surface, axis=1, keepdims=True)
    stray = rng.uniform(-1.1, 1.1, size=(1000, 3))
    stray = stray[np.abs(np.linalg.norm(stray, axis=1) - 1.0) > 0.1]  # really off the surface
    keep = statistical_inliers(np.concatenate([surface, stray]), std_ratio=2.0)
    assert (~keep[len(surface):]).mean() > 0.9       # the stray points go
    assert keep[:len(surface)].mean() > 0.95         # the surface stays (a tail of its own goes)
    assert statistical_inliers(surface[:1], 2.0).tolist() == [True]


def test_smooth_points_keeps_a_plane_and_denoises_a_sphere_without_shrinking_it():
    """CGAL's jet smoothing: points on a plane stay where they are (a quadratic jet fits a plane exactly);
    Gaussian noise on a unit sphere falls several-fold, and the mean radius stays 1 (a plane fit would pull
    every point inward by about r^2 / 4 for a neighbourhood of radius r)."""
    from dmesh.recon.init import smooth_points

    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)] @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    np.testing.assert_allclose(smooth_points(plane, 30), plane, atol=1e-9)

    sphere = rng.normal(size=(20_000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    noisy = sphere + rng.normal(scale=0.01, size=sphere.shape)
    out = smooth_points(noisy, 60)
    before = np.abs(np.linalg.norm(noisy, axis=1) - 1).mean()
    after = np.abs(np.linalg.norm(out, axis=1) - 1).mean()
    assert after < before / 3, (before, after)
    assert abs(np.linalg.norm(out, axis=1).mean() - 1.0) < 1e-3
    np.testing.assert_array_equal(smooth_points(noisy, 60, workers=2), out)  # threads change nothing
    for k in (5, 20_000):
        with pytest.raises(ValueError, match="smooth_points: k must be in"):
            smooth_points(noisy, k)
