"""Sweep definition: methods x shapes x input kinds x configs x seeds, and the key of every run.

A `Sweep` is a frozen, validated dataclass loadable from YAML (`Sweep.from_yaml`) or built from CLI flags.
`expand(sweep)` turns it into `RunSpec`s, one per run; a method only runs on the input kind it takes
(`Method.input_kind`). Each run is keyed by `run_key`: the SHA-256 of the canonical JSON of

    method, shape id, GT hash, input kind, input settings, full config dict, seed, code version

where the GT hash is the SHA-256 of a real mesh's file bytes, or of a synthetic shape's generator name and
seed, and the code version is the package version plus a hash of the source files the run depends on
(`code_version`). Same key, same result: the runner never recomputes a finished key. A stored run whose key
holds an earlier code version stays current when the code it executed did not change (`eval.code_deps`): the
runner then adopts it under its own key (`eval.runner.adopt_current`), found by its `base_key` (the run key
without the code version).

Shape specs (strings):
    "torus"                a synthetic shape of `datasets.synthetic.SHAPES`, generator seed 0
    "torus@3"              the same generator with seed 3
    "closed/spot.obj"      a mesh file: as given if it exists, else relative to the data root
Data root: `--data-root` flag, else the `DMESH_DATA` environment variable, else `../shared/meshes`
relative to the repository.

Input kinds: "pointcloud" (`n_points` area-uniform samples with normals), "multiview" (a `views`-view
capture at `resolution` and `distance`), and "mesh" (the normalised GT itself, for mesh to DMesh / Table 1;
use `radius: 0.8` there, the paper's frame for that experiment).

Input variants (robustness sweeps): `variants:` lists dicts of input settings, each one input of every run of
its input kind, e.g. `[{}, {noise: 0.005}, {outliers: 0.01}, {scan: 6, noise: 0.0025}, {views: 8}]` (the keys
and their levels: `datasets.corrupt`). Levels are validated (one-line errors), levels at their clean value
are dropped, and the canonical dict goes into the input settings as `"corruption"` (so into the run key and the
input's cache name). A sweep without `variants` keeps the plain settings and run keys.

Pre-processing (`preprocess:`, DESIGN.md 8.5): a list of specs of `eval.preprocess` ("none", "outliers",
"outliers+smooth", "outliers=3+smooth=60", "autosmooth", ...), e.g. `preprocess: [none, outliers+smooth]`; every
point-cloud method runs once per spec on the same pre-processed points (the runner prepares them once per
input). A spec other than "none" goes into the input settings as `"preprocess": {"stages": spec, "code": hash of
eval.preprocess and what it imports}` (so into the run key and the input's cache name) and into the row's label
as "+spec" (`psr [+outliers+smooth]`, `psr [depth=9,+outliers]`); "none" keeps the plain settings, keys and
labels. Methods that take images or meshes run once, unpreprocessed. Default: [none].

Lifted depth (`lift_depth: true`): every point-cloud method also runs on each multi-view input, on its depth
pixels lifted to points as the multi-view `depth` preset lifts them (`eval.preprocess.lift_depth`); the run's
input kind stays "multiview" (its rows sit in the multi-view tables), its settings get `"lift": {"points",
"normals": "estimated", "code"}` and its label the tag "lifted-depth" (`psr [lifted-depth]`). Pre-processing
specs apply to these points too.

User-given values are checked here for every command: `parse_value` / `parse_sets` read `--set KEY=VALUE`
values and sweep files as YAML (one loader, which also reads `1e-3` as a number), and `check_seed`,
`check_points` and `check_capture_size` bound seeds and sizes, saying what a larger value would cost.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
INPUT_KINDS = ("pointcloud", "multiview", "mesh")
CATEGORIES = ("closed", "open", "mixed")
MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")


# --------------------------------------------------------------------------------------------------- values

#: The largest seed: the results store keeps seeds as SQLite INTEGER (64-bit signed); numpy takes no negatives.
MAX_SEED = 2**63 - 1
#: The most points a cloud or a metric may sample (a sanity bound: 100x the paper's 100K).
MAX_POINTS = 20_000_000
#: Bytes per sampled point: float64 position and normal (what `datasets.sampling.sample_points` returns).
POINT_BYTES = 48
#: The most views and the largest image side of a capture.
MAX_VIEWS = 10_000
MAX_RESOLUTION = 8192
#: Bytes per captured pixel (float32 diffuse and depth, a bool mask) and the most a capture may hold.
PIXEL_BYTES = 9
MAX_CAPTURE_BYTES = 16 * 2**30


def _size_text(n_bytes: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n_bytes < 1024 or unit == "PiB":
            return f"{n_bytes:.3g} {unit}"
        n_bytes /= 1024
    return ""  # unreachable


def _integer(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    return value


def check_seed(name: str, value) -> int:
    """`value` if it is a seed every generator and the store take (0 to 2**63 - 1), else ValueError."""
    value = _integer(name, value)
    if not 0 <= value <= MAX_SEED:
        raise ValueError(f"{name}: a seed must be from 0 to 2**63 - 1 (numpy takes no negative seed, the "
                         f"results store keeps 64-bit integers), got {value}")
    return value


def check_points(name: str, value, low: int = 1) -> int:
    """`value` if it is a point or sample count from `low` to `MAX_POINTS`, else ValueError saying why."""
    value = _integer(name, value)
    if value < low:
        raise ValueError(f"{name}: expected at least {low}, got {value}")
    if value > MAX_POINTS:
        raise ValueError(f"{name}: at most {MAX_POINTS:,} points, got {value:,} (their positions and normals "
                         f"alone would need {_size_text(value * POINT_BYTES)} of memory)")
    return value


def check_capture_size(views, resolution, names: tuple[str, str] = ("views", "resolution")) -> None:
    """ValueError unless `views` images of `resolution`^2 pixels are within the bounds above."""
    views, resolution = _integer(names[0], views), _integer(names[1], resolution)
    if views < 1 or resolution < 1:
        raise ValueError(f"{names[0]} and {names[1]}: expected positive integers, got {views} and {resolution}")
    need = _size_text(views * resolution**2 * PIXEL_BYTES)
    if views > MAX_VIEWS:
        raise ValueError(f"{names[0]}: at most {MAX_VIEWS:,} views, got {views:,} (their images at "
                         f"{resolution}x{resolution} would need {need} of memory)")
    if resolution > MAX_RESOLUTION:
        raise ValueError(f"{names[1]}: at most {MAX_RESOLUTION}, got {resolution} ({views} images would need "
                         f"{need} of memory)")
    if views * resolution**2 * PIXEL_BYTES > MAX_CAPTURE_BYTES:
        raise ValueError(f"{names[0]} {views} at {names[1]} {resolution}: the images would need {need} of memory, "
                         f"more than the {_size_text(MAX_CAPTURE_BYTES)} a capture may hold; use fewer views or "
                         f"a lower resolution")


@functools.lru_cache(maxsize=None)
def _yaml_loader():
    """PyYAML's safe loader, also reading `1e-3` and `5E+4` as floats (YAML 1.1 needs a dot in them) and
    refusing a key given twice in one mapping (PyYAML keeps the last silently)."""
    import re

    import yaml

    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base` keys may repeat a merged key
                        continue
                    key = self.construct_object(key_node, deep=True)
                    try:
                        first = seen.setdefault(key, key_node.start_mark)
                    except TypeError:  # an unhashable key: the base class says so
                        continue
                    if first is not key_node.start_mark:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {key!r} (first on line {first.line + 1})",
                            key_node.start_mark)
            return super().construct_mapping(node, deep)

    Loader.add_implicit_resolver("tag:yaml.org,2002:float",
                                 re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
                                 list("-+0123456789"))
    return Loader


def _yaml_problem(exc: Exception) -> str:
    """One line saying what is wrong in a YAML text and where (line and column, 1-based)."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return " ".join(f"{where}{problem}".split())


