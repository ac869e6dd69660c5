"""The experiment runner: prepares inputs once, runs every pending run of a sweep, stores each result.

Flow of `run_sweep(sweep, work, ...)`:

1. Resolve shapes and prepare each GT once (cached under `WORK/inputs/<shape>-<gt hash>/`): the GT is
   loaded or generated, classified (closed / open / mixed) and normalised (vertex mean at the origin, max
   vertex norm `sweep.radius`), then written as `gt.ply` beside `meta.json`.
2. Expand the sweep into runs (`eval.sweep.expand`) and skip every run whose key is `done` (or `failed`,
   unless `retry_failed`), unless `rerun` asks for stored runs again (all, or those scored by an earlier
   metric code). Runs left `running` by a killed process are redone. A run with no row under its key whose
   latest done twin of an earlier code version executed only code that is unchanged is adopted instead
   (`adopt_current`, `eval.code_deps`): skipped, and shown by the reports as the current code's.
3. Prepare the inputs of the pending runs once per (shape, input kind, seed), cached beside the GT:
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
   cluster, see `eval.ray_executor`). The worker calls the method, computes
   `eval.metrics.compute_metrics(pred, gt)` in the normalised GT frame, and hands the result back with the
   hashes of the project code the run executed (`eval.code_deps`); the output
   mesh lands atomically in `WORK/meshes/<key[:2]>/<key>.ply` (written by a local worker; by this process
   from a Ray task's result). Only this (parent) process writes the store.

Every failure of a run (exception, empty mesh, timeout, worker crash) is stored as a `failed` row with a
one-line error, and the sweep goes on.

Checkpoints. Each run may keep a resumable state in `WORK/states/<key[:2]>/<key>.pt` (`checkpoint_path`,
handed to the method as `Inputs.checkpoint`; the DMesh procedures save theirs every `save_every` steps). It
is removed when the run's outcome is stored, except when its worker died (killed, out of memory, or the
machine stopped), so a rerun of a run whose process died (redone as above, or with `retry_failed`) goes on
from its last save instead of from step 0; its time includes the earlier attempts up to that save. A run that
timed out or raised starts over.

Sharing a store. Two sweeps (processes) may run on one work folder and store at once; each run is computed
once. A run is claimed atomically with a lease (this process's id and host, a token of this sweep and a
heartbeat; `eval.store.Store.claim`), and this process refreshes the heartbeat every `lease_s / 6` seconds
from its wait loop while it holds runs (not from a thread: the local pool forks, and forking a process with a
second thread that may hold a lock is asking for a deadlock). A run that another live sweep holds is put
aside and asked about again every 2 s: this sweep *waits* for it rather than computing it twice or returning
without it, so that when `run_sweep` returns every run of the sweep is stored and its reports are complete.
Runs that another sweep finished meanwhile are counted in `SweepSummary.elsewhere` ("finished by another
sweep" in the summary line). When the holder dies, its runs are taken over: at once when it ran on this host
(its process is gone), after `lease_s` seconds without a heartbeat when it ran on another one. A `done` row
is never overwritten, and a sweep whose run was taken over (it stalled longer than `lease_s`) does not store
its late outcome. On the way out (also on an exception or Ctrl-C) the sweep releases what it still holds.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import multiprocessing as mp
import os
import shutil
import signal
import tempfile
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import wait as mp_wait
from pathlib import Path
from typing import Callable

import numpy as np

from eval import code_deps
from eval.io import atomic_path, honour_umask, write_mesh, write_text
from eval.store import LEASE_S, Lease, Store
from eval.sweep import RunSpec, ShapeRef, Sweep, build_config, expand, get_method, sources_changed

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")
#: What a sweep runs again of the runs already stored done (`RunnerConfig.rerun`): nothing, all, or those scored
#: by an earlier metric code.
RERUN_MODES = (None, "all", "stale-metrics")


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


# --------------------------------------------------------------------------------------------------- inputs

#: Version of the GT preparation, in the cache folder names: bumped when `prepare_gt` changes the GT it
#: writes, so that no input derived from an older GT is reused (2: inside-out closed GTs flipped outward).
GT_CACHE_VERSION = 2


def shape_dir(work: str | Path, shape: ShapeRef, radius: float) -> Path:
    """Cache folder of one GT shape in one normalisation."""
    safe = "".join(c if c.isalnum() or c in "-_@." else "_" for c in shape.id)
    return Path(work) / "inputs" / f"{safe}-{shape.gt_hash[:12]}-r{radius:g}-v{GT_CACHE_VERSION}"


def prepare_gt(shape: ShapeRef, work: str | Path, radius: float = 1.0) -> tuple[ShapeRef, Path]:
    """Loads or generates, classifies and normalises the GT once; returns (shape with category, gt.ply path)."""
    folder = shape_dir(work, shape, radius)
    meta_path, gt_path = folder / "meta.json", folder / "gt.ply"
    if meta_path.is_file() and gt_path.is_file():
        meta = json.loads(meta_path.read_text())
        return dataclasses.replace(shape, category=meta["category"]), gt_path
    from datasets.normalize import normalize

    if shape.kind == "synthetic":
        from datasets import synthetic

        mesh = synthetic.generate(shape.source, seed=shape.gen_seed)
        category = shape.category
    else:
        from datasets.meshes import classify, load_mesh

        mesh = load_mesh(shape.source)
        category = classify(mesh)
    if category not in ("closed", "open", "mixed"):
        raise ValueError(f"shape {shape.id}: unexpected category {category!r}")
    from datasets.meshes import orient_outward

    mesh, orientation = orient_outward(mesh, name=shape.source)  # before anything is sampled or rendered
    mesh, transform = normalize(mesh, radius=radius)
    folder.mkdir(parents=True, exist_ok=True)
    write_mesh(mesh, gt_path)
    meta = {"id": shape.id, "kind": shape.kind, "source": shape.source, "gen_seed": shape.gen_seed,
            "category": category, "gt_hash": shape.gt_hash, "radius": radius, "orientation": orientation,
            "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
            "transform": _jsonable(transform)}
    write_text(meta_path, json.dumps(meta, indent=2) + "\n")
    return dataclasses.replace(shape, category=category), gt_path


def _jsonable(obj):
    if hasattr(obj, "to_dict"):
        obj = obj.to_dict()
    elif dataclasses.is_dataclass(obj):
        obj = dataclasses.asdict(obj)
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj if isinstance(obj, (int, float, str, bool, type(None))) else str(obj)


def load_gt(gt_path: str | Path):
    """The cached normalised GT as a trimesh.Trimesh (exact vertices and faces, no processing), oriented.

    `prepare_gt` turns an inside-out closed GT outward before writing it and records what it found in
    meta.json ("orientation"); that status goes into `mesh.metadata["orientation"]`, where
    `eval.metrics.compute_metrics` reports it. A gt.ply without that record (written elsewhere) is passed
    through `datasets.meshes.orient_outward` here.
    """
    import trimesh

    gt_path = Path(gt_path)
    mesh = trimesh.load(gt_path, process=False, force="mesh")
    meta_path = gt_path.parent / "meta.json"
    found = json.loads(meta_path.read_text()).get("orientation") if meta_path.is_file() else None
    if found is not None:
        mesh.metadata["orientation"] = found
        return mesh
    from datasets.meshes import orient_outward

    return orient_outward(mesh, name=str(gt_path))[0]


def input_path(work: str | Path, shape: ShapeRef, kind: str, settings: dict, seed: int) -> Path:
    """Cache path of one prepared input (a .npz file for point clouds, a folder for multi-view).

    A corrupted input (settings["corruption"], see `eval.sweep.Sweep.input_variants`) gets the suffix
    `datasets.corrupt.cache_tag` of its corruption, e.g. `pc_n100000_s0_noise0.005.npz`."""
    from datasets.corrupt import cache_tag

    if "preprocess" in settings:  # beside the raw input it is made from
        pre = settings["preprocess"]
        raw = input_path(work, shape, kind, _without(settings, "preprocess"), seed)
        return raw.with_name(f"{raw.name[:-4] if raw.suffix == '.npz' else raw.name}.pre-{pre['stages']}-"
                             f"{pre['code'][:8]}.npz")
    if "lift" in settings:  # beside the capture it is lifted from
        lift = settings["lift"]
        capture = input_path(work, shape, kind, _without(settings, "lift"), seed)
        return capture.with_name(f"{capture.name}_lift{lift['points']}_s{seed}-{lift['code'][:8]}.npz")
    folder = shape_dir(work, shape, settings["radius"])
    tag = cache_tag(settings.get("corruption"))
    if kind == "pointcloud":
        return folder / f"pc_n{settings['n_points']}_s{seed}{tag}.npz"
    if kind == "multiview":
        return folder / f"mv_v{settings['views']}_r{settings['resolution']}_d{settings['distance']:g}{tag}"
    return folder / "gt.ply"


def _without(settings: dict, key: str) -> dict:
    return {k: v for k, v in settings.items() if k != key}


def input_id(spec: RunSpec) -> tuple:
    """What identifies the prepared input of a run: (shape id, input kind, seed, input settings as JSON)."""
    from eval.sweep import canonical_json

    return spec.shape.id, spec.input_kind, spec.seed, canonical_json(dict(spec.inputs))


def prepare_input(shape: ShapeRef, gt_path: Path, kind: str, settings: dict, seed: int, work: str | Path) -> Path:
    """Creates the cached input of (shape, kind, settings, seed) unless it exists; returns its path.

    A corrupted input is made from the clean one of the same sizes (prepared first, and cached too):
    `datasets.corrupt.corrupt_cloud` for point clouds (its extra arrays, e.g. a scan's cameras, are saved
    beside `points` and `normals`), `datasets.corrupt.add_depth_noise` for a multi-view capture."""
    path = input_path(work, shape, kind, settings, seed)
    if path.exists():
        return path
    if "preprocess" in settings or "lift" in settings:
        _prepare_harness_input(shape, gt_path, kind, settings, seed, work, path)
        return path
    from datasets.corrupt import cache_tag

    corruption = dict(settings.get("corruption") or {})
    clean = {k: v for k, v in settings.items() if k != "corruption"}
    if kind == "pointcloud" and cache_tag(corruption):
        from datasets.corrupt import corrupt_cloud

        with np.load(prepare_input(shape, gt_path, kind, clean, seed, work)) as z:
            points, normals = z["points"], z["normals"]
        arrays = corrupt_cloud(load_gt(gt_path), points, normals, corruption, seed, float(settings["radius"]))
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
    elif kind == "pointcloud":
        from datasets.sampling import sample_points

        points, normals = sample_points(load_gt(gt_path), settings["n_points"], seed)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, points=np.asarray(points, np.float32), normals=np.asarray(normals, np.float32))
    elif kind == "multiview":
        from datasets.capture import MultiView, capture
        from datasets.corrupt import add_depth_noise

        if cache_tag(corruption):
            views = MultiView.load(prepare_input(shape, gt_path, kind, clean, seed, work))
            views = add_depth_noise(views, float(corruption.get("depth_noise", 0.0)) * float(settings["radius"]), seed)
        else:
            views = capture(load_gt(gt_path), views=settings["views"], resolution=settings["resolution"],
                            distance=settings["distance"])
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
        try:
            honour_umask(tmp)  # mkdtemp makes it 0o700
            views.save(tmp)
            os.replace(tmp, path)
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if not path.exists():
                raise
            # Another process sharing the work folder finished the same capture first: use its copy.
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return path


def _prepare_harness_input(shape: ShapeRef, gt_path: Path, kind: str, settings: dict, seed: int, work,
                           path: Path) -> None:
    """Writes `path`: the pre-processed points of the input without `"preprocess"` (`eval.preprocess.apply`,
    with its record as `preprocess_info`), or the lifted depth pixels of the capture without `"lift"`
    (`eval.preprocess.lift_depth`, record `lift_info`). Points and normals are float32, as every raw input."""
    from eval import preprocess

    if "preprocess" in settings:
        raw = prepare_input(shape, gt_path, kind, _without(settings, "preprocess"), seed, work)
        with np.load(raw) as z:
            arrays = {k: z[k] for k in z.files}
        points, normals, info = preprocess.apply(arrays["points"], arrays["normals"], settings["preprocess"]["stages"],
                                                 is_outlier=arrays.get("is_outlier"))
        out = {"preprocess_info": np.array(json.dumps(info))}
        if "lift_info" in arrays:  # pre-processed lifted depth pixels keep the lift's record
            out["lift_info"] = arrays["lift_info"]
    else:
        from datasets.capture import MultiView

        views = MultiView.load(prepare_input(shape, gt_path, kind, _without(settings, "lift"), seed, work))
        points, normals, info = preprocess.lift_depth(views, int(settings["lift"]["points"]), seed)
        out = {"lift_info": np.array(json.dumps(info))}
    out.update(points=np.asarray(points, np.float32), normals=np.asarray(normals, np.float32))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **out)


def load_inputs(spec: RunSpec, gt_path: Path, work: str | Path):
    """The `baselines.base.Inputs` of a run, read from the cache. A pre-processed input's record goes to
    `Inputs.preprocess`, a lifted one's to the attribute `lifted_depth` (the runner puts both in the run's
    info)."""
    from baselines.base import Inputs

    path = input_path(work, spec.shape, spec.input_kind, dict(spec.inputs), spec.seed)
    if spec.input_kind == "pointcloud" or "lift" in spec.inputs:
        with np.load(path) as z:
            inputs = Inputs(points=z["points"], normals=z["normals"], views=None, seed=spec.seed)
            if "preprocess_info" in z.files:
                inputs.preprocess = json.loads(str(z["preprocess_info"]))
            if "lift_info" in z.files:
                inputs.lifted_depth = json.loads(str(z["lift_info"]))
        return inputs
    if spec.input_kind == "multiview":
        from datasets.capture import MultiView

        return Inputs(points=None, normals=None, views=MultiView.load(path), seed=spec.seed)
    # "mesh" input (mesh to DMesh, Table 1): the normalised GT mesh itself, as `inputs.mesh`.
    inputs = Inputs(points=None, normals=None, views=None, seed=spec.seed)
    inputs.mesh = load_gt(gt_path)
    return inputs


# --------------------------------------------------------------------------------------------------- one run

def mesh_path_for(work: str | Path, key: str) -> Path:
    return Path(work) / "meshes" / key[:2] / f"{key}.ply"


def checkpoint_path(work: str | Path, key: str) -> Path:
    """The run's `Inputs.checkpoint`: where a long DMesh run keeps its resumable state until its outcome is
    stored. The key hashes the method's code, config and input, so a state only ever resumes its own run."""
    return Path(work) / "states" / key[:2] / f"{key}.pt"


