"""Metrics: exact closest points against brute force, Chamfer sanity cases, RE/FP, mesh statistics, CLI."""
from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import trimesh

from eval.closest_point import (TriangleIndex, closest_point, closest_point_naive, make_index, point_triangle,
                                point_triangle_regions)
from eval.metrics import (chamfer_l1_p2s, chamfer_l1_samples, compute_metrics, f_score, mesh_stats,
                          normal_consistency, re_fp)


def _square(subdiv: int = 0) -> trimesh.Trimesh:
    """The open square [-1, 1]^2 at z = 0 (two triangles, optionally subdivided)."""
    m = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    for _ in range(subdiv):
        m = m.subdivide()
    return m


def _mixed_sizes() -> trimesh.Trimesh:
    """Huge and tiny triangles together, plus degenerate ones (a repeated vertex, three collinear corners)."""
    box = trimesh.creation.box(extents=[2, 2, 2])
    small = trimesh.creation.icosphere(2, radius=0.1)
    small.apply_translation([0.6, 0.0, 0.0])
    torus = trimesh.creation.torus(0.5, 0.15, major_sections=12, minor_sections=6)
    m = trimesh.util.concatenate([box, small, torus])
    v = np.vstack([m.vertices, [[0.0, 0.0, 0.5], [0.1, 0.0, 0.5], [0.3, 0.0, 0.5]]])
    n = len(m.vertices)
    f = np.vstack([m.faces, [[n, n + 1, n + 2], [n, n, n + 1]]])
    return trimesh.Trimesh(v, f, process=False)


# --------------------------------------------------------------------------------------- closest point

def test_kernels_agree_including_degenerate(rng):
    p = 5000
    a, b, c, q = (rng.normal(size=(p, 3)) for _ in range(4))
    b[:500] = a[:500]                                            # repeated corner
    c[500:1000] = a[500:1000] + 2.0 * (b[500:1000] - a[500:1000])  # collinear corners
    a[1000:1500] = b[1000:1500] = c[1000:1500]                   # a point
    d1, c1 = point_triangle(q, a, b, c)
    d2, c2 = point_triangle_regions(q, a, b, c)
    # Two independent kernels (edge/plane tests vs Voronoi regions); float64 round-off only.
    np.testing.assert_allclose(np.sqrt(d1), np.sqrt(d2), atol=1e-12)
    np.testing.assert_allclose(c1, c2, atol=1e-9)


@pytest.mark.parametrize("k", [1, 3, 16])
def test_closest_point_matches_brute_force(rng, k):
    m = _mixed_sizes()
    near = m.vertices[m.faces[:, 0]] + 1e-4 * rng.normal(size=(len(m.faces), 3))
    q = np.vstack([rng.uniform(-1.5, 1.5, (1500, 3)), near])
    d, f, c = closest_point(q, m.vertices, m.faces, k=k)
    dn, fn, cn = closest_point_naive(q, m.vertices, m.faces)
    np.testing.assert_allclose(d, dn, atol=1e-12)
    np.testing.assert_allclose(c, cn, atol=1e-9)
    # The face may differ only at ties (equal distance).
    tri = m.vertices[m.faces[f]]
    dd, _ = point_triangle(q, tri[:, 0], tri[:, 1], tri[:, 2])
    np.testing.assert_allclose(np.sqrt(dd), dn, atol=1e-12)


def test_open3d_backend_matches_brute_force(rng):
    pytest.importorskip("open3d")
    m = _mixed_sizes()
    q = rng.uniform(-1.5, 1.5, (3000, 3))
    d, f, c = make_index(m.vertices, m.faces, "open3d").query(q)
    dn, _, cn = closest_point_naive(q, m.vertices, m.faces)
    # float32 coordinates inside open3d: errors of a few 1e-8 on a mesh of size ~2.
    np.testing.assert_allclose(d, dn, atol=1e-6)
    np.testing.assert_allclose(c, cn, atol=1e-6)
    assert make_index(m.vertices, m.faces, "numpy").query(q)[0] == pytest.approx(dn, abs=1e-12)
    with pytest.raises(ValueError, match="backend"):
        make_index(m.vertices, m.faces, "gpu")


def test_closest_point_matches_trimesh(rng):
    pytest.importorskip("rtree")
    m = trimesh.creation.torus(0.6, 0.2, major_sections=10, minor_sections=6)
    q = rng.uniform(-1, 1, (300, 3))
    ct, dt, _ = trimesh.proximity.closest_point(m, q)
    d, _, c = closest_point(q, m.vertices, m.faces)
    np.testing.assert_allclose(d, dt, atol=1e-10)
    np.testing.assert_allclose(c, ct, atol=1e-8)


