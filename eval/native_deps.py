"""Which native sources a run executed: the files behind the `dmesh.native` wrappers it called.

`dmesh/native.py` is the one module that imports the compiled core (`dmesh._native`), with one Python wrapper
per native entry point, and a run's record (`eval.code_deps`) names the wrappers it executed
(`def:dmesh/native.py::NAME`). A wrapper depends on:

- the bindings file that registers each `_native` attribute it names (`m.def("name", ...)`,
  `m.attr("name")`, `nb::class_<T>(m, "Name", ...)`; a class brings its methods);
- every local file that file includes (`#include "x.h"`), transitively, and for each included header
  `native/src/X.h` its implementation `native/src/X.cpp`, with what that includes in turn.

Every run that loads the module also depends on the build (`native/CMakeLists.txt`), the module's entry
(`native/bindings/module.cpp`) and what `dmesh/native.py` reads from `_native` at import. So an edit of the
face-probability kernels (`native/src/delta_recompute.cpp`) leaves current the runs that never called them (the
point-cloud `fast` preset triangulates and takes no gradient step), where one hash of the whole tree made
every DMesh run stale. The answer is conservative at file level (a wrapper depends on the whole of each file it
reaches), and a wrapper that names an attribute no bindings file registers gives None: the caller then
depends on the whole tree, as before.
"""
from __future__ import annotations

import ast
import functools
import hashlib
import re
from pathlib import Path

#: The module whose functions wrap the native entry points, and the name it imports the core as.
WRAPPERS = "dmesh/native.py"
CORE = "_native"
#: Native files every run that loads the module depends on.
ALWAYS = ("native/CMakeLists.txt", "native/bindings/module.cpp")
BINDINGS, SOURCES = "native/bindings", "native/src"

_REGISTERS = re.compile(r'(?:\bm\.(?:def|attr)\(\s*|\(\s*m\s*,\s*)"(\w+)"')
_INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.MULTILINE)


def _mtimes(root: Path, paths) -> tuple:
    out = []
    for p in paths:
        try:
            st = (root / p).stat()
            out.append((str(p), st.st_mtime_ns, st.st_size))
        except OSError:
            out.append((str(p), None, None))
    return tuple(out)


def wrapper_names(root: Path) -> tuple[dict[str, frozenset], frozenset]:
    """({wrapper function: the `_native` attributes it names}, the attributes module-level code names) of
    `dmesh/native.py` under `root`."""
    return _wrapper_names(str(root), _mtimes(root, [WRAPPERS]))


@functools.lru_cache(maxsize=8)
def _wrapper_names(root: str, stamp: tuple) -> tuple[dict[str, frozenset], frozenset]:
    path = Path(root) / WRAPPERS
    if not path.is_file():
        return {}, frozenset()
    tree = ast.parse(path.read_bytes(), str(path))

    def names(node) -> frozenset:
        return frozenset(n.attr for n in ast.walk(node) if isinstance(n, ast.Attribute)
                         and isinstance(n.value, ast.Name) and n.value.id == CORE)

    funcs = {n.name: names(n) for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    module_level = [n for n in tree.body if not isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    return funcs, frozenset().union(*(names(n) for n in module_level))


def registered(root: Path) -> dict[str, str]:
    """{`_native` attribute: the bindings file (relative path) that registers it} under `root`."""
    files = sorted(p.relative_to(root).as_posix() for p in (root / BINDINGS).glob("*.cpp"))
    return _registered(str(root), _mtimes(root, files))


@functools.lru_cache(maxsize=8)
def _registered(root: str, stamp: tuple) -> dict[str, str]:
    out: dict[str, str] = {}
    for rel, _, _ in stamp:
        text = (Path(root) / rel).read_text(errors="replace")
        for name in _REGISTERS.findall(text):
            out.setdefault(name, rel)
    return out


def closure(files, root: Path) -> set[str]:
    """`files` (relative paths) with the local files they include, transitively, and each included
    `native/src` header's implementation."""
    todo, seen = list(files), set()
    while todo:
        rel = todo.pop()
        if rel in seen:
            continue
        seen.add(rel)
        path = root / rel
        if not path.is_file():
            continue
        if path.suffix == ".h":
            impl = path.with_suffix(".cpp")
            if impl.is_file():
                todo.append(impl.relative_to(root).as_posix())
        for inc in _INCLUDE.findall(path.read_text(errors="replace")):
            for folder in (path.parent, root / SOURCES, root / BINDINGS):
                if (folder / inc).is_file():
                    todo.append((folder / inc).resolve().relative_to(root.resolve()).as_posix())
                    break
    return seen


def file_hash(root: Path, rel: str) -> str | None:
    """16 hex digits of the SHA-256 of the relative path and bytes of the native file `rel` under `root` (the
    hash `eval.code_hash.source_hash` gives one file), cached while its size and time stay; None if it is
    gone."""
    try:
        st = (Path(root) / rel).stat()
    except OSError:
        return None
    return _file_hash(str(root), rel, st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=512)
def _file_hash(root: str, rel: str, mtime_ns: int, size: int) -> str:
    data = (Path(root) / rel).read_bytes()
    return hashlib.sha256(rel.encode() + b"\0" + data + b"\0").hexdigest()[:16]


def files_for(wrappers, root: Path) -> list[str] | None:
    """The native files (sorted relative paths) a run that executed the `dmesh/native.py` functions
    `wrappers` depends on; None when one of them names an attribute no bindings file registers (the caller
    then depends on the whole tree)."""
    root = Path(root)
    funcs, at_import = wrapper_names(root)
    where = registered(root)
    names = set(at_import).union(*(funcs.get(w, frozenset()) for w in wrappers))
    if any(n not in where for n in names):
        return None
    return sorted(closure([*ALWAYS, *(where[n] for n in names)], root))


__all__ = ["WRAPPERS", "ALWAYS", "wrapper_names", "registered", "closure", "file_hash", "files_for"]
