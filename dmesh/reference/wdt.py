"""Naive references for the weighted Delaunay triangulation and power diagram.

Letters: N points, T tets, F faces.
"""
from __future__ import annotations

import numpy as np


def lifted_hull_tets(points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(T, 4) int tets of the WDT as the lower convex hull of the lifted points (SciPy Qhull).

    Lift p -> (p, |p|^2 - w); lower-hull facets project to the regular tetrahedra. Only valid for points in
    general position (Qhull adds flat tets on degenerate input such as grids).
    """
    from scipy.spatial import ConvexHull

    p = np.asarray(points, dtype=np.float64)
    c = p.mean(axis=0)
    q = p - c  # centre first: the lift is translation-covariant and this keeps the numbers small
    lifted = np.c_[q, (q * q).sum(1) - np.asarray(weights, dtype=np.float64)]
    hull = ConvexHull(lifted, qhull_options="Qt")
    return hull.simplices[lower_facets(hull)]


def lower_facets(hull) -> np.ndarray:
    """(facets,) bool: facets of a lifted 4D hull whose outward normal points down the lift axis."""
    return hull.equations[:, 3] < -1e-12


def gudhi_tets(points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(T, 4) int tets of the WDT from gudhi's weighted Delaunay complex (CGAL dD, exact)."""
    import gudhi

    st = gudhi.DelaunayComplex(points=np.asarray(points, dtype=np.float64).tolist(),
                               weights=np.asarray(weights, dtype=np.float64).tolist(),
                               precision="safe").create_simplex_tree()
    tets = [s for s, _ in st.get_skeleton(3) if len(s) == 4]
    return np.array(tets, dtype=np.int64).reshape(-1, 4)


def canonical_tets(tets: np.ndarray) -> np.ndarray:
    """Sorted rows, lexicographically sorted: a canonical form for comparing tet sets."""
    t = np.sort(np.asarray(tets, dtype=np.int64), axis=1)
    return t[np.lexsort(t.T[::-1])] if len(t) else t.reshape(0, 4)


def orthocentres(points: np.ndarray, weights: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T, 3) orthocentres by solving 2 (p_j - p_0) . c = |p_j|^2 - |p_0|^2 - (w_j - w_0) per tet."""
    p = np.asarray(points, dtype=np.float64)[tets]
    w = np.asarray(weights, dtype=np.float64)[tets]
    A = 2 * (p[:, 1:] - p[:, :1])
    b = (p[:, 1:] ** 2).sum(-1) - (p[:, :1] ** 2).sum(-1) - (w[:, 1:] - w[:, :1])
    return np.linalg.solve(A, b[..., None])[..., 0]


def power_distance(x: np.ndarray, points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(M, N) power distance |x_m - p_n|^2 - w_n."""
    d = x[:, None, :] - points[None, :, :]
    return (d * d).sum(-1) - weights[None, :]


def empty_power_sphere_violations(points: np.ndarray, weights: np.ndarray, tets: np.ndarray,
                                  tol: float = 1e-9) -> np.ndarray:
    """(T,) bool: tets whose orthosphere has some other point strictly closer in power than its own points.

    A triangulation is the WDT exactly when no tet has such a violation (brute force, O(T N)).
    """
    c = orthocentres(points, weights, tets)
    pd = power_distance(c, np.asarray(points, np.float64), np.asarray(weights, np.float64))
    own = np.take_along_axis(pd, np.asarray(tets, np.int64), axis=1).mean(axis=1)
    scale = 1.0 + np.abs(own)
    mask = np.ones_like(pd, dtype=bool)
    np.put_along_axis(mask, np.asarray(tets, np.int64), False, axis=1)
    return ((pd < own[:, None] - tol * scale[:, None]) & mask).any(axis=1)
