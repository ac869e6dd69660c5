"""No data file runs code, and no command reads a value of the user's as an option (issue 57).

Two parts. A source check over the project's Python: no `torch.load` without `weights_only=True`, no pickle
loads, no `allow_pickle=True`, no YAML load without a safe loader, and (outside the tests) no `subprocess` call
that puts a value it did not write itself where the program reads options. Then the state files of resumable runs: a state
whose unpickling would call `os.system` is refused in one line, and the command runs nothing.
"""
from __future__ import annotations

import ast
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dmesh.recon.loop import load_state, save_state

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("dmesh", "eval", "datasets", "baselines", "tools", "tests")


def _sources():
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), path.read_text()


def _calls(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            owner = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else ""
            yield node, owner, name


def _keyword(node: ast.Call, name: str):
    for kw in node.keywords:
        if kw.arg == name:
            return kw.value
    return None


def _is_true(value) -> bool:
    return isinstance(value, ast.Constant) and value.value is True


#: Markers after which a program reads no more options (git's and POSIX's).
END_OF_OPTIONS = ("--", "--end-of-options")


def _unsafe_argument(node: ast.Call, line: str) -> str | None:
    """The first element of a subprocess call's argument list that a user value could make an option: not a
    string the code wrote, not after an end-of-options marker, and not a line marked `# option-safe: why`."""
    if "# option-safe:" in line or not node.args:
        return None
    args = node.args[0]
    if not isinstance(args, (ast.List, ast.Tuple)):
        return ast.unparse(args)
    ended = False
    for element in args.elts:
        if isinstance(element, ast.Constant) and isinstance(element.value, str):
            ended = ended or element.value in END_OF_OPTIONS
            continue
        if not ended and ast.unparse(element) not in ("sys.executable",):
            return ast.unparse(element)
    return None


def test_no_source_loads_code_from_data():
    found = []
    for rel, text in _sources():
        if rel == "tests/test_security.py":
            continue
        lines = text.splitlines()
        for node, owner, name in _calls(ast.parse(text)):
            where = f"{rel}:{node.lineno}"
            if owner == "torch" and name == "load" and not _is_true(_keyword(node, "weights_only")):
                found.append(f"{where}: torch.load without weights_only=True")
            if owner in ("pickle", "cPickle", "dill", "joblib", "marshal") and name in ("load", "loads"):
                found.append(f"{where}: {owner}.{name}")
            if _is_true(_keyword(node, "allow_pickle")) and not rel.startswith("tests/"):
                found.append(f"{where}: allow_pickle=True")
            if owner == "yaml" and name in ("unsafe_load", "full_load", "load_all", "unsafe_load_all"):
                found.append(f"{where}: yaml.{name}")
            if owner == "yaml" and name == "load":
                loader = _keyword(node, "Loader")
                if loader is None or "Safe" not in ast.unparse(loader) and "_yaml_loader" not in ast.unparse(loader):
                    found.append(f"{where}: yaml.load without a safe loader")
            if (owner == "subprocess" and name in ("run", "call", "check_call", "check_output", "Popen")
                    and not rel.startswith("tests/")):  # tests pass values they wrote themselves
                bad = _unsafe_argument(node, lines[node.lineno - 1])
                if bad is not None:
                    found.append(f"{where}: subprocess argument {bad} where options are read")
    assert not found, "\n".join(found)


def test_the_sweep_yaml_loader_is_a_safe_loader():
    import yaml

    from eval.sweep import _yaml_loader

    assert issubclass(_yaml_loader(), yaml.SafeLoader)


def test_the_source_check_sees_what_it_looks_for():
    """The checks above find each pattern they look for, on a sample of bad code (a check that finds nothing
    would pass on any source)."""
    bad = ("torch.load(p)\ntorch.load(p, weights_only=False)\npickle.loads(b)\nnp.load(p, allow_pickle=True)\n"
           "yaml.load(t)\nyaml.full_load(t)\nsubprocess.run(['git', 'show', rev])\n")
    tree = ast.parse(bad)
    lines = bad.splitlines()
    hits = 0
    for node, owner, name in _calls(tree):
        if owner == "torch" and not _is_true(_keyword(node, "weights_only")):
            hits += 1
        hits += owner == "pickle"
        hits += _is_true(_keyword(node, "allow_pickle"))
        hits += owner == "yaml"
        hits += owner == "subprocess" and _unsafe_argument(node, lines[node.lineno - 1]) == "rev"
    assert hits == 7
    safe = ast.parse("subprocess.run(['git', 'rev-parse', '--verify', '--end-of-options', rev])")
    assert all(_unsafe_argument(node, "") is None for node, owner, _ in _calls(safe) if owner == "subprocess")


# ------------------------------------------------------------------------------------------- state files

class _Shell:
    """Unpickled by the full unpickler, this runs `touch MARKER` (what a hostile state file would do)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _hostile_state(path: Path, marker: Path) -> None:
    torch.save({"fingerprint": "x", "points": torch.zeros(2, 3), "payload": _Shell(marker)}, path)


def test_a_hostile_state_is_refused_and_runs_nothing(tmp_path):
    state, marker = tmp_path / "state.pt", tmp_path / "PWNED"
    _hostile_state(state, marker)
    with pytest.raises(ValueError, match=r"not a DMesh state \(it names posix.system"):
        load_state(state, "x")
    assert not marker.exists()


def test_a_state_written_by_a_run_loads_with_its_own_types(tmp_path):
    """The probability pass's caches (objects of the library's classes, with NumPy arrays) are in the
    weights-only allowlist: a real run's state round-trips."""
    from dmesh.model import DMesh

    rng = np.random.default_rng(0)
    dm = DMesh(rng.random((40, 3)), np.zeros(40), np.ones(40))
    dm.face_probabilities()
    save_state(tmp_path / "s.pt", {"fingerprint": "f", "probability": dm.state,
                                   "rng": np.random.default_rng(1).bit_generator.state})
    back = load_state(tmp_path / "s.pt", "f")
    assert type(back["probability"]) is type(dm.state) and back["probability"].passes == dm.state.passes
    assert back["rng"] == np.random.default_rng(1).bit_generator.state


