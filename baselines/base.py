"""The interface every reconstruction method implements, and the stopwatch that times it.

Shape letters: N input points, V views, H x W pixels, F output faces.

A method takes `Inputs` (an oriented point cloud or a `datasets.capture.MultiView` capture, both in the GT's
normalisation frame: vertex mean at the origin, max vertex norm 1) and returns a `Result` holding the mesh,
per-stage wall times and the peak memory of the call.

Peak memory, measured honestly for native code too (pymeshlab, open3d and CGAL allocate outside Python, so
`tracemalloc` would miss them): on Linux the kernel's resident-set high-water mark `VmHWM` is reset by
writing `5` to `/proc/self/clear_refs` before the call and read from `/proc/self/status` after it; the figure
is that high-water mark minus the resident size at the start of the call, i.e. the extra resident memory the
call needed at its worst moment. Where `/proc` cannot be used, a psutil thread samples the RSS every 2 ms
(which can miss short spikes), and without psutil the `resource.getrusage` high-water delta is used (which
reads 0 when the process had already been larger before the call). The reset is process-wide, so probes do
not nest and a second thread allocating meanwhile is counted too (the runner runs one method per process).

Timings are wall-clock seconds of `_run`'s stages plus "total"; the method's optional imports happen in
`prepare()` before the clock starts, so the first run in a fresh process is not charged for them.
"""
from __future__ import annotations

import abc
import contextlib
import dataclasses
import logging
import resource
import sys
import threading
import time
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: Fewest input points any method accepts.
MIN_POINTS = 10


@dataclasses.dataclass
class Inputs:
    """What a method reconstructs from, in the GT's normalisation frame.

    Attributes:
        points: (N, 3) float32 surface samples, or None for multi-view input.
        normals: (N, 3) float32 unit normals of `points` (oriented outwards for closed surfaces), or None.
        views: a `datasets.capture.MultiView` (diffuse, depth, mask (V, H, W), cameras), or None.
        seed: seed for any randomness inside the method.
        monitor: optional harness hook, `monitor(mesh) -> dict` of figures (e.g. {"cd_p2s": ...} against the
            GT), for curves of an iterative method's intermediate meshes. The method never sees the GT itself;
            seconds spent in it go to the "monitor" stage and are not charged to "total".
        checkpoint: optional file where a long, iterative method keeps its resumable state (the DMesh
            procedures' `state_path`). The harness gives each run its own (`eval.runner.checkpoint_path`) and
            removes it once the run's outcome is stored, so only a run whose process died (a killed sweep, a
            stopped machine) finds one, and resumes it. A method that resumed puts the wall seconds of its
            earlier attempts in the "earlier_attempts" stage; "total" includes them.
        preprocess: what the harness's pre-processing stage did to `points` before the method got them
            (`eval.preprocess.apply`'s info: "spec", "outliers_removed", "smoothed", ...), or None when it did
            nothing. The same points and record reach every method of a sweep; a method may adapt its own
            settings to it (DMesh caps its seeds on smoothed input), never filter again by itself.
    """

    points: np.ndarray | None = None
    normals: np.ndarray | None = None
    views: Any = None
    seed: int = 0
    monitor: Any = None
    checkpoint: str | None = None
    preprocess: dict | None = None


@dataclasses.dataclass
class Result:
    """A method's output.

    Attributes:
        mesh: the reconstructed `trimesh.Trimesh` (in the inputs' frame); may be empty if the method found
            no surface.
        timings: seconds of wall time per stage, plus "total" for the whole call.
        peak_memory_mb: extra resident memory at the call's high-water mark, in MiB (see module docstring).
        info: method-specific figures (parameters chosen automatically, counts, the memory probe used).
    """

    mesh: Any
    timings: dict[str, float]
    peak_memory_mb: float
    info: dict = dataclasses.field(default_factory=dict)


