"""Face existence probabilities (`dmesh.probability`): sign against an independent triangulation, gradients
against finite differences, degenerate candidates, the line-crosses-cell case, probability ranges, native
against reference, and the coherent pass against a full search."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import dmesh
from dmesh import native, probability, wdt
from dmesh.candidates import knn_triples
from dmesh.reference import probability as ref_prob
from dmesh.reference import wdt as ref_wdt
from common import spacing_weights


def oracle_faces(points, weights) -> set:
    """Faces of the WDT computed independently (gudhi; SciPy's lifted hull when gudhi is missing)."""
    try:
        tets = ref_wdt.gudhi_tets(points, weights)
    except ImportError:
        tets = ref_wdt.lifted_hull_tets(points, weights)
    faces = np.sort(np.concatenate([np.delete(tets, k, axis=1) for k in range(4)]), axis=1)
    return {tuple(f) for f in faces.tolist()}


@pytest.mark.parametrize("n, seed", [(200, 0), (700, 1), (2000, 2)])
def test_sign_of_delta_matches_an_independent_triangulation(n, seed):
    rng = np.random.default_rng(seed)
    p = rng.random((n, 3))
    w = spacing_weights(rng, n, scale=0.5)
    pd = wdt.PowerDiagram.from_points(p, w)
    faces = np.unique(np.concatenate([pd.faces, knn_triples(p, None, ~pd.hidden)]), axis=0)
    d = probability.delta(torch.from_numpy(p), torch.from_numpy(w), faces).numpy()
    truth = oracle_faces(p, w)
    in_truth = np.array([tuple(f) in truth for f in faces.tolist()])
    # Non-degenerate faces only: |Delta| above round-off (a face can be exactly on the fence).
    clear = np.abs(d) > 1e-9
    assert clear.mean() > 0.99
    assert in_truth.sum() > 0 and (~in_truth).sum() > 0
    np.testing.assert_array_equal(d[clear] > 0, in_truth[clear])
    assert np.isfinite(d).all()


def _small_config(seed=3, n=40):
    rng = np.random.default_rng(seed)
    p = rng.random((n, 3))
    w = spacing_weights(rng, n, scale=0.5)
    return p, w


def test_delta_gradients_match_central_finite_differences():
    p, w = _small_config()
    pd = wdt.PowerDiagram.from_points(p, w)
    faces = np.unique(np.concatenate([pd.faces[~pd.is_hull][::3], knn_triples(p, None)[::5]]), axis=0)
    pt = torch.tensor(p, requires_grad=True)
    wt = torch.tensor(w, requires_grad=True)

    def f(pp, ww):
        return probability.delta(pp, ww, faces)

    # Central differences with h = 1e-7 in float64: truncation ~h^2 and round-off ~1e-16/h, so agreement
    # to ~1e-6 relative is expected where the combinatorics do not change inside +-h.
    assert torch.autograd.gradcheck(f, (pt, wt), eps=1e-7, atol=1e-5, rtol=1e-4, nondet_tol=0.0)


def test_probability_gradients_match_finite_differences_with_fixed_state():
    p, w = _small_config(seed=5, n=60)
    r = np.random.default_rng(5).random(60)
    # active_band=None: every face carries its exact gradient (the default drops the gradient of faces with
    # Lambda_wdt < sigmoid(-10), an approximation this test would see).
    cfg = probability.ProbabilityConfig(active_band=None)
    dm = dmesh.DMesh(p, w, r, config=cfg, dtype=torch.float64)
    base = dm.face_probabilities()  # fills the phase's candidates and cache
    upstream = torch.from_numpy(np.random.default_rng(0).random(len(base.prob)))

    def loss():
        fp = dm.face_probabilities()
        assert torch.equal(fp.faces, base.faces)  # same combinatorics
        return (fp.prob * upstream).sum()

    loss().backward()
    grads = [dm.points.grad.clone(), dm.weights.grad.clone()]
    h = 1e-7
    rng = np.random.default_rng(1)
    # Reals are left out: Lambda_real's softmin weights are detached by design (as upstream), so its
    # gradient is not the finite difference of the forward value; it is checked against its formula below.
    for param, grad in zip([dm.points, dm.weights], grads):
        flat = param.data.view(-1)
        for k in rng.choice(len(flat), 6, replace=False):
            old = flat[k].item()
            with torch.no_grad():
                flat[k] = old + h
                up = loss().item()
                flat[k] = old - h
                down = loss().item()
                flat[k] = old
            fd = (up - down) / (2 * h)
            assert fd == pytest.approx(grad.view(-1)[k].item(), rel=1e-3, abs=1e-4)
    r = dm.reals.detach()[base.faces]
    wts = torch.softmax(-dm.config.alpha_real * r, dim=-1)
    expect = torch.zeros(len(dm), dtype=torch.float64).index_add_(0, base.faces.reshape(-1),
                                            (wts * (upstream * base.prob_wdt.detach())[:, None]).reshape(-1))
    assert torch.allclose(dm.reals.grad, expect.to(dm.reals.grad.dtype), rtol=1e-9, atol=1e-12)


def test_degenerate_candidates_give_finite_values_and_gradients():
    rng = np.random.default_rng(7)
    p = rng.random((60, 3))
    p[1] = p[0]                                   # coincident pair (1 is merged into 0: hidden)
    p[3] = 0.5 * (p[2] + p[4])                    # collinear triple 2-3-4
    p[6] = 0.5 * (p[5] + p[7]) + 1e-9             # nearly collinear triple 5-6-7
    faces = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7], [0, 2, 5], [8, 9, 10]])
    pt = torch.tensor(p, requires_grad=True)
    wt = torch.zeros(60, dtype=torch.float64, requires_grad=True)
    d = probability.delta(pt, wt, faces)
    assert torch.isfinite(d).all()
    assert d[0] == 0                               # a hidden vertex: scored 0
    assert d[1] < 0                                # collinear: never a face
    d.sum().backward()
    assert torch.isfinite(pt.grad).all() and torch.isfinite(wt.grad).all()
    dm = dmesh.DMesh(p, reals=rng.random(60), dtype=torch.float64)
    fp = dm.face_probabilities(extra_candidates=faces)
    assert torch.isfinite(fp.prob).all()
    fp.prob.sum().backward()
    assert all(torch.isfinite(t.grad).all() for t in dm.parameters())


