"""Regularisers (`dmesh.losses.regularizers`): values by hand, gradients, and the native weight regulariser
against the torch reference."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dmesh import native, probability, wdt
from dmesh.losses.regularizers import aspect_ratios, quality_regularizer, real_regularizer, weight_regularizer
from common import leaves, spacing_weights


def test_regularizers(rng):
    from dmesh import wdt

    s3 = np.sqrt(3.0)
    points = torch.tensor([[0, 0, 0], [1, 0, 0], [0.5, s3 / 2, 0], [0, 0, 1], [10, 0, 0], [0, 0.01, 0]],
                          dtype=torch.float64)
    ratio, longest = aspect_ratios(points, torch.tensor([[0, 1, 2], [0, 4, 5]]))
    assert ratio[0].item() == pytest.approx(1.0) and longest[0].item() == pytest.approx(1.0)
    assert ratio[1].item() > 20
    q = quality_regularizer(points, torch.tensor([[0, 1, 2], [0, 4, 5]]), torch.tensor([1.0, 1.0]))
    assert q.item() == pytest.approx((1.0 + 20 * 10) / 2)
    reals = torch.ones(6, dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [1, 2, 3]])
    assert real_regularizer(reals, faces, torch.ones(2)).item() == 0.0
    r = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    val = real_regularizer(r, torch.tensor([[0, 1, 2]]), torch.ones(1))
    assert val.item() == pytest.approx((2 / 3 + 2 * 1 / 3) / 3 + 2 / 3)
    val.backward()
    assert r.grad[1] < 0  # growth pushes the imaginary neighbours of a real point up
    p = torch.tensor(rng.random((40, 3)), requires_grad=True)
    w = torch.zeros(40, dtype=torch.float64, requires_grad=True)
    pd = wdt.PowerDiagram.from_points(p.detach(), w.detach())
    reg = weight_regularizer(p, w, pd)
    reg.backward()
    assert reg.item() > 0 and w.grad.abs().sum() > 0


def test_weight_regularizer_native_matches_the_torch_reference():
    from dmesh.losses.regularizers import weight_regularizer

    rng = np.random.default_rng(3)
    n = 2000
    p = rng.random((n, 3))
    w = spacing_weights(rng, n, scale=0.1)
    pd = wdt.PowerDiagram.from_points(p, w)
    out = []
    for native_impl in (True, False):
        pt, wt = leaves(p, w)
        diagram = probability.delta_diagram(pt, wt, pd) if native_impl else None
        reg = weight_regularizer(pt, wt, pd, max_length=0.05, diagram=diagram)  # some edges clamped
        reg.backward()
        out.append((reg.detach(), pt.grad, wt.grad))
    (rn, gpn, gwn), (rr, gpr, gwr) = out
    assert (gwr != 0).sum() > n // 2
    torch.testing.assert_close(rn, rr, rtol=1e-9, atol=0.0)
    torch.testing.assert_close(gpn, gpr, rtol=1e-9, atol=1e-9 * gpr.abs().max().item())
    torch.testing.assert_close(gwn, gwr, rtol=1e-9, atol=1e-9 * gwr.abs().max().item())
    # The adjoint's per-point reduction does not depend on the thread count.
    g = rng.standard_normal((len(pd.tets), 3))
    grads = [native.orthocentre_backward(native.delta_diagram(p, w, pd, num_threads=t), g, num_threads=t)
             for t in (1, 3)]
    assert all(np.array_equal(a, b) for a, b in zip(*grads))
