"""Which triangles cross which (MeshLab's definition of a self-intersection), and smoothing a patch until its
faces cross none: the surface step's tests of its hole fills and faired lids.

Letters: V vertices, F faces, T tested triangles, P pairs.

Written here: pymeshlab's self-intersection filter is a harness extra, and CGAL's (through the native module)
tests every pair of the mesh where only the few fill triangles against their neighbours are needed.
"""
from __future__ import annotations

import numpy as np

from dmesh.surface.config import Fair
from dmesh.surface.topology import half_edges
from dmesh.tolerances import FLOAT64_FLOOR


def segments_through_triangles(p0: np.ndarray, p1: np.ndarray, a: np.ndarray, b: np.ndarray,
                               c: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """(P,) bool: segment p0[i] p1[i] passes through the interior of triangle a[i] b[i] c[i], all (P, 3)
    float64 (Moller and Trumbore, "Fast, minimum storage ray-triangle intersection", JGT 1997). A segment
    that only touches the triangle, or lies in its plane, does not."""
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("pc,pc->p", e1, h)
    ok = np.abs(det) > FLOAT64_FLOOR
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p0 - a
    u = np.einsum("pc,pc->p", s, h) * inv
    q = np.cross(s, e1)
    w = np.einsum("pc,pc->p", d, q) * inv
    t = np.einsum("pc,pc->p", e2, q) * inv
    return ok & (u > eps) & (w > eps) & (u + w < 1 - eps) & (t > eps) & (t < 1 - eps)


def triangles_cross(vertices: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(P,) bool over pairs of triangles s[i], t[i] ((P, 3) vertex ids): an edge of one passes through the
    other. Pairs sharing one vertex test only the edges opposite it (as VCG's self-intersection filter
    does); pairs sharing an edge or more never cross."""
    same = s[:, :, None] == t[:, None, :]
    n = same.any(2).sum(1)
    out = np.zeros(len(s), bool)
    for x, y, x_shared in ((s, t, same.any(2)), (t, s, same.any(1))):
        a, b, c = (vertices[y[:, k]] for k in range(3))
        for i in range(3):  # the edge of x opposite its corner i
            use = (n == 0) | ((n == 1) & x_shared[:, i])
            if use.any():
                j, k = (i + 1) % 3, (i + 2) % 3
                hit = segments_through_triangles(vertices[x[use, j]], vertices[x[use, k]], a[use], b[use], c[use])
                out[np.flatnonzero(use)[hit]] = True
    return out


class FaceIndex:
    """Bounding spheres (centroid, farthest corner) of faces and a tree of their centroids, to find the faces
    that a few triangles cross (`crossing`) without rebuilding it for each batch."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        from scipy.spatial import cKDTree

        self.vertices, self.faces = vertices, np.asarray(faces, dtype=np.int64)
        self.centres, self.radii = _spheres(vertices, self.faces)
        # One tree per power-of-two band of radii: a search reaches only as far as the band's largest face.
        band = np.floor(np.log2(np.maximum(self.radii, FLOAT64_FLOOR))).astype(np.int64)
        self.bands = []
        for b in np.unique(band):
            members = np.flatnonzero(band == b)
            self.bands.append((members, cKDTree(self.centres[members]), self.radii[members].max()))

    def crossing(self, tris: np.ndarray) -> np.ndarray:
        """(T,) bool: triangles `tris` ((T, 3) vertex ids) crossing one of the faces (`triangles_cross`;
        the faces may contain them). Candidate pairs are those whose bounding spheres overlap."""
        tris = np.asarray(tris, dtype=np.int64)
        hit = np.zeros(len(tris), bool)
        if len(tris) == 0 or len(self.faces) == 0:
            return hit
        centres, radii = _spheres(self.vertices, tris)
        for members, tree, reach in self.bands:
            near = tree.query_ball_point(centres, radii + reach)
            ti = np.repeat(np.arange(len(tris)), [len(x) for x in near])
            if len(ti) == 0:
                continue
            fi = members[np.concatenate([np.asarray(x, np.int64) for x in near])]
            close = np.linalg.norm(centres[ti] - self.centres[fi], axis=1) <= radii[ti] + self.radii[fi]
            ti, fi = ti[close], fi[close]
            hit[ti[triangles_cross(self.vertices, tris[ti], self.faces[fi])]] = True
        return hit


def _spheres(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3) centroids and (F,) distances to the farthest corner of the triangles `faces`."""
    corners = vertices[faces]
    centres = corners.mean(1)
    return centres, np.linalg.norm(corners - centres[:, None], axis=2).max(1)


def crossing_triangles(vertices: np.ndarray, tris: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T,) bool: triangles `tris` crossing a triangle of `faces` (`FaceIndex.crossing`)."""
    return FaceIndex(vertices, faces).crossing(tris)


def untangle(vertices: np.ndarray, faces: np.ndarray, patch: np.ndarray, rounds: int = Fair.untangle_rounds,
             hold: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Smooths away the folds of a patch: where a patch face crosses another face (`FaceIndex`), the patch's
    free vertices (those on patch faces only) within two rings of it move to the mean of their neighbours (five
    uniform Laplacian sweeps), and the test runs again, up to `rounds` times.

    Written here: the folds are a few faces of a faired patch (`dmesh.native.refine_and_fair` over a jagged
    rim), and the smoothing must stay inside the patch, which the libraries' whole-mesh smoothers do not.

    Args:
        vertices: (V, 3) float; faces: (F, 3) int; patch: (F,) bool.
        hold: None, or (H,) bool over the first H vertices: those that are never free.
    Returns:
        (V, 3) float64 vertices (only free patch vertices moved) and (P,) bool over `faces[patch]`: the patch
        faces that still cross a face.
    """
    from scipy.sparse import coo_matrix

    v = np.array(vertices, dtype=np.float64, copy=True)
    f = np.asarray(faces, dtype=np.int64)
    patch = np.asarray(patch, dtype=bool)
    tris = f[patch]
    hit = FaceIndex(v, f).crossing(tris)
    if not hit.any():
        return v, hit
    free = np.zeros(len(v), bool)
    free[tris.reshape(-1)] = True
    free[f[~patch].reshape(-1)] = False
    if hold is not None:
        free[:len(hold)] &= ~np.asarray(hold, dtype=bool)
    e = half_edges(tris)
    ring = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(v), len(v))).tocsr()
    ring = ((ring + ring.T) > 0).astype(np.float64)
    degree = np.maximum(np.asarray(ring.sum(1)).reshape(-1), 1.0)
    for _ in range(rounds):
        region = np.zeros(len(v), bool)
        region[tris[hit].reshape(-1)] = True
        for _ in range(2):
            region |= (ring @ region.astype(np.float64)) > 0
        region &= free
        if not region.any():
            break
        rows = ring[region]
        for _ in range(5):
            v[region] = (rows @ v) / degree[region, None]
        hit = FaceIndex(v, f).crossing(tris)
        if not hit.any():
            break
    return v, hit


__all__ = ["segments_through_triangles", "triangles_cross", "FaceIndex", "crossing_triangles", "untangle"]
