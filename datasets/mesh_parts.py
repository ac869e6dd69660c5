"""Building blocks of the synthetic shapes (`datasets.synthetic`, `datasets.families`): parameter-grid faces,
polar patches, tubes around closed curves, the Z-up to Y-up turn of every generator's output, rotations,
concatenation without merging, and manifold3d booleans.

Shape letters: V vertices, F faces, U x W a parameter grid of vertices.
"""
from __future__ import annotations

import functools
from typing import Callable

import numpy as np
import trimesh

__all__ = ["grid_faces", "polar_patch", "tube", "y_up", "rotation", "concat", "boolean", "Z_UP_TO_Y_UP"]


def grid_faces(nu: int, nw: int, wrap_u: bool = False, wrap_w: bool = False,
                flip_u: bool = False) -> np.ndarray:
    """Triangles of a U x W vertex grid (vertex (i, j) has index i * nw + j).

    Args:
        nu, nw: grid size along u and w.
        wrap_u: connect row nu-1 back to row 0 (a tube along u).
        wrap_w: connect column nw-1 back to column 0.
        flip_u: with wrap_u, row 0 is glued reversed (j -> nw-1-j): a Mobius band.

    Returns:
        (F, 3) int64 faces, two per grid quad, consistently oriented (except across a Mobius seam).
    """
    iu = np.arange(nu if wrap_u else nu - 1)
    jw = np.arange(nw if wrap_w else nw - 1)
    i, j = np.meshgrid(iu, jw, indexing="ij")
    i, j = i.ravel(), j.ravel()
    i1 = (i + 1) % nu
    j1 = (j + 1) % nw
    a = i * nw + j
    d = i * nw + j1
    seam = wrap_u & (i1 == 0) if flip_u else np.zeros_like(i, bool)
    jb = np.where(seam, nw - 1 - j, j)
    jc = np.where(seam, nw - 1 - j1, j1)
    b = i1 * nw + jb
    c = i1 * nw + jc
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)


def polar_patch(rings: np.ndarray, center: np.ndarray) -> trimesh.Trimesh:
    """An open disc-like patch: a centre vertex fanned to the first of concentric closed rings.

    Args:
        rings: (R, S, 3) float64, R rings of S points each, from the centre outwards.
        center: (3,) float64, the centre vertex.

    Returns:
        A mesh with 1 + R * S vertices and S * (2R - 1) faces; the last ring is its boundary.
    """
    r, s = rings.shape[:2]
    verts = np.concatenate([center[None], rings.reshape(-1, 3)])
    j = np.arange(s)
    fan = np.stack([np.zeros(s, np.int64), 1 + j, 1 + (j + 1) % s], 1)
    quads = grid_faces(r, s, wrap_w=True) + 1
    return trimesh.Trimesh(verts, np.concatenate([fan, quads]), process=False)


def tube(curve: np.ndarray, radius: float | np.ndarray, sides: int) -> trimesh.Trimesh:
    """A watertight tube around a closed polyline, with twist-corrected parallel-transport frames.

    Args:
        curve: (U, 3) float64 points of a closed curve (the last point is not repeated).
        radius: tube radius, a float or (U,) float64.
        sides: vertices around each cross-section.

    Returns:
        A closed (watertight, genus-1 topology) mesh with U * sides vertices.
    """
    n = len(curve)
    tangent = np.roll(curve, -1, 0) - np.roll(curve, 1, 0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.zeros_like(curve)
    seed = np.array([0.0, 0.0, 1.0]) if abs(tangent[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    normal[0] = np.cross(tangent[0], np.cross(seed, tangent[0]))
    normal[0] /= np.linalg.norm(normal[0])
    for k in range(1, n + 1):  # parallel transport, once around (k == n measures the holonomy)
        t = tangent[k % n]
        nk = normal[k - 1] - np.dot(normal[k - 1], t) * t
        nk /= np.linalg.norm(nk)
        if k < n:
            normal[k] = nk
        else:
            closing = nk
    # Spread the holonomy angle along the curve so the frames close up.
    b0 = np.cross(tangent[0], normal[0])
    twist = np.arctan2(np.dot(closing, b0), np.dot(closing, normal[0]))
    angle = -twist * np.arange(n) / n
    binormal = np.cross(tangent, normal)
    normal, binormal = (np.cos(angle)[:, None] * normal + np.sin(angle)[:, None] * binormal,
                        -np.sin(angle)[:, None] * normal + np.cos(angle)[:, None] * binormal)
    phi = 2 * np.pi * np.arange(sides) / sides
    r = np.broadcast_to(np.asarray(radius, float), (n,))[:, None, None]
    ring = np.cos(phi)[None, :, None] * normal[:, None] + np.sin(phi)[None, :, None] * binormal[:, None]
    verts = (curve[:, None] + r * ring).reshape(-1, 3)
    faces = grid_faces(n, sides, wrap_u=True, wrap_w=True)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


#: Z-up (how the generators model) to Y-up (how shapes are returned): (x, y, z) -> (x, z, -y).
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def y_up(fn: Callable[..., trimesh.Trimesh]) -> Callable[..., trimesh.Trimesh]:
    """Rotate a Z-up generator's output to Y-up (a proper rotation: winding and volume sign are kept).

    Composite shapes build on the raw Z-up parts through `fn.__wrapped__`.
    """
    @functools.wraps(fn)
    def wrapper(*args, **kwargs) -> trimesh.Trimesh:
        m = fn(*args, **kwargs)
        return trimesh.Trimesh(np.asarray(m.vertices, np.float64) @ Z_UP_TO_Y_UP[:3, :3].T,
                               np.asarray(m.faces, np.int64), process=False)
    return wrapper


def rotation(axis, angle: float) -> np.ndarray:
    """(4, 4) float64 rotation about `axis` through the origin."""
    return trimesh.transformations.rotation_matrix(angle, np.asarray(axis, float))


def concat(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Concatenate parts into one mesh without merging any vertices (components stay apart)."""
    verts, faces, offset = [], [], 0
    for p in parts:
        verts.append(np.asarray(p.vertices, np.float64))
        faces.append(np.asarray(p.faces, np.int64) + offset)
        offset += len(p.vertices)
    return trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)


def boolean(op: str, meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """A trimesh boolean with the manifold3d engine; says which extra to install if it is missing."""
    try:
        import manifold3d  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("CSG shapes need the manifold3d package: pip install 'dmesh-harness[harness]'") from exc
    fn = {"union": trimesh.boolean.union, "difference": trimesh.boolean.difference,
          "intersection": trimesh.boolean.intersection}[op]
    out = fn(meshes, engine="manifold", check_volume=False)
    return trimesh.Trimesh(out.vertices, out.faces, process=False)