def test_closest_point_edges():
    m = _square()
    d, f, c = closest_point(np.array([[0.2, 0.3, 0.5], [3.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), m.vertices, m.faces)
    np.testing.assert_allclose(d, [0.5, 2.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(c[1], [1, 0, 0])
    d, _, _ = closest_point(np.zeros((0, 3)), m.vertices, m.faces)
    assert d.shape == (0,)
    one = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False)
    d, f, _ = TriangleIndex(one.vertices, one.faces).query(np.array([[1.0, 1.0, 0.0]]), k=8)
    assert f[0] == 0 and d[0] == pytest.approx(math.sqrt(0.5))
    with pytest.raises(ValueError, match="no faces"):
        TriangleIndex(np.zeros((3, 3)), np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="NaN"):
        TriangleIndex(m.vertices, m.faces).query(np.array([[np.nan, 0, 0]]))


# -------------------------------------------------------------------------------------------- chamfer

@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(3)


def test_self_distance(sphere):
    assert chamfer_l1_p2s(sphere, sphere, n=5000, backend="numpy") < 1e-12
    assert chamfer_l1_p2s(sphere, sphere, n=5000) < 1e-6  # open3d's float32 when installed
    floors = [chamfer_l1_samples(sphere, sphere, n=n) for n in (1000, 10_000)]
    # The sample CD has a floor > 0 that shrinks like 1/sqrt(n) (10x samples: about 3.2x smaller).
    assert floors[0] > 1e-2 and 2.0 < floors[0] / floors[1] < 4.5


def test_translated_square_gives_2d():
    gt = _square(1)
    d = 0.01
    pred = gt.copy()
    pred.apply_translation([0, 0, d])
    # GT frame: max vertex norm sqrt(2) -> 1, so the offset d becomes d / sqrt(2) each way.
    assert chamfer_l1_p2s(pred, gt, n=4000, backend="numpy") == pytest.approx(2 * d / math.sqrt(2), rel=1e-9)
    assert chamfer_l1_p2s(pred, gt, n=4000) == pytest.approx(2 * d / math.sqrt(2), rel=1e-4)


def test_translated_sphere(sphere):
    d = 0.01
    pred = sphere.copy()
    pred.apply_translation([d, 0, 0])
    # Each way the mean distance is d * mean|cos| = d / 2 on a sphere, so the sum is about d.
    assert chamfer_l1_p2s(pred, sphere, n=20_000) == pytest.approx(d, rel=0.1)


def test_gt_frame_invariance(sphere):
    pred = sphere.copy()
    pred.apply_scale(0.9)
    base = compute_metrics(pred, sphere, n=3000, self_intersections=False)
    big_gt, big_pred = sphere.copy(), pred.copy()
    for m in (big_gt, big_pred):
        m.apply_scale(7.0)
        m.apply_translation([3.0, -2.0, 5.0])
    moved = compute_metrics(big_pred, big_gt, n=3000, self_intersections=False)
    for key in ("cd_l1", "cd_p2s", "cd_l2_ndc", "f_score", "normal_consistency"):
        assert moved[key] == pytest.approx(base[key], rel=1e-6, abs=1e-12), key
    # The GT's transform is used for both: a 0.9 copy of the unit sphere is 0.1 away in each direction.
    assert base["cd_p2s"] == pytest.approx(0.2, rel=0.02)
    swapped = compute_metrics(sphere, pred, n=3000, self_intersections=False)
    assert swapped["cd_p2s"] == pytest.approx(0.2 / 0.9, rel=0.02)


def test_ndc_metrics(sphere):
    assert f_score(sphere, sphere, n=20_000) > 0.3  # identical meshes: limited by the sampling floor
    far = sphere.copy()
    far.apply_translation([0.5, 0, 0])
    assert f_score(far, sphere, n=5000) < 0.05
    assert normal_consistency(sphere, sphere, n=5000) > 0.99
    m = compute_metrics(far, sphere, n=5000, self_intersections=False)
    assert 0 < m["cd_l2_ndc"] and 0 <= m["precision"] <= 1 and 0 <= m["recall"] <= 1


def test_empty_prediction_is_flagged(sphere):
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)  # zero area
    for pred in (empty, flat):
        m = compute_metrics(pred, sphere, n=1000)
        assert m["empty"] is True
        assert math.isinf(m["cd_p2s"]) and math.isinf(m["cd_l1"]) and m["f_score"] == 0.0
        assert math.isnan(m["normal_consistency"])
    assert compute_metrics(empty, sphere, n=1000)["faces"] == 0
    assert math.isinf(chamfer_l1_p2s(empty, sphere, n=100))


def test_bad_meshes(sphere):
    bad = sphere.copy()
    bad.vertices[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        compute_metrics(bad, sphere, n=100)
    with pytest.raises(ValueError, match="GT"):
        compute_metrics(sphere, trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), n=100)


def test_compute_metrics_keys(sphere):
    m = compute_metrics(sphere, sphere, n=2000)
    for key in ("empty", "n_samples", "seed", "cd_l1", "cd_p2s", "cd_l2_ndc", "f_score", "normal_consistency",
                "vertices", "faces", "boundary_edges", "non_manifold_edges", "components", "watertight",
                "self_intersecting_faces", "aspect_ratio_mean", "aspect_ratio_max", "angles_below_10_pct"):
        assert key in m, key
    assert m["cd_p2s"] == pytest.approx(0.0, abs=1e-6)


# ---------------------------------------------------------------------------------------------- RE/FP

def test_re_fp_hand_made():
    gt = np.array([[0, 1, 2], [0, 2, 3], [2, 1, 0]])            # the reversed duplicate counts once
    pred = np.array([[2, 0, 1], [0, 1, 3], [0, 1, 4], [1, 2, 0]])  # match, false, off-GT vertex 4, match again
    r = re_fp(pred, gt, n_gt_vertices=4)
    assert r == {"re": 0.5, "fp": 0.5, "gt_faces": 2, "on_gt": 2, "recovered": 1, "false": 1}
    assert re_fp(gt, gt)["re"] == 1.0 and re_fp(gt, gt)["fp"] == 0.0
    empty = re_fp(np.zeros((0, 3), int), gt)
    assert empty["re"] == 0.0 and empty["fp"] == 0.0 and empty["on_gt"] == 0
    with pytest.raises(ValueError):
        re_fp(pred, np.zeros((0, 3), int))


def test_re_fp_in_compute_metrics():
    gt = trimesh.creation.icosphere(1)
    extra = [[0, 1, len(gt.vertices)]]  # a face on a non-GT vertex: ignored by RE/FP
    pred = trimesh.Trimesh(np.vstack([gt.vertices, [[0, 0, 0]]]), np.vstack([gt.faces[:-4], extra]), process=False)
    m = compute_metrics(pred, gt, n=500, self_intersections=False, re_fp_vertices=len(gt.vertices))
    assert m["re"] == pytest.approx((len(gt.faces) - 4) / len(gt.faces)) and m["fp"] == 0.0


# ------------------------------------------------------------------------------------------ mesh stats

def test_mesh_stats_cube():
    s = mesh_stats(trimesh.creation.box())
    assert (s["vertices"], s["faces"], s["edges"]) == (8, 12, 18)
    assert s["boundary_edges"] == 0 and s["non_manifold_edges"] == 0 and s["components"] == 1
    assert s["watertight"] is True and s["self_intersecting_faces"] in (0, -1)
    # Right isosceles triangles: R / (2 r) = 1 + sqrt(2) / 2 ... exactly (sqrt(2) + 1) / 2 * sqrt(2).
    a, b, c = 1.0, 1.0, math.sqrt(2)
    area = 0.5
    assert s["aspect_ratio_mean"] == pytest.approx(a * b * c * (a + b + c) / (16 * area * area))
    assert s["angles_below_10_pct"] == 0.0


def test_mesh_stats_open_square_and_fan():
    s = mesh_stats(_square())
    assert s["boundary_edges"] == 4 and s["watertight"] is False and s["components"] == 1
    fan = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], [[0, 1, 2], [0, 1, 3], [0, 1, 4]],
                          process=False)
    s = mesh_stats(fan)
    assert s["non_manifold_edges"] == 1 and s["boundary_edges"] == 6
    thin = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0.5, 0.01, 0]], [[0, 1, 2]], process=False)
    s = mesh_stats(thin)
    assert s["angles_below_10_pct"] == pytest.approx(200 / 3) and s["aspect_ratio_max"] > 10
    s = mesh_stats(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)))
    assert s["faces"] == 0 and math.isnan(s["aspect_ratio_mean"])


