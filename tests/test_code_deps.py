"""What code a run executed (`eval.code_deps`): per-function hashes, module outlines, and which edits leave a
recorded run current. The runner's adoption of such runs is tested in tests/test_runner.py."""
from __future__ import annotations

import ast
import shutil
import textwrap
from pathlib import Path

import numpy as np

from eval import code_deps
from eval.code_deps import file_code
from eval.code_hash import INPUT_VERSION

REPO = Path(__file__).resolve().parents[1]

MODULE = textwrap.dedent('''
    """A module."""
    import math
    import os.path as osp
    from os.path import basename, join

    SCALE = 2.0
    ROOT = join("a", "b")
    HOME = osp.normpath("a")


    def name_of(p):
        return basename(p)


    def _twice(f):
        def inner(x):
            return 2 * f(x)
        return inner


    def _build(i):
        return i * i


    TABLE = [_build(i) for i in range(3)]


    @_twice
    def area(r):
        """Area."""
        return math.pi * r * r * SCALE


    def unused(x):
        return x + 1


    class Box:
        size: int = 3

        def volume(self):
            def cube(s):
                return s ** 3
            return cube(self.size)

        @property
        def side(self):
            return self.size

        @side.setter
        def side(self, value):
            self.size = value
''')


def _hashes(path: Path, text: str):
    path.write_text(text)
    fc = file_code(path)
    return fc.whole, fc.outline, dict(fc.units)


def test_each_function_has_its_own_hash_and_the_outline_holds_what_runs_at_import(tmp_path):
    path = tmp_path / "mod.py"
    whole, outline, units = _hashes(path, MODULE)
    assert set(units) == {"_twice", "_build", "area", "unused", "Box.volume", "Box.side", "name_of"}
    fc = file_code(path)
    # Called at import (by name, or as a module's attribute); `basename` only inside a function.
    assert fc.imported == [("os.path", "join"), ("os.path", "normpath")]
    lines = MODULE.splitlines()
    line = {s.strip(): i + 1 for i, s in enumerate(lines)}
    assert fc.unit_at(line["def inner(x):"]) == "_twice"         # a nested function belongs to its unit
    assert fc.unit_at(line["def cube(s):"]) == "Box.volume"
    assert fc.unit_at(line["@_twice"]) == "area"                 # decorators are part of the def
    assert fc.unit_at(line["SCALE = 2.0"]) is None

    def changed(text):
        w, o, u = _hashes(path, text)
        return w != whole, o != outline, {k for k in units if u.get(k) != units[k]}

    # A body edit changes that function only, not the outline.
    assert changed(MODULE.replace("return x + 1", "return x + 2")) == (True, False, {"unused"})
    assert changed(MODULE.replace("return s ** 3", "return s ** 2")) == (True, False, {"Box.volume"})
    # Both defs of one name (a property's getter and setter) count for it.
    assert changed(MODULE.replace("return self.size", "return 2 * self.size")) == (True, False, {"Box.side"})
    assert changed(MODULE.replace("self.size = value", "self.size = 2 * value")) == (True, False, {"Box.side"})
    # Docstrings, comments and layout change nothing.
    assert changed(MODULE.replace('"""Area."""', '"""The area."""').replace("SCALE = 2.0", "SCALE = 2.0  # x")) \
        == (False, False, set())
    # Module-level code: constants, class bodies, signatures and defaults are in the outline.
    assert changed(MODULE.replace("SCALE = 2.0", "SCALE = 3.0")) == (True, True, set())
    assert changed(MODULE.replace("size: int = 3", "size: int = 4")) == (True, True, set())
    assert changed(MODULE.replace("def unused(x):", "def unused(x, y=1):"))[:2] == (True, True)
    # A function that module-level code calls or decorates with runs at import: its body is in the outline.
    assert changed(MODULE.replace("return i * i", "return i + i")) == (True, True, {"_build"})
    assert changed(MODULE.replace("return 2 * f(x)", "return 3 * f(x)")) == (True, True, {"_twice"})


def _edit_unit(path: Path, name: str) -> None:
    """Appends a statement to the body of function `name` ("f" or "Class.f") of the file `path`."""
    text = path.read_text()
    tree = ast.parse(text)
    body, node = tree.body, None
    for part in name.split("."):
        node = next(n for n in body if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name == part)
        body = node.body
    lines = text.splitlines()
    lines.insert(node.end_lineno, " " * node.body[0].col_offset + "_edited = 1")
    path.write_text("\n".join(lines) + "\n")


