"""Candidate faces and the neighbour cache (`dmesh.candidates`): they only grow within a phase, and validate."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import dmesh
from dmesh import wdt
from dmesh.candidates import CandidateFaces, NeighbourCache


def test_candidates_and_cache_only_grow():
    rng = np.random.default_rng(19)
    n = 200
    dm = dmesh.DMesh(rng.random((n, 3)), reals=rng.random(n))
    dm.face_probabilities()
    c0, k0 = len(dm.state.candidates), dm.state.cache.csr.indices.copy()
    with torch.no_grad():
        dm.points += 0.02 * torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    fp = dm.face_probabilities()
    assert len(dm.state.candidates) >= c0
    cache = dm.state.cache.csr
    assert len(cache.indices) >= len(k0)
    pdn = fp.power_diagram.point_neighbors
    for i in range(0, n, 17):
        assert set(pdn.row(i)) <= set(cache.row(i))
        assert (np.diff(cache.row(i)) > 0).all()
    dm.new_phase()
    assert len(dm.state.candidates) == 0


def test_candidate_faces_validate():
    c = CandidateFaces(5)
    c.add([[2, 1, 0], [0, 1, 2], [1, 1, 2]])
    np.testing.assert_array_equal(c.faces, [[0, 1, 2]])
    with pytest.raises(ValueError, match="index points"):
        c.add([[0, 1, 9]])
    with pytest.raises(ValueError, match="cover"):
        NeighbourCache(5).update(wdt.Csr(np.zeros(3, np.int32), np.zeros(0, np.int32)))
