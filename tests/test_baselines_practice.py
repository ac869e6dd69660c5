"""The baselines' best-practice settings (issue 58): PSR density trimming, BPA radii, grid voxels, QEM budgets.

Small inputs (8000 points, PSR depth 8 at most) so the file runs in seconds. The trimming tests build their
densities by hand where the expected cut is known exactly, and run PSR itself only for the two claims that
matter in the tables: an open sheet loses its closing cap, a closed shape loses nothing.
"""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import trimesh

from baselines.base import Inputs, mean_spacing
from baselines.bpa import meshlab_auto_radius
from baselines.grid import choose_resolution
from baselines.psr import sampled_vertices, smooth_values, trim_surface
from baselines.registry import get_method
from eval.metrics import chamfer_l1_p2s
from eval.sweep import config_label

N_METRIC = 10_000


def _has(mod: str) -> bool:
    return importlib.util.find_spec(mod) is not None


needs_pymeshlab = pytest.mark.skipif(not _has("pymeshlab"), reason="pymeshlab missing")
needs_open3d = pytest.mark.skipif(not _has("open3d"), reason="open3d missing")


def _normalised(m: trimesh.Trimesh) -> trimesh.Trimesh:
    m.remove_unreferenced_vertices()
    m.apply_translation(-m.vertices.mean(0))
    m.apply_scale(1.0 / np.linalg.norm(m.vertices, axis=1).max())
    return m


def _cloud(m: trimesh.Trimesh, n: int = 8000, seed: int = 0) -> Inputs:
    pts, fi = trimesh.sample.sample_surface(m, n, seed=seed)
    return Inputs(points=pts.astype(np.float32), normals=m.face_normals[fi].astype(np.float32))


def _pole_dense_sphere(seed: int = 0) -> Inputs:
    """About 8000 points on the unit sphere, 8x denser at one pole than at the other, with exact normals."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(14_300, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    weight = 1 + 7 * (p[:, 2] + 1) / 2
    p = p[rng.random(len(p)) < weight / weight.max()]
    return Inputs(points=p.astype(np.float32), normals=p.astype(np.float32))


@pytest.fixture(scope="module")
def sphere():
    return _normalised(trimesh.creation.icosphere(4))


@pytest.fixture(scope="module")
def cap():
    """An open spherical cap (the upper half of a sphere), the simplest open sheet."""
    s = trimesh.creation.icosphere(4)
    return _normalised(trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0], process=False))


def _sheet(n: int = 21):
    """A flat (n x n)-vertex grid on [0, 1]^2 with 2 (n-1)^2 triangles wound +z."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f


# ------------------------------------------------------------------------------------------ trim_surface

def test_smooth_values_matches_a_naive_loop():
    v, f = _sheet(6)
    rng = np.random.default_rng(0)
    vals = rng.normal(size=len(v))
    want = vals.copy()
    for _ in range(3):
        sums, count = np.zeros(len(v)), np.zeros(len(v))
        for tri in f:
            for j in range(3):
                p, q = tri[j], tri[(j + 1) % 3]
                sums[p] += want[q]
                sums[q] += want[p]
                count[p] += 1
                count[q] += 1
        want = (sums + want) / (count + 1)
    np.testing.assert_allclose(smooth_values(vals, f, 3), want, rtol=1e-12)
    np.testing.assert_allclose(smooth_values(np.full(len(v), 7.5), f, 5), 7.5)  # a constant stays put


def test_trim_cuts_on_the_level_set():
    """Density rising with x: the kept part is x >= 0.305 exactly (cut vertices interpolated on the edges; the
    level runs between grid lines, so no cut vertex lands on a grid vertex and no face degenerates)."""
    v, f = _sheet(21)
    dens = 10.0 * v[:, 0]                                  # linear: smoothing on the interior leaves it alone
    kv, kf, kval, info = trim_surface(v, f, dens, 3.05, smooth=0, area_ratio=0.0)
    assert kv[:, 0].min() == pytest.approx(0.305, abs=1e-12)
    assert (kval >= 3.05 - 1e-12).all()
    area = trimesh.Trimesh(kv, kf, process=False).area
    assert area == pytest.approx(0.695, rel=1e-9)
    assert info["area_trimmed_fraction"] == pytest.approx(0.305, rel=1e-9)
    # Winding kept: every kept face still faces +z.
    n = np.cross(kv[kf[:, 1]] - kv[kf[:, 0]], kv[kf[:, 2]] - kv[kf[:, 0]])
    assert (n[:, 2] > 0).all()
    # One connected piece: the cut vertices are shared by neighbouring faces.
    assert trimesh.Trimesh(kv, kf, process=False).body_count == 1


