"""dmesh.recon.config: presets, overrides and the checks every entry point shares."""
from __future__ import annotations

import pytest

from dmesh.recon.config import MULTIVIEW_PRESETS, POINTCLOUD_PRESETS, MultiViewConfig, PointCloudConfig, as_tuple


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
