"""dmesh.recon.config: presets, their recipes, overrides and the checks every entry point shares."""
from __future__ import annotations

import pytest

from dmesh.recon.config import MULTIVIEW_PRESETS, POINTCLOUD_PRESETS, PointCloudConfig, as_tuple
from dmesh.recon.multiview_config import MultiViewConfig


def test_from_preset_applies_overrides_to_the_named_preset():
    cfg = PointCloudConfig.from_preset("paper", {"lr": 1e-4})
    assert cfg == PointCloudConfig.paper(lr=1e-4) and cfg.num_init == 10_000
    assert PointCloudConfig.from_preset() == PointCloudConfig.fast()
    for name in MULTIVIEW_PRESETS:
        assert MultiViewConfig.from_preset(name) == MultiViewConfig.preset(name)
    for name in POINTCLOUD_PRESETS:
        assert PointCloudConfig.from_preset(name) == PointCloudConfig.preset(name)


def test_unknown_keys_and_presets_are_one_line_errors_naming_them():
    with pytest.raises(ValueError, match=r"dmesh: unknown config keys \['bogus'\]; known: .*'lr'"):
        PointCloudConfig.from_preset("fast", {"bogus": 1}, owner="dmesh")
    with pytest.raises(ValueError, match="unknown preset 'depth'"):
        PointCloudConfig.from_preset("depth")


def test_a_scalar_means_the_same_in_every_tuple_field():
    assert PointCloudConfig(freeze_phase2=5).freeze_phase2 == (5,) == PointCloudConfig(freeze_phase2=[5]).freeze_phase2
    assert MultiViewConfig(freeze_phase2=3).freeze_phase2 == (3,)
    assert MultiViewConfig(refine_seeds=500, steps_phase1=9, steps_phase2=9).refine_seeds == (500,)
    assert PointCloudConfig(knn_thresholds=0.5).knn_thresholds == (0.5,)
    assert MultiViewConfig(steps_phase1=7).steps_phase1 == (7,) * 4  # per-epoch fields repeat a scalar
    for bad in ("abc", [1, "x"], [1.5], True):
        with pytest.raises(ValueError, match="freeze_phase2"):
            PointCloudConfig(freeze_phase2=bad)
    assert as_tuple(2.0, int, "f") == (2,)


@pytest.mark.parametrize("kind", ["pointcloud", "multiview"])
def test_every_preset_has_a_recipe(kind):
    from dmesh.recon import config, multiview_config

    recipes = getattr(config if kind == "pointcloud" else multiview_config, f"{kind.upper()}_RECIPES")
    assert set(recipes) == set(getattr(config, f"{kind.upper()}_PRESETS"))
    for steps, text in recipes.values():
        assert isinstance(steps, bool) and len(text) > 20
    # The rows the harness shows by default are the fast presets: one takes steps, one does not.
    assert config.POINTCLOUD_RECIPES["fast"][0] is False and multiview_config.MULTIVIEW_RECIPES["fast"][0] is True


def test_a_point_cloud_recipe_says_gradient_steps_exactly_when_its_preset_takes_some():
    """The tables label each row "gradient steps" or "initialisation" from the recipe; the preset decides."""
    from dmesh.recon.config import POINTCLOUD_RECIPES

    for preset, (steps, _) in POINTCLOUD_RECIPES.items():
        cfg = PointCloudConfig.preset(preset)
        assert steps == (cfg.steps_phase1 + cfg.steps_phase2 > 0), preset


def test_pointcloud_config_validation():
    with pytest.raises(ValueError, match="num_init"):
        PointCloudConfig(num_init=0)
    with pytest.raises(ValueError, match="unknown preset"):
        PointCloudConfig.preset("slow")
    assert PointCloudConfig.paper().steps_phase1 == 1000 and PointCloudConfig.paper().num_init == 10_000


def test_multiview_config_validation():
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
    with pytest.raises(ValueError, match="reseed_phong"):
        MultiViewConfig(reseed_phong=1.5)
    with pytest.raises(ValueError, match="init_preset"):
        MultiViewConfig(init="depth", init_preset="slow")
    with pytest.raises(ValueError, match="init_pool_k"):
        MultiViewConfig(init="depth", init_pool_k=3)
    depth = MultiViewConfig.depth()
    assert depth.init == "depth" and depth.epochs == 1 and depth.total_steps() == 0
    paper = MultiViewConfig.paper()
    assert paper.epochs == 4 and paper.refine_seeds == (1000, 3000, 10_000) and paper.grid == 20
    assert paper.steps_phase1 == (500,) * 4 and paper.steps_phase2 == (500,) * 4
    assert MultiViewConfig(steps_phase1=7).steps_phase1 == (7,) * 4
