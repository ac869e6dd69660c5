"""A sweep's pending runs, handed to the executors one at a time, each claimed in the store under the sweep's lease."""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

from eval.inputs import input_id
from eval.plain import one_line
from eval.store import Lease, Store
from eval.sweep import RunSpec

log = logging.getLogger(__name__)


class Claims:
    """Hands out the pending runs of a sweep one at a time, each claimed in the store under the sweep's lease.

    A run another live sweep holds is put aside and asked about again every `poll_s` seconds, until it is
    finished there (`on_elsewhere`) or its holder is gone (then it is claimed here). A claimed run whose input
    could not be prepared is stored as failed at once. `beat()` refreshes the lease's heartbeat at most every
    `heartbeat_s` seconds; the executors call it from their wait loops.
    """

    def __init__(self, store: Store, lease: Lease, pending: list[RunSpec], gts: dict, *, stale_s: float,
                 retry_attempts: dict, input_errors: dict, on_start: Callable, on_done: Callable,
                 on_elsewhere: Callable):
        self.store, self.lease, self.gts, self.stale_s = store, lease, gts, float(stale_s)
        self.queue, self.deferred = list(pending), []
        self.retry_attempts, self.input_errors = retry_attempts, input_errors
        self.on_start, self.on_done, self.on_elsewhere = on_start, on_done, on_elsewhere
        self.heartbeat_s = self.stale_s / 6.0
        self.poll_s = min(2.0, self.heartbeat_s)
        self._next_poll = 0.0
        self._next_beat = time.monotonic() + self.heartbeat_s
        self._told_waiting = False

    @property
    def finished(self) -> bool:
        """Nothing left to claim or wait for."""
        return not self.queue and not self.deferred

    def next(self) -> tuple[RunSpec, Path] | None:
        """The next run this sweep claimed, with its GT path; None when nothing can be claimed now."""
        while True:
            if not self.queue:
                if not self.deferred or time.monotonic() < self._next_poll:
                    return None
                self.queue, self.deferred = self.deferred, []
            spec = self.queue.pop(0)
            claim = self.store.claim(spec.identity(), self.lease, stale_s=self.stale_s,
                                     retry_attempts=self.retry_attempts.get(spec.key))
            if claim == "held":
                self.deferred.append(spec)
                self._next_poll = time.monotonic() + self.poll_s
                continue
            if claim in ("done", "failed"):
                self.on_elsewhere(spec, claim)
                continue
            if claim == "resumed":
                log.info("run %s (%s on %s) was left running by an interrupted sweep; redoing it",
                         spec.key[:12], spec.method, spec.shape.id)
            self.on_start(spec)
            err = self.input_errors.get(input_id(spec))
            if err is not None:
                self.on_done(spec, {"status": "failed", "error": err})
                continue
            return spec, self.gts[spec.shape.id]

    def beat(self) -> None:
        """Refreshes the heartbeat of the runs this sweep holds, if `heartbeat_s` passed since the last one."""
        now = time.monotonic()
        if now < self._next_beat:
            return
        self._next_beat = now + self.heartbeat_s
        try:
            self.store.heartbeat(self.lease)
        except Exception as exc:  # noqa: BLE001 - a busy store must not stop the sweep; the next beat retries
            log.warning("could not refresh the heartbeat of this sweep's runs: %s", one_line(exc))

    def wait(self) -> None:
        """Sleeps until the runs put aside are due to be asked about again (nothing runs here meanwhile)."""
        if not self._told_waiting:
            log.info("waiting for %d run(s) that another sweep sharing the store is computing",
                     len(self.deferred))
            self._told_waiting = True
        self.beat()
        time.sleep(min(self.poll_s, max(0.05, self._next_poll - time.monotonic())))
