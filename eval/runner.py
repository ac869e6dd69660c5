"""The experiment runner: prepares inputs once, runs every pending run of a sweep, stores each result.

Flow of `run_sweep(sweep, runner)`:

1. Resolve shapes and prepare each GT once (cached under `WORK/inputs/<shape>-<gt hash>/`): the GT is
   loaded or generated, classified (closed / open / mixed) and normalised (vertex mean at the origin, max
   vertex norm `sweep.radius`), then written as `gt.ply` beside `meta.json`.
2. Expand the sweep into runs (`eval.sweep.expand`) and skip every run whose key is `done` (or `failed`,
   unless `retry_failed`), unless `rerun` asks for stored runs again (all, or those scored by an earlier
   metric code). Runs left `running` by a killed process are redone. A run with no row under its key whose
   latest done twin of an earlier code version executed only code that is unchanged is adopted instead
   (`eval.stored.adopt_current`, `eval.code_deps`): skipped, and shown by the reports as the current code's.
3. Prepare the inputs of the pending runs once per (shape, input kind, seed), cached beside the GT (`eval.inputs`):
   `pc_n<N>_s<seed>.npz` holds `points` (N, 3) float32 and `normals` (N, 3) float32 (area-uniform samples
   of the normalised GT); `mv_v<V>_r<R>_d<D>/` holds the multi-view capture (`datasets.capture.MultiView`).
   A pre-processed input (`"preprocess"` in the settings, `eval.sweep.Sweep.preprocess`) is made once from the
   raw one by `eval.preprocess.apply` and cached beside it (`<raw>.pre-<spec>-<code>.npz`, with the stages'
   record), so every method of the sweep gets the same points; a point-cloud method on a multi-view input
   (`"lift"`, `Sweep.lift_depth`) gets the capture's lifted depth pixels (`eval.preprocess.lift_depth`,
   `mv_..._lift<N>_s<seed>-<code>.npz`). The run's info holds the record ("preprocess", "lifted_depth").
4. Claim each pending run in the store (see "Sharing a store" below) and run it in a worker process (a
   local pool of `jobs` forked processes, each run in its own process so that a per-run timeout or a crash in
   native code cannot take the sweep down; or, with `executor="ray"`, Ray tasks on a local Ray or an existing
   cluster, see `eval.ray_executor`). The worker (`eval.execute.execute_run`) calls the method, computes
   `eval.metrics.compute_metrics(pred, gt)` in the normalised GT frame, and hands the result back with the
   hashes of the project code the run executed (`eval.code_deps`); the output
   mesh lands atomically in `WORK/meshes/<key[:2]>/<key>.ply` (written by a local worker; by this process
   from a Ray task's result). Only this (parent) process writes the store (`eval.outcomes`).

Every failure of a run (exception, empty mesh, timeout, worker crash) is stored as a `failed` row with a
one-line error, and the sweep goes on.

Checkpoints. Each run may keep a resumable state in `WORK/states/<key[:2]>/<key>.pt` (`eval.execute.checkpoint_path`,
handed to the method as `Inputs.checkpoint`; the DMesh procedures save theirs every `save_every` steps). It
is removed when the run's outcome is stored, except when its worker died (killed, out of memory, or the
machine stopped), so a rerun of a run whose process died (redone as above, or with `retry_failed`) goes on
from its last save instead of from step 0; its time includes the earlier attempts up to that save. A run that
timed out or raised starts over.

Sharing a store. Two sweeps (processes) may run on one work folder and store at once; each run is computed
once. A run is claimed atomically with a lease (this process's id and host, a token of this sweep and a
heartbeat; `eval.store.Store.claim`, `eval.claims`), and this process refreshes the heartbeat every `lease_s / 6`
seconds from its wait loop while it holds runs (not from a thread: the local pool forks, and forking a process with a
second thread that may hold a lock is asking for a deadlock). A run that another live sweep holds is put
aside and asked about again every 2 s: this sweep *waits* for it rather than computing it twice or returning
without it, so that when `run_sweep` returns every run of the sweep is stored and its reports are complete.
Runs that another sweep finished meanwhile are counted in `SweepSummary.elsewhere` ("finished by another
sweep" in the summary line). When the holder dies, its runs are taken over: at once when it ran on this host
(its process is gone), after `lease_s` seconds without a heartbeat when it ran on another one. A `done` row
is never overwritten, and a sweep whose run was taken over (it stalled longer than `lease_s`) does not store
its late outcome. On the way out (also on an exception or Ctrl-C) the sweep releases what it still holds.

Modules: this one holds `RunnerConfig` and `run_sweep`, and keeps importable the names that callers take from
it; `eval.inputs` (GT and input cache), `eval.stored` (what is stored, adoption), `eval.plan` (`--plan`),
`eval.claims` (claiming under a lease), `eval.local_executor` and `eval.ray_executor` (the executors),
`eval.execute` (one run in a worker), `eval.outcomes` (storing outcomes) and `eval.plain` (one-line errors).
"""
from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from eval.claims import Claims
from eval.local_executor import run_local
from eval.outcomes import Outcomes
from eval.plain import one_line
from eval.store import LEASE_S, Lease, Store
from eval.stored import RERUN_MODES, adopt, is_stored, migrate_records
from eval.sweep import Sweep, expand, get_method
# Re-exported: callers import these from here.
from eval.execute import (MONITOR_SAMPLES, checkpoint_path, drop_checkpoint, execute_run,  # noqa: F401
                          limit_threads, mesh_path_for, resolve_mesh_path, score)
