"""User-given values, checked the same way by every command.

`parse_value` / `parse_sets` read `--set KEY=VALUE` values, and `load_yaml` sweep files, as YAML (one loader,
`_yaml_loader`, a safe one that also reads `1e-3` as a number and refuses a key given twice); `check_seed`,
`check_points` and `check_capture_size` bound seeds and sizes, saying what a larger value would cost. Errors
are one-line ValueErrors naming the value.
"""
from __future__ import annotations

import functools
from typing import Any

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