def test_trim_drops_small_islands_and_keeps_small_holes():
    v, f = _sheet(41)
    x, y = v[:, 0], v[:, 1]
    dens = np.where(x < 0.5, 2.0, 8.0)                    # low left half, high right half
    dens[(np.abs(x - 0.2) < 0.03) & (np.abs(y - 0.5) < 0.03)] = 8.0    # a tiny high island in the low half
    dens[(np.abs(x - 0.8) < 0.03) & (np.abs(y - 0.5) < 0.03)] = 2.0    # a tiny low hole in the high half
    kv, kf, _, info = trim_surface(v, f, dens, 5.0, smooth=0, area_ratio=0.001 * 10)
    assert info["islands_removed"] == 1 and info["holes_kept"] == 1
    assert kv[:, 0].min() > 0.4                           # the island is gone
    m = trimesh.Trimesh(kv, kf, process=False)
    assert m.body_count == 1
    assert m.area == pytest.approx(0.5, abs=0.02)         # the hole came back: the right half is whole
    # Without the area rule both stay.
    _, _, _, plain = trim_surface(v, f, dens, 5.0, smooth=0, area_ratio=0.0)
    assert plain["islands_removed"] == 0 and plain["holes_kept"] == 0


def test_supported_vertices_are_not_trimmed():
    """Density rising with x, trim at 5: the vertices marked supported on the low side stay, and the cut
    between a supported vertex and an unsupported one passes through the supported one: x = 0.2 exactly, no
    new vertex, no degenerate face."""
    v, f = _sheet(21)                                       # grid step 0.05
    dens = 10.0 * v[:, 0]
    supported = v[:, 0] >= 0.2 - 1e-9                       # everything from x = 0.2 on
    kv, kf, _, info = trim_surface(v, f, dens, 5.0, smooth=0, area_ratio=0.0, supported=supported)
    x_cut = 0.2
    assert kv[:, 0].min() == pytest.approx(x_cut, abs=1e-12)
    assert len(kv) == int((v[:, 0] >= 0.2 - 1e-9).sum())    # the grid's own vertices only
    m = trimesh.Trimesh(kv, kf, process=False)
    assert (m.area_faces > 1e-6).all() and m.body_count == 1
    assert info["supported_vertices"] == int(((v[:, 0] >= 0.2 - 1e-9) & (dens <= 5.0)).sum())
    assert m.area == pytest.approx(1.0 - x_cut, rel=1e-9)
    _, _, _, plain = trim_surface(v, f, dens, 5.0, smooth=0, area_ratio=0.0)
    assert plain["area_trimmed_fraction"] == pytest.approx(0.5, rel=1e-9) and plain["supported_vertices"] == 0


def test_sampled_vertices_local_spacing_and_outliers():
    rng = np.random.default_rng(0)
    dense = np.c_[rng.random((4000, 2)), np.zeros(4000)]          # a unit square, spacing about 0.01
    sparse = np.c_[rng.random((450, 2)) + [2.0, 0.0], np.zeros(450)]  # 9x sparser beside it: spacing 3x
    outlier = np.array([[0.5, 0.5, 3.0]])                          # alone, far above
    points = np.concatenate([dense, sparse, outlier])
    verts = np.array([[0.5, 0.5, 0.005],      # on the dense square, within its spacing
                      [0.5, 0.5, 0.2],        # 20 dense spacings off it
                      [2.5, 0.5, 0.02],       # on the sparse square, within its (larger) spacing
                      [0.5, 0.5, 2.9]])       # beside the outlier: its spacing is far over 4x the median
    np.testing.assert_array_equal(sampled_vertices(verts, points, 1.0), [True, False, True, False])
    with pytest.raises(ValueError, match="trim_support"):
        sampled_vertices(verts, points, 0.0)


def test_trim_everything_or_nothing():
    v, f = _sheet(5)
    kv, kf, _, _ = trim_surface(v, f, np.full(len(v), 1.0), 5.0)
    assert len(kf) == 0 and len(kv) == 0
    kv, kf, _, info = trim_surface(v, f, np.full(len(v), 9.0), 5.0)
    assert len(kf) == len(f) and info["area_trimmed_fraction"] == 0.0


# ----------------------------------------------------------------------------------------------- PSR

