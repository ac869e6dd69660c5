"""Expected Chamfer distance between a DMesh and a target point cloud (paper appendix 8.2, Eq. 12-13).

Letters: N DMesh points, M scored faces, S samples drawn on the DMesh, G target points, K neighbours.

- Sampling (no gradient for the choice): half of the S faces are drawn with probability proportional to
  area * Lambda_wdt * min(r), the other half to area * Lambda_wdt * max(r) (raw real values, not dmin);
  faces whose factor Lambda_wdt * min(r) (resp. max(r)) is at most `prob_threshold` are never drawn. One
  uniform barycentric point per drawn face; its position is differentiable in the face's vertices and it
  carries its face id and the face's full probability Lambda = Lambda_wdt * dmin(r).
- Target -> ours: for each target point, its K nearest samples sorted by distance; a sample whose face
  already appeared earlier in the row counts with probability 0 (at most one sample per face); expected
  nearest distance sum_i d_i P_i prod_{j<i} (1 - P_j) (mass beyond K is dropped, as upstream). K adapts
  between calls: +1 while any row keeps more than `mass_tol` of probability beyond K, -1 when none does.
  Not upstream: a row stops at its `k_first` (16) nearest samples when it keeps at most `mass_tol` beyond
  them, and only the other rows are searched to K. Every row then drops at most `mass_tol` of probability,
  the bound the global K keeps for its worst row, and K adapts exactly as with every row at K. It saves work
  when the global K is set by a few rows (`python -m eval.bench step`).
- Ours -> target: Lambda times the distance from each sample to its nearest target point.
- Distances are Euclidean (not squared); both terms are means. With `lambda_normal` > 0 every distance
  becomes d + lambda_normal (1 - |n . n'|) (Eq. 13): target rows are re-sorted by that distance, and a
  sample takes the minimum over its `k_normal` nearest target points. Needs target normals.

Implementations (`ExpectedChamfer.impl`):
- "native" (default): each target row's nearest samples come from the native kNN search
  (`dmesh.native.knn_search_trees`, exact, ties to the smaller id; the target's k-d tree is built once, the
  samples' once per call and used by both terms) and the target -> ours term from the native kernel
  (native/src/expected_chamfer.h) in one autograd Function (`expected_distance`, rows of both tiers in one
  call), with an analytic backward whose gradients are byte-identical on any thread count.
- "reference": the naive torch path of `dmesh.reference.chamfer` with SciPy's cKDTree, as before the kernel.
The normal term (lambda_normal > 0) re-sorts rows by the normal-augmented distance and stays on the torch
path in both (the native kNN still finds the candidates in "native"). The ours -> target term is a small
torch computation on each sample's nearest target points (native kNN search in "native", a cKDTree of the
fixed target, built once, in "reference"). The target is kept in a Z-order (the loss
is a mean over it) for cache locality in the kernel. `ExpectedChamfer` runs the float64 kernel: float32
was no faster and less accurate. Timings: `python -m eval.bench step` (reports/bench_step.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from dmesh import native
from dmesh.reference.chamfer import expected_min_distance, first_occurrence, miss_term, sample_term, target_term
from dmesh.tolerances import DIVISION_FLOOR

#: Implementations of `ExpectedChamfer` (module docstring).
IMPLS = ("native", "reference")


@dataclass
class SurfaceSamples:
    """Points drawn on a DMesh's probable faces.

    Attributes:
        points: (S, 3) float64, differentiable in the DMesh positions.
        face: (S,) int64 index into the scored faces.
        prob: (S,) float64 Lambda of the sample's face (differentiable).
        normals: (S, 3) float64 unit face normals (differentiable), or None when not asked for.
    """

    points: torch.Tensor
    face: torch.Tensor
    prob: torch.Tensor
    normals: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.face)


def sample_faces(points: torch.Tensor, faces: torch.Tensor, prob_wdt: torch.Tensor, reals: torch.Tensor,
                 prob: torch.Tensor, num: int, rng: np.random.Generator, prob_threshold: float = 1e-3,
                 with_normals: bool = False) -> SurfaceSamples:
    """Stratified area x probability sampling of `num` points on the faces (see the module docstring).

    Args:
        points: (N, 3) float tensor; faces: (M, 3) int64; prob_wdt: (M,) Lambda_wdt; reals: (N,) real values
            in [0, 1]; prob: (M,) Lambda; num: total samples (half per stratum); rng: NumPy generator.
        prob_threshold: faces at or below it in a stratum are skipped in that stratum.
        with_normals: also return the sampled faces' unit normals.
    Returns:
        `SurfaceSamples`; empty (S = 0) when no face passes the threshold in either stratum.
    """
    # The choice in NumPy, one column per vertex (reductions and cross products along a length-3 axis are
    # several times slower in torch, over every scored face).
    fv = faces.numpy()
    rv = reals.detach().double().numpy()
    pw = prob_wdt.detach().double().numpy()
    r = [rv[fv[:, k]] for k in range(3)]
    strata = [pw * np.minimum(np.minimum(r[0], r[1]), r[2]), pw * np.maximum(np.maximum(r[0], r[1]), r[2])]
    ids = np.flatnonzero(strata[1] > prob_threshold)
    if len(ids) == 0 or num <= 0:
        return _empty_samples(points, with_normals)
    pv = points.detach().double().numpy()
    f = fv[ids]
    x0 = pv[f[:, 0]]
    e1, e2 = (pv[f[:, 1]] - x0).T, (pv[f[:, 2]] - x0).T
    area = 0.5 * np.sqrt((e1[1] * e2[2] - e1[2] * e2[1]) ** 2 + (e1[2] * e2[0] - e1[0] * e2[2]) ** 2
                         + (e1[0] * e2[1] - e1[1] * e2[0]) ** 2)
    chosen = []
    for k, eta_bar in enumerate(strata):
        e = eta_bar[ids]
        eta = np.where(e > prob_threshold, area * e, 0.0)
        total = eta.sum()
        if not total > 0:
            continue
        count = num // 2 if k == 0 else num - num // 2
        cum = np.cumsum(eta)
        pick = np.searchsorted(cum, rng.random(count) * cum[-1], side="right").clip(max=len(eta) - 1)
        chosen.append(pick)
    if not chosen:
        return _empty_samples(points, with_normals)
    pick = np.concatenate(chosen)
    uv = rng.random((len(pick), 2))
    fold = uv[:, 0] + uv[:, 1] > 1.0
    uv[fold] = 1.0 - uv[fold]
    face = torch.from_numpy(ids[pick])
    tri = faces[face]
    p = points.double()
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    u = torch.from_numpy(uv[:, :1])
    v = torch.from_numpy(uv[:, 1:])
    pts = a + u * (b - a) + v * (c - a)
    normals = None
    if with_normals:
        n = torch.linalg.cross(b - a, c - a)
        normals = n / n.norm(dim=1, keepdim=True).clamp_min(DIVISION_FLOOR)
    return SurfaceSamples(pts, face, prob.double()[face], normals)


def _empty_samples(points: torch.Tensor, with_normals: bool) -> SurfaceSamples:
    z = points.new_zeros((0, 3), dtype=torch.float64)
    return SurfaceSamples(z, torch.zeros(0, dtype=torch.long), points.new_zeros(0, dtype=torch.float64),
                          z.clone() if with_normals else None)


def _threads(num_threads: int | None) -> int:
    return int(num_threads) if num_threads else max(1, torch.get_num_threads())


class _ExpectedDistance(torch.autograd.Function):
    """(points, prob) -> (expected, residual) of the target rows; native forward/backward pair."""

    @staticmethod
    def forward(ctx, points, prob, target, face, knn, settings, known):
        # settings = (dtype: np.float64 or np.float32, num_threads, target normals (G, 3) or None, tangent weight)
        # known: None, or the (expected, residual) arrays these inputs give, computed by the caller
        if known is None:
            known = native.expected_chamfer_forward(target, points, prob, face, knn, settings[1], settings[0],
                                                    settings[2], settings[3])
        expected, residual = known
        ctx.settings = settings
        ctx.save_for_backward(points, prob, target, face, knn)
        residual = torch.from_numpy(residual)
        ctx.mark_non_differentiable(residual)
        return torch.from_numpy(expected), residual

    @staticmethod
    @once_differentiable
    def backward(ctx, g_expected, g_residual):
        points, prob, target, face, knn = ctx.saved_tensors
        if g_expected is None:
            g_expected = torch.zeros(len(target), dtype=torch.float64)
        gp, gq = native.expected_chamfer_backward(target, points, prob, face, knn, g_expected.double(),
                                                  ctx.settings[1], ctx.settings[0], ctx.settings[2], ctx.settings[3])
        grad_points = torch.from_numpy(gp).to(points.dtype) if ctx.needs_input_grad[0] else None
        grad_prob = torch.from_numpy(gq).to(prob.dtype) if ctx.needs_input_grad[1] else None
        # one gradient per forward input: points, prob, target, face, knn, settings, known
        return grad_points, grad_prob, None, None, None, None, None


def expected_distance(target, points: torch.Tensor, prob: torch.Tensor, face, knn, *,
                      dtype: torch.dtype = torch.float64, num_threads: int | None = None,
                      target_normals=None, tangent_weight: float = 1.0, known=None):
    """Native `expected_min_distance` of kNN rows: what `target_term` of `dmesh.reference.chamfer` computes
    without the normal term, with an analytic backward (native/src/expected_chamfer.h).

    Args:
        target: (G, 3) float tensor or array (no gradient).
        points: (S, 3) float tensor, sample positions (differentiable).
        prob: (S,) float tensor, Lambda of each sample's face (differentiable).
        face: (S,) integer tensor or array, face ids >= 0 (the first-occurrence mask compares them).
        knn: (G, K) integer tensor or array in [0, S), each row's sample ids sorted by distance; a row ends
            early at its first -1 (rows of different lengths).
        dtype: torch.float64, or torch.float32 to run the kernel on float32 geometry (row sums in float64 either
            way; gradients come back in the inputs' dtype).
        num_threads: OpenMP threads (default torch.get_num_threads()); results do not depend on it.
        target_normals, tangent_weight: (G, 3) unit normals and a weight below 1: tangent-weighted distances
            (`ExpectedChamfer.tangent_weight`), each row taken in increasing distance.
        known: None, or the float64 (expected, residual) arrays of these inputs, already computed by the caller
            (`ExpectedChamfer` assembles them from two searches); the forward then returns them as they are.
    Returns:
        expected: (G,) float64 sum_i d_i P_i prod_{j<i} (1 - P_j), P zeroed for repeated faces.
        residual: (G,) float64 prod_i (1 - P_i) (not differentiable).

    Example:
        >>> import torch; from dmesh.losses.chamfer import expected_distance
        >>> pts = torch.tensor([[1.0, 0, 0], [2.0, 0, 0]], dtype=torch.float64, requires_grad=True)
        >>> prob = torch.tensor([0.5, 1.0], dtype=torch.float64, requires_grad=True)
        >>> e, r = expected_distance(torch.zeros(1, 3), pts, prob, torch.tensor([0, 1]), torch.tensor([[0, 1]]))
        >>> e.item(), r.item()
        (1.5, 0.0)
    """
    if dtype not in (torch.float64, torch.float32):
        raise ValueError(f"expected_distance: dtype must be torch.float64 or torch.float32, got {dtype}")

    def as_t(a, d):  # a tensor for save_for_backward; face keeps its dtype (native.py checks the int32 range)
        a = a.detach() if isinstance(a, torch.Tensor) else torch.as_tensor(np.ascontiguousarray(a))
        return (a if d is None else a.to(d)).contiguous()

    np_dtype = np.float64 if dtype == torch.float64 else np.float32
    normals = None if target_normals is None else np.ascontiguousarray(
        target_normals.detach().numpy() if isinstance(target_normals, torch.Tensor) else target_normals, np.float64)
    return _ExpectedDistance.apply(points, prob, as_t(target, torch.float64), as_t(face, None),
                                   as_t(knn, torch.int32), (np_dtype, _threads(num_threads), normals,
                                                            float(tangent_weight)), known)


@dataclass
class ExpectedChamfer:
    """Expected Chamfer distance to a fixed target cloud, with the adaptive K of the target side.

    Args:
        target: (G, 3) float target points; target_normals: (G, 3) float or None.
        k_max: largest K (and the starting K); mass_tol: residual mass that makes K grow.
        lambda_normal: weight of the normal term (Eq. 13); 0 disables it.
        tangent_weight: 1 (the paper): Euclidean distances; below 1 (needs target normals; not upstream): the
            tangential part of each offset, relative to the target point's normal, is scaled by it, which lowers
            the loss's sampling floor (`python -m studies loss_floor`).
        k_normal: target neighbours searched per sample when the normal term is on.
        coverage: False (the paper): a target row's probability mass beyond its K candidates is dropped, so
            lowering every probability lowers the loss; True (not upstream; the `compact` preset): that mass
            is charged at the row's farthest candidate's distance (`dmesh.reference.chamfer.miss_term`), so
            the loss never rewards losing surface.
        k_first: neighbours every target row takes first; only the rows that keep more than `mass_tol` of
            probability beyond them take the full K (0, or at least K: every row takes K, as upstream). Not
            with the normal term (its rows are re-sorted, so they take K).
        workers: threads of the k-d tree queries and of the native kernel, at most
            `torch.get_num_threads()` (the process's thread budget, which a sweep's runner sets per run).
        impl: "native" (kNN search and kernel in C++) or "reference" (torch and cKDTree); module docstring.
    Attributes:
        k: the current K of the target -> ours term.
    """

    target: np.ndarray
    target_normals: np.ndarray | None = None
    k_max: int = 100
    mass_tol: float = 1e-4
    lambda_normal: float = 0.0
    k_normal: int = 8
    workers: int = 1
    impl: str = "native"
    tangent_weight: float = 1.0
    k_first: int = 16
    coverage: bool = False
    k: int = field(init=False)

    def __post_init__(self):
        from scipy.spatial import cKDTree

        self.target = np.ascontiguousarray(self.target, dtype=np.float64)
        if self.target.ndim != 2 or self.target.shape[1] != 3 or len(self.target) == 0:
            raise ValueError(f"target must have shape (G, 3) with G > 0, got {self.target.shape}")
        if not np.isfinite(self.target).all():
            raise ValueError("target must be finite")
        if self.k_max < 1:
            raise ValueError(f"k_max must be >= 1, got {self.k_max}")
        if self.k_first < 0:
            raise ValueError(f"k_first must be >= 0, got {self.k_first}")
        if self.lambda_normal > 0 and self.target_normals is None:
            raise ValueError("lambda_normal > 0 needs target normals")
        if not 0.0 <= self.tangent_weight <= 1.0:
            raise ValueError(f"tangent_weight must be in [0, 1], got {self.tangent_weight}")
        if self.tangent_weight < 1.0 and self.target_normals is None:
            raise ValueError("tangent_weight < 1 needs target normals")
        if self.impl not in IMPLS:
            raise ValueError(f"impl must be one of {IMPLS}, got {self.impl!r}")
        if self.target_normals is not None:
            self.target_normals = np.ascontiguousarray(self.target_normals, dtype=np.float64)
        self.k = self.k_max
        # The loss is a mean over the target points, so their order is free: a Z-order keeps each run of
        # rows on nearby samples, which makes the native kernel about 1.5x faster (cache locality).
        order = _z_order(self.target)
        self._target = np.ascontiguousarray(self.target[order])
        # The target's k-d tree, built once: the native one serves both searches of every call (the target
        # rows' nearest samples and the samples' nearest target points).
        if self.impl == "reference":
            self._tree = cKDTree(self._target)
        else:
            self._tree = native.point_tree(self._target, _TARGET_LEAF)
        self._target_t = torch.from_numpy(self._target)
        self._normals_t = (None if self.target_normals is None
                           else torch.from_numpy(np.ascontiguousarray(self.target_normals[order])))

    def reset_k(self) -> None:
        self.k = self.k_max

    def __call__(self, samples: SurfaceSamples, adapt: bool = True) -> tuple[torch.Tensor, dict]:
        """Loss CD_gt + CD_ours (a 0-dim float64 tensor) and figures {"cd_gt", "cd_ours", "k", "residual"}.

        With no samples the loss is a constant 0 with no gradient path (the caller sees `empty`)."""
        s = len(samples)
        if s == 0:
            zero = torch.zeros((), dtype=torch.float64)
            return zero, {"cd_gt": float("nan"), "cd_ours": float("nan"), "k": self.k, "residual": 1.0,
                          "empty": True}
        use_normals = self.lambda_normal > 0 and samples.normals is not None
        tw = self.tangent_weight
        sp = samples.points.detach().numpy()
        k = min(self.k, s)
        # Every row first takes its k_first nearest samples; only the rows that keep more than mass_tol of
        # probability beyond them are searched again with the full K (module docstring).
        k1 = k if use_normals or not 0 < self.k_first < k else self.k_first
        if self.impl == "native":
            sample_tree = native.point_tree(sp, _SAMPLE_LEAF)
            expected, residual, rows = self._native_rows(samples, sample_tree, k, k1, use_normals)
        else:
            expected, residual, rows = self._reference_rows(samples, sp, k, k1, use_normals)
        if self.coverage:
            expected = expected + miss_term(self._target_t, samples.points, samples.prob, samples.face, rows,
                                            self._normals_t, tw)
        cd_gt = expected.mean()

        kk = min(self.k_normal, len(self.target)) if use_normals or tw < 1.0 else 1
        if self.impl == "native":  # the cKDTree is slow for samples far from the target
            j = native.knn_search_trees(self._tree, sample_tree, kk, self._workers)
        else:
            j = self._tree.query(sp, kk, workers=self._workers)[1]
        j = torch.from_numpy(np.asarray(j, dtype=np.int64).reshape(s, kk))
        cd_ours = sample_term(samples.points, samples.prob, self._target_t, j, samples.normals, self._normals_t,
                              self.lambda_normal if use_normals else 0.0, tw).mean()

        max_residual = float(residual.max())
        if adapt:
            self.k = min(self.k + 1, self.k_max) if max_residual > self.mass_tol else max(self.k - 1, 1)
        return cd_gt + cd_ours, {"cd_gt": float(cd_gt.detach()), "cd_ours": float(cd_ours.detach()), "k": k,
                                 "residual": max_residual, "empty": False}

    @property
    def _workers(self) -> int:
        return max(1, min(int(self.workers), torch.get_num_threads()))

    def _native_rows(self, samples: SurfaceSamples, sample_tree, k: int, k1: int,
                     use_normals: bool) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        """(expected, residual, rows) of the target rows, native kNN search and kernel: every row at its k1
        nearest samples, the rows that keep more than mass_tol beyond them at k, in one autograd node (rows of
        two lengths, the shorter ones ending at -1); rows: the (G, K) sample ids taken."""
        normals = self._normals_t if self.tangent_weight < 1.0 else None
        knn = native.knn_search_trees(sample_tree, self._tree, k1, self._workers)
        if use_normals:
            return (*target_term(self._target_t, samples.points, samples.prob, samples.face,
                                 torch.from_numpy(knn.astype(np.int64)), self._normals_t, samples.normals,
                                 self.lambda_normal, self.tangent_weight), knn)

        def forward(rows, ids):
            return native.expected_chamfer_forward(self._target if rows is None else self._target[rows],
                                                   samples.points.detach(), samples.prob.detach(), samples.face,
                                                   ids, self._workers, np.float64,
                                                   None if normals is None else
                                                   (normals if rows is None else normals[rows]),
                                                   self.tangent_weight)

        known = None
        if k1 < k:
            expected, residual = known = forward(None, knn)
            hard = np.flatnonzero(residual > self.mass_tol)
            if len(hard):
                hard_ids = native.knn_search_trees(sample_tree, native.point_tree(self._target[hard], _TARGET_LEAF),
                                                   k, self._workers)
                rows = np.full((len(knn), k), -1, dtype=np.int32)
                rows[:, :k1] = knn
                rows[hard] = hard_ids
                knn = rows
                expected[hard], residual[hard] = forward(hard, hard_ids)
        return (*expected_distance(self._target_t, samples.points, samples.prob, samples.face, knn,
                                   num_threads=self._workers, target_normals=normals,
                                   tangent_weight=self.tangent_weight, known=known), knn)

    def _reference_rows(self, samples: SurfaceSamples, sp: np.ndarray, k: int, k1: int,
                        use_normals: bool) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        """`_native_rows` with SciPy's cKDTree and the torch terms of `dmesh.reference.chamfer`."""
        from scipy.spatial import cKDTree

        tree = cKDTree(sp)

        def rows_term(rows, kk):
            target = self._target if rows is None else self._target[rows]
            _, idx = tree.query(target, kk, workers=self._workers)
            idx = torch.from_numpy(np.asarray(idx, dtype=np.int64).reshape(len(target), kk))
            normals = self._normals_t if rows is None or self._normals_t is None else self._normals_t[rows]
            return (*target_term(torch.from_numpy(target), samples.points, samples.prob, samples.face, idx,
                                 normals, samples.normals, self.lambda_normal if use_normals else 0.0,
                                 self.tangent_weight), idx.numpy())

        expected, residual, ids = rows_term(None, k1)
        if k1 < k:
            hard = np.flatnonzero(residual.detach().numpy() > self.mass_tol)
            if len(hard):
                e_hard, r_hard, hard_ids = rows_term(hard, k)
                rows = torch.from_numpy(hard)
                expected = expected.index_put((rows,), e_hard)
                residual = residual.index_put((rows,), r_hard)
                padded = np.full((len(ids), k), -1, dtype=np.int64)
                padded[:, :k1] = ids
                padded[hard] = hard_ids
                ids = padded
        return expected, residual, ids


#: Leaf sizes of the native k-d trees, the target's and the samples' (`python -m eval.bench step` times them).
_TARGET_LEAF = 16
_SAMPLE_LEAF = 32


def _z_order(points: np.ndarray) -> np.ndarray:
    """(N,) int64 permutation sorting (N, 3) points along a Z-order (Morton) curve, 21 bits per axis."""
    lo = points.min(0)
    ext = float((points.max(0) - lo).max())
    q = np.zeros(points.shape, dtype=np.uint64) if ext <= 0 else (
        np.clip((points - lo) / ext, 0.0, 1.0) * (2**21 - 1)).astype(np.uint64)
    code = np.zeros(len(points), dtype=np.uint64)
    for axis in range(3):
        v = q[:, axis] & np.uint64(0x1FFFFF)
        for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                            (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        code |= v << np.uint64(axis)
    return np.argsort(code, kind="stable")


def chamfer_l1(a: np.ndarray, b: np.ndarray, workers: int = 1) -> float:
    """Plain symmetric Chamfer L1 (mean nearest Euclidean distance both ways, summed) of (A, 3) and (B, 3)."""
    from scipy.spatial import cKDTree

    da, _ = cKDTree(b).query(a, workers=workers)
    db, _ = cKDTree(a).query(b, workers=workers)
    return float(da.mean() + db.mean())


__all__ = ["SurfaceSamples", "sample_faces", "first_occurrence", "expected_min_distance", "expected_distance",
           "ExpectedChamfer", "chamfer_l1", "IMPLS"]
