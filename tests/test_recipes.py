"""Every DMesh row says its recipe; the gradients of one phase-1 step agree with finite differences."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from eval.reports.recipes import recipe_markdown, recipe_rows


@pytest.mark.parametrize("kind", ["pointcloud", "multiview"])
def test_every_preset_has_a_recipe(kind):
    from dmesh.recon import config

    recipes = getattr(config, f"{kind.upper()}_RECIPES")
    assert set(recipes) == set(getattr(config, f"{kind.upper()}_PRESETS"))
    for steps, text in recipes.values():
        assert isinstance(steps, bool) and len(text) > 20
    # The rows the harness shows by default are the fast presets: one takes steps, one does not.
    assert config.POINTCLOUD_RECIPES["fast"][0] is False and config.MULTIVIEW_RECIPES["fast"][0] is True


def test_recipe_rows_name_preset_kind_and_overrides():
    df = pd.DataFrame([
        {"method": "dmesh", "config_label": "", "input_kind": "pointcloud"},
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud"},
        {"method": "dmesh", "config_label": "lr=1e-05,preset=paper", "input_kind": "pointcloud"},
        {"method": "psr", "config_label": "", "input_kind": "pointcloud"},
        {"method": "dmesh_mv", "config_label": "preset=depth", "input_kind": "multiview"},
    ])
    rows = {r["method"]: r for r in recipe_rows(df, "pointcloud")}
    assert set(rows) == {"dmesh", "dmesh [preset=paper]", "dmesh [lr=1e-05,preset=paper]"}
    assert rows["dmesh"]["preset"] == "fast" and rows["dmesh"]["kind"] == "initialisation"
    assert rows["dmesh [preset=paper]"]["kind"] == "gradient steps"
    assert rows["dmesh [lr=1e-05,preset=paper]"]["recipe"].endswith("Overrides: lr=1e-05.")
    mv = recipe_rows(df, "multiview")
    assert [(r["method"], r["kind"]) for r in mv] == [("dmesh [preset=depth]", "initialisation")]
    md = recipe_markdown(mv)
    assert md.startswith("## DMesh recipes") and "| dmesh [preset=depth] | depth | initialisation |" in md
    assert recipe_markdown([]) == "" and recipe_rows(df.iloc[:0], "pointcloud") == []


def test_step_gradients_agree_with_finite_differences_at_a_fixed_triangulation():
    # The whole phase-1 step on a small torus input, with the triangulation, candidates, Chamfer K and the
    # drawn (face, barycentric) pairs fixed: the expected Chamfer's position and weight gradients are the
    # derivative of the loss. (Steps of 1e-4 along a unit direction: the parameters are float32.)
    from dmesh.recon.pointcloud import PointCloudConfig
    from eval.bench.gradients import StepTerms, _initial_dmesh, _input

    pts, _ = _input(5000)
    cfg = PointCloudConfig.paper(num_init=250, num_target=2000, num_samples=2000)
    dm = _initial_dmesh(pts, cfg)
    terms = StepTerms(dm, pts, cfg)
    for group in ("points", "weights"):
        param = getattr(dm, group)
        for p in (dm.points, dm.weights, dm.reals):
            p.grad = None
        terms()["chamfer"].backward()
        u = torch.randn(param.shape, generator=torch.Generator().manual_seed(1), dtype=param.dtype)
        u /= u.norm()
        autograd = float((param.grad * u).sum())
        fd = []
        for h in (1e-3, 1e-4):
            vals = []
            origin = param.detach().clone()
            for sign in (1.0, -1.0):
                with torch.no_grad():
                    param.copy_(origin + sign * h * u)
                    vals.append(float(terms()["chamfer"]))
                    param.copy_(origin)
            fd.append((vals[0] - vals[1]) / (2 * h))
        assert terms.missing == 0
        assert abs(autograd) > 1e-4
        np.testing.assert_allclose(fd, autograd, rtol=0.02)


def test_curves_figure_from_stored_run_info(tmp_path):
    from eval.reports.curves import curve_figure, curve_runs

    curve = [{"phase": 1, "step": 49, "loss": 0.02, "cd_p2s": 2e-3}, {"phase": 1, "step": 99, "loss": 0.015,
              "cd_p2s": 1.5e-3}, {"phase": 2, "step": 49, "loss": 0.014, "cd_p2s": 1.4e-3}]
    df = pd.DataFrame([
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud", "status": "done",
         "shape": "torus", "category": "closed", "info": {"curve": curve}},
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud", "status": "done",
         "shape": "zz", "category": "closed", "info": {"curve": curve}},     # second closed shape: not drawn
        {"method": "dmesh", "config_label": "", "input_kind": "pointcloud", "status": "done",
         "shape": "torus", "category": "closed", "info": {"curve": curve[:1]}},  # one point: no line
    ])
    runs = curve_runs(df)
    assert [(r["label"], r["shape"]) for r in runs] == [("dmesh [preset=paper]", "torus")]
    from eval.reports.curves import _x

    assert _x(curve) == [50, 100, 150]
    out = curve_figure(runs, tmp_path / "c.png", "t")
    assert out.is_file() and out.stat().st_size > 1000
    assert curve_figure([], tmp_path / "none.png", "t") is None and not (tmp_path / "none.png").exists()


def test_train_phase1_moves_only_what_it_names():
    from datasets.normalize import normalize
    from datasets.sampling import sample_points
    from datasets.synthetic import generate
    from dmesh.recon.pointcloud import PointCloudConfig, reconstruct

    with pytest.raises(ValueError, match="train_phase1"):
        PointCloudConfig(train_phase1=("points", "colour"))
    assert PointCloudConfig(train_phase1="points").train_phase1 == ("points",)
    gt, _ = normalize(generate("sphere"))
    pts, _ = sample_points(gt, 5000, 0)
    base = dict(num_init=300, num_target=2000, num_samples=2000, steps_phase2=0, lr=1e-3, update_bound=1e-3)
    start = reconstruct(pts, None, PointCloudConfig.tiny(**base, steps_phase1=0)).dmesh
    moved = reconstruct(pts, None, PointCloudConfig.tiny(**base, steps_phase1=3, train_phase1=("points",))).dmesh
    assert not torch.equal(start.points, moved.points)
    assert torch.equal(start.weights, moved.weights) and torch.equal(start.reals, moved.reals)