def test_a_recorded_run_stays_current_until_code_it_ran_changes(tmp_path):
    """A real point-cloud reconstruction (the `tiny` preset) under `record`: its dependencies hold on a copy of
    the sources; an edit of a function it never ran, or of a docstring, leaves them holding; an edit of a
    function it ran, or of a module-level constant of its closure, does not."""
    import trimesh

    from datasets.synthetic import torus
    from dmesh.recon import pointcloud
    from dmesh.recon.config import PointCloudConfig
    from eval.sweep import get_method

    for pkg in ("dmesh", "baselines", "datasets", "eval"):
        shutil.copytree(REPO / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    mesh = torus()
    points, faces = trimesh.sample.sample_surface(mesh, 3000, seed=0)
    with code_deps.record() as executed:
        pointcloud.reconstruct(np.asarray(points), mesh.face_normals[faces], config=PointCloudConfig.preset("tiny"))
    assert executed, "nothing recorded (is another trace function set?)"
    deps = code_deps.deps_for(get_method("dmesh"), executed, root=tmp_path, code_root=REPO)
    hashes = code_deps.entry_hashes(get_method("dmesh"), executed, root=tmp_path, code_root=REPO)
    assert deps == {"entries": sorted(hashes), "digest": code_deps.digest(hashes)}
    assert all(len(v) == 16 for k, v in hashes.items() if k != "inputs:version")
    ran = {k.split("::")[1] for k in hashes if k.startswith("def:dmesh/recon/pointcloud.py::")}
    assert {"reconstruct", "_reconstruct_once", "_Run.setup"} <= ran
    assert "outline:dmesh/recon/pointcloud.py" in hashes and "file:baselines/dmesh_pointcloud.py" in hashes
    assert hashes["inputs:version"] == str(INPUT_VERSION)  # the input data's version, not the generating code
    assert not any(k.startswith(("file:datasets/", "outline:datasets/")) for k in hashes)
    assert not any(k.startswith(("def:eval/", "outline:eval/")) for k in hashes)  # the harness is not a run's code
    assert code_deps.fresh(deps, tmp_path)

    ran_in = {}
    for k in hashes:
        if k.startswith("def:"):
            path, _, unit = k[4:].partition("::")
            ran_in.setdefault(path, set()).add(unit)
    never = [(path, unit) for path in sorted(ran_in) for unit in sorted(file_code(tmp_path / path).units)
             if unit not in ran_in[path]]
    assert len(never) > 10, "the tiny run executed nearly every function of the files it used"
    for path, unit in never[:5]:
        _edit_unit(tmp_path / path, unit)
        assert code_deps.fresh(deps, tmp_path), f"an edit of {path}::{unit}, which the run never ran, made it stale"

    source = tmp_path / "dmesh" / "recon" / "pointcloud.py"
    text = source.read_text()
    doc = ast.get_docstring(next(n for n in ast.parse(text).body
                                 if isinstance(n, ast.FunctionDef) and n.name == "reconstruct"))
    first = doc.splitlines()[0]
    source.write_text(text.replace(first, first + " Edited.", 1))
    assert code_deps.fresh(deps, tmp_path), "a docstring edit made the run stale"

    _edit_unit(source, "_Run.setup")
    assert not code_deps.fresh(deps, tmp_path)
    source.write_text(text)
    assert code_deps.fresh(deps, tmp_path)
    with open(tmp_path / "dmesh" / "recon" / "loop.py", "a") as f:
        f.write("\nEDITED = 1\n")
    assert not code_deps.fresh(deps, tmp_path)


def test_a_record_from_before_the_input_version_is_migrated_while_it_holds(tmp_path, monkeypatch):
    """A record that held the input generation as whole files becomes the current form while those files are
    unchanged; then a refactor of datasets/ leaves it fresh, and a new INPUT_VERSION makes it stale. A record
    whose code changed is not migrated, nor is a current one."""
    from eval.code_hash import INPUT_MODULES, module_closure
    from eval.sweep import get_method

    for pkg in ("dmesh", "baselines", "datasets", "eval"):
        shutil.copytree(REPO / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    psr = get_method("psr")
    now = code_deps.entry_hashes(psr, [], root=tmp_path)
    inputs = {f"file:{f}": code_deps.current(f"file:{f}", tmp_path) for f in module_closure(INPUT_MODULES, str(tmp_path))}
    old = {**{k: v for k, v in now.items() if k != "inputs:version"}, **inputs}
    legacy = {"entries": sorted(old), "digest": code_deps.digest(old)}
    assert code_deps.fresh(legacy, tmp_path)
    migrated = code_deps.migrate(legacy, psr, tmp_path)
    assert migrated == {"entries": sorted(now), "digest": code_deps.digest(now)}
    assert code_deps.migrate(migrated, psr, tmp_path) is None  # already current
    with open(tmp_path / "datasets" / "families.py", "a") as f:  # a refactor: same data
        f.write("\n\ndef _moved_here():\n    return 1\n")
    assert code_deps.fresh(migrated, tmp_path) and not code_deps.fresh(legacy, tmp_path)
    assert code_deps.migrate(legacy, psr, tmp_path) is None  # holds no longer: stale either way
    monkeypatch.setattr("eval.code_deps.INPUT_VERSION", INPUT_VERSION + 1)
    assert not code_deps.fresh(migrated, tmp_path)


def test_the_record_sees_threads_started_inside_it():
    import threading

    import torch

    from dmesh.geometry import face_normals

    def work():
        face_normals(torch.eye(3, dtype=torch.float64), torch.tensor([[0, 1, 2]]))

    with code_deps.record() as executed:
        t = threading.Thread(target=work)
        t.start()
        t.join()
    assert face_normals.__code__ in executed


def test_nothing_is_recorded_under_another_trace_function():
    import sys

    def other(frame, event, arg):
        return None

    sys.settrace(other)
    try:
        with code_deps.record() as executed:
            pass
    finally:
        sys.settrace(None)
    assert executed is None
    assert not code_deps.fresh(None) and not code_deps.fresh({}) and not code_deps.fresh({"entries": [],
                                                                                           "digest": "0"})


def test_a_store_is_migrated_once(tmp_path):
    """`eval.stored.migrate_records` rewrites the records from before the input version in a store (the runner
    calls it at the start of every sweep, `import-store` after loading an export), then finds none left."""
    from eval.code_hash import INPUT_MODULES, module_closure
    from eval.store import Store
    from eval.stored import migrate_records
    from eval.sweep import get_method

    now = code_deps.entry_hashes(get_method("psr"), [])
    old = {**{k: v for k, v in now.items() if k != "inputs:version"},
           **{f"file:{f}": code_deps.current(f"file:{f}") for f in module_closure(INPUT_MODULES, str(REPO))}}
    row = {"key": "k" * 64, "method": "psr", "config_label": "", "shape": "torus", "category": "closed",
           "input_kind": "pointcloud", "seed": 0, "status": "done", "gt_hash": "0" * 64, "code_version": "0+src.old",
           "code_deps": {"entries": sorted(old), "digest": code_deps.digest(old)}}
    with Store(tmp_path / "s.sqlite") as store:
        store.upsert(row)
        store.upsert({**row, "key": "j" * 64, "method": "no_such_method"})  # unknown: left as it is
        assert migrate_records(store) == 1 and migrate_records(store) == 0
        assert store.get("k" * 64)["code_deps"] == {"entries": sorted(now), "digest": code_deps.digest(now)}
        assert store.get("j" * 64)["code_deps"] == row["code_deps"]


def test_a_run_depends_on_the_native_files_behind_the_wrappers_it_called(tmp_path):
    """A point-cloud `fast` run triangulates and takes no gradient step: its record names the native files
    behind the wrappers it called (triangulation, power diagram), not the face-probability kernels. An edit of
    those kernels leaves it current; an edit of a file it called, or of the build, does not. A record that held
    the whole tree (`tree:native`) is migrated to the files while it holds."""
    import trimesh

    from datasets.synthetic import torus
    from dmesh.recon import pointcloud
    from dmesh.recon.config import PointCloudConfig
    from eval.code_hash import _source_hash
    from eval.sweep import get_method

    for pkg in ("dmesh", "baselines", "datasets", "eval", "native"):
        shutil.copytree(REPO / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    mesh = torus()
    points, faces = trimesh.sample.sample_surface(mesh, 3000, seed=0)
    with code_deps.record() as executed:
        pointcloud.reconstruct(np.asarray(points), mesh.face_normals[faces], config=PointCloudConfig.preset("fast"))
    dmesh_method = get_method("dmesh")
    hashes = code_deps.entry_hashes(dmesh_method, executed, root=tmp_path, code_root=REPO)
    deps = {"entries": sorted(hashes), "digest": code_deps.digest(hashes)}
    native = {k.removeprefix("native:") for k in hashes if k.startswith("native:")}
    assert code_deps.NATIVE_ENTRY not in hashes
    assert {"native/CMakeLists.txt", "native/bindings/bind_wdt.cpp", "native/src/regular_triangulation.cpp",
            "native/src/power_diagram.cpp", "native/src/types.h"} <= native
    assert "native/src/delta_recompute.cpp" not in native and "native/src/soft_render.cpp" not in native
    assert code_deps.fresh(deps, tmp_path)

    def edit(rel: str):
        path = tmp_path / rel
        text = path.read_text()
        path.write_text(text + "\n// edited\n")
        return path, text

    path, text = edit("native/src/delta_recompute.cpp")
    assert code_deps.fresh(deps, tmp_path), "an edit of kernels the run never called made it stale"
    for rel in ("native/src/power_diagram.cpp", "native/src/types.h", "native/CMakeLists.txt"):
        path, text = edit(rel)
        assert not code_deps.fresh(deps, tmp_path), f"an edit of {rel} left the run current"
        path.write_text(text)
    assert code_deps.fresh(deps, tmp_path)

    old = {k: v for k, v in hashes.items() if not k.startswith("native:")}
    old[code_deps.NATIVE_ENTRY] = code_deps.current(code_deps.NATIVE_ENTRY, tmp_path)
    legacy = {"entries": sorted(old), "digest": code_deps.digest(old)}
    assert code_deps.fresh(legacy, tmp_path)
    assert code_deps.migrate(legacy, dmesh_method, tmp_path) == deps
    assert code_deps.migrate(deps, dmesh_method, tmp_path) is None  # already current
    edit("native/src/tet_render.cpp")                               # the tree changed: stale, nothing to keep
    _source_hash.cache_clear()                                      # (a tree's hash is cached per process)
    assert not code_deps.fresh(legacy, tmp_path) and code_deps.migrate(legacy, dmesh_method, tmp_path) is None
    assert code_deps.fresh(deps, tmp_path)


def test_native_files_of_a_wrapper_follow_its_bindings_and_includes(tmp_path):
    """`eval.native_deps`: a wrapper's attribute maps to the bindings file that registers it, then to the local
    includes and each header's implementation; an attribute no bindings file registers gives None (the whole
    tree)."""
    from eval import native_deps

    (tmp_path / "dmesh").mkdir()
    (tmp_path / "dmesh" / "native.py").write_text(textwrap.dedent('''
        from dmesh import _native
        LIMIT = _native.LIMIT

        def tri(p):
            return _native.tri(p)

        def tree(p):
            return _native.Tree(p)

        def lost(p):
            return _native.nowhere(p)

        def plain(p):
            return p
    '''))
    files = {
        "CMakeLists.txt": "project(x)\n",
        "bindings/module.cpp": "// module\n",
        "bindings/bind_a.cpp": ('#include "a.h"\nvoid f(M& m) {\n  m.def(\n      "tri", &tri);\n'
                                '  m.attr("LIMIT") = 3;\n}\n'),
        "bindings/bind_b.cpp": '#include "b.h"\nvoid g(M& m) { nb::class_<T>(m, "Tree", "doc"); }\n',
        "src/a.h": '#include "types.h"\n', "src/a.cpp": '#include "a.h"\n#include "c.h"\n',
        "src/b.h": '#include "types.h"\n', "src/b.cpp": '#include "b.h"\n', "src/c.h": "", "src/types.h": "",
    }
    for rel, text in files.items():
        (tmp_path / "native" / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "native" / rel).write_text(text)
    base = ["native/CMakeLists.txt", "native/bindings/bind_a.cpp", "native/bindings/module.cpp",
            "native/src/a.cpp", "native/src/a.h", "native/src/c.h", "native/src/types.h"]
    assert native_deps.files_for([], tmp_path) == base            # LIMIT, read at import, is bind_a's
    assert native_deps.files_for(["plain"], tmp_path) == base
    assert native_deps.files_for(["tri"], tmp_path) == base
    assert native_deps.files_for(["tree"], tmp_path) == sorted(base + ["native/bindings/bind_b.cpp",
                                                                       "native/src/b.cpp", "native/src/b.h"])
    assert native_deps.files_for(["tri", "lost"], tmp_path) is None
