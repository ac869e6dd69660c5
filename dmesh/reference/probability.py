"""Naive references for the probability kernels.

`line_cell_distance` measures the distance between a line and a bounded convex power cell by projecting
the cell's vertices (its tets' orthocentres) onto the plane normal to the line and measuring the distance
of the line's trace to their 2D convex hull; independent of the native edge search.
"""
from __future__ import annotations

import numpy as np


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
    if np.linalg.norm(a0) < 1e-6:
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