class Stopwatch:
    """Collects wall time per named stage: `with sw.stage("grid"): ...`; repeated names accumulate."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            dt = time.perf_counter() - t0
            self.timings[name] = self.timings.get(name, 0.0) + dt
            log.debug("stage %s: %.3f s", name, dt)


def _proc_status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


class MemoryProbe:
    """Peak extra resident memory of a block of code: `with MemoryProbe() as m: ...; m.peak_mb`.

    `m.method` names the probe used: "vmhwm" (exact kernel high-water mark), "psutil-sampling" (2 ms RSS
    sampling) or "getrusage" (process-lifetime high-water delta; 0 if the process was larger before).
    """

    def __init__(self, interval: float = 0.002) -> None:
        self.interval = interval
        self.peak_mb = 0.0
        self.method = ""
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def __enter__(self) -> "MemoryProbe":
        self._start_rss = _proc_status_kib("VmRSS")
        if self._start_rss is not None and sys.platform.startswith("linux"):
            try:
                with open("/proc/self/clear_refs", "w") as fh:
                    fh.write("5")
                self.method = "vmhwm"
                return self
            except OSError:
                pass
        try:
            import psutil
        except ImportError:
            self.method = "getrusage"
            self._start_ru = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
            return self
        self.method = "psutil-sampling"
        proc = psutil.Process()
        self._start_bytes = proc.memory_info().rss
        self._max_bytes = self._start_bytes

        def sample():
            while not self._stop.is_set():
                self._max_bytes = max(self._max_bytes, proc.memory_info().rss)
                self._stop.wait(self.interval)

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.method == "vmhwm":
            hwm = _proc_status_kib("VmHWM") or 0
            self.peak_mb = max(0.0, (hwm - self._start_rss) / 1024.0)
        elif self.method == "psutil-sampling":
            self._stop.set()
            assert self._thread is not None
            self._thread.join()
            self.peak_mb = max(0.0, (self._max_bytes - self._start_bytes) / 2**20)
        else:
            now = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            self.peak_mb = max(0.0, (now - self._start_ru) / 1024.0)


def check_points(inputs: Inputs, need_normals: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Validated copies of the inputs' points and normals.

    Args:
        inputs: must hold `points` (N, 3) with N >= MIN_POINTS, finite; `normals` (N, 3) finite and non-zero
            when `need_normals` (normals are renormalised to unit length).
        need_normals: raise if normals are missing.

    Returns:
        points: (N, 3) float64. normals: (N, 3) float64 unit vectors, or None when absent.

    Raises:
        ValueError: naming the problem (missing, wrong shape, too few, NaN/inf, zero normals).
    """
    if inputs.points is None:
        raise ValueError("this method needs a point cloud (inputs.points is None)")
    pts = np.asarray(inputs.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if len(pts) < MIN_POINTS:
        raise ValueError(f"need at least {MIN_POINTS} points, got {len(pts)}")
    if not np.isfinite(pts).all():
        raise ValueError(f"points contain NaN or inf ({int((~np.isfinite(pts)).any(axis=1).sum())} rows)")
    nrm = None
    if inputs.normals is not None:
        nrm = np.asarray(inputs.normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals must have the points' shape {pts.shape}, got {nrm.shape}")
        if not np.isfinite(nrm).all():
            raise ValueError("normals contain NaN or inf")
        length = np.linalg.norm(nrm, axis=1)
        if (length < 1e-12).any():
            raise ValueError(f"{int((length < 1e-12).sum())} normals have zero length")
        nrm = nrm / length[:, None]
    elif need_normals:
        raise ValueError("this method needs oriented normals (inputs.normals is None)")
    return pts, nrm


def mean_spacing(points: np.ndarray) -> float:
    """Mean distance from each point of `points` (N, 3) to its nearest other point, in the points' units."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=2, workers=-1)
    return float(d[:, 1].mean())


class Method(abc.ABC):
    """A reconstruction method. Subclasses set `name`, `input_kind` and implement `default_config` and `_run`.

    `reconstruct` merges the config over the defaults (unknown keys raise ValueError), times and measures
    `_run`, and packs a `Result`. Instances are stateless, so one instance serves every run.
    """

    name: str = ""
    input_kind: str = "pointcloud"  # "pointcloud" or "multiview"

    @abc.abstractmethod
    def default_config(self) -> dict:
        """A fresh dict of this method's parameters and their defaults."""

    @abc.abstractmethod
    def _run(self, inputs: Inputs, config: dict, sw: Stopwatch) -> tuple[Any, dict]:
        """Reconstruct; returns (trimesh.Trimesh, info dict). Time stages with `sw.stage(name)`."""

    def prepare(self) -> None:
        """Import the method's optional dependencies (called before timing starts, so a first run in a fresh
        process is not charged seconds of imports); raise ImportError naming the extra if one is missing."""

    def resolve_config(self, config) -> dict:
        """The defaults updated with `config`; raises ValueError on keys the method does not know.

        A method whose `default_config` returns a frozen dataclass (DMesh) gets a dataclass back: `config` may
        then be an instance of it (used as is) or a mapping of overrides, optionally with a `"preset"` key
        naming the preset they apply to (the class's `from_preset`, `dmesh.recon.config.Presets`) instead of
        the default.
        """
        default = self.default_config()
        if dataclasses.is_dataclass(default):
            if config is None:
                return default
            if dataclasses.is_dataclass(config):
                return config
            overrides = dict(config)
            if "preset" in overrides and hasattr(type(default), "from_preset"):
                return type(default).from_preset(overrides.pop("preset"), overrides, owner=self.name)
            known = {f.name for f in dataclasses.fields(default)}
            return dataclasses.replace(default, **_known(self.name, overrides, known))
        default = dict(default or {})
        default.update(_known(self.name, config or {}, set(default)))
        return default

    def reconstruct(self, inputs: Inputs, config=None) -> Result:
        """Run the method on `inputs` with `config` (a dict of overrides; None: defaults) and return a `Result`.

        Raises:
            ValueError: missing or bad inputs, unknown config keys.
            ImportError: the method's optional dependency is missing (the message names the extra).
        """
        if not isinstance(inputs, Inputs):
            raise TypeError(f"inputs must be baselines.base.Inputs, got {type(inputs).__name__}")
        cfg = self.resolve_config(config)
        self.prepare()
        sw = Stopwatch()
        t0 = time.perf_counter()
        with MemoryProbe() as mem:
            mesh, info = self._run(inputs, cfg, sw)
        # The harness's monitor (curves against the GT) is not part of the method: its time is left out. A
        # resumed run's earlier attempts are (`Inputs.checkpoint`).
        sw.timings["total"] = (time.perf_counter() - t0 - sw.timings.get("monitor", 0.0)
                               + sw.timings.get("earlier_attempts", 0.0))
        info = dict(info)
        info.setdefault("config", dataclasses.asdict(cfg) if dataclasses.is_dataclass(cfg) else cfg)
        info["memory_probe"] = mem.method
        log.info("%s: %d vertices, %d faces in %.2f s, peak +%.0f MiB", self.name, len(mesh.vertices),
                 len(mesh.faces), sw.timings["total"], mem.peak_mb)
        return Result(mesh=mesh, timings=sw.timings, peak_memory_mb=mem.peak_mb, info=info)


def require(module: str, extra: str = "harness", package: str | None = None):
    """Import `module` lazily; on failure raise ImportError naming the pip package and the project extra."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImportError(f"{module} is not importable ({exc}); install it with "
                          f"`pip install {package or module}` or the project's [{extra}] extra") from exc


def empty_mesh():
    """An empty `trimesh.Trimesh` (0 vertices, 0 faces)."""
    import trimesh

    return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)


def _known(owner: str, config, known: set) -> dict:
    """`config` as a dict; ValueError naming the keys that are not in `known` (and the known ones)."""
    unknown = sorted(set(config) - known)
    if unknown:
        raise ValueError(f"{owner}: unknown config keys {unknown}; known: {sorted(known)}")
    return dict(config)
