"""Corrupted inputs: what real scans look like, as settings of a sweep (DESIGN.md 8.1).

Shape letters: N points, C cameras, V views, H x W pixels.

Every input of the harness starts clean: N area-uniform samples of the normalised GT with their exact face
normals, or a noiseless multi-view capture. A *corruption* is a dict of settings, each at a *level* in the
unit-radius frame (the GT normalised to max vertex norm `radius`, 1 for these inputs; distances are
fractions of that radius). Benchmarks that separate reconstruction methods corrupt their inputs this way
(dsr-benchmark, SCUTSurface; see `../shared/reference/baselines_and_benchmarks.md`).

Point-cloud settings (composable; every random choice takes the run seed, one independent stream per stage):

- ``noise`` (float, 0 = clean): Gaussian noise of this standard deviation (times `radius`) on every
  coordinate of every point, so each axis of the displacement has std `noise`; in a scan the noise is along
  each point's ray instead (range noise), with the same std.
- ``outliers`` (float fraction, 0 = clean): exactly round(outliers * N) of the N points, chosen at random, are
  replaced by points uniform in the *bounding cube* of the cloud enlarged by 10 %: centred on the centre of
  the points' axis-aligned bounding box, with half-side 1.1 times the box's largest half-extent. A cube, not
  the box itself, so that flat shapes (a disc, a sheet) also get outliers away from their plane. The count
  stays N (outliers replace inliers), so density and outliers do not interact.
- ``density`` (int, absent = all N): keep this many of the N points, a uniform random subset.
- ``nonuniform`` (float contrast >= 1, 1 = clean): the N points are drawn with a density that grows
  exponentially along a random direction u (seeded): proportional to contrast ** t, t in [0, 1] the position
  of the point along u between the GT's extreme vertices; so the densest end has `contrast` times the density
  of the sparsest. Drawn from the mesh by rejection (area-uniform candidates kept with probability
  contrast ** (t - 1)), not from the clean cloud, so the count stays exactly N.
- ``scan`` (int cameras, 0 = clean): the points are a simulated scan (`datasets.scan.simulate_scan`): the
  first hits of random rays from that many cameras on spheres of 2.5 r and 3.5 r; occluded parts get none.
- ``normals`` ("gt" or "estimated"; default "gt", and "estimated" for scans): which normals the points carry.
  "gt": each point keeps the exact normal of the surface point it came from (a noisy point the normal of the
  point it was displaced from; a scan hit the normal of the triangle it hit), and every outlier gets a random
  unit normal (a stray return has no meaningful normal). "estimated": what a real pipeline has: normals from
  the points themselves (open3d's PCA of the 16 nearest neighbours), oriented toward the camera that saw the
  point in a scan (outliers: a random camera of the scan), else by consistent tangent-plane propagation
  (`orient_by_propagation`, Hoppe et al. 1992), then flipped as a whole so that most point away from the
  centroid (outward, for closed shapes).

Multi-view settings: ``depth_noise`` (float, 0 = clean): Gaussian noise of this std (times `radius`) on the
depth of every covered pixel (diffuse and mask unchanged); ``views`` and ``resolution`` (ints): a capture with
that many views / pixels per side instead of the sweep's.

`canonical_variant` validates a user's dict (one-line ValueError naming the key, the allowed levels and the
value) and drops the settings at their clean level, so that equal inputs get equal run keys; `corrupt_cloud`
and `add_depth_noise` make the inputs; `cache_tag` names their cache files.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Mapping

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["POINTCLOUD_KEYS", "MULTIVIEW_KEYS", "canonical_variant", "variant_kind", "clean_level", "cache_tag",
           "add_noise", "add_outliers", "subsample", "nonuniform_sample", "estimate_normals", "orient_by_propagation",
           "corrupt_cloud",
           "add_depth_noise", "OUTLIER_MARGIN", "NORMAL_K"]

POINTCLOUD_KEYS = ("noise", "outliers", "density", "nonuniform", "scan", "normals")
MULTIVIEW_KEYS = ("depth_noise", "views", "resolution")
#: Largest noise level (std as a fraction of the radius): beyond it the shape is gone.
MAX_NOISE = 0.1
#: Largest outlier fraction (more outliers than points is not a scan of the object).
MAX_OUTLIERS = 0.5
#: Largest density contrast of `nonuniform` (the rejection sampler draws about contrast / ln(contrast) x N).
MAX_CONTRAST = 1000.0
#: Enlargement of the bounding cube the outliers are drawn in (10 % of its half-side on each side).
OUTLIER_MARGIN = 0.1
#: Neighbours of the PCA normal estimate and of the orientation propagation.
NORMAL_K = 16
#: Fewest points a corrupted cloud may have (`baselines.base.MIN_POINTS`).
MIN_POINTS = 10
#: Seed streams of the stages (so that adding one stage does not change the random numbers of another).
_STREAM = {"noise": 1, "outliers": 2, "density": 3, "nonuniform": 4, "scan": 5, "depth_noise": 6,
           "outlier_camera": 7}


# --------------------------------------------------------------------------------------------------- settings

def _number(what: str, key: str, value, low: float, high: float, unit: str) -> float:
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    if not ok or not low <= value <= high:
        raise ValueError(f"{what}: {key}: expected a number from {low:g} to {high:g} ({unit}), got {value!r}")
    return float(value)


def _count(what: str, key: str, value, low: int, high: int, unit: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{what}: {key}: expected an integer from {low} to {high} ({unit}), got {value!r}")
    return int(value)


def canonical_variant(variant: Mapping, *, n_points: int, views: int, resolution: int,
                      what: str = "variant") -> dict:
    """The validated, canonical form of one input variant: settings at their clean level dropped, numbers
    as float (levels) or int (counts), and `normals: estimated` made explicit for scans.

    Args:
        variant: the user's dict, e.g. {"noise": 0.005} or {"scan": 6, "outliers": 0.01}.
        n_points, views, resolution: the sweep's clean input sizes (a `density` of n_points, or the sweep's own
            views and resolution, are the clean level).
        what: prefix of error messages (e.g. "Sweep.variants[3]").
    Raises:
        ValueError: one line naming the bad key, its allowed levels and the value given.
    """
    from datasets.scan import MAX_CAMERAS

    if not isinstance(variant, Mapping):
        raise ValueError(f"{what}: expected a mapping of input settings, got {variant!r}")
    unknown = sorted(set(variant) - set(POINTCLOUD_KEYS) - set(MULTIVIEW_KEYS))
    if unknown:
        raise ValueError(f"{what}: unknown settings {unknown}; known: point cloud {', '.join(POINTCLOUD_KEYS)}; "
                         f"multi-view {', '.join(MULTIVIEW_KEYS)}")
    v = dict(variant)
    out: dict[str, Any] = {}
    if "noise" in v:
        out["noise"] = _number(what, "noise", v["noise"], 0, MAX_NOISE, "std as a fraction of the radius")
    if "outliers" in v:
        out["outliers"] = _number(what, "outliers", v["outliers"], 0, MAX_OUTLIERS, "fraction of the points")
    if "density" in v:
        out["density"] = _count(what, "density", v["density"], MIN_POINTS, n_points,
                                f"points kept of the sweep's n_points {n_points}")
    if "nonuniform" in v:
        out["nonuniform"] = _number(what, "nonuniform", v["nonuniform"], 1, MAX_CONTRAST,
                                    "densest / sparsest density")
    if "scan" in v:
        out["scan"] = _count(what, "scan", v["scan"], 0, MAX_CAMERAS, "cameras; 0: no scan")
    if "normals" in v and v["normals"] not in ("gt", "estimated"):
        raise ValueError(f"{what}: normals: expected 'gt' or 'estimated', got {v['normals']!r}")
    if "depth_noise" in v:
        out["depth_noise"] = _number(what, "depth_noise", v["depth_noise"], 0, MAX_NOISE,
                                     "depth std as a fraction of the radius")
    for key, clean in (("views", views), ("resolution", resolution)):
        if key in v:
            out[key] = _count(what, key, v[key], 1, 10**6, "a multi-view capture size")
            if out[key] == clean:
                del out[key]
    clean_levels = {"noise": 0.0, "outliers": 0.0, "density": n_points, "nonuniform": 1.0, "scan": 0,
                    "depth_noise": 0.0}
    out = {k: x for k, x in out.items() if clean_levels.get(k, object()) != x}
    if out.get("scan"):
        out["normals"] = v.get("normals", "estimated")
        if "nonuniform" in out:
            raise ValueError(f"{what}: scan and nonuniform both choose where the points lie; use one of them")
    elif v.get("normals", "gt") != "gt":
        out["normals"] = v["normals"]
    if variant_kind(out) == "mixed":
        raise ValueError(f"{what}: mixes point-cloud settings ({', '.join(k for k in out if k in POINTCLOUD_KEYS)}) "
                         f"with multi-view ones ({', '.join(k for k in out if k in MULTIVIEW_KEYS)}); a variant "
                         f"corrupts one input kind")
    return dict(sorted(out.items()))


def variant_kind(variant: Mapping) -> str | None:
    """"pointcloud" or "multiview" (the input kind a canonical variant changes), None for the clean variant,
    "mixed" when it holds keys of both kinds."""
    kinds = {"pointcloud" if k in POINTCLOUD_KEYS else "multiview" for k in variant}
    return None if not kinds else kinds.pop() if len(kinds) == 1 else "mixed"


def clean_level(key: str, settings: Mapping):
    """The clean level of setting `key` for an input with `settings` (the run's input settings)."""
    return {"noise": 0.0, "outliers": 0.0, "density": settings.get("n_points"), "nonuniform": 1.0, "scan": 0,
            "normals": "gt", "depth_noise": 0.0, "views": settings.get("views"),
            "resolution": settings.get("resolution")}[key]


def cache_tag(corruption: Mapping | None) -> str:
    """Suffix of a corrupted input's cache name: "" when clean, else e.g. "_noise0.005_outliers0.01"; capture
    sizes (views, resolution) are left out, as they are in the name already. Values are written exactly (repr),
    so different levels never share a file."""
    parts = []
    for k, v in sorted((corruption or {}).items()):
        if k in ("views", "resolution"):
            continue
        parts.append(f"{k}-{v}" if isinstance(v, str) else f"{k}{v!r}")
    return "".join(f"_{p}" for p in parts)


# --------------------------------------------------------------------------------------------------- stages

def _rng(seed: int, stage: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), _STREAM[stage]])


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.standard_normal((n, 3))
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def add_noise(points: np.ndarray, sigma: float, seed: int = 0) -> np.ndarray:
    """(N, 3) float64: `points` plus N(0, sigma^2) on every coordinate (seeded)."""
    points = np.asarray(points, np.float64)
    if sigma <= 0:
        return points.copy()
    return points + _rng(seed, "noise").normal(0.0, sigma, size=points.shape)


