"""The local executor: a sweep's runs in a pool of forked worker processes, one process per run.

Each run gets a fresh process (`fork`: it inherits the parent's imports and method registry), so that a per-run
timeout or a crash in native code cannot take the sweep down. The parent waits on the workers' pipes, kills a
run past its time limit, stores a worker that died as failed ("WorkerDied"), and refreshes the sweep's lease
from that wait loop (`eval.claims.Claims.beat`).
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import time
from multiprocessing.connection import wait as mp_wait
from typing import Callable

from eval.claims import Claims
from eval.execute import execute_run, limit_threads
from eval.plain import one_line
from eval.sweep import RunSpec


def _child(spec: RunSpec, gt_path: str, work: str, conn, threads: int) -> None:
    # Die with the parent: a killed sweep must not leave orphans computing runs nobody will store.
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    try:
        limit_threads(threads)
        outcome = execute_run(spec, gt_path, work)
    except BaseException as exc:  # noqa: BLE001 - report KeyboardInterrupt etc. as a failure, then exit
        outcome = {"status": "failed", "error": one_line(exc)}
    try:
        conn.send(outcome)
    finally:
        conn.close()


def _mp_context():
    # fork: workers inherit the parent's imports and method registry (methods registered at run time, e.g.
    # by tests, are visible); each run gets a fresh process so timeouts and crashes stay contained.
    return mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")


def run_local(claims: Claims, work: str, jobs: int, timeout_s: float, on_done: Callable,
               threads: int = 1) -> None:
    ctx = _mp_context()
    active: dict = {}  # conn -> (proc, spec, deadline)
    while True:
        while len(active) < jobs and (item := claims.next()) is not None:
            spec, gt_path = item
            parent_conn, child_conn = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_child, args=(spec, str(gt_path), str(work), child_conn, threads),
                               daemon=True)
            proc.start()
            child_conn.close()
            active[parent_conn] = (proc, spec, time.monotonic() + timeout_s)
        if not active:
            if claims.finished:
                return
            claims.wait()
            continue
        now = time.monotonic()
        soonest = min(d for _, _, d in active.values())
        ready = mp_wait(list(active) + [p.sentinel for p, _, _ in active.values()],
                        timeout=max(0.0, min(soonest - now, 1.0)))
        claims.beat()
        for conn in list(active):
            proc, spec, deadline = active[conn]
            outcome = None
            if conn in ready or proc.sentinel in ready:
                try:
                    if conn.poll():
                        outcome = conn.recv()
                except (EOFError, OSError):
                    outcome = None
                if outcome is None and not proc.is_alive():
                    proc.join()
                    code = proc.exitcode
                    sig = f" ({signal.Signals(-code).name})" if code is not None and code < 0 else ""
                    outcome = {"status": "failed", "error": f"WorkerDied: the worker exited with code {code}{sig}"}
            if outcome is None and time.monotonic() > deadline:
                proc.kill()
                outcome = {"status": "failed", "error": f"Timeout: the run took more than {timeout_s:g} s"}
            if outcome is not None:
                proc.join(timeout=5)
                conn.close()
                del active[conn]
                on_done(spec, outcome)
