"""What moved between two sets of runs: each configuration's latest run now against its latest run then.

A rerun of a sweep under new code replaces the rows the reports show; a row that got worse is easy to miss
among hundreds that did not move. This compares two sets of runs (each the latest finished run of every
configuration, as the reports and the export select them: `eval.export.latest_by_configuration`) and lists
the configurations whose metric moved by more than a tolerance, or whose status changed (done -> failed is a
regression too):

    before   the export committed at a git revision (`reports/store/runs.jsonl.gz` there), or an export file
    after    the results store of a work folder, or an export file (default: the working tree's export)

`dmesh changes --since REV` writes `reports/changes.{md,csv}` and prints the worst rows. The default
tolerance sits above CD p2s's own sampling noise on the Table 2 meshes (`python -m studies metric_noise`).
"""
from __future__ import annotations

import json
import math

#: Relative change of the metric below which a configuration counts as unchanged.
TOLERANCE = 0.05
#: Input settings left out of a row's "input" column (the same for every run of the harness's sweeps).
_QUIET_INPUTS = ("metric_samples", "distance", "radius")

__all__ = ["TOLERANCE", "compare_runs", "changes_markdown"]


def _metric(run: dict, metric: str) -> float | None:
    metrics = run.get("metrics_json")
    if isinstance(metrics, str):
        metrics = json.loads(metrics)
    value = (metrics or {}).get(metric) if run.get("status") == "done" else None
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _input(run: dict) -> str:
    settings = run.get("inputs_json")
    if isinstance(settings, str):
        settings = json.loads(settings)
    settings = dict(settings or {})
    corruption = settings.pop("corruption", None) or {}
    for k in _QUIET_INPUTS:
        settings.pop(k, None)
    parts = [f"{k}={v}" for k, v in sorted(corruption.items())] + [f"{k}={v}" for k, v in sorted(settings.items())]
    return f"{run['input_kind']} " + ", ".join(parts)


def compare_runs(before: list[dict], after: list[dict], metric: str = "cd_p2s",
                 tolerance: float = TOLERANCE) -> tuple[list[dict], dict]:
    """(rows, counts): the configurations found in both sets whose `metric` moved by more than `tolerance`
    (relative) or whose status changed, worst first; counts of "compared", "worse", "better", "failed now",
    "done now", "unchanged", "only before", "only after".

    A row: change ("worse", "better", "failed now", "done now"), method, config, shape, category, input,
    seed, before, after, ratio (after / before), and the code versions and finish times of both runs."""
    from eval.export import latest_by_configuration

    if not tolerance >= 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    then, now = latest_by_configuration(before), latest_by_configuration(after)
    counts = dict.fromkeys(("compared", "worse", "better", "failed now", "done now", "unchanged"), 0)
    counts["only before"] = len(set(then) - set(now))
    counts["only after"] = len(set(now) - set(then))
    rows = []
    for key in sorted(set(then) & set(now)):
        old, new = then[key], now[key]
        counts["compared"] += 1
        a, b = _metric(old, metric), _metric(new, metric)
        ratio = b / a if a is not None and b is not None and a > 0 else None
        if old["status"] == "done" and new["status"] == "failed":
            change = "failed now"
        elif old["status"] == "failed" and new["status"] == "done":
            change = "done now"
        elif ratio is not None and ratio > 1 + tolerance:
            change = "worse"
        elif ratio is not None and ratio < 1 / (1 + tolerance):
            change = "better"
        else:
            counts["unchanged"] += 1
            continue
        counts[change] += 1
        rows.append({"change": change, "method": new["method"], "config": new.get("config_label") or "",
                     "shape": new["shape"], "category": new.get("category") or "", "input": _input(new),
                     "seed": int(new.get("seed") or 0), "before": a, "after": b, "ratio": ratio,
                     "error": (new.get("error") or "") if change == "failed now" else "",
                     "code_before": _short(old.get("code_version")), "code_after": _short(new.get("code_version")),
                     "finished_before": old.get("finished_at") or "", "finished_after": new.get("finished_at") or ""})
    order = {"failed now": 0, "worse": 1, "better": 2, "done now": 3}
    rows.sort(key=lambda r: (order[r["change"]], -(r["ratio"] or 0) if r["change"] == "worse" else (r["ratio"] or 0)))
    return rows, counts


def _short(version) -> str:
    """The hash part of a code version ("0.1.0+src.817101e39aca56fb" -> "817101e3")."""
    return str(version or "").rsplit(".", 1)[-1][:8]


def changes_markdown(rows: list[dict], counts: dict, metric: str, tolerance: float, before: str,
                     after: str) -> str:
    """The report: what was compared, the counts, and the table of moved configurations."""
    from eval.reports.render import markdown, md_text

    metric, before, after = md_text(metric), md_text(before), md_text(after)  # names from the command line
    lines = [f"# What moved: {metric}, {before} -> {after}", "",
             f"Each configuration's latest finished run in {after} against its latest in {before} "
             f"(`eval.reports.changes`). Listed: {metric} worse or better by more than {tolerance:.0%} "
             "(CD p2s's own sampling noise: `studies/reports/metric_noise.md`), and runs that failed or "
             "succeeded where they had not. "
             "*ratio*: after / before; *code*: the code version of each run (equal: the metric or the "
             "machine moved, not the method).", "",
             ", ".join(f"{k}: {v}" for k, v in counts.items()), ""]
    if rows:
        scale = 1e3 if metric.startswith("cd") else 1.0
        unit = " x1e-3" if scale == 1e3 else ""
        cols = [("change", "change", None), ("method", "method", None), ("config", "config", None),
                ("shape", "shape", None), ("category", "class", None), ("input", "input", None),
                ("seed", "seed", 1), ("before", f"before{unit}", scale), ("after", f"after{unit}", scale),
                ("ratio", "ratio", 1, ".3f"), ("code_before", "code before", None),
                ("code_after", "code after", None), ("error", "error", None)]
        lines.append(markdown(rows, cols))
    else:
        lines.append("Nothing moved.")
    return "\n".join(lines) + "\n"
