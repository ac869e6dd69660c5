"""The optimisation loop of the reconstruction procedures (DESIGN.md section 6), written once.

Letters: N points, F faces.

Each procedure (point cloud, multi-view, mesh to DMesh) supplies its data term as a step function and its
schedule: which phases, how many steps each, which parameters train, the learning rates and bounds (one
`BoundedAdam` per phase, which the procedure creates), the freezes. `Loop.run_phase` runs one phase; its
body is one optimisation step, in this order:
1. `step_fn(step)`: the procedure's forward pass (re-triangulate and score the faces, sample or render,
   data term, regularisers), timed by the procedure under the phase's prefix; returns the loss and the
   step's figures.
2. `stop(figures)` (optional): True ends the phase before the update; the record is kept (mesh to DMesh's
   early stop).
3. Backward (`<prefix>backward`).
4. The `BoundedAdam` update, then `after_step(step)` (optional): the procedure's constraints on the new
   state, and figures measured on it (`<prefix>step`).
5. The record {position, "step", "steps", "loss", figures, "seconds"} is appended to the history and passed
   to the callback.
6. Every `save_every` steps (except after the phase's last), the resumable state is written.

The resumable state is one torch file (`save_state`: written under a temporary name, then renamed): the
fingerprint of the input and config, the position (e.g. phase and next step), the points, weights and
reals, the optimiser's state (None at a phase's step 0, where a fresh optimiser starts), the history, the
timings and the procedure's own entries (its RNG state, ...). `load_state` ignores a state of another
fingerprint, and an unreadable one with a warning; it reads with torch's weights-only unpickler, allowing
only the state's own types (`state_types`), and refuses a file that names any other (no data file runs code). The callback also hears {"stage": name} when the
procedure starts a stage (`Loop.stage`); the CLI progress bars show it.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from dmesh.recon.config import TRAIN_ALL  # noqa: F401 - re-exported (every parameter trains in phase 1)
from dmesh.recon.optim import BoundedAdam
from dmesh.timing import Clock  # re-exported (the stage clock of a run)

log = logging.getLogger(__name__)


@dataclass
class ReconstructionResult:
    """What every procedure returns (its result type adds its own attributes).

    Attributes:
        mesh: `trimesh.Trimesh` in the input frame (may be empty).
        dmesh: the final `DMesh` (in the frame of `center`/`scale`).
        center: (3,) float64 and scale: float, the normalisation x -> (x - center) * scale.
        timings: wall seconds per stage, and beside each its process CPU seconds (all threads) under the
            stage's name + "_cpu"; "total" and "total_cpu" for the whole run.
        history: one dict per step (the records of `Loop.run_phase`).
        info: counts and figures of the run.
    """

    mesh: object
    dmesh: object
    center: np.ndarray
    scale: float
    timings: dict = field(default_factory=dict)
    history: list = field(default_factory=list)
    info: dict = field(default_factory=dict)


def deterministic(fn: Callable) -> Callable:
    """Runs `fn` with torch's deterministic algorithms on (restoring the caller's setting after), so the same
    seed gives the same mesh on any number of threads. Without them, the backward of an index gather on a
    CPU tensor (`x[idx]`) adds into its result in the order the threads happen to run, so two runs differ in
    the last bits, and a threshold decision later may differ too."""

    import torch.utils.deterministic as torch_deterministic

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        before, warn_only = torch.are_deterministic_algorithms_enabled(), \
            torch.is_deterministic_algorithms_warn_only_enabled()
        fill = torch_deterministic.fill_uninitialized_memory
        torch.use_deterministic_algorithms(True)
        # Without the NaN-filling of every new empty tensor that the mode also turns on: it costs time on
        # every allocation and only shows reads of uninitialised memory, which no kernel here makes.
        torch_deterministic.fill_uninitialized_memory = False
        try:
            return fn(*args, **kwargs)
        finally:
            torch.use_deterministic_algorithms(before, warn_only=warn_only)
            torch_deterministic.fill_uninitialized_memory = fill

    return wrapper


def fingerprint(data: np.ndarray, config) -> str:
    """16 hex digits identifying an input array and a config dataclass (a state resumes only its own run)."""
    h = hashlib.sha256(np.ascontiguousarray(data).tobytes())
    h.update(repr(sorted(dataclasses.asdict(config).items())).encode())
    return h.hexdigest()[:16]


def save_state(path, state: dict) -> None:
    """Writes `state` to `path` atomically: a temporary name in the same folder, then a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def state_types() -> list:
    """The types a state holds beyond tensors and Python's plain values: the probability pass's caches
    (`ProbabilityState` and its parts, with their NumPy arrays). `load_state` allows these and no other to
    torch's weights-only unpickler, so a state file cannot run code when it is read (the full unpickler calls
    whatever a file names: a `__reduce__` that runs a shell command, say)."""
    from dmesh.candidates import CandidateFaces, NeighbourCache
    from dmesh.probability import ProbabilityConfig, ProbabilityState, _Coherence
    from dmesh.wdt import Csr

    reconstruct = np.zeros(1).__reduce__()[0]  # numpy's array rebuilder (numpy._core.multiarray._reconstruct)
    return [ProbabilityState, ProbabilityConfig, _Coherence, NeighbourCache, CandidateFaces, Csr, reconstruct,
            np.ndarray, np.dtype, *{type(np.dtype(c)) for c in "?bBhHiIlLqQefdgFDG"}]


