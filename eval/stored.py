"""Which runs of a sweep the results store already holds, so that the sweep skips them.

A run is skipped when its row is done (or failed, unless failures are retried), unless the sweep asks for stored
runs again (`RERUN_MODES`). A run with no row under its key whose latest done twin of an earlier code version
executed only code that is unchanged is adopted instead (`adopt_current`, `eval.code_deps`): skipped, and shown
by the reports as the current code's. Planning (`eval.plan`) and running (`eval.runner`) count alike.
"""
from __future__ import annotations

import dataclasses

from eval import code_deps
from eval.code_hash import metrics_current
from eval.store import Store
from eval.sweep import RunSpec

#: What a sweep runs again of the runs already stored done (`RunnerConfig.rerun`): nothing, all, or those scored
#: by an earlier metric code.
RERUN_MODES = (None, "all", "stale-metrics")


def is_stored(row: dict | None, runner) -> bool:
    """Whether a sweep skips the run whose store row is `row`: done (unless `runner.rerun` asks for it again),
    or failed (unless failures are retried, or `rerun` is "all").

    `rerun="stale-metrics"` reruns the done runs scored by other metrics than the current ones
    (`eval.code_hash.metrics_current`): what `dmesh rescore` cannot reach when a run's mesh is not on disk.
    """
    status = None if row is None else row["status"]
    if status == "failed":
        return not (runner.retry_failed or runner.rerun == "all")
    if status != "done":
        return False
    if runner.rerun == "all":
        return False
    if runner.rerun == "stale-metrics":
        return metrics_current((row.get("metrics_json") or {}).get("metrics_version"))
    return True


def adopt_current(runs: list[RunSpec], store: Store) -> list[RunSpec]:
    """`runs` with each run that has no finished row under its key replaced by its latest done twin (same
    `base_key`, an earlier code version) whose executed code is unchanged (`eval.code_deps.fresh`): such a run
    is the current code's result, so the sweep skips it and the reports show it as current."""
    out = []
    for spec in runs:
        if spec.base_key and store.status(spec.key) is None:
            twin = next((r for r in store.twins(spec.base_key) if code_deps.fresh(r["code_deps"])), None)
            if twin is not None:
                spec = dataclasses.replace(spec, key=twin["key"], code_version=twin["code_version"])
        out.append(spec)
    return out


def migrate_records(store: Store) -> int:
    """Rewrites, in `store`, the `code_deps` of each done run recorded in an earlier form (before
    "inputs:version": the input generation as whole files; before `native:` entries: the whole native tree)
    that still holds, into the current form (`eval.code_deps.migrate`), so that a later refactor of datasets/,
    or an edit of native code the run never called, leaves it current; returns how many. A run of a method no
    longer registered, or whose record holds no longer, is left as it is. Two queries when none is left."""
    from eval.sweep import get_method

    methods: dict = {}
    migrated = 0
    rows = {r["key"]: r for r in store.code_deps_without(code_deps.INPUTS_ENTRY)}
    rows.update((r["key"], r) for r in store.code_deps_with(code_deps.NATIVE_ENTRY))
    for row in rows.values():
        if row["method"] not in methods:
            try:
                methods[row["method"]] = get_method(row["method"])
            except ValueError:
                methods[row["method"]] = None
        method = methods[row["method"]]
        new = code_deps.migrate(row["code_deps"], method) if method is not None else None
        if new is not None:
            migrated += store.set_code_deps(row["key"], new)
    return migrated


def adopt(runs: list[RunSpec], store: Store, runner) -> tuple[list[RunSpec], int]:
    """(`runs` with the current runs of earlier code versions adopted (`adopt_current`), how many were): none
    when `runner.rerun` asks for stored runs again, since a rerun runs the current code under its own key."""
    if runner.rerun is not None:
        return runs, 0
    adopted = adopt_current(runs, store)
    return adopted, sum(a.key != r.key for a, r in zip(adopted, runs))
