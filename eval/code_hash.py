"""The hashes of the code a run depends on: its method's code version, the metric and pre-processing versions.

A run's key holds its method's code version (`code_version`): the package version, a hash of the method's
module closure (`method_trees`: the files of its module and of every project module they import, lazy imports
included) and the version of the inputs (`INPUT_VERSION`), so editing one baseline reruns no other method's
stored runs. A run depends on its input's data, not on the text of the code that generated it: the harness
caches each input by shape, settings and `INPUT_VERSION` (`eval.inputs`), never by that code, so a refactor of
the input generation reruns nothing, and a change to what it generates bumps `INPUT_VERSION`
(tests/test_input_version.py holds fingerprints of generated inputs and fails until it is bumped). The metrics
are versioned apart, the same way, by what they compute (`METRICS_VERSION`, in each run's metrics, not in its
key: `dmesh rescore` scores a stored mesh again; tests/test_metrics_version.py holds fingerprints of the
metrics of fixed meshes), and so is `eval.preprocess` (`preprocess_version`, in the settings of a pre-processed or
lifted input). Hashes are over each Python file's syntax tree without docstrings (`code_text`), so comments,
docstrings and layout change no key. `eval.code_deps` narrows a code version to the code a run executed;
`eval.sweep` puts the code version into every run's key.
"""
from __future__ import annotations

import ast
import functools
import hashlib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Version of every input the harness generates and caches: the normalised GT, point samples, captures,
#: corruptions and scans (`INPUT_MODULES`). In the input cache's folder names (`eval.inputs.shape_dir`), in every
#: run's code version and in its `code_deps` (entry "inputs:version"). Bump it with any change to what those
#: modules generate, so that no cached input and no stored run made from the earlier data is reused; a change
#: that generates the same data (a refactor, a module split) keeps it. tests/test_input_version.py fails on a
#: generated input that differs from its fingerprint at this version. (2: inside-out closed GTs flipped outward.)
INPUT_VERSION = 2
#: The input generation: the modules whose output `INPUT_VERSION` versions (tests/test_input_version.py).
INPUT_MODULES = ("datasets.synthetic", "datasets.normalize", "datasets.meshes", "datasets.mesh_files",
                 "datasets.sampling", "datasets.capture", "datasets.corrupt", "datasets.scan")
#: Version of the metrics a run's mesh is scored with (`eval.metrics.compute_metrics`, `METRIC_MODULES` and the
#: project code they import). Not in a run's key: a stored mesh is scored again under new metrics without
#: rerunning its method (`dmesh rescore`); each run's metrics carry the `metrics_version` that made them. Bump it
#: with any change to what the metrics compute for the same meshes; a change that computes the same figures (a
#: refactor, a module split) keeps it. tests/test_metrics_version.py fails on metrics of fixed meshes that differ
#: from their fingerprints at this version.
METRICS_VERSION = 1
#: The metric code's hashes under which the figures of a METRICS_VERSION were computed, before the metrics were
#: versioned by what they compute (a run's metrics carried the hash of the metric code's files): those runs'
#: figures are the version's. dc0ea2e4fcf4f59f: the metric code of commit 2441970, fingerprinted as version 1.
METRICS_HASHES = {"dc0ea2e4fcf4f59f": 1}
#: The metric modules: the code whose output `METRICS_VERSION` versions.
METRIC_MODULES = ("eval.metrics", "eval.closest_point")
#: Packages of this repository whose modules a run's code version follows through imports.
PROJECT_PACKAGES = ("dmesh", "baselines", "datasets", "eval")
#: The native sources, which a run depends on when its closure imports `dmesh.native`.
NATIVE_TREES = ("native",)
_SOURCE_SUFFIXES = (".py", ".cpp", ".cc", ".h", ".hpp", ".cu", ".cuh", ".txt", ".cmake")