def read_state(path) -> object | None:
    """What the state file at `path` holds, read with torch's weights-only unpickler allowing `state_types`;
    None (with a warning) when it is unreadable, e.g. cut short.

    Raises:
        ValueError: the file names another type (it was not written by `save_state`, and reading it with the
            full unpickler could run code): nothing of it is loaded.
    """
    import pickle

    try:
        with torch.serialization.safe_globals(state_types()):
            state = torch.load(path, weights_only=True)
    except pickle.UnpicklingError as exc:
        named = re.search(r"GLOBAL (\S+)", str(exc))
        if named is None:  # not a pickle the unpickler can follow (garbage bytes): unreadable, ignored
            log.warning("ignoring unreadable state %s: %s", path, " ".join(str(exc).split())[:200])
            return None
        raise ValueError(f"{path}: not a DMesh state (it names {named.group(1)}, which reading could run as "
                         f"code); delete it or give another file") from None
    except Exception as exc:  # an unreadable state is ignored, not fatal: the run starts over
        log.warning("ignoring unreadable state %s: %s", path, " ".join(str(exc).split())[:200])
        return None
    return state


def load_state(path, fingerprint: str) -> dict | None:
    """The state at `path` if it is readable (`read_state`) and of this fingerprint, else None.

    Raises:
        ValueError: a file that names other types than `state_types` (`read_state`).
    """
    if path is None or not Path(path).exists():
        return None
    state = read_state(path)
    if not isinstance(state, dict) or state.get("fingerprint") != fingerprint:
        log.info("state %s is for another input or config; starting over", path)
        return None
    return state


def mesh_mask(reals: torch.Tensor, faces: np.ndarray, threshold: float) -> np.ndarray:
    """(F,) bool: faces ((F, 3) indices) whose three real values exceed `threshold` (the current mesh)."""
    return (reals.detach().numpy()[faces] > threshold).all(1)


def freeze_faces(opt: BoundedAdam, faces: np.ndarray) -> None:
    """Freezes the points of `faces` ((F, 3) indices) at real value 1 (`BoundedAdam.freeze`)."""
    mask = np.zeros(len(opt.frozen), bool)
    mask[np.asarray(faces, dtype=np.int64).reshape(-1)] = True
    opt.freeze(torch.from_numpy(mask))


def timed_probabilities(dm, clock: Clock, prefix: str):
    """`dm.face_probabilities()` (a `DMesh`'s), the seconds of its stages added to `clock` under `prefix`
    (e.g. "phase1_wdt"): how a phase-1 step scores its faces."""
    stage_t: dict = {}
    probs = dm.face_probabilities(timings=stage_t)
    clock.add(stage_t, prefix)
    return probs


