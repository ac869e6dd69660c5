"""The DMesh model (`dmesh.model`): extraction, save and load, bad parameters."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import dmesh
from common import spacing_weights


def test_dmesh_extract_save_load(tmp_path):
    rng = np.random.default_rng(23)
    n = 300
    r = (rng.random(n) > 0.5).astype(np.float32)
    dm = dmesh.DMesh(rng.random((n, 3)), spacing_weights(rng, n), r)
    mesh = dm.extract_mesh()
    pd = dm.power_diagram()
    expect = pd.faces[(r[pd.faces] > 0.5).all(1)]
    assert len(mesh.faces) == len(expect) > 0
    dm.save(tmp_path / "state.npz")
    back = dmesh.DMesh.load(tmp_path / "state.npz")
    for a, b in zip(dm.parameters(), back.parameters()):
        assert torch.equal(a, b)
    assert back.config == dm.config
    with pytest.raises(ValueError, match="cannot read"):
        dmesh.DMesh.load(tmp_path / "missing.npz")
    with pytest.raises(ValueError, match="reals"):
        dmesh.DMesh(rng.random((10, 3)), reals=np.full(10, 2.0))
