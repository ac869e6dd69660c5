"""The surface ablation's variants come from the stage list, and its figures are what they say."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dmesh.surface import STAGES
from eval.bench import surface_ablation as ablation


def test_variants_leave_out_every_optional_stage_and_run_every_mode():
    names = [name for name, _ in ablation.variants()]
    assert names[0] == "all" and len(set(names)) == len(names)
    assert [n[1:] for n in names if n.startswith("-")] == [s.name for s in STAGES if not s.required]
    assert {"mode=closed", "mode=open"} <= set(names)


def test_boundary_length_of_an_open_tube_is_its_two_rims():
    tube = trimesh.creation.cylinder(radius=0.5, height=1.0, sections=64)
    tube = trimesh.Trimesh(tube.vertices, tube.faces[np.abs(tube.face_normals[:, 2]) < 0.5])
    edges, length = ablation._boundary(np.asarray(tube.vertices), np.asarray(tube.faces))
    assert edges == 128
    assert np.isclose(length, 2 * 64 * 2 * 0.5 * np.sin(np.pi / 64))
    # A file read back with its vertices unmerged has the same rim.
    soup = tube.vertices[tube.faces].reshape(-1, 3)
    assert ablation._boundary(soup, np.arange(len(soup)).reshape(-1, 3)) == (edges, length)


def test_summary_compares_each_variant_with_all_on_the_same_runs():
    def row(shape, variant, cd, rim):
        return {"split": "dev", "class": "open", "shape": shape, "seed": "0", "variant": variant, "cd_p2s": cd,
                "boundary_edges": 10, "boundary_length": rim, "gt_boundary_length": 2.0, "components": 1,
                "watertight": "False", "seconds": 1.0}

    rows = [row("a", "all", 1.0, 2.0), row("b", "all", 2.0, 2.0), row("a", "-lids", 3.0, 1.0),
            row("b", "-lids", 2.0, 1.0)]
    out = {r["variant"]: r for r in ablation.summary(rows)}
    assert np.isclose(out["-lids"]["cd_vs_all"], (3.0 + 1.0) / 2) and out["-lids"]["worst_vs_all"] == 3.0
    assert out["all"]["cd_vs_all"] == 1.0 and out["-lids"]["rim_vs_gt"] == 0.5
    assert [r["variant"] for r in ablation.summary(rows)] == ["all", "-lids"]


def test_variants_filter_keeps_all_and_rejects_unknown_names():
    assert [n for n, _ in ablation.variants(["-fins", "mode=open"])] == ["all", "-fins", "mode=open"]
    assert [n for n, _ in ablation.variants(["fins"])] == ["all", "-fins"]
    with pytest.raises(ValueError, match="-nonesuch"):
        ablation.variants(["-nonesuch"])
