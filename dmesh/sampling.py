"""Area-uniform random points on a triangle mesh.

Letters: F faces, n samples.

Each draw picks a face with probability proportional to its area, then a uniform point in it: two uniform
numbers (u, w), folded into the triangle when u + w > 1, give a + u (b - a) + w (c - a).
"""
from __future__ import annotations

import numpy as np

from dmesh.solid import face_areas


def vertex_axes(vertices: np.ndarray, faces: np.ndarray, smooth: float = 0.7) -> np.ndarray:
    """(V, 3) unit normal axis per vertex, whatever the faces' winding; zero rows at creases and corners.

    The axis is the main eigenvector of sum(area n n^T) over the vertex's faces (unit face normals n), so
    a face wound either way counts the same. Where the main eigenvalue is below `smooth` x the trace (the
    faces around the vertex do not share one plane) the row is zero.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    twice_area = np.linalg.norm(cross, axis=1)
    n = cross / np.maximum(twice_area, 1e-300)[:, None]
    outer = 0.5 * twice_area[:, None, None] * n[:, :, None] * n[:, None, :]
    m = np.zeros((len(v), 3, 3))
    for corner in range(3):
        np.add.at(m, f[:, corner], outer)
    values, vectors = np.linalg.eigh(m)
    axis = vectors[:, :, 2].copy()
    trace = values.sum(1)
    axis[~(values[:, 2] >= smooth * np.maximum(trace, 1e-300)) | ~(trace > 0)] = 0.0
    return axis


def sample_surface(mesh, n: int, rng: np.random.Generator, phong: float = 0.0) -> np.ndarray:
    """(n, 3) float64 area-uniform random points on a triangle mesh (anything with `vertices`, `faces`).

    A mesh of zero area gives (up to n of) its corners instead. Draws from `rng`: one face choice, then u,
    then w, n each.

    phong: alpha of Phong tessellation (Boubekeur and Alexa 2008; 0: the flat faces, 0.75: their choice).
    Each sample moves to (1 - alpha) p + alpha sum_i b_i P_i(p), b its barycentric weights and P_i the
    projection onto corner i's tangent plane (`vertex_axes`; crease corners do not project), so samples of
    a mesh inscribed in a smooth surface land near that surface instead of a sagitta inside it.
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
    p = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])
    if not phong:
        return p
    axes = vertex_axes(v, f)[f[pick]]  # (n, 3 corners, 3)
    bary = np.stack([1.0 - u - w, u, w], axis=1)
    offset = np.einsum("nij,nij->ni", p[:, None, :] - t, axes)  # (p - v_i) . a_i per corner
    projected = p[:, None, :] - offset[:, :, None] * axes
    return (1.0 - phong) * p + phong * np.einsum("ni,nij->nj", bary, projected)


__all__ = ["sample_surface", "vertex_axes"]