def strip_docstrings(tree: ast.AST) -> ast.AST:
    """Removes, in place, the docstrings of the module, classes and functions of `tree`; returns it."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
                    and isinstance(first.value.value, str):
                node.body = node.body[1:] or [ast.Pass()]
    return tree


def source_hash(trees: tuple[str, ...], root: str | Path = REPO) -> str:
    """SHA-256 (hex) over the relative paths and code of the source files under `trees` of `root`: a Python
    file's syntax tree without its docstrings (`code_text`: comments, docstrings and layout change no key), the
    bytes of any other source."""
    return _source_hash(tuple(sorted(set(trees))), str(root))


def code_text(path: Path) -> bytes:
    """What of a source file a run's key depends on: for Python, the dump of its syntax tree with the
    docstrings of the module, classes and functions removed (so editing a comment, a docstring or the layout
    reruns nothing); the raw bytes of other files and of Python that does not parse."""
    data = path.read_bytes()
    if path.suffix != ".py":
        return data
    try:
        tree = ast.parse(data, str(path))
    except (SyntaxError, ValueError):
        return data
    return ast.dump(strip_docstrings(tree), include_attributes=False).encode()


@functools.lru_cache(maxsize=None)
def _source_hash(trees: tuple[str, ...], root: str) -> str:
    h = hashlib.sha256()
    base = Path(root)
    for tree in trees:
        p = base / tree
        files = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else []
        for f in files:
            if f.suffix not in _SOURCE_SUFFIXES or "__pycache__" in f.parts:
                continue
            h.update(str(f.relative_to(base)).encode() + b"\0" + code_text(f) + b"\0")
    return h.hexdigest()


def package_version() -> str:
    try:
        from importlib.metadata import version

        return version("dmesh-harness")
    except Exception:  # noqa: BLE001 - not installed (plain checkout): fall back to a marker
        return "0+unknown"


def _module_file(name: str, root: Path) -> Path | None:
    """The source file of project module `name` under `root` (a module or a package's __init__), or None."""
    if name.split(".")[0] not in PROJECT_PACKAGES:
        return None
    base = root.joinpath(*name.split("."))
    for f in (base.with_suffix(".py"), base / "__init__.py"):
        if f.is_file():
            return f
    return None


def _imported_modules(path: Path, name: str) -> set[str]:
    """Module names that the source at `path` (module `name`) imports anywhere, lazy imports included; for
    `from a import b` both `a` and `a.b` (b may be a submodule)."""
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                pkg = name.split(".")[: len(name.split(".")) - node.level + (1 if is_pkg else 0)]
                mod = ".".join(pkg + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{alias.name}" for alias in node.names)
    return out


@functools.lru_cache(maxsize=None)
def module_closure(roots: tuple[str, ...], root: str) -> tuple[str, ...]:
    """Repository-relative source files of the project modules `roots` and of every project module they import,
    transitively (lazy imports included), plus the `__init__.py` of each package on the way and, when
    `dmesh.native` is among them, the native sources. A package's `__init__` is hashed but its imports are not
    followed (a re-exporting `__init__` would otherwise tie every module of the package to every other)."""
    base = Path(root)
    files: set[Path] = set()
    seen: set[str] = set()
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        f = _module_file(name, base)
        if f is None:
            continue
        files.add(f)
        parts = name.split(".")
        for i in range(1, len(parts)):
            init = _module_file(".".join(parts[:i]), base)
            if init is not None:
                files.add(init)
        if f.name != "__init__.py" or name in roots:
            todo.extend(_imported_modules(f, name))
    out = sorted(str(f.relative_to(base)) for f in files)
    if "dmesh.native" in seen and _module_file("dmesh.native", base) is not None:
        out += list(NATIVE_TREES)
    return tuple(out)


def method_trees(method, root: str | Path = REPO) -> tuple[str, ...]:
    """The sources a method's results depend on: its own `code_trees` attribute if it has one, else the files of
    its module and of the project modules it imports (`module_closure`). So editing one baseline, or the harness
    around the runs, reruns no other method's stored runs; editing the metrics reruns nothing
    (`METRICS_VERSION`), and the inputs are versioned by `INPUT_VERSION`."""
    own = getattr(method, "code_trees", None)
    if own:
        return tuple(own)
    modules = {getattr(type(method), "__module__", "") or "",
               getattr(getattr(method, "reconstruct", None), "__module__", "") or ""}
    roots = tuple(sorted(m for m in modules if m and m != "builtins"))
    return module_closure(roots, str(root))


def metrics_version() -> str:
    """The version of the metrics, as each run's metrics record it: "metrics-v" + `METRICS_VERSION`."""
    return f"metrics-v{METRICS_VERSION}"


def metrics_current(version) -> bool:
    """Whether metrics recorded with `metrics_version` `version` are the current metrics' figures: the current
    version, or a hash of the metric code that computed them (`METRICS_HASHES`). False for None (runs stored
    before their metrics carried a version)."""
    return version == metrics_version() or (isinstance(version, str)
                                            and METRICS_HASHES.get(version) == METRICS_VERSION)


def code_version(method, root: str | Path = REPO) -> str:
    """Package version + '+src.' + the first 16 hex digits of the hash of the method's sources (`method_trees`)
    and the inputs' version (`INPUT_VERSION`)."""
    sources = source_hash(method_trees(method, root), root)
    return f"{package_version()}+src.{hashlib.sha256(f'{sources}:inputs-v{INPUT_VERSION}'.encode()).hexdigest()[:16]}"


def sources_changed(method, expected: str, root: str | Path = REPO) -> str | None:
    """None when the method's sources on disk still hash to `expected` (a run's `code_version`), else a one-line
    reason. Reads the files again: a forked worker inherits the parent's cached hashes, and it imports any
    module its parent had not imported from the files as they are now, so a sweep whose sources were edited
    after it started would otherwise run a mixture of old and new code under the old key."""
    module_closure.cache_clear()
    _source_hash.cache_clear()
    now = code_version(method, root)
    if now == expected:
        return None
    return (f"the sources of method {getattr(method, 'name', method)!r} changed after the sweep started "
            f"({expected} -> {now}); run the sweep again to run them under their own key")


def preprocess_version(root: str | Path = REPO) -> str:
    """The first 16 hex digits of the hash of `eval.preprocess` and the project code it imports: in the input
    settings of every pre-processed or lifted input, so a change of that code reruns those runs (and only
    those) and names a new cache file."""
    return source_hash(module_closure(("eval.preprocess",), str(root)), root)[:16]
