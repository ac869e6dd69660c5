"""Seconds per named stage: wall time and process CPU time, accumulated into a dict the caller holds.

`Clock` times the stages of a reconstruction run; `stage` times one block into an optional dict (the
face-probability pass reports its stages this way when asked).
"""
from __future__ import annotations

import time
from contextlib import contextmanager


class Clock:
    """Seconds per named stage, accumulated into `timings` (a dict shared with the caller): wall time under
    the stage's name, process CPU time (all threads) under name + "_cpu"."""

    def __init__(self, timings: dict):
        self.timings = timings

    @contextmanager
    def __call__(self, name: str):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
            self.timings[name + "_cpu"] = self.timings.get(name + "_cpu", 0.0) + time.process_time() - c0

    def add(self, other: dict, prefix: str = "") -> None:
        """Adds seconds per stage measured elsewhere (e.g. `DMesh.face_probabilities(timings=...)`)."""
        for k, v in other.items():
            self.timings[prefix + k] = self.timings.get(prefix + k, 0.0) + v


@contextmanager
def stage(timings: dict | None, name: str):
    """Times the block into timings[name] and timings[name + "_cpu"] like `Clock`; nothing when timings is
    None."""
    if timings is None:
        yield
        return
    with Clock(timings)(name):
        yield


__all__ = ["Clock", "stage"]
