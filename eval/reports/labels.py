"""Row names: a row says what ran.

Harness methods show under their name and the config overrides of the run (`psr [depth=10]`). A DMesh row
also says which preset ran and whether it takes gradient steps: the default point-cloud preset, `fast`, is
the Delaunay triangulation of the samples and their poles (Amenta and Bern's crust) and the surface step,
with no gradient step, and a table that called it `dmesh` beside the paper's figures would claim more than
ran. The step count comes from the preset's config with the row's overrides applied.
"""
from __future__ import annotations

import functools

#: Names shown per input kind where the harness name differs: DMesh is one method in the paper, registered
#: twice here (`dmesh` for point clouds, `dmesh_mv` for images).
DISPLAY_NAMES = {"multiview": {"dmesh_mv": "dmesh"}}

#: The harness methods whose rows name their preset and step count, with the config class of each.
_DMESH = {"dmesh": "pointcloud", "dmesh_mv": "multiview"}


#: What a DMesh preset without gradient steps runs, by input kind.
START = {"pointcloud": "crust + surface step", "multiview": "crust of the lifted depth pixels + surface step"}


def display_name(method: str, input_kind: str) -> str:
    """The name tables of `input_kind` show for the harness method `method`."""
    return DISPLAY_NAMES.get(input_kind, {}).get(method, method)


def overrides_of(config_label: str) -> dict:
    """The config overrides a label ("depth=7,preset=paper,+outliers") was made from, values read back as
    YAML; its pre-processing tag ("+outliers") is not one."""
    import yaml

    out = {}
    for item in filter(None, (config_label or "").split(",")):
        if item.startswith("+"):  # the harness pre-processing the run's input had (`eval.preprocess`)
            continue
        key, _, value = item.partition("=")
        try:
            out[key] = yaml.safe_load(value)
        except yaml.YAMLError:
            out[key] = value
        if isinstance(out[key], str):  # YAML 1.1 reads "1e-05" (no dot) as text; the label came from a number
            try:
                out[key] = float(out[key])
            except ValueError:
                pass
    return out


def preset_of(method: str, config_label: str) -> str | None:
    """The DMesh preset a row ran (the default when its overrides name none); None for other methods."""
    if method not in _DMESH:
        return None
    from dmesh.recon.config import DEFAULT_PRESET

    return str(overrides_of(config_label).get("preset", DEFAULT_PRESET))


@functools.lru_cache(maxsize=None)
def gradient_steps(method: str, config_label: str) -> int | None:
    """Gradient steps a DMesh row's config takes in all (None when the config cannot be rebuilt)."""
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.multiview_config import MultiViewConfig

    overrides = overrides_of(config_label)
    preset = preset_of(method, config_label)
    overrides.pop("preset", None)
    try:
        if _DMESH[method] == "pointcloud":
            cfg = PointCloudConfig.from_preset(preset, overrides)
            return int(cfg.steps_phase1 + cfg.steps_phase2)
        return int(MultiViewConfig.from_preset(preset, overrides).total_steps())
    except (TypeError, ValueError):  # overrides of an older config: say the preset only
        return None


def method_label(method: str, config_label: str, input_kind: str | None = None) -> str:
    """A row's name: the method's display name for `input_kind`, then in brackets its config overrides; for
    DMesh the preset first, with its gradient steps ("dmesh [fast: crust + surface step, no gradient step]",
    "dmesh [paper: 1500 gradient steps; num_init=2500]")."""
    name = display_name(method, input_kind) if input_kind else method
    if method not in _DMESH:
        return f"{name} [{config_label}]" if config_label else name
    steps = gradient_steps(method, config_label)
    what = "" if steps is None else f": {START[_DMESH[method]]}, no gradient step" if steps == 0 else \
        f": {steps} gradient steps"
    rest = ",".join(i for i in (config_label or "").split(",") if i and not i.startswith("preset="))
    return f"{name} [{preset_of(method, config_label)}{what}{'; ' + rest if rest else ''}]"


__all__ = ["DISPLAY_NAMES", "display_name", "gradient_steps", "method_label", "overrides_of", "preset_of"]
