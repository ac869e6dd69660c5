"""Seeded area-uniform surface samples with face normals (the point-cloud inputs, DESIGN.md 8.1).

Shape letters: N samples, F faces, V vertices.
"""
from __future__ import annotations

import logging

import numpy as np
import trimesh

log = logging.getLogger(__name__)

__all__ = ["sample_points", "DEFAULT_SAMPLES"]

#: Samples per point cloud in the paper's convention.
DEFAULT_SAMPLES = 100_000


def sample_points(mesh: trimesh.Trimesh, n: int = DEFAULT_SAMPLES, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Draw `n` points uniformly by area on the surface, each with its face's unit normal.

    A face is drawn with probability proportional to its area (inverse CDF of the cumulative areas), then a
    point uniformly inside it (barycentric coordinates u, v ~ U(0, 1), folded when u + v > 1). Computed in
    float64 and returned as float32; the same mesh, n and seed give identical arrays.

    Args:
        mesh: vertices (V, 3), faces (F, 3) with positive total area.
        n: number of samples, >= 0.
        seed: seed of `numpy.random.default_rng`.

    Returns:
        points: (n, 3) float32 on the surface.
        normals: (n, 3) float32 unit face normals (winding orientation; zero-area faces are never drawn).

    Raises:
        ValueError: n < 0, no faces, or zero total area.
    """
    n = int(n)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    if len(f) == 0:
        raise ValueError("cannot sample a mesh without faces")
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    cum = np.cumsum(double_area)
    total = cum[-1]
    if not np.isfinite(total) or total <= 0:
        raise ValueError(f"cannot sample a mesh with total area {total / 2:g}")
    rng = np.random.default_rng(seed)
    idx = np.searchsorted(cum, rng.random(n) * total, side="right")
    idx = np.minimum(idx, len(f) - 1)
    uv = rng.random((n, 2))
    fold = uv.sum(axis=1) > 1.0
    uv[fold] = 1.0 - uv[fold]
    t = tri[idx]
    points = t[:, 0] + uv[:, :1] * (t[:, 1] - t[:, 0]) + uv[:, 1:] * (t[:, 2] - t[:, 0])
    normals = cross[idx] / double_area[idx, None]
    return points.astype(np.float32), normals.astype(np.float32)
