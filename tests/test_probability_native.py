"""Fused native Delta kernels (native/src/delta_recompute.h) against finite differences, against the torch
reference (dmesh.reference.probability) and across thread counts."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dmesh import native, probability, wdt
from dmesh.candidates import knn_triples
from conftest import spacing_weights

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


def _leaves(p, w):
    return torch.tensor(p, requires_grad=True), torch.tensor(w, requires_grad=True)


def test_existing_deltas_gradcheck_including_hull_rays():
    p, w, pd = _config(24, seed=1)
    assert pd.is_hull.sum() >= 4 and (~pd.is_hull).sum() >= 4
    hull = np.flatnonzero(pd.is_hull)[:6]
    inner = np.flatnonzero(~pd.is_hull)[:10]
    ids = np.concatenate([hull, inner])
    pt, wt = _leaves(p, w)

    def f(pp, ww):
        return probability.existing_deltas(pp, ww, pd, pd.point_neighbors, RAY, face_ids=ids)

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
    pt, wt = _leaves(p, w)

    def f(pp, ww):
        return probability.nonexisting_deltas(pp, ww, pd, sub, RAY)

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
    for impl in probability.IMPLS:
        pt, wt = _leaves(p, w)
        e = probability.existing_deltas(pt, wt, pd, pd.point_neighbors, 500.0, upper=band, impl=impl)
        c = probability.nonexisting_deltas(pt, wt, pd, cand, 500.0, band=band, impl=impl)
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
    pt, wt = _leaves(p, w)
    # An empty neighbour cache: no plane for any vertex, value ray_length and no gradient.
    empty = wdt.Csr(np.zeros(len(p) + 1, np.int32), np.zeros(0, np.int32))
    d = probability.existing_deltas(pt, wt, pd, empty, 7.0)
    assert (d == 7.0).all()
    d.sum().backward()
    assert not pt.grad.any() and not wt.grad.any()
    # upper below every Delta: every row inactive.
    pt.grad = wt.grad = None
    d = probability.existing_deltas(pt, wt, pd, pd.point_neighbors, 7.0, upper=0.0)
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


def test_face_probabilities_agree_between_impls():
    rng = np.random.default_rng(14)
    n = 800
    pts, w, r = rng.random((n, 3)), spacing_weights(rng, n), rng.random(n)
    import dmesh

    fps = {}
    for impl in probability.IMPLS:
        dm = dmesh.DMesh(pts, w, r, config=probability.ProbabilityConfig(impl=impl), dtype=torch.float64)
        fp = dm.face_probabilities()
        (fp.prob * torch.linspace(0, 1, len(fp.prob), dtype=torch.float64)).sum().backward()
        fps[impl] = (fp, [t.grad for t in dm.parameters()])
    (a, ga), (b, gb) = fps["native"], fps["reference"]
    assert torch.equal(a.faces, b.faces)
    for x, y in [(a.delta, b.delta), (a.prob, b.prob), *zip(ga, gb)]:
        assert torch.allclose(x, y, rtol=1e-9, atol=1e-9 * y.abs().max().item())


def _pair(n: int, seed: int, every: int):
    """Two DMesh over the same float64 points: full search every pass, and every `every` passes."""
    import dmesh

    rng = np.random.default_rng(seed)
    p, w, r = rng.random((n, 3)), spacing_weights(rng, n), rng.random(n)
    return [dmesh.DMesh(p.copy(), w.copy(), r.copy(), config=probability.ProbabilityConfig(full_search_every=k),
                        dtype=torch.float64) for k in (1, every)]


def test_coherent_pass_matches_a_full_search_under_tiny_moves_and_searches_every_k():
    full, coherent = _pair(600, 15, every=3)
    moves = torch.randn(5, 600, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ages = []
    for move in moves:
        a, b = full.face_probabilities(), coherent.face_probabilities()
        ages.append(coherent.state.coherence.age)
        assert torch.equal(a.faces, b.faces)
        # A move of 1e-9 keeps every argmin except at ties closer than ~1e-9, where the distances agree
        # to that order: the reused argmins give the full search's Delta.
        assert (a.delta - b.delta).abs().max() < 1e-7
        for dm in (full, coherent):
            with torch.no_grad():
                dm.points += 1e-9 * move
    assert ages == [0, 1, 2, 0, 1]


def test_coherent_pass_searches_around_a_point_whose_neighbours_changed():
    full, coherent = _pair(600, 16, every=10)
    for dm in (full, coherent):
        dm.face_probabilities()
        with torch.no_grad():
            dm.points[7] += torch.tensor([0.04, -0.03, 0.02], dtype=torch.float64)   # changes its star
    a, b = full.face_probabilities(), coherent.face_probabilities()
    assert coherent.state.coherence.age == 1 and torch.equal(a.faces, b.faces)
    around = (a.faces == 7).any(1)
    assert around.sum() > 10
    assert torch.allclose(a.delta[around], b.delta[around], rtol=0, atol=1e-12)


def test_orthocentres_gradcheck():
    p, w, pd = _config(24, seed=1)
    pt, wt = _leaves(p, w)

    def f(pp, ww):  # a fresh handle per call: its forward returns the orthocentres it computed
        return probability.orthocentres(pp, ww, probability.delta_diagram(pp, ww, pd))

    assert torch.autograd.gradcheck(f, (pt, wt), nondet_tol=0.0)


def test_weight_regularizer_native_matches_the_torch_reference():
    from dmesh.losses.regularizers import weight_regularizer

    rng = np.random.default_rng(3)
    n = 2000
    p = rng.random((n, 3))
    w = spacing_weights(rng, n, scale=0.1)
    pd = wdt.PowerDiagram.from_points(p, w)
    out = []
    for native_impl in (True, False):
        pt, wt = _leaves(p, w)
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
