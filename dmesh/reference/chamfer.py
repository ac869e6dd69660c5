"""Naive torch reference of the expected Chamfer terms (`dmesh.losses.chamfer`, native/src/expected_chamfer.h).

Slow and simple on purpose: plain tensor gathers and autograd, the way `ExpectedChamfer` computed the loss
before the native kernel; `ExpectedChamfer(impl="reference")` uses it, and the normal term (Eq. 13) always
does. Letters: G target points, S samples on the DMesh, K candidates per target row, J target neighbours per
sample.
"""
from __future__ import annotations

import torch


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


def plane_weighted_distance(offset: torch.Tensor, normal: torch.Tensor, tangent_weight: float) -> torch.Tensor:
    """sqrt((o . n)^2 + w^2 |o - (o . n) n|^2) of offsets o (..., 3) and unit normals n (..., 3): the distance
    with its tangential part scaled by w = `tangent_weight` (1: Euclidean; 0: point to plane)."""
    along = (offset * normal).sum(-1)
    tangential = (offset * offset).sum(-1) - along * along
    return (along * along + tangent_weight ** 2 * tangential.clamp_min(0.0)).clamp_min(1e-24).sqrt()


def _distances(origin: torch.Tensor, others: torch.Tensor, rows: torch.Tensor, origin_normals, other_normals,
               lambda_normal: float, with_normals: bool, plane_normals=None,
               tangent_weight: float = 1.0) -> torch.Tensor:
    """(R, K) distance from origin[r] to others[rows[r, k]]; with normals, plus lambda_normal (1 - |n . n'|)
    of the two points' normals. With `plane_normals` ((R, K, 3) unit normals of the pairs) and a tangent weight
    below 1, the tangential part of each offset is scaled by it (`plane_weighted_distance`)."""
    if plane_normals is not None and tangent_weight < 1.0:
        d = plane_weighted_distance(origin[:, None, :] - others[rows], plane_normals, tangent_weight)
    else:
        d = (origin[:, None, :] - others[rows]).norm(dim=-1)
    if with_normals:
        cos = (origin_normals[:, None, :] * other_normals[rows]).sum(-1).abs()
        d = d + lambda_normal * (1.0 - cos)
    return d


def target_term(target: torch.Tensor, points: torch.Tensor, prob: torch.Tensor, face: torch.Tensor,
                knn: torch.Tensor, target_normals: torch.Tensor | None = None,
                normals: torch.Tensor | None = None, lambda_normal: float = 0.0, tangent_weight: float = 1.0):
    """Target -> ours: each target point's expected distance to its first existing candidate.

    Args:
        target: (G, 3) float64; points: (S, 3) float64 sample positions; prob: (S,) float64 Lambda of each
            sample's face; face: (S,) int64 face ids; knn: (G, K) int64 sample ids, each row sorted by
            distance.
        target_normals, normals: (G, 3) and (S, 3) unit normals, used when lambda_normal > 0: distances
            become d + lambda_normal (1 - |n . n'|) and each row is re-sorted by them.
        tangent_weight: below 1 (needs target_normals), the tangential part of each offset, relative to the
            target point's normal, is scaled by it (`plane_weighted_distance`) and each row is re-sorted.
    Returns:
        expected: (G,) float64, differentiable in points, prob (and normals).
        residual: (G,) float64 (detached), the probability mass beyond the K candidates.
    """
    with_normals = lambda_normal > 0 and normals is not None
    plane = target_normals[:, None, :].expand(-1, knn.shape[1], -1) if tangent_weight < 1.0 else None
    d = _distances(target, points, knn, target_normals, normals, lambda_normal, with_normals, plane, tangent_weight)
    if with_normals or plane is not None:
        order = torch.argsort(d.detach(), dim=1)
        d, knn = torch.gather(d, 1, order), torch.gather(knn, 1, order)
    return expected_min_distance(d, prob[knn], face[knn])


def miss_term(target: torch.Tensor, points: torch.Tensor, prob: torch.Tensor, face: torch.Tensor, knn,
              target_normals: torch.Tensor | None = None, tangent_weight: float = 1.0) -> torch.Tensor:
    """Each target row's probability mass beyond its candidates, charged at its farthest candidate's distance
    (not upstream; `ExpectedChamfer.coverage`).

    The expected nearest distance of a row (`expected_min_distance`) drops the mass prod_i (1 - P_i) that no
    candidate exists, as if the nearest sample beyond the K candidates lay at distance 0. So lowering every
    probability lowers the loss, and a run can trade its surface away (the mesh empties while the loss
    falls). Charging that mass at the farthest candidate's distance makes the row's figure the expected
    distance to the nearest existing sample capped at that distance, a lower bound that never rewards less
    surface: d/dP_i of the sum is (d_i - [distance of the rest]) times the mass before i, <= 0.

    Args:
        target: (G, 3) float64; points: (S, 3) float64 sample positions; prob: (S,) Lambda of each sample's
            face; face: (S,) int64 face ids; knn: (G, K) int sample ids of each row (rows may end early at -1).
        target_normals, tangent_weight: the rows' distances with the tangential part scaled
            (`plane_weighted_distance`), as the rows were taken.
    Returns:
        (G,) float64: residual x farthest distance, differentiable in prob (the distance is a constant).
    """
    knn = torch.as_tensor(knn).long()
    valid = knn >= 0
    ids = knn.clamp_min(0)
    first = first_occurrence(torch.where(valid, face[ids], -1)) & valid
    residual = torch.prod(1.0 - prob[ids] * first.to(prob.dtype), dim=1)
    with torch.no_grad():
        offset = points.detach()[ids] - target[:, None, :]
        if target_normals is not None and tangent_weight < 1.0:
            d = plane_weighted_distance(offset, target_normals[:, None, :], tangent_weight)
        else:
            d = offset.norm(dim=-1)
        far = torch.where(valid, d, torch.zeros_like(d)).max(dim=1).values
    return residual * far


def sample_term(points: torch.Tensor, prob: torch.Tensor, target: torch.Tensor, nearest: torch.Tensor,
                normals: torch.Tensor | None = None, target_normals: torch.Tensor | None = None,
                lambda_normal: float = 0.0, tangent_weight: float = 1.0) -> torch.Tensor:
    """Ours -> target: (S,) Lambda times the distance from each sample to its nearest target point.

    Args:
        points: (S, 3) float64; prob: (S,) float64; target: (G, 3) float64; nearest: (S, J) int64 target ids
            near each sample (J = 1 without the normal term; with it, the minimum over the J of
            d + lambda_normal (1 - |n . n'|)); normals, target_normals: (S, 3), (G, 3) or None.
        tangent_weight: below 1 (needs target_normals), the tangential part of each offset, relative to the
            target point's normal, is scaled by it; the minimum is then over the J targets.
    """
    plane = target_normals[nearest] if tangent_weight < 1.0 else None
    e = _distances(points, target, nearest, normals, target_normals, lambda_normal,
                   lambda_normal > 0 and normals is not None, plane, tangent_weight)
    return prob * e.min(dim=1).values


__all__ = ["first_occurrence", "expected_min_distance", "miss_term", "plane_weighted_distance", "target_term",
           "sample_term"]
