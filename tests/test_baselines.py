"""Each baseline on one small shape, the registry, and bad inputs.

Thresholds are point-to-surface Chamfer L1 (GT-radius units) measured on this machine with these settings,
with about 2x margin: psr 1.4e-3, sdf_mc 1.7e-3, bpa 1.2e-3, alpha_wrap 4.5e-3 (alpha = 5 mean spacings
rounds off detail, and the wrap sits `offset` outside the points), udf_mc 2.1e-3 single-sheet / ~8e-2 double
shell; tsdf 1.2e-2 on the analytic sphere and 5e-3 on the captured torus (coarse 64-96 px images and 96-128
voxel grids).
"""
from __future__ import annotations

import importlib.util
import math
import types

import numpy as np
import pytest
import trimesh

from baselines.base import Inputs, MemoryProbe, Method, Result
from baselines.registry import METHODS, get_method
from eval.metrics import chamfer_l1_p2s

N_METRIC = 10_000


def _has(mod: str) -> bool:
    return importlib.util.find_spec(mod) is not None


@pytest.fixture(scope="module")
def torus():
    """A torus normalised to max vertex norm 1 (vertex mean is already 0)."""
    m = trimesh.creation.torus(0.65, 0.3, major_sections=48, minor_sections=24)
    m.apply_scale(1.0 / np.linalg.norm(m.vertices, axis=1).max())
    return m


@pytest.fixture(scope="module")
def cloud(torus):
    pts, fi = trimesh.sample.sample_surface(torus, 8000, seed=0)
    return Inputs(points=pts.astype(np.float32), normals=torus.face_normals[fi].astype(np.float32), seed=0)


CASES = [
    ("psr", {"depth": 6}, 3e-3, "pymeshlab"),
    ("sdf_mc", {"resolution": 48}, 3.5e-3, "skimage"),
    ("bpa", {}, 2.5e-3, "open3d"),
    ("alpha_wrap", {}, 9e-3, "CGAL"),
    ("udf_mc", {"resolution": 48}, 4e-3, "skimage"),
]


@pytest.mark.parametrize("name,config,limit,dep", CASES, ids=[c[0] for c in CASES])
def test_pointcloud_baseline(name, config, limit, dep, torus, cloud):
    if not _has(dep):
        pytest.skip(f"{dep} not installed")
    method = get_method(name)
    assert method.input_kind == "pointcloud"
    res = method.reconstruct(cloud, config)
    assert isinstance(res, Result)
    assert len(res.mesh.faces) > 100
    assert np.isfinite(res.mesh.vertices).all()
    assert "total" in res.timings and all(v >= 0 for v in res.timings.values())
    assert res.peak_memory_mb >= 0 and math.isfinite(res.peak_memory_mb)
    cd = chamfer_l1_p2s(res.mesh, torus, n=N_METRIC)
    assert cd < limit, f"{name}: p2s CD {cd:.3e} >= {limit:.1e}"


def test_closed_methods_are_watertight_and_outward(torus, cloud):
    for name, cfg in (("psr", {"depth": 6}), ("sdf_mc", {"resolution": 48}), ("alpha_wrap", {})):
        if name == "alpha_wrap" and not _has("CGAL"):
            continue
        m = get_method(name).reconstruct(cloud, cfg).mesh
        m.merge_vertices()
        assert m.is_watertight, name
        # Outward normals, one shell: the enclosed volume is close to the torus's (not negative, not ~0 as
        # when a wrap slips inside and adds an inner shell).
        assert m.volume == pytest.approx(torus.volume, rel=0.15), name


def test_udf_single_sheet_beats_double_shell(torus, cloud):
    method = get_method("udf_mc")
    single = method.reconstruct(cloud, {"resolution": 48})
    double = method.reconstruct(cloud, {"resolution": 48, "single_sheet": False})
    assert single.info["single_sheet"] and not double.info["single_sheet"]
    cd_single = chamfer_l1_p2s(single.mesh, torus, n=N_METRIC)
    cd_double = chamfer_l1_p2s(double.mesh, torus, n=N_METRIC)
    # The double shell sits at +-iso around the surface: its p2s CD is about 2 * iso.
    assert cd_double == pytest.approx(2 * double.info["iso"], rel=0.3)
    assert cd_single < cd_double / 5
    # Without normals there is no side to keep: the shell stays double.
    no_normals = Inputs(points=cloud.points, normals=None)
    assert not method.reconstruct(no_normals, {"resolution": 48}).info["single_sheet"]

