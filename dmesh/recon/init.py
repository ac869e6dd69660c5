"""Initialisation of a DMesh from surface samples (paper appendix 9.2, "Point Initialization with Sample
Points"; upstream `sample_points_init`).

Letters: G input points, S seeds, V Voronoi vertices kept.

Seeds are a random subset of the input points (real value 1); the Voronoi vertices of the seeds (the
circumcentres of their Delaunay tets), which lie near the medial axis, are added inside the box
[-domain, domain]^3 as imaginary points (real value 0), with optional box corners (see below). All weights
start at 1 (equal weights: the first triangulation is the Delaunay triangulation).

`vertices="poles"` keeps only each seed's two poles (Amenta and Bern's crust: the farthest vertex of its
Voronoi cell, and the farthest on the other side of the seed), instead of every Voronoi vertex. Poles lie
near the medial axis, so the faces among seeds that survive are the crust, which contains the restricted
Delaunay surface: the first mesh has no holes. The other Voronoi vertices include the circumcentres of flat
tets on the surface; they hug the surface and punch holes into the first mesh. Measured on the torus
(10K seeds, point-to-surface CD x1e-3 of the first mesh): all vertices 2.30 (52K of them, 2616 boundary
edges), poles 0.97 (12K). Poles also cost about 4x fewer points, which buys more seeds (40K seeds with
poles: 51K points, CD 0.29).

Walls thinner than the sample spacing (a cup whose wall is 1.1 spacings thick) break the crust: each sample's
nearest neighbours include the other side's, the Voronoi cells are not long across the wall, so the inner poles
lie beside the samples rather than between the two sides and cut the surface triangles, while the faces
across the wall stay. With oriented normals the two sides are told apart: `thin_wall_points` puts imaginary
points on the mid-surface of every wall whose other side lies within a few spacings behind a sample, and
`separate_thin_walls` uses them instead of the poles there (docs/preset_choices.md, "Thin walls").
"""
from __future__ import annotations

import numpy as np

from dmesh import native, wdt
from dmesh.neighbourhoods import SURFACE_VARIATION, plane_offsets


