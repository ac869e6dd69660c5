"""Shared fixtures (helpers are in common.py). Tests write only under tmp_path and never assert on timings."""
from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")

#: The multi-view test capture: few views at low resolution (the tiny preset optimises at 48 pixels).
VIEWS, RESOLUTION = 16, 96


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="module")
def sphere():
    """The synthetic sphere, normalised to radius 1 (the multi-view tests' object)."""
    from datasets import synthetic
    from datasets.normalize import normalize

    gt, _ = normalize(synthetic.generate("sphere", seed=0), radius=1.0)
    return gt


@pytest.fixture(scope="module")
def sphere_views(sphere):
    """The test capture of `sphere`; skips without headless OpenGL."""
    from datasets import capture as cap

    problem = cap.gl_problem()
    if problem is not None:
        pytest.skip(f"no headless OpenGL (OSMesa/EGL): {problem}")
    return cap.capture(sphere, views=VIEWS, resolution=RESOLUTION)
