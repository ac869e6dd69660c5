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


def test_the_native_key_merges_match_numpys_set_operations():
    """`add_sorted_keys` and `off_wdt` (linear merges in native/src/face_keys.cpp) against NumPy's set
    operations on random key sets with overlaps, empties and hidden points."""
    rng = np.random.default_rng(3)
    n = 40
    for trial in range(20):
        c = CandidateFaces(n)
        expected = np.zeros(0, np.int64)
        for _ in range(3):
            keys = np.unique(rng.integers(0, n**3, rng.integers(0, 300)))
            c.add_sorted_keys(keys)
            expected = np.union1d(expected, keys)
            np.testing.assert_array_equal(c.keys, expected)
        wdt_keys = np.sort(np.concatenate([rng.choice(c.keys, min(len(c.keys), 50)) if len(c.keys) else
                                           np.zeros(0, np.int64), rng.integers(0, n**3, 30)]))
        hidden = rng.random(n) < 0.2
        faces, keys = c.off_wdt(wdt_keys, hidden)
        want = np.setdiff1d(c.keys, wdt_keys)
        tri = c.faces_of(want)
        want = want[~hidden[tri].any(1)]
        np.testing.assert_array_equal(keys, want)
        np.testing.assert_array_equal(faces, c.faces_of(want))


def test_the_native_key_merges_refuse_unsorted_input():
    from dmesh import native

    with pytest.raises(ValueError, match="a must be sorted and unique"):
        native.union_sorted_keys(np.array([3, 1]), np.array([2]))
    with pytest.raises(ValueError, match="b must be sorted and unique"):
        native.union_sorted_keys(np.array([1, 3]), np.array([2, 2]))
    with pytest.raises(ValueError, match="wdt must be sorted"):
        native.off_wdt_candidates(np.array([1, 2]), np.array([5, 4]), np.zeros(3, bool))
    with pytest.raises(ValueError, match="hidden covers 4 points, the candidates 5"):
        CandidateFaces(5).off_wdt(np.zeros(0, np.int64), np.zeros(4, bool))
    with pytest.raises(ValueError, match=r"\[0, n\^3\)"):
        native.off_wdt_candidates(np.array([1, 27]), np.array([5]), np.zeros(3, bool))
