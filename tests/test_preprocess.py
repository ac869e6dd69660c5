"""The harness's pre-processing stage (`eval.preprocess`, issue 58 item 3): what the stages do to a point cloud,
that one and the same pre-processed cloud reaches every method of a sweep, that it is in the run key and the
row label, and that the DMesh harness rows keep no filter of their own.

The methods here are test-only fakes registered into `baselines.registry.METHODS` for one test: each saves the
points it was given, then returns their convex hull.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from eval import preprocess
from eval.sweep import Sweep, expand

SMALL = {"n_points": 1500, "metric_samples": 1500, "views": 4, "resolution": 32}


def _sphere(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    p = np.random.default_rng(seed).normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return p, p.copy()


def _planted(n_out: int, seed: int = 1) -> np.ndarray:
    """Uniform points of [-1.5, 1.5]^3 at least 0.2 off the unit sphere (true strays)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n_out:
        q = rng.uniform(-1.5, 1.5, 3)
        if abs(np.linalg.norm(q) - 1.0) > 0.2:
            out.append(q)
    return np.array(out)


# ------------------------------------------------------------------------------------------------ stages

def test_outlier_stage_removes_planted_strays_and_keeps_the_surface():
    pts, nrm = _sphere(4000)
    strays = _planted(80)
    cloud = np.concatenate([pts, strays])
    normals = np.concatenate([nrm, np.tile([0.0, 0.0, 1.0], (80, 1))])
    planted = np.r_[np.zeros(4000, bool), np.ones(80, bool)]
    kept, kept_n, info = preprocess.apply(cloud, normals, "outliers", is_outlier=planted)
    assert info["planted_outliers"] == 80 and info["planted_outliers_removed"] >= 76  # >= 95 % of the strays
    assert info["outliers_removed"] - info["planted_outliers_removed"] <= 40          # <= 1 % of the surface
    assert info["points"] == len(kept) == len(kept_n) == 4080 - info["outliers_removed"]
    # normals travel with their points: a surface point's normal is its position on the unit sphere
    on = np.abs(np.linalg.norm(kept, axis=1) - 1) < 1e-9
    assert np.allclose(kept_n[on], kept[on])


def test_smoothing_leaves_a_clean_sphere_nearly_unchanged_and_takes_noise_off():
    pts, nrm = _sphere(4000)
    out, out_n, info = preprocess.apply(pts, nrm, "outliers+smooth")
    assert info["smoothed"] and info["smooth_k"] == 120 and info["outliers_removed"] <= 40
    # A quadratic jet of 120 neighbours fits a sphere to well under the spacing (about 0.03 here).
    assert np.abs(np.linalg.norm(out, axis=1) - 1).max() < 2e-3
    assert out_n is not None and len(out_n) == len(out)
    noisy = pts + np.random.default_rng(2).normal(scale=0.01, size=pts.shape)
    smoothed, _, _ = preprocess.apply(noisy, None, "smooth")
    before, after = (np.abs(np.linalg.norm(x, axis=1) - 1).mean() for x in (noisy, smoothed))
    assert after < 0.4 * before, (before, after)


def test_autosmooth_smooths_only_what_looks_noisy():
    pts, _ = _sphere(4000)
    clean, _, info = preprocess.apply(pts, None, "autosmooth")
    assert not info["smoothed"] and np.array_equal(clean, pts)
    noisy = pts + np.random.default_rng(2).normal(scale=0.02, size=pts.shape)  # noise ratio 0.14 (clean: 0.04)
    _, _, info = preprocess.apply(noisy, None, "autosmooth=60")
    assert info["smoothed"] and info["smooth_k"] == 60 and info["noise_ratio"] > 0.1


def test_specs_are_canonical_and_bad_ones_are_one_line_errors():
    assert preprocess.parse_spec("smooth+outliers")[0] == "outliers+smooth"
    assert preprocess.parse_spec("outliers=2+smooth=120")[0] == "outliers+smooth"  # defaults left out
    assert preprocess.parse_spec("outliers=3+smooth=60")[0] == "outliers=3+smooth=60"
    assert preprocess.parse_spec(" none ")[0] == "none" and preprocess.label("none") == ""
    assert preprocess.label("outliers+smooth") == "+outliers+smooth"
    for bad, msg in (("denoise", "unknown pre-processing stage"), ("smooth+autosmooth", "exclude each other"),
                     ("outliers+outliers", "twice"), ("smooth=x", "expected an integer"), ("smooth=3", "at least 6"),
                     ("outliers=-1", "positive"), ("outliers++smooth", "empty stage"), (3, "expected a spec")):
        with pytest.raises(ValueError, match=msg):
            preprocess.parse_spec(bad)


