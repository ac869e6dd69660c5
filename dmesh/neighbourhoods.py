"""Local planes of point neighbourhoods (NumPy): how flat a point's neighbours lie and how far off their plane
the point lies. Shared by the point-cloud outlier filter (`dmesh.recon.init.statistical_inliers`) and the surface
step (`dmesh.surface.holes.sheet_hole_loops`, `dmesh.surface.debris.floating_crumbs`), which ask the same question
of a sample and of a mesh vertex: does it lie on the surface its neighbours form?
"""
from __future__ import annotations

import numpy as np

#: A neighbourhood counts as a piece of surface when its smallest PCA eigenvalue is under this share of the sum.
SURFACE_VARIATION = 0.03


def plane_offsets(points: np.ndarray, at: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each point `points[at[i]]`, the least-squares plane of `points[neighbours[i]]` ((Q, k) ints, the point
    itself not among them): (Q,) its variation (smallest PCA eigenvalue over their sum; `SURFACE_VARIATION`) and
    (Q,) the point's distance from that plane."""
    nb = points[neighbours]
    centre = nb.mean(1, keepdims=True)
    vals, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb - centre, nb - centre))
    variation = vals[:, 0] / np.maximum(vals.sum(1), np.finfo(float).tiny)
    off = np.abs(np.einsum("ni,ni->n", points[at] - centre[:, 0], vecs[:, :, 0]))
    return variation, off
