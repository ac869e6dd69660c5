"""One run, executed in a worker process: the method on its cached input, then the metrics of its mesh.

`execute_run` builds the run's config, reads its input (`eval.inputs.load_inputs`), calls the method with a GT
monitor (`gt_monitor`) and a checkpoint path (`checkpoint_path`), writes the output mesh atomically to
`WORK/meshes/<key[:2]>/<key>.ply` (`mesh_path_for`), scores it in the normalised GT frame (`score`:
`eval.metrics.compute_metrics` and the `metrics_version`) and returns the outcome with the hashes of the project
code the run executed (`eval.code_deps`). It never raises for a failing method: every failure is an outcome
with a one-line error. Both executors call it: the local pool (`eval.local_executor`) and Ray
(`eval.ray_executor`).
"""
from __future__ import annotations

import logging
import os
import time
import traceback
from pathlib import Path

import numpy as np

from eval import code_deps
from eval.code_hash import metrics_version, sources_changed
from eval.inputs import load_gt, load_inputs
from eval.io import write_mesh
from eval.plain import jsonable, one_line
from eval.sweep import RunSpec, build_config, get_method

log = logging.getLogger(__name__)


def _threads() -> int:
    """Threads of torch's intra-op pool in this process (the pool the DMesh kernels follow)."""
    import torch

    return int(torch.get_num_threads())


def limit_threads(n: int) -> None:
    """Caps this process's compute threads at `n`: torch's intra-op pool (which the DMesh kernels and
    renderers follow, `dmesh.render`, `dmesh.wdt`, `dmesh.losses.chamfer`), and the OpenMP, BLAS and
    numexpr pools of libraries that start theirs later in this process."""
    import torch

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        os.environ[var] = str(n)
    torch.set_num_threads(n)


def mesh_path_for(work: str | Path, key: str) -> Path:
    return Path(work) / "meshes" / key[:2] / f"{key}.ply"


def resolve_mesh_path(row: dict, db_path: str | Path) -> Path | None:
    """Absolute path of a stored run's output mesh (paths are stored relative to the store's folder)."""
    p = row.get("mesh_path")
    if not isinstance(p, (str, os.PathLike)) or not str(p):
        return None  # no mesh (a failed run): None from SQLite, NaN once the rows went through pandas
    p = Path(p)
    return p if p.is_absolute() else (Path(db_path).parent / p)


def checkpoint_path(work: str | Path, key: str) -> Path:
    """The run's `Inputs.checkpoint`: where a long DMesh run keeps its resumable state until its outcome is
    stored. The key hashes the method's code, config and input, so a state only ever resumes its own run."""
    return Path(work) / "states" / key[:2] / f"{key}.pt"


def drop_checkpoint(work: str | Path, key: str) -> None:
    """Removes the run's checkpoint (its outcome is stored, or will be); missing is fine."""
    checkpoint_path(work, key).unlink(missing_ok=True)


#: Samples per side of the monitor's CD p2s (curves of intermediate meshes; the final metrics use the sweep's).
MONITOR_SAMPLES = 20_000


def gt_monitor(gt):
    """`Inputs.monitor` of a run: CD p2s of an intermediate mesh against the GT (20K samples per side)."""
    from eval.metrics import chamfer_l1_p2s

    def monitor(mesh) -> dict:
        if mesh is None or len(mesh.faces) == 0:
            return {"cd_p2s": None, "faces": 0}
        return {"cd_p2s": float(chamfer_l1_p2s(mesh, gt, n=MONITOR_SAMPLES)), "faces": int(len(mesh.faces))}

    return monitor


def with_gt_figures(gt, gt_path: str | Path):
    """`gt` with its `gt_*` figures attached (`eval.metrics.GT_FIGURES_KEY`), from `gt_figures.json` beside the GT
    file when that was computed from the same file by the same metrics version, else computed and written there.

    Every run of a shape scores against the same GT, whose orientation and topology dominate the scoring of a
    million-face GT. Only a GT that `eval.metrics.gt_figures` leaves as it is (outward already, as `load_gt`
    returns it) is cached; any other is scored as before. Returns `gt` (its metadata updated in place when the figures apply).
    """
    import hashlib
    import json

    from eval.io import write_text
    from eval.metrics import GT_FIGURES_KEY, gt_figures

    gt_path = Path(gt_path)
    cache = gt_path.parent / "gt_figures.json"
    try:
        digest = hashlib.sha256(gt_path.read_bytes()).hexdigest()
    except OSError:
        return gt
    stamp = {"metrics_version": metrics_version(), "gt_sha256": digest}
    try:
        saved = json.loads(cache.read_text()) if cache.is_file() else None
    except (OSError, ValueError):
        saved = None
    if isinstance(saved, dict) and all(saved.get(k) == v for k, v in stamp.items()):
        gt.metadata[GT_FIGURES_KEY] = saved["figures"]
        return gt
    oriented, figures = gt_figures(gt)
    if np.array_equal(np.asarray(oriented.faces), np.asarray(gt.faces)):
        gt.metadata[GT_FIGURES_KEY] = figures
        try:
            write_text(cache, json.dumps({**stamp, "figures": jsonable(figures)}, sort_keys=True))
        except OSError as exc:  # a read-only work folder scores without the cache
            log.debug("gt_figures.json not written: %s", exc)
    return gt