def test_a_line_through_the_cell_gives_distance_zero_and_others_match_a_reference():
    rng = np.random.default_rng(11)
    p = rng.random((300, 3))
    w = np.zeros(300)
    pd = wdt.PowerDiagram.from_points(p, w)
    start, end = pd.dual_edges(ray_length=1.0)
    interior = [i for i in range(300) if not pd.is_hull[pd.point_faces.row(i)].any()][:20]
    assert len(interior) >= 10
    for i in interior:
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        for offset in (0.0, 0.02, 0.2):  # through p_i (inside its Voronoi cell), then further away
            side = np.cross(u, rng.normal(size=3))
            side /= np.linalg.norm(side)
            o = p[i] + offset * side
            edge, crosses, dist = native.nearest_cell_edges_raw(
                pd.points, pd.weights, np.array([[i, i, i]], np.int32), o[None], u[None],
                pd.point_faces.offsets, pd.point_faces.indices, start, np.where(pd.is_hull[:, None], pd.ray_dirs, end),
                pd.is_hull.astype(np.uint8), pd.point_neighbors.offsets, pd.point_neighbors.indices)
            cell = pd.orthocentres[pd.point_tets.row(i)]
            want = ref_prob.line_cell_distance(o, u, cell)
            if crosses[0, 0]:
                got = 0.0
            else:
                g = edge[0, 0]
                assert g >= 0  # never -1 for a point with a cell
                from dmesh import geometry

                got = geometry.line_segment_distance(torch.from_numpy(o), torch.from_numpy(u),
                                                     torch.from_numpy(start[g]), torch.from_numpy(end[g]),
                                                     torch.tensor(False)).item()
            if offset == 0.0:
                assert crosses[0, 0] == 1 and want == 0.0
            assert got == pytest.approx(want, abs=1e-9)
            assert dist[0, 0] == pytest.approx(want, abs=1e-9)


