"""Shared fixtures. Tests write only under tmp_path and never assert on timings."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")

#: Real test meshes live beside the checkout (never copied into the repository).
SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def spacing_weights(rng: np.random.Generator, n: int, scale: float = 0.1) -> np.ndarray:
    """Weights in [0, scale * h^2] with h = n^(-1/3): relative to the point spacing, so few are hidden."""
    return rng.random(n) * scale * n ** (-2.0 / 3.0)


def shared_mesh(rel: str) -> Path:
    path = SHARED_MESHES / rel
    if not path.exists():
        pytest.skip(f"shared test mesh {rel} not found beside the checkout")
    return path
