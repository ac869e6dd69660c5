"""Differentiable power-diagram geometry in torch (float64 inside), on elements chosen elsewhere.

These are the formulas whose gradients reach point positions and weights: orthocentres, bisector planes,
face normals and dual lines, and line-to-segment distances. Letters: N points, T tets, F faces.
Every function is safe on degenerate input (coincident or collinear points): denominators are clamped
so no NaN or inf appears, and callers mask the affected elements.
"""
from __future__ import annotations

import torch

from dmesh.tolerances import GEOMETRY_EPS


def gather(values: torch.Tensor, index) -> torch.Tensor:
    """values[index] along the first axis (index: an integer tensor or array of any shape), through
    `index_select`: on a CPU tensor its backward (`index_add_`) adds in a fixed order and is the fastest of
    the gathers, where `values[index]`'s (`index_put_` with accumulate) adds in thread-schedule order, or, under
    torch's deterministic algorithms (`dmesh.recon.loop.deterministic`), sorts first."""
    index = torch.as_tensor(index)
    if index.dtype not in (torch.int64, torch.int32):
        index = index.long()
    return values.index_select(0, index.reshape(-1)).reshape(*index.shape, *values.shape[1:])


def _safe(x: torch.Tensor, eps: float = GEOMETRY_EPS) -> torch.Tensor:
    """x with |x| >= eps, keeping its sign (0 maps to +eps)."""
    return torch.where(x.abs() < eps, torch.full_like(x, eps) * torch.where(x < 0, -1.0, 1.0), x)


def orthocentres(points: torch.Tensor, weights: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Weighted circumcentres (power-diagram vertices) of tets.

    Args:
        points: (N, 3) float; weights: (N,) float; tets: (T, 4) int64.
    Returns:
        (T, 3) float64 point c with equal power |c - p|^2 - w to the tet's four points. Solves
        2 (p_j - p_0) . x = |p_j - p_0|^2 - (w_j - w_0) for x = c - p_0 by Cramer's rule.
    """
    p = points.double()
    w = weights.double()
    p0 = p[tets[:, 0]]
    d = p[tets[:, 1:]] - p0[:, None, :]                                     # (T, 3, 3) rows d_j
    b = (d * d).sum(-1) - (w[tets[:, 1:]] - w[tets[:, :1]])                 # (T, 3)
    r0, r1, r2 = d[:, 0], d[:, 1], d[:, 2]
    c12, c20, c01 = torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)
    det = _safe((r0 * c12).sum(-1))                                        # det of d; A = 2 d
    x = (b[:, 0:1] * c12 + b[:, 1:2] * c20 + b[:, 2:3] * c01) / (2.0 * det[:, None])
    return p0 + x


def bisector_distance(p_i: torch.Tensor, w_i: torch.Tensor, p_j: torch.Tensor, w_j: torch.Tensor,
                      s: torch.Tensor) -> torch.Tensor:
    """Unsigned distance of points s to the power bisector planes of (i, j).

    The plane has normal n = d/|d| (d = p_j - p_i) and passes through p_i + t d with
    t = 1/2 (1 - (w_j - w_i)/|d|^2); the distance is |(s - p_i) . n - t |d||.

    Args:
        p_i, p_j, s: (..., 3); w_i, w_j: (...). Returns: (...) float64.
    """
    d = p_j.double() - p_i.double()
    len2 = (d * d).sum(-1).clamp_min(GEOMETRY_EPS)
    length = len2.sqrt()
    t_len = 0.5 * (length - (w_j.double() - w_i.double()) / length)
    return (((s.double() - p_i.double()) * d).sum(-1) / length - t_len).abs()


def face_normals(points: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) float64 unit normals (p_b - p_a) x (p_c - p_a) / |.| of faces (F, 3); zero-safe."""
    p = points.double()
    n = torch.linalg.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    return n / (n * n).sum(-1, keepdim=True).clamp_min(GEOMETRY_EPS).sqrt()


def dual_lines(points: torch.Tensor, weights: torch.Tensor, faces: torch.Tensor):
    """The dual line of each face: the points of equal power to its three weighted vertices.

    Args:
        points: (N, 3); weights: (N,); faces: (F, 3) int64.
    Returns:
        origin: (F, 3) float64, the power centre of the face in its own plane;
        direction: (F, 3) float64 unit normal of the face;
        area2: (F,) float64 squared norm of the face's cross product (0 for collinear faces, which have no
            dual line; their origin and direction are finite but meaningless).
    """
    p = points.double()
    w = weights.double()
    a = p[faces[:, 0]]
    e1 = p[faces[:, 1]] - a
    e2 = p[faces[:, 2]] - a
    n = torch.linalg.cross(e1, e2)
    area2 = (n * n).sum(-1)
    rb = (e1 * e1).sum(-1) - (w[faces[:, 1]] - w[faces[:, 0]])
    rc = (e2 * e2).sum(-1) - (w[faces[:, 2]] - w[faces[:, 0]])
    e11, e12, e22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    den = 2.0 * area2.clamp_min(GEOMETRY_EPS)
    alpha = (rb * e22 - rc * e12) / den
    beta = (rc * e11 - rb * e12) / den
    origin = a + alpha[:, None] * e1 + beta[:, None] * e2
    direction = n / area2.clamp_min(GEOMETRY_EPS).sqrt()[:, None]
    return origin, direction, area2


def line_segment_distance(origin: torch.Tensor, direction: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
                          is_ray: torch.Tensor) -> torch.Tensor:
    """Distance between lines (origin, unit direction) and segments [a, b] or rays a + s b (s >= 0).

    Projects the segment onto the plane normal to the line and measures the distance of the line's trace
    to it. Args: origin, direction, a, b: (..., 3); is_ray: (...) bool. Returns: (...) float64.
    """
    u = direction.double()
    pa = a.double() - origin.double()
    pa = pa - (pa * u).sum(-1, keepdim=True) * u
    b = b.double()
    pb_seg = b - origin.double()
    pb_seg = pb_seg - (pb_seg * u).sum(-1, keepdim=True) * u
    ray_dir = b - (b * u).sum(-1, keepdim=True) * u
    e = torch.where(is_ray[..., None], ray_dir, pb_seg - pa)
    ee = (e * e).sum(-1)
    t = -(pa * e).sum(-1) / ee.clamp_min(GEOMETRY_EPS)
    t = t.clamp_min(0.0)
    t = torch.where(is_ray, t, t.clamp_max(1.0))
    t = torch.where(ee > GEOMETRY_EPS, t, torch.zeros_like(t))
    q = pa + t[..., None] * e
    return (q * q).sum(-1).clamp_min(GEOMETRY_EPS * GEOMETRY_EPS).sqrt()
