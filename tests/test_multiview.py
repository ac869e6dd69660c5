"""Multi-view images to mesh: input checks, image resampling, interior-face removal, the procedure (tiny
preset on a small capture), determinism, resuming, the CLI, the harness method and the report alias.

The accuracy threshold is ~1.5x the value measured with the `tiny` preset (number in the comment), so a
regression fails here; timings are never asserted. The captures need headless OpenGL (OSMesa or EGL).
"""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from datasets import capture as cap
from datasets import synthetic
from datasets.normalize import normalize
from dmesh.camera import eyes as camera_eyes
from dmesh.extract import depth_consistent_faces, mesh_faces, visible_faces
from dmesh.recon.multiview import MultiViewConfig, reconstruct
from dmesh.recon.views import check_views, depth_channel, downsample, soft_band_targets


_NO_GL = cap.gl_problem()
needs_gl = pytest.mark.skipif(_NO_GL is not None, reason=f"no headless OpenGL (OSMesa/EGL): {_NO_GL}")

#: The test capture: few views at low resolution (the tiny preset optimises at 48 pixels).
VIEWS, RESOLUTION = 16, 96


@pytest.fixture(scope="module")
def sphere():
    gt, _ = normalize(synthetic.generate("sphere", seed=0), radius=1.0)
    return gt


@pytest.fixture(scope="module")
def sphere_views(sphere):
    if _NO_GL is not None:
        pytest.skip(f"no headless OpenGL (OSMesa/EGL): {_NO_GL}")
    return cap.capture(sphere, views=VIEWS, resolution=RESOLUTION)


def _fake_views(v=2, res=8, **changes):
    """A MultiView with a lit square in every view (no OpenGL), for the input checks."""
    depth = np.zeros((v, res, res), np.float32)
    depth[:, 2:6, 2:6] = 1.5
    fields = dict(diffuse=(depth > 0).astype(np.float32), depth=depth, mask=depth > 0,
                  world_to_camera=cap.camera_rig(v)[0], projection=cap.perspective(65.0, 1.0, 0.1, 100.0),
                  fov_y_degrees=65.0, resolution=res)
    fields.update(changes)
    return cap.MultiView(**fields)


# ------------------------------------------------------------------------------------------------ inputs

def _nan_depth():
    views = _fake_views()
    views.depth[0, 3, 3] = np.nan
    return views


@pytest.mark.parametrize("make,match", [
    (lambda: None, "no views"),
    (lambda: _fake_views(diffuse=np.zeros((0, 8, 8), np.float32), depth=np.zeros((0, 8, 8), np.float32),
                         mask=np.zeros((0, 8, 8), bool), world_to_camera=np.zeros((0, 4, 4))), "V >= 1"),
    (lambda: _fake_views(depth=np.zeros((2, 8, 7), np.float32)), "shape"),
    (lambda: _fake_views(mask=np.zeros((3, 8, 8), bool)), "mask"),
    (lambda: _fake_views(world_to_camera=np.zeros((3, 4, 4))), "world_to_camera"),
    (_nan_depth, "NaN"),
    (lambda: _fake_views(depth=np.zeros((2, 8, 8), np.float32), mask=np.zeros((2, 8, 8), bool)), "empty"),
    # An object much larger than the camera distance: normalised to radius 1, the cameras fall inside it.
    (lambda: _fake_views(depth=np.full((2, 8, 8), 10, np.float32), mask=np.ones((2, 8, 8), bool)), "too close"),
])
def test_bad_views(make, match):
    with pytest.raises(ValueError, match=match) as info:
        reconstruct(make(), MultiViewConfig.tiny())
    assert "\n" not in str(info.value)


def test_check_views_masks_the_background():
    views = _fake_views()
    views.diffuse[:, 0, 0] = 0.7                   # lit background pixel: not part of the object
    vw = check_views(views)
    assert vw.diffuse[:, 0, 0].max() == 0 and vw.depth.dtype == np.float32


