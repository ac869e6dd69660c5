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
- Ours -> target: Lambda times the distance from each sample to its nearest target point.
- Distances are Euclidean (not squared); both terms are means. With `lambda_normal` > 0 every distance
  becomes d + lambda_normal (1 - |n . n'|) (Eq. 13): target rows are re-sorted by that distance, and a
  sample takes the minimum over its `k_normal` nearest target points. Needs target normals.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


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
    with torch.no_grad():
        r = reals.detach().double()[faces]
        pw = prob_wdt.detach().double()
        strata = [pw * r.min(1).values, pw * r.max(1).values]
        keep = (strata[1] > prob_threshold).numpy()
        ids = np.flatnonzero(keep)
        if len(ids) == 0 or num <= 0:
            return _empty_samples(points, with_normals)
        p = points.detach().double()
        f = faces[ids]
        cross = torch.linalg.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
        area = 0.5 * cross.norm(dim=1).numpy()
        chosen = []
        for k, eta_bar in enumerate(strata):
            e = eta_bar.numpy()[ids]
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
        fold = uv.sum(1) > 1.0
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
        normals = n / n.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return SurfaceSamples(pts, face, prob.double()[face], normals)


def _empty_samples(points: torch.Tensor, with_normals: bool) -> SurfaceSamples:
    z = points.new_zeros((0, 3), dtype=torch.float64)
    return SurfaceSamples(z, torch.zeros(0, dtype=torch.long), points.new_zeros(0, dtype=torch.float64),
                          z.clone() if with_normals else None)


def first_occurrence(ids: torch.Tensor) -> torch.Tensor:
    """(G, K) bool: True where ids[g, k] does not appear earlier in row g (ids: (G, K) ints)."""
    if ids.shape[1] <= 1:
        return torch.ones_like(ids, dtype=torch.bool)
    order = torch.sort(ids, dim=1, stable=True).indices
    sorted_ids = torch.gather(ids, 1, order)
    first_sorted = torch.ones_like(sorted_ids, dtype=torch.bool)
    first_sorted[:, 1:] = sorted_ids[:, 1:] != sorted_ids[:, :-1]
    out = torch.empty_like(first_sorted)
    out.scatter_(1, order, first_sorted)
    return out


def expected_min_distance(dist: torch.Tensor, prob: torch.Tensor, face: torch.Tensor):
    """Expected nearest distance of rows of candidates sorted by distance.

    Args:
        dist: (G, K) distances, ascending in each row; prob: (G, K) existence probability of each
            candidate's face; face: (G, K) int64 face id of each candidate.
    Returns:
        expected: (G,) sum_i d_i P_i prod_{j<i} (1 - P_j) with P zeroed for repeated faces.
        residual: (G,) prod_i (1 - P_i) (detached), the mass beyond the K candidates.
    """
    p = prob * first_occurrence(face).to(prob.dtype)
    keep = 1.0 - p
    # Exclusive cumulative product: the probability that no earlier candidate exists.
    before = torch.cumprod(torch.cat([torch.ones_like(keep[:, :1]), keep[:, :-1]], dim=1), dim=1)
    expected = (dist * p * before).sum(1)
    residual = (before[:, -1] * keep[:, -1]).detach()
    return expected, residual


@dataclass
class ExpectedChamfer:
    """Expected Chamfer distance to a fixed target cloud, with the adaptive K of the target side.

    Args:
        target: (G, 3) float target points; target_normals: (G, 3) float or None.
        k_max: largest K (and the starting K); mass_tol: residual mass that makes K grow.
        lambda_normal: weight of the normal term (Eq. 13); 0 disables it.
        k_normal: target neighbours searched per sample when the normal term is on.
        workers: threads of the k-d tree queries.
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
    k: int = field(init=False)

    def __post_init__(self):
        from scipy.spatial import cKDTree

        self.target = np.ascontiguousarray(self.target, dtype=np.float64)
        if self.target.ndim != 2 or self.target.shape[1] != 3 or len(self.target) == 0:
            raise ValueError(f"target must have shape (G, 3) with G > 0, got {self.target.shape}")
        if self.k_max < 1:
            raise ValueError(f"k_max must be >= 1, got {self.k_max}")
        if self.lambda_normal > 0 and self.target_normals is None:
            raise ValueError("lambda_normal > 0 needs target normals")
        if self.target_normals is not None:
            self.target_normals = np.ascontiguousarray(self.target_normals, dtype=np.float64)
        self.k = self.k_max
        self._tree = cKDTree(self.target)
        self._target_t = torch.from_numpy(self.target)
        self._normals_t = None if self.target_normals is None else torch.from_numpy(self.target_normals)

    def reset_k(self) -> None:
        self.k = self.k_max

    def __call__(self, samples: SurfaceSamples, adapt: bool = True) -> tuple[torch.Tensor, dict]:
        """Loss CD_gt + CD_ours (a 0-dim float64 tensor) and figures {"cd_gt", "cd_ours", "k", "residual"}.

        With no samples the loss is a constant 0 with no gradient path (the caller sees `empty`)."""
        from scipy.spatial import cKDTree

        s = len(samples)
        if s == 0:
            zero = torch.zeros((), dtype=torch.float64)
            return zero, {"cd_gt": float("nan"), "cd_ours": float("nan"), "k": self.k, "residual": 1.0,
                          "empty": True}
        use_normals = self.lambda_normal > 0 and samples.normals is not None
        sp = samples.points.detach().numpy()
        k = min(self.k, s)
        _, idx = cKDTree(sp).query(self.target, k, workers=self.workers)
        idx = torch.from_numpy(np.asarray(idx, dtype=np.int64).reshape(len(self.target), k))
        d = (self._target_t[:, None, :] - samples.points[idx]).norm(dim=-1)
        if use_normals:
            cos = (self._normals_t[:, None, :] * samples.normals[idx]).sum(-1).abs()
            d = d + self.lambda_normal * (1.0 - cos)
            order = torch.argsort(d.detach(), dim=1)
            d, idx = torch.gather(d, 1, order), torch.gather(idx, 1, order)
        expected, residual = expected_min_distance(d, samples.prob[idx], samples.face[idx])
        cd_gt = expected.mean()

        kk = min(self.k_normal, len(self.target)) if use_normals else 1
        _, j = self._tree.query(sp, kk, workers=self.workers)
        j = torch.from_numpy(np.asarray(j, dtype=np.int64).reshape(s, kk))
        e = (samples.points[:, None, :] - self._target_t[j]).norm(dim=-1)
        if use_normals:
            cos = (samples.normals[:, None, :] * self._normals_t[j]).sum(-1).abs()
            e = e + self.lambda_normal * (1.0 - cos)
        cd_ours = (samples.prob * e.min(dim=1).values).mean()

        max_residual = float(residual.max())
        if adapt:
            self.k = min(self.k + 1, self.k_max) if max_residual > self.mass_tol else max(self.k - 1, 1)
        return cd_gt + cd_ours, {"cd_gt": float(cd_gt.detach()), "cd_ours": float(cd_ours.detach()), "k": k,
                                 "residual": max_residual, "empty": False}


def chamfer_l1(a: np.ndarray, b: np.ndarray, workers: int = 1) -> float:
    """Plain symmetric Chamfer L1 (mean nearest Euclidean distance both ways, summed) of (A, 3) and (B, 3)."""
    from scipy.spatial import cKDTree

    da, _ = cKDTree(b).query(a, workers=workers)
    db, _ = cKDTree(a).query(b, workers=workers)
    return float(da.mean() + db.mean())


__all__ = ["SurfaceSamples", "sample_faces", "first_occurrence", "expected_min_distance", "ExpectedChamfer",
           "chamfer_l1"]