class Loop:
    """One run's stage clock, history, callback and resumable state, and the phase loop.

    Args:
        callback: called with every step's record and with {"stage": name}; None: nobody listens.
        state_path: file of the resumable state (None: no state is read or written).
        fingerprint: of the input and config (`fingerprint`); a state of another is not resumed.
        save_every: steps between state saves within a phase (0: only where the procedure calls `save`).
        extra_state: returns the procedure's own entries of the state (RNG state, ...) at save time.
        probe: optional (every, fn): fn(opt.params, record) after every `every`-th step of a phase and after
            its last step, for figures that need the whole state; its seconds go to timings["probe"].
    Attributes:
        timings: seconds per stage; clock: its `Clock`; history: the step records; resumed: the state
        this run resumed (after `resume`), else None.
    """

    def __init__(self, callback: Callable[[dict], None] | None = None, state_path=None,
                 fingerprint: str | None = None, save_every: int = 0,
                 extra_state: Callable[[], dict] | None = None,
                 probe: tuple[int, Callable[[dict, dict], None]] | None = None):
        self.callback = callback
        self.state_path = state_path
        self.fingerprint = fingerprint
        self.save_every = int(save_every)
        self.extra_state = extra_state or dict
        self.probe = probe
        self.timings: dict = {}
        self.clock = Clock(self.timings)
        self.history: list = []
        self.resumed: dict | None = None
        self._start = (time.perf_counter(), time.process_time())
        self._earlier = (0.0, 0.0)  # (wall, CPU) seconds of the resumed state's attempts

    def notify(self, record: dict) -> None:
        if self.callback is not None:
            self.callback(record)

    def stage(self, name: str, **figures) -> None:
        """Tells the callback that stage `name` starts (or, with figures, ends)."""
        self.notify({"stage": name, **figures})

    def resume(self) -> dict | None:
        """The saved state of this run, if any; its history and timings become this run's."""
        state = load_state(self.state_path, self.fingerprint)
        if state is not None:
            self.resumed = state
            self.history = list(state["history"])
            self.timings.update(state["timings"])
            earlier = state["timings"]
            self._earlier = (float(earlier.get("total", 0.0)), float(earlier.get("total_cpu", 0.0)))
        return state

    def elapsed(self) -> tuple[float, float]:
        """(wall, process CPU) seconds of this run so far, its interrupted attempts up to their last save
        included."""
        return (self._earlier[0] + time.perf_counter() - self._start[0],
                self._earlier[1] + time.process_time() - self._start[1])

    @property
    def earlier_seconds(self) -> float:
        """Wall seconds of the interrupted attempts this run resumed (up to their last save), without their
        probe's seconds; 0 for a fresh run."""
        probe = float(self.resumed["timings"].get("probe", 0.0)) if self.resumed is not None else 0.0
        return max(self._earlier[0] - probe, 0.0)

    def save(self, position: dict, opt: BoundedAdam) -> None:
        """Writes the resumable state at `position` ({..., "step": the next step}); no-op without a path."""
        if self.state_path is None:
            return
        p = opt.params
        wall, cpu = self.elapsed()
        save_state(self.state_path, {
            "fingerprint": self.fingerprint, **position,
            "points": p["points"].detach().clone(), "weights": p["weights"].detach().clone(),
            "reals": p["reals"].detach().clone(),
            "optimizer": opt.state_dict() if position.get("step", 0) > 0 else None,
            "history": self.history, "timings": {**self.timings, "total": wall, "total_cpu": cpu},
            **self.extra_state()})

    def run_phase(self, step_fn: Callable[[int], tuple[torch.Tensor, dict]], opt: BoundedAdam, steps: int,
                  start: int = 0, position: dict | None = None, prefix: str = "",
                  after_step: Callable[[int], dict | None] | None = None,
                  stop: Callable[[dict], bool] | None = None) -> bool:
        """Runs steps `start` .. `steps` - 1 of one phase (module docstring, steps 1-6).

        Args:
            step_fn: step -> (scalar loss tensor, dict of figures).
            opt: the phase's `BoundedAdam` (its parameters are the ones saved).
            steps: the phase's step count; start: the first step to run (a resumed phase's).
            position: leads every record and the saved state's position (e.g. {"phase": 1}).
            prefix: of the stage timers ("phase1_" -> "phase1_backward", "phase1_step").
            after_step: step -> figures or None, run after each update (constraints on the new state).
            stop: figures -> True ends the phase before that step's update.
        Returns:
            Whether `stop` ended the phase.
        """
        position = position or {}
        for step in range(start, steps):
            t0 = time.perf_counter()
            loss, figures = step_fn(step)
            stopping = stop is not None and stop(figures)
            if not stopping:
                with self.clock(prefix + "backward"):
                    opt.zero_grad()
                    if loss.requires_grad:
                        loss.backward()
                with self.clock(prefix + "step"):
                    opt.step()
                    if after_step is not None:
                        figures = {**figures, **(after_step(step) or {})}
            record = {**position, "step": step, "steps": steps, "loss": float(loss.detach()), **figures,
                      "seconds": time.perf_counter() - t0}
            self.history.append(record)
            self.notify(record)
            if self.probe is not None and ((step + 1) % self.probe[0] == 0 or step + 1 == steps):
                with self.clock("probe"):
                    self.probe[1](opt.params, record)
            if stopping:
                return True
            if self.save_every and (step + 1) % self.save_every == 0 and step + 1 < steps:
                self.save({**position, "step": step + 1}, opt)
        return False

    def finish(self) -> dict:
        """Sets "total" (wall seconds) and "total_cpu" (process CPU seconds), the interrupted attempts this run
        resumed included (`elapsed`)."""
        self.timings["total"], self.timings["total_cpu"] = self.elapsed()
        return self.timings


__all__ = ["TRAIN_ALL", "Clock", "Loop", "ReconstructionResult", "deterministic", "fingerprint", "freeze_faces",
           "load_state", "mesh_mask", "read_state", "save_state", "state_types", "timed_probabilities"]
