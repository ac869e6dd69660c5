"""Sweep definition: methods x shapes x input kinds x configs x seeds, and the key of every run.

A `Sweep` is a frozen, validated dataclass loadable from YAML (`Sweep.from_yaml`) or built from CLI flags.
`expand(sweep)` turns it into `RunSpec`s, one per run; a method only runs on the input kind it takes
(`Method.input_kind`). Each run is keyed by `run_key`: the SHA-256 of the canonical JSON of

    method, shape id, GT hash, input kind, input settings, full config dict, seed, code version

where the GT hash is the SHA-256 of a real mesh's file bytes, or of a synthetic shape's generator name and
seed, and the code version is the package version plus a hash of the source files the run depends on
(`code_version`). Same key, same result: the runner never recomputes a finished key. A stored run whose key
holds an earlier code version stays current when the code it executed did not change (`eval.code_deps`): the
runner then adopts it under its own key (`eval.stored.adopt_current`), found by its `base_key` (the run key
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

Beside this module: `eval.values` checks the user-given values (`--set`, sweep files, seeds and sizes) for
every command, `eval.shapes` resolves shape specs, and `eval.code_hash` hashes the code a run depends on (its
code version, the metric and pre-processing versions). Their names stay importable from here.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from eval import code_hash
# Re-exported: callers import these from here.
from eval.code_hash import (INPUT_MODULES, METRIC_MODULES, NATIVE_TREES, PROJECT_PACKAGES, REPO,  # noqa: F401
                            _module_file, _source_hash, code_text, code_version, method_trees, metrics_version,
                            module_closure, package_version, preprocess_version, source_hash, sources_changed)
from eval.shapes import CATEGORIES, MESH_SUFFIXES, ShapeRef, default_data_root, resolve_shape  # noqa: F401
from eval.values import (MAX_CAPTURE_BYTES, MAX_POINTS, MAX_RESOLUTION, MAX_SEED, MAX_VIEWS,  # noqa: F401
                         _yaml_loader, check_capture_size, check_points, check_seed, load_yaml, parse_sets,
                         parse_value)

log = logging.getLogger(__name__)

INPUT_KINDS = ("pointcloud", "multiview", "mesh")


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
    base_key: str = ""             # the run key without the code version (`eval.stored.adopt_current`)

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
    versions = {m.name: code_hash.code_version(m) for m in methods}
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