def seeds_and_voronoi(points: np.ndarray, num_seeds: int, rng: np.random.Generator, domain: float = 1.0,
                      max_voronoi: int | None = None, corner_box: float | None = 1.25,
                      vertices: str = "all") -> tuple[np.ndarray, np.ndarray]:
    """Initial DMesh points and real values.

    Args:
        points: (G, 3) float input samples (in a unit-radius frame).
        num_seeds: seeds drawn without replacement (all points when G is smaller).
        rng: NumPy generator.
        domain: Voronoi vertices outside [-domain, domain]^3 are dropped.
        max_voronoi: keep at most this many Voronoi vertices, those farthest from the seeds (the largest
            empty spheres: nearest the medial axis, where they carve; small spheres hug the surface and are
            what punches holes into the first mesh); None keeps all.
        vertices: "all" Voronoi vertices (upstream) or each seed's two "poles" (module docstring).
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
    if vertices == "poles":
        chosen = poles(pd, len(seeds))
        vor, radius = vor[chosen], radius[chosen]
    elif vertices != "all":
        raise ValueError(f"vertices must be 'all' or 'poles', got {vertices!r}")
    inside = np.isfinite(vor).all(1) & (np.abs(vor) <= domain).all(1)
    vor, radius = vor[inside], radius[inside]
    vor, first = np.unique(np.round(vor, 12), axis=0, return_index=True)
    radius = radius[first]
    if max_voronoi is not None and len(vor) > max_voronoi:
        vor = vor[np.argsort(-radius, kind="stable")[: int(max_voronoi)]]
    positions = np.concatenate([seeds, vor, corners])
    reals = np.r_[np.ones(len(seeds)), np.zeros(len(vor) + len(corners))]
    return positions, reals


def carve_far_faces(positions: np.ndarray, reals: np.ndarray, data: np.ndarray, factor: float = 5.0,
                    mode: str = "sheet", max_rounds: int = 5, workers: int = 2) -> tuple[np.ndarray, np.ndarray, int]:
    """Adds imaginary points at the centroids of mesh faces far from the data, until none is left.

    Poles alone do not separate seeds across a hole or past the border of an open surface, so the first
    mesh spans them with large faces. A face whose centroid is farther than `factor` times the median
    seed spacing from every `data` point is such a face: an imaginary point at its centroid removes it
    (and the other faces whose empty spheres hold that point, i.e. the rest of the span). Measured on
    wavy_sheet (a sheet with 3 holes; 40K seeds): point-to-surface CD 2.27e-3 -> 4.3e-5 in one round;
    the torus and plant meshes have no such face at factor 5 and stay the same (at factor 2 good faces
    on sparsely seeded spots go too, and holes open).

    Args:
        positions: (N, 3) float64 points, reals (N,) float64 (> 0.5: real); data: (G, 3) input points.
        factor: the distance threshold in median seed spacings.
        mode: extraction mode of the mesh being checked (`dmesh.extract.MODES`).
    Returns:
        positions, reals (with the added imaginary points at the end) and the number added.
    """
    from scipy.spatial import cKDTree

    from dmesh.extract import mesh_faces

    real = reals > 0.5
    seeds = positions[real]
    if len(seeds) < 2:
        return positions, reals, 0
    spacing = float(np.median(cKDTree(seeds).query(seeds, k=2, workers=workers)[0][:, 1]))
    tree = cKDTree(data)
    added = 0
    for _ in range(max_rounds):
        pd = wdt.PowerDiagram.from_points(positions, None)
        faces = pd.faces[mesh_faces(pd, reals > 0.5, mode)]
        centre = positions[faces].mean(1)
        far = tree.query(centre, workers=workers)[0] > factor * spacing
        if not far.any():
            break
        positions = np.concatenate([positions, centre[far]])
        reals = np.r_[reals, np.zeros(int(far.sum()))]
        added += int(far.sum())
    return positions, reals, added


#: A point flagged by the distance test lies on the surface its neighbours form (their plane's variation under
#: `dmesh.neighbourhoods.SURFACE_VARIATION`) when it is within this many of the neighbours' spacings of it ...
ON_SURFACE = 0.35
#: ... and is as dense as they are when its mean neighbour distance is at most this many times their median.
AS_DENSE = 3.0
#: A point the distance test keeps is still a stray when its neighbours form a piece of surface and it lies more
#: than this many of their spacings off its plane: an outlier that fell near the surface, where its neighbours
#: are as close as the surface's own. Far above where noise the presets leave unsmoothed puts surface samples
#: (such a neighbourhood is too thick to count as a surface), and where a sharp edge bends the plane.
OFF_SURFACE = 1.0


def statistical_inliers(points: np.ndarray, std_ratio: float, k: int = 16, workers: int = 1,
                        keep_surface: bool = True, off_surface: bool = True) -> np.ndarray:
    """(G,) bool: the points kept by statistical outlier removal (as PCL's and Open3D's), with surface samples
    rescued and strays near the surface dropped.

    The distance test flags points whose mean distance to their `k` nearest neighbours is more than the mean of
    those distances plus `std_ratio` standard deviations. Alone it also flags the sparsest few percent of any
    clean sample, and whole regions of a scan where rays graze the surface: the holes it leaves there are what
    carving then opens. So with `keep_surface`, a flagged point stays when its neighbours (without it) form a
    piece of surface (`SURFACE_VARIATION`), it lies on that piece (`ON_SURFACE`) and it is about as dense as
    they are (`AS_DENSE`): a sample of a sparse stretch of surface, not a stray point near one. With
    `off_surface`, a point the distance test keeps is dropped when its neighbours form a piece of surface and it
    lies more than `OFF_SURFACE` of their spacings off it: outliers that fell within a few spacings of the
    surface pass the distance test, and a mesh through them has a spike at each. How much each rule drops on
    the robustness inputs: docs/preset_choices.md and `python -m studies outlier_filter`.

    Written with SciPy's k-d tree and NumPy because the library does not depend on Open3D (a harness extra),
    whose filters have no such rescue."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    kk = min(int(k) + 1, len(pts))
    if kk < 2:
        return np.ones(len(pts), bool)
    dist, idx = cKDTree(pts).query(pts, kk, workers=workers)
    mean = dist[:, 1:].mean(1)
    keep = mean <= mean.mean() + float(std_ratio) * mean.std()
    if kk < 4 or not (keep_surface or off_surface):
        return keep
    test = np.arange(len(pts)) if off_surface else np.flatnonzero(~keep)
    variation, off = plane_offsets(pts, test, idx[test, 1:])
    surface = variation < SURFACE_VARIATION
    spacing = np.median(mean[idx[test, 1:]], axis=1)  # the neighbours' own mean neighbour distance
    if keep_surface:
        on = ~keep[test] & surface & (off < ON_SURFACE * spacing) & (mean[test] <= AS_DENSE * spacing)
        rescued = test[on]
    if off_surface:
        keep[test[keep[test] & surface & (off > OFF_SURFACE * spacing)]] = False
    if keep_surface:
        keep[rescued] = True
    return keep


