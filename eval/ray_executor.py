"""The Ray executor of `eval.runner`: a sweep's runs as Ray tasks, on a local Ray or on an existing cluster
(the local executor: `eval.local_executor`).

Where Ray runs (`connect`): `--ray-address` (host:port of a head started with `ray start --head`, or `auto`;
Ray's other address forms are passed on as they are), else `$RAY_ADDRESS`, else a local Ray of `--jobs` CPUs
started for the sweep. An existing cluster is joined as it is (its own CPU count, no `num_cpus`). An address
where nothing listens is one `ValueError` line after at most `CONNECT_TIMEOUT_S` seconds, one where something
other than a Ray head listens after about a minute (`_CONNECT_ENV`); both before anything is prepared.

Nothing assumes a disk shared between the driver (the process running the sweep) and the workers:

- the driver prepares every GT and input in its work folder, exactly as for the local executor, and puts
  the bytes of each into the Ray object store once (`_Payloads`);
- a task writes them into a scratch folder of its node, laid out like the work folder, runs
  `eval.execute.execute_run` there (the same code as a local run, the GT monitor included) and returns the
  outcome with the output mesh as PLY bytes; the scratch folder is removed;
- the driver writes each mesh file (atomically) and its store row as the result arrives, so a worker or a
  node that dies loses only the run it was computing, which Ray resubmits (`TASK_RETRIES` times).

At most `jobs` tasks are in flight (each asks for `TASK_CPUS` CPUs and runs on that many threads,
`eval.execute.limit_threads`), so `--jobs` bounds the load a sweep puts on a
cluster. A run's timeout counts from its submission (keep `--jobs` at or under the free CPUs, or queueing
counts too) and over Ray's resubmissions; a run past it is cancelled (its worker is killed) and stored as
failed. A method's own exceptions are outcomes (stored failed, then retried only by `--retry-failed`); only
a dead worker process or node makes Ray resubmit a task, so a run that crashes its worker every time is
stored failed after `TASK_RETRIES + 1` tries where the local executor stores it after one.
"""
from __future__ import annotations

import logging
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path
from typing import Callable

from eval.io import atomic_path
from eval.execute import execute_run, limit_threads, mesh_path_for
from eval.inputs import input_path
from eval.plain import one_line
from eval.leases import pid_alive
from eval.sweep import RunSpec, get_method

log = logging.getLogger(__name__)

#: Seconds to wait for a TCP connection to a cluster's address (and for its GCS to answer) before giving up.
CONNECT_TIMEOUT_S = 10.0
#: Times Ray resubmits a task whose worker process or node died.
TASK_RETRIES = 3
#: CPUs a task asks Ray for, and the threads its run computes on (a worker process is reused for many tasks
#: and a node may have more cores than it offers, so the cap is set per task rather than left to Ray's
#: environment defaults).
TASK_CPUS = 1
#: Name prefix of the tasks' scratch folders (in each node's temporary folder).
_SCRATCH_PREFIX = "dmesh-run-"
#: Ray settings for joining a cluster, unless set in the environment: an address where something other than
#: a Ray head listens fails within about a minute instead of retrying forever (seconds per GCS connection
#: attempt, and attempts).
_CONNECT_ENV = {"RAY_py_gcs_connect_timeout_s": str(int(CONNECT_TIMEOUT_S)), "RAY_gcs_server_port_wait_time_s": "2"}


def import_ray():
    """The `ray` module; ValueError (one line) when it is not installed."""
    try:
        import ray
    except ImportError:
        raise ValueError("the ray executor needs Ray, which is not installed: pip install -e .[ray]") from None
    return ray


def resolve_address(address: str | None) -> str | None:
    """The cluster to join: `address`, else `$RAY_ADDRESS`; None (or "local"): start a local Ray."""
    address = address or os.environ.get("RAY_ADDRESS") or None
    return None if address == "local" else address


