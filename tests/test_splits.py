"""datasets.splits and datasets.families: the dev / test splits, the smooth test families, the test sweeps."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common import shared_mesh
from datasets import families, fine_mesh, meshes, splits, synthetic

REPO = Path(__file__).resolve().parents[1]
FAMILY_NAMES = list(families.FAMILIES)
#: Input points of the fast checks: the families' default resolution follows `samples`, so 2,000 samples
#: give meshes of about 30K faces that pass through the same code as the 100K-sample defaults (2M faces).
FAST_SAMPLES = 2_000


def _sweep(name):
    from eval.sweep import Sweep

    return Sweep.from_yaml(REPO / "eval" / "sweeps" / f"{name}.yaml")


# ------------------------------------------------------------------------------------------------ families

@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_family_is_deterministic_per_seed_with_its_class(name):
    cls = families.FAMILIES[name][0]
    a = synthetic.generate(name, seed=1, samples=FAST_SAMPLES)
    b = synthetic.generate(name, seed=1, samples=FAST_SAMPLES)
    c = synthetic.generate(name, seed=2, samples=FAST_SAMPLES)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert not (a.vertices.shape == c.vertices.shape and np.allclose(a.vertices, c.vertices)), \
        "the seed should change the shape"
    assert synthetic.SHAPES[name][0] == cls
    assert meshes.classify(a) == cls
    # Merging by position (what load_mesh does) must not change the class: parts never share vertices.
    merged = a.copy()
    merged.merge_vertices()
    assert meshes.classify(merged) == cls
    _, closed = meshes.components(a)
    if cls == "closed":
        assert a.is_watertight and a.volume > 0
    elif cls == "open":
        assert not closed.any()
    else:
        assert closed.any() and (~closed).any()


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_family_is_smooth_at_the_sampling_scale(name):
    # The same rule as at 100K samples (the slow test below), at FAST_SAMPLES: every edge of the normalised
    # mesh shorter than the mean nearest-neighbour spacing of that many area-uniform samples.
    ratio, _, _ = splits.edge_to_spacing(synthetic.generate(name, seed=0, samples=FAST_SAMPLES), FAST_SAMPLES)
    assert ratio < 1.0


@pytest.mark.slow
@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_family_default_is_smooth_at_100k_samples(name):
    ratio, edge, spacing = splits.edge_to_spacing(synthetic.generate(name, seed=0), 100_000)
    assert ratio < 1.0, f"{name}: longest edge {edge:.4g} >= sample spacing {spacing:.4g}"


def test_family_topology():
    assert synthetic.generate("thin_cup", samples=FAST_SAMPLES).euler_number == 2
    assert synthetic.generate("bracket", samples=FAST_SAMPLES).euler_number == -6  # 4 through-holes
    tree = synthetic.generate("vessel", samples=FAST_SAMPLES)
    # One tube tree with 1 + 4 cut ends: a sphere with 5 holes.
    assert len(meshes.components(tree)[1]) == 1 and tree.euler_number == 2 - 5


def test_thin_cup_wall_is_one_percent_of_its_radius():
    cup = synthetic.generate("thin_cup", samples=FAST_SAMPLES)
    v = np.asarray(cup.vertices)
    # A thin shell's volume is its thickness times half its area (outer and inner sides). The wall is 1 % of
    # the cup's base radius; the widest radius (Y-up: around the y axis) is 1 to 1.28 times that.
    thickness = cup.volume / (cup.area / 2)
    assert 0.007 < thickness / np.hypot(v[:, 0], v[:, 2]).max() < 0.011


def test_edge_split_keeps_a_closed_mesh_closed():
    import trimesh

    box = trimesh.creation.box(extents=[1.0, 0.5, 0.2])
    out = fine_mesh.split_long_edges(box, 0.1)
    assert out.is_watertight and out.edges_unique_length.max() <= 0.1
    assert np.isclose(out.volume, box.volume) and np.isclose(out.area, box.area)


# ------------------------------------------------------------------------------------------------ splits

def test_splits_are_disjoint_and_test_has_five_per_class():
    dev, test = set(splits.shapes("dev")), set(splits.shapes("test"))
    assert len(dev) == 12 and not dev & test
    assert not {splits._shape_id(s) for s in dev} & {splits._shape_id(s) for s in test}
    for cls in splits.CLASSES:
        assert len(splits.shapes("test", cls)) >= 5
        assert len(splits.shapes("dev", cls)) == 4


def test_split_of_names_specs_and_ids():
    assert splits.split_of("torus") == "dev"
    assert splits.split_of("torus@3") == "dev"
    assert splits.split_of("closed/spot.obj") == splits.split_of("spot") == "dev"
    assert splits.split_of("vessel") == "test" and splits.split_of("fandisk") == "test"
    assert splits.split_of("beetle") == "test" and splits.shape_class("mixed/beetle.obj") == "open"
    assert splits.split_of("teacup") is None
    with pytest.raises(ValueError, match="unknown split"):
        splits.shapes("train")
    with pytest.raises(ValueError, match="unknown shape class"):
        splits.shapes("test", "solid")


def test_dev_split_is_paper_yaml_table_2():
    assert list(_sweep("paper").shapes) == splits.shapes("dev")


@pytest.mark.parametrize("spec", [s for s in splits.shapes("test") if s in synthetic.SHAPES])
def test_every_synthetic_test_shape_loads_with_its_class(spec):
    params = {"samples": FAST_SAMPLES} if spec in families.FAMILIES else {}
    assert meshes.classify(synthetic.generate(spec, **params)) == splits.TEST[spec]
    assert synthetic.SHAPES[spec][0] == splits.TEST[spec]


@pytest.mark.parametrize("spec", [s for s in splits.shapes("test") if s not in synthetic.SHAPES])
def test_every_shared_test_mesh_loads_with_its_class(spec):
    m = meshes.load_mesh(shared_mesh(spec))
    assert meshes.classify(m) == splits.TEST[spec]


# ------------------------------------------------------------------------------------------------ sweeps

def _method_configs(sweep, methods):
    return {m: [dict(c) for c in sweep.configs.get(m, ({},))] for m in methods}


@pytest.mark.parametrize("name, kind", [("test", "pointcloud"), ("test_scan", "pointcloud"),
                                        ("test_multiview", "multiview")])
def test_test_sweeps_run_paper_yaml_methods_and_configs(name, kind):
    from eval.sweep import get_method

    paper, sweep = _sweep("paper"), _sweep(name)
    paper_methods = [m for m in paper.methods if get_method(m).input_kind == kind]
    assert sorted(sweep.methods) == sorted(paper_methods), "test sweeps run paper.yaml's methods of their input"
    assert _method_configs(sweep, sweep.methods) == _method_configs(paper, sweep.methods), \
        "configs must equal paper.yaml's (change both together)"
    for field in ("n_points", "radius", "metric_samples") + (("views", "resolution", "distance")
                                                             if kind == "multiview" else ()):
        assert getattr(sweep, field) == getattr(paper, field), field


def test_test_sweeps_list_the_test_split():
    assert list(_sweep("test").shapes) == splits.shapes("test")
    assert list(_sweep("test_multiview").shapes) == splits.shapes("test")
    assert list(_sweep("test_scan").shapes) == splits.shapes("test", "closed")
    assert _sweep("test").seeds == (0, 1, 2) and _sweep("test_multiview").seeds == (0,)
    assert [dict(v) for v in _sweep("test_scan").variants] == [{"scan": 6}]
