"""The bounded step (`dmesh.recon.optim`): update bounds, frozen points, parameter groups."""
from __future__ import annotations

import torch

from dmesh.recon.optim import BoundedAdam, StepConfig


def test_bounded_adam_bounds_and_freezing(rng):
    n = 30
    pts = torch.nn.Parameter(torch.tensor(rng.random((n, 3))))
    w = torch.nn.Parameter(torch.full((n,), 0.5, dtype=torch.float64))
    r = torch.nn.Parameter(torch.full((n,), 0.5, dtype=torch.float64))
    opt = BoundedAdam(pts, w, r, StepConfig(lr=0.1, update_bound=1e-3, max_real=1e-2))
    opt.freeze(torch.arange(n) < 5)
    before = pts.detach().clone()
    for _ in range(3):
        opt.zero_grad()
        (pts.sum() * 1e3 + w.sum() + (r * r).sum() * float("nan")).backward()  # NaN grads of r are zeroed
        opt.step()
    assert (pts.detach() - before).abs().max() <= 3e-3 + 1e-12
    assert (r[:5] == 1).all() and (r[5:] == 0.5).all()
    assert ((w >= 0) & (w <= 1)).all()
    only_reals = BoundedAdam(pts, w, r, StepConfig(), train=("reals",))
    assert [g["name"] for g in only_reals.optimizer.param_groups] == ["reals"]
