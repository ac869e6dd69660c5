"""Two sweeps sharing one store (issue 15 item 4): runs are claimed with a lease, so each run is computed
once, a `done` row is never downgraded, and runs of a dead or silent holder are taken over.

Computations are counted from a file the fake method appends to (one line per call: seed and the sweep's
pid), never from timings. The fake method (the convex hull of the input points after a delay) is registered
by the tests only, in this process or in the sweep subprocesses.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from eval.store import Lease, Store, lease_live, pid_alive

REPO = Path(__file__).resolve().parents[1]
#: Tiny inputs: the fake method and the metrics need few samples.
TINY = {"n_points": 400, "metric_samples": 400}

FAKE_SRC = '''
import os, time
import numpy as np
from baselines.base import Method


class FakeHull(Method):
    """Test-only fake: appends "<seed> <sweep pid>" to `counter`, waits `delay` s, returns the convex hull."""

    name = "fake_hull"
    input_kind = "pointcloud"
    # Run keys hash the method's source trees; this fake has none in the checkout, so two sweeps started a
    # moment apart agree on the keys even while someone edits the sources.
    code_trees = ("tests/no-such-tree",)

    def default_config(self):
        return {"delay": 0.0, "counter": ""}

    def _run(self, inputs, cfg, sw):
        import trimesh

        if cfg["counter"]:
            with open(cfg["counter"], "a") as fh:  # the worker is a child of the sweep process
                fh.write(f"{inputs.seed} {os.getppid()}\\n")
        time.sleep(float(cfg["delay"]))
        with sw.stage("hull"):
            mesh = trimesh.convex.convex_hull(np.asarray(inputs.points, np.float64))
        return mesh, {"steps": 1}
'''

#: A sweep process: registers the fake, signals it is ready, waits for its go file, runs the sweep and
#: prints its summary as JSON. argv: work, ready file, go file, seeds (JSON), delay, counter.
SWEEP_SCRIPT = FAKE_SRC + textwrap.dedent(f'''
    import dataclasses, json, sys
    from pathlib import Path
    from baselines import registry
    from eval.runner import RunnerConfig, run_sweep
    from eval.sweep import Sweep

    registry.METHODS["fake_hull"] = FakeHull()
    work, ready, go, seeds, delay, counter = sys.argv[1:7]
    Path(ready).touch()
    while not Path(go).exists():
        time.sleep(0.02)
    sweep = Sweep(methods=("fake_hull",), shapes=("sphere",), seeds=tuple(json.loads(seeds)),
                  configs={{"fake_hull": [{{"delay": float(delay), "counter": counter}}]}}, **{TINY!r})
    summary = run_sweep(sweep, RunnerConfig(work=work))
    print(json.dumps({{"pid": os.getpid(), **dataclasses.asdict(summary)}}))
''')

#: A store client in another process. argv: db, mode, row (JSON). Modes: "claim" prints the claim's
#: outcome; "claim-and-die" claims and exits at once without releasing (like a killed sweep).
CLIENT_SCRIPT = textwrap.dedent('''
    import json, os, sys
    from eval.store import Lease, Store

    db, mode, row = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
    store = Store(db)
    outcome = store.claim(row, Lease.new())
    print(outcome, flush=True)
    if mode == "claim-and-die":
        os._exit(0)
''')


def _row(key: str, seed: int = 0) -> dict:
    return {"key": key, "method": "psr", "config_label": "", "shape": "torus", "category": "closed",
            "input_kind": "pointcloud", "config_json": {"depth": 6}, "inputs_json": {"n_points": 100},
            "seed": seed, "gt_hash": "ab" * 32, "code_version": "test"}


def _client(tmp_path: Path, db: Path, mode: str, row: dict) -> str:
    script = tmp_path / "client.py"
    script.write_text(CLIENT_SCRIPT)
    r = subprocess.run([sys.executable, str(script), str(db), mode, json.dumps(row)], cwd=REPO,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.strip()


def _other_host(token: str = "other") -> Lease:
    return Lease(pid=12345, host=socket.gethostname() + "-elsewhere", token=token)


# --------------------------------------------------------------------------------------------------- store


def _sweep_beside(other, sweep, runner):
    """Runs `sweep` while `other` (another sweep's moves on the store) runs in a thread; its summary."""
    from eval.runner import run_sweep

    t = threading.Thread(target=other)
    t.start()
    try:
        return run_sweep(sweep, runner)
    finally:
        t.join()


def test_done_row_stays_done_whatever_tries_to_claim_it(tmp_path):
    db = tmp_path / "results.sqlite"
    mine = Lease.new()
    with Store(db) as s:
        assert s.claim(_row("k"), mine) == "claimed"
        assert s.finish("k", status="done", metrics={"cd_p2s": 1e-3}, timings={"total": 1.0}, mesh_path="m.ply",
                        lease=mine)
        before = s.get("k")
    # Another process tries to claim it.
    assert _client(tmp_path, db, "claim", _row("k")) == "done"
    with Store(db) as s:
        assert s.claim(_row("k"), Lease.new()) == "done"
        assert s.mark_running(_row("k")) == "done"
        assert s.upsert({**_row("k"), "status": "running"}) is False
        assert s.upsert({**_row("k"), "status": "failed", "error": "late"}) is False
        assert s.finish("k", status="failed", error="late") is False
        assert s.finish("k", status="done", metrics={"cd_p2s": 9.0}, timings={"total": 1.0}, lease=mine) is False
        assert s.get("k") == before
        with pytest.raises(ValueError, match="no run with key"):
            s.finish("missing", status="done")



def test_a_done_row_is_claimed_again_only_by_a_rerun_that_saw_its_attempts(tmp_path):
    """A sweep that reruns stored runs passes the `attempts` it saw: the row is claimed once; a second sweep
    that saw the same count finds it running (or done again), not claimable."""
    db = tmp_path / "results.sqlite"
    mine = Lease.new()
    with Store(db) as s:
        s.claim(_row("k"), mine)
        s.finish("k", status="done", metrics={"cd_p2s": 1e-3}, timings={"total": 1.0}, lease=mine)
        seen = s.get("k")["attempts"]
        first, second = Lease(pid=os.getppid(), host=socket.gethostname(), token="first"), Lease.new()
        assert s.claim(_row("k"), first, retry_attempts=seen + 1) == "done"
        assert s.claim(_row("k"), first, retry_attempts=seen) == "claimed"
        assert s.get("k")["status"] == "running" and s.get("k")["metrics_json"] is None
        assert s.claim(_row("k"), second, retry_attempts=seen) == "held"
        assert s.finish("k", status="done", metrics={"cd_p2s": 2e-3}, timings={"total": 1.0}, lease=first)
        assert s.claim(_row("k"), second, retry_attempts=seen) == "done"
        assert s.get("k")["metrics_json"] == {"cd_p2s": 2e-3} and s.get("k")["attempts"] == seen + 1

def test_a_live_lease_keeps_others_out_until_it_finishes(tmp_path):
    holder, other = Lease(pid=os.getppid(), host=socket.gethostname(), token="holder"), Lease.new()
    with Store(tmp_path / "s.sqlite") as s:
        assert s.claim(_row("k"), holder) == "claimed"  # a live process on this host
        assert s.claim(_row("k"), other) == "held"
        assert s.heartbeat(holder) == 1 and s.heartbeat(other) == 0
        assert s.finish("k", status="done", metrics={}, timings={"total": 1.0}, lease=other) is False
        assert s.finish("k", status="failed", error="E: x", lease=holder)
        assert s.claim(_row("k"), other) == "failed"  # a failure is a result, unless a retry is asked
        assert s.get("k")["attempts"] == 1
        assert s.claim(_row("k"), other, retry_attempts=1) == "claimed"
        s.finish("k", status="failed", error="E: again", lease=other)
        # Another sweep that also decided to retry it (it saw attempts=1) does not retry it a second time.
        assert s.claim(_row("k"), holder, retry_attempts=1) == "failed"
        # Another host: only the heartbeat tells.
        far = _other_host()
        assert s.claim(_row("j"), far) == "claimed" and s.claim(_row("j"), other) == "held"


def test_a_dead_holder_is_taken_over(tmp_path):
    """A process that claimed a run and died (exited without finishing or releasing) loses it at once."""
    db = tmp_path / "results.sqlite"
    Store(db).close()
    assert _client(tmp_path, db, "claim-and-die", _row("k")) == "claimed"
    mine = Lease.new()
    with Store(db) as s:
        row = s.get("k")
        assert row["status"] == "running" and row["lease_host"] == socket.gethostname()
        assert not pid_alive(row["lease_pid"])
        assert s.claim(_row("k"), mine) == "resumed"
        assert s.get("k")["lease_token"] == mine.token and s.get("k")["attempts"] == 2
        assert s.finish("k", status="done", metrics={}, timings={"total": 1.0}, lease=mine)


def test_an_expired_or_released_lease_is_taken_over(tmp_path):
    far, mine = _other_host(), Lease.new()
    with Store(tmp_path / "s.sqlite") as s:
        assert s.claim(_row("k"), far) == "claimed"
        assert s.claim(_row("k"), mine, stale_s=60) == "held"
        s._conn.execute("UPDATE runs SET heartbeat_at=? WHERE key='k'", (time.time() - 61,))
        assert s.claim(_row("k"), mine, stale_s=60) == "resumed"
        # The old holder comes back: its heartbeat no longer covers the run, its outcome is not stored.
        assert s.heartbeat(far) == 0
        assert s.finish("k", status="done", metrics={}, timings={"total": 1.0}, lease=far) is False
        assert s.get("k")["status"] == "running" and s.get("k")["lease_token"] == mine.token
        # A released lease is free at once.
        assert s.claim(_row("j"), far) == "claimed" and s.release(far) == 1
        assert s.claim(_row("j"), mine) == "resumed"
        # An older store's running row has no lease at all: it was interrupted.
        s._conn.execute("UPDATE runs SET lease_token=NULL, heartbeat_at=NULL WHERE key='j'")
        assert s.claim(_row("j"), far) == "resumed"


def test_pid_alive_sees_through_zombies():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    deadline = time.monotonic() + 20
    while pid_alive(proc.pid) and time.monotonic() < deadline:  # exits, stays a zombie until reaped
        time.sleep(0.02)
    assert not pid_alive(proc.pid)
    proc.wait()
    assert not pid_alive(proc.pid) and pid_alive(os.getpid()) and not pid_alive(None)
    row = {"lease_token": "t", "heartbeat_at": time.time(), "lease_host": socket.gethostname(), "lease_pid": proc.pid}
    assert not lease_live(row, Lease.new(), 60.0)


def _claim_all(db: str, keys: list[str], queue) -> None:
    with Store(db) as s:
        lease = Lease.new()
        queue.put([k for k in keys if s.claim(_row(k), lease) == "claimed"])


def test_concurrent_claims_are_exclusive(tmp_path):
    """Four processes claim the same 40 runs at once: each run goes to exactly one of them."""
    db = str(tmp_path / "results.sqlite")
    Store(db).close()
    keys = [f"k{i:02d}" for i in range(40)]
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_claim_all, args=(db, keys, queue)) for _ in range(4)]
    for p in procs:
        p.start()
    got = [queue.get(timeout=60) for _ in procs]
    for p in procs:
        p.join(timeout=30)
    assert sorted(k for g in got for k in g) == keys