def test_config_validation():
    with pytest.raises(ValueError, match="steps_phase1"):
        MultiViewConfig(steps_phase1=(1, 2))       # one entry per epoch: 4 for the default re-seeds
    with pytest.raises(ValueError, match="interior"):
        MultiViewConfig(interior="some")
    with pytest.raises(ValueError, match="unknown preset"):
        MultiViewConfig.preset("slow")
    with pytest.raises(ValueError, match="depth_tolerance"):
        MultiViewConfig(depth_tolerance=0.0)
    with pytest.raises(ValueError, match="voronoi"):
        MultiViewConfig(voronoi="some")
    with pytest.raises(ValueError, match="init must be"):
        MultiViewConfig(init="points")
    with pytest.raises(ValueError, match="init_preset"):
        MultiViewConfig(init="depth", init_preset="slow")
    depth = MultiViewConfig.depth()
    assert depth.init == "depth" and depth.epochs == 1 and depth.total_steps() == 0
    paper = MultiViewConfig.paper()
    assert paper.epochs == 4 and paper.refine_seeds == (1000, 3000, 10_000) and paper.grid == 20
    assert paper.steps_phase1 == (500,) * 4 and paper.steps_phase2 == (500,) * 4
    assert MultiViewConfig(steps_phase1=7).steps_phase1 == (7,) * 4


# ------------------------------------------------------------------------------------------------ helpers

def test_downsample_is_an_area_average(rng):
    img = rng.random((3, 12, 12)).astype(np.float32)
    half = downsample(img, 6)
    want = img.reshape(3, 6, 2, 6, 2).mean(axis=(2, 4))
    assert np.allclose(half, want, atol=1e-6)
    odd = downsample(img, 5)                       # non-integer ratio: each pixel averages its footprint
    assert odd.shape == (3, 5, 5) and np.allclose(odd.mean(axis=(1, 2)), img.mean(axis=(1, 2)), atol=1e-6)
    assert np.array_equal(downsample(img, 12), img)


@needs_gl
def test_band_targets_make_the_soft_fit_unbiased(sphere, sphere_views):
    """The GT sphere, drawn opaque by the soft renderer at 48 pixels, fits the plain targets best when shrunk
    (its band puts the silhouette about half a pixel outside) but the band targets best at its true size."""
    from dmesh.render import Camera, soft_render_views

    res, width = 48, 1.0
    vw = check_views(sphere_views)
    far = np.linalg.norm(camera_eyes(vw.world_to_camera), axis=1) + 2.0
    channel = far[:, None, None] * vw.mask - vw.depth.astype(np.float64)
    plain = [torch.from_numpy(downsample(x, res)) for x in (vw.diffuse, channel)]
    band = [torch.from_numpy(x) for x in soft_band_targets([vw.diffuse, channel], vw.mask, res, width)]
    assert torch.equal(band[0][plain[0] > 0.999], plain[0][plain[0] > 0.999])  # object pixels unchanged
    cams = Camera.from_views(vw.world_to_camera, vw.fov_y_degrees, res)
    faces = torch.from_numpy(np.asarray(sphere.faces, np.int64))
    pixel = 2.0 * 2.0 * np.tan(np.radians(vw.fov_y_degrees) / 2) / res  # one pixel at the sphere's distance
    offsets = np.array([-1.0, -0.5, 0.0, 0.5]) * pixel
    losses = {"plain": [], "band": []}
    for off in offsets:
        verts = torch.from_numpy(np.asarray(sphere.vertices) * (1.0 + off)).float()
        out = soft_render_views(verts, faces, torch.ones(len(faces)), cams, edge_width=width, min_opacity=0.0)
        z = depth_channel(out["depth"], out["alpha"], torch.from_numpy(far).float()) * 2.0
        for name, (td, tz) in (("plain", plain), ("band", band)):
            losses[name].append(float((out["diffuse"] - td).abs().mean() + (z - tz).abs().mean()))
    assert offsets[int(np.argmin(losses["plain"]))] < 0, losses
    assert offsets[int(np.argmin(losses["band"]))] == 0.0, losses


def test_look_at_point_of_the_capture_rig():
    from dmesh.camera import look_at_point

    w2c, _ = cap.camera_rig(64)
    shifted = w2c.copy()
    shifted[:, :3, 3] -= np.einsum("vij,j->vi", w2c[:, :3, :3], [0.3, -0.2, 0.1])  # rig moved to (0.3, -0.2, 0.1)
    assert np.allclose(look_at_point(w2c), 0.0, atol=1e-9)
    assert np.allclose(look_at_point(shifted), [0.3, -0.2, 0.1], atol=1e-9)
    assert look_at_point(np.repeat(w2c[:1], 3, axis=0)) is None  # one axis: no single nearest point