@needs_pymeshlab
def test_psr_trimming_removes_the_cap_of_an_open_sheet(cap):
    # PoissonRecon's density is the octree depth the local sampling supports, whatever the `depth` asked:
    # on 8000 points it sits near 5.5 (median), as 7.7 does on the harness's 100K at depth 10. Depth 7 here
    # (trim value 4) keeps that 100K pairing's margin on the closed sphere below. Measured: untrimmed
    # 70e-3, trimmed 10.6e-3 (0.19 of the area cut); depth 8 (trim 5) cuts more of the cap (1.1e-3) but also
    # nicks the sphere (51 faces, 0.1 % of its area).
    inputs = _cloud(cap)
    untrimmed = get_method("psr").reconstruct(inputs, {"depth": 7, "trim_depth_offset": None})
    trimmed = get_method("psr").reconstruct(inputs, {"depth": 7})
    cd_u = chamfer_l1_p2s(untrimmed.mesh, cap, n=N_METRIC)
    cd_t = chamfer_l1_p2s(trimmed.mesh, cap, n=N_METRIC)
    assert cd_t < 0.25 * cd_u, (cd_t, cd_u)
    assert trimmed.info["area_trimmed_fraction"] > 0.15
    assert len(trimmed.mesh.faces) < len(untrimmed.mesh.faces)


@needs_pymeshlab
def test_psr_trimming_keeps_a_closed_sphere_whole(sphere):
    inputs = _cloud(sphere)
    untrimmed = get_method("psr").reconstruct(inputs, {"depth": 7, "trim_depth_offset": None})
    trimmed = get_method("psr").reconstruct(inputs, {"depth": 7})
    assert trimmed.info["faces_cut_or_dropped"] == 0 and trimmed.info["area_trimmed_fraction"] == 0.0
    assert len(trimmed.mesh.faces) == len(untrimmed.mesh.faces)
    m = trimmed.mesh.copy()
    m.merge_vertices()
    assert m.is_watertight
    assert chamfer_l1_p2s(trimmed.mesh, sphere, n=N_METRIC) == pytest.approx(
        chamfer_l1_p2s(untrimmed.mesh, sphere, n=N_METRIC), rel=1e-9)


@needs_pymeshlab
def test_psr_trimming_keeps_a_non_uniformly_sampled_sphere_whole():
    """8x denser at one pole than at the other: one trim value cut the sparse side off (14 % of the area, CD
    p2s 23e-3 against 0.53e-3 untrimmed, measured); the vertices the samples vouch for stay. At 8000 points
    and depth 7 the sparse pole's Poisson surface strays from the samples in places: up to 0.3 % of the area
    is still cut, depending on the draw."""
    inputs = _pole_dense_sphere()
    whole = get_method("psr").reconstruct(inputs, {"depth": 7})
    assert whole.info["area_trimmed_fraction"] < 0.005 and whole.info["supported_vertices"] > 0
    cut = get_method("psr").reconstruct(inputs, {"depth": 7, "trim_support_ratio": None})
    assert cut.info["area_trimmed_fraction"] > 0.05           # SurfaceTrimmer alone: the failure the rule is for
    gt = trimesh.creation.icosphere(5)
    assert chamfer_l1_p2s(whole.mesh, gt, n=N_METRIC) < 0.2 * chamfer_l1_p2s(cut.mesh, gt, n=N_METRIC)


def test_psr_presets_and_their_labels():
    psr = get_method("psr")
    d = psr.resolve_config({})
    assert d["depth"] == 10 and d["trim_depth_offset"] == 2.0 and d["island_area_ratio"] == 0.001
    paper = psr.resolve_config({"preset": "paper"})
    assert paper["depth"] == 8 and paper["trim_depth_offset"] is None and paper["trim_quantile"] == 0.0
    assert psr.resolve_config({"preset": "paper", "depth": 9})["depth"] == 9   # overrides after the preset
    assert config_label({"preset": "paper"}) == "preset=paper"
    with pytest.raises(ValueError, match="unknown preset"):
        psr.resolve_config({"preset": "nope"})


# ----------------------------------------------------------------------------------------------- BPA

@needs_open3d
def test_bpa_radii_scale_with_the_spacing(sphere):
    inputs = _cloud(sphere, n=4000)
    bpa = get_method("bpa")
    assert bpa.resolve_config({})["radii"] == [1.0, 2.0, 4.0, 8.0]
    res = bpa.reconstruct(inputs)
    h = mean_spacing(inputs.points.astype(np.float64))
    np.testing.assert_allclose(res.info["radii_abs"], [h, 2 * h, 4 * h, 8 * h], rtol=1e-9)
    big = Inputs(points=inputs.points * 2, normals=inputs.normals)
    np.testing.assert_allclose(bpa.reconstruct(big).info["radii_abs"], 2 * np.asarray(res.info["radii_abs"]),
                               rtol=1e-5)
    assert chamfer_l1_p2s(res.mesh, sphere, n=N_METRIC) < 3e-3