def smooth_points(points: np.ndarray, k: int, workers: int = 1) -> np.ndarray:
    """(G, 3) float64: every point moved onto the quadratic jet (a height field over the principal plane of
    its neighbourhood) fitted to its `k` nearest neighbours, all fitted to the input positions (CGAL's
    `jet_smooth_point_set`, Cazals and Pouget 2005). Removes noise along the surface normal without the
    inward pull of a plane fit on curved parts; sharp edges are rounded over about k points. `workers` > 1
    lets CGAL use TBB threads. ValueError for k < 6 (a quadratic jet has 6 coefficients) or k >= G."""
    pts = np.asarray(points, dtype=np.float64)
    if not 6 <= int(k) < len(pts):
        raise ValueError(f"smooth_points: k must be in [6, {len(pts) - 1}] for {len(pts)} points, got {k}")
    return native.jet_smooth(pts, int(k), degree=2, parallel=1 if workers > 1 else 0)


#: `noise_ratio` above which an input looks noisy; calibrated on the robustness inputs (docs/preset_choices.md).
NOISY_RATIO = 0.1
#: `noise_ratio` above which lifted depth pixels look noisy (the multi-view `depth` start's `init_preset="auto"`).
#: Lower than `NOISY_RATIO`: depth pixels of overlapping views sample the surface far more densely and evenly than
#: a point cloud, so clean ones lie much closer to their local planes (calibration: docs/preset_choices.md).
DEPTH_NOISY_RATIO = 0.04


def noise_ratio(points: np.ndarray, k: int = 16, workers: int = 1, normals: np.ndarray | None = None) -> float:
    """How far the points lie off their local planes, in neighbour spacings: the median over the points of
    the distance to the least-squares plane of the point and its `k` nearest neighbours, divided by the mean
    distance to those neighbours. Samples of a smooth surface lie nearly on their planes (a small ratio that
    grows with curvature and sparsity); noise along the normal lifts it (`NOISY_RATIO`). With `normals` ((G, 3)
    oriented), neighbours whose normal points the other way (the far side of a wall thinner than the
    neighbourhood) are left out of the plane and the spacing, so a thin wall does not read as noise. Written
    with SciPy and NumPy: the one figure is not in a library the package depends on."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 4:
        return 0.0
    k = min(int(k), len(pts) - 1)
    dist, idx = cKDTree(pts).query(pts, k + 1, workers=workers)
    nb = pts[idx]
    if normals is None:
        use = np.ones(idx.shape)
    else:
        nrm = np.asarray(normals, dtype=np.float64)
        use = (np.einsum("nj,nkj->nk", nrm, nrm[idx]) >= 0).astype(np.float64)  # row 0 (the point) always
    count = use.sum(1)
    centred = (nb - (nb * use[:, :, None]).sum(1, keepdims=True) / count[:, None, None]) * use[:, :, None]
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    off = np.abs(np.einsum("ni,ni->n", centred[:, 0], vecs[:, :, 0]))  # row 0 of each neighbourhood is the point
    spacing = (dist[:, 1:] * use[:, 1:]).sum(1) / np.maximum(count - 1, 1)
    ok = (spacing > 0) & (count >= 4)
    return float(np.median(off[ok] / spacing[ok])) if ok.any() else 0.0


#: A sample's wall is thin when a sample with an opposite normal (cosine below this) lies behind it ...
OPPOSITE_COSINE = -0.5
#: ... deeper than this many seed spacings (flipped normals on one surface, as at a Moebius strip's seam, lie
#: beside the sample, not behind it).
MIN_WALL = 0.5
#: Imaginary points (poles) of thin-wall seeds within this many seed spacings of a mid-surface point are dropped:
#: with the mid-surface point half a wall below, a pole a few spacings above leaves the surface triangles no empty
#: sphere. Why 8: docs/preset_choices.md, "Thin walls".
THIN_WALL_CLEARANCE = 8.0


def wall_gaps(seeds: np.ndarray, seed_normals: np.ndarray, max_gap: float, k: int = 16,
              workers: int = 1) -> np.ndarray:
    """(S,) float64: for each seed on a thin wall, the wall's thickness there, inf elsewhere. A seed is on a thin
    wall when a seed among its `k` nearest has an opposite normal (`OPPOSITE_COSINE`) and lies behind it
    (against its normal) by between `MIN_WALL` and `max_gap` median seed spacings; the thickness is the least
    such depth. Written with SciPy: the crust's libraries (CGAL's included) take no normals.

    Args:
        seeds: (S, 3) float64 seed positions; seed_normals: (S, 3) unit outward normals.
        max_gap: walls up to this many median seed spacings thick count as thin.
    """
    from scipy.spatial import cKDTree

    seeds = np.asarray(seeds, dtype=np.float64)
    nrm = np.asarray(seed_normals, dtype=np.float64)
    if len(seeds) < 2 or max_gap <= 0:
        return np.full(len(seeds), np.inf)
    dist, idx = cKDTree(seeds).query(seeds, min(k + 1, len(seeds)), workers=workers)
    spacing = float(np.median(dist[:, 1]))
    idx = idx[:, 1:]
    opposite = np.einsum("ij,ikj->ik", nrm, nrm[idx]) < OPPOSITE_COSINE
    depth = -np.einsum("ikj,ij->ik", seeds[idx] - seeds[:, None], nrm)
    depth = np.where(opposite & (depth > MIN_WALL * spacing) & (depth < max_gap * spacing), depth, np.inf)
    return depth.min(1)


def thin_wall_points(seeds: np.ndarray, seed_normals: np.ndarray, max_gap: float, k: int = 16,
                     workers: int = 1) -> np.ndarray:
    """(W, 3) imaginary points on the mid-surface of thin walls (`wall_gaps`): each seed on one, moved half the
    wall's thickness against its normal."""
    gap = wall_gaps(seeds, seed_normals, max_gap, k, workers)
    thin = np.isfinite(gap)
    return np.asarray(seeds, dtype=np.float64)[thin] - np.asarray(seed_normals)[thin] * (0.5 * gap[thin])[:, None]