def test_udf_single_sheet_has_no_two_vertices_on_one_point():
    """Where a sheet meets a box, the projection sends both tube crossings of a grid line to one point; the
    output must weld them, so its topology by vertex id is what a reader merging by position sees."""
    from datasets.meshes import merge_vertices
    from datasets.normalize import normalize
    from datasets.sampling import sample_points
    from datasets.synthetic import generate
    from eval.metrics import topology

    gt = normalize(generate("flag_box"), radius=1.0)[0]
    pts, nrm = sample_points(gt, 8000, 0)
    mesh = get_method("udf_mc").reconstruct(Inputs(points=pts, normals=nrm), {"resolution": 96}).mesh
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    assert len(np.unique(f)) == len(v)
    assert len(np.unique(v, axis=0)) == len(v)
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f)
    by_id, by_position = topology(v, f), topology(*merge_vertices(v, f))
    for key in ("non_manifold_edges", "non_manifold_vertices", "boundary_edges", "components"):
        assert by_id[key] == by_position[key], key



# --------------------------------------------------------------------------------------------- TSDF

def _look_at(eye):
    """OpenGL world-to-camera for a camera at `eye` looking at the origin, +Y up."""
    z = eye / np.linalg.norm(eye)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z])
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def _sphere_views(center, radius, views=24, res=64, fov=60.0, distance=2.0):
    """A MultiView-like capture of a sphere, ray-cast analytically with the capture's pixel conventions."""
    center = np.asarray(center, float)
    t = math.tan(math.radians(fov) / 2)
    c = (np.arange(res) + 0.5) / res
    d = np.stack(np.broadcast_arrays((2 * c - 1)[None, :] * t, (1 - 2 * c)[:, None] * t, -np.ones((res, res))), -1)
    w2c, depth = [], []
    golden = math.pi * (3 - math.sqrt(5))
    for k in range(views):
        yk = 1 - 2 * (k + 0.5) / views
        r = math.sqrt(1 - yk * yk)
        eye = distance * np.array([r * math.cos(golden * k), yk, r * math.sin(golden * k)])
        m = _look_at(eye)
        dirs = d @ m[:3, :3]                            # camera -> world (rotation transpose)
        u = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
        oc = eye - center
        b = u @ oc
        disc = b * b - (oc @ oc - radius * radius)
        s = -b - np.sqrt(np.maximum(disc, 0))
        hit = (disc > 0) & (s > 0)
        # distance along the ray -> distance along the view axis (d has z = -1)
        depth.append(np.where(hit, s / np.linalg.norm(d, axis=-1), 0.0).astype(np.float32))
        w2c.append(m)
    depth = np.stack(depth)
    proj = np.zeros((4, 4))
    proj[0, 0] = proj[1, 1] = 1 / t
    return types.SimpleNamespace(depth=depth, mask=depth > 0, diffuse=(depth > 0).astype(np.float32),
                                 world_to_camera=np.stack(w2c), projection=proj, fov_y_degrees=fov,
                                 resolution=res)


@pytest.mark.skipif(not _has("open3d"), reason="open3d not installed")
def test_tsdf_analytic_sphere():
    # An off-centre sphere: a wrong axis flip or principal point would smear the fused surface.
    center, radius = np.array([0.3, 0.2, -0.1]), 0.5
    gt = trimesh.creation.icosphere(4, radius=radius)
    gt.apply_translation(center)
    views = _sphere_views(center, radius)
    res = get_method("tsdf").reconstruct(Inputs(views=views), {"resolution": 96})
    assert len(res.mesh.faces) > 1000
    r = np.linalg.norm(res.mesh.vertices - center, axis=1)
    assert abs(np.median(r) - radius) < 0.01
    # Measured 1.17e-2 in the GT frame (radius 0.5 scaled to 1; voxel 0.023 in world units).
    assert chamfer_l1_p2s(res.mesh, gt, n=N_METRIC) < 2.5e-2


