"""Which recipe made each DMesh row: gradient steps or an initialisation, and how it differs from the paper.

The descriptions live beside the presets (`POINTCLOUD_RECIPES` in `dmesh.recon.config`, `MULTIVIEW_RECIPES` in
`dmesh.recon.multiview_config`);
this module matches them to the rows of a report by the run's config label ("preset=paper", or "" for the
method's default preset, `fast`).
"""
from __future__ import annotations

from dmesh.recon.config import DEFAULT_PRESET, POINTCLOUD_RECIPES
from dmesh.recon.multiview_config import MULTIVIEW_RECIPES
from eval.reports.labels import method_label
from eval.reports.render import markdown

#: The DMesh harness methods with presets, by input kind, and the recipes of their presets.
DMESH_METHODS = {"pointcloud": {"dmesh": POINTCLOUD_RECIPES}, "multiview": {"dmesh_mv": MULTIVIEW_RECIPES}}
#: The columns of the recipes table (`recipe_rows`), in the Table 2 Markdown reports and on index.html alike.
RECIPE_COLUMNS = [("method", "row", None), ("preset", "preset", None), ("kind", "made by", None),
                  ("recipe", "recipe", None)]


def _preset(config_label: str) -> tuple[str, str]:
    """(preset, the other overrides as a label) of a config label such as "preset=paper,lr=1e-05"."""
    parts = [p for p in str(config_label or "").split(",") if p]
    preset = next((p.split("=", 1)[1] for p in parts if p.startswith("preset=")), DEFAULT_PRESET)
    rest = ",".join(p for p in parts if not p.startswith("preset="))
    return preset, rest


def recipe_rows(df, input_kind: str) -> list[dict]:
    """One row per DMesh configuration of `input_kind` in `df` (the store's dataframe): label, preset,
    "gradient steps" or "initialisation", and the recipe."""
    methods = DMESH_METHODS.get(input_kind, {})
    if not len(df):
        return []
    sub = df[(df["input_kind"] == input_kind) & df["method"].isin(list(methods))]
    rows = []
    for (method, label), g in sub.groupby(["method", "config_label"], sort=True):
        recipes = methods[method]
        preset, rest = _preset(label)
        steps, text = recipes.get(preset, (None, f"unknown preset {preset!r}"))
        if rest:
            text += f" Overrides: {rest}."
        finished = g[g["status"].isin(["done", "failed"])]  # a run left running is not in the tables
        older = _older_runs(method, finished)
        if older:
            which = "its one run was" if len(finished) == 1 else f"{older} of its {len(finished)} runs were"
            text += f" ({which} made by earlier code of the method, which may predate part of this recipe.)"
        kind = "gradient steps" if steps else ("initialisation" if steps is not None else "?")
        rows.append({"method": method_label(method, label, input_kind), "preset": preset,
                     "kind": kind, "recipe": text})
    return rows


def _older_runs(method: str, runs) -> int:
    """How many of `runs` (store rows of `method`) carry another code version than the method's sources now:
    the recipe text is the current code's, so a report says when its rows are older."""
    now = current_code_version(method)
    if now is None or "code_version" not in getattr(runs, "columns", ()):
        return 0
    return sum(made_by_earlier_code(r, now) for _, r in runs.iterrows())


def made_by_earlier_code(row, now: str | None) -> bool:
    """Whether the store row `row` (a dict or a pandas row) was made by other code than its method's sources
    now: another code version than `now` (`current_code_version`; None: nothing to compare, False), unless
    the code the run executed is unchanged (`eval.code_deps.fresh`), which makes it the current code's."""
    from eval.code_deps import fresh

    if now is None or row.get("code_version") == now:
        return False
    return not fresh(row.get("code_deps"))


def current_code_version(method: str) -> str | None:
    """The code version of `method`'s sources now (`eval.sweep.code_version`); None for an unregistered method
    or unreadable sources (nothing to compare)."""
    from eval.code_hash import code_version
    from eval.sweep import get_method

    try:
        return code_version(get_method(method))
    except (ValueError, OSError):
        return None


def recipe_markdown(rows: list[dict]) -> str:
    """The "DMesh recipes" section of a Table 2 Markdown report ("" without DMesh rows)."""
    if not rows:
        return ""
    out = ["## DMesh recipes", "",
           "Which DMesh rows take gradient steps and which come from an initialisation, and how each recipe "
           "differs from the paper's.", "",
           markdown(rows, RECIPE_COLUMNS)]
    return "\n".join(out)


__all__ = ["recipe_rows", "recipe_markdown", "current_code_version", "made_by_earlier_code", "DMESH_METHODS",
           "RECIPE_COLUMNS"]
