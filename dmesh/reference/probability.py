"""Naive references for the probability kernels.

`line_cell_distance` measures the distance between a line and a bounded convex power cell by projecting
the cell's vertices (its tets' orthocentres) onto the plane normal to the line and measuring the distance
of the line's trace to their 2D convex hull; independent of the native edge search.

`existing_deltas`, `nonexisting_deltas` and `dual_edges` are the torch path of the face probabilities
(`ProbabilityConfig.impl = "reference"`): the native argmin searches (no gradient) pick a bisector plane or
a power-cell edge per face vertex, and the chosen distances are recomputed in float64 torch
(`dmesh.geometry`) so autograd reaches positions and weights. Slow and simple on purpose: the fused
native kernels of `dmesh.probability` are tested and benchmarked against them.
Letters: N points, F faces of the WDT, K scored WDT faces, C candidates.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dmesh import geometry, native
from dmesh.tolerances import COLLINEAR, PARALLEL


def _point_segment_2d(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    e = b - a
    t = 0.0 if not (e @ e) > 0 else float(np.clip(-(a - q) @ e / (e @ e), 0.0, 1.0))
    return float(np.linalg.norm(a + t * e - q))


def line_cell_distance(origin: np.ndarray, direction: np.ndarray, cell_vertices: np.ndarray) -> float:
    """Distance between the line (origin, unit direction) and conv(cell_vertices) ((K, 3), K >= 4); 0 when
    the line passes through it."""
    from scipy.spatial import ConvexHull

    u = direction / np.linalg.norm(direction)
    a0 = np.cross(u, [1.0, 0.0, 0.0])
    if np.linalg.norm(a0) < PARALLEL:
        a0 = np.cross(u, [0.0, 1.0, 0.0])
    a0 /= np.linalg.norm(a0)
    a1 = np.cross(u, a0)
    rel = cell_vertices - origin
    pts = np.c_[rel @ a0, rel @ a1]
    hull = ConvexHull(pts)
    poly = pts[hull.vertices]
    q = np.zeros(2)
    inside = (hull.equations[:, :2] @ q + hull.equations[:, 2] <= 0).all()
    if inside:
        return 0.0
    return min(_point_segment_2d(q, poly[k], poly[(k + 1) % len(poly)]) for k in range(len(poly)))


@dataclass
class DualEdges:
    """Power-diagram edges of some WDT faces, recomputed in torch (float64, differentiable).

    Attributes:
        start: (K, 3) orthocentre of the face's first tet.
        end: (K, 3) orthocentre of the second tet, or the unit outward ray direction for hull faces.
        sample: (K, 3) midpoint of a segment, or start + ray_length * direction for a ray.
        is_ray: (K,) bool.
    """

    start: torch.Tensor
    end: torch.Tensor
    sample: torch.Tensor
    is_ray: torch.Tensor


def dual_edges(points: torch.Tensor, weights: torch.Tensor, pd, face_ids: np.ndarray,
               ray_length: float) -> DualEdges:
    """Recomputes the dual edges of WDT faces `face_ids` ((K,) ints) of the `PowerDiagram` pd in torch from
    (points, weights) and the diagram's combinatorics; only the orthocentres of their tets are computed."""
    face_ids = np.asarray(face_ids, dtype=np.int64)
    ft = pd.face_tets[face_ids]
    tets, inverse = np.unique(np.maximum(ft, 0), return_inverse=True)
    inverse = torch.from_numpy(inverse.reshape(-1, 2))
    cc = geometry.orthocentres(points, weights, torch.from_numpy(pd.tets[tets]).long())
    is_ray = torch.from_numpy(pd.is_hull[face_ids])
    start = cc[inverse[:, 0]]
    end = cc[inverse[:, 1]]
    hull = np.flatnonzero(pd.is_hull[face_ids])
    if len(hull):
        n = geometry.face_normals(points, torch.from_numpy(pd.faces[face_ids[hull]]).long())
        sign = torch.sign((n.detach() * torch.from_numpy(pd.ray_dirs[face_ids[hull]])).sum(-1))
        sign = torch.where(sign == 0, torch.ones_like(sign), sign)
        end = end.index_put((torch.from_numpy(hull),), n * sign[:, None])
    sample = torch.where(is_ray[:, None], start + ray_length * end, 0.5 * (start + end))
    return DualEdges(start, end, sample, is_ray)


def _numpy_edges(pd, ray_length: float):
    """(F, 3) start, (F, 3) end (ray direction for hull faces), (F, 3) sample of every dual edge (float64)."""
    start = pd.orthocentres[pd.face_tets[:, 0]]
    hull = pd.is_hull[:, None]
    end = np.where(hull, pd.ray_dirs, pd.orthocentres[np.maximum(pd.face_tets[:, 1], 0)])
    sample = np.where(hull, start + ray_length * end, 0.5 * (start + end))
    return start, end, sample


