"""Which faces of a DMesh make its mesh (paper section 4; DESIGN.md section 6).

Letters: N points, T tets, F WDT faces.

A face is on the mesh when it is in the WDT and its three points are real (real value above a threshold).
Modes, from upstream's to ours:

- "all": every such face (upstream's extraction for point clouds).
- "no_interior": also drops faces whose two tets are both all-real, i.e. faces inside a solid block of
  real tets (upstream's `remove_invisible`, used for multi-view).
- "sheet": a connected block of all-real tets ("cluster") is a thickened piece of surface: four surface
  samples that no imaginary point separates. Its interior faces are dropped as in "no_interior", and of its
  boundary, which is two sheets (one facing each side of the surface), only one is kept: the one with the
  larger area, which on a convex patch is the one closer to the surface. A side is told by the apex of the
  tet across each boundary face, against the cluster's normal (its points' direction of least variance).
  Upstream keeps both sheets, so its meshes have many non-manifold edges (e.g. 42K on a torus from 40K
  samples), and the inner sheet lies farther from the surface. Measured on that torus (point-to-surface CD
  x1e-3, first mesh of `seeds_and_voronoi(..., vertices="poles")`): "all" 0.283 with 42634 non-manifold
  edges; "no_interior" 0.251; "sheet" 0.201 with no non-manifold or boundary edge (the smaller sheet: 0.299).
  Clusters are small there (median 2 tets, largest 24), so one normal per cluster is enough.
"""
from __future__ import annotations

import numpy as np

MODES = ("all", "no_interior", "sheet")


def mesh_faces(pd, real: np.ndarray, mode: str = "all") -> np.ndarray:
    """(F,) bool mask of the faces of `pd` (a `dmesh.wdt.PowerDiagram`) on the mesh.

    Args:
        pd: the power diagram (faces, face_tets, tets, points).
        real: (N,) bool, which points are real.
        mode: "all", "no_interior" or "sheet" (module docstring).
    """
    if mode not in MODES:
        raise ValueError(f"unknown extraction mode {mode!r}; choose from {', '.join(MODES)}")
    real = np.asarray(real, dtype=bool)
    on = real[pd.faces].all(1)
    if mode == "all" or not on.any():
        return on
    real_tet = np.r_[real[pd.tets].all(1), False]  # index -1 (hull side) reads False
    n_real = real_tet[pd.face_tets].sum(1)
    if mode == "no_interior":
        return on & (n_real < 2)
    keep = on & (n_real == 0)
    keep[_one_sheet(pd, real_tet[:-1], on & (n_real == 1), on & (n_real == 2))] = True
    return keep


def _one_sheet(pd, real_tet: np.ndarray, boundary: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """Ids of the boundary faces of each all-real-tet cluster on its larger-area side."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    T = len(pd.tets)
    a, b = pd.face_tets[interior, 0], pd.face_tets[interior, 1]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(T, T))
    n_comp, label = connected_components(graph, directed=False)

    ids = np.flatnonzero(boundary)
    ft = pd.face_tets[ids].astype(np.int64)
    first_real = real_tet[ft[:, 0]]
    inner = np.where(first_real, ft[:, 0], ft[:, 1])
    outer = np.where(first_real, ft[:, 1], ft[:, 0])
    cluster = label[inner]

    normal = _cluster_normals(pd.points, pd.tets, np.flatnonzero(real_tet), label, n_comp)
    faces = pd.faces[ids].astype(np.int64)
    p = pd.points
    centre = p[faces].mean(1)
    # The apex of the tet across: its vertex sum minus the face's (vertex ids are distinct). A hull face
    # has no tet across; its apex is taken on the negative side.
    apex = pd.tets[np.maximum(outer, 0)].astype(np.int64).sum(1) - faces.sum(1)
    side = np.einsum("ij,ij->i", p[apex] - centre, normal[cluster]) > 0
    side &= outer >= 0
    area = 0.5 * np.linalg.norm(np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]]), axis=1)
    area_pos = np.bincount(cluster, area * side, n_comp)
    area_neg = np.bincount(cluster, area * ~side, n_comp)
    return ids[side == (area_pos >= area_neg)[cluster]]


def _cluster_normals(points: np.ndarray, tets: np.ndarray, real_tets: np.ndarray, label: np.ndarray,
                     n_comp: int) -> np.ndarray:
    """(n_comp, 3) unit direction of least variance of each cluster's tet vertices (zero for no tets)."""
    x = points[tets[real_tets].reshape(-1)]
    lab = np.repeat(label[real_tets], 4)
    count = np.maximum(np.bincount(lab, minlength=n_comp), 1)[:, None]
    mean = np.stack([np.bincount(lab, x[:, i], n_comp) for i in range(3)], 1) / count
    y = x - mean[lab]
    cov = np.empty((n_comp, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(lab, y[:, i] * y[:, j], n_comp)
    _, vectors = np.linalg.eigh(cov)  # ascending eigenvalues: column 0 is the least-variance direction
    return vectors[:, :, 0]


__all__ = ["MODES", "mesh_faces"]