def drop_checkpoint(work: str | Path, key: str) -> None:
    """Removes the run's checkpoint (its outcome is stored, or will be); missing is fine."""
    checkpoint_path(work, key).unlink(missing_ok=True)


def one_line(exc: BaseException) -> str:
    """`Type: message` on one line, at most 500 characters."""
    msg = " ".join(str(exc).split()) or repr(exc)
    return f"{type(exc).__name__}: {msg}"[:500]


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


def score(mesh, gt, inputs: dict, info: dict | None) -> dict:
    """The stored metrics of a run's mesh: `eval.metrics.compute_metrics` with the sweep's sample count, plus
    the `metrics_version` of the code that computed them (`dmesh rescore` recomputes older ones).

    Args: mesh, gt: trimesh meshes; inputs: the run's input settings (`metric_samples`); info: the method's
    info. Mesh to DMesh: a method whose output keeps the GT vertices first says how many in its info
    ("re_fp_vertices"), which adds RE / FP to the metrics (Table 1).
    """
    from eval.metrics import compute_metrics
    from eval.sweep import metrics_version

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
                "info": {**_jsonable(dict(result.info or {})), "worker_threads": _threads(),  # the timings' budget
                         "method_cpu_s": cpu_s}}  # CPU seconds of the worker (all threads) in the method
        # What the harness did to the input before the method (not in the method's time): the same for every
        # method on this input.
        for key, record in (("preprocess", inputs.preprocess), ("lifted_depth", getattr(inputs, "lifted_depth", None))):
            if record is not None:
                told["info"][key] = _jsonable(record)
        mesh = result.mesh
        if mesh is None or len(mesh.faces) == 0:
            raise ValueError("the method returned an empty mesh")
        if not np.isfinite(np.asarray(mesh.vertices)).all():
            raise ValueError("the method returned a mesh with NaN or inf vertices")
        out = mesh_path_for(work, spec.key)
        write_mesh(mesh, out)
        metrics = score(mesh, gt, spec.inputs, result.info)
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


