"""Which code made and scored the runs a table shows.

A report shows each run's latest result (`eval.reports.select_runs`), whatever code made it: a method edited
since its runs keeps them in the tables until they are run again, and a metric edited since a run was scored
keeps that run's old figures until `dmesh rescore` recomputes them (which needs the mesh on disk). Both are
visible here, per table row, so a table never mixes two versions of the code silently:

    earlier code       runs whose `code_version` is not the method's sources' now (`eval.sweep.code_version`)
                       and whose executed code changed since (`eval.code_deps.fresh`)
    earlier metrics    done runs whose `metrics_version` is not the current metrics version (or that carry none)
"""
from __future__ import annotations

from eval.reports.labels import method_label
from eval.reports.render import markdown

PROVENANCE_NOTE = (
    "Which code made and scored the runs of each row. *earlier code*: runs made by an earlier version of the "
    "method's sources that changed code the run executed (the code version hashes the method's module "
    "closure; a run whose executed functions, module-level code and inputs' code are unchanged stays current, "
    "`eval.code_deps`; `dmesh bench` runs the current code under a new key and the table then shows the new "
    "run). *earlier metrics*: done runs scored by an "
    "earlier `eval.metrics` (their figures may be counted another way; `dmesh rescore --work W` recomputes "
    "those whose mesh is on disk). Zero in both: the row is the current code's.")

#: The columns of the provenance table (`provenance_rows`), in the Markdown reports and on index.html alike.
PROVENANCE_COLUMNS = [("method", "method", None), ("runs", "runs", 1), ("earlier_code", "earlier code", 1),
                      ("earlier_metrics", "earlier metrics", 1)]


def provenance_rows(df, input_kind: str | None = None, label=None) -> list[dict]:
    """One row per method and config of `df` (a `select_runs` selection; only `input_kind`'s runs when
    given): finished runs, those made by earlier code, the done runs scored by earlier metrics.

    `label(r)` names a row (default: the method and its config label, as Table 2 shows them).
    """
    from eval.reports.recipes import current_code_version, made_by_earlier_code
    from eval.code_hash import metrics_current

    if df is None or not len(df):
        return []
    sub = df[df["status"].isin(["done", "failed"])]
    if input_kind is not None:
        sub = sub[sub["input_kind"] == input_kind]
    if not len(sub):
        return []
    code_now = {m: current_code_version(m) for m in set(sub["method"])}
    rows: dict[str, dict] = {}
    for _, r in sub.iterrows():
        name = label(r) if label else method_label(r["method"], r["config_label"], r["input_kind"])
        row = rows.setdefault(name, {"method": name, "runs": 0, "earlier_code": 0, "earlier_metrics": 0})
        row["runs"] += 1
        if made_by_earlier_code(r, code_now[r["method"]]):
            row["earlier_code"] += 1
        version = r.get("metrics_version")
        if r["status"] == "done" and not metrics_current(version if isinstance(version, str) else None):
            row["earlier_metrics"] += 1
    return sorted(rows.values(), key=lambda x: x["method"])


def provenance_markdown(rows: list[dict]) -> list[str]:
    """The "Provenance" section of a report, as lines ([] without rows)."""
    if not rows:
        return []
    return ["", "## Provenance", "", PROVENANCE_NOTE, "",
            markdown(rows, PROVENANCE_COLUMNS)]


__all__ = ["provenance_rows", "provenance_markdown", "PROVENANCE_NOTE", "PROVENANCE_COLUMNS"]
