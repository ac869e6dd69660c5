"""Sweeps on an existing Ray cluster (`--ray-address`): a real head and a second node on the loopback address.

The cluster is started with `ray start` in sessions of its own and torn down by killing the processes of those
sessions (not `ray stop`, which would also stop any other Ray on this machine). A sweep run through the
cluster, with one of its worker processes killed mid-run, must leave the same store rows and mesh files as a
local sweep.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from eval.runner import resolve_mesh_path
from eval.store import Store

REPO = Path(__file__).resolve().parents[1]
RAY = str(Path(sys.executable).with_name("ray"))
#: Two cheap baselines on two small shapes; psr and sdf_mc on coarse grids take about a second per run.
SWEEP_ARGS = ["--methods", "psr", "sdf_mc", "--shapes", "torus", "bowl", "--set", "n_points=3000",
              "--set", "metric_samples=5000", "--set", "psr.depth=6", "--set", "sdf_mc.resolution=48"]
#: Environment of the cluster's nodes and of the drivers: no usage reports, no inherited address, and no
#: token authentication (a loopback-only cluster; Ray would otherwise turn it on whenever ~/.ray/auth_token
#: exists, and the second node would need the token too).
RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_ADDRESS": "", "RAY_AUTH_MODE": "disabled"}
#: What a run's stored row must share with the same run of a local sweep.
COMPARED = ("method", "config_label", "shape", "category", "input_kind", "config_json", "inputs_json", "seed",
            "status", "error", "metrics_json", "gt_hash", "code_version", "attempts")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _session_processes(sessions: set[int]) -> dict[int, str]:
    """{pid: command line (the process title for Ray workers)} of the live processes in the sessions
    `sessions` (a node's processes stay in the session of its `ray start`; workers get process groups of
    their own)."""
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, IndexError):
            continue
        if fields[0] not in ("Z", "X") and int(fields[3]) in sessions:  # state, ppid, pgrp, session
            out[int(entry.name)] = cmd
    return out


def _stop(sessions: set[int]) -> dict[int, str]:
    """Stops every process of `sessions` (SIGTERM, then SIGKILL); returns those still alive (none, we hope)."""
    for sig, wait_s in ((signal.SIGTERM, 2.0), (signal.SIGKILL, 10.0)):
        for pid in _session_processes(sessions):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait_s
        while _session_processes(sessions) and time.monotonic() < deadline:
            time.sleep(0.1)
    return _session_processes(sessions)


def _ray_start(args: list[str], env: dict, sessions: set[int]) -> None:
    """Runs `ray start ARGS` in a new session, whose id (where the node's processes live) goes into
    `sessions` at once, so that the teardown finds it even when the start fails."""
    proc = subprocess.Popen([RAY, "start", "--disable-usage-stats", "--object-store-memory=100000000",
                             f"--dashboard-agent-listen-port={_free_port()}", *args],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    sessions.add(proc.pid)
    _, err = proc.communicate(timeout=120)
    if proc.returncode != 0:
        raise RuntimeError(f"ray start failed: {err[-2000:]}")


@pytest.fixture(scope="module")
def cluster():
    """A Ray head (1 CPU) and a second node (1 CPU) on 127.0.0.1; yields (address, session ids, scratch root)."""
    # A short temp dir: Ray's Unix sockets live under it and their paths must stay under 108 bytes.
    tmp = tempfile.mkdtemp(prefix="dray", dir="/tmp")
    # The tasks' scratch folders go under the cluster's temp dir, where the tests look for leftovers.
    scratch = Path(tmp) / "scratch"
    scratch.mkdir()
    env = dict(os.environ, **RAY_ENV, TMPDIR=str(scratch))
    port, sessions = _free_port(), set()
    try:
        _ray_start(["--head", f"--port={port}", "--node-ip-address=127.0.0.1", "--num-cpus=1",
                    "--include-dashboard=false", f"--temp-dir={tmp}"], env, sessions)
        address = f"127.0.0.1:{port}"
        _ray_start([f"--address={address}", "--node-ip-address=127.0.0.1", "--num-cpus=1"], env, sessions)
        yield address, sessions, scratch
    finally:
        left = _stop(sessions)
        shutil.rmtree(tmp, ignore_errors=True)
        assert not left, f"Ray processes left behind: {left}"


def _rows(db: Path) -> dict[str, dict]:
    with Store(db) as store:
        return {r["key"]: r for r in store.rows()}


def test_sweep_on_a_cluster_with_a_killed_worker_matches_a_local_sweep(cluster, tmp_path):
    address, sessions, scratch = cluster
    local, remote = tmp_path / "local", tmp_path / "remote"
    # The local reference sweep in a fresh interpreter: the local executor forks, and a fork of this test
    # process (earlier tests started OpenMP thread pools) can deadlock in pymeshlab's OpenMP code.
    ref = subprocess.run([sys.executable, "-m", "eval.cli", "-q", "bench", *SWEEP_ARGS, "--work", str(local),
                          "--jobs", "2"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert ref.returncode == 0, ref.stderr[-2000:]

    env = dict(os.environ, **RAY_ENV)
    driver = subprocess.Popen([sys.executable, "-m", "eval.cli", "-q", "bench", *SWEEP_ARGS, "--work", str(remote),
                               "--executor", "ray", "--ray-address", address, "--jobs", "2"],
                              cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed, stored_before = None, {}
    try:
        deadline = time.monotonic() + 120
        while killed is None and driver.poll() is None and time.monotonic() < deadline:
            db = remote / "results.sqlite"
            done = {k: r for k, r in _rows(db).items() if r["status"] == "done"} if db.is_file() else {}
            busy = [pid for pid, cmd in _session_processes(sessions).items() if cmd.startswith("ray::_task")]
            if done and busy:  # a result is stored and another run is being computed: kill its worker
                os.kill(busy[0], signal.SIGKILL)
                killed, stored_before = busy[0], done
            time.sleep(0.02)
        out, err = driver.communicate(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if driver.poll() is None:
            driver.kill()
            driver.communicate()
    assert killed is not None, f"no worker was caught mid-run: {err[-1000:]}"
    assert driver.returncode == 0, err[-2000:]
    assert "4 runs: 4 done now, 0 failed now" in out, out  # the killed run was resubmitted and finished

    want, got = _rows(local / "results.sqlite"), _rows(remote / "results.sqlite")
    assert sorted(got) == sorted(want) and len(got) == 4
    for key, row in got.items():
        assert {c: row[c] for c in COMPARED} == {c: want[key][c] for c in COMPARED}, key
        assert row["info_json"]["worker_threads"] == 1, key  # a task computes on the one CPU it asked for
        # The driver wrote the mesh that came back from the task: byte for byte the local run's mesh.
        mine = resolve_mesh_path(row, remote / "results.sqlite")
        theirs = resolve_mesh_path(want[key], local / "results.sqlite")
        assert mine.is_relative_to(remote) and mine.read_bytes() == theirs.read_bytes()
    for key, row in stored_before.items():  # results stored before the kill are untouched
        assert got[key]["finished_at"] == row["finished_at"] and got[key]["attempts"] == 1
    # The killed worker's scratch folder was removed by a later task; the others by their own tasks.
    assert not list(scratch.glob("dmesh-run-*"))


def test_timeout_then_retry_failed_on_the_cluster(cluster, tmp_path, monkeypatch):
    """A run past its timeout is cancelled and stored failed; `retry_failed` later computes it (same key)."""
    import ray

    from eval.runner import RunnerConfig, run_sweep
    from eval.sweep import Sweep

    address, _, scratch = cluster
    for k, v in RAY_ENV.items():
        monkeypatch.setenv(k, v)
    sweep = Sweep(methods=("sdf_mc",), shapes=("torus",), n_points=3000, metric_samples=5000,
                  configs={"sdf_mc": ({"resolution": 48},)})
    work = tmp_path / "work"
    try:
        # 0.2 s: less than a fresh worker needs to import the method, so the run is always cut short.
        s = run_sweep(dataclasses.replace(sweep, timeout_s=0.2),
                      RunnerConfig(work=str(work), executor="ray", ray_address=address))
        assert (s.done, s.failed) == (0, 1)
        (row,) = _rows(work / "results.sqlite").values()
        assert row["status"] == "failed" and row["error"].startswith("Timeout: the run took more than 0.2 s")
        s = run_sweep(sweep, RunnerConfig(work=str(work), executor="ray", ray_address=address))
        assert (s.done, s.failed, s.skipped) == (0, 0, 1)  # failed runs stay failed without retry_failed
        s = run_sweep(sweep, RunnerConfig(work=str(work), executor="ray", ray_address=address, retry_failed=True))
        assert (s.done, s.failed, s.skipped) == (1, 0, 0)
    finally:
        ray.shutdown()
    (after,) = _rows(work / "results.sqlite").values()
    assert after["key"] == row["key"] and after["status"] == "done" and after["attempts"] == 2
    assert resolve_mesh_path(after, work / "results.sqlite").is_file()
    assert not list(scratch.glob("dmesh-run-*"))  # the cancelled run's worker was killed; its folder is gone


def test_unreachable_address_is_one_line_error_without_output(tmp_path, monkeypatch, capsys):
    from eval.cli import main
    from eval.runner import RunnerConfig

    port = _free_port()  # nothing listens there
    work = tmp_path / "work"
    start = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "eval.cli", "bench", "--methods", "psr", "--shapes", "disc",
                        "--executor", "ray", "--ray-address", f"127.0.0.1:{port}", "--work", str(work)],
                       cwd=REPO, capture_output=True, text=True, timeout=120, env=dict(os.environ, **RAY_ENV))
    assert time.monotonic() - start < 60
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0 and f"127.0.0.1:{port}: cannot be reached" in r.stderr, r.stderr
    assert not work.exists()

    import ray

    assert not ray.is_initialized()
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")  # the default address comes from $RAY_ADDRESS
    assert main(["bench", "--methods", "psr", "--shapes", "disc", "--executor", "ray", "--work", str(work)]) == 2
    assert "cannot be reached" in capsys.readouterr().err and not work.exists()

    with pytest.raises(ValueError, match="needs the ray executor"):
        RunnerConfig(work=str(work), ray_address="127.0.0.1:1")