@needs_open3d
def test_bpa_radii_span_the_sparse_side_of_a_non_uniform_cloud():
    """8x denser at one pole than at the other: the mean spacing is the dense side's, and balls of up to 4
    spacings fell through the sparse side (the list before the dev split chose {1, 2, 4, 8}): 4-5 % of the
    area left out, CD p2s about 2x the four radii's (measured at draws 0-2)."""
    inputs = _pole_dense_sphere()
    bpa = get_method("bpa")
    covered = bpa.reconstruct(inputs).mesh
    short = bpa.reconstruct(inputs, {"radii": [1.0, 2.0, 4.0]}).mesh
    sphere_area = 4 * np.pi
    assert covered.area > 0.97 * sphere_area > short.area
    gt = trimesh.creation.icosphere(5)
    assert chamfer_l1_p2s(covered, gt, n=N_METRIC) < 0.7 * chamfer_l1_p2s(short, gt, n=N_METRIC)


@needs_pymeshlab
def test_bpa_meshlab_backend_uses_its_automatic_radius(sphere):
    inputs = _cloud(sphere, n=4000)
    res = get_method("bpa").reconstruct(inputs, {"backend": "meshlab"})
    pts = inputs.points.astype(np.float64)
    assert res.info["radii_abs"] == [pytest.approx(np.linalg.norm(pts.max(0) - pts.min(0)) / np.sqrt(len(pts)))]
    assert meshlab_auto_radius(pts) == pytest.approx(res.info["radii_abs"][0])
    assert len(res.mesh.faces) > 1000
    # MeshLab's radius is diag / sqrt(N) = 5 spacings here: coarse faces, 12e-3 measured.
    assert chamfer_l1_p2s(res.mesh, sphere, n=N_METRIC) < 25e-3
    with pytest.raises(ValueError, match="backend"):
        get_method("bpa").reconstruct(inputs, {"backend": "nope"})


# ---------------------------------------------------------------------------------------------- grids

def test_grid_voxel_no_larger_than_the_spacing():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(5000, 3))
    h = mean_spacing(pts)
    res, capped = choose_resolution(pts, h, None, 1.0, max_resolution=10_000)
    assert not capped and 2.0 * (1 - 1e-3) / res <= h   # extent ~2 over res cells
    assert choose_resolution(pts, h, None, 1.0, max_resolution=16) == (16, True)
    assert choose_resolution(pts, h, 48, 1.0) == (48, False)  # an explicit resolution wins
    for name in ("sdf_mc", "udf_mc"):
        cfg = get_method(name).resolve_config({})
        assert cfg["resolution"] is None and cfg["voxel_spacings"] == 1.0
    assert get_method("tsdf").resolve_config({})["resolution"] is None


# ------------------------------------------------------------------------------------ decimation (QEM)

@needs_pymeshlab
@pytest.mark.parametrize("name,config", [("psr_qem", {"depth": 7, "faces": 2000}),
                                         ("bpa_qem", {"faces": 2000})])
def test_decimation_hits_the_face_budget(name, config, sphere):
    if name == "bpa_qem" and not _has("open3d"):
        pytest.skip("open3d missing")
    res = get_method(name).reconstruct(_cloud(sphere, n=6000), config)
    assert res.info["faces_before_decimation"] > 2 * config["faces"]
    assert abs(len(res.mesh.faces) - config["faces"]) <= 0.03 * config["faces"]
    assert "decimate" in res.timings
    assert chamfer_l1_p2s(res.mesh, sphere, n=N_METRIC) < 5e-3
    # The base method's keys are checked as the base method checks them.
    with pytest.raises(ValueError):
        get_method(name).reconstruct(_cloud(sphere, n=500), {"no_such_key": 1})


@needs_pymeshlab
def test_psr_default_depth_on_a_sparse_cloud_trims_to_what_the_samples_support(sphere, cap):
    """At the default depth 10 the README's trim value 7 lies above every density 8000 points support (median
    near 5.5): uncapped it removed every face. Capped at the median - 0.7, the closed sphere stays whole and
    the open cap loses its closing surface."""
    psr = get_method("psr")
    closed = psr.reconstruct(_cloud(sphere))
    assert closed.info["faces_cut_or_dropped"] == 0 and len(closed.mesh.faces) == closed.info["faces_untrimmed"]
    sheet = psr.reconstruct(_cloud(cap))
    untrimmed = psr.reconstruct(_cloud(cap), {"trim_median_margin": None, "trim_depth_offset": None})
    assert 0.15 < sheet.info["area_trimmed_fraction"] < 0.9
    assert chamfer_l1_p2s(sheet.mesh, cap, n=N_METRIC) < 0.25 * chamfer_l1_p2s(untrimmed.mesh, cap, n=N_METRIC)
    uncapped = psr.reconstruct(_cloud(cap), {"trim_median_margin": None, "trim_support_ratio": None})
    assert len(uncapped.mesh.faces) == 0  # the failure the cap exists for
