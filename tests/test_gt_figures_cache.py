"""The GT's own figures are computed once per GT file (`eval.execute.with_gt_figures`) and score exactly as
when each run computed them."""
from __future__ import annotations

import json

import numpy as np
import trimesh

from eval.code_hash import metrics_version
from eval.execute import with_gt_figures
from eval.inputs import load_gt
from eval.io import write_mesh
from eval.metrics import GT_FIGURES_KEY, compute_metrics


def _gt_file(tmp_path, mesh):
    path = tmp_path / "gt.ply"
    write_mesh(mesh, path)
    (tmp_path / "meta.json").write_text(json.dumps({"orientation": "outward"}))
    return path


def _pred():
    m = trimesh.creation.icosphere(2)
    m.vertices = m.vertices * 1.02 + 0.01
    return m


def test_cached_figures_score_the_same(tmp_path):
    path = _gt_file(tmp_path, trimesh.creation.icosphere(3))
    plain = compute_metrics(_pred(), load_gt(path), n=5000)
    cached = compute_metrics(_pred(), with_gt_figures(load_gt(path), path), n=5000)
    saved = json.loads((tmp_path / "gt_figures.json").read_text())
    assert saved["metrics_version"] == metrics_version() and len(saved["gt_sha256"]) == 64
    again = compute_metrics(_pred(), with_gt_figures(load_gt(path), path), n=5000)   # read back from the file
    for m in (cached, again):
        assert m.keys() == plain.keys()
        assert all(m[k] == plain[k] or (m[k] != m[k] and plain[k] != plain[k]) for k in plain)


def test_the_cache_is_read_only_for_the_same_file_and_version(tmp_path):
    path = _gt_file(tmp_path, trimesh.creation.icosphere(3))
    with_gt_figures(load_gt(path), path)
    cache = tmp_path / "gt_figures.json"
    saved = json.loads(cache.read_text())
    saved["figures"]["gt_components"] = 99                # marks figures that came from the file
    cache.write_text(json.dumps(saved))
    assert with_gt_figures(load_gt(path), path).metadata[GT_FIGURES_KEY]["gt_components"] == 99
    cache.write_text(json.dumps({**saved, "metrics_version": "metrics-v0"}))   # another metrics version
    assert with_gt_figures(load_gt(path), path).metadata[GT_FIGURES_KEY]["gt_components"] == 1
    saved = json.loads(cache.read_text())
    saved["figures"]["gt_components"] = 99
    cache.write_text(json.dumps(saved))
    write_mesh(trimesh.creation.icosphere(2), path)       # another GT in the same place
    assert with_gt_figures(load_gt(path), path).metadata[GT_FIGURES_KEY]["gt_components"] == 1


def test_a_gt_the_metrics_would_turn_is_not_cached(tmp_path):
    inside_out = trimesh.creation.icosphere(3)
    inside_out.faces = np.ascontiguousarray(inside_out.faces[:, ::-1])
    path = tmp_path / "gt.ply"
    write_mesh(inside_out, path)
    raw = trimesh.load(path, process=False, force="mesh")  # not through load_gt, which turns it outward
    out = with_gt_figures(raw, path)
    assert GT_FIGURES_KEY not in out.metadata and not (tmp_path / "gt_figures.json").exists()
    assert compute_metrics(_pred(), out, n=2000)["gt_orientation"] == "flipped"