# --------------------------------------------------------------------------------------------------- sweeps

@pytest.fixture
def fake(monkeypatch):
    registry = pytest.importorskip("baselines.registry")
    pytest.importorskip("eval.metrics")
    ns: dict = {}
    exec(compile(FAKE_SRC, "<fake_hull>", "exec"), ns)
    monkeypatch.setitem(registry.METHODS, "fake_hull", ns["FakeHull"]())
    return registry.METHODS


def _sweep(seeds, counter, delay=0.0):
    from eval.sweep import Sweep

    return Sweep(methods=("fake_hull",), shapes=("sphere",), seeds=tuple(seeds),
                 configs={"fake_hull": [{"delay": delay, "counter": str(counter)}]}, **TINY)


def _specs(sweep, work):
    from eval.runner import resolve_and_prepare_shapes
    from eval.sweep import expand

    shapes, _ = resolve_and_prepare_shapes(sweep, work)
    return {s.seed: s for s in expand(sweep, shapes)}


def _calls(counter: Path) -> list[tuple[int, int]]:
    if not counter.is_file():
        return []
    return [tuple(int(x) for x in line.split()) for line in counter.read_text().split("\n") if line.strip()]


def test_sweep_waits_for_a_run_held_elsewhere_and_takes_over_a_silent_one(fake, tmp_path):
    """In one process: seed 1 is held by a live sweep on another host, which stores it 1.5 s later; seed 2
    by a sweep whose heartbeat stopped long ago. The sweep computes seeds 0 and 2 and waits for seed 1."""
    from eval.runner import RunnerConfig

    work, counter = tmp_path / "work", tmp_path / "calls.txt"
    sweep = _sweep((0, 1, 2), counter)
    runner = RunnerConfig(work=str(work), lease_s=30.0)
    specs = _specs(sweep, work)
    busy, silent = _other_host("busy"), _other_host("silent")
    with Store(runner.db_path) as s:
        assert s.claim(specs[1].identity(), busy) == "claimed"
        assert s.claim(specs[2].identity(), silent) == "claimed"
        s._conn.execute("UPDATE runs SET heartbeat_at=? WHERE key=?", (time.time() - 31, specs[2].key))

    def other_sweep():
        with Store(runner.db_path) as s:
            for _ in range(6):  # keeps its lease fresh, then stores its outcome
                time.sleep(0.25)
                s.heartbeat(busy)
            s.finish(specs[1].key, status="done", metrics={"cd_p2s": 0.0}, timings={"total": 1.5}, lease=busy)

    summary = _sweep_beside(other_sweep, sweep, runner)
    assert (summary.done, summary.failed, summary.skipped, summary.elsewhere) == (2, 0, 0, 1)
    assert "1 finished by another sweep sharing the store" in summary.line()
    assert sorted(seed for seed, _ in _calls(counter)) == [0, 2]
    with Store(runner.db_path) as s:
        rows = {r["seed"]: r for r in s.rows()}
    assert {k: r["status"] for k, r in rows.items()} == {0: "done", 1: "done", 2: "done"}
    assert rows[1]["lease_token"] == "busy" and rows[1]["timings_json"] == {"total": 1.5}
    assert rows[2]["attempts"] == 2 and rows[2]["lease_pid"] == os.getpid()
    assert rows[2]["heartbeat_at"] is None  # finished runs hold no lease