@needs_gl
def test_lopsided_object_falls_back_to_the_look_at_centre():
    """The shared face mask is lopsided: its lifted box centre moves towards a camera of the rig, which then
    sits inside the object's box; the cameras' look-at point (the vertex mean) keeps every camera out."""
    from conftest import shared_mesh

    from dmesh.recon.views import BOX_MARGIN, MIN_BOX, lifted_points, normalisation

    from datasets.meshes import load_mesh

    gt, _ = normalize(load_mesh(shared_mesh("open/face.off")), radius=1.0)
    vw = check_views(cap.capture(gt, views=64, resolution=64))
    pts = lifted_points(vw)
    box_centre = 0.5 * (pts.min(0) + pts.max(0))
    radius = np.linalg.norm(pts - box_centre, axis=1).max()
    eyes = camera_eyes(vw.world_to_camera)
    assert BOX_MARGIN * np.abs((eyes - box_centre) / radius).max(1).min() < MIN_BOX  # the box centre fails
    center, scale, _, eyes_n = normalisation(vw)
    cam_box = np.abs(eyes_n).max(1).min()
    assert np.allclose(center, 0.0, atol=1e-6) and BOX_MARGIN * cam_box >= MIN_BOX


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


# ------------------------------------------------------------------------------------------------ procedure

def _p2s(mesh, gt):
    from eval.metrics import chamfer_l1_p2s

    return chamfer_l1_p2s(mesh, gt, n=20_000, seed=0)


# Measured with the tiny preset (seed 0, 16 views at 96 pixels, one thread, metrics from 20K samples): sphere
# cd_p2s 0.0994 (epoch 1 selected by its image loss 0.221 against epoch 0's 0.32; a 48-pixel image is 0.05
# wide per pixel at the object; 0.144 without the depth-consistency filter); the limit is 1.5x that.
TINY_LIMIT = 0.149