def test_the_defaults_are_dmesh_s_former_private_settings():
    from dmesh.recon.config import NOISY_SMOOTH_K, PointCloudConfig
    from dmesh.recon.multiview_config import MultiViewConfig

    assert preprocess.OutlierConfig().std_ratio == PointCloudConfig.fast().outlier_std
    assert preprocess.SmoothConfig().k == NOISY_SMOOTH_K == PointCloudConfig.noisy().smooth_k
    assert preprocess.lift_points_default() == MultiViewConfig.depth().init_points


def test_lifted_depth_pixels_are_the_depth_preset_s_and_face_their_cameras():
    from dmesh.camera import eyes
    from dmesh.recon.views import check_views, lifted_points
    from tests.common import fake_views

    pytest.importorskip("open3d")
    views = fake_views(v=3, res=16)
    pixels = lifted_points(check_views(views))
    pts, nrm, info = preprocess.lift_depth(views, 20, seed=4)
    idx = np.sort(np.random.default_rng(4).choice(len(pixels), 20, replace=False))
    assert info == {"pixels": len(pixels), "points": 20} and np.array_equal(pts, pixels[idx])
    view = np.repeat(np.arange(3), 16)[idx]  # 16 lit pixels per view, in view order
    toward = eyes(np.asarray(views.world_to_camera, np.float64))[view] - pts
    assert (np.einsum("ij,ij->i", nrm, toward) >= 0).all()
    assert np.array_equal(preprocess.lift_depth(views, 10_000, seed=4)[0], pixels)  # fewer pixels: all


# ------------------------------------------------------------------------------------------------ sweeps

def test_preprocess_is_in_the_run_key_and_the_label_and_none_keeps_the_old_keys():
    plain = expand(Sweep(methods=("psr", "tsdf"), shapes=("sphere",), inputs=("pointcloud", "multiview"), **SMALL))
    both = expand(Sweep(methods=("psr", "tsdf"), shapes=("sphere",), inputs=("pointcloud", "multiview"),
                        preprocess=("none", "smooth+outliers"), **SMALL))
    assert {(r.method, r.config_label) for r in both} == {("psr", ""), ("psr", "+outliers+smooth"), ("tsdf", "")}
    assert {r.key for r in plain} < {r.key for r in both}  # "none" rows are the plain sweep's runs
    pre = next(r for r in both if r.config_label)
    assert pre.inputs["preprocess"]["stages"] == "outliers+smooth" and len(pre.inputs["preprocess"]["code"]) == 16
    other = expand(Sweep(methods=("psr",), shapes=("sphere",), preprocess=("outliers",), **SMALL))
    assert other[0].key not in {r.key for r in both} and other[0].config_label == "+outliers"
    tuned = expand(Sweep(methods=("psr",), shapes=("sphere",), preprocess=("outliers",),
                         configs={"psr": [{"depth": 7}]}, **SMALL))
    assert tuned[0].config_label == "depth=7,+outliers"
    with pytest.raises(ValueError, match="repeats"):
        Sweep(methods=("psr",), shapes=("sphere",), preprocess=("outliers+smooth", "smooth+outliers"))
    with pytest.raises(ValueError, match="lift_depth"):
        Sweep(methods=("psr",), shapes=("sphere",), lift_depth=True)


def test_lift_depth_gives_point_cloud_methods_a_multiview_row():
    runs = expand(Sweep(methods=("psr", "tsdf"), shapes=("sphere",), inputs=("multiview",), lift_depth=True,
                        preprocess=("none", "outliers"), **SMALL))
    got = {(r.method, r.input_kind, r.config_label) for r in runs}
    assert got == {("psr", "multiview", "lifted-depth"), ("psr", "multiview", "lifted-depth,+outliers"),
                   ("tsdf", "multiview", "")}
    lifted = next(r for r in runs if r.config_label == "lifted-depth")
    assert lifted.inputs["lift"]["points"] == preprocess.lift_points_default()


RECORDER_SRC = '''
import numpy as np
from baselines.base import Method


class Recorder(Method):
    """Test-only: saves the points and the pre-processing record it got to `out`, returns their convex hull."""

    name = "recorder_a"
    input_kind = "pointcloud"

    def default_config(self):
        return {"out": ""}

    def _run(self, inputs, cfg, sw):
        import json
        import trimesh

        np.save(cfg["out"] + f"/{self.name}_{len(inputs.points)}.npy", np.asarray(inputs.points))
        with open(cfg["out"] + f"/{self.name}_{len(inputs.points)}.json", "w") as fh:
            json.dump(inputs.preprocess, fh)
        return trimesh.convex.convex_hull(np.asarray(inputs.points, np.float64)), {}
'''


