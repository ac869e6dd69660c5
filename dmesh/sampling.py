"""Area-uniform random points on a triangle mesh.

Letters: F faces, n samples.

Each draw picks a face with probability proportional to its area, then a uniform point in it: two uniform
numbers (u, w), folded into the triangle when u + w > 1, give a + u (b - a) + w (c - a).
"""
from __future__ import annotations

import numpy as np

from dmesh.solid import face_areas


def sample_surface(mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 area-uniform random points on a triangle mesh (anything with `vertices`, `faces`).

    A mesh of zero area gives (up to n of) its corners instead. Draws from `rng`: one face choice, then u,
    then w, n each.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    tri = v[f]
    area = face_areas(v, f)
    if not area.sum() > 0:
        return tri.reshape(-1, 3)[:n].copy()
    pick = rng.choice(len(f), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    fold = u + w > 1.0
    u[fold], w[fold] = 1.0 - u[fold], 1.0 - w[fold]
    t = tri[pick]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])


__all__ = ["sample_surface"]