def add_outliers(points: np.ndarray, normals: np.ndarray, fraction: float, seed: int = 0,
                 margin: float = OUTLIER_MARGIN) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replaces exactly round(fraction * N) random points by points uniform in the enlarged bounding cube.

    Args:
        points: (N, 3) float; normals: (N, 3) float.
        fraction: in [0, 1].
        margin: the cube's half-side is (1 + margin) times the bounding box's largest half-extent.
    Returns:
        points (N, 3) float64, normals (N, 3) float64 (outliers: random unit vectors), is_outlier (N,) bool.
    """
    points, normals = np.array(points, np.float64), np.array(normals, np.float64)
    n = len(points)
    k = int(math.floor(fraction * n + 0.5))
    mask = np.zeros(n, bool)
    if k == 0:
        return points, normals, mask
    rng = _rng(seed, "outliers")
    lo, hi = points.min(0), points.max(0)
    centre, half = (lo + hi) / 2.0, float((hi - lo).max() / 2.0) * (1.0 + margin)
    idx = rng.choice(n, size=k, replace=False)
    points[idx] = centre + rng.uniform(-half, half, size=(k, 3))
    normals[idx] = _unit(rng, k)
    mask[idx] = True
    return points, normals, mask


def subsample(n_total: int, n: int, seed: int = 0) -> np.ndarray:
    """(n,) int64 sorted indices of a uniform random subset of size n of range(n_total)."""
    if not 0 <= n <= n_total:
        raise ValueError(f"subsample: cannot keep {n} of {n_total} points")
    return np.sort(_rng(seed, "density").choice(n_total, size=n, replace=False)).astype(np.int64)


def nonuniform_sample(mesh, n: int, contrast: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """N surface points whose density grows as contrast ** t along a random direction (module docstring).

    Returns:
        points (N, 3) float64, normals (N, 3) float64 (face normals), direction (3,) float64 (unit u).
    """
    from datasets.sampling import sample_points

    if not 1.0 <= contrast <= MAX_CONTRAST:
        raise ValueError(f"nonuniform_sample: contrast must be from 1 to {MAX_CONTRAST:g}, got {contrast!r}")
    rng = _rng(seed, "nonuniform")
    u = _unit(rng, 1)[0]
    proj = np.asarray(mesh.vertices, np.float64) @ u
    lo, span = float(proj.min()), max(float(np.ptp(proj)), 1e-12)
    pts_out, nrm_out, have = [], [], 0
    batch = int(n * min(contrast, 4.0)) + 64
    while have < n:
        p, nr = sample_points(mesh, batch, int(rng.integers(2**62)))
        t = np.clip((p.astype(np.float64) @ u - lo) / span, 0.0, 1.0)
        keep = rng.random(len(p)) < contrast ** (t - 1.0)
        pts_out.append(p[keep])
        nrm_out.append(nr[keep])
        have += int(keep.sum())
    points = np.concatenate(pts_out)[:n].astype(np.float64)
    normals = np.concatenate(nrm_out)[:n].astype(np.float64)
    return points, normals, u


def estimate_normals(points: np.ndarray, viewpoints: np.ndarray | None = None, k: int = NORMAL_K) -> np.ndarray:
    """(N, 3) float64 unit normals estimated from the points alone (module docstring, ``normals``).

    Args:
        points: (N, 3) float.
        viewpoints: (N, 3) float, the sensor position of each point (normals are turned toward it), or None
            (orientation by tangent-plane propagation, then outward on the whole).
        k: neighbours of the PCA and of the propagation.
    """
    import open3d as o3d

    pts = np.asarray(points, np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(int(k)))
    nrm = np.asarray(pcd.normals, np.float64).copy()
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    if viewpoints is None:
        nrm = orient_by_propagation(pts, nrm, k)
    if viewpoints is not None:
        flip = np.einsum("ij,ij->i", nrm, np.asarray(viewpoints, np.float64) - pts) < 0
        nrm[flip] *= -1.0
    elif np.einsum("ij,ij->i", nrm, pts - pts.mean(0)).sum() < 0:
        nrm *= -1.0
    return nrm


def orient_by_propagation(points: np.ndarray, normals: np.ndarray, k: int = NORMAL_K) -> np.ndarray:
    """(N, 3) `normals` flipped to agree along a minimum spanning tree of the k-nearest-neighbour graph with
    edge costs 1 - |n_i . n_j| (Hoppe et al. 1992, "consistent tangent planes"); in each connected part the
    walk starts at its point of largest z, turned to +z, and every point takes its tree parent's side.

    Written with SciPy because Open3D's `orient_normals_consistent_tangent_plane`, the same algorithm, runs for
    hours on clouds with coplanar parts (isl-org/Open3D#6482; the robustness sweep's flag_box, a box).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    nrm = np.asarray(normals, np.float64).copy()
    n = len(pts)
    if n < 2:
        return nrm
    kk = min(int(k) + 1, n)
    _, nb = cKDTree(pts).query(pts, kk)
    rows = np.repeat(np.arange(n), kk - 1)
    cols = nb[:, 1:].reshape(-1)
    # Costs must be positive for the sparse graph to keep the edge: parallel neighbours cost a tiny epsilon.
    cost = 1.0 - np.abs(np.einsum("ij,ij->i", nrm[rows], nrm[cols])) + 1e-9
    graph = coo_matrix((cost, (rows, cols)), shape=(n, n)).tocsr()
    graph = graph.maximum(graph.T)
    tree = minimum_spanning_tree(graph)
    tree = tree + tree.T
    parts, label = connected_components(tree, directed=False)
    for part in range(parts):
        members = np.flatnonzero(label == part)
        root = members[np.argmax(pts[members, 2])]
        if nrm[root, 2] < 0:
            nrm[root] *= -1.0
        order, parent = breadth_first_order(tree, root, directed=False)
        for child in order[1:]:  # parents come before their children in breadth-first order
            if np.dot(nrm[child], nrm[parent[child]]) < 0:
                nrm[child] *= -1.0
    return nrm


def corrupt_cloud(mesh, points: np.ndarray, normals: np.ndarray, corruption: Mapping, seed: int = 0,
                  radius: float = 1.0) -> dict[str, np.ndarray]:
    """The corrupted cloud of a canonical `corruption` (see `canonical_variant`).

    Stages, in order: where the points lie (the clean `points`, a `nonuniform` draw from `mesh`, or a `scan` of
    `mesh`, each of N = len(points) points), `density`, `noise`, `outliers`, then the `normals`.

    Args:
        mesh: the normalised GT (for `nonuniform` and `scan`).
        points, normals: (N, 3) the clean cloud: area-uniform samples and their face normals.
        corruption: canonical settings (levels in units of `radius`).
        seed: the run seed.
        radius: the normalisation radius of the frame (levels are fractions of it).
    Returns:
        {"points": (M, 3) float32, "normals": (M, 3) float32, "is_outlier": (M,) bool} plus, for scans,
        "camera_index" (M,) int64 (-1 for an outlier not seen by any camera) and "cameras" (C, 3) float64.
    """
    c = dict(corruption)
    n = len(points)
    sigma = float(c.get("noise", 0.0)) * radius
    cams = cam_idx = None
    if c.get("scan"):
        from datasets.scan import simulate_scan

        s = simulate_scan(mesh, n, int(c["scan"]), seed=int(_rng(seed, "scan").integers(2**62)), noise=sigma)
        pts, nrm, cams, cam_idx = s.points, s.face_normals, s.cameras, s.camera_index
    elif c.get("nonuniform", 1.0) > 1.0:
        pts, nrm, _ = nonuniform_sample(mesh, n, float(c["nonuniform"]), seed)
    else:
        pts, nrm = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    if "density" in c:
        keep = subsample(len(pts), int(c["density"]), seed)
        pts, nrm = pts[keep], nrm[keep]
        cam_idx = cam_idx[keep] if cam_idx is not None else None
    if not c.get("scan"):
        pts = add_noise(pts, sigma, seed)
    pts, nrm, outlier = add_outliers(pts, nrm, float(c.get("outliers", 0.0)), seed)
    out: dict[str, np.ndarray] = {"is_outlier": outlier}
    if cams is not None:
        # An outlier is a stray return of some camera of the scan: a random one, for the normals' orientation.
        cam_idx = cam_idx.copy()
        cam_idx[outlier] = _rng(seed, "outlier_camera").integers(len(cams), size=int(outlier.sum()))
        out.update(camera_index=cam_idx, cameras=cams)
    if c.get("normals", "gt") == "estimated":
        nrm = estimate_normals(pts, cams[cam_idx] if cams is not None else None)
    out.update(points=pts.astype(np.float32), normals=nrm.astype(np.float32))
    return out


def add_depth_noise(views, sigma: float, seed: int = 0):
    """A copy of the capture `views` (`datasets.capture.MultiView`) with N(0, sigma^2) added to the depth of
    every covered pixel (kept at least 1e-6, so covered pixels keep a positive depth); diffuse and mask are
    unchanged."""
    depth = np.array(views.depth, np.float32)
    if sigma > 0:
        e = _rng(seed, "depth_noise").normal(0.0, sigma, size=depth.shape).astype(np.float32)
        depth = np.where(views.mask, np.maximum(depth + e, np.float32(1e-6)), np.float32(0.0))
    return dataclasses.replace(views, depth=depth)
