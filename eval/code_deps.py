"""The code a run executed, so that an edit of code it never ran leaves it current.

A run's key holds its method's code version (`eval.code_hash.code_version`), a hash of the whole module closure of
the method: any edit inside that closure makes every stored run of the method stale, though most edits touch
code that many runs never execute (a change to the multi-view depth fit cannot change a run of the `paper`
preset). So while a run executes, its worker also records which project functions ran (`record`), and the
run's store row keeps, in `code_deps` (`deps_for`), the list of the following entries and one digest of
their hashes:

    def:PATH::NAME   a module-level function or a method (NAME "Class.method") the run executed, whole
                     (its nested functions and lambdas belong to it)
    outline:PATH     a module of the method's closure without its function bodies: imports, constants,
                     class bodies, signatures and defaults (what runs at import); a function that this
                     module-level code names (a decorator, a call at import) stays whole in it, and one of
                     another project module that it names (imported by name, or as an attribute of an
                     imported module) is added as a `def:` entry
    file:PATH        a file the run depends on whole: the method's own package (`baselines/`: the wrapper
                     the registry built before the worker started)
    native:PATH      a native source file (C++, the build file) behind the `dmesh.native` wrappers the run
                     executed (`eval.native_deps`), when the closure imports `dmesh.native`; `tree:native`
                     (the whole tree) where that cannot be told, and in records made before this entry
    inputs:version   the version of the cached input data (`eval.code_hash.INPUT_VERSION`): a run depends on
                     its input's data, not on the text of the code that generated it

Records made before "inputs:version" held the input generation as `file:` entries (`INPUT_MODULES` and what
they import, whole), so that any refactor of datasets/ made every stored run stale; `migrate` rewrites such a
record, while it still holds, into the current form; so does a record that held the native sources as one
`tree:native` entry (into its `native:` files).

A later sweep whose closure hash differs from a stored run's adopts that run as current when the entries'
hashes, taken from the sources now, give the same digest (`fresh`; `eval.stored.adopt_current`). One digest
rather than a hash per entry keeps the record small. Hashes are over
the syntax tree without docstrings, like the code version, so comments, docstrings and layout change nothing.

What the record cannot see, and how it is covered: code that ran before the worker started (imports, the
registry's method objects) is in the outlines and `file:` entries; a change to a function that did not run
can only start to matter through a change to code that did run (the caller, or module-level code), which
makes the run stale. A run recorded while another trace function was set (a debugger, coverage), and a run
resumed from an earlier attempt's checkpoint (that attempt's code is not in the record), record nothing and
are never adopted.

The record is `sys.settrace` with a global trace function that notes each new frame's code object and
returns None, so no line of the run is traced; its cost is one Python call per Python function call of
the run.
"""
from __future__ import annotations

import ast
import contextlib
import functools
import hashlib
import sys
import threading
from pathlib import Path
from typing import Iterator, Mapping

from eval import native_deps
from eval.code_hash import (INPUT_MODULES, INPUT_VERSION, NATIVE_TREES, REPO, _module_file, method_trees,
                             module_closure, source_hash, strip_docstrings)

#: Packages whose executed functions are recorded one by one (the harness, `eval`, is not a run's code).
TRACED_PACKAGES = ("dmesh", "datasets", "baselines")
#: Packages a run depends on whole, file by file, when they are in its closure (the method wrappers).
WHOLE_PACKAGES = ("baselines",)
#: The entry of a run's record that holds the version of its input data (`eval.code_hash.INPUT_VERSION`).
INPUTS_ENTRY = "inputs:version"
#: The entry of the whole native tree (records before `native:` entries, and wrappers `native_deps` cannot map).
NATIVE_ENTRY = "tree:native"


@contextlib.contextmanager
def record() -> Iterator[set | None]:
    """Collects the code objects of every Python function called inside the block, by this thread and by
    threads it starts there.

    Yields the set being filled, or None when another trace function is already set (nothing is recorded:
    the caller then stores no dependencies)."""
    if sys.gettrace() is not None:
        yield None
        return
    seen: set = set()
    add = seen.add

    def tracer(frame, event, arg):
        add(frame.f_code)
        return None

    sys.settrace(tracer)
    threading.settrace(tracer)  # and threads started inside the block
    try:
        yield seen
    finally:
        sys.settrace(None)
        threading.settrace(None)


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def _dump(node: ast.AST) -> bytes:
    return ast.dump(node, include_attributes=False).encode()


