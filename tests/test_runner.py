"""The experiment runner and results store: run keys, done / failed rows, resume after a killed process,
timeouts, worker crashes, and one-line CLI errors for bad inputs.

The methods here are tiny fakes registered into `baselines.registry.METHODS` by the tests only (the convex
hull of the input points, with an optional delay, failure or invocation counter); they are never shipped.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import trimesh

from eval.store import Store
from eval.sweep import Sweep, resolve_shape, run_key, source_hash

REPO = Path(__file__).resolve().parents[1]
#: Small inputs: the fake methods and metrics need few samples.
SMALL = {"n_points": 1500, "metric_samples": 1500, "views": 4, "resolution": 32}

FAKE_METHOD_SRC = '''
import os, time
import numpy as np
from baselines.base import Method


class FakeHull(Method):
    """Test-only fake: the convex hull of the input points, after `delay` seconds; raises if `fail`; returns an
    empty mesh if `empty`;
    appends its seed to the file `counter` on every call; exits the process hard if `crash`. With `save` it
    writes its checkpoint (`inputs.checkpoint`) first, or resumes an existing one (info "resumed", 5 s of
    earlier attempts); with `crash_fresh` it exits hard unless it resumed."""

    name = "fake_hull"
    input_kind = "pointcloud"

    def default_config(self):
        return {"delay": 0.0, "fail": False, "crash": False, "counter": "", "save": False, "crash_fresh": False,
                "empty": False}

    def _run(self, inputs, cfg, sw):
        import trimesh

        if cfg["counter"]:
            with open(cfg["counter"], "a") as fh:
                fh.write(f"{inputs.seed}\\n")
        resumed = False
        if cfg["save"]:
            resumed = os.path.exists(inputs.checkpoint)
            if resumed:
                sw.timings["earlier_attempts"] = 5.0
            else:
                os.makedirs(os.path.dirname(inputs.checkpoint), exist_ok=True)
                with open(inputs.checkpoint, "w") as fh:
                    fh.write("state")
        if cfg["crash_fresh"] and not resumed:
            os._exit(3)
        time.sleep(float(cfg["delay"]))
        if cfg["crash"]:
            os._exit(3)
        if cfg["fail"]:
            raise RuntimeError("fake failure: boom")
        if cfg["empty"]:
            return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), {"steps": 1, "reals_left": 0}
        with sw.stage("hull"):
            mesh = trimesh.convex.convex_hull(np.asarray(inputs.points, np.float64))
        import torch

        return mesh, {"steps": 1, "resumed": resumed, "threads": torch.get_num_threads(),
                      "omp_env": os.environ.get("OMP_NUM_THREADS")}
'''


def _fake_class():
    ns: dict = {}
    exec(compile(FAKE_METHOD_SRC, "<fake_hull>", "exec"), ns)
    return ns["FakeHull"]


@pytest.fixture
def fake(monkeypatch):
    """Registers the fake method (and a failing twin) for the duration of a test."""
    registry = pytest.importorskip("baselines.registry")
    pytest.importorskip("eval.metrics")
    cls = _fake_class()
    fail_cls = type("FakeFail", (cls,), {"name": "fake_fail",
                                         "default_config": lambda self: {**cls.default_config(self), "fail": True}})
    monkeypatch.setitem(registry.METHODS, "fake_hull", cls())
    monkeypatch.setitem(registry.METHODS, "fake_fail", fail_cls())
    return registry.METHODS


def small_sweep(**kw) -> Sweep:
    return Sweep(**{"methods": ("fake_hull",), "shapes": ("sphere",), **SMALL, **kw})


# --------------------------------------------------------------------------------------------------- keys

def test_run_key_is_stable_and_changes_with_every_part():
    base = dict(method="psr", shape_id="torus", gt_hash="ab" * 32, input_kind="pointcloud",
                input_settings={"n_points": 100_000, "radius": 1.0}, config={"depth": 8, "scale": 1.1}, seed=0,
                code_version="0.1.0+src.0123")
    k = run_key(**base)
    assert k == run_key(**base) and len(k) == 64
    # Dict order does not matter; values do.
    assert k == run_key(**{**base, "config": {"scale": 1.1, "depth": 8}})
    for change in ({"config": {"depth": 7, "scale": 1.1}}, {"seed": 1}, {"code_version": "0.1.0+src.4567"},
                   {"gt_hash": "cd" * 32}, {"input_settings": {"n_points": 50_000, "radius": 1.0}},
                   {"method": "bpa"}, {"shape_id": "sphere"}, {"input_kind": "multiview"}):
        assert run_key(**{**base, **change}) != k, change


def test_source_hash_changes_with_the_code(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    h1 = source_hash(("pkg",), tmp_path)
    assert h1 == source_hash(("pkg",), tmp_path)
    from eval import sweep as sweep_mod

    # Comments, docstrings and layout are not code: they leave the hash (and every run's key) as it was.
    (tmp_path / "pkg" / "a.py").write_text('"""A module."""\n# a comment\nx  =  1  # set x\n')
    sweep_mod._source_hash.cache_clear()
    assert source_hash(("pkg",), tmp_path) == h1
    (tmp_path / "pkg" / "a.py").write_text("x = 2\n")
    sweep_mod._source_hash.cache_clear()
    assert source_hash(("pkg",), tmp_path) != h1
    (tmp_path / "pkg" / "b.cpp").write_text("int f() { return 1; }\n")  # other sources: their bytes
    sweep_mod._source_hash.cache_clear()
    h2 = source_hash(("pkg",), tmp_path)
    (tmp_path / "pkg" / "b.cpp").write_text("int f() { return 1; }  // a comment\n")
    sweep_mod._source_hash.cache_clear()
    assert source_hash(("pkg",), tmp_path) != h2


def test_a_runs_code_version_follows_its_own_method_only(tmp_path):
    """Keys hash the method's module and what it imports and the inputs' version (not the input generation's
    code, not the metrics): editing one baseline changes its own code version and no other method's; DMesh
    methods follow the library and native code; an edit of datasets/ changes none, a new INPUT_VERSION all."""
    import shutil

    from eval.code_hash import INPUT_VERSION, METRICS_VERSION, metrics_current
    from eval.sweep import (REPO, _source_hash, code_version, get_method, method_trees, metrics_version,
                            module_closure)

    psr, bpa, dm = get_method("psr"), get_method("bpa"), get_method("dmesh")
    assert "baselines/psr.py" in method_trees(psr) and "baselines/bpa.py" not in method_trees(psr)
    assert not any(t.startswith(("dmesh/", "datasets/")) or t == "native" for t in method_trees(psr))
    assert {"dmesh/recon/pointcloud.py", "dmesh/losses/chamfer.py", "native"} <= set(method_trees(dm))
    assert not any("eval/metrics.py" in method_trees(m) for m in (psr, bpa, dm))  # metrics: metrics_version

    for pkg in ("dmesh", "baselines", "datasets", "eval"):
        shutil.copytree(Path(REPO) / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    before = {m.name: code_version(m, tmp_path) for m in (psr, bpa, dm)}
    with open(tmp_path / "baselines" / "bpa.py", "a") as f:
        f.write("\nEDITED = 1\n")
    _source_hash.cache_clear()
    module_closure.cache_clear()
    after = {m.name: code_version(m, tmp_path) for m in (psr, bpa, dm)}
    assert after["bpa"] != before["bpa"]
    assert after["psr"] == before["psr"] and after["dmesh"] == before["dmesh"]
    with open(tmp_path / "datasets" / "sampling.py", "a") as f:
        f.write("\nEDITED = 1\n")
    _source_hash.cache_clear()
    assert all(code_version(m, tmp_path) == after[m.name] for m in (psr, bpa, dm))  # inputs: INPUT_VERSION
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("eval.code_hash.INPUT_VERSION", INPUT_VERSION + 1)
        assert all(code_version(m, tmp_path) != after[m.name] for m in (psr, bpa, dm))
    # An edit of the metrics reruns no method; what they compute is versioned by METRICS_VERSION
    # (tests/test_metrics_version.py), which a new version changes and nothing else does (`dmesh rescore`).
    versions = {m.name: code_version(m, tmp_path) for m in (psr, bpa, dm)}
    scored = metrics_version()
    with open(tmp_path / "eval" / "metrics.py", "a") as f:
        f.write("\nEDITED = 1\n")
    _source_hash.cache_clear()
    assert {m.name: code_version(m, tmp_path) for m in (psr, bpa, dm)} == versions
    assert metrics_version() == scored
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("eval.code_hash.METRICS_VERSION", METRICS_VERSION + 1)
        assert metrics_version() != scored and not metrics_current(scored)
        assert {m.name: code_version(m, tmp_path) for m in (psr, bpa, dm)} == versions


def test_sweep_yaml_round_trip_and_validation(tmp_path):
    import yaml

    s = Sweep(methods=("psr", "bpa"), shapes=("torus", "sphere@2"), seeds=(0, 1),
              configs={"psr": [{"depth": 7}, {"depth": 8}]})
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(s.to_dict()))
    assert Sweep.from_yaml(path) == s
    s2 = s.with_overrides(["n_points=2000", "psr.trim_quantile=0.1"])
    assert s2.n_points == 2000 and s2.configs["psr"] == ({"depth": 7, "trim_quantile": 0.1},
                                                         {"depth": 8, "trim_quantile": 0.1})
    for bad in ({"methods": ()}, {"inputs": ("photos",)}, {"seeds": ("x",)}, {"n_points": 0}, {"timeout_s": -1}):
        with pytest.raises(ValueError):
            Sweep(**{"methods": ("psr",), "shapes": ("torus",), **bad})
    with pytest.raises(ValueError, match="unknown sweep field"):
        s.with_overrides(["nope=1"])
    with pytest.raises(ValueError, match="unknown shape"):
        resolve_shape("no_such_shape")
    with pytest.raises(ValueError, match="no such mesh file"):
        resolve_shape("closed/missing.obj", tmp_path)


def test_bundled_sweeps_load():
    """Every sweep file loads, and each of its method configs resolves (a config a harness method refuses, such
    as a DMesh private filter, fails here rather than in every run of the sweep)."""
    from eval.sweep import get_method

    for path in sorted((REPO / "eval" / "sweeps").glob("*.yaml")):
        s = Sweep.from_yaml(path)
        assert s.methods and s.shapes, path
        for name in s.methods:
            try:
                method = get_method(name)
            except (KeyError, ValueError):
                continue  # a method this install does not register: the sweep leaves it out with a warning
            for config in s.configs.get(name, [{}]):
                method.resolve_config(dict(config))


def test_the_recipe_sweeps_run_on_the_tables_inputs_and_split_their_configs():
    """recipes.yaml (`make reproduce-recipes`) takes the same shapes and input settings as paper.yaml, so their
    runs share inputs and land in the same Table 2, and no configuration runs in both sets."""
    tables, recipes = (Sweep.from_yaml(REPO / "eval" / "sweeps" / n) for n in ("paper.yaml", "recipes.yaml"))
    assert recipes.shapes == tables.shapes and set(recipes.inputs) == set(tables.inputs)
    for kind in recipes.inputs:
        assert recipes.input_settings(kind) == tables.input_settings(kind), kind
    for method in recipes.methods:
        assert method in tables.methods
        assert not {repr(c) for c in recipes.configs[method]} & {repr(c) for c in tables.configs.get(method, [{}])}


def test_reproduce_tables_sets_keep_each_others_rows_in_the_report(fake, tmp_path, monkeypatch, capsys):
    """`dmesh reproduce-tables` and `--recipes` run their own sweeps, then report every configuration in the
    store: a run of one set keeps the other's rows in Table 2; `--sweep FILES` reports only those files' runs."""
    import pandas as pd

    from eval.cli import main
    from eval.commands import reproduce_tables

    def sweep_file(name, delay):
        path = tmp_path / f"{name}.yaml"
        path.write_text(f"name: {name}\nmethods: [fake_hull]\nshapes: [sphere]\nn_points: 1500\n"
                        f"metric_samples: 1500\nconfigs:\n  fake_hull:\n    - {{delay: {delay}}}\n")
        return str(path)

    monkeypatch.setattr(reproduce_tables, "DEFAULT_SWEEPS", [sweep_file("tables", 0.0)])
    monkeypatch.setattr(reproduce_tables, "RECIPE_SWEEPS", [sweep_file("recipes", 0.01)])
    work, rep = str(tmp_path / "work"), tmp_path / "rep"

    def labels():
        return sorted(set(pd.read_csv(rep / "table2_pointcloud.csv")["method"]))

    base = ["-q", "reproduce-tables", "--work", work, "-o", str(rep), "--no-renders"]
    assert main(base + ["--recipes"]) == 0
    assert main(base) == 0
    assert labels() == sorted(["fake_hull [delay=0.0]", "fake_hull [delay=0.01]"])
    assert main(base + ["--sweep", sweep_file("tables", 0.0)]) == 0
    assert labels() == ["fake_hull [delay=0.0]"]


# --------------------------------------------------------------------------------------------------- sweeps

def test_sweep_stores_done_rows_then_skips_them(fake, tmp_path):
    from eval.runner import RunnerConfig, run_sweep

    counter = tmp_path / "calls.txt"
    sweep = small_sweep(seeds=(0, 1), configs={"fake_hull": [{"counter": str(counter)}]})
    runner = RunnerConfig(work=str(tmp_path / "work"))
    s = run_sweep(sweep, runner)
    assert (s.total, s.done, s.failed, s.skipped) == (2, 2, 0, 0)
    with Store(runner.db_path) as store:
        rows = store.rows()
    assert [r["status"] for r in rows] == ["done", "done"]
    for r in rows:
        assert r["category"] == "closed" and r["method"] == "fake_hull" and r["input_kind"] == "pointcloud"
        assert r["metrics_json"]["cd_p2s"] >= 0 and "total" in r["timings_json"]
        assert 0 < r["info_json"]["method_cpu_s"] < 60  # the worker's CPU seconds in the method
        assert r["config_json"]["counter"] == str(counter) and r["code_version"].startswith(("0", "1"))
        assert (runner.db_path.parent / r["mesh_path"]).is_file()
        assert r["started_at"] <= r["finished_at"]
    # Inputs were prepared once per (shape, kind, seed) and cached, and the GT's own figures once per GT.
    cached = sorted(p.name for p in (tmp_path / "work" / "inputs").rglob("*") if p.is_file())
    assert cached == ["gt.ply", "gt_figures.json", "meta.json", "pc_n1500_s0.npz", "pc_n1500_s1.npz"]
    assert counter.read_text().split() == ["0", "1"]
    # A second run recomputes nothing.
    s = run_sweep(sweep, runner)
    assert (s.done, s.skipped) == (0, 2) and counter.read_text().split() == ["0", "1"]


@pytest.mark.parametrize("jobs, threads", [(2, None), (1, 1), (2, 3)])
def test_each_run_gets_its_share_of_the_cores(fake, tmp_path, jobs, threads):
    """Concurrent runs split the cores (or take the threads asked for): torch's pool, which the DMesh kernels
    follow, and the OpenMP variable of libraries started later, are set in each worker."""
    from eval.runner import RunnerConfig, available_cores, run_sweep

    runner = RunnerConfig(work=str(tmp_path / "work"), jobs=jobs, threads=threads)
    want = threads if threads is not None else max(1, available_cores() // jobs)
    assert runner.threads_per_run == want
    run_sweep(small_sweep(seeds=(0, 1)), runner)
    with Store(runner.db_path) as store:
        infos = [r["info_json"] for r in store.rows()]
    assert [(i["threads"], i["omp_env"], i["worker_threads"]) for i in infos] == [(want, str(want), want)] * 2
    with pytest.raises(ValueError, match="threads"):
        RunnerConfig(work=str(tmp_path), threads=0)


def test_failing_run_is_recorded_and_the_sweep_goes_on(fake, tmp_path):
    from eval.runner import RunnerConfig, run_sweep

    sweep = small_sweep(methods=("fake_fail", "fake_hull"))
    runner = RunnerConfig(work=str(tmp_path / "work"))
    s = run_sweep(sweep, runner)
    assert (s.done, s.failed) == (1, 1)
    with Store(runner.db_path) as store:
        by = {r["method"]: r for r in store.rows()}
    assert by["fake_fail"]["status"] == "failed"
    assert by["fake_fail"]["error"] == "RuntimeError: fake failure: boom"
    assert by["fake_hull"]["status"] == "done"
    # Failed runs are results too: not retried unless asked.
    assert run_sweep(sweep, runner).skipped == 2
    assert run_sweep(sweep, RunnerConfig(work=str(tmp_path / "work"), retry_failed=True)).failed == 1


def test_a_run_whose_method_returned_an_empty_mesh_fails_with_what_the_method_said(fake, tmp_path):
    """A method that returned (here an empty mesh) leaves its info and timings on the failed row, so the store
    says how far it got; a method that raised has none."""
    from eval.runner import RunnerConfig, run_sweep

    sweep = small_sweep(methods=("fake_fail", "fake_hull"), configs={"fake_hull": [{"empty": True}]})
    runner = RunnerConfig(work=str(tmp_path / "work"))
    assert run_sweep(sweep, runner).failed == 2
    with Store(runner.db_path) as store:
        by = {r["method"]: r for r in store.rows()}
    empty, raised = by["fake_hull"], by["fake_fail"]
    assert empty["error"] == "ValueError: the method returned an empty mesh" and empty["mesh_path"] is None
    assert empty["info_json"]["reals_left"] == 0 and empty["info_json"]["method_cpu_s"] >= 0
    assert "total" in empty["timings_json"] and empty["metrics_json"] is None
    assert not raised["info_json"] and not raised["timings_json"]


def test_a_run_whose_method_sources_changed_since_planning_fails_with_the_reason(fake, tmp_path):
    """A worker checks that its method's sources still hash to the run's key, so a sweep whose code was edited
    while it ran records those runs as failed (rerun under their own key) instead of storing a mixture."""
    import dataclasses

    from eval.runner import execute_run
    from eval.sweep import expand, get_method, sources_changed

    (spec,) = expand(small_sweep())
    assert sources_changed(get_method(spec.method), spec.code_version) is None
    stale = dataclasses.replace(spec, code_version=spec.code_version + "0")
    out = execute_run(stale, tmp_path / "missing_gt.ply", tmp_path / "work")
    assert out["status"] == "failed"
    assert "sources of method 'fake_hull' changed after the sweep started" in out["error"]


def test_a_run_whose_executed_code_is_unchanged_stays_current_under_a_new_code_version(fake, tmp_path, monkeypatch):
    """A done run records the hashes of the code it executed; when the method's code version changes but that
    code did not, the next sweep adopts the stored run (nothing runs, the report counts it as current); once a
    recorded hash no longer holds, the run is made again under the new key."""
    import eval.code_hash
    from eval.reports.recipes import made_by_earlier_code
    from eval.runner import RunnerConfig, plan_sweep, run_sweep

    counter = tmp_path / "calls.txt"
    sweep = small_sweep(configs={"fake_hull": [{"counter": str(counter)}]})
    runner = RunnerConfig(work=str(tmp_path / "work"))
    first = run_sweep(sweep, runner)
    with Store(runner.db_path) as store:
        (row,) = store.rows()
    assert row["base_key"] and len(row["code_deps"]["digest"]) == 16
    assert "inputs:version" in row["code_deps"]["entries"]  # the inputs by their version, not by their code

    monkeypatch.setattr(eval.code_hash, "code_version", lambda method, root=REPO: "9.9+src.elsewhere")
    plan = plan_sweep(sweep, runner)
    assert (plan.stored, plan.kept, plan.pending) == (1, 1, 0)
    assert "1 stored (1 under earlier code versions, current: the code they ran is unchanged), 0 to run" in plan.line()
    again = run_sweep(sweep, runner)
    assert (again.skipped, again.kept, again.done, again.keys) == (1, 1, 0, first.keys)
    assert "1 already stored (1 under earlier code versions, current" in again.line()
    assert counter.read_text().split() == ["0"]
    assert not made_by_earlier_code(row, "9.9+src.elsewhere")

    with Store(runner.db_path) as store:  # as if a file it depends on had changed since the run
        store.upsert({**row, "code_deps": {**row["code_deps"], "digest": "0" * 16}})
        assert made_by_earlier_code(store.get(row["key"]), "9.9+src.elsewhere")
    assert plan_sweep(sweep, runner).pending == 1
    third = run_sweep(sweep, runner)
    assert third.done == 1 and third.keys != first.keys
    assert counter.read_text().split() == ["0", "0"]
    with Store(runner.db_path) as store:
        assert store.get(third.keys[0])["code_version"] == "9.9+src.elsewhere"


def test_timeout_and_worker_crash_are_failed_runs(fake, tmp_path):
    from eval.runner import RunnerConfig, run_sweep

    # The limit leaves a loaded machine time to start the crashing worker (at 1.5 s it sometimes timed out
    # first, and at 6 s once with five processes on two cores); the sleeping run is far longer, so finishing
    # well before it shows the limit stopped it.
    sweep = small_sweep(configs={"fake_hull": [{"delay": 300.0}, {"crash": True}]}, timeout_s=20.0)
    runner = RunnerConfig(work=str(tmp_path / "work"), jobs=2)
    t0 = time.monotonic()
    s = run_sweep(sweep, runner)
    assert s.failed == 2 and time.monotonic() - t0 < 150
    with Store(runner.db_path) as store:
        errors = sorted(r["error"] for r in store.rows())
    assert errors[0].startswith("Timeout: the run took more than 20 s")
    assert errors[1] == "WorkerDied: the worker exited with code 3"


def test_checkpoint_outlives_only_a_dead_worker_and_is_resumed(fake, tmp_path):
    """A run's checkpoint (`Inputs.checkpoint`) stays when its worker dies, so a retry resumes it (its time
    counts the earlier attempt); it is removed once an outcome is stored: done, raised or timed out."""
    from eval.runner import RunnerConfig, checkpoint_path, run_sweep
    from eval.sweep import expand

    work = tmp_path / "work"
    runner = RunnerConfig(work=str(work))
    sweep = small_sweep(configs={"fake_hull": [{"save": True, "crash_fresh": True}]})
    (spec,) = expand(sweep)
    state = checkpoint_path(work, spec.key)
    assert run_sweep(sweep, runner).failed == 1
    assert state.is_file()                                   # the worker died: its state stays
    assert run_sweep(sweep, RunnerConfig(work=str(work), retry_failed=True)).done == 1
    assert not state.exists()                                # stored: removed
    with Store(runner.db_path) as store:
        (row,) = store.rows()
    assert row["info_json"]["resumed"] is True
    assert row["code_deps"] is None  # what the first attempt ran is not in this attempt's record
    assert row["timings_json"]["earlier_attempts"] == 5.0
    assert row["timings_json"]["total"] >= 5.0               # the earlier attempt's time is counted

    for config, timeout in (({"save": True, "fail": True}, 60.0), ({"save": True, "delay": 30.0}, 1.5)):
        sweep = small_sweep(configs={"fake_hull": [config]}, timeout_s=timeout)
        (spec,) = expand(sweep)
        assert run_sweep(sweep, runner).failed == 1
        assert not checkpoint_path(work, spec.key).exists()  # a raising or timed-out run starts over


def test_resume_after_killed_process(fake, tmp_path):
    """Start a sweep of slow fake runs in a subprocess, SIGKILL it once some runs are done, rerun: the
    finished runs are not recomputed, the one left `running` is redone, and all end done."""
    from eval.runner import RunnerConfig, run_sweep

    counter, work = tmp_path / "calls.txt", tmp_path / "work"
    seeds = (0, 1, 2, 3)
    config = {"delay": 1.0, "counter": str(counter)}
    script = tmp_path / "sweep.py"
    script.write_text(FAKE_METHOD_SRC + textwrap.dedent(f"""
        from baselines import registry
        from eval.runner import RunnerConfig, run_sweep
        from eval.sweep import Sweep
        registry.METHODS["fake_hull"] = FakeHull()
        sweep = Sweep(methods=("fake_hull",), shapes=("sphere",), seeds={seeds!r},
                      configs={{"fake_hull": [{config!r}]}}, **{SMALL!r})
        run_sweep(sweep, RunnerConfig(work={str(work)!r}))
    """))
    proc = subprocess.Popen([sys.executable, str(script)], cwd=REPO, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    db = work / "results.sqlite"
    deadline = time.monotonic() + 60
    done = 0
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if db.is_file():
                with Store(db) as store:
                    counts = store.counts()
                done = counts.get("done", 0)
                # Killed only once the next run is marked running: between two runs nothing is (the race
                # that made this test flaky under load).
                if done >= 1 and counts.get("running", 0) >= 1:
                    break
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
    assert 1 <= done < len(seeds), f"the sweep was not caught mid-way (done={done}): {err[-500:]}"
    with Store(db) as store:
        before = {r["seed"]: r["status"] for r in store.rows()}
    finished_before = {s for s, st in before.items() if st == "done"}
    assert "running" in before.values()
    calls_before = counter.read_text().split()

    s = run_sweep(Sweep(methods=("fake_hull",), shapes=("sphere",), seeds=seeds,
                        configs={"fake_hull": [config]}, **SMALL), RunnerConfig(work=str(work)))
    assert s.skipped == len(finished_before) and s.done == len(seeds) - len(finished_before)
    with Store(db) as store:
        assert {r["status"] for r in store.rows()} == {"done"} and len(store.rows()) == len(seeds)
    calls = counter.read_text().split()
    for seed in finished_before:  # each finished run was invoked exactly once, before the kill
        assert calls.count(str(seed)) == 1 == calls_before.count(str(seed))
    assert sorted(set(calls)) == [str(x) for x in seeds]


def test_ray_executor_runs_the_same_sweep(fake, tmp_path, monkeypatch):
    """A local Ray (no address, no $RAY_ADDRESS) stores what the local executor stores, meshes included."""
    import ray

    from eval.runner import RunnerConfig, resolve_mesh_path, run_sweep

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    sweep = small_sweep(methods=("fake_hull", "fake_fail"))
    run_sweep(sweep, RunnerConfig(work=str(tmp_path / "local")))
    try:
        s = run_sweep(sweep, RunnerConfig(work=str(tmp_path / "work"), executor="ray", jobs=2))
    finally:
        ray.shutdown()
    assert (s.done, s.failed) == (1, 1)
    with Store(tmp_path / "work" / "results.sqlite") as store, Store(tmp_path / "local" / "results.sqlite") as ref:
        rows, want = store.rows(), {r["key"]: r for r in ref.rows()}
    assert {r["method"]: r["status"] for r in rows} == {"fake_hull": "done", "fake_fail": "failed"}
    for r in rows:
        w = want[r["key"]]
        assert (r["status"], r["error"], r["metrics_json"]) == (w["status"], w["error"], w["metrics_json"])
        if r["status"] == "done":
            mesh = resolve_mesh_path(r, tmp_path / "work" / "results.sqlite")
            assert mesh.read_bytes() == resolve_mesh_path(w, tmp_path / "local" / "results.sqlite").read_bytes()


def test_ray_missing_is_one_clear_error(fake, tmp_path, monkeypatch):
    from eval.runner import RunnerConfig, run_sweep

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ValueError, match=r"pip install -e \.\[ray\]"):
        run_sweep(small_sweep(), RunnerConfig(work=str(tmp_path / "work"), executor="ray"))
    assert not (tmp_path / "work").exists()


def test_bench_cli_end_to_end_in_process(fake, tmp_path, capsys):
    from eval.cli import main

    work, rep = tmp_path / "work", tmp_path / "rep"
    args = ["-q", "bench", "--methods", "fake_hull", "fake_fail", "--shapes", "sphere", "disc", "--work", str(work),
            "--set", "n_points=1500", "--set", "metric_samples=1500", "--report", str(rep)]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "fake_hull" in out and "4 runs: 2 done now, 2 failed now" in out
    assert (rep / "index.html").is_file() and (rep / "table2_pointcloud.csv").is_file()
    assert main(args) == 0
    assert "0 done now, 0 failed now, 4 already stored" in capsys.readouterr().out


def test_rescore_recomputes_old_metrics_from_the_stored_mesh(fake, tmp_path, capsys):
    from eval.cli import main
    from eval.metrics import compute_metrics
    from eval.runner import RunnerConfig, load_gt, run_sweep
    from eval.sweep import metrics_version

    runner = RunnerConfig(work=str(tmp_path / "work"))
    run_sweep(small_sweep(seeds=(0, 1)), runner)
    with Store(runner.db_path) as store:
        rows = store.rows()
        assert all(r["metrics_json"]["metrics_version"] == metrics_version() for r in rows)
        # One run scored by older metric code (a wrong figure, an old version, a metric it lacked).
        old = {**rows[0]["metrics_json"], "cd_p2s": 9.0, "metrics_version": "0" * 16}
        old.pop("oriented_fraction_any_side")
        store.set_metrics(rows[0]["key"], old)
    work = str(tmp_path / "work")
    assert main(["-q", "rescore", "--work", work, "--plan"]) == 0
    assert "1 runs to score, 1 already scored by it" in capsys.readouterr().out
    assert main(["-q", "rescore", "--work", work]) == 0
    with Store(runner.db_path) as store:
        again = store.get(rows[0]["key"])["metrics_json"]
    mesh = trimesh.load(runner.db_path.parent / rows[0]["mesh_path"], process=False, force="mesh")
    gt = load_gt(next((tmp_path / "work" / "inputs").glob("sphere-*")) / "gt.ply")
    assert again["metrics_version"] == metrics_version() and "oriented_fraction_any_side" in again
    assert again["cd_p2s"] == pytest.approx(compute_metrics(mesh, gt, n=1500, seed=0)["cd_p2s"], rel=1e-12)
    assert main(["-q", "rescore", "--work", work]) == 0
    assert "0 runs to score, 2 already scored by it" in capsys.readouterr().out



def test_rerun_redoes_stored_runs_all_or_those_scored_by_older_metrics(fake, tmp_path):
    """`rerun="stale-metrics"` runs again only the done runs whose metrics came from another metric code (a run
    whose mesh is gone cannot be rescored), `rerun="all"` every stored run, failed ones included; the new result
    replaces the old one under the same key."""
    from eval.runner import RunnerConfig, run_sweep

    counter = tmp_path / "calls.txt"
    sweep = small_sweep(seeds=(0, 1), configs={"fake_hull": [{"counter": str(counter)}]})
    runner = RunnerConfig(work=str(tmp_path / "work"))
    run_sweep(sweep, runner)
    with Store(runner.db_path) as store:
        rows = store.rows()
        store.set_metrics(rows[0]["key"], {**rows[0]["metrics_json"], "cd_p2s": 9.0, "metrics_version": "0" * 16})
    stale = RunnerConfig(work=str(tmp_path / "work"), rerun="stale-metrics")
    s = run_sweep(sweep, stale)
    assert (s.done, s.skipped) == (1, 1) and counter.read_text().split() == ["0", "1", str(rows[0]["seed"])]
    with Store(runner.db_path) as store:
        again = store.get(rows[0]["key"])
    assert again["status"] == "done" and again["metrics_json"]["cd_p2s"] == rows[0]["metrics_json"]["cd_p2s"]
    assert again["attempts"] == rows[0]["attempts"] + 1
    assert run_sweep(sweep, stale).skipped == 2  # now scored by the current metrics
    s = run_sweep(sweep, RunnerConfig(work=str(tmp_path / "work"), rerun="all"))
    assert (s.done, s.skipped) == (2, 0) and len(counter.read_text().split()) == 5
    failing = small_sweep(methods=("fake_fail",))
    run_sweep(failing, runner)
    assert run_sweep(failing, RunnerConfig(work=str(tmp_path / "work"), rerun="all")).failed == 1
    with pytest.raises(ValueError, match="rerun"):
        RunnerConfig(work=str(tmp_path), rerun="everything")


# --------------------------------------------------------------------------------------------------- bad input

def run_cli(*args, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "eval.cli", *args], capture_output=True, text=True, cwd=cwd)


def _one_line_exit_2(r):
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0, r.stderr


def _main_one_line_exit_2(capsys, *args) -> str:
    """Runs the CLI in-process (fast); checks exit status 2 and a one-line error; returns it."""
    from eval.cli import main

    code = main(list(args))
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.count("\n") == 0 and err.startswith("dmesh "), err
    return err


def test_bench_unknown_method_or_shape_is_one_line_error(tmp_path, capsys):
    pytest.importorskip("baselines.registry")
    work = tmp_path / "work"
    r = run_cli("bench", "--methods", "no_such_method", "--shapes", "sphere", "--work", str(work))
    _one_line_exit_2(r)
    assert "unknown method 'no_such_method'" in r.stderr
    err = _main_one_line_exit_2(capsys, "bench", "--methods", "psr", "--shapes", "no_such_shape", "--work", str(work))
    assert "unknown shape 'no_such_shape'" in err
    err = _main_one_line_exit_2(capsys, "bench", "--methods", "psr", "--shapes", "sphere", "--work", str(work),
                                "--set", "psr.no_such_key=1")
    assert "unknown config keys ['no_such_key']" in err
    _main_one_line_exit_2(capsys, "bench", str(tmp_path / "missing.yaml"), "--work", str(work))
    assert not work.exists()


def test_compare_unreadable_mesh_is_one_line_error(tmp_path, capsys):
    pytest.importorskip("datasets.meshes")
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    out = tmp_path / "cmp"
    r = run_cli("compare", str(bad), "--methods", "psr", "-o", str(out))
    _one_line_exit_2(r)
    assert "bad.obj" in r.stderr
    err = _main_one_line_exit_2(capsys, "compare", str(tmp_path / "missing.ply"), "--methods", "psr", "-o", str(out))
    assert "missing.ply" in err
    err = _main_one_line_exit_2(capsys, "compare", str(bad), "--methods", "no_such_method", "-o", str(out))
    assert "unknown method" in err
    assert not out.exists()


def test_prepare_input_tolerates_a_concurrent_capture(tmp_path, monkeypatch):
    """Two processes sharing a work folder may capture the same views; the one that finishes second keeps
    the first one's folder instead of failing (os.replace cannot replace a non-empty folder)."""
    import datasets.capture as capture_mod
    from eval.runner import input_path, prepare_gt, prepare_input

    shape, gt_path = prepare_gt(resolve_shape("torus"), tmp_path)
    settings = {"views": 2, "resolution": 16, "distance": 2.0, "radius": 1.0}
    dest = input_path(tmp_path, shape, "multiview", settings, 0)

    class RacingViews:
        def save(self, folder):
            (Path(folder) / "mine.txt").write_text("second")
            dest.mkdir()  # the other process wins the race while this one is saving
            (dest / "theirs.txt").write_text("first")

    monkeypatch.setattr(capture_mod, "capture", lambda *a, **k: RacingViews())
    assert prepare_input(shape, gt_path, "multiview", settings, 0, tmp_path) == dest
    assert sorted(p.name for p in dest.iterdir()) == ["theirs.txt"]
    assert [p.name for p in dest.parent.iterdir() if p.name.startswith(".")] == []


