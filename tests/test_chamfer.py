"""Expected Chamfer (`dmesh.losses.chamfer`): by hand, adaptive K, the normal term, face sampling; the native
kernel (native/src/expected_chamfer.h) against the torch reference (dmesh.reference.chamfer), finite
differences, SciPy's cKDTree and itself on other thread counts. Letters: G target points, S samples, K
candidates per target row.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from dmesh import native
from dmesh.losses.chamfer import (IMPLS, ExpectedChamfer, SurfaceSamples, chamfer_l1, expected_distance,
                                  expected_min_distance, first_occurrence, sample_faces)
from dmesh.reference.chamfer import target_term
from common import assert_close


def _sphere(rng, n: int) -> np.ndarray:
    x = rng.standard_normal((n, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _problem(rng, G: int, S: int, K: int, faces: int, p_range=(0.01, 0.99)):
    """Target and samples on the unit sphere, random face ids in [0, faces), knn rows from cKDTree."""
    target = _sphere(rng, G)
    pts = torch.tensor(_sphere(rng, S), requires_grad=True)
    prob = torch.tensor(rng.uniform(*p_range, S), requires_grad=True)
    face = torch.from_numpy(rng.integers(0, faces, S))
    _, knn = cKDTree(pts.detach().numpy()).query(target, K)
    return target, pts, prob, face, torch.from_numpy(np.asarray(knn, np.int64).reshape(G, K))


def _grads(expected, pts, prob, w):
    pts.grad = prob.grad = None
    (expected * w).sum().backward()
    return pts.grad.clone(), prob.grad.clone()


# ------------------------------------------------------------------------------- kernel vs reference

@pytest.mark.parametrize("case", ["plain", "repeated_faces", "p_near_0_and_1", "k_above_distinct_faces"])
def test_gradcheck_native(case):
    rng = np.random.default_rng(7)
    G, S, K = 5, 9, 6
    faces = {"plain": 1000, "repeated_faces": 4, "p_near_0_and_1": 1000, "k_above_distinct_faces": 2}[case]
    target, pts, prob, face, knn = _problem(rng, G, S, K, faces)
    if case == "p_near_0_and_1":
        prob = torch.tensor(rng.choice([1e-7, 1.0 - 1e-7, 0.5], S), requires_grad=True)
    if case == "repeated_faces":
        face[knn[0, :3]] = 3  # three candidates of row 0 on one face: the last two are masked
    t = torch.from_numpy(target)
    # gradcheck's float64 central differences (eps 1e-6) against the analytic backward; the loss is smooth
    # in the positions (no candidate at distance 0) and polynomial in the probabilities.
    assert torch.autograd.gradcheck(lambda x, p: expected_distance(t, x, p, face, knn)[0], (pts, prob))


def test_by_hand():
    pts = torch.tensor([[1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]], dtype=torch.float64, requires_grad=True)
    prob = torch.tensor([0.5, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    e, r = expected_distance(np.zeros((1, 3)), pts, prob, [7, 7, 2], [[0, 1, 2]])
    assert e.item() == pytest.approx(0.5 * 1 + 0.5 * 3)  # the second sample repeats face 7: masked
    assert r.item() == 0.0 and not r.requires_grad
    e.sum().backward()
    # dE/dp = B_i (d_i - T_{i+1}): p_0: 1 * (1 - 3) = -2, p_1 masked: 0, p_2: 0.5 * 3.
    assert prob.grad.tolist() == pytest.approx([-2.0, 0.0, 1.5])
    assert pts.grad[:, 0].tolist() == pytest.approx([0.5, 0.0, 0.5])


def test_matches_reference_large():
    rng = np.random.default_rng(11)
    G = S = 20_000
    target, pts, prob, face, knn = _problem(rng, G, S, 60, faces=2 * S)
    face[rng.integers(0, S, S // 10)] = 17  # a face with many samples: masks in many rows
    w = torch.from_numpy(rng.standard_normal(G))
    e_ref, r_ref = target_term(torch.from_numpy(target), pts, prob, face, knn)
    g_ref = _grads(e_ref, pts, prob, w)
    e, r = expected_distance(target, pts, prob, face, knn, num_threads=2)
    g = _grads(e, pts, prob, w)
    # Both are float64 with the same operations up to summation order: measured max diffs ~1e-16 relative to
    # the largest value; 1e-6 leaves room for other compilers and BLAS-free torch reductions.
    assert_close(e, e_ref, 1e-6, what="expected")
    assert_close(r, r_ref, 1e-6, what="residual")
    assert_close(g[0], g_ref[0], 1e-6, what="grad points")
    assert_close(g[1], g_ref[1], 1e-6, what="grad prob")


def test_float32_within_tolerance():
    rng = np.random.default_rng(3)
    target, pts, prob, face, knn = _problem(rng, 5000, 5000, 40, faces=10_000)
    w = torch.ones(5000, dtype=torch.float64)
    e64, _ = expected_distance(target, pts, prob, face, knn)
    g64 = _grads(e64, pts, prob, w)
    e32, _ = expected_distance(target, pts, prob, face, knn, dtype=torch.float32)
    g32 = _grads(e32, pts, prob, w)
    # float32 coordinates round x - t to ~1e-7 absolute, so the directions (x - t) / d of candidates ~1e-2
    # apart carry ~1e-5 relative error. Measured at this size, relative to the largest value: loss 1.4e-9,
    # position gradients 8.6e-6, probability gradients 6.4e-7 (paper size: about 4e-4 for positions).
    assert abs(e32.mean().item() / e64.mean().item() - 1) < 1e-5
    assert_close(g32[0], g64[0], 1e-3, what="grad points float32")
    assert_close(g32[1], g64[1], 1e-4, what="grad prob float32")


def test_sparse_face_ids_and_edge_sizes(rng):
    target, pts, prob, face, knn = _problem(rng, 50, 40, 10, faces=8)
    e, r = expected_distance(target, pts, prob, face, knn)
    e_big, r_big = expected_distance(target, pts, prob, face * 200_000_000 + 5, knn)  # ranked, not indexed
    assert torch.equal(e, e_big) and torch.equal(r, r_big)
    e0, r0 = expected_distance(target, pts, prob, face, knn[:, :0])  # K = 0: nothing exists
    assert (e0 == 0).all() and (r0 == 1).all()
    e1, _ = expected_distance(target[:0], pts, prob, face, knn[:0])
    assert e1.shape == (0,)


def test_bad_input_names_the_argument(rng):
    target, pts, prob, face, knn = _problem(rng, 10, 12, 4, faces=20)
    with pytest.raises(ValueError, match="knn holds a sample id outside"):
        expected_distance(target, pts, prob, face, knn + 12)
    with pytest.raises(ValueError, match="prob must have shape"):
        expected_distance(target, pts, prob[:5], face, knn)
    with pytest.raises(ValueError, match="face ids must"):
        expected_distance(target, pts, prob, face - 100, knn)
    with pytest.raises(ValueError, match="knn must have shape"):
        expected_distance(target, pts, prob, face, knn[:3])
    with pytest.raises(ValueError, match="k must be in"):
        native.knn_search(pts, target, 13)


# ------------------------------------------------------------------------------------- determinism

def test_byte_identical_on_any_thread_count():
    rng = np.random.default_rng(5)
    target, pts, prob, face, knn = _problem(rng, 4000, 3000, 30, faces=3000)  # 120K candidates: threaded
    tn, pn, qn = target, pts.detach().numpy(), prob.detach().numpy()
    w = rng.standard_normal(4000)
    out = []
    for threads in (1, 2, 3):
        fwd = native.expected_chamfer_forward(tn, pn, qn, face, knn, threads)
        bwd = native.expected_chamfer_backward(tn, pn, qn, face, knn, w, threads)
        ids = native.knn_search(pn, tn, 30, threads)
        out.append(b"".join(a.tobytes() for a in (*fwd, *bwd, ids)))
    assert out[0] == out[1] == out[2]
    grads = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        try:
            grads.append(_grads(expected_distance(target, pts, prob, face, knn)[0], pts, prob, torch.from_numpy(w)))
        finally:
            torch.set_num_threads(2)
    assert all(torch.equal(a, b) for a, b in zip(*grads))


# --------------------------------------------------------------------------------------------- kNN

@pytest.mark.parametrize("kind,k", list(itertools.product(["surface", "cluster_far", "grid_ties"], [1, 7, 50])))
def test_knn_matches_cKDTree(kind, k):
    rng = np.random.default_rng(2)
    if kind == "surface":
        data, queries = _sphere(rng, 3000), _sphere(rng, 2000)
    elif kind == "cluster_far":  # data in a small blob, queries far away and spread out
        data, queries = 0.01 * rng.standard_normal((500, 3)), 5 * rng.standard_normal((300, 3))
    else:  # a coarse grid with duplicates: many equal distances, broken by the smaller id
        g = np.stack(np.meshgrid(*[np.arange(5.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
        data, queries = np.concatenate([g, g[:40]]), rng.integers(0, 5, (200, 3)) + 0.5 * rng.random((200, 3))
    ids = native.knn_search(data, queries, k)
    assert ids.dtype == np.int32 and ids.shape == (len(queries), k)
    d = np.linalg.norm(queries[:, None, :] - data[ids], axis=-1)
    dist, ref = cKDTree(data).query(queries, k)
    dist = dist.reshape(len(queries), k)
    assert_close(d, dist, 1e-12, what="knn distances")
    # Exact ranking by (distance, id): nearest first, ties to the smaller id.
    d2 = ((queries[:, None, :] - data[ids]) ** 2).sum(-1)
    assert ((d2[:, 1:] > d2[:, :-1]) | ((d2[:, 1:] == d2[:, :-1]) & (ids[:, 1:] > ids[:, :-1]))).all()
    if kind != "grid_ties":
        assert np.array_equal(ids, np.asarray(ref).reshape(len(queries), k))


@pytest.mark.parametrize("kind,k,leaves", [("surface", 1, (8, 16)), ("surface", 30, (16, 8)),
                                            ("cluster_far", 7, (3, 40)), ("grid_ties", 50, (1, 8))])
def test_knn_of_built_trees_matches_knn_search(kind, k, leaves):
    """Trees built once (`point_tree`) and searched either way give knn_search's ids, whatever their leaves."""
    rng = np.random.default_rng(3)
    if kind == "surface":
        data, queries = _sphere(rng, 3000), _sphere(rng, 2000)
    elif kind == "cluster_far":
        data, queries = 0.01 * rng.standard_normal((500, 3)), 5 * rng.standard_normal((300, 3))
    else:
        g = np.stack(np.meshgrid(*[np.arange(5.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
        data, queries = np.concatenate([g, g[:40]]), rng.integers(0, 5, (200, 3)) + 0.5 * rng.random((200, 3))
    dt, qt = native.point_tree(data, leaves[0]), native.point_tree(queries, leaves[1])
    assert dt.size == len(data) and qt.size == len(queries)
    assert np.array_equal(native.knn_search_trees(dt, qt, k, 2), native.knn_search(data, queries, k, 2))
    assert np.array_equal(native.knn_search_trees(qt, dt, 1, 1), native.knn_search(queries, data, 1, 1))
    with pytest.raises(ValueError, match="k must be in"):
        native.knn_search_trees(qt, dt, len(queries) + 1)
    with pytest.raises(ValueError, match="not finite"):
        native.point_tree(np.array([[0.0, np.nan, 0.0]]), 8)


@pytest.mark.parametrize("normals", [False, True])
def test_rows_ending_at_minus_one_are_the_shorter_rows(rng, normals):
    """A knn row that ends early (-1 after its last candidate) gives, forward and backward, what the row
    of its candidates alone gives (per-row calls), with and without the tangent-weighted distances."""
    G, S, K = 30, 200, 12
    target, pts, prob, face, knn = _problem(rng, G, S, K, faces=120)
    length = rng.integers(1, K + 1, G)
    ragged = knn.clone()
    for g in range(G):
        ragged[g, length[g]:] = -1
    tn = torch.from_numpy(_sphere(rng, G)) if normals else None
    kw = dict(target_normals=tn, tangent_weight=0.5 if normals else 1.0)
    w = torch.from_numpy(rng.standard_normal(G))
    e, r = expected_distance(target, pts, prob, face, ragged, **kw)
    grads = _grads(e, pts, prob, w)
    pts.grad = prob.grad = None
    rows = []
    for g in range(G):
        kg = dict(kw, target_normals=None if tn is None else tn[g:g + 1])
        eg, rg = expected_distance(target[g:g + 1], pts, prob, face, knn[g:g + 1, :length[g]], **kg)
        rows.append((eg, rg))
        (eg * w[g]).sum().backward()
    assert_close(e, torch.cat([a for a, _ in rows]), 1e-14, what="expected")
    assert_close(r, torch.cat([b for _, b in rows]), 1e-14, what="residual")
    assert_close(grads[0], pts.grad, 1e-12, what="grad points")
    assert_close(grads[1], prob.grad, 1e-12, what="grad prob")


# ----------------------------------------------------------------------------------- ExpectedChamfer

@pytest.mark.parametrize("k_max,n_samples,k_first", [(8, 300, 16), (50, 20, 16), (4, 1, 16), (40, 300, 4)])
def test_impls_agree(rng, k_max, n_samples, k_first):
    """native and reference ExpectedChamfer give the same loss, gradients and K (K > S included; the last
    case takes its rows in two tiers)."""
    target = _sphere(rng, 400)
    pts = torch.tensor(_sphere(rng, n_samples), requires_grad=True)
    prob = torch.tensor(rng.uniform(0.05, 0.95, n_samples), requires_grad=True)
    s = SurfaceSamples(pts, torch.from_numpy(rng.integers(0, n_samples // 2 + 1, n_samples)), prob)
    res = {}
    for impl in ("reference", "native"):
        ec = ExpectedChamfer(target, k_max=k_max, impl=impl, workers=2, k_first=k_first)
        loss, fig = ec(s)
        res[impl] = (loss.detach(), *_grads(loss, pts, prob, 1.0), fig["k"], ec.k, fig["residual"])
    ref, nat = res["reference"], res["native"]
    for a, b, what in zip(nat[:3], ref[:3], ("loss", "grad points", "grad prob")):
        assert_close(a, b, 1e-9, what=what)
    assert nat[3:5] == ref[3:5] and nat[5] == pytest.approx(ref[5], rel=1e-9, abs=1e-15)


def test_normal_term_same_in_both_impls(rng):
    target = _sphere(rng, 200)
    pts = torch.tensor(_sphere(rng, 150), requires_grad=True)
    s = SurfaceSamples(pts, torch.arange(150), torch.full((150,), 0.7, dtype=torch.float64),
                       torch.from_numpy(_sphere(rng, 150)))
    losses = [ExpectedChamfer(target, target, k_max=10, lambda_normal=0.3, impl=impl)(s)[0].item()
              for impl in ("reference", "native")]
    assert losses[0] == pytest.approx(losses[1], rel=1e-12)


def test_empty_samples_and_bad_impl():
    z = torch.zeros((0, 3), dtype=torch.float64)
    loss, fig = ExpectedChamfer(np.zeros((3, 3)))(SurfaceSamples(z, torch.zeros(0, dtype=torch.long),
                                                                 torch.zeros(0, dtype=torch.float64)))
    assert fig["empty"] and loss.item() == 0.0
    with pytest.raises(ValueError, match="impl must be one of"):
        ExpectedChamfer(np.zeros((3, 3)), impl="cuda")


# ----------------------------------------------------------------------------- expected Chamfer by hand

def _samples(points, prob=None, face=None):
    pts = torch.as_tensor(points, dtype=torch.float64)
    n = len(pts)
    prob = torch.ones(n, dtype=torch.float64) if prob is None else torch.as_tensor(prob, dtype=torch.float64)
    face = torch.arange(n) if face is None else torch.as_tensor(face)
    return SurfaceSamples(pts, face, prob)


def test_expected_min_distance_by_hand():
    d = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    p = torch.tensor([[0.5, 0.5, 1.0]], dtype=torch.float64)
    e, res = expected_min_distance(d, p, torch.tensor([[0, 1, 2]]))
    assert e.item() == pytest.approx(0.5 * 1 + 0.25 * 2 + 0.25 * 3)
    assert res.item() == pytest.approx(0.0)
    # The second sample repeats the first one's face: it cannot be the nearest (at most one per face).
    e, res = expected_min_distance(d, p, torch.tensor([[7, 7, 2]]))
    assert e.item() == pytest.approx(0.5 * 1 + 0.5 * 3)
    e, res = expected_min_distance(d[:, :2], p[:, :2], torch.tensor([[0, 1]]))
    assert res.item() == pytest.approx(0.25)


def test_first_occurrence():
    ids = torch.tensor([[1, 2, 3, 2, 3, 4], [5, 5, 5, 5, 5, 5]])
    want = torch.tensor([[1, 1, 1, 0, 0, 1], [1, 0, 0, 0, 0, 0]], dtype=torch.bool)
    assert torch.equal(first_occurrence(ids), want)


def test_all_probabilities_one_is_plain_chamfer(rng):
    target = rng.random((300, 3))
    ours = rng.random((200, 3))
    ec = ExpectedChamfer(target, k_max=5)
    loss, fig = ec(_samples(ours))
    assert loss.item() == pytest.approx(chamfer_l1(target, ours), rel=1e-12)
    assert fig["residual"] == 0.0


def test_gradient_reaches_probabilities_and_positions(rng):
    target = rng.random((100, 3))
    pts = torch.tensor(rng.random((80, 3)), requires_grad=True)
    prob = torch.full((80,), 0.6, dtype=torch.float64, requires_grad=True)
    loss, _ = ExpectedChamfer(target, k_max=8)(SurfaceSamples(pts, torch.arange(80), prob))
    loss.backward()
    assert prob.grad.abs().sum() > 0 and pts.grad.abs().sum() > 0
    assert torch.isfinite(prob.grad).all() and torch.isfinite(pts.grad).all()


@pytest.mark.parametrize("impl", IMPLS)
def test_rows_that_stop_at_k_first_drop_at_most_mass_tol(rng, impl):
    """Two tiers of rows (`k_first`) against every row at K: each row drops at most `mass_tol` of probability
    beyond its neighbours, so the loss moves by at most mass_tol times the largest distance; the rows that need
    more than k_first neighbours get all K, and K adapts as with every row at K."""
    target = _sphere(rng, 500)
    n = 600
    pts = torch.tensor(_sphere(rng, n) * rng.uniform(0.95, 1.05, (n, 1)), requires_grad=True)
    p = np.where(rng.random(n) < 0.7, 0.999, rng.uniform(0.01, 0.3, n))  # most rows finish early, some do not
    prob = torch.tensor(p, requires_grad=True)
    face = torch.arange(n)
    # Rows that keep more than mass_tol beyond their 6 nearest samples (independent of the class).
    _, idx = cKDTree(pts.detach().numpy()).query(target, 6)
    first = target_term(torch.from_numpy(target), pts, prob, face, torch.from_numpy(idx), None, None, 0.0)[1]
    hard = int((first > 1e-4).sum())
    assert 0 < hard < len(target) // 2  # both tiers are used
    out = {}
    for k_first in (0, 6):
        ec = ExpectedChamfer(target, k_max=40, impl=impl, k_first=k_first, mass_tol=1e-4)
        loss, fig = ec(SurfaceSamples(pts, face, prob))
        out[k_first] = (loss.detach(), *_grads(loss, pts, prob, 1.0), fig, ec.k)
    full, tiered = out[0], out[6]
    assert abs(float(tiered[0] - full[0])) <= 1e-4 * 2.1  # distances on the unit sphere are below 2.1
    assert float(tiered[0]) != float(full[0])             # the dropped tails are not empty
    # The largest dropped mass differs (an early row drops up to mass_tol), but not on which side of mass_tol
    # it lies, so K moves the same way.
    assert (tiered[3]["residual"] > 1e-4) == (full[3]["residual"] > 1e-4)
    assert tiered[3]["residual"] <= 1e-4 or tiered[3]["residual"] == full[3]["residual"]
    assert tiered[4] == full[4] and tiered[3]["k"] == full[3]["k"]
    for a, b in zip(tiered[1:3], full[1:3]):                # gradients: positions, probabilities
        a, b = a.numpy().ravel(), b.numpy().ravel()
        assert 0 < np.linalg.norm(a - b) < 1e-2 * np.linalg.norm(b)


def test_adaptive_k():
    target = np.zeros((1, 3))
    ours = np.array([[0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]])
    ec = ExpectedChamfer(target, k_max=3)
    ec(_samples(ours, prob=[0.5, 0.5, 0.5]))            # mass 1/8 left beyond K = 3: stays at the cap
    assert ec.k == 3
    ec(_samples(ours))                                  # certain faces: no mass left, K shrinks
    assert ec.k == 2


def test_normal_term_prefers_aligned_faces():
    target = np.zeros((1, 3))
    normals = np.array([[0.0, 0.0, 1.0]])
    s = _samples([[0.1, 0, 0], [0.0, 0.1, 0]])
    s.normals = torch.tensor([[1.0, 0, 0], [0, 0, 1.0]], dtype=torch.float64)
    plain, _ = ExpectedChamfer(target, k_max=2)(s)
    with_n, _ = ExpectedChamfer(target, normals, k_max=2, lambda_normal=0.5)(s)
    assert plain.item() == pytest.approx(0.2)
    # GT side: the aligned sample (distance 0.1, no normal penalty) is the nearest; ours side: the misaligned
    # sample pays 0.5 on top of its 0.1.
    assert with_n.item() == pytest.approx(0.1 + (0.1 + 0.6) / 2)


def test_sampling_follows_strata_and_threshold(rng):
    points = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 1, 3], [1, 2, 3]])
    reals = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=torch.float64)
    pw = torch.ones(3, dtype=torch.float64)
    prob = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    s = sample_faces(points, faces, pw, reals, prob, 1000, rng)
    assert len(s) == 1000
    # Stratum min(r): only face 0; stratum max(r): all three by area (face 2 is the largest).
    assert (s.face[:500] == 0).all()
    assert set(s.face[500:].tolist()) == {0, 1, 2}
    assert s.points[:, 2].max() <= 1 and (s.points[:500, 2] == 0).all()
    none = sample_faces(points, faces, torch.zeros(3, dtype=torch.float64), reals, prob, 100, rng)
    assert len(none) == 0
    loss, fig = ExpectedChamfer(np.zeros((2, 3)))(none)
    assert fig["empty"] and loss.item() == 0.0


def test_dmesh_chamfer_gradients(rng):
    from dmesh import DMesh

    pts = rng.random((60, 3))
    dm = DMesh(pts, np.ones(60), rng.random(60))
    fp = dm.face_probabilities()
    s = sample_faces(dm.points, fp.faces, fp.prob_wdt, dm.reals, fp.prob, 2000, rng)
    loss, _ = ExpectedChamfer(rng.random((500, 3)), k_max=16)(s)
    loss.backward()
    for p in dm.parameters():
        assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_loss_floor_bench_gradient_matches_finite_differences_and_plane_has_no_floor():
    """`studies.loss_floor`'s two-sided distances: gradients against central differences; on a flat patch the
    point-to-plane distance of two independent samplings is 0 while the Euclidean one is not (the floor)."""
    from studies.loss_floor import loss_and_gradient

    rng = np.random.default_rng(0)
    t = np.c_[rng.uniform(-1, 1, (400, 2)), np.zeros(400)]
    s = np.c_[rng.uniform(-1, 1, (300, 2)), np.zeros(300)]
    n_t = np.tile([0.0, 0.0, 1.0], (400, 1))
    n_s = np.tile([0.0, 0.0, 1.0], (300, 1))
    floor_e, _ = loss_and_gradient(s, n_s, t, n_t, "euclidean")
    floor_p, _ = loss_and_gradient(s, n_s, t, n_t, "plane")
    assert floor_e > 0.02 and floor_p == 0.0
    moved = s + [0.0, 0.0, 0.01] + 1e-3 * rng.normal(size=s.shape)  # off the plane: no kink at the matches
    u = rng.normal(size=s.shape)
    u /= np.linalg.norm(u)
    h = 1e-7  # small enough that no nearest neighbour changes
    for mode in ("euclidean", "plane"):
        _, g = loss_and_gradient(moved, n_s, t, n_t, mode)
        fd = (loss_and_gradient(moved + h * u, n_s, t, n_t, mode)[0]
              - loss_and_gradient(moved - h * u, n_s, t, n_t, mode)[0]) / (2 * h)
        assert (g * u).sum() == pytest.approx(fd, rel=1e-4)


def test_tangent_weight_scales_the_tangential_part_and_lowers_the_floor():
    """`tangent_weight`: 1 is the Euclidean distance, 0 point to plane; on a flat patch sampled twice the loss
    falls with the weight (the sampling floor is tangential), and gradients match finite differences."""
    from dmesh.reference.chamfer import plane_weighted_distance

    rng = np.random.default_rng(0)
    o = torch.from_numpy(rng.normal(size=(40, 3)))
    n = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(40, 3))), dim=1)
    assert_close(plane_weighted_distance(o, n, 1.0), o.norm(dim=1), rtol=1e-12)
    assert_close(plane_weighted_distance(o, n, 0.0), (o * n).sum(1).abs(), rtol=1e-12, atol=1e-12)
    target = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    normals = np.tile([0.0, 0.0, 1.0], (500, 1))
    with pytest.raises(ValueError, match="needs target normals"):
        ExpectedChamfer(target, None, tangent_weight=0.5)
    with pytest.raises(ValueError, match="tangent_weight"):
        ExpectedChamfer(target, normals, tangent_weight=1.5)
    pts = torch.from_numpy(np.c_[rng.uniform(-1, 1, (400, 2)), 0.01 + 1e-3 * rng.normal(size=400)])
    losses = []
    for w in (1.0, 0.3, 0.0):
        x = pts.clone().requires_grad_(True)
        samples = SurfaceSamples(points=x, prob=torch.full((400,), 0.9, dtype=torch.float64),
                                 face=torch.arange(400), normals=None)
        chamfer = ExpectedChamfer(target, normals, k_max=8, tangent_weight=w, impl="reference")
        loss, _ = chamfer(samples, adapt=False)
        loss.backward()
        u = torch.from_numpy(rng.normal(size=x.shape))
        h = 1e-7
        fd = [chamfer(SurfaceSamples(points=(pts + sgn * h * u), prob=samples.prob, face=samples.face, normals=None),
                      adapt=False)[0].item() for sgn in (1, -1)]
        if w > 0:  # at 0, samples at equal plane distances tie in the row order: a kink within h
            assert (x.grad * u).sum().item() == pytest.approx((fd[0] - fd[1]) / (2 * h), rel=1e-4)
        losses.append(loss.item())
    assert losses[0] > losses[1] > losses[2] > 0
    assert 0.015 < losses[2] < 0.02  # point to plane: the 0.01 offset, both ways, is left; not the spacing


