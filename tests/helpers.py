"""Shared test helpers (imported by the test modules; pytest puts tests/ on sys.path)."""
from __future__ import annotations

import numpy as np
import torch


def assert_close(actual, expected, rtol: float = 0.0, atol: float = 0.0, what: str = ""):
    """|actual - expected| <= atol + rtol * max|expected| everywhere; on failure, reports the worst element
    (STYLE rule 17). Tensors (detached) or arrays of the same shape."""
    a = np.asarray(actual.detach() if isinstance(actual, torch.Tensor) else actual, np.float64)
    e = np.asarray(expected.detach() if isinstance(expected, torch.Tensor) else expected, np.float64)
    assert a.shape == e.shape, f"{what}: shape {a.shape} != {e.shape}"
    if a.size == 0:
        return
    err = np.abs(a - e)
    scale = np.abs(e).max()
    tol = atol + rtol * scale
    k = np.unravel_index(int(np.argmax(err)), err.shape)
    assert err.max() <= tol, (f"{what}: max abs diff {err.max():.3g} > {tol:.3g} at {k} "
                              f"(actual {a[k]:.6g}, expected {e[k]:.6g}, max rel {err.max() / max(scale, 1e-300):.3g})")
