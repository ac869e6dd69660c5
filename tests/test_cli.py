"""The `dmesh` console script end to end on tiny inputs."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "eval.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_demo_writes_table_and_meshes(tmp_path):
    r = run_cli("-q", "demo", "-o", str(tmp_path / "out"), "--tiny")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "out"
    summary = json.loads((out / "demo_summary.json").read_text())
    assert set(summary["metrics"]) == {"dmesh", "psr"} and summary["class"] == "mixed"
    assert summary["metrics"]["dmesh"]["faces"] > 0 and summary["metrics"]["psr"]["faces"] > 0
    table = (out / "demo_table.md").read_text()
    assert "| dmesh |" in table and "| psr |" in table
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