@pytest.mark.skipif(not (_has("open3d") and _has("pyrender")), reason="open3d or pyrender not installed")
def test_tsdf_real_capture(torus):
    try:
        from datasets.capture import capture

        views = capture(torus, views=16, resolution=96)
    except (ImportError, RuntimeError, OSError) as exc:  # no OpenGL platform on this machine
        pytest.skip(f"capture unavailable: {exc}")
    res = get_method("tsdf").reconstruct(Inputs(views=views), {"resolution": 128})
    assert chamfer_l1_p2s(res.mesh, torus, n=N_METRIC) < 1.2e-2


# ------------------------------------------------------------------------------------ bad inputs, API

def test_registry():
    assert set(METHODS) >= {"psr", "sdf_mc", "bpa", "alpha_wrap", "udf_mc", "tsdf"}
    assert all(isinstance(m, Method) and m.name == k for k, m in METHODS.items())
    assert get_method("tsdf").input_kind == "multiview"
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        get_method("nope")


def test_bad_inputs(cloud):
    psr = get_method("psr")
    with pytest.raises(ValueError, match="normals"):
        psr.reconstruct(Inputs(points=cloud.points))
    with pytest.raises(ValueError, match="at least"):
        get_method("bpa").reconstruct(Inputs(points=cloud.points[:5], normals=cloud.normals[:5]))
    bad = cloud.points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        get_method("sdf_mc").reconstruct(Inputs(points=bad, normals=cloud.normals))
    with pytest.raises(ValueError, match="shape"):
        get_method("udf_mc").reconstruct(Inputs(points=cloud.points[:, :2]))
    with pytest.raises(ValueError, match="point cloud"):
        get_method("udf_mc").reconstruct(Inputs())
    with pytest.raises(ValueError, match="unknown config keys"):
        psr.reconstruct(cloud, {"dpeth": 6})
    with pytest.raises(ValueError, match="multi-view"):
        get_method("tsdf").reconstruct(cloud)
    with pytest.raises(TypeError):
        psr.reconstruct(cloud.points)


@pytest.mark.skipif(not _has("open3d"), reason="open3d not installed")
def test_tsdf_outside_every_camera():
    views = _sphere_views([0, 0, 0], 0.5, views=2, res=16)
    views.depth[:] = 0
    with pytest.raises(ValueError, match="outside every camera"):
        get_method("tsdf").reconstruct(Inputs(views=views))


def test_memory_probe_sees_native_allocation():
    with MemoryProbe() as m:
        a = np.ones(40 * 2**20 // 8)  # 40 MiB, touched
        del a
    assert m.peak_mb > 30, (m.method, m.peak_mb)


@pytest.fixture(scope="module")
def bowl():
    """An open hemisphere in the GT frame, with 8000 oriented samples."""
    s = trimesh.creation.icosphere(4)
    m = trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0], process=False)
    m.remove_unreferenced_vertices()
    m.apply_translation(-m.vertices.mean(0))
    m.apply_scale(1.0 / np.linalg.norm(m.vertices, axis=1).max())
    pts, fi = trimesh.sample.sample_surface(m, 8000, seed=0)
    return m, Inputs(points=pts.astype(np.float32), normals=m.face_normals[fi].astype(np.float32))


@pytest.mark.skipif(not (_has("pymeshlab") and _has("skimage")), reason="pymeshlab or scikit-image missing")
def test_open_surface(bowl):
    gt, inputs = bowl
    # Measured: udf_mc (single sheet) 0.7e-3; psr closes the bowl into a blob (70e-3), trimming its
    # low-density vertices removes most of the blob (12e-3 at quantile 0.3).
    udf = get_method("udf_mc").reconstruct(inputs, {"resolution": 48})
    assert chamfer_l1_p2s(udf.mesh, gt, n=N_METRIC) < 2e-3
    closed = get_method("psr").reconstruct(inputs, {"depth": 6, "trim_depth_offset": None})
    trimmed = get_method("psr").reconstruct(inputs, {"depth": 6, "trim_depth_offset": None, "trim_quantile": 0.3})
    assert len(trimmed.mesh.faces) < len(closed.mesh.faces)
    assert chamfer_l1_p2s(trimmed.mesh, gt, n=N_METRIC) < 0.5 * chamfer_l1_p2s(closed.mesh, gt, n=N_METRIC)
