"""The shared optimisation loop (`dmesh.recon.loop`) on a toy problem: the state round trip, a resumed run
continuing identically, the stage timers and records, the early stop. Timings are never asserted."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from dmesh.recon.loop import Clock, Loop, fingerprint, load_state, save_state
from dmesh.recon.optim import BoundedAdam, StepConfig

N = 8


class Interrupt(Exception):
    pass


def _toy(state_path=None, steps=7, interrupt_at=None, save_every=2, seen=None):
    """A run of one phase pulling N points, weights and reals towards fixed targets, with noise drawn from a
    seeded generator each step (its state travels in the checkpoint, as the procedures' does)."""
    rng = np.random.default_rng(0)
    target = torch.from_numpy(np.random.default_rng(1).random((N, 3)))
    points = torch.nn.Parameter(torch.zeros(N, 3, dtype=torch.float64))
    weights = torch.nn.Parameter(torch.full((N,), 0.5, dtype=torch.float64))
    reals = torch.nn.Parameter(torch.full((N,), 0.5, dtype=torch.float64))
    config = StepConfig(lr=1e-2, update_bound=1e-2, max_real=1.0)

    def callback(rec):
        if seen is not None:
            seen.append(rec)
        if interrupt_at is not None and rec.get("step") == interrupt_at:
            raise Interrupt

    loop = Loop(callback, state_path, fingerprint(target.numpy(), config), save_every,
                extra_state=lambda: {"rng": rng.bit_generator.state})
    opt = BoundedAdam(points, weights, reals, config)
    start = 0
    state = loop.resume()
    if state is not None:
        with torch.no_grad():
            points.copy_(state["points"])
            weights.copy_(state["weights"])
            reals.copy_(state["reals"])
        if state["optimizer"] is not None:
            opt.load_state_dict(state["optimizer"])
        rng.bit_generator.state = state["rng"]
        start = state["step"]

    def toy_step(step):
        noise = torch.from_numpy(rng.normal(size=(N, 3)) * 1e-3)
        with loop.clock("toy_loss"):
            loss = ((points - target - noise) ** 2).sum() + ((weights - 0.7) ** 2).sum() + ((reals - 0.3) ** 2).sum()
        return loss, {"noise": float(noise.sum())}

    loop.stage("toy")
    loop.run_phase(toy_step, opt, steps, start, {"phase": 1}, "toy_")
    loop.finish()
    return loop, torch.cat([points.detach().reshape(-1), weights.detach(), reals.detach()])


def _without_seconds(history):
    return [{k: v for k, v in r.items() if k != "seconds"} for r in history]


def test_state_round_trip(tmp_path, caplog):
    path = tmp_path / "sub" / "state.pt"
    state = {"fingerprint": "abc", "phase": 2, "step": 5, "points": torch.arange(6.0).reshape(2, 3)}
    save_state(path, state)
    assert sorted(p.name for p in path.parent.iterdir()) == ["state.pt"]  # the temporary name is gone
    back = load_state(path, "abc")
    assert back["phase"] == 2 and back["step"] == 5 and torch.equal(back["points"], state["points"])
    assert load_state(path, "another") is None               # another input or config
    assert load_state(tmp_path / "missing.pt", "abc") is None
    path.write_bytes(b"not a torch file")
    with caplog.at_level(logging.WARNING, logger="dmesh.recon.loop"):
        assert load_state(path, "abc") is None                # unreadable: ignored with a warning
    assert "ignoring unreadable state" in caplog.text


def test_fingerprint_tells_inputs_and_configs_apart():
    a = np.arange(6.0)
    assert fingerprint(a, StepConfig()) == fingerprint(a.copy(), StepConfig())
    assert fingerprint(a, StepConfig()) != fingerprint(a + 1, StepConfig())
    assert fingerprint(a, StepConfig()) != fingerprint(a, StepConfig(lr=1e-3))


@pytest.mark.parametrize("interrupt_at", [1, 2, 5])
def test_resumed_run_continues_identically(tmp_path, interrupt_at):
    straight, params = _toy()
    path = tmp_path / "state.pt"
    with pytest.raises(Interrupt):
        _toy(path, interrupt_at=interrupt_at)
    seen = []
    resumed, params_resumed = _toy(path, seen=seen)
    # Saves come every 2 steps after the record, so the run restarts at the last even step <= the interrupt.
    restart = interrupt_at - interrupt_at % 2
    assert [r["step"] for r in seen if "step" in r] == list(range(restart, 7))
    assert torch.equal(params, params_resumed)
    assert _without_seconds(resumed.history) == _without_seconds(straight.history)
    assert (resumed.resumed is not None) == (restart > 0) and straight.resumed is None  # (no save before step 2)


def test_a_resumed_runs_total_counts_its_interrupted_attempt(tmp_path):
    path = tmp_path / "state.pt"
    with pytest.raises(Interrupt):
        _toy(path, interrupt_at=5)
    saved = torch.load(path, weights_only=True)["timings"]
    assert saved["total"] > 0 and saved["total_cpu"] >= 0   # the state carries the time up to its save
    resumed, _ = _toy(path)
    assert resumed.earlier_seconds == saved["total"]        # (the toy has no probe)
    assert resumed.timings["total"] > saved["total"] and resumed.timings["total_cpu"] >= saved["total_cpu"]
    fresh, _ = _toy()
    assert fresh.earlier_seconds == 0.0


def test_records_timers_and_stage_notifications():
    seen = []
    loop, _ = _toy(steps=3, seen=seen)
    assert seen[0] == {"stage": "toy"}
    records = [r for r in seen if "stage" not in r]
    assert records == loop.history and len(records) == 3
    assert list(records[0]) == ["phase", "step", "steps", "loss", "noise", "seconds"]
    assert [r["step"] for r in records] == [0, 1, 2] and all(r["steps"] == 3 for r in records)
    assert records[-1]["loss"] < records[0]["loss"]
    # The procedure's own stage, the loop's backward and update stages, and the totals.
    assert {"toy_loss", "toy_backward", "toy_step", "total", "total_cpu"} <= set(loop.timings)
    assert all(v >= 0 for v in loop.timings.values())


def test_clock_accumulates_and_adds_prefixed_stages():
    timings = {}
    clock = Clock(timings)
    for _ in range(2):
        with clock("a"):
            pass
    clock.add({"wdt": 1.0, "knn": 2.0}, "phase1_")
    clock.add({"wdt": 0.5}, "phase1_")
    assert set(timings) == {"a", "a_cpu", "phase1_wdt", "phase1_knn"} and timings["phase1_wdt"] == 1.5
    assert timings["a_cpu"] >= 0
    with pytest.raises(RuntimeError):  # a failing stage still counts its time
        with clock("b"):
            raise RuntimeError
    assert "b" in timings


def test_stop_ends_the_phase_before_the_update():
    x = torch.nn.Parameter(torch.zeros(4, 3, dtype=torch.float64))
    w = torch.nn.Parameter(torch.ones(4, dtype=torch.float64))
    r = torch.nn.Parameter(torch.ones(4, dtype=torch.float64))
    opt = BoundedAdam(x, w, r, StepConfig(lr=0.1, update_bound=0.1), train=("points",))
    loop, after = Loop(), []

    def pull(step):
        return ((x - 1.0) ** 2).sum(), {"x": float(x[0, 0].detach())}

    stopped = loop.run_phase(pull, opt, 10, 0, after_step=lambda s: after.append(s),
                             stop=lambda fig: fig["x"] >= 0.25)
    assert stopped and loop.history[-1]["x"] >= 0.25
    # The stopping step is recorded but not applied: the state is the one its figures describe.
    assert float(x[0, 0].detach()) == loop.history[-1]["x"] and after == [r["step"] for r in loop.history[:-1]]
    assert not Loop().run_phase(pull, opt, 2, 0)  # without `stop`, every step runs


def test_deterministic_turns_torchs_deterministic_algorithms_on_for_the_call_only():
    """The reconstructions run under `deterministic` (backward of CPU gathers in a fixed order); the caller's
    setting comes back afterwards, also after an exception."""
    from dmesh.recon.loop import deterministic
    from dmesh.recon.mesh_to_dmesh import mesh_to_dmesh
    from dmesh.recon.multiview import reconstruct as mv_reconstruct
    from dmesh.recon.pointcloud import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct as pc_reconstruct

    seen = []

    @deterministic
    def probe(fail=False):
        seen.append(torch.are_deterministic_algorithms_enabled())
        if fail:
            raise RuntimeError("boom")

    assert not torch.are_deterministic_algorithms_enabled()
    probe()
    with pytest.raises(RuntimeError):
        probe(fail=True)
    assert seen == [True, True] and not torch.are_deterministic_algorithms_enabled()
    for fn in (pc_reconstruct, mv_reconstruct, mesh_to_dmesh):  # each is `deterministic`'s wrapper
        assert fn.__code__ is probe.__code__, fn.__name__
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3000, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    during = []
    pc_reconstruct(pts, None, PointCloudConfig.tiny(num_init=200, steps_phase1=1, steps_phase2=1),
                   callback=lambda rec: during.append(torch.are_deterministic_algorithms_enabled()))
    assert during and all(during) and not torch.are_deterministic_algorithms_enabled()