@pytest.mark.parametrize("weight", [0.3, 0.0])
def test_native_tangent_weighted_kernel_matches_the_torch_reference_on_any_thread_count(weight):
    rng = np.random.default_rng(3)
    G, S, K = 300, 400, 12
    target = rng.normal(size=(G, 3))
    normals = rng.normal(size=(G, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    pts = torch.from_numpy(rng.normal(size=(S, 3)))
    prob = torch.from_numpy(rng.uniform(0.1, 1.0, S))
    face = torch.from_numpy(rng.integers(0, 250, S))  # repeated faces: first-occurrence masking
    knn = cKDTree(pts.numpy()).query(target, K)[1]
    x = pts.clone().requires_grad_(True)
    p = prob.clone().requires_grad_(True)
    expected, _ = target_term(torch.from_numpy(target), x, p, face, torch.from_numpy(knn),
                              torch.from_numpy(normals), None, 0.0, weight)
    expected.sum().backward()
    runs = []
    for threads in (1, 2):
        xn = pts.clone().requires_grad_(True)
        pn = prob.clone().requires_grad_(True)
        e, _ = expected_distance(target, xn, pn, face, knn, num_threads=threads, target_normals=normals,
                                 tangent_weight=weight)
        e.sum().backward()
        assert_close(e, expected.detach(), rtol=1e-12, atol=1e-14, what="expected")
        assert_close(xn.grad, x.grad, atol=1e-12, what="grad points")
        assert_close(pn.grad, p.grad, atol=1e-12, what="grad prob")
        runs.append((e.detach().numpy().tobytes(), xn.grad.numpy().tobytes(), pn.grad.numpy().tobytes()))
    assert runs[0] == runs[1]
    with pytest.raises(ValueError, match="tangent_weight"):
        expected_distance(target, pts, prob, face, knn, target_normals=normals, tangent_weight=-0.1)
    with pytest.raises(ValueError, match="target_normals"):
        expected_distance(target, pts, prob, face, knn, target_normals=normals[:5], tangent_weight=0.5)
