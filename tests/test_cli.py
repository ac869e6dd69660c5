"""The `dmesh` console script end to end on tiny inputs, and its point readers."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "eval.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_demo_writes_table_and_meshes(tmp_path):
    r = run_cli("-q", "demo", "-o", str(tmp_path / "out"), "--tiny")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "out"
    summary = json.loads((out / "demo_summary.json").read_text())
    assert set(summary["metrics"]) == {"dmesh", "psr", "bpa"} and summary["class"] == "mixed"
    assert all(m["faces"] > 0 for m in summary["metrics"].values())
    table = (out / "demo_table.md").read_text()
    assert "| dmesh [tiny: 10 gradient steps; steps_phase2=8] |" in table and "| psr [depth=6] |" in table and "| bpa |" in table
    import trimesh

    mesh = trimesh.load(out / "dmesh.obj", process=False)
    assert len(mesh.faces) == summary["metrics"]["dmesh"]["faces"]
    assert (out / "demo_renders.png").exists() or summary["renders_skipped"]
    assert not list(out.glob(".*tmp*"))


def test_bad_input_is_one_line_error(tmp_path):
    r = run_cli("demo", "-o", str(tmp_path / "out"), "--shape", "no-such-shape")
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "unknown synthetic shape" in r.stderr
    assert not (tmp_path / "out").exists()


def test_cli_lists_the_library_presets_without_importing_torch():
    code = ("import sys, argparse; from eval.commands import reconstruct as r; p = argparse.ArgumentParser(); "
            "r.add_arguments(p); a = [x for x in p._actions if x.dest == 'preset'][0]; "
            "print(' '.join(a.choices), 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True).stdout
    *names, torch_loaded = out.split()
    from dmesh.recon.config import MULTIVIEW_PRESETS, POINTCLOUD_PRESETS

    assert set(names) == set(POINTCLOUD_PRESETS) | set(MULTIVIEW_PRESETS) and torch_loaded == "False"


def test_read_points_formats(tmp_path):
    from eval.commands.reconstruct import read_points

    rng = np.random.default_rng(0)
    p, n = rng.random((30, 3)), rng.normal(size=(30, 3))
    with open(tmp_path / "pts.ply", "w") as f:
        f.write("ply\nformat ascii 1.0\nelement vertex 30\n" + "".join(f"property float {c}\n" for c in
                ("x", "y", "z", "nx", "ny", "nz")) + "end_header\n")
        f.writelines(" ".join(f"{v:.6f}" for v in row) + "\n" for row in np.c_[p, n])
    pts, nrm = read_points(tmp_path / "pts.ply")
    assert np.allclose(pts, p, atol=1e-5) and np.allclose(nrm, n, atol=1e-5)
    np.savetxt(tmp_path / "pts.xyz", p)
    pts, nrm = read_points(tmp_path / "pts.xyz")
    assert np.allclose(pts, p) and nrm is None
    import trimesh

    trimesh.creation.icosphere(2).export(tmp_path / "ball.obj")
    pts, nrm = read_points(tmp_path / "ball.obj", samples=500)
    assert pts.shape == (500, 3) and nrm.shape == (500, 3)
    with pytest.raises(ValueError, match="unsupported"):
        (tmp_path / "x.abc").write_text("1 2 3\n")
        read_points(tmp_path / "x.abc")
