"""GT orientation at load (`datasets.meshes.orient_outward`): an inside-out closed GT is flipped outward, with
a warning naming the file, before anything is sampled from it; hollow solids, open and non-orientable GTs are
left as they are and reported; and a baseline run on an inside-out GT through the runner faces outward."""
from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from datasets.meshes import load_mesh, orient_outward

ROOT = Path(__file__).resolve().parents[1]


def _inverted(m: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(m.vertices, m.faces[:, ::-1], process=False)


def _hollow() -> trimesh.Trimesh:
    """A solid shell: outer sphere facing out, inner sphere (the cavity wall) facing in, towards the cavity."""
    outer = trimesh.creation.icosphere(2)
    inner = _inverted(trimesh.creation.icosphere(2, radius=0.5))
    return trimesh.util.concatenate([outer, inner])


def test_inside_out_closed_mesh_is_flipped():
    s = trimesh.creation.icosphere(2)
    out, status = orient_outward(_inverted(s), name="x")
    assert status == "flipped" and out.metadata["orientation"] == "flipped"
    np.testing.assert_array_equal(out.faces, s.faces)            # exactly the original winding back
    out, status = orient_outward(s)
    assert status == "outward" and out is not s and np.array_equal(out.faces, s.faces)
    assert "orientation" not in s.metadata                        # the caller's mesh is not touched


def test_hollow_solid_keeps_its_cavity_and_flips_as_a_whole():
    h = _hollow()
    out, status = orient_outward(h)
    assert status == "outward" and np.array_equal(out.faces, h.faces)
    out, status = orient_outward(_inverted(h))
    assert status == "flipped" and np.array_equal(out.faces, h.faces)


def test_open_non_orientable_and_inconsistent_are_reported_not_changed():
    from datasets.synthetic import generate

    bowl = generate("bowl", seed=0)                  # open, and its signed "volume" is negative
    out, status = orient_outward(bowl)
    assert status == "open" and np.array_equal(out.faces, bowl.faces)
    mobius = generate("mobius", seed=0)
    out, status = orient_outward(mobius)
    assert status == "non_orientable" and np.array_equal(out.faces, mobius.faces)
    s = trimesh.creation.icosphere(2)
    f = s.faces.copy()
    f[:4] = f[:4, ::-1]
    out, status = orient_outward(trimesh.Trimesh(s.vertices, f, process=False))
    assert status == "inconsistent" and np.array_equal(out.faces, f)


def test_load_mesh_orients_only_when_asked(tmp_path, caplog):
    path = tmp_path / "inside_out.obj"
    _inverted(trimesh.creation.icosphere(2)).export(path)
    assert load_mesh(path).volume < 0                             # a prediction is read as it is
    with caplog.at_level(logging.WARNING, logger="datasets.meshes"):
        gt = load_mesh(path, orient=True)
    assert gt.volume > 0 and gt.metadata["orientation"] == "flipped"
    assert any(str(path) in r.getMessage() and "inside-out" in r.getMessage() for r in caplog.records)


def test_mobius_gt_is_reported_non_orientable_by_the_cli(tmp_path, capsys):
    from datasets.synthetic import generate
    from eval.cli import main

    gt = tmp_path / "mobius.ply"
    generate("mobius", seed=0).export(gt)
    assert main(["metrics", str(gt), str(gt), "--samples", "2000", "--json", "--no-self-intersections"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["gt_orientation"] == "non_orientable" and data["gt_orientable"] is False
    assert data["normal_consistency_oriented"] is None and data["oriented_fraction"] is None
    assert data["normal_consistency"] > 0.99


def test_baseline_on_an_inside_out_gt_faces_outward(tmp_path):
    """An inside-out sphere file through the runner: its cached GT and sampled normals face outward, and so
    does screened Poisson's output (which follows the input normals)."""
    pytest.importorskip("pymeshlab")
    from eval.runner import RunnerConfig
    from eval.store import Store

    path = tmp_path / "inside_out_sphere.ply"
    _inverted(trimesh.creation.icosphere(3)).export(path)
    runner = RunnerConfig(work=str(tmp_path / "work"))
    # In a fresh interpreter: the runner forks its run process, and a fork of this test process (whose earlier
    # tests started OpenMP thread pools) can deadlock in pymeshlab's OpenMP code.
    script = (f"from eval.runner import RunnerConfig, run_sweep; from eval.sweep import Sweep; "
              f"s = run_sweep(Sweep(methods=('psr',), shapes=({str(path)!r},), n_points=3000, metric_samples=3000, "
              f"configs={{'psr': ({{'depth': 5}},)}}), RunnerConfig(work={runner.work!r})); print(s.done)")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0 and r.stdout.split()[-1] == "1", r.stderr[-2000:]
    folder = next((tmp_path / "work" / "inputs").iterdir())
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["orientation"] == "flipped"
    assert trimesh.load(folder / "gt.ply", process=False).volume > 0
    with np.load(folder / "pc_n3000_s0.npz") as z:               # sphere at the origin: normals point out
        assert (np.einsum("nc,nc->n", z["points"], z["normals"]) > 0).all()
    with Store(runner.db_path) as store:
        (row,) = store.rows()
    m = row["metrics_json"]
    assert m["gt_orientation"] == "flipped" and m["gt_orientable"] is True
    assert m["oriented_fraction"] >= 0.99 and m["normal_consistency_oriented"] > 0.9
    out = trimesh.load(runner.db_path.parent / row["mesh_path"], process=False)
    assert out.volume > 0