from eval.inputs import (input_id, input_path, load_gt, load_inputs,  # noqa: F401
                         prepare_gt, prepare_input, resolve_and_prepare_shapes, shape_dir)
from eval.plan import SweepPlan, plan_sweep  # noqa: F401
from eval.stored import adopt_current  # noqa: F401

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")


@dataclass(frozen=True)
class RunnerConfig:
    """How to execute a sweep (not part of any run key)."""

    work: str                      # work folder: input cache, output meshes, default store
    db: str | None = None          # SQLite store; None: WORK/results.sqlite
    jobs: int = 1                  # concurrent runs (worker processes or Ray tasks)
    executor: str = "local"        # local (process pool) or ray
    retry_failed: bool = False     # rerun runs stored as failed
    rerun: str | None = None       # also rerun done runs: "all", or "stale-metrics" (scored by older metrics)
    lease_s: float = LEASE_S       # a run whose holder sent no heartbeat for this many seconds is taken over
    ray_address: str | None = None  # ray executor: cluster to join; None: $RAY_ADDRESS, else a local Ray
    threads: int | None = None     # local executor: threads per run; None: the machine's cores / jobs

    def __post_init__(self):
        if not isinstance(self.jobs, int) or self.jobs < 1:
            raise ValueError(f"RunnerConfig.jobs: expected a positive integer, got {self.jobs!r}")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise ValueError(f"RunnerConfig.threads: expected a positive integer or None, got {self.threads!r}")
        if not isinstance(self.lease_s, (int, float)) or not self.lease_s > 0:
            raise ValueError(f"RunnerConfig.lease_s: expected a positive number of seconds, got {self.lease_s!r}")
        if self.rerun not in RERUN_MODES:
            raise ValueError(f"RunnerConfig.rerun: expected one of {RERUN_MODES}, got {self.rerun!r}")
        if self.executor not in EXECUTORS:
            raise ValueError(f"RunnerConfig.executor: expected one of {EXECUTORS}, got {self.executor!r}")
        if self.ray_address and self.executor != "ray":
            raise ValueError(f"a Ray address ({self.ray_address}) needs the ray executor (--executor ray)")

    @property
    def db_path(self) -> Path:
        return Path(self.db) if self.db else Path(self.work) / "results.sqlite"

    @property
    def threads_per_run(self) -> int:
        """`threads`, else the cores this process may use divided among the `jobs` concurrent runs (at least 1):
        runs side by side then share the cores instead of each starting a thread per core, which
        oversubscribes them and makes a run's time depend on its neighbour's."""
        if self.threads is not None:
            return self.threads
        return max(1, available_cores() // self.jobs)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform tells it, else os.cpu_count())."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


@dataclass
class SweepSummary:
    """What `run_sweep` did: counts of runs by outcome and the store path."""

    total: int = 0
    skipped: int = 0      # already done (or failed, without retry_failed) when the sweep started
    kept: int = 0         # of those, done under an earlier code version whose executed code is unchanged
    done: int = 0         # computed by this sweep
    failed: int = 0       # failed in this sweep
    elsewhere: int = 0    # finished (done or failed) by another sweep sharing the store; this one waited
    db: str = ""
    keys: list[str] = dataclasses.field(default_factory=list)

    def line(self) -> str:
        """One line for the CLI, e.g. "3 runs: 1 done now, 0 failed now, 0 already stored, 2 finished by
        another sweep sharing the store"."""
        text = f"{self.total} runs: {self.done} done now, {self.failed} failed now, {self.skipped} already stored"
        if self.kept:
            text += f" ({self.kept} under earlier code versions, current: the code they ran is unchanged)"
        if self.elsewhere:
            text += f", {self.elsewhere} finished by another sweep sharing the store"
        return text


def run_sweep(sweep: Sweep, runner: RunnerConfig) -> SweepSummary:
    """Runs every pending run of `sweep` and stores the outcomes; see the module docstring.

    Raises:
        ValueError: unknown method, shape or config key (before anything runs); Ray missing.
    """
    from eval.inputs import prepare_inputs
    from eval.progress import progress

    work = Path(runner.work)
    # Validate methods, shapes and config keys before preparing anything: a typo costs nothing and
    # leaves no output behind.
    if not expand(sweep, sweep.resolved_shapes()):
        kinds = ", ".join(f"{m} takes {get_method(m).input_kind}" for m in sweep.methods)
        raise ValueError(f"the sweep has no runs: {kinds}, but it asks for {', '.join(sweep.inputs)} input")
    if runner.executor == "ray":  # Ray missing or a cluster that does not answer: fail before preparing anything
        from eval.ray_executor import connect

        connect(runner.ray_address, runner.jobs)
    shapes, gts = resolve_and_prepare_shapes(sweep, work)
    lease = Lease.new()
    with Store(runner.db_path) as store:
        migrated = migrate_records(store)
        if migrated:
            log.info("%d stored runs' code records rewritten to version their inputs by INPUT_VERSION", migrated)
        runs, kept = adopt(expand(sweep, shapes), store, runner)
        summary = SweepSummary(total=len(runs), kept=kept, db=str(runner.db_path), keys=[r.key for r in runs])
        pending, retry_attempts = [], {}
        for spec in runs:
            row = store.get(spec.key)
            if is_stored(row, runner):
                summary.skipped += 1
                continue
            if row is not None and row["status"] in ("done", "failed"):  # run again only if no other sweep
                retry_attempts[spec.key] = row["attempts"]                # does it first
            pending.append(spec)
        log.info("sweep %s: %d runs, %d already stored%s, %d to run", sweep.name, len(runs), summary.skipped,
                 f" ({kept} under earlier code versions whose executed code is unchanged)" if kept else "",
                 len(pending))
        if not pending:
            return summary

        input_errors = prepare_inputs(pending, shapes, gts, work, progress)
        bar = progress(total=len(pending), desc=f"sweep {sweep.name}", unit="run")
        outcomes = Outcomes(store, lease, summary, bar, work, runner.db_path)
        claims = Claims(store, lease, pending, gts, stale_s=runner.lease_s, retry_attempts=retry_attempts,
                        input_errors=input_errors, on_start=outcomes.start, on_done=outcomes.done,
                        on_elsewhere=outcomes.elsewhere)
        try:
            if runner.executor == "ray":
                from eval.ray_executor import run_ray

                run_ray(claims, str(work), runner.jobs, float(sweep.timeout_s), outcomes.done)
            else:
                log.info("%d concurrent run(s), %d thread(s) each", runner.jobs, runner.threads_per_run)
                run_local(claims, str(work), runner.jobs, float(sweep.timeout_s), outcomes.done,
                          runner.threads_per_run)
        finally:
            bar.close()
            try:
                store.release(lease)
            except Exception as exc:  # noqa: BLE001 - never hide the exception that brought us here
                log.warning("could not release this sweep's runs: %s", one_line(exc))
    return summary