@pytest.fixture
def one_thread():
    """Runs are bit-for-bit repeatable only on one thread: the renderers are deterministic on any thread
    count, but torch's parallel scatter-adds (candidate scores, regularisers) sum in schedule order."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@needs_gl
def test_tiny_reconstruction(sphere, sphere_views, tmp_path, one_thread):
    seen = []
    cfg = MultiViewConfig.tiny()
    res = reconstruct(sphere_views, cfg, callback=seen.append, state_path=tmp_path / "state.pt")
    assert len(res.mesh.faces) > 0
    assert _p2s(res.mesh, sphere) < TINY_LIMIT
    steps = [r for r in seen if "stage" not in r]
    assert len(steps) == cfg.total_steps() == len(res.history)
    stages = {r["stage"] for r in seen if "stage" in r}
    assert {"init", "epoch0_phase1", "epoch0_phase2", "epoch1_phase1", "epoch1_end", "extract"} <= stages
    assert len(res.info["epochs"]) == cfg.epochs and res.timings["total"] > 0
    losses = [e["eval_loss"] for e in res.info["epochs"]]
    assert res.info["selected_epoch"] == int(np.argmin(losses))
    # Same seed, same mesh (bit for bit); the finished state resumes straight to extraction.
    again = reconstruct(sphere_views, cfg)
    assert np.array_equal(again.mesh.faces, res.mesh.faces)
    assert np.array_equal(again.mesh.vertices, res.mesh.vertices)
    resumed = reconstruct(sphere_views, cfg, state_path=tmp_path / "state.pt")
    assert "resumed_from" in resumed.info and np.array_equal(resumed.mesh.faces, res.mesh.faces)


# Measured with the depth preset on the point-cloud tiny fit of 20K lifted pixels (seed 0, one thread, same
# capture and metric as above): sphere cd_p2s 0.0096, ten times below the grid start's; the limit is 1.5x.
DEPTH_LIMIT = 0.0144


@needs_gl
def test_depth_start_reconstruction(sphere, sphere_views, one_thread):
    cfg = MultiViewConfig.depth(init_preset="tiny", init_points=20_000)
    seen = []
    res = reconstruct(sphere_views, cfg, callback=seen.append)
    assert _p2s(res.mesh, sphere) < DEPTH_LIMIT
    assert [r["stage"] for r in seen if "stage" in r][:2] == ["init", "init_depth"]
    assert res.info["init_depth"]["lifted_points"] == 20_000 and res.history == []
    again = reconstruct(sphere_views, cfg)
    assert np.array_equal(again.mesh.faces, res.mesh.faces)
    assert np.array_equal(again.mesh.vertices, res.mesh.vertices)
    # The one-sheet extraction of the point-cloud fit is an interior rule too.
    sheet = reconstruct(sphere_views, dataclasses.replace(cfg, interior="sheet"))
    assert _p2s(sheet.mesh, sphere) < DEPTH_LIMIT


@needs_gl
def test_refine_never_keeps_a_mesh_that_renders_worse_than_its_start(sphere, sphere_views, one_thread):
    # The start is a candidate of select_best: whatever the steps do, the kept mesh's image loss over all
    # views is at most the start's. A learning rate 100x the preset's makes the steps hurt, so the start wins.
    for lr, start_wins in ((1e-5, None), (1e-3, True)):
        cfg = MultiViewConfig.refine(init_preset="tiny", init_points=20_000, steps_phase1=(4,), steps_phase2=(2,),
                                     resolution=48, lr_first=lr, bound_first=lr)
        res = reconstruct(sphere_views, cfg)
        start, epochs = res.info["start_eval_loss"], res.info["epochs"]
        kept = res.info["selected_epoch"]
        assert kept in (-1, 0) and len(res.history) == 6
        assert (start if kept == -1 else epochs[0]["eval_loss"]) <= min(start, epochs[0]["eval_loss"])
        if start_wins:
            assert kept == -1 and epochs[0]["eval_loss"] > start
        assert _p2s(res.mesh, sphere) < DEPTH_LIMIT * (1.0 if kept == -1 else 1.5)


@needs_gl
def test_without_select_best_the_last_epoch_is_returned(sphere_views):
    cfg = MultiViewConfig.tiny(steps_phase1=(3, 2), steps_phase2=(1, 1), select_best=False)
    res = reconstruct(sphere_views, cfg)
    assert "selected_epoch" not in res.info
    assert len(res.mesh.faces) == res.info["epochs"][-1]["faces"]


@needs_gl
def test_interrupted_run_resumes(sphere_views, tmp_path):
    cfg = MultiViewConfig.tiny(steps_phase1=(3, 2), steps_phase2=(1, 1), save_every=1)

    class Stop(Exception):
        pass

    def interrupt(rec):
        if rec.get("epoch") == 1 and rec.get("phase") == 1 and rec.get("step") == 1:
            raise Stop

    with pytest.raises(Stop):
        reconstruct(sphere_views, cfg, callback=interrupt, state_path=tmp_path / "s.pt")
    seen = []
    res = reconstruct(sphere_views, cfg, callback=seen.append, state_path=tmp_path / "s.pt")
    assert res.info["resumed_from"] == {"epoch": 1, "phase": 1, "step": 1}
    assert [(r["epoch"], r["phase"], r["step"]) for r in seen if "step" in r] == [(1, 1, 1), (1, 2, 0)]
    assert len(res.history) == cfg.total_steps()
    other = reconstruct(sphere_views, dataclasses.replace(cfg, seed=1), state_path=tmp_path / "s.pt")
    assert "resumed_from" not in other.info        # another config: starts over


@needs_gl
def test_harness_method(sphere_views):
    from baselines.base import Inputs
    from baselines.registry import get_method

    method = get_method("dmesh_mv")
    assert method.input_kind == "multiview" and method.default_config() == MultiViewConfig.fast()
    res = method.reconstruct(Inputs(views=sphere_views, seed=3),
                             {"preset": "tiny", "steps_phase1": [4, 2], "steps_phase2": [2, 2]})
    assert len(res.mesh.faces) > 0 and res.timings["total"] > 0 and "phase1_wdt" in res.timings
    assert res.info["config"]["seed"] == 3 and res.info["config"]["steps_phase1"] == (4, 2)
    with pytest.raises(ValueError, match="unknown config keys"):
        method.reconstruct(Inputs(views=sphere_views), {"preset": "tiny", "bogus": 1})
    with pytest.raises(ValueError, match="multi-view capture"):
        method.reconstruct(Inputs(points=np.zeros((20, 3))), {"preset": "tiny"})


# ------------------------------------------------------------------------------------------------ CLI

def _cli(*args):
    return subprocess.run([sys.executable, "-m", "eval.cli", *args], capture_output=True, text=True)


@needs_gl
def test_cli_reconstruct_multiview_end_to_end(sphere_views, tmp_path):
    sphere_views.save(tmp_path / "capture")
    out = tmp_path / "out" / "mesh.obj"
    r = _cli("reconstruct", "multiview", str(tmp_path / "capture"), "-o", str(out), "--preset", "tiny",
             "--seed", "2", "--set", "steps_phase1=[4, 2]", "--set", "steps_phase2=2")
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "out" / "mesh.timings.json").read_text())
    assert report["kind"] == "multiview" and report["config"]["seed"] == 2
    assert report["config"]["steps_phase1"] == [4, 2] and report["timings_s"]["total"] > 0
    assert len(report["info"]["epochs"]) == 2
    import trimesh

    assert len(trimesh.load(out, process=False).faces) > 0
    assert not list((tmp_path / "out").glob(".*tmp*"))


@needs_gl
def test_cli_depth_preset_and_its_pointcloud_refusal(sphere_views, tmp_path):
    sphere_views.save(tmp_path / "capture")
    out = tmp_path / "mesh.ply"
    r = _cli("reconstruct", "multiview", str(tmp_path / "capture"), "-o", str(out), "--preset", "depth",
             "--set", "init_preset=tiny", "--set", "init_points=5000")
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "mesh.timings.json").read_text())
    assert report["config"]["init"] == "depth" and report["info"]["init_depth"]["lifted_points"] == 5000
    r = _cli("reconstruct", "pointcloud", str(out), "-o", str(tmp_path / "again.ply"), "--preset", "depth")
    assert r.returncode != 0 and "'depth' is for multi-view input only" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("setup,match", [
    (lambda d: None, "no such folder"),
    (lambda d: d.mkdir(), "not a capture folder"),
    (lambda d: (d.mkdir(), (d / "views.npz").write_bytes(b"junk")), "cannot read"),
    (lambda d: d.write_text("x"), "not a folder"),
])
def test_cli_bad_capture_one_line(tmp_path, capsys, setup, match):
    from eval.cli import main

    src = tmp_path / "cap"
    setup(src)
    out = tmp_path / "out.obj"
    code = main(["-q", "reconstruct", "multiview", str(src), "-o", str(out), "--preset", "tiny"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.strip().count("\n") == 0 and match in err, err
    assert not out.exists() and not list(tmp_path.glob("*.json"))


# ------------------------------------------------------------------------------------------------ reports

def test_multiview_table_shows_dmesh_mv_as_dmesh(tmp_path):
    from eval.reports import tables
    from eval.store import Store

    def row(key, method, kind, cd):
        return {"key": key, "method": method, "config_label": "", "shape": "torus", "category": "closed",
                "input_kind": kind, "config_json": {}, "inputs_json": {"views": 64, "metric_samples": 1000},
                "seed": 0, "status": "done", "error": None, "gt_hash": "0" * 64, "code_version": "test",
                "metrics_json": {"cd_p2s": cd, "cd_l1": cd}, "timings_json": {"total": 1.0}, "info_json": {},
                "peak_memory_mb": 1.0}

    with Store(tmp_path / "s.sqlite") as s:
        s.upsert(row("a", "dmesh_mv", "multiview", 2e-3))
        s.upsert(row("b", "tsdf", "multiview", 1e-3))
        s.upsert(row("c", "dmesh", "pointcloud", 3e-3))
        df = s.dataframe()
    mv = {r["method"]: r for r in tables.table2(df, "multiview")}
    assert set(mv) == {"dmesh", "tsdf"} and mv["dmesh"]["cd_p2s"] == 2e-3
    assert mv["dmesh"]["paper_cd_l1"] is not None   # the paper's "Ours" row sits beside it
    assert [r["method"] for r in tables.table2(df, "pointcloud")] == ["dmesh"]
    md, _ = tables.write_table2(df, tmp_path / "rep", "multiview")
    assert "dmesh_mv" not in md.read_text() and "| dmesh |" in md.read_text()
