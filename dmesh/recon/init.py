"""Initialisation of a DMesh from surface samples (paper appendix 9.2, "Point Initialization with Sample
Points"; upstream `sample_points_init`).

Letters: G input points, S seeds, V Voronoi vertices kept.

Seeds are a random subset of the input points (real value 1); the Voronoi vertices of the seeds (the
circumcentres of their Delaunay tets), which lie near the medial axis, are added inside the box
[-domain, domain]^3 as imaginary points (real value 0), with optional box corners (see below). All weights start at 1 (equal weights: the first
triangulation is the Delaunay triangulation).
"""
from __future__ import annotations

import numpy as np

from dmesh import wdt


def seeds_and_voronoi(points: np.ndarray, num_seeds: int, rng: np.random.Generator, domain: float = 1.0,
                      max_voronoi: int | None = None, corner_box: float | None = 1.25,
                      keep: str = "largest") -> tuple[np.ndarray, np.ndarray]:
    """Initial DMesh points and real values.

    Args:
        points: (G, 3) float input samples (in a unit-radius frame).
        num_seeds: seeds drawn without replacement (all points when G is smaller).
        rng: NumPy generator.
        domain: Voronoi vertices outside [-domain, domain]^3 are dropped.
        max_voronoi: keep at most this many Voronoi vertices; None keeps all.
        keep: which ones `max_voronoi` keeps: "largest" (those farthest from the seeds, i.e. with the
            largest empty sphere: nearest the medial axis, where they carve; small spheres hug the surface
            and are what punches holes into the first mesh) or "random".
        corner_box: when set, the 8 corners of [-corner_box, corner_box]^3 join the seeds' triangulation
            and are returned as imaginary points: flat inputs (a disc) then still have a 3D triangulation,
            and the surface stays away from the hull. None: seeds only (upstream; fails on flat inputs).
    Returns:
        positions: (S + V (+ 8), 3) float64, seeds first, then Voronoi vertices, then corners;
        reals: float64, 1 for seeds and 0 otherwise.
    Raises:
        ValueError: fewer than 4 distinct seeds or all of them coplanar.
    """
    pts = np.asarray(points, dtype=np.float64)
    s = min(int(num_seeds), len(pts))
    seeds = pts[rng.choice(len(pts), s, replace=False)] if s < len(pts) else pts.copy()
    seeds = np.unique(seeds, axis=0)
    if len(seeds) < 4:
        raise ValueError(f"need at least 4 distinct points to initialise, got {len(seeds)}")
    corners = np.zeros((0, 3))
    if corner_box is not None:
        corners = corner_box * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    pd = wdt.PowerDiagram.from_points(np.concatenate([seeds, corners]), None)
    vor = pd.orthocentres
    radius = np.linalg.norm(vor - pd.points[pd.tets[:, 0]], axis=1)
    inside = np.isfinite(vor).all(1) & (np.abs(vor) <= domain).all(1)
    vor, radius = vor[inside], radius[inside]
    vor, first = np.unique(np.round(vor, 12), axis=0, return_index=True)
    radius = radius[first]
    if max_voronoi is not None and len(vor) > max_voronoi:
        if keep == "largest":
            vor = vor[np.argsort(-radius, kind="stable")[: int(max_voronoi)]]
        elif keep == "random":
            vor = vor[rng.choice(len(vor), int(max_voronoi), replace=False)]
        else:
            raise ValueError(f"keep must be 'largest' or 'random', got {keep!r}")
    positions = np.concatenate([seeds, vor, corners])
    reals = np.r_[np.ones(len(seeds)), np.zeros(len(vor) + len(corners))]
    return positions, reals


__all__ = ["seeds_and_voronoi"]