def test_probabilities_lie_in_unit_interval_and_hull_faces_saturate():
    rng = np.random.default_rng(13)
    n = 500
    dm = dmesh.DMesh(rng.random((n, 3)), spacing_weights(rng, n), rng.random(n))
    fp = dm.face_probabilities()
    for t in (fp.prob, fp.prob_wdt, fp.prob_real):
        assert ((t >= 0) & (t <= 1)).all()
    hull = np.flatnonzero(fp.power_diagram.is_hull)
    # Hull faces sample their dual ray 500 units out: Delta is clamped and Lambda_wdt = sigmoid(10).
    assert torch.allclose(fp.prob_wdt[hull], torch.sigmoid(torch.tensor(10.0)), atol=1e-6)
    assert (fp.prob_wdt[fp.in_wdt] >= 0.5).all() and (fp.prob_wdt[~fp.in_wdt] <= 0.5).all()
    # Lambda_real is (close to) the minimum real value of the face.
    rmin = dm.reals.detach()[fp.faces].min(1).values
    assert torch.allclose(fp.prob_real, rmin, atol=0.05)


def test_power_cell_factor_flag():
    rng = np.random.default_rng(17)
    n = 300
    pts, w, r = rng.random((n, 3)), spacing_weights(rng, n), rng.random(n)
    plain = dmesh.DMesh(pts, w, r).face_probabilities()
    cfg = probability.ProbabilityConfig(power_cell_factor=True)
    with_pc = dmesh.DMesh(pts, w, r, config=cfg).face_probabilities()
    assert torch.equal(plain.faces, with_pc.faces)
    assert (with_pc.prob_wdt <= plain.prob_wdt + 1e-7).all()
    assert torch.allclose(with_pc.prob_wdt[plain.in_wdt], plain.prob_wdt[plain.in_wdt], atol=1e-3)


# -------------------------------------------------------------- native against reference, coherent pass

def _both_impls(seed: int, n: int, outputs=("prob",)) -> dict:
    """impl -> (FaceProbabilities, gradients of points, weights, reals) of one random DMesh, the loss a ramp-
    weighted sum of the named outputs (a gradient nothing reaches is zeros)."""
    import dmesh

    rng = np.random.default_rng(seed)
    pts, w, r = rng.random((n, 3)), spacing_weights(rng, n), rng.random(n)
    out = {}
    for impl in probability.IMPLS:
        dm = dmesh.DMesh(pts, w, r, config=probability.ProbabilityConfig(impl=impl), dtype=torch.float64)
        fp = dm.face_probabilities()
        up = torch.linspace(0, 1, len(fp.prob), dtype=torch.float64)
        sum((getattr(fp, name) * up).sum() for name in outputs).backward()
        out[impl] = (fp, [torch.zeros_like(t) if t.grad is None else t.grad for t in dm.parameters()])
    return out


def _close(x, y):
    assert torch.allclose(x, y, rtol=1e-9, atol=1e-9 * y.abs().max().item())


def test_face_probabilities_agree_between_impls():
    fps = _both_impls(14, 800)
    (a, ga), (b, gb) = fps["native"], fps["reference"]
    assert torch.equal(a.faces, b.faces)
    for x, y in [(a.delta, b.delta), (a.prob, b.prob), *zip(ga, gb)]:
        _close(x, y)


@pytest.mark.parametrize("outputs", [("delta",), ("prob_wdt",), ("prob_real",), ("delta", "prob"),
                                     ("prob_wdt", "prob_real", "prob")])
def test_gradients_through_any_outputs_agree_between_impls(outputs):
    # The native Lambda's backward skips the outputs nothing differentiates (their gradient arrives as None);
    # each subset must still give the reference's gradients.
    grads = {impl: g for impl, (_, g) in _both_impls(15, 300, outputs).items()}
    for x, y in zip(grads["native"], grads["reference"]):
        _close(x, y)
    assert any(g.abs().max() > 0 for g in grads["native"])


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