def test_mesh_stats_self_intersecting_pair():
    pytest.importorskip("pymeshlab")
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, -0.5], [0.3, 0.3, 0.5], [0.9, 0.9, 0.5]]
    s = mesh_stats(trimesh.Trimesh(v, [[0, 1, 2], [3, 4, 5]], process=False))
    assert s["self_intersecting_faces"] == 2 and s["components"] == 2
    assert mesh_stats(trimesh.creation.icosphere(2))["self_intersecting_faces"] == 0


# ------------------------------------------------------------------------------------------------- CLI

def _cli(argv, capsys):
    from eval.cli import main

    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def test_cli_metrics(tmp_path, capsys, sphere):
    gt, pred = tmp_path / "gt.ply", tmp_path / "pred.obj"
    sphere.export(gt)
    moved = sphere.copy()
    moved.apply_translation([0.01, 0, 0])
    moved.export(pred)
    rc, out, err = _cli(["metrics", str(pred), str(gt), "--samples", "2000"], capsys)
    assert rc == 0, err
    assert "cd_p2s" in out and "watertight" in out and "frame:" in out
    rc, out, err = _cli(["metrics", str(pred), str(gt), "--samples", "2000", "--json"], capsys)
    assert rc == 0, err
    data = json.loads(out)
    assert data["cd_p2s"] == pytest.approx(0.01, rel=0.2) and data["faces"] == len(sphere.faces)