def connect(address: str | None, jobs: int) -> None:
    """Joins the Ray cluster at `resolve_address(address)`, or starts a local Ray of `jobs` CPUs.

    Does nothing when Ray is already initialised in this process (a second sweep of one command).

    Raises:
        ValueError: Ray is not installed, the address is malformed, or no Ray cluster answers there.
    """
    address = resolve_address(address)
    saved = {k: os.environ.get(k) for k in _CONNECT_ENV}
    if address is not None:  # Ray reads these when it is first imported in this process (and in ray.init)
        for k, v in _CONNECT_ENV.items():
            os.environ.setdefault(k, v)
    try:
        ray = import_ray()
        if ray.is_initialized():
            return
        if address is None:
            # "local": never join a cluster that `ray start` left running on this machine (that would refuse
            # num_cpus); the sweep gets a Ray of its own, gone when this process exits.
            ray.init(address="local", num_cpus=jobs, include_dashboard=False, log_to_driver=False)
            return
        _check_reachable(address)
        try:
            ray.init(address=address, log_to_driver=False)
        except Exception as exc:  # noqa: BLE001 - refused, timed out, version mismatch: one line naming it
            raise ValueError(f"Ray cluster at {address}: cannot connect ({one_line(exc)})") from None
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    cpus = ray.cluster_resources().get("CPU", 0)
    log.info("joined the Ray cluster at %s: %d node(s), %g CPUs; at most %d runs in flight", address,
             len([n for n in ray.nodes() if n.get("Alive")]), cpus, jobs)
    if cpus < jobs:
        log.warning("--jobs %d is more than the cluster's %g CPUs: queued runs count against their timeout",
                    jobs, cpus)


def _check_reachable(address: str) -> None:
    """ValueError (one line) unless something accepts a TCP connection at the address's host:port."""
    target = address
    if address == "auto":
        try:
            from ray._private.services import canonicalize_bootstrap_address

            target = canonicalize_bootstrap_address("auto")
        except ConnectionError as exc:  # no cluster started on this machine
            raise ValueError(f"Ray address auto: {one_line(exc)}") from None
        except Exception:  # noqa: BLE001 - Ray's private helper changed: let ray.init find the cluster
            return
    host, sep, port = target.split("://", 1)[-1].rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"Ray address {address!r}: expected host:port, auto or ray://host:port")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise ValueError(f"Ray cluster at {address}: cannot be reached ({why}); start a head with "
                         f"`ray start --head` or fix --ray-address / $RAY_ADDRESS") from None


# ------------------------------------------------------------------------------------------ inputs and task

def _files(root: Path, path: Path) -> dict[str, bytes]:
    """{path relative to `root`: bytes} of the file `path`, or of every file under the folder `path`."""
    paths = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    return {os.path.relpath(p, root): p.read_bytes() for p in paths}


class _Payloads:
    """Object-store copies of a sweep's GTs and inputs, each put once and shared by the runs that read it.

    A GT travels as the files `eval.inputs.load_gt` reads (gt.ply and meta.json beside it), an input as its
    cache file or folder (`eval.inputs.input_path`), both keyed by their paths relative to the work folder.
    """

    def __init__(self, ray, work: str | Path):
        self.ray, self.work, self.refs = ray, Path(work), {}

    def _put(self, path: Path, extra: tuple[Path, ...] = ()):
        rel = os.path.relpath(path, self.work)
        if rel not in self.refs:
            files = _files(self.work, path)
            for p in extra:
                if p.is_file():
                    files.update(_files(self.work, p))
            self.refs[rel] = self.ray.put(files)
        return self.refs[rel]

    def args(self, spec: RunSpec, gt_path: Path) -> tuple:
        """(GT path relative to the work folder, GT files ref, input files ref) of a run."""
        gt = self._put(Path(gt_path), (Path(gt_path).parent / "meta.json",))
        path = input_path(self.work, spec.shape, spec.input_kind, dict(spec.inputs), spec.seed)
        inputs = gt if path == Path(gt_path) else self._put(path)
        return os.path.relpath(gt_path, self.work), gt, inputs


