"""`dmesh bench --plan`: what a sweep would run, and how long the stored runs of the same configurations took."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from eval.store import Store
from eval.stored import adopt, is_stored
from eval.sweep import Sweep, expand


@dataclasses.dataclass
class SweepPlan:
    """What a sweep would run (`plan_sweep`), and how long the stored runs of the same configurations took."""

    name: str = ""
    total: int = 0
    stored: int = 0         # done (or failed, without retry_failed): skipped
    kept: int = 0           # of those, done under an earlier code version whose executed code is unchanged
    pending: int = 0        # to run
    known: int = 0          # pending runs with a stored run of the same configuration (any code version)
    known_s: float = 0.0    # the wall seconds of those stored runs (input preparation, method, metrics)
    #: per method and config label ("psr", "dmesh [preset=paper]"): (pending runs, known runs, their seconds)
    by_method: dict = dataclasses.field(default_factory=dict)

    def line(self, jobs: int = 1) -> str:
        """One line for the CLI, e.g. "sweep robustness: 546 runs, 500 stored, 46 to run; 40 of them took
        1.2 h when stored (0.6 h at 2 jobs), 6 never ran"."""
        text = f"sweep {self.name}: {self.total} runs, {self.stored} stored"
        if self.kept:
            text += f" ({self.kept} under earlier code versions, current: the code they ran is unchanged)"
        text += f", {self.pending} to run"
        if self.pending:
            text += (f"; {self.known} of them took {self.known_s / 3600:.2f} h when stored "
                     f"({self.known_s / 3600 / max(1, jobs):.2f} h at {max(1, jobs)} jobs)")
            if self.pending > self.known:
                text += f", {self.pending - self.known} never ran"
        return text

    def breakdown(self) -> list[str]:
        """One line per method and config with pending runs, the longest stored total first, e.g.
        "  dmesh_mv: 12 to run, 12 took 4.07 h"."""
        rows = sorted(self.by_method.items(), key=lambda kv: (-kv[1][2], kv[0]))
        return [f"  {label}: {pending} to run, {known} took {seconds / 3600:.2f} h"
                + (f", {pending - known} never ran" if pending > known else "")
                for label, (pending, known, seconds) in rows]


def _wall_s(row: dict) -> float | None:
    from datetime import datetime

    try:
        return (datetime.fromisoformat(row["finished_at"]) - datetime.fromisoformat(row["started_at"])).total_seconds()
    except (TypeError, ValueError):
        return None


def plan_sweep(sweep: Sweep, runner) -> SweepPlan:
    """What `eval.runner.run_sweep` would run with `runner` (a `RunnerConfig`), without running it: the runs
    stored and pending, and for the pending ones the wall time (start to finish, metrics included) of the latest
    finished run of the same configuration (method, config overrides, shape, input kind, input settings, seed) of
    any code version in the store. A time estimate from measured runs: they ran under whatever load the machine
    had then.

    Writes nothing: no GT is prepared (a run's key needs its shape's GT hash, not the GT) and the store is only
    read (`Store(readonly=True)`)."""
    runs = expand(sweep, sweep.resolved_shapes())
    plan = SweepPlan(name=sweep.name, total=len(runs))
    if not Path(runner.db_path).is_file():  # no store yet: everything is to run, nothing was ever timed
        plan.pending = len(runs)
        return plan
    with Store(runner.db_path, readonly=True) as store:
        runs, plan.kept = adopt(runs, store, runner)
        walls: dict[str, tuple[str, float]] = {}
        for row in store.rows():
            wall = _wall_s(row) if row["status"] == "done" else None
            if wall is None:
                continue
            ident = json.dumps([row["method"], row["config_label"], row["shape"], row["input_kind"],
                                row["inputs_json"], int(row["seed"])], sort_keys=True, default=str)
            if ident not in walls or row["started_at"] > walls[ident][0]:
                walls[ident] = (row["started_at"], wall)
        for spec in runs:
            if is_stored(store.get(spec.key), runner):
                plan.stored += 1
                continue
            plan.pending += 1
            ident = json.dumps([spec.method, spec.config_label, spec.shape.id, spec.input_kind, dict(spec.inputs),
                                int(spec.seed)], sort_keys=True, default=str)
            label = spec.method + (f" [{spec.config_label}]" if spec.config_label else "")
            pending, known, seconds = plan.by_method.get(label, (0, 0, 0.0))
            if ident in walls:
                plan.known += 1
                plan.known_s += walls[ident][1]
                known, seconds = known + 1, seconds + walls[ident][1]
            plan.by_method[label] = (pending + 1, known, seconds)
    return plan