def test_resolve_mesh_path_of_a_failed_run(tmp_path):
    from eval.runner import resolve_mesh_path

    db = tmp_path / "results.sqlite"
    assert resolve_mesh_path({"mesh_path": None}, db) is None
    assert resolve_mesh_path({"mesh_path": float("nan")}, db) is None  # a failed row read through pandas
    assert resolve_mesh_path({"mesh_path": "meshes/a.ply"}, db) == tmp_path / "meshes" / "a.ply"


def test_sweep_configs_may_name_a_preset():
    from baselines.registry import get_method
    from dmesh.recon.config import PointCloudConfig
    from eval.sweep import build_config

    cfg, as_dict = build_config(get_method("dmesh"), {"preset": "paper", "steps_phase1": 3})
    assert cfg == PointCloudConfig.paper(steps_phase1=3) and as_dict["num_init"] == 10_000
    with pytest.raises(ValueError, match="unknown config keys"):
        build_config(get_method("dmesh"), {"preset": "paper", "stepz": 3})


def test_plan_counts_stored_runs_and_times_the_rest_by_their_stored_twins(fake, tmp_path, capsys):
    """`--plan`: nothing runs; runs stored under their key are skipped, a pending run whose configuration ran
    under other code is timed by that run's wall time, and one that never ran is counted as such."""
    from eval.cli import main
    from eval.runner import RunnerConfig, plan_sweep, run_sweep

    runner = RunnerConfig(work=str(tmp_path / "work"))
    assert plan_sweep(small_sweep(seeds=(0, 1)), runner).pending == 2  # no store yet
    run_sweep(small_sweep(seeds=(0,)), runner)
    with Store(runner.db_path) as store:  # the stored run as if made by older code (no record of what it ran)
        row = store.rows()[0]             # in 90 s
        store.delete([row["key"]])
        store.upsert({**row, "key": "older", "code_deps": None, "started_at": "2026-01-01T00:00:00+00:00",
                      "finished_at": "2026-01-01T00:01:30+00:00"})
    plan = plan_sweep(small_sweep(seeds=(0, 1)), runner)
    assert (plan.total, plan.stored, plan.pending, plan.known, plan.known_s) == (2, 0, 2, 1, 90.0)
    assert "1 never ran" in plan.line(2) and "(0.01 h at 2 jobs)" in plan.line(2)
    assert plan.by_method == {"fake_hull": (2, 1, 90.0)}
    assert plan.breakdown() == ["  fake_hull: 2 to run, 1 took 0.03 h, 1 never ran"]
    run_sweep(small_sweep(seeds=(1,)), runner)
    assert plan_sweep(small_sweep(seeds=(0, 1)), runner).stored == 1
    with Store(runner.db_path) as store:
        before = len(store.rows())
    assert main(["-q", "bench", "--methods", "fake_hull", "--shapes", "sphere", "--set", "n_points=1500",
                 "--work", str(tmp_path / "work"), "--plan"]) == 0
    out = capsys.readouterr().out
    assert "sweep" in out and "  fake_hull: " in out
    with Store(runner.db_path) as store:
        assert len(store.rows()) == before  # nothing ran


def test_a_run_that_lost_accuracy_after_its_last_step_is_warned_about(caplog):
    """The runner logs a warning when the final CD p2s is well above the monitor's last one (and none when
    they agree, or the run has no curve)."""
    import logging
    from types import SimpleNamespace

    from eval.execute import _warn_post_step_damage

    spec = SimpleNamespace(key="abcdef0123456789", method="dmesh", shape=SimpleNamespace(id="mushroom"))
    info = {"curve": [{"phase": 2, "step": 9, "loss": 0.01, "cd_p2s": 1e-3}]}
    with caplog.at_level(logging.WARNING, logger="eval.execute"):
        _warn_post_step_damage(spec, info, {"cd_p2s": 1.1e-3})
        _warn_post_step_damage(spec, {}, {"cd_p2s": 5e-3})
        assert not caplog.records
        _warn_post_step_damage(spec, info, {"cd_p2s": 3e-3})
    assert len(caplog.records) == 1 and "3.00x the last monitored" in caplog.records[0].getMessage()
    assert "mushroom" in caplog.records[0].getMessage()