class _FileCode:
    """The hashes of one Python source file: whole, outline and one per unit (module-level function or
    method), and the line span of each unit (decorators included) for mapping code objects to units."""

    def __init__(self, path: Path):
        data = path.read_bytes()
        self.units: dict[str, str] = {}
        self.spans: list[tuple[int, int, str]] = []
        self.imported: list[tuple[str, str]] = []
        try:
            tree = ast.parse(data, str(path))
        except (SyntaxError, ValueError):
            self.whole = self.outline = _digest(data)  # unparsable: every unit of it follows the whole file
            return
        defs: list[tuple[str, ast.AST]] = []  # (unit name, def node)

        def collect(body: list, prefix: str) -> None:
            for node in body:
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    defs.append((prefix + node.name, node))
                elif isinstance(node, ast.ClassDef):
                    collect(node.body, f"{prefix}{node.name}.")

        collect(tree.body, "")
        for name, node in defs:
            start = min([node.lineno] + [d.lineno for d in node.decorator_list])
            self.spans.append((start, node.end_lineno or node.lineno, name))
        self.whole = _digest(_dump(strip_docstrings(tree)))
        for name, node in defs:  # a name defined twice (a property's getter and setter) hashes both
            self.units[name] = _digest(self.units.get(name, "").encode() + _dump(node))
        # The outline: function bodies out, except those of functions the module-level code names (a
        # decorator, a call at import, an alias), found again in what remains until nothing new is named.
        bodies = [node.body for _, node in defs]
        keep: set[str] = set()
        while True:
            for (name, node), body in zip(defs, bodies):
                node.body = body if name in keep else [ast.Pass()]
            named = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
            more = {name for name, _ in defs if name in named} - keep  # module-level functions only
            if not more:
                break
            keep |= more
        self.outline = _digest(_dump(tree))
        attrs = {(n.value.id, n.attr) for n in ast.walk(tree)  # in the outline: what runs at import
                 if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)}
        for (_, node), body in zip(defs, bodies):
            node.body = body
        # Names imported from project modules that the module-level code names (a function of another
        # module called at import): `deps_for` adds their defs.
        imported = set()
        for node in tree.body:
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                for alias in node.names:
                    local = alias.asname or alias.name
                    if local in named:  # `from m import f` ... f(...); or `from pkg import mod` ... mod.f(...)
                        imported.add((node.module, alias.name))
                        imported.update((f"{node.module}.{alias.name}", a) for n, a in attrs if n == local)
            elif isinstance(node, ast.Import):
                for alias in node.names:  # `import pkg.mod as m` ... m.f(...)
                    imported.update((alias.name, a) for n, a in attrs if n == (alias.asname or alias.name))
        self.imported = sorted(imported)

    def unit_at(self, line: int) -> str | None:
        """The unit whose span holds `line` (the outermost: a nested function belongs to its unit)."""
        for start, end, name in self.spans:
            if start <= line <= end:
                return name
        return None


@functools.lru_cache(maxsize=256)
def _file_code(path: str, mtime_ns: int, size: int) -> _FileCode:
    return _FileCode(Path(path))