def load_yaml(text: str, what: str):
    """The YAML document `text`, read by the one loader of every command; ValueError (one line naming
    `what`, the line and the column) when it is not valid YAML."""
    import yaml

    try:
        return yaml.load(text, Loader=_yaml_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise ValueError(f"{what}: not valid YAML ({_yaml_problem(exc)})") from None


def parse_value(raw: str, what: str = "value"):
    """A `--set` value as YAML: `7` int, `1e-3` float, `[1, 2]` list, `true` bool, `null` None, else the text."""
    return load_yaml(raw, what)


def parse_sets(items: list[str] | tuple[str, ...], flag: str = "--set") -> dict[str, Any]:
    """`KEY=VALUE` strings to {key: value}, values parsed as YAML (`parse_value`); the last of a key wins.

    The one parser of `--set` for every command (sweeps, `reconstruct`, `compare`). Raises ValueError (one
    line) for an item without `=`, an empty key or a value that is not valid YAML."""
    out: dict[str, Any] = {}
    for item in items or ():
        key, eq, raw = str(item).partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(f"{flag} {item!r}: expected KEY=VALUE")
        out[key] = parse_value(raw, f"{flag} {item!r}")
    return out


def default_data_root() -> Path:
    """Data root for real meshes: $DMESH_DATA, else ../shared/meshes beside the repository."""
    env = os.environ.get("DMESH_DATA")
    return Path(env) if env else REPO.parent / "shared" / "meshes"


@dataclass(frozen=True)
class Sweep:
    """A benchmark sweep. Every field round-trips through YAML (`to_dict` / `from_dict`)."""

    name: str = "bench"                       # label shown in reports
    methods: tuple[str, ...] = ()             # registered method names (`baselines.registry.METHODS`)
    shapes: tuple[str, ...] = ()              # shape specs (see module docstring)
    inputs: tuple[str, ...] = ("pointcloud",)  # input kinds to run: pointcloud, multiview, mesh
    seeds: tuple[int, ...] = (0,)             # run seeds (point sampling and the method's own seed)
    configs: Mapping[str, tuple[Mapping[str, Any], ...]] = field(default_factory=dict)  # method -> overrides list
    n_points: int = 100_000                   # point-cloud input: area-uniform samples with normals
    views: int = 64                           # multi-view input: number of views (8 azimuths x 8 elevations)
    resolution: int = 256                     # multi-view input: image side in pixels
    distance: float = 2.0                     # multi-view input: camera distance from the origin
    radius: float = 1.0                       # normalisation: max vertex norm of the GT
    metric_samples: int = 100_000             # surface samples per side for the metrics
    timeout_s: float = 1800.0                 # per-run wall-clock limit in seconds
    data_root: str | None = None              # real meshes' root; None: $DMESH_DATA or ../shared/meshes
    skip_missing: bool = False                # leave out mesh files that do not exist (with a warning)
    variants: tuple[Mapping[str, Any], ...] = ()  # input variants (corruptions, capture sizes); (): inputs as above
    preprocess: tuple[str, ...] = ("none",)   # point-cloud pre-processing specs (eval.preprocess), one row set each
    lift_depth: bool = False                  # point-cloud methods also run on each multiview input's lifted depth

    def __post_init__(self):
        for name in ("methods", "shapes", "inputs", "seeds", "preprocess"):
            value = getattr(self, name)
            if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
                raise TypeError(f"Sweep.{name}: expected a list, got {type(value).__name__} {value!r} "
                                f"(a list is written [{value}])")
            object.__setattr__(self, name, tuple(value))
        if not self.methods:
            raise ValueError("Sweep.methods: at least one method is needed")
        if not self.shapes:
            raise ValueError("Sweep.shapes: at least one shape is needed")
        bad = [k for k in self.inputs if k not in INPUT_KINDS]
        if bad or not self.inputs:
            raise ValueError(f"Sweep.inputs: each must be one of {INPUT_KINDS}, got {list(self.inputs)}")
        if not all(isinstance(s, int) and not isinstance(s, bool) for s in self.seeds) or not self.seeds:
            raise ValueError(f"Sweep.seeds: expected a non-empty list of integers, got {list(self.seeds)}")
        for s in self.seeds:
            check_seed("Sweep.seeds", s)
        for name in ("n_points", "metric_samples"):
            check_points(f"Sweep.{name}", getattr(self, name))
        check_capture_size(self.views, self.resolution, ("Sweep.views", "Sweep.resolution"))
        for name in ("distance", "radius", "timeout_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ValueError(f"Sweep.{name}: expected a positive number, got {value!r}")
        if self.data_root is not None and not isinstance(self.data_root, (str, os.PathLike)):
            raise ValueError(f"Sweep.data_root: expected a folder path, got {self.data_root!r}")
        if not isinstance(self.configs, Mapping):
            raise TypeError(f"Sweep.configs: expected a mapping method -> list of dicts, got "
                            f"{type(self.configs).__name__}")
        configs = {}
        for method, lst in self.configs.items():
            if isinstance(lst, Mapping):
                lst = [lst]
            if not isinstance(lst, (list, tuple)) or not all(isinstance(c, Mapping) for c in lst):
                raise TypeError(f"Sweep.configs[{method!r}]: expected a list of dicts, got {lst!r}")
            configs[str(method)] = tuple(dict(c) for c in lst) or ({},)
        object.__setattr__(self, "configs", configs)
        if len(set(self.methods)) != len(self.methods) or len(set(self.shapes)) != len(self.shapes):
            raise ValueError("Sweep: methods and shapes must not repeat")
        self._check_variants()
        self._check_preprocess()

    def _check_preprocess(self) -> None:
        """Validates `preprocess` and `lift_depth`; keeps the canonical specs (`eval.preprocess.parse_spec`)."""
        from eval.preprocess import parse_spec

        if not self.preprocess:
            raise ValueError("Sweep.preprocess: expected a non-empty list of specs, e.g. [none, outliers+smooth]")
        canon = tuple(parse_spec(p, f"Sweep.preprocess[{i}]")[0] for i, p in enumerate(self.preprocess))
        if len(set(canon)) != len(canon):
            raise ValueError(f"Sweep.preprocess: a spec repeats once written canonically: {list(canon)}")
        object.__setattr__(self, "preprocess", canon)
        if not isinstance(self.lift_depth, bool):
            raise ValueError(f"Sweep.lift_depth: expected true or false, got {self.lift_depth!r}")
        if self.lift_depth and "multiview" not in self.inputs:
            raise ValueError("Sweep.lift_depth: the lifted depth pixels come from the multiview input, which the "
                             f"sweep does not run (inputs: {', '.join(self.inputs)})")

    def _check_variants(self) -> None:
        """Validates `variants` (see `input_variants`); one-line ValueError naming the variant and the key."""
        if isinstance(self.variants, Mapping) or not isinstance(self.variants, (list, tuple)):
            raise ValueError(f"Sweep.variants: expected a list of input-setting dicts, got {self.variants!r}")
        object.__setattr__(self, "variants", tuple(dict(v) if isinstance(v, Mapping) else v for v in self.variants))
        seen: dict[str, int] = {}
        for i, variant in enumerate(self.variants):
            canon = self._canonical(variant, f"Sweep.variants[{i}]")
            kind = _variant_kind(canon)
            if kind is not None and kind not in self.inputs:
                raise ValueError(f"Sweep.variants[{i}]: {canonical_json(canon)} changes {kind} input, which the "
                                 f"sweep does not run (inputs: {', '.join(self.inputs)})")
            if canonical_json(canon) in seen:
                raise ValueError(f"Sweep.variants[{i}]: the same input as variants[{seen[canonical_json(canon)]}] "
                                 f"({canonical_json(canon)} once levels at their clean value are dropped)")
            seen[canonical_json(canon)] = i
            if "views" in canon or "resolution" in canon:
                check_capture_size(canon.get("views", self.views), canon.get("resolution", self.resolution),
                                   (f"Sweep.variants[{i}].views", f"Sweep.variants[{i}].resolution"))

    def _canonical(self, variant, what: str) -> dict:
        from datasets.corrupt import canonical_variant

        return canonical_variant(variant, n_points=self.n_points, views=self.views, resolution=self.resolution,
                                 what=what)

    # -- (de)serialisation
    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k in ("methods", "shapes", "inputs", "seeds", "preprocess"):
            d[k] = list(d[k])
        d["variants"] = [dict(v) for v in self.variants]
        d["configs"] = {m: [dict(c) for c in cs] for m, cs in self.configs.items()}
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "Sweep":
        """The sweep of the user-given mapping `d`; ValueError (one line) for any bad key, type or value."""
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"sweep: unknown keys {sorted(unknown)}")
        try:
            return cls(**dict(d))
        except TypeError as exc:  # a wrong type in the user's file or flags is a bad value there
            raise ValueError(str(exc)) from None

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Sweep":
        path = Path(path)
        if path.is_dir():
            raise ValueError(f"sweep file {path}: is a folder, not a YAML file")
        if not path.is_file():
            raise FileNotFoundError(f"sweep file {path} not found")
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            raise ValueError(f"sweep file {path}: not a text file (not UTF-8)") from None
        d = load_yaml(text, f"sweep file {path}")
        if d is None:
            raise ValueError(f"sweep file {path}: empty (expected methods: [...] and shapes: [...])")
        if not isinstance(d, Mapping):
            raise ValueError(f"sweep file {path}: expected a mapping at the top level, got {type(d).__name__}")
        try:
            return cls.from_dict(d)
        except ValueError as exc:
            raise ValueError(f"sweep file {path}: {exc}") from None

    def with_overrides(self, sets: list[str], strict: bool = True) -> "Sweep":
        """Applies `key=value` overrides (values parsed as YAML by `parse_sets`).

        `field=value` sets a sweep field (e.g. `n_points=20000`); `method.key=value` sets a config
        key for every config of that method (e.g. `psr.depth=7`). With `strict`, the method must be one of
        the sweep's (a typo would otherwise change nothing).
        """
        d = self.to_dict()
        for key, value in parse_sets(sets).items():
            if "." in key:
                method, ckey = key.split(".", 1)
                if strict and method not in d["methods"]:
                    raise ValueError(f"--set {key}=...: {method!r} is not among the methods run "
                                     f"({', '.join(d['methods'])})")
                if not ckey:
                    raise ValueError(f"--set {key}=...: expected METHOD.KEY=VALUE")
                cfgs = d["configs"].get(method) or [{}]
                d["configs"][method] = [{**c, ckey: value} for c in cfgs]
            elif key in d:
                d[key] = value
            else:
                raise ValueError(f"--set {key}=...: unknown sweep field {key!r}")
        return Sweep.from_dict(d)

    def resolved_shapes(self) -> list[ShapeRef]:
        """The shapes resolved against the data root; missing mesh files are left out with a warning when
        `skip_missing`, else (like unknown names) raise ValueError."""
        out = []
        for spec in self.shapes:
            try:
                out.append(resolve_shape(spec, self.root()))
            except ValueError as exc:
                if not (self.skip_missing and "no such mesh file" in str(exc)):
                    raise
                log.warning("sweep %s: %s; left out (skip_missing)", self.name, exc)
        if not out:
            raise ValueError(f"sweep {self.name}: none of its shapes is available")
        return out

    def root(self) -> Path:
        return Path(self.data_root) if self.data_root else default_data_root()

    def input_settings(self, kind: str, variant: Mapping | None = None) -> dict:
        """The settings that define the input of `kind` (they go into the run key).

        `variant` (a canonical variant of `input_variants`) adds its settings as `"corruption"` (a dict, `{}`
        for the clean input of a sweep with variants), and its `views` / `resolution` replace the sweep's.
        Without a variant the settings are those of a sweep without `variants` (unchanged run keys)."""
        base = {"radius": float(self.radius), "metric_samples": self.metric_samples}
        if kind == "pointcloud":
            out = {**base, "n_points": self.n_points}
        elif kind == "multiview":
            out = {**base, "n_points": self.n_points, "views": self.views, "resolution": self.resolution,
                   "distance": float(self.distance)}
        else:
            return base
        if variant is not None:
            out.update({k: variant[k] for k in ("views", "resolution") if k in variant and kind == "multiview"})
            out["corruption"] = dict(variant)
        return out

    def input_variants(self, kind: str) -> list[dict | None]:
        """The canonical variants (`datasets.corrupt.canonical_variant`) that apply to input `kind`: the clean
        one and those changing `kind`; [None] (the plain input) when the sweep has no `variants`, or for "mesh".

        A variant is a dict of input settings at one level each (e.g. `{noise: 0.005}`, `{scan: 6, outliers:
        0.01}`, `{views: 8}`; `{}` is the clean input); each one is a separate input of every run."""
        if not self.variants or kind == "mesh":
            return [None]
        out = []
        for i, v in enumerate(self.variants):
            canon = self._canonical(v, f"Sweep.variants[{i}]")
            if _variant_kind(canon) in (None, kind):
                out.append(canon)
        return out


@dataclass(frozen=True)
class ShapeRef:
    """A resolved shape spec."""

    id: str                 # shape id used in tables ("torus", "torus@3", "spot")
    kind: str               # "synthetic" or "file"
    source: str             # synthetic generator name, or the absolute mesh path
    gen_seed: int = 0       # synthetic generator seed
    category: str | None = None  # closed/open/mixed; None for a file until it is classified
    gt_hash: str = ""       # SHA-256 of the file bytes / generator name and seed

    def __post_init__(self):
        if self.kind not in ("synthetic", "file"):
            raise ValueError(f"ShapeRef.kind: expected 'synthetic' or 'file', got {self.kind!r}")


def resolve_shape(spec: str, data_root: str | Path | None = None) -> ShapeRef:
    """Resolves a shape spec (see module docstring); raises ValueError for an unknown shape."""
    spec = str(spec).strip()
    if spec.lower().endswith(MESH_SUFFIXES) or os.sep in spec:
        candidates = [Path(spec).expanduser()]
        if not Path(spec).is_absolute():
            candidates.append(Path(data_root or default_data_root()) / spec)
        for p in candidates:
            if p.is_file():
                digest = hashlib.sha256(p.read_bytes()).hexdigest()
                return ShapeRef(id=p.stem, kind="file", source=str(p.resolve()), gt_hash=digest)
        raise ValueError(f"unknown shape {spec!r}: no such mesh file (looked in "
                         f"{', '.join(str(c) for c in candidates)})")
    name, _, seed_txt = spec.partition("@")
    try:
        gen_seed = int(seed_txt) if seed_txt else 0
    except ValueError:
        raise ValueError(f"unknown shape {spec!r}: the generator seed after '@' must be an integer") from None
    from datasets import synthetic

    if name not in synthetic.SHAPES:
        raise ValueError(f"unknown shape {spec!r}; synthetic shapes: {', '.join(sorted(synthetic.SHAPES))}; "
                         f"or give a mesh file path")
    category = synthetic.SHAPES[name][0]
    digest = hashlib.sha256(f"synthetic/{name}/seed={gen_seed}".encode()).hexdigest()
    return ShapeRef(id=spec, kind="synthetic", source=name, gen_seed=gen_seed, category=category, gt_hash=digest)


# --------------------------------------------------------------------------------------------------- code

#: Modules every run depends on besides its method: the GT and input generation and the metrics.
INPUT_MODULES = ("datasets.synthetic", "datasets.normalize", "datasets.meshes", "datasets.sampling",
                 "datasets.capture", "datasets.corrupt", "datasets.scan")
#: The metrics of a run. Not in its key: a stored mesh is scored again under new metric code without
#: rerunning its method (`dmesh rescore`); each run's metrics carry the `metrics_version` that made them.
METRIC_MODULES = ("eval.metrics", "eval.closest_point")
#: Packages of this repository whose modules a run's code version follows through imports.
PROJECT_PACKAGES = ("dmesh", "baselines", "datasets", "eval")
#: The native sources, which a run depends on when its closure imports `dmesh.native`.
NATIVE_TREES = ("native",)
_SOURCE_SUFFIXES = (".py", ".cpp", ".cc", ".h", ".hpp", ".cu", ".cuh", ".txt", ".cmake")


def source_hash(trees: tuple[str, ...], root: str | Path = REPO) -> str:
    """SHA-256 (hex) over the relative paths and code of the source files under `trees` of `root`: a Python
    file's syntax tree without its docstrings (`code_text`: comments, docstrings and layout change no key), the
    bytes of any other source."""
    return _source_hash(tuple(sorted(set(trees))), str(root))


def code_text(path: Path) -> bytes:
    """What of a source file a run's key depends on: for Python, the dump of its syntax tree with the
    docstrings of the module, classes and functions removed (so editing a comment, a docstring or the layout
    reruns nothing); the raw bytes of other files and of Python that does not parse."""
    import ast

    from eval.code_deps import strip_docstrings

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
    import ast

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
    its module and of the project modules it imports (`module_closure`), plus the input generation
    (`INPUT_MODULES`). So editing one baseline, or the harness around the runs, reruns no other method's stored
    runs; editing the metrics reruns nothing (`metrics_version`)."""
    own = getattr(method, "code_trees", None)
    if own:
        return tuple(own)
    modules = {getattr(type(method), "__module__", "") or "",
               getattr(getattr(method, "reconstruct", None), "__module__", "") or ""}
    roots = tuple(sorted(m for m in modules if m and m != "builtins")) + INPUT_MODULES
    return module_closure(roots, str(root))


def metrics_version(root: str | Path = REPO) -> str:
    """The first 16 hex digits of the hash of the metric code (`METRIC_MODULES` and what they import)."""
    return source_hash(module_closure(METRIC_MODULES, str(root)), root)[:16]


def code_version(method, root: str | Path = REPO) -> str:
    """Package version + '+' + the first 16 hex digits of the hash of the method's sources (`method_trees`)."""
    return f"{package_version()}+src.{source_hash(method_trees(method, root), root)[:16]}"


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


# --------------------------------------------------------------------------------------------------- runs

def _variant_kind(variant: Mapping) -> str | None:
    from datasets.corrupt import variant_kind

    return variant_kind(variant)


def canonical_json(obj: Any) -> str:
    """JSON with sorted keys and no whitespace, floats as repr: the hashing form."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def run_key(*, method: str, shape_id: str, gt_hash: str, input_kind: str, input_settings: Mapping,
            config: Mapping, seed: int, code_version: str) -> str:
    """The SHA-256 (hex) run key; every argument changes it."""
    payload = {"method": method, "shape": shape_id, "gt": gt_hash, "input_kind": input_kind,
               "inputs": dict(input_settings), "config": dict(config), "seed": int(seed), "code": code_version}
    return hashlib.sha256(canonical_json(payload).encode()).hexdigest()


def config_label(overrides: Mapping, tags: tuple[str, ...] = ()) -> str:
    """Short label of config overrides and the input's harness tags: "depth=7,trim=0.1" ("" for the defaults),
    then the tags ("lifted-depth", "+outliers+smooth"): "depth=7,+outliers+smooth"."""
    return ",".join([f"{k}={overrides[k]}" for k in sorted(overrides)] + [t for t in tags if t])


def preprocess_version(root: str | Path = REPO) -> str:
    """The first 16 hex digits of the hash of `eval.preprocess` and the project code it imports: in the input
    settings of every pre-processed or lifted input, so a change of that code reruns those runs (and only
    those) and names a new cache file."""
    return source_hash(module_closure(("eval.preprocess",), str(root)), root)[:16]


def harness_inputs(sweep: "Sweep", method, kind: str, settings: Mapping) -> list[tuple[dict, tuple[str, ...]]]:
    """The inputs `method` gets of one input of `kind` (settings `settings`): [(input settings, label tags)], one
    per pre-processing spec of the sweep (module docstring); [] when the method does not take that input."""
    from eval.preprocess import NONE, label, lift_points_default

    if method.input_kind == kind:
        base, tags = dict(settings), ()
    elif sweep.lift_depth and kind == "multiview" and method.input_kind == "pointcloud":
        base = {**settings, "lift": {"points": lift_points_default(), "normals": "estimated",
                                     "code": preprocess_version()}}
        tags = ("lifted-depth",)
    else:
        return []
    if method.input_kind != "pointcloud":
        return [(base, tags)]
    return [(base if spec == NONE else {**base, "preprocess": {"stages": spec, "code": preprocess_version()}},
             tags + (label(spec),)) for spec in sweep.preprocess]


def build_config(method, overrides: Mapping):
    """(config object, config dict): the method's default config with `overrides` applied by the method's own
    `resolve_config` (unknown keys raise ValueError; DMesh's `preset` key picks the base). A frozen dataclass
    config is validated again by its __post_init__; a method without config settings takes any overrides."""
    default = method.default_config()
    overrides = dict(overrides)
    if default is not None and not dataclasses.is_dataclass(default) and not isinstance(default, Mapping):
        raise TypeError(f"method {method.name}: default_config() must return a dataclass or a dict")
    if not default and not dataclasses.is_dataclass(default):
        return dict(overrides), dict(overrides)
    cfg = method.resolve_config(overrides) if overrides else default
    return cfg, (dataclasses.asdict(cfg) if dataclasses.is_dataclass(cfg) else dict(cfg))


@dataclass(frozen=True)
class RunSpec:
    """One run of a sweep, fully resolved."""

    key: str
    method: str
    overrides: Mapping[str, Any]   # config overrides (the config itself is rebuilt in the worker)
    config: Mapping[str, Any]      # the full config dict (in the key)
    config_label: str
    shape: ShapeRef
    input_kind: str
    inputs: Mapping[str, Any]      # input settings (in the key)
    seed: int
    code_version: str
    base_key: str = ""             # the run key without the code version (`eval.runner.adopt_current`)

    def identity(self) -> dict:
        """The store columns that identify the run (without results)."""
        return {"key": self.key, "method": self.method, "config_label": self.config_label,
                "shape": self.shape.id, "category": self.shape.category or "unknown",
                "input_kind": self.input_kind, "config_json": dict(self.config), "inputs_json": dict(self.inputs),
                "seed": self.seed, "gt_hash": self.shape.gt_hash, "code_version": self.code_version,
                "base_key": self.base_key or None}


def get_method(name: str):
    """The registered method `name`; ValueError naming the known ones otherwise."""
    from baselines import registry

    if name not in registry.METHODS:
        raise ValueError(f"unknown method {name!r}; registered: {', '.join(sorted(registry.METHODS))}")
    return registry.METHODS[name]


def expand(sweep: Sweep, shapes: list[ShapeRef] | None = None) -> list[RunSpec]:
    """All runs of `sweep`, ordered shape-major (so inputs prepared for a shape are reused at once).

    Args:
        sweep: the sweep.
        shapes: resolved shapes (with categories), in the order of `sweep.shapes`; resolved here if None.
    Raises:
        ValueError: an unknown method or shape, or a config key the method does not have.
    """
    methods = [get_method(m) for m in sweep.methods]
    lifted = ("pointcloud",) if sweep.lift_depth else ()
    unused = [m.name for m in methods if m.input_kind not in sweep.inputs + lifted]
    if unused:
        log.warning("methods %s take no input kind of this sweep (%s); they are skipped",
                    ", ".join(unused), ", ".join(sweep.inputs))
    if shapes is None:
        shapes = sweep.resolved_shapes()
    configs = {}
    for m in methods:
        configs[m.name] = []
        for ov in sweep.configs.get(m.name, ({},)):
            _, cfg = build_config(m, ov)
            configs[m.name].append((dict(ov), cfg))
    versions = {m.name: code_version(m) for m in methods}
    runs = []
    for shape in shapes:
        for kind, variant in ((k, v) for k in sweep.inputs for v in sweep.input_variants(k)):
            settings = sweep.input_settings(kind, variant)
            for m in methods:
                for given, tags in harness_inputs(sweep, m, kind, settings):
                    for ov, cfg in configs[m.name]:
                        for seed in sweep.seeds:
                            ident = dict(method=m.name, shape_id=shape.id, gt_hash=shape.gt_hash, input_kind=kind,
                                         input_settings=given, config=cfg, seed=seed)
                            runs.append(RunSpec(key=run_key(**ident, code_version=versions[m.name]), method=m.name,
                                                overrides=ov, config=cfg, config_label=config_label(ov, tags),
                                                shape=shape, input_kind=kind, inputs=given, seed=seed,
                                                code_version=versions[m.name],
                                                base_key=run_key(**ident, code_version="")))
    return runs
