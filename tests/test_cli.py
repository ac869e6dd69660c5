"""The `dmesh` console script end to end on tiny inputs."""
from __future__ import annotations

import json
import subprocess
import sys


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "eval.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_demo_writes_summary_and_mesh(tmp_path):
    r = run_cli("demo", "-o", str(tmp_path / "out"), "--points", "500")
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "out" / "demo_summary.json").read_text())
    assert summary["tets"] > 0 and summary["faces_on_real_points"] > 0
    import trimesh

    mesh = trimesh.load(tmp_path / "out" / "demo_wdt_faces.ply", process=False)
    assert len(mesh.faces) == summary["faces_on_real_points"]
    assert not list((tmp_path / "out").glob("*.tmp"))


def test_bad_input_is_one_line_error(tmp_path):
    r = run_cli("demo", "-o", str(tmp_path / "out"), "--shape", "no-such-shape")
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "unknown synthetic shape" in r.stderr
    assert not (tmp_path / "out").exists()