def _start_sweeps(tmp_path, n, seeds, delay, counter, work):
    script = tmp_path / "sweep.py"
    script.write_text(SWEEP_SCRIPT)
    procs = []
    for i in range(n):
        procs.append(subprocess.Popen(
            [sys.executable, str(script), str(work), str(tmp_path / f"ready{i}"), str(tmp_path / f"go{i}"),
             json.dumps(list(seeds)), str(delay), str(counter)],
            cwd=REPO, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    deadline = time.monotonic() + 60
    while not all((tmp_path / f"ready{i}").exists() for i in range(n)):
        assert time.monotonic() < deadline and all(p.poll() is None for p in procs), \
            [p.communicate()[1][-2000:] for p in procs if p.poll() is not None]
        time.sleep(0.02)
    return procs


def _finish(proc) -> dict:
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def _kill(proc) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate()


def test_two_concurrent_sweeps_compute_each_run_once(tmp_path):
    pytest.importorskip("baselines.registry")
    work, counter, seeds = tmp_path / "work", tmp_path / "calls.txt", (0, 1, 2)
    procs = _start_sweeps(tmp_path, 2, seeds, 0.5, counter, work)
    try:
        for i in range(2):  # both start their sweeps at the same moment
            (tmp_path / f"go{i}").touch()
        summaries = [_finish(p) for p in procs]
    finally:
        for p in procs:
            _kill(p)
    calls = _calls(counter)
    assert sorted(seed for seed, _ in calls) == list(seeds), calls  # each run computed exactly once
    assert {pid for _, pid in calls} <= {s["pid"] for s in summaries}
    for s in summaries:  # every run of each sweep is accounted for, and nothing was recomputed
        assert s["failed"] == 0 and s["done"] + s["skipped"] + s["elsewhere"] == len(seeds), s
        assert s["done"] == sum(1 for _, pid in calls if pid == s["pid"])
    assert sum(s["done"] for s in summaries) == len(seeds)
    with Store(work / "results.sqlite") as store:
        assert [r["status"] for r in store.rows()] == ["done"] * len(seeds)
        assert store.counts() == {"done": len(seeds)}


def test_a_killed_sweep_leaves_the_other_to_finish(tmp_path):
    """Sweep A starts, B joins once A holds a run; A is SIGKILLed while it computes one. B takes A's
    interrupted run over, waits for nothing more, and the store ends with every run done; runs finished
    before the kill are not recomputed."""
    pytest.importorskip("baselines.registry")
    work, counter, seeds = tmp_path / "work", tmp_path / "calls.txt", (0, 1, 2, 3)
    db = work / "results.sqlite"
    a, b = procs = _start_sweeps(tmp_path, 2, seeds, 1.0, counter, work)

    def wait_for(pred, what):
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            assert all(p.poll() is None for p in procs), f"a sweep ended early while waiting for {what}"
            if db.is_file():
                with Store(db) as s:
                    rows = s.rows()
                if pred(rows):
                    return rows
            time.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}")

    def running_under(pid, within=None):
        # within: claimed less than this many seconds ago (the heartbeat is the claim time for the first
        # lease_s / 6 = 10 s), so the run is surely still in progress when the test acts on it.
        return lambda rows: any(r["status"] == "running" and r["lease_pid"] == pid and
                                (within is None or time.time() - r["heartbeat_at"] < within) for r in rows)

    try:
        (tmp_path / "go0").touch()
        wait_for(running_under(a.pid), "sweep A to hold a run")
        (tmp_path / "go1").touch()
        wait_for(running_under(b.pid), "sweep B to hold a run")
        wait_for(running_under(a.pid, within=0.4), "sweep A to claim a run afresh")
        os.killpg(a.pid, signal.SIGKILL)
        a.communicate()
        with Store(db) as s:
            rows = s.rows()
        held_by_a = {r["seed"] for r in rows if r["status"] == "running" and r["lease_pid"] == a.pid}
        done_before = {r["seed"] for r in rows if r["status"] == "done"}
        assert held_by_a
        summary = _finish(b)
    finally:
        for p in procs:
            _kill(p)
    with Store(db) as s:
        rows = s.rows()
    assert [r["status"] for r in rows] == ["done"] * len(seeds)
    assert all(r["lease_pid"] == b.pid for r in rows if r["seed"] in held_by_a)  # taken over by B
    calls = [seed for seed, _ in _calls(counter)]
    assert sorted(set(calls)) == list(seeds)
    for seed in done_before:
        assert calls.count(seed) == 1, calls
    assert summary["failed"] == 0 and summary["done"] + summary["skipped"] + summary["elsewhere"] == len(seeds)


def test_ray_executor_path_claims_runs_too(fake, tmp_path):
    """The Ray executor (a real local Ray) goes through the same claims: a run held elsewhere is waited for."""
    import ray

    from eval.runner import RunnerConfig

    work, counter = tmp_path / "work", tmp_path / "calls.txt"
    sweep = _sweep((0, 1), counter)
    runner = RunnerConfig(work=str(work), executor="ray", jobs=2)
    specs = _specs(sweep, work)
    with Store(runner.db_path) as s:  # seed 1 is held by a live sweep on another host, which stores it soon
        s.claim(specs[1].identity(), _other_host("busy"))

    def other_sweep():
        deadline = time.monotonic() + 120
        while not ray.is_initialized() and time.monotonic() < deadline:  # the sweep is past starting Ray
            time.sleep(0.1)
        time.sleep(1.0)
        with Store(runner.db_path) as s:
            s.finish(specs[1].key, status="done", metrics={}, timings={"total": 1.0}, lease=_other_host("busy"))

    try:
        summary = _sweep_beside(other_sweep, sweep, runner)
    finally:
        ray.shutdown()
    assert (summary.done, summary.failed, summary.skipped, summary.elsewhere) == (1, 0, 0, 1)
    assert [seed for seed, _ in _calls(counter)] == [0]
    with Store(runner.db_path) as s:
        assert s.counts() == {"done": 2}


def test_a_metric_named_like_a_run_column_does_not_replace_it(tmp_path):
    """The metrics hold their own sampling "seed"; the report frame keeps the run's seed (a rerun at seed 2 is
    not taken for another run of seed 0) and the metric's as metric_seed."""
    db = tmp_path / "results.sqlite"
    lease = Lease.new()
    with Store(db) as s:
        for key, seed in (("a", 0), ("b", 2)):
            assert s.claim({**_row(key), "seed": seed}, lease) == "claimed"
            s.finish(key, status="done", metrics={"cd_p2s": 1e-3, "seed": 0}, timings={"total": 1.0}, lease=lease)
        df = s.dataframe()
    assert sorted(df["seed"].astype(int)) == [0, 2] and list(df["metric_seed"]) == [0, 0]
