"""datasets.capture and `dmesh capture`: the camera rig, images against an independent ray cast, I/O, CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from datasets import capture as cap
from datasets import synthetic


_NO_GL = cap.gl_problem()
needs_gl = pytest.mark.skipif(_NO_GL is not None, reason=f"no headless OpenGL (OSMesa/EGL): {_NO_GL}")


# ------------------------------------------------------------------------------------------------ cameras

def test_camera_rig_layout():
    w2c, angles = cap.camera_rig(64, distance=2.0)
    assert w2c.shape == (64, 4, 4) and w2c.dtype == np.float64
    elev = np.unique(np.round(angles[:, 0], 9))
    assert len(elev) == 8 and elev.min() == pytest.approx(-70) and elev.max() == pytest.approx(70)
    assert len(np.unique(np.round(angles[:, 1], 9))) == 8
    c2w = np.linalg.inv(w2c)
    eyes = c2w[:, :3, 3]
    assert np.allclose(np.linalg.norm(eyes, axis=1), 2.0)
    # Rigid, and the origin is straight ahead (on the camera's -Z axis).
    assert np.allclose(np.einsum("vij,vkj->vik", w2c[:, :3, :3], w2c[:, :3, :3]), np.eye(3))
    assert np.allclose(np.linalg.det(w2c[:, :3, :3]), 1.0)
    origin_cam = w2c[:, :3, 3]
    assert np.allclose(origin_cam, [0.0, 0.0, -2.0])
    assert cap.camera_rig(4)[0].shape == (4, 4, 4)
    assert cap.camera_rig(7)[0].shape == (7, 4, 4)
    assert not np.allclose(cap.camera_rig(8, seed=1)[0], cap.camera_rig(8, seed=0)[0])
    with pytest.raises(ValueError):
        cap.camera_rig(0)


# ------------------------------------------------------------------------------------------------ capture

@pytest.fixture(scope="module")
def torus():
    return synthetic.generate("torus", sections=24)


@needs_gl
def test_capture_is_deterministic(torus):
    a = cap.capture(torus, views=4, resolution=48)
    b = cap.capture(torus, views=4, resolution=48)
    for k in ("diffuse", "depth", "mask", "world_to_camera", "projection"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert a.diffuse.shape == (4, 48, 48) and a.diffuse.dtype == np.float32
    assert a.depth.dtype == np.float32 and a.mask.dtype == bool
    assert a.world_to_camera.shape == (4, 4, 4) and a.projection.shape == (4, 4)
    assert a.fov_y_degrees == cap.FOV_Y_DEGREES and a.resolution == 48


@needs_gl
def test_sphere_depth_mask_and_diffuse():
    r, dist, res = 0.6, 2.0, 65  # odd resolution: the centre pixel's ray is the optical axis
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=r)
    mv = cap.capture(sphere, views=4, resolution=res, distance=dist)
    c = res // 2
    t = np.tan(np.radians(mv.fov_y_degrees) / 2)
    pixel = 2 * t * (dist - r) / res  # pixel footprint at the sphere's front
    assert np.allclose(mv.depth[:, c, c], dist - r, atol=pixel)
    # Diffuse near 1 facing the camera; 0 on the background; depth 0 exactly off the mask.
    assert (mv.diffuse[:, c, c] > 0.99).all()
    assert (mv.diffuse[~mv.mask] == 0).all() and (mv.depth[~mv.mask] == 0).all()
    assert (mv.depth[mv.mask] > dist - r - 1e-3).all() and (mv.diffuse <= 1).all()
    # The silhouette is a disc of radius tan(asin(r / d)) / tan(fov / 2) half-widths.
    radius_px = np.tan(np.arcsin(r / dist)) / t * res / 2
    assert mv.mask.sum(axis=(1, 2)) == pytest.approx(np.pi * radius_px ** 2, rel=0.03)


def _ray_cast_view(mesh, mv, k):
    """Reference: trimesh ray casting through each pixel centre of view k (first hit)."""
    c2w = np.linalg.inv(mv.world_to_camera[k])
    d_cam = cap.pixel_rays(mv.resolution, mv.resolution, mv.fov_y_degrees, ndc=True).reshape(-1, 3)
    d_world = d_cam @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], d_world.shape)
    locs, ray_idx, tri_idx = mesh.ray.intersects_location(origins, d_world, multiple_hits=True)
    depth = np.full(len(d_cam), np.inf)
    face = np.full(len(d_cam), -1)
    t = -(locs - c2w[:3, 3]) @ c2w[:3, 2]  # distance along the view axis (-z_cam)
    order = np.argsort(-t)  # write farthest first so the nearest hit stays
    depth[ray_idx[order]] = t[order]
    face[ray_idx[order]] = tri_idx[order]
    n = mesh.face_normals[np.maximum(face, 0)]
    unit = d_world / np.linalg.norm(d_world, axis=1, keepdims=True)
    diffuse = np.where(face >= 0, np.abs(np.einsum("ij,ij->i", n, unit)), 0.0)
    shape = (mv.resolution, mv.resolution)
    return face.reshape(shape) >= 0, np.where(face >= 0, depth, 0).reshape(shape), diffuse.reshape(shape)


@needs_gl
def test_capture_matches_independent_ray_cast():
    mesh = synthetic.generate("trefoil", samples=60, sides=8)  # self-occluding, many silhouettes
    mv = cap.capture(mesh, views=4, resolution=40)
    for k in (0, 3):
        mask, depth, diffuse = _ray_cast_view(mesh, mv, k)
        both = mask & mv.mask[k]
        # Pixel centres exactly on a silhouette edge may go either way; almost all must agree.
        assert (mask == mv.mask[k]).mean() > 0.99
        close = np.abs(depth[both] - mv.depth[k][both]) < 1e-4
        assert close.mean() > 0.99
        # Where both hit the same surface point, diffuse follows |n . v| (float32 rounding only); a ray
        # through a crease edge may take either face's normal, hence "almost all".
        same = np.abs(diffuse[both][close] - mv.diffuse[k][both][close]) < 1e-5
        assert same.mean() > 0.98


@needs_gl
def test_capture_bad_meshes():
    far = trimesh.creation.icosphere(subdivisions=1)
    far.apply_translation([100.0, 0, 0])
    with pytest.raises(ValueError, match="no camera sees the mesh") as info:
        cap.capture(far, views=4, resolution=16)
    assert "\n" not in str(info.value)
    nan = trimesh.creation.box()
    nan.vertices[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        cap.capture(nan, views=4, resolution=16)
    with pytest.raises(ValueError, match="without faces"):
        cap.capture(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int), process=False), views=4)


@needs_gl
def test_save_load_round_trip(tmp_path, torus):
    mv = cap.capture(torus, views=4, resolution=32)
    out = mv.save(tmp_path / "cap")
    back = cap.MultiView.load(out)
    for k in ("diffuse", "depth", "mask", "world_to_camera", "projection"):
        a, b = getattr(mv, k), getattr(back, k)
        assert a.dtype == b.dtype and np.array_equal(a, b), k
    assert back.fov_y_degrees == mv.fov_y_degrees and back.resolution == mv.resolution
    cams = json.loads((out / "cameras.json").read_text())
    assert len(cams["views"]) == 4 and np.allclose(cams["views"][1]["world_to_camera"], mv.world_to_camera[1])
    assert len(list((out / "images").glob("diffuse_*.png"))) == 4
    assert (out / "diffuse_grid.png").exists()
    with pytest.raises(FileNotFoundError):
        cap.MultiView.load(tmp_path / "nothing")


@needs_gl
def test_capture_reports_progress(torus):
    calls = []
    cap.capture(torus, views=4, resolution=16, callback=lambda done, total: calls.append((done, total)))
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]


# ------------------------------------------------------------------------------------------------ CLI

@needs_gl
def test_cli_capture_end_to_end(tmp_path, torus, capsys):
    from eval.cli import main

    src = tmp_path / "torus.ply"
    moved = torus.copy()
    moved.apply_scale(5.0)
    moved.apply_translation([10.0, 0, 0])
    moved.export(src)
    out = tmp_path / "out" / "cap"
    assert main(["-q", "capture", str(src), "-o", str(out), "--views", "4", "--resolution", "64"]) == 0
    mv = cap.MultiView.load(out)
    assert mv.diffuse.shape == (4, 64, 64) and mv.mask.any(axis=(1, 2)).all()
    info = json.loads((out / "capture.json").read_text())
    assert info["normalized"] and info["transform"]["scale"] == pytest.approx(1 / 5 / (0.7 + 0.25), rel=0.1)
    # Running again replaces the capture.
    assert main(["-q", "capture", str(src), "-o", str(out), "--views", "2", "--resolution", "16"]) == 0
    assert cap.MultiView.load(out).views == 2
    assert sorted(p.name for p in out.parent.iterdir()) == ["cap"]  # no temporary folders left


@needs_gl
def test_cli_capture_failures_leave_nothing(tmp_path, torus, capsys):
    from eval.cli import main

    far = torus.copy()
    far.apply_translation([50.0, 0, 0])
    src = tmp_path / "far.obj"
    far.export(src)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01not a mesh")
    out = tmp_path / "out"
    cases = [
        [str(src), "--no-normalize"],  # outside every camera
        [str(garbage)],  # unreadable
        [str(tmp_path / "missing.obj")],  # no such file
    ]
    for extra in cases:
        capsys.readouterr()
        rc = main(["-q", "capture", *extra, "-o", str(out), "--views", "4", "--resolution", "32"])
        err = capsys.readouterr().err.strip()
        assert rc == 2, extra
        assert err.startswith("dmesh capture: error:") and "\n" not in err, err
        assert not out.exists()
        assert sorted(p.name for p in tmp_path.iterdir()) == ["far.obj", "garbage.ply"]
    # A folder that is not a capture is never replaced.
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert main(["-q", "capture", str(src), "-o", str(other), "--views", "4", "--resolution", "16"]) == 2
    assert (other / "keep.txt").read_text() == "mine"