def score(mesh, gt, inputs: dict, info: dict | None) -> dict:
    """The stored metrics of a run's mesh: `eval.metrics.compute_metrics` with the sweep's sample count, plus
    the `metrics_version` of the code that computed them (`dmesh rescore` recomputes older ones).

    Args: mesh, gt: trimesh meshes; inputs: the run's input settings (`metric_samples`); info: the method's
    info. Mesh to DMesh: a method whose output keeps the GT vertices first says how many in its info
    ("re_fp_vertices"), which adds RE / FP to the metrics (Table 1).
    """
    from eval.metrics import compute_metrics

    k = (info or {}).get("re_fp_vertices")
    metrics = compute_metrics(mesh, gt, n=int(inputs.get("metric_samples", 100_000)), seed=0,
                              **({"re_fp_vertices": int(k)} if k is not None else {}))
    return {**metrics, "metrics_version": metrics_version()}


def execute_run(spec: RunSpec, gt_path: str | Path, work: str | Path, method=None) -> dict:
    """Runs one run in this process and returns its outcome (never raises for a failing method).

    `method` is the method object; None looks `spec.method` up in the registry (Ray tasks get the object
    itself, since a fresh Ray worker only knows the methods registered at import time).

    Returns:
        {"status": "done", "metrics", "timings", "info", "peak_memory_mb", "mesh_path"} or
        {"status": "failed", "error": one line}; a failed run whose method returned (an empty mesh, NaN
        vertices) also keeps the method's "timings" and "info", so the store says how far it got.
    """
    told: dict = {}  # what a method that returned said of its run, kept on a failed outcome too
    try:
        method = method if method is not None else get_method(spec.method)
        changed = sources_changed(method, spec.code_version)
        if changed:
            raise RuntimeError(changed)
        with code_deps.record() as executed:
            config, _ = build_config(method, spec.overrides)
            inputs = load_inputs(spec, Path(gt_path), work)
            gt = load_gt(gt_path)
            inputs.monitor = gt_monitor(gt)
            inputs.checkpoint = str(checkpoint_path(work, spec.key))
            resumed = Path(inputs.checkpoint).exists()  # an earlier attempt ran code this one may skip
            cpu0 = time.process_time()
            result = method.reconstruct(inputs, config)
            cpu_s = time.process_time() - cpu0
        drop_checkpoint(work, spec.key)
        told = {"timings": {k: float(v) for k, v in dict(result.timings).items()},
                "info": {**jsonable(dict(result.info or {})), "worker_threads": _threads(),  # the timings' budget
                         "method_cpu_s": cpu_s}}  # CPU seconds of the worker (all threads) in the method
        # What the harness did to the input before the method (not in the method's time): the same for every
        # method on this input.
        for key, record in (("preprocess", inputs.preprocess), ("lifted_depth", getattr(inputs, "lifted_depth", None))):
            if record is not None:
                told["info"][key] = jsonable(record)
        mesh = result.mesh
        if mesh is None or len(mesh.faces) == 0:
            raise ValueError("the method returned an empty mesh")
        if not np.isfinite(np.asarray(mesh.vertices)).all():
            raise ValueError("the method returned a mesh with NaN or inf vertices")
        out = mesh_path_for(work, spec.key)
        write_mesh(mesh, out)
        metrics = score(mesh, with_gt_figures(gt, gt_path), spec.inputs, result.info)
        _warn_post_step_damage(spec, result.info, metrics)
        if "total" not in told["timings"]:
            raise ValueError("the method's timings lack 'total'")
        return {"status": "done", "metrics": dict(metrics), **told, "peak_memory_mb": float(result.peak_memory_mb),
                "mesh_path": str(out), "code_deps": None if resumed else _code_deps(method, spec, executed)}
    except Exception as exc:  # noqa: BLE001 - every failure of a run is a result (stored as failed)
        log.debug("run %s failed:\n%s", spec.key, traceback.format_exc())
        drop_checkpoint(work, spec.key)  # a failing run starts over when retried
        return {"status": "failed", "error": one_line(exc), **told}


def _code_deps(method, spec: RunSpec, executed) -> dict | None:
    """The hashes of the code the run executed (`eval.code_deps.deps_for`), or None when nothing was recorded,
    the method names its own code trees, or its sources changed while it ran (the record would not match).
    A run resumed from an earlier attempt's checkpoint records none either (`execute_run`): the code that
    attempt ran is not in this one's record."""
    if executed is None or getattr(method, "code_trees", None) or sources_changed(method, spec.code_version):
        return None
    try:
        return code_deps.deps_for(method, executed)
    except (OSError, ValueError) as exc:  # a source file vanished meanwhile: the run is simply not adoptable
        log.warning("run %s: could not hash the code it executed: %s", spec.key[:12], one_line(exc))
        return None


def _warn_post_step_damage(spec: RunSpec, info, metrics) -> None:
    """Logs a warning when the run's final CD p2s is well above the monitor's last one (`eval.reports.checks`):
    something after the last step (the surface step) damaged the mesh."""
    from eval.reports.checks import GAP_RATIO, monitor_gap

    gap = monitor_gap(info, metrics.get("cd_p2s"))
    if gap is not None and gap[0] > GAP_RATIO:
        log.warning("run %s (%s on %s): final CD p2s %.3g is %.2fx the last monitored mesh's (%.3g): the mesh lost "
                    "accuracy after its last step", spec.key[:12], spec.method, spec.shape.id, metrics["cd_p2s"],
                    gap[0], gap[1]["cd_p2s"])