def test_cli_metrics_bad_inputs(tmp_path, capsys, sphere):
    gt = tmp_path / "gt.ply"
    sphere.export(gt)
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\n")
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat nonsense\n\x00\x01")
    cases = [(tmp_path / "missing.ply", gt), (empty, gt), (nan, gt), (garbage, gt), (gt, empty)]
    for pred, g in cases:
        rc, out, err = _cli(["metrics", str(pred), str(g)], capsys)
        assert rc == 2, (pred, out, err)
        assert err.count("\n") == 1 and err.startswith("dmesh metrics: error:"), err
    rc, _, err = _cli(["metrics", str(gt), str(gt), "--samples", "0"], capsys)
    assert rc == 2 and "--samples" in err


def test_grid_of_small_cases(rng):
    """Closest points on tiny meshes of every size from 1 to 4 faces, with queries on, near and far."""
    base = rng.normal(size=(6, 3))
    faces = np.array(list(itertools.combinations(range(6), 3)))[:4]
    for f in range(1, 5):
        q = np.vstack([base, rng.normal(size=(50, 3)) * 3, base[faces[:f]].mean(1)])
        for k in (1, 2, 8):
            d, _, _ = closest_point(q, base, faces[:f], k=k)
            dn, _, _ = closest_point_naive(q, base, faces[:f])
            np.testing.assert_allclose(d, dn, atol=1e-12)


# ------------------------------------------------------------------------------------ independent streams

def _faces_of(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """The face each surface point lies on (its closest face)."""
    return trimesh.proximity.closest_point(mesh, points)[2]


@pytest.mark.parametrize("input_seed", [0, 1, 2, 3])
def test_metric_samples_share_no_draw_with_the_input(input_seed):
    """The i-th metric sample of either side lies on the i-th input point's face no more often than chance
    (sum of squared face probabilities), for the runner's metric seed 0 and for the input's own seed. The GT
    side once drew from the input's own stream: the same face every time (the prediction side, seed + 1,
    repeated the input of seed + 1)."""
    from datasets.sampling import sample_points
    from eval.metrics import sample

    mesh = trimesh.creation.icosphere(2)
    n = 4000
    pts, _ = sample_points(mesh, n, seed=input_seed)
    on = _faces_of(mesh, pts.astype(np.float64))
    area = mesh.area_faces / mesh.area
    chance = float((area ** 2).sum())  # about 1 / 320 on the sphere
    for metric_seed in {0, input_seed, max(input_seed - 1, 0)}:
        for side in ("gt", "pred"):
            _, face, _ = sample(np.asarray(mesh.vertices), np.asarray(mesh.faces), n, metric_seed, side)
            same = float((face == on).mean())
            assert same < 4 * chance + 0.005, (metric_seed, side, same, chance)


def test_metric_sides_differ_and_repeat():
    from eval.metrics import sample

    mesh = trimesh.creation.icosphere(1)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    gt, _, _ = sample(v, f, 100, 5, "gt")
    assert np.array_equal(gt, sample(v, f, 100, 5, "gt")[0])       # the same seed, the same samples
    assert not np.allclose(gt, sample(v, f, 100, 5, "pred")[0])    # the two sides apart
    assert not np.allclose(gt, sample(v, f, 100, 6, "gt")[0])      # and the seeds