def _warn_post_step_damage(spec: RunSpec, info, metrics) -> None:
    """Logs a warning when the run's final CD p2s is well above the monitor's last one (`eval.reports.checks`):
    something after the last step (the surface step) damaged the mesh."""
    from eval.reports.checks import GAP_RATIO, monitor_gap

    gap = monitor_gap(info, metrics.get("cd_p2s"))
    if gap is not None and gap[0] > GAP_RATIO:
        log.warning("run %s (%s on %s): final CD p2s %.3g is %.2fx the last monitored mesh's (%.3g): the mesh lost "
                    "accuracy after its last step", spec.key[:12], spec.method, spec.shape.id, metrics["cd_p2s"],
                    gap[0], gap[1]["cd_p2s"])


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


class _Claims:
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


def _run_local(claims: _Claims, work: str, jobs: int, timeout_s: float, on_done: Callable,
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


def _run_ray(claims: _Claims, work: str, jobs: int, timeout_s: float, on_done: Callable) -> None:
    from eval.ray_executor import run_ray

    run_ray(claims, work, jobs, timeout_s, on_done)


# --------------------------------------------------------------------------------------------------- sweep

def resolve_and_prepare_shapes(sweep: Sweep, work: str | Path, progress=None) -> tuple[list[ShapeRef], dict]:
    """Resolves the sweep's shapes and prepares their GT; returns (shapes, {shape id: gt path})."""
    from eval.progress import progress as bar

    refs = sweep.resolved_shapes()
    shapes, gts = [], {}
    for ref in (progress or bar)(refs, desc="ground truth", unit="shape", leave=False):
        ref, gt = prepare_gt(ref, work, sweep.radius)
        shapes.append(ref)
        gts[ref.id] = gt
    return shapes, gts


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


def _stored(row: dict | None, runner: RunnerConfig, metrics_now: str | None = None) -> bool:
    """Whether a sweep skips the run whose store row is `row`: done (unless `runner.rerun` asks for it again),
    or failed (unless failures are retried, or `rerun` is "all").

    `rerun="stale-metrics"` reruns the done runs scored by another metric code than `metrics_now` (the
    current `metrics_version`): what `dmesh rescore` cannot reach when a run's mesh is not on disk.
    """
    status = None if row is None else row["status"]
    if status == "failed":
        return not (runner.retry_failed or runner.rerun == "all")
    if status != "done":
        return False
    if runner.rerun == "all":
        return False
    if runner.rerun == "stale-metrics":
        return (row.get("metrics_json") or {}).get("metrics_version") == metrics_now
    return True


def _metrics_now(runner: RunnerConfig) -> str | None:
    """The current metrics version when `runner` reruns runs by it, else None (not computed)."""
    from eval.sweep import metrics_version

    return metrics_version() if runner.rerun == "stale-metrics" else None


def _wall_s(row: dict) -> float | None:
    from datetime import datetime

    try:
        return (datetime.fromisoformat(row["finished_at"]) - datetime.fromisoformat(row["started_at"])).total_seconds()
    except (TypeError, ValueError):
        return None


def plan_sweep(sweep: Sweep, runner: RunnerConfig) -> SweepPlan:
    """What `run_sweep` would run, without running it: the runs stored and pending, and for the pending ones
    the wall time (start to finish, metrics included) of the latest finished run of the same configuration
    (method, config overrides, shape, input kind, input settings, seed) of any code version in the store. A time
    estimate from measured runs: they ran under whatever load the machine had then.

    Writes nothing: no GT is prepared (a run's key needs its shape's GT hash, not the GT) and the store is only
    read (`Store(readonly=True)`)."""
    runs = expand(sweep, sweep.resolved_shapes())
    plan = SweepPlan(name=sweep.name, total=len(runs))
    if not Path(runner.db_path).is_file():  # no store yet: everything is to run, nothing was ever timed
        plan.pending = len(runs)
        return plan
    with Store(runner.db_path, readonly=True) as store:
        if runner.rerun is None:
            planned = [r.key for r in runs]
            runs = adopt_current(runs, store)
            plan.kept = sum(a != r.key for a, r in zip(planned, runs))
        walls: dict[str, tuple[str, float]] = {}
        for row in store.rows():
            wall = _wall_s(row) if row["status"] == "done" else None
            if wall is None:
                continue
            ident = json.dumps([row["method"], row["config_label"], row["shape"], row["input_kind"],
                                row["inputs_json"], int(row["seed"])], sort_keys=True, default=str)
            if ident not in walls or row["started_at"] > walls[ident][0]:
                walls[ident] = (row["started_at"], wall)
        metrics_now = _metrics_now(runner)
        for spec in runs:
            if _stored(store.get(spec.key), runner, metrics_now):
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


def run_sweep(sweep: Sweep, runner: RunnerConfig) -> SweepSummary:
    """Runs every pending run of `sweep` and stores the outcomes; see the module docstring.

    Raises:
        ValueError: unknown method, shape or config key (before anything runs); Ray missing.
    """
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
    runs = expand(sweep, shapes)
    lease = Lease.new()
    with Store(runner.db_path) as store:
        kept = 0
        if runner.rerun is None:  # a rerun runs the current code under its own key
            planned = [r.key for r in runs]
            runs = adopt_current(runs, store)
            kept = sum(a != r.key for a, r in zip(planned, runs))
        summary = SweepSummary(total=len(runs), kept=kept, db=str(runner.db_path), keys=[r.key for r in runs])
        pending, retry_attempts = [], {}
        metrics_now = _metrics_now(runner)
        for spec in runs:
            row = store.get(spec.key)
            if _stored(row, runner, metrics_now):
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

        needed = sorted({input_id(s) for s in pending})
        by_id = {s.id: s for s in shapes}
        input_errors = {}  # input_id -> error; its runs are stored failed when claimed
        for ident in progress(needed, desc="inputs", unit="input", leave=False):
            shape_id, kind, seed, _ = ident
            spec = next(s for s in pending if input_id(s) == ident)
            try:
                prepare_input(by_id[shape_id], gts[shape_id], kind, dict(spec.inputs), seed, work)
            except Exception as exc:  # noqa: BLE001 - an input that cannot be prepared fails its runs
                err = f"input preparation failed: {one_line(exc)}"
                log.warning("%s %s seed %d: %s", shape_id, kind, seed, err)
                input_errors[ident] = err

        bar = progress(total=len(pending), desc=f"sweep {sweep.name}", unit="run")

        def on_start(spec: RunSpec) -> None:
            bar.set_postfix_str(f"{spec.method} / {spec.shape.id} / {spec.input_kind}", refresh=False)

        def on_elsewhere(spec: RunSpec, status: str) -> None:
            summary.elsewhere += 1
            log.info("%s on %s (%s, seed %d): %s by another sweep sharing the store", spec.method, spec.shape.id,
                     spec.input_kind, spec.seed, status)
            bar.update(1)

        def on_done(spec: RunSpec, outcome: dict) -> None:
            # A checkpoint outlives only a run whose worker died (killed, or the machine stopped): a retry resumes
            # it. A timed-out run starts over, so a retry does not extend its time limit.
            if not str(outcome.get("error", "")).startswith("WorkerDied"):
                drop_checkpoint(work, spec.key)
            if outcome["status"] == "done":
                mesh_path = outcome["mesh_path"]
                try:  # store paths relative to the store's folder when possible (movable work folders)
                    mesh_path = os.path.relpath(mesh_path, runner.db_path.parent)
                except ValueError:
                    pass
                stored = store.finish(spec.key, status="done", metrics=outcome["metrics"],
                                      timings=outcome["timings"], info=outcome.get("info"),
                                      peak_memory_mb=outcome.get("peak_memory_mb"), mesh_path=mesh_path, lease=lease,
                                      code_deps=outcome.get("code_deps"))
            else:
                stored = store.finish(spec.key, status="failed", error=outcome["error"], lease=lease,
                                      timings=outcome.get("timings"), info=outcome.get("info"))
                if stored:
                    log.warning("%s on %s (%s, seed %d) failed: %s", spec.method, spec.shape.id, spec.input_kind,
                                spec.seed, outcome["error"])
            if not stored:  # another sweep took the run over (this one stalled past lease_s); its outcome wins
                summary.elsewhere += 1
            elif outcome["status"] == "done":
                summary.done += 1
            else:
                summary.failed += 1
            bar.update(1)

        claims = _Claims(store, lease, pending, gts, stale_s=runner.lease_s, retry_attempts=retry_attempts,
                         input_errors=input_errors, on_start=on_start, on_done=on_done, on_elsewhere=on_elsewhere)
        try:
            if runner.executor == "ray":
                _run_ray(claims, str(work), runner.jobs, float(sweep.timeout_s), on_done)
            else:
                log.info("%d concurrent run(s), %d thread(s) each", runner.jobs, runner.threads_per_run)
                _run_local(claims, str(work), runner.jobs, float(sweep.timeout_s), on_done, runner.threads_per_run)
        finally:
            bar.close()
            try:
                store.release(lease)
            except Exception as exc:  # noqa: BLE001 - never hide the exception that brought us here
                log.warning("could not release this sweep's runs: %s", one_line(exc))
    return summary


def resolve_mesh_path(row: dict, db_path: str | Path) -> Path | None:
    """Absolute path of a stored run's output mesh (paths are stored relative to the store's folder)."""
    p = row.get("mesh_path")
    if not isinstance(p, (str, os.PathLike)) or not str(p):
        return None  # no mesh (a failed run): None from SQLite, NaN once the rows went through pandas
    p = Path(p)
    return p if p.is_absolute() else (Path(db_path).parent / p)