def _digests(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_reconstruct_refuses_a_hostile_state_in_one_line(tmp_path):
    """Through the CLI in its own process (so stderr is what a terminal shows): exit 2, one line, the marker
    never made, the folder as it was."""
    pts = np.random.default_rng(0).normal(size=(300, 3))
    np.save(tmp_path / "pts.npy", pts / np.linalg.norm(pts, axis=1, keepdims=True))  # a clean sphere
    state, marker = tmp_path / "state.pt", tmp_path / "PWNED"
    _hostile_state(state, marker)
    before = _digests(tmp_path)
    got = subprocess.run([sys.executable, "-m", "eval.cli", "-q", "reconstruct", "pointcloud",
                          str(tmp_path / "pts.npy"), "-o", str(tmp_path / "out.obj"), "--preset", "tiny",
                          "--state", str(state)], capture_output=True, text=True, cwd=ROOT)
    assert got.returncode == 2, got.stderr
    assert got.stderr.count("\n") == 1 and "not a DMesh state" in got.stderr, got.stderr
    assert not marker.exists() and _digests(tmp_path) == before


@pytest.mark.parametrize("name,content,fragment", [
    ("comments.xyz", b"# a header and nothing else\n", "no points"),
    ("flat.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n", "no face has a positive area"),
])
def test_quiet_failures_are_one_line_on_a_terminal(tmp_path, name, content, fragment):
    """Warnings printed before an error once made two or more lines under -q (numpy's UserWarning with its
    source line; a winding warning before a GT's error)."""
    (tmp_path / name).write_bytes(content)
    got = subprocess.run([sys.executable, "-m", "eval.cli", "-q", "reconstruct", "pointcloud",
                          str(tmp_path / name), "-o", str(tmp_path / "out.obj")], capture_output=True, text=True,
                         cwd=ROOT)
    assert got.returncode == 2 and got.stderr.count("\n") == 1 and fragment in got.stderr, got.stderr
    assert got.stdout == "" and not (tmp_path / "out.obj").exists()