@pytest.fixture
def recorders(monkeypatch):
    registry = pytest.importorskip("baselines.registry")
    pytest.importorskip("eval.metrics")
    ns: dict = {}
    exec(compile(RECORDER_SRC, "<recorder>", "exec"), ns)
    a = ns["Recorder"]
    b = type("RecorderB", (a,), {"name": "recorder_b"})
    monkeypatch.setitem(registry.METHODS, "recorder_a", a())
    monkeypatch.setitem(registry.METHODS, "recorder_b", b())


def test_the_same_preprocessed_points_reach_every_method(recorders, tmp_path):
    from eval.runner import RunnerConfig, run_sweep
    from eval.store import Store

    out = tmp_path / "seen"
    out.mkdir()
    cfg = [{"out": str(out)}]
    sweep = Sweep(methods=("recorder_a", "recorder_b"), shapes=("sphere",), preprocess=("none", "outliers+smooth"),
                  variants=({"outliers": 0.05},), configs={"recorder_a": cfg, "recorder_b": cfg}, **SMALL)
    summary = run_sweep(sweep, RunnerConfig(work=str(tmp_path / "w")))
    assert summary.done == 4 and summary.failed == 0
    seen = {p.stem: np.load(p) for p in out.glob("*.npy")}
    sizes = sorted({int(k.rsplit("_", 1)[1]) for k in seen})
    assert len(sizes) == 2 and sizes[1] == 1500  # the raw cloud and the pre-processed one (strays removed)
    raw_a, raw_b = seen["recorder_a_1500"], seen["recorder_b_1500"]
    pre_a, pre_b = seen[f"recorder_a_{sizes[0]}"], seen[f"recorder_b_{sizes[0]}"]
    assert np.array_equal(raw_a, raw_b) and np.array_equal(pre_a, pre_b)
    records = [json.loads((out / f"recorder_{m}_{sizes[0]}.json").read_text()) for m in "ab"]
    assert records[0] == records[1] and records[0]["spec"] == "outliers+smooth"
    # uniform strays of the enlarged cube: some fall within a spacing of the surface and stay
    assert records[0]["planted_outliers_removed"] >= 0.5 * records[0]["planted_outliers"] > 0
    assert json.loads((out / "recorder_a_1500.json").read_text()) is None
    with Store(tmp_path / "w" / "results.sqlite") as s:
        rows = list(s.rows())
    labels = {(r["method"], r["config_label"]) for r in rows}
    assert labels == {(m, lab) for m in ("recorder_a", "recorder_b") for lab in ("out=" + str(out),
                                                                                 f"out={out},+outliers+smooth")}
    for r in rows:
        info = r["info_json"] if isinstance(r["info_json"], dict) else json.loads(r["info_json"] or "{}")
        assert ("preprocess" in info) == r["config_label"].endswith("+outliers+smooth")


# ------------------------------------------------------------------------------------------------ DMesh

def test_dmesh_harness_rows_keep_no_private_filter():
    from baselines.dmesh_multiview import DMeshMultiView
    from baselines.dmesh_pointcloud import PRIVATE_FILTERS, DMeshPointCloud, seeds_for_input
    from dmesh.recon.config import PointCloudConfig

    method = DMeshPointCloud()
    for cfg in (method.default_config(), method.resolve_config(None), method.resolve_config({"num_init": 500}),
                method.resolve_config({"preset": "fast"}), method.resolve_config(PointCloudConfig.noisy())):
        assert {k: getattr(cfg, k) for k in PRIVATE_FILTERS} == PRIVATE_FILTERS
    assert method.resolve_config({"preset": "paper"}) == PointCloudConfig.paper()  # nothing to turn off there
    for asked, msg in (({"preset": "noisy"}, "preprocess: \\[outliers\\+smooth\\]"),
                       ({"outlier_std": 2.0}, "outlier_std -> outliers"),
                       ({"preset": "fast", "auto_smooth_k": 60}, "auto_smooth_k -> autosmooth")):
        with pytest.raises(ValueError, match=msg):
            method.resolve_config(asked)
    # the sweep's config (and so the run key) is the harness one
    run = expand(Sweep(methods=("dmesh",), shapes=("sphere",), **SMALL))[0]
    assert {k: run.config[k] for k in PRIVATE_FILTERS} == PRIVATE_FILTERS
    # the presets' seed cap follows the harness's smoothing, not a private one
    fast = method.default_config()
    assert seeds_for_input(fast, {"smoothed": True}) == (dataclasses.replace(fast, num_init=fast.smoothed_seeds), True)
    assert seeds_for_input(fast, {"smoothed": False}) == (fast, False) == seeds_for_input(fast, None)
    # the multi-view method's configs are its own
    assert DMeshMultiView().resolve_config({"preset": "depth"}).init == "depth"