def file_code(path: Path) -> _FileCode | None:
    """The hashes of the source file `path` (cached while its size and time stay), or None if it is gone."""
    try:
        st = path.stat()
    except OSError:
        return None
    return _file_code(str(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=4096)
def _project_path(filename: str, root: Path) -> str | None:
    """`filename` relative to `root` when it is a Python file of a traced package, else None."""
    try:
        rel = Path(filename).resolve().relative_to(root)
    except (ValueError, OSError):
        return None
    if rel.suffix != ".py" or not rel.parts or rel.parts[0] not in TRACED_PACKAGES:
        return None
    return rel.as_posix()


def deps_for(method, codes, root: str | Path | None = None, code_root: str | Path | None = None) -> dict:
    """The `code_deps` of a run of `method` that executed `codes` (from `record`): {"entries": the sorted
    entries, "digest": `digest` of their hashes in the sources under `root` (default: the repository)}.
    `code_root` is where the executed code was loaded from (default: `root`)."""
    hashes = entry_hashes(method, codes, root, code_root)
    return {"entries": sorted(hashes), "digest": digest(hashes)}


def digest(hashes: Mapping[str, str | None]) -> str:
    """16 hex digits of the SHA-256 of the sorted "entry=hash" lines of `hashes`."""
    return _digest("".join(f"{k}={hashes[k]}\n" for k in sorted(hashes)).encode())


def entry_hashes(method, codes, root: str | Path | None = None,
                 code_root: str | Path | None = None) -> dict[str, str]:
    """{entry: hash} of a run of `method` that executed `codes` (see `deps_for`)."""
    base = Path(root if root is not None else REPO).resolve()
    loaded = Path(code_root).resolve() if code_root is not None else base
    trees = method_trees(method, base)
    deps: dict[str, str] = {INPUTS_ENTRY: str(INPUT_VERSION)}
    native = False
    for tree in trees:
        if tree in NATIVE_TREES:
            native = True
            continue
        fc = file_code(base / tree)
        if fc is None:
            continue
        if tree.split("/")[0] in WHOLE_PACKAGES:
            deps[f"file:{tree}"] = fc.whole
            continue
        deps[f"outline:{tree}"] = fc.outline
        for module, name in fc.imported:
            src = _module_file(module, base)
            other = file_code(src) if src is not None else None
            if other is not None and name in other.units:
                deps[f"def:{src.relative_to(base).as_posix()}::{name}"] = other.units[name]
    for code in codes:
        rel = _project_path(code.co_filename, loaded)
        if rel is None or f"file:{rel}" in deps or rel.split("/")[0] in WHOLE_PACKAGES:
            continue
        fc = file_code(base / rel)
        if fc is None:
            continue
        unit = fc.unit_at(code.co_firstlineno)
        deps[f"outline:{rel}"] = fc.outline  # module-level code, and the constants its functions read
        if unit is not None:  # else module-level code ran (a lazy import, a module-level lambda)
            deps[f"def:{rel}::{unit}"] = fc.units[unit]
    if native:
        deps.update(_native_entries(deps, base))
    return dict(sorted(deps.items()))


def _native_entries(deps, base: Path) -> dict[str, str]:
    """{entry: hash} of the native sources behind the `dmesh.native` wrappers that `deps` (entries) name as
    executed: one `native:` entry per file, or the whole tree (`NATIVE_ENTRY`) when they cannot be told."""
    prefix = f"def:{native_deps.WRAPPERS}::"
    files = native_deps.files_for([e[len(prefix):] for e in deps if e.startswith(prefix)], base)
    if files is None:
        return {NATIVE_ENTRY: current(NATIVE_ENTRY, base)}
    return {f"native:{f}": current(f"native:{f}", base) for f in files}


def current(entry: str, root: str | Path | None = None) -> str | None:
    """The hash that dependency `entry` (a `deps_for` key) has in the sources under `root` now; None if its
    file or unit is gone."""
    base = Path(root if root is not None else REPO)
    if entry == INPUTS_ENTRY:
        return str(INPUT_VERSION)
    kind, _, rest = entry.partition(":")
    if kind == "tree":
        return source_hash((rest,), base)[:16]
    if kind == "native":
        return native_deps.file_hash(base, rest)
    path, _, unit = rest.partition("::")
    fc = file_code(base / path)
    if fc is None:
        return None
    if kind == "file":
        return fc.whole
    if kind == "outline":
        return fc.outline
    if kind == "def":
        return fc.units.get(unit)
    return None


def fresh(deps: Mapping | None, root: str | Path | None = None) -> bool:
    """Whether a run's `code_deps` still hold in the sources under `root`: its entries' hashes now give its
    digest (or, in the first records, which kept a hash per entry, every hash still holds). False without
    dependencies."""
    if not deps or not isinstance(deps, Mapping):
        return False
    if "digest" in deps:
        entries = deps.get("entries") or []
        return bool(entries) and digest({e: current(e, root) for e in entries}) == deps["digest"]
    return all(current(entry, root) == value for entry, value in deps.items())


def migrate(deps: Mapping | None, method, root: str | Path | None = None) -> dict | None:
    """A record of a run of `method` in an earlier form, in the current form, when it still holds (`fresh`);
    None when `deps` is already current, or holds no longer (the run is stale either way: nothing to keep).

    Two earlier forms: before "inputs:version", the input generation as whole `file:` entries, which give way
    to "inputs:version" (but for the files of `method`'s own closure: a baseline that calls a datasets/ helper
    keeps depending on that file); before `native:` entries, the whole native tree as one `tree:native` entry,
    which gives way to the files behind the wrappers the record names as executed (`eval.native_deps`)."""
    if not deps or not isinstance(deps, Mapping) or "digest" not in deps:
        return None
    base = Path(root if root is not None else REPO).resolve()
    entries = list(deps.get("entries") or [])
    own = set(method_trees(method, base))
    legacy = {f"file:{f}" for f in module_closure(INPUT_MODULES, str(base)) if f not in own}
    old_inputs = INPUTS_ENTRY not in entries and bool(legacy.intersection(entries))
    if not (old_inputs or NATIVE_ENTRY in entries) or not fresh(deps, base):
        return None
    native = _native_entries(entries, base) if NATIVE_ENTRY in entries else None
    if native is not None and NATIVE_ENTRY in native:
        native = None  # the wrappers cannot be told apart: the whole tree stays
    if not (old_inputs or native):
        return None
    drop = (legacy if old_inputs else set()) | ({NATIVE_ENTRY} if native else set())
    hashes = {e: current(e, base) for e in entries if e not in drop}
    if old_inputs:
        hashes[INPUTS_ENTRY] = str(INPUT_VERSION)
    hashes.update(native or {})
    return {"entries": sorted(hashes), "digest": digest(hashes)}


__all__ = ["record", "deps_for", "migrate", "INPUTS_ENTRY", "NATIVE_ENTRY", "entry_hashes", "digest", "fresh", "current",
           "file_code", "strip_docstrings", "TRACED_PACKAGES"]