def existing_deltas(points: torch.Tensor, weights: torch.Tensor, pd, neighbours, ray_length: float,
                    upper: float | None = None, face_ids: np.ndarray | None = None) -> torch.Tensor:
    """Torch reference of `dmesh.probability.existing_deltas` (same arguments and result)."""
    p = native.as_points(points)
    w = native.as_weights(weights, len(p))
    ids = np.arange(len(pd.faces)) if face_ids is None else np.asarray(face_ids, dtype=np.int64)
    faces_np = pd.faces if face_ids is None else pd.faces[ids]
    start = pd.orthocentres[pd.face_tets[ids, 0]]
    hull = pd.is_hull[ids, None]
    other = pd.orthocentres[np.maximum(pd.face_tets[ids, 1], 0)]
    sample = np.where(hull, start + ray_length * pd.ray_dirs[ids], 0.5 * (start + other))
    j, dist = native.nearest_planes_raw(p, w, faces_np, sample, neighbours.offsets, neighbours.indices)
    dist = np.where(j >= 0, dist, ray_length)
    out = torch.from_numpy(dist)
    active = np.arange(len(ids)) if upper is None else np.flatnonzero(dist.mean(1) < upper)
    if len(active) == 0:
        return out
    edges = dual_edges(points, weights, pd, ids[active], ray_length)
    faces = torch.from_numpy(faces_np[active]).long()
    jt = torch.from_numpy(j[active]).long()
    valid = jt >= 0
    jj = torch.where(valid, jt, faces)  # a harmless stand-in index where there is none, masked below
    d = geometry.bisector_distance(points[faces], weights[faces], points[jj], weights[jj],
                                   edges.sample[:, None, :].expand(-1, 3, -1))
    d = torch.where(valid, d, torch.full_like(d, ray_length))
    return out.index_put((torch.from_numpy(active),), d)


def nonexisting_deltas(points: torch.Tensor, weights: torch.Tensor, pd, faces: np.ndarray,
                       ray_length: float, band: float | None = None) -> torch.Tensor:
    """Torch reference of `dmesh.probability.nonexisting_deltas` (same arguments and result)."""
    out = torch.full((len(faces), 3), float(ray_length), dtype=torch.float64)
    if len(faces) == 0:
        return out
    p64 = native.as_points(points)
    w64 = native.as_weights(weights, len(p64))
    e1 = p64[faces[:, 1]] - p64[faces[:, 0]]
    e2 = p64[faces[:, 2]] - p64[faces[:, 0]]
    area2 = (np.cross(e1, e2) ** 2).sum(1)
    good = np.flatnonzero(area2 > COLLINEAR * (e1 ** 2).sum(1) * (e2 ** 2).sum(1))
    if len(good) == 0:
        return out
    fg = np.ascontiguousarray(faces[good], dtype=np.int32)
    with torch.no_grad():
        origin, direction, _ = geometry.dual_lines(torch.from_numpy(p64), torch.from_numpy(w64),
                                                   torch.from_numpy(fg).long())
    start, end, _ = _numpy_edges(pd, ray_length)
    edge, crosses, dist = native.nearest_cell_edges_raw(
        p64, w64, fg, origin.numpy(), direction.numpy(), pd.point_faces.offsets, pd.point_faces.indices,
        start, end, pd.is_hull.astype(np.uint8), pd.point_neighbors.offsets, pd.point_neighbors.indices)
    dist = np.where((edge >= 0) | (crosses > 0), dist, ray_length)
    out = out.index_put((torch.from_numpy(good),), torch.from_numpy(dist))
    sel = np.arange(len(good)) if band is None else np.flatnonzero(dist.mean(1) < band)
    # Only elements with a gradient are recomputed: an edge was chosen and the line misses the cell.
    sel = sel[((edge[sel] >= 0) & (crosses[sel] == 0)).any(1)]
    if len(sel) == 0:
        return out
    o, u, _ = geometry.dual_lines(points, weights, torch.from_numpy(fg[sel]).long())
    et = edge[sel]
    has_edge = et >= 0
    used, inverse = np.unique(np.maximum(et, 0), return_inverse=True)
    edges = dual_edges(points, weights, pd, used, ray_length)
    inv = torch.from_numpy(inverse.reshape(-1, 3))
    d = geometry.line_segment_distance(o[:, None, :].expand(-1, 3, -1), u[:, None, :].expand(-1, 3, -1),
                                       edges.start[inv], edges.end[inv], edges.is_ray[inv])
    keep = torch.from_numpy(has_edge & (crosses[sel] == 0))
    d = torch.where(keep, d, torch.from_numpy(dist[sel]))
    return out.index_put((torch.from_numpy(good[sel]),), d)