def _scratch() -> Path:
    """A new scratch folder `dmesh-run-<pid>-*` in this node's temporary folder, made after removing those of
    worker processes that are gone (a killed worker, e.g. a run past its timeout, cannot clean up)."""
    root = Path(tempfile.gettempdir())
    for old in root.glob(f"{_SCRATCH_PREFIX}*-*"):
        pid = old.name[len(_SCRATCH_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not pid_alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return Path(tempfile.mkdtemp(prefix=f"{_SCRATCH_PREFIX}{os.getpid()}-", dir=root))


def _task(spec: RunSpec, gt_rel: str, gt_files: dict, input_files: dict, method) -> dict:
    """One run as a Ray task: `execute_run` in a scratch folder of this node filled from the object store.

    Returns its outcome with the output mesh as PLY bytes ("mesh_ply") in place of "mesh_path".
    """
    scratch = _scratch()
    try:
        limit_threads(TASK_CPUS)
        for rel, data in {**gt_files, **input_files}.items():
            target = scratch / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        outcome = execute_run(spec, scratch / gt_rel, scratch, method)
        if outcome["status"] == "done":
            outcome["mesh_ply"] = Path(outcome.pop("mesh_path")).read_bytes()
        return outcome
    except OSError as exc:  # the node's scratch disk (full, unwritable): the run failed here
        return {"status": "failed", "error": f"worker scratch folder: {one_line(exc)}"}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _land(work: str, spec: RunSpec, outcome: dict) -> dict:
    """Writes a finished run's mesh bytes to its place in the work folder (atomically); the local outcome."""
    if outcome.get("status") != "done":
        return outcome
    out = mesh_path_for(work, spec.key)
    try:
        with atomic_path(out) as tmp:
            tmp.write_bytes(outcome.pop("mesh_ply"))
    except OSError as exc:
        return {"status": "failed", "error": f"could not write the output mesh: {one_line(exc)}"}
    return {**outcome, "mesh_path": str(out)}


# --------------------------------------------------------------------------------------------- the loop

def run_ray(claims, work: str, jobs: int, timeout_s: float, on_done: Callable) -> None:
    """Runs the runs `claims` hands out as Ray tasks, at most `jobs` at a time; `on_done(spec, outcome)`
    (which stores the outcome) is called in this process as each one finishes. See the module docstring."""
    ray = import_ray()
    if not ray.is_initialized():
        connect(None, jobs)
    # The function is sent by reference (module and name): every node needs this project installed.
    remote = ray.remote(num_cpus=TASK_CPUS, max_retries=TASK_RETRIES, retry_exceptions=False)(_task)
    payloads = _Payloads(ray, work)
    active: dict = {}  # ObjectRef -> (spec, deadline)
    while True:
        while len(active) < jobs and (item := claims.next()) is not None:
            spec, gt_path = item
            try:
                args = payloads.args(spec, gt_path)
            except OSError as exc:  # a cache file vanished or cannot be read on the driver
                on_done(spec, {"status": "failed", "error": f"input could not be read: {one_line(exc)}"})
                continue
            # The method object itself: a fresh worker knows only the methods registered at import time.
            ref = remote.remote(spec, *args, get_method(spec.method))
            active[ref] = (spec, time.monotonic() + timeout_s)
        if not active:
            if claims.finished:
                return
            claims.wait()
            continue
        ready, _ = ray.wait(list(active), num_returns=1, timeout=1.0)
        claims.beat()
        for ref in list(active):
            spec, deadline = active[ref]
            outcome = None
            if ref in ready:
                try:
                    outcome = _land(work, spec, ray.get(ref))
                except Exception as exc:  # noqa: BLE001 - a worker that died TASK_RETRIES + 1 times: failed run
                    outcome = {"status": "failed", "error": one_line(exc)}
            elif time.monotonic() > deadline:
                ray.cancel(ref, force=True)
                outcome = {"status": "failed", "error": f"Timeout: the run took more than {timeout_s:g} s"}
            if outcome is not None:
                del active[ref]
                on_done(spec, outcome)