def separate_thin_walls(positions: np.ndarray, reals: np.ndarray, points: np.ndarray, normals: np.ndarray,
                        max_gap: float, clearance: float = THIN_WALL_CLEARANCE,
                        workers: int = 1) -> tuple[np.ndarray, np.ndarray, dict]:
    """The initial points with `thin_wall_points` added (imaginary), and without the imaginary points that lie
    within `clearance` median seed spacings of those and whose nearest seed is on a thin wall (the poles of the
    walls' seeds; those of the thick parts beside them stay; module docstring).

    Args:
        positions, reals: as `seeds_and_voronoi` returns them (seeds first); points, normals: (G, 3) the input
            samples and their oriented normals (each seed is one of the points).
    Returns:
        positions, reals, and counts {"thin_wall_points", "poles_dropped"}.
    """
    from scipy.spatial import cKDTree

    real = reals > 0.5
    seeds = positions[real]
    seed_normals = np.asarray(normals, dtype=np.float64)[cKDTree(points).query(seeds, workers=workers)[1]]
    gap = wall_gaps(seeds, seed_normals, max_gap, workers=workers)
    thin = np.isfinite(gap)
    if not thin.any():
        return positions, reals, {"thin_wall_points": 0, "poles_dropped": 0}
    mid = seeds[thin] - seed_normals[thin] * (0.5 * gap[thin])[:, None]
    spacing = float(np.median(cKDTree(seeds).query(seeds, 2, workers=workers)[0][:, 1]))
    others = positions[~real]
    near = cKDTree(mid).query(others, workers=workers)[0] < clearance * spacing
    near[near] = thin[cKDTree(seeds).query(others[near], workers=workers)[1]]
    drop = np.zeros(len(positions), bool)
    drop[~real] = near
    positions = np.concatenate([positions[~drop], mid])
    reals = np.r_[reals[~drop], np.zeros(len(mid))]
    return positions, reals, {"thin_wall_points": int(len(mid)), "poles_dropped": int(drop.sum())}


def poles(pd: wdt.PowerDiagram, n: int) -> np.ndarray:
    """Tets whose circumcentres are the poles of points 0..n-1 of the (unweighted) diagram `pd`.

    The first pole of point i is the farthest circumcentre among its tets; the second is the farthest
    among those on the other side of i (negative dot product with the first pole's direction).
    Returns the sorted unique tet ids (int64).
    """
    rows = pd.point_tets.rows()
    tets = pd.point_tets.indices.astype(np.int64)
    keep = rows < n
    rows, tets = rows[keep], tets[keep]
    d = pd.orthocentres[tets] - pd.points[rows]
    r = np.linalg.norm(d, axis=1)
    first = _argmax_per_row(rows, r, n)
    ok = first >= 0
    dir1 = np.zeros((n, 3))
    dir1[ok] = d[first[ok]]
    other = np.einsum("ij,ij->i", d, dir1[rows]) < 0
    second = _argmax_per_row(rows[other], r[other], n)
    second = np.flatnonzero(other)[second[second >= 0]]
    return np.unique(np.r_[tets[first[ok]], tets[second]])


def _argmax_per_row(rows: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n,) index into `values` of each row's largest value, -1 for empty rows."""
    out = np.full(n, -1, dtype=np.int64)
    if len(rows) == 0:
        return out
    order = np.lexsort((values, rows))  # by row, then ascending value: each row's last is its max
    last = np.r_[rows[order][1:] != rows[order][:-1], True]
    out[rows[order][last]] = order[last]
    return out


__all__ = ["seeds_and_voronoi", "poles", "carve_far_faces", "statistical_inliers"]
