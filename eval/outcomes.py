"""The outcomes of a sweep's runs, stored as the executors hand them back (only the sweep's own process writes).

A done run's mesh path is stored relative to the store's folder when it is inside it (movable work folders); a
failed run keeps its one-line error. An outcome is stored only while the sweep still holds the run's lease
(`eval.store.Store.finish`): a sweep whose run was taken over (it stalled longer than the lease) does not store
its late outcome, and the run counts as finished elsewhere. A run's checkpoint is dropped with its outcome,
except when its worker died, so that a retry resumes it (`eval.execute.checkpoint_path`).
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

from eval.execute import drop_checkpoint
from eval.store import Lease, Store
from eval.sweep import RunSpec

log = logging.getLogger(__name__)


class Outcomes:
    """Stores the outcomes of one sweep's runs and counts them in its summary (an `eval.runner.SweepSummary`);
    `start`, `elsewhere` and `done` are the callbacks of `eval.claims.Claims` and the executors. `bar` is the
    sweep's progress bar."""

    def __init__(self, store: Store, lease: Lease, summary, bar, work: str | Path, db_path: str | Path):
        self.store, self.lease, self.summary, self.bar = store, lease, summary, bar
        self.work, self.db_path = Path(work), Path(db_path)

    def start(self, spec: RunSpec) -> None:
        """A run was claimed by this sweep and starts."""
        self.bar.set_postfix_str(f"{spec.method} / {spec.shape.id} / {spec.input_kind}", refresh=False)

    def elsewhere(self, spec: RunSpec, status: str) -> None:
        """A run was finished (`status`: done or failed) by another sweep sharing the store."""
        self.summary.elsewhere += 1
        log.info("%s on %s (%s, seed %d): %s by another sweep sharing the store", spec.method, spec.shape.id,
                 spec.input_kind, spec.seed, status)
        self.bar.update(1)

    def done(self, spec: RunSpec, outcome: dict) -> None:
        """Stores the outcome of a run this sweep ran (`eval.execute.execute_run`'s, or an executor's failure)."""
        # A checkpoint outlives only a run whose worker died (killed, or the machine stopped): a retry resumes
        # it. A timed-out run starts over, so a retry does not extend its time limit.
        if not str(outcome.get("error", "")).startswith("WorkerDied"):
            drop_checkpoint(self.work, spec.key)
        if outcome["status"] == "done":
            mesh_path = outcome["mesh_path"]
            try:  # store paths relative to the store's folder when possible (movable work folders)
                mesh_path = os.path.relpath(mesh_path, self.db_path.parent)
            except ValueError:
                pass
            stored = self.store.finish(spec.key, status="done", metrics=outcome["metrics"],
                                       timings=outcome["timings"], info=outcome.get("info"),
                                       peak_memory_mb=outcome.get("peak_memory_mb"), mesh_path=mesh_path,
                                       lease=self.lease, code_deps=outcome.get("code_deps"))
        else:
            stored = self.store.finish(spec.key, status="failed", error=outcome["error"], lease=self.lease,
                                       timings=outcome.get("timings"), info=outcome.get("info"))
            if stored:
                log.warning("%s on %s (%s, seed %d) failed: %s", spec.method, spec.shape.id, spec.input_kind,
                            spec.seed, outcome["error"])
        if not stored:  # another sweep took the run over (this one stalled past lease_s); its outcome wins
            self.summary.elsewhere += 1
        elif outcome["status"] == "done":
            self.summary.done += 1
        else:
            self.summary.failed += 1
        self.bar.update(1)
