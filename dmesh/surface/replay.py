"""The surface step under several configs at once, each stage run once for all the configs that agree up to it.

An ablation (`python -m eval.bench surface_ablation`) runs the step once per variant, each leaving out one stage:
every variant runs the stages before the one it leaves out exactly as the full step does, and the first two
stages (the vote and the revote) take most of the step's time. `run_variants` runs the configs as a tree: the
stages that a group of configs runs alike (same stage, same section of settings, same run-wide fields) run once on
one state, which is copied where the configs part. Each result equals `dmesh.surface.run` of its config
(tests/test_surface_replay.py); its `info["stages"]` holds the seconds of every stage on its own path, shared
ones included, so a variant's time reads as if it had run alone.

Not imported by the surface step itself: only the tools that compare configs use it.
"""
from __future__ import annotations

import copy
from typing import Mapping

import numpy as np

from dmesh.surface import STAGES, Surface, SurfaceConfig, SurfaceState, _run_stage, run


def _steps(cfg: SurfaceConfig) -> list[tuple]:
    """The stages `run` runs for `cfg`, in order, each as (stage, its section of `cfg` or None)."""
    return [(stage, getattr(cfg, stage.section) if stage.section else None) for stage in STAGES
            if stage.name not in cfg.skip and (cfg.clean or not stage.cleanup)]


def _snapshot(state: SurfaceState) -> SurfaceState:
    """A copy of `state` that the stages can change without changing `state`: its arrays, labels and counts
    copied; the triangulation, the input samples and the sample evidence (which no stage changes) shared."""
    out = copy.copy(state)
    for name, value in vars(state).items():
        if isinstance(value, np.ndarray):
            setattr(out, name, value.copy())
    out.info = copy.deepcopy(state.info)
    out.vote = copy.deepcopy(state.vote)
    return out


def run_variants(pd, walls: np.ndarray, normals=None, samples: np.ndarray | None = None,
                 configs: Mapping[str, SurfaceConfig] | None = None) -> dict[str, Surface]:
    """{name: `dmesh.surface.run(pd, walls, normals, samples, config)`} for each (name, config) of `configs`,
    sharing the stages the configs run alike (module docstring). Arguments as `dmesh.surface.run`."""
    configs = dict(configs or {})
    walls = np.asarray(walls, dtype=bool)
    if not walls.any():
        return {name: run(pd, walls, normals, samples, cfg) for name, cfg in configs.items()}
    samples = normals[0] if samples is None and normals is not None else samples
    if normals is not None:
        normals = (np.asarray(normals[0], dtype=np.float64), np.asarray(normals[1], dtype=np.float64))
    groups: dict[tuple, list[str]] = {}
    for name, cfg in configs.items():  # the run-wide fields are the state's own: shared only when equal
        groups.setdefault((cfg.seed, cfg.workers, cfg.mode, cfg.spacing_neighbours), []).append(name)
    out: dict[str, Surface] = {}
    for (seed, workers, mode, spacing), names in groups.items():
        state = SurfaceState(pd, walls, normals, samples, seed, workers, mode, spacing)
        state.evidence()  # built once for every branch (the stages build it when they first need it)
        plans = {name: _steps(configs[name]) for name in names}
        _descend(state, {}, plans, 0, configs[names[0]], out)
    return {name: out[name] for name in configs}


def _descend(state: SurfaceState, records: dict, plans: dict[str, list], depth: int, cfg: SurfaceConfig,
             out: dict) -> None:
    """Runs step `depth` of every plan in `plans` (all at the same state so far), once per distinct step, and
    goes on with each group; a plan that has no step left gets its result."""
    branches: list[tuple[object, list[str]]] = []
    for name, steps in plans.items():
        key = steps[depth] if depth < len(steps) else None
        for branch in branches:
            if branch[0] == key:
                branch[1].append(name)
                break
        else:
            branches.append((key, [name]))
    for i, (key, names) in enumerate(branches):
        last = i == len(branches) - 1
        here, recs = (state, records) if last else (_snapshot(state), copy.deepcopy(records))
        if key is None:
            here.info["sheet_faces"] = int(len(here.sheet))
            here.info["stages"] = recs
            for name in names:
                out[name] = copy.deepcopy(here.result())
            continue
        stage, section = key
        here, recs[stage.name] = _run_stage(stage, here, _with_section(cfg, stage, section))
        _descend(here, recs, {name: plans[name] for name in names}, depth + 1, cfg, out)


def _with_section(cfg: SurfaceConfig, stage, section) -> SurfaceConfig:
    """`cfg` with `section` as the section of `stage` (what `_run_stage` reads of the config)."""
    if stage.section is None or getattr(cfg, stage.section) == section:
        return cfg
    return cfg.with_overrides({stage.section: section})


__all__ = ["run_variants"]
