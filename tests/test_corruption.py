"""Corrupted inputs (`datasets.corrupt`, `datasets.scan`) and their sweep settings (`eval.sweep` variants).

Each corruption is checked against what it promises, measured independently: the noise's standard deviation,
the exact outlier count and region, exact subset sizes, the density ratio of the non-uniform draw (against
uniform samples of the same mesh), scans that see only visible surface (an independent ray cast by trimesh's
own intersector, and a sphere hidden inside a closed box) with normals facing their camera, and run keys and
cache names that differ per level while sweeps without variants keep theirs.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datasets import corrupt
from datasets.sampling import sample_points
from datasets.scan import DEFAULT_RADII, simulate_scan
from eval.sweep import Sweep, expand

pytest.importorskip("open3d")


def _sphere(subdivisions: int = 4) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)


def _clean(n: int = 4000, seed: int = 0):
    mesh = _sphere()
    p, nrm = sample_points(mesh, n, seed)
    return mesh, p, nrm


# --------------------------------------------------------------------------------------------------- stages

def test_same_seed_same_cloud_other_seed_other_cloud():
    mesh, p, n = _clean()
    c = {"noise": 0.005, "outliers": 0.05, "density": 3000, "normals": "estimated"}
    a, b = corrupt.corrupt_cloud(mesh, p, n, c, seed=3), corrupt.corrupt_cloud(mesh, p, n, c, seed=3)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    other = corrupt.corrupt_cloud(mesh, p, n, c, seed=4)
    assert not np.array_equal(a["points"], other["points"])
    s1 = corrupt.corrupt_cloud(mesh, p, n, {"scan": 3, "noise": 0.002}, seed=1)
    s2 = corrupt.corrupt_cloud(mesh, p, n, {"scan": 3, "noise": 0.002}, seed=1)
    np.testing.assert_array_equal(s1["points"], s2["points"])
    np.testing.assert_array_equal(s1["normals"], s2["normals"])


@pytest.mark.parametrize("sigma", [0.0025, 0.005, 0.01])
def test_noise_std_matches_the_level(sigma):
    _, p, _ = _clean(20000)
    d = corrupt.add_noise(p, sigma, seed=0) - p
    # 60000 coordinates: the sample std is within ~0.6 % of sigma (1 sigma); 3 % is ~5 sigma.
    assert abs(d.std() / sigma - 1) < 0.03 and abs(d.mean()) < sigma * 0.03
    np.testing.assert_allclose(d.std(axis=0) / sigma, 1.0, atol=0.05)  # isotropic


@pytest.mark.parametrize("fraction", [0.0, 0.01, 0.05, 0.1])
def test_outlier_count_is_exact_and_they_lie_in_the_enlarged_cube(fraction):
    _, p, n = _clean(1000)
    q, m, mask = corrupt.add_outliers(p, n, fraction, seed=2)
    assert mask.sum() == round(fraction * 1000) and len(q) == 1000
    np.testing.assert_array_equal(q[~mask], p[~mask].astype(np.float64))
    np.testing.assert_array_equal(m[~mask], n[~mask].astype(np.float64))
    lo, hi = p.min(0), p.max(0)
    half = (hi - lo).max() / 2 * (1 + corrupt.OUTLIER_MARGIN)
    assert (np.abs(q[mask] - (lo + hi) / 2) <= half + 1e-12).all()
    np.testing.assert_allclose(np.linalg.norm(m[mask], axis=1), 1.0, atol=1e-12)
    if fraction >= 0.05:  # the cube is larger than the sphere's box: some outliers lie outside it
        assert (np.abs(q[mask]) > 1.0 + 1e-3).any()


def test_outliers_of_a_flat_shape_leave_its_plane():
    disc = trimesh.creation.cylinder(radius=1.0, height=1e-6, sections=64)
    p, n = sample_points(disc, 2000, 0)
    q, _, mask = corrupt.add_outliers(p, n, 0.1, seed=0)
    assert np.abs(q[mask][:, 2]).max() > 0.5  # a cube around the disc, not its flat box


def test_density_keeps_exact_counts_of_the_clean_points():
    mesh, p, n = _clean(5000)
    for k in (5000, 2000, 10):
        out = corrupt.corrupt_cloud(mesh, p, n, {"density": k}, seed=0)
        assert len(out["points"]) == k
        rows = {tuple(r) for r in p}
        assert all(tuple(r) in rows for r in out["points"])
    with pytest.raises(ValueError, match="cannot keep"):
        corrupt.subsample(10, 11)


def test_nonuniform_density_grows_by_the_contrast_along_its_direction():
    mesh = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    contrast = 16.0
    p, _, u = corrupt.nonuniform_sample(mesh, 40000, contrast, seed=5)
    ref, _ = sample_points(mesh, 200000, 7)  # uniform samples of the same mesh: the area along u
    proj = np.asarray(mesh.vertices) @ u
    lo, span = proj.min(), np.ptp(proj)
    bins = np.linspace(0, 1, 9)
    h, _ = np.histogram((p @ u - lo) / span, bins)
    h_ref, _ = np.histogram((ref @ u - lo) / span, bins)
    ok = h_ref > 2000  # bins with enough area to measure
    centres = (bins[:-1] + bins[1:]) / 2
    slope = np.polyfit(centres[ok], np.log(h[ok] / h_ref[ok]), 1)[0]
    assert abs(slope / np.log(contrast) - 1) < 0.1, slope  # density ratio contrast ** t


def test_estimated_normals_point_outward_on_a_sphere():
    _, p, n = _clean(4000)
    est = corrupt.estimate_normals(p)
    assert (np.einsum("ij,ij->i", est, n) > 0.95).mean() > 0.99


def test_estimated_normals_on_a_box_turn_outward_on_every_face():
    """Coplanar parts (a box's faces) are where Open3D's propagation stalls (isl-org/Open3D#6482); ours turns
    them all outward. Two boxes side by side are two connected parts, each oriented."""
    import trimesh

    a = trimesh.creation.box((1.0, 1.0, 1.0))
    b = trimesh.creation.box((0.5, 0.5, 0.5))
    b.apply_translation([3.0, 0.0, 0.0])
    pts, normals = [], []
    for mesh in (a, b):
        p, face = trimesh.sample.sample_surface(mesh, 3000, seed=1)
        pts.append(p)
        normals.append(mesh.face_normals[face])
    p, n = np.concatenate(pts), np.concatenate(normals)
    est = corrupt.estimate_normals(p)
    agree = np.einsum("ij,ij->i", est, n)
    assert (agree > 0).mean() > 0.99 and np.median(agree) > 0.99


# --------------------------------------------------------------------------------------------------- scans

def _first_hit_distances(mesh, origins, points):
    """Distance from each origin to the first triangle its ray toward the point hits, by trimesh's own ray
    intersector (independent of the Embree scene the scan uses)."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    dirs = points - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    loc, ray_idx, _ = RayMeshIntersector(mesh).intersects_location(origins, dirs, multiple_hits=True)
    first = np.full(len(origins), np.inf)
    np.minimum.at(first, ray_idx, np.linalg.norm(loc - origins[ray_idx], axis=1))
    return first


def test_scan_points_are_first_hits_and_hidden_parts_get_none():
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    inner = trimesh.creation.icosphere(subdivisions=2, radius=0.5)  # inside the closed box: never visible
    mesh = trimesh.util.concatenate([box, inner])
    s = simulate_scan(mesh, 3000, cameras=5, seed=0)
    assert len(s.points) == 3000
    assert np.linalg.norm(s.points, axis=1).min() > 0.99  # all on the box (|p| >= 1), none on the sphere
    sub = np.random.default_rng(0).choice(3000, 300, replace=False)
    origins = s.cameras[s.camera_index[sub]]
    first = _first_hit_distances(mesh, origins, s.points[sub])
    np.testing.assert_allclose(first, np.linalg.norm(s.points[sub] - origins, axis=1), atol=2e-4)


def test_scan_of_a_torus_sees_only_visible_points():
    mesh = trimesh.creation.torus(major_radius=0.7, minor_radius=0.25, major_sections=48, minor_sections=24)
    s = simulate_scan(mesh, 2000, cameras=3, seed=4)
    origins = s.cameras[s.camera_index]
    first = _first_hit_distances(mesh, origins, s.points)
    np.testing.assert_allclose(first, np.linalg.norm(s.points - origins, axis=1), atol=2e-4)
    # Hit triangles face their camera (first hits of a closed outward-wound surface).
    assert (np.einsum("ij,ij->i", s.face_normals, origins - s.points) > 0).all()


def test_scan_cameras_sit_on_the_two_spheres_and_noise_is_along_the_ray():
    mesh = _sphere()
    s0 = simulate_scan(mesh, 2000, cameras=4, seed=1)
    lo, hi = mesh.bounds
    r = np.linalg.norm(hi - lo) / 2
    np.testing.assert_allclose(np.linalg.norm(s0.cameras - (lo + hi) / 2, axis=1) / r,
                               [DEFAULT_RADII[k % 2] for k in range(4)], rtol=1e-12)
    s1 = simulate_scan(mesh, 2000, cameras=4, seed=1, noise=0.01)
    d = s1.points - s0.points  # same rays, same hits: only the range differs
    along = np.einsum("ij,ij->i", d, s0.ray_dirs)
    np.testing.assert_allclose(d, along[:, None] * s0.ray_dirs, atol=1e-9)
    assert abs(along.std() / 0.01 - 1) < 0.1


def test_scan_normals_are_estimated_and_face_the_camera_that_saw_them():
    mesh, p, n = _clean(3000)
    out = corrupt.corrupt_cloud(mesh, p, n, {"scan": 4, "noise": 0.0025, "outliers": 0.01,
                                             "normals": "estimated"}, seed=0)
    cams, idx = out["cameras"], out["camera_index"]
    to_cam = cams[idx] - out["points"].astype(np.float64)
    assert (np.einsum("ij,ij->i", out["normals"], to_cam) > 0).all()
    assert out["is_outlier"].sum() == 30
    inl = ~out["is_outlier"]
    radial = out["points"][inl] / np.linalg.norm(out["points"][inl], axis=1, keepdims=True)
    # Estimated from noisy points, not copied from the GT: close to the sphere's normal, yet not identical.
    cos = np.einsum("ij,ij->i", out["normals"][inl], radial)
    assert np.median(cos) > 0.97 and (cos < 0.99999).mean() > 0.5


def test_scan_bad_arguments_are_one_line_errors():
    for kw, match in (({"cameras": 0}, "cameras"), ({"n": 0}, "n must"), ({"noise": -1.0}, "noise")):
        args = {"n": 10, "cameras": 2, **kw}
        with pytest.raises(ValueError, match=match):
            simulate_scan(_sphere(1), args.pop("n"), **args)


def test_depth_noise_on_covered_pixels_only():
    from datasets.capture import MultiView

    rng = np.random.default_rng(0)
    mask = rng.random((4, 64, 64)) < 0.5
    depth = np.where(mask, 2.0, 0.0).astype(np.float32)
    mv = MultiView(diffuse=mask.astype(np.float32), depth=depth, mask=mask,
                   world_to_camera=np.tile(np.eye(4), (4, 1, 1)), projection=np.eye(4), fov_y_degrees=65.0,
                   resolution=64)
    noisy = corrupt.add_depth_noise(mv, 0.01, seed=0)
    d = (noisy.depth - depth)[mask]
    assert abs(d.std() / 0.01 - 1) < 0.05 and (noisy.depth[~mask] == 0).all()
    np.testing.assert_array_equal(noisy.mask, mask)
    np.testing.assert_array_equal(noisy.diffuse, mv.diffuse)
    np.testing.assert_array_equal(corrupt.add_depth_noise(mv, 0.01, seed=0).depth, noisy.depth)


# --------------------------------------------------------------------------------------------------- settings

def test_canonical_variants_drop_clean_levels_and_name_bad_ones():
    kw = {"n_points": 1000, "views": 64, "resolution": 256}
    assert corrupt.canonical_variant({"noise": 0, "outliers": 0.0, "density": 1000, "views": 64}, **kw) == {}
    assert corrupt.canonical_variant({"noise": 1e-2}, **kw) == {"noise": 0.01}
    assert corrupt.canonical_variant({"scan": 5}, **kw) == {"normals": "estimated", "scan": 5}
    assert corrupt.canonical_variant({"scan": 5, "normals": "gt"}, **kw) == {"normals": "gt", "scan": 5}
    for bad, match in (({"noise": -0.1}, "noise: expected a number from 0 to 0.1"),
                       ({"noise": "x"}, "noise"), ({"outliers": 0.9}, "outliers"),
                       ({"density": 2000}, "density: expected an integer from 10 to 1000"),
                       ({"density": 10.5}, "density"), ({"scan": -1}, "scan"), ({"normals": "pca"}, "normals"),
                       ({"nonuniform": 0.5}, "nonuniform"), ({"noise": 0.01, "depth_noise": 0.01}, "mixes"),
                       ({"scan": 3, "nonuniform": 4}, "scan and nonuniform"), ({"blur": 1}, "unknown settings")):
        with pytest.raises(ValueError, match=match) as info:
            corrupt.canonical_variant(bad, **kw, what="Sweep.variants[0]")
        assert "\n" not in str(info.value) and str(info.value).startswith("Sweep.variants[0]")


def test_cache_tags_differ_per_level():
    tags = {corrupt.cache_tag(c) for c in ({"noise": 0.0025}, {"noise": 0.005}, {"noise": 0.01},
                                           {"outliers": 0.01}, {"scan": 6, "normals": "estimated"}, {})}
    assert len(tags) == 6 and corrupt.cache_tag({}) == "" and corrupt.cache_tag(None) == ""
    assert corrupt.cache_tag({"views": 8}) == ""  # capture sizes are in the name already


def test_sweep_keys_differ_per_level_and_plain_sweeps_keep_theirs(tmp_path):
    from eval.runner import input_path
    from eval.sweep import resolve_shape

    base = dict(methods=("psr", "tsdf"), shapes=("torus",), inputs=("pointcloud", "multiview"), n_points=2000)
    variants = [{}, {"noise": 0.0025}, {"noise": 0.005}, {"noise": 0.01}, {"outliers": 0.01},
                {"scan": 6, "noise": 0.0025, "outliers": 0.01}, {"depth_noise": 0.005}, {"views": 8}]
    runs = expand(Sweep(**base, variants=variants))
    assert len({r.key for r in runs}) == len(runs) == 6 + 3  # psr: 6 point-cloud variants; tsdf: {} + 2
    assert sorted(r.input_kind for r in runs).count("multiview") == 3
    plain = expand(Sweep(**base))
    assert all("corruption" not in r.inputs for r in plain)
    assert {r.key for r in plain}.isdisjoint({r.key for r in runs})
    assert plain[0].inputs == {"radius": 1.0, "metric_samples": 100_000, "n_points": 2000}  # the legacy settings
    shape = resolve_shape("torus")
    paths = [input_path(tmp_path, shape, r.input_kind, dict(r.inputs), r.seed) for r in runs]
    assert len(set(paths)) == len(runs)  # every level has its own cached input
    # ... and the clean variant reads the same cached files as the plain sweep (same content).
    assert input_path(tmp_path, shape, "pointcloud", dict(plain[0].inputs), 0) in paths


def test_sweep_variants_validation_is_one_line(tmp_path):
    base = dict(methods=("psr",), shapes=("torus",))
    for variants, match in (([{"noise": 0.5}], r"Sweep.variants\[0\]: noise"),
                            ([{}, {"noise": 0}], r"variants\[1\]: the same input as variants\[0\]"),
                            ([{"depth_noise": 0.01}], "does not run"), ({"noise": 0.01}, "a list")):
        with pytest.raises(ValueError, match=match):
            Sweep(**base, variants=variants)
    path = tmp_path / "s.yaml"
    path.write_text("methods: [psr]\nshapes: [torus]\nvariants:\n  - {outliers: 2}\n")
    with pytest.raises(ValueError, match=r"sweep file .*s.yaml: Sweep.variants\[0\]: outliers"):
        Sweep.from_yaml(path)
    s = Sweep(**base, variants=[{}, {"noise": 0.005}])
    assert Sweep.from_dict(s.to_dict()) == s
    assert s.with_overrides(["variants=[{noise: 0.01}]"]).variants == ({"noise": 0.01},)
