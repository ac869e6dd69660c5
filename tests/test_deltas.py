"""Per-vertex distances (`dmesh.deltas`): the fused native Delta kernels (native/src/delta_recompute.h)
against finite differences, against the torch reference (dmesh.reference.probability) and across thread
counts."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dmesh import deltas, native, probability, wdt
from dmesh.candidates import knn_triples
from common import leaves, spacing_weights


# A short ray keeps hull-face values O(1), so gradcheck's default tolerances apply to them as to the rest.
RAY = 3.0


def _config(n: int, seed: int, scale: float = 0.5):
    rng = np.random.default_rng(seed)
    p = rng.random((n, 3))
    w = spacing_weights(rng, n, scale=scale)
    pd = wdt.PowerDiagram.from_points(p, w)
    return p, w, pd


def _candidates(p: np.ndarray, pd: wdt.PowerDiagram) -> np.ndarray:
    """kNN triples that are not WDT faces and whose vertices own cells, as int32."""
    faces = np.unique(knn_triples(p, None, ~pd.hidden, k=6), axis=0)
    faces = faces[(pd.face_ids(faces) < 0) & ~pd.hidden[faces].any(1)]
    return faces.astype(np.int32)


def test_existing_deltas_gradcheck_including_hull_rays():
    p, w, pd = _config(24, seed=1)
    assert pd.is_hull.sum() >= 4 and (~pd.is_hull).sum() >= 4
    hull = np.flatnonzero(pd.is_hull)[:6]
    inner = np.flatnonzero(~pd.is_hull)[:10]
    ids = np.concatenate([hull, inner])
    pt, wt = leaves(p, w)

    def f(pp, ww):
        return deltas.existing_deltas(pp, ww, pd, pd.point_neighbors, RAY, face_ids=ids)

    d = f(pt, wt)
    assert (d.detach() != RAY).all()  # every vertex has a plane: all 3 * K values carry a gradient
    # Central differences with eps = 1e-6 in float64 (gradcheck's default): truncation ~eps^2 and round-off
    # ~1e-16/eps, far below gradcheck's atol 1e-5 / rtol 1e-3, as long as no argmin flips within eps.
    assert torch.autograd.gradcheck(f, (pt, wt), nondet_tol=0.0)


def test_candidate_deltas_gradcheck_including_nearest_rays():
    p, w, pd = _config(30, seed=4)
    cand = _candidates(p, pd)
    diagram = native.delta_diagram(pd.points, pd.weights, pd)
    edge, crosses, dist = native.candidate_delta_forward(diagram, cand, RAY)
    scored = (edge >= 0) & (crosses == 0)
    ray_rows = np.flatnonzero((scored & pd.is_hull[np.maximum(edge, 0)]).any(1))
    seg_rows = np.flatnonzero((scored & ~pd.is_hull[np.maximum(edge, 0)]).any(1))
    assert len(ray_rows) >= 2 and len(seg_rows) >= 2
    rows = np.concatenate([ray_rows[:6], seg_rows[:6]])
    sub = cand[rows]
    pt, wt = leaves(p, w)

    def f(pp, ww):
        return deltas.nonexisting_deltas(pp, ww, pd, sub, RAY)

    # Same tolerances as above; the crossing test and the edge search are discrete and stay fixed within eps
    # on this seed (the forward searches again at every perturbed point).
    assert torch.autograd.gradcheck(f, (pt, wt), nondet_tol=0.0)


@pytest.mark.parametrize("band", [None, 0.02])
def test_native_matches_the_torch_reference(band):
    n = 2500
    p, w, pd = _config(n, seed=7, scale=0.1)
    cand = _candidates(p, pd)
    rng = np.random.default_rng(8)
    up_e = torch.from_numpy(rng.random((len(pd.faces), 3)))
    up_c = torch.from_numpy(rng.random((len(cand), 3)))
    out = {}
    for impl in deltas.IMPLS:
        pt, wt = leaves(p, w)
        e = deltas.existing_deltas(pt, wt, pd, pd.point_neighbors, 500.0, upper=band, impl=impl)
        c = deltas.nonexisting_deltas(pt, wt, pd, cand, 500.0, band=band, impl=impl)
        ((e * up_e).sum() + (c * up_c).sum()).backward()
        out[impl] = [e.detach(), c.detach(), pt.grad, wt.grad]
    # Same formulas in a different evaluation order: agreement to round-off (~1e-13 relative to the largest
    # entry is observed); 1e-6 relative leaves room for a rare argmin tie broken the other way, which gives
    # the same distance.
    for name, a, b in zip(["existing", "candidates", "d/dpoints", "d/dweights"], out["native"], out["reference"]):
        scale = b.abs().max().item()
        worst = (a - b).abs().max().item()
        assert worst <= 1e-6 * scale, f"{name}: max abs diff {worst:.3g} against scale {scale:.3g}"
    assert (out["native"][2] != 0).any()


def test_backward_is_bitwise_identical_on_one_and_two_threads():
    p, w, pd = _config(1500, seed=9, scale=0.1)
    cand = _candidates(p, pd)
    ids = np.arange(len(pd.faces), dtype=np.int32)
    rng = np.random.default_rng(10)
    results = []
    for threads in (1, 2, 3):
        diagram = native.delta_diagram(pd.points, pd.weights, pd, num_threads=threads)
        j, de = native.existing_delta_forward(diagram, ids, pd.point_neighbors.offsets,
                                              pd.point_neighbors.indices, 500.0, num_threads=threads)
        edge, crosses, dc = native.candidate_delta_forward(diagram, cand, 500.0, num_threads=threads)
        ge = rng.random(de.shape) if threads == 1 else results[0][-1][0]
        gc = rng.random(dc.shape) if threads == 1 else results[0][-1][1]
        be = native.existing_delta_backward(diagram, ids, j, ge, None, 500.0, num_threads=threads)
        bc = native.candidate_delta_backward(diagram, cand, edge, crosses, gc, None, num_threads=threads)
        results.append([diagram.orthocentres, j, de, edge, crosses, dc, *be, *bc, (ge, gc)])
    for other in results[1:]:
        for a, b in zip(results[0][:-1], other[:-1]):
            assert np.array_equal(a, b)


def test_inactive_rows_and_missing_neighbours_get_no_gradient():
    p, w, pd = _config(200, seed=12)
    pt, wt = leaves(p, w)
    # An empty neighbour cache: no plane for any vertex, value ray_length and no gradient.
    empty = wdt.Csr(np.zeros(len(p) + 1, np.int32), np.zeros(0, np.int32))
    d = deltas.existing_deltas(pt, wt, pd, empty, 7.0)
    assert (d == 7.0).all()
    d.sum().backward()
    assert not pt.grad.any() and not wt.grad.any()
    # upper below every Delta: every row inactive.
    pt.grad = wt.grad = None
    d = deltas.existing_deltas(pt, wt, pd, pd.point_neighbors, 7.0, upper=0.0)
    d.sum().backward()
    assert not pt.grad.any() and not wt.grad.any()


def test_native_kernels_validate_their_inputs():
    p, w, pd = _config(50, seed=13)
    ids = np.arange(len(pd.faces), dtype=np.int32)
    nb = pd.point_neighbors
    diagram = native.delta_diagram(pd.points, pd.weights, pd)
    with pytest.raises(ValueError, match="face_ids"):
        native.existing_delta_forward(diagram, ids + len(pd.faces), nb.offsets, nb.indices, 1.0)
    with pytest.raises(ValueError, match="cand"):
        native.candidate_delta_forward(diagram, np.array([[0, 1, 99]], np.int32), 1.0)
    with pytest.raises(ValueError, match="weights"):
        native.delta_diagram(pd.points, pd.weights[:-1], pd)
    with pytest.raises(ValueError, match="tets"):
        bad = wdt.PowerDiagram.from_points(p, w)
        bad.tets = bad.tets.copy()
        bad.tets[3, 1] = len(p)
        native.delta_diagram(pd.points, pd.weights, bad)
    with pytest.raises(ValueError, match="impl"):
        probability.ProbabilityConfig(impl="cuda")


def test_orthocentres_gradcheck():
    p, w, pd = _config(24, seed=1)
    pt, wt = leaves(p, w)

    def f(pp, ww):  # a fresh handle per call: its forward returns the orthocentres it computed
        return deltas.orthocentres(pp, ww, deltas.delta_diagram(pp, ww, pd))

    assert torch.autograd.gradcheck(f, (pt, wt), nondet_tol=0.0)


def test_neighbour_rows_are_exact_where_the_power_diagram_runs_in_parallel():
    # Above native kParallelMin (20000) points the power diagram builds its neighbour rows (which the Delta
    # kernels' half-spaces and the neighbour cache read) on several threads, each with its own marks for
    # dropping repeats (kept across calls): every row must be the sorted set of the point's tet mates, also
    # on a second diagram of the same points.
    p, w, pd = _config(21000, seed=16, scale=0.1)
    pd = wdt.PowerDiagram(p, w, pd.tets, pd.neighbors)
    t = pd.tets.astype(np.int64)
    pairs = np.concatenate([t[:, [a, b]] for a in range(4) for b in range(4) if a != b])
    pairs = np.unique(pairs, axis=0)  # rows ascending, then neighbours ascending
    nb = pd.point_neighbors
    assert np.array_equal(nb.offsets, np.concatenate([[0], np.cumsum(np.bincount(pairs[:, 0], minlength=len(p)))]))
    assert np.array_equal(nb.indices, pairs[:, 1])
