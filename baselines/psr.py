"""Screened Poisson surface reconstruction (Kazhdan and Hoppe 2013) through pymeshlab, trimmed by density.

Shape letters: N input points, V output vertices, F output faces.

Settings and their sources (docs/protocol.md, "Baselines", has the dev-split measurement that chose them):

- `depth` 10, chosen on the dev split (the 12 Table 2 shapes, 100K points) among 8 / 9 / 10, the grid of
  PoissonRecon's README (its 100,000-point horse runs at depth 10) and of dsr-benchmark's tuning on its train
  split ({6, 8, 10}). Depth is an upper bound: the octree adapts to the sampling (PoissonRecon issue #37).
- `full_depth` 5, `scale` 1.1, `samples_per_node` 1.5, `point_weight` 4, `iters` 8: MeshLab's / pymeshlab's
  filter defaults (`filter_screened_poisson.cpp`), the values Points2Surf's `poisson.mlx` runs;
  samplesPerNode 1.5 is PoissonRecon's advice for noise-free samples (README: [1, 5] clean, [15, 20] noisy).
- Trimming as PoissonRecon's SurfaceTrimmer does it (`trim_depth_offset` 2, `trim_smooth` 5,
  `island_area_ratio` 0.001). pymeshlab leaves PoissonRecon's `--density` output as the per-vertex quality:
  MeshLab's plugin sets `DensityFlag = true` and copies each iso-vertex's value into `Q()`
  (`poisson_utils.h`), the estimated octree depth of the local sampling (PoissonRecon issue #246: "the depth
  to which the point would be assigned given the local sampling density"). The trim value is depth - 2,
  chosen on the dev split (`python -m studies psr_trim`, studies/reports/psr_trim.md: open class 0.105e-3 at
  depth - 2 against 0.248e-3 at depth - 3, mixed 0.329 against 0.543, no closed dev shape cut at any level
  from depth - 3 to depth - 1). The public defaults are depth - 3: PoissonRecon's README (depth 10,
  `--trim 7`) and COLMAP's `poisson_mesher` (depth 13, trim 10); row `psr [trim_depth_offset=3.0]` in a sweep
  gives them. As SurfaceTrimmer (V5): the values
  are smoothed 5 times over the mesh (`--smooth 5`), every face is cut along the trim level set (vertices
  interpolated on the crossing edges), and pieces that touch the cut and hold less than 0.001 of the total
  area (`--aRatio 0.001`) change side: small kept islands go, small trimmed holes come back. One setting for
  closed, open and mixed shapes; on closed, well-sampled shapes the density stays above the trim value and
  nothing is cut (measured, docs/protocol.md).
- The trim value is at most the median density - 0.7 (`trim_median_margin`): the density follows the
  sampling, not the depth asked for, so on a sparse cloud depth - 2 would lie above every vertex and remove
  the whole surface. 0.7 is where depth 10 / trim 7 sits on the dev torus at 100K points; at depth - 2 the
  cap decides the trim value wherever the median density is below 8.7 (measurement: docs/protocol.md, "Sparse inputs").
- Density follows the sampling, so one trim value cuts the sparse side of a non-uniformly sampled or scanned
  closed shape. A vertex below it therefore stays when an input point lies within `trim_support_ratio` = 1 of
  that point's local spacings (mean distance to its `trim_support_neighbours` = 8 nearest), counting only
  points whose spacing is at most `trim_support_max_spacing` = 4 x the median (outliers vouch for nothing); the
  DMesh surface step's `reopen` evidence rule, given to PSR's trim, chosen on the dev split (docs/protocol.md,
  "Non-uniform sampling"; `python -m studies psr_support`). PoissonRecon has none: `trim_support_ratio` None.
- `threads` 1: the harness's thread budget (OpenMP spin-waits make 2 much slower on a busy 2-core box).

The `paper` preset (`{preset: paper}` in a sweep, row `psr [preset=paper]`) is the setting of the tables
before issue 58: depth 8, no trimming (`trim_quantile` 0), the same library defaults otherwise.
"""
from __future__ import annotations

import logging

import numpy as np

from baselines.base import Inputs, Method, Stopwatch, check_points, require

log = logging.getLogger(__name__)

#: Named presets: overrides of `ScreenedPoisson.default_config()`, picked by a config's `preset` key.
PRESETS = {
    "practice": {},
    # The tables before issue 58: pymeshlab's default depth, untrimmed.
    "paper": {"depth": 8, "trim_depth_offset": None, "trim_quantile": 0.0},
}


class ScreenedPoisson(Method):
    name = "psr"
    input_kind = "pointcloud"

    def default_config(self) -> dict:
        return {
            "preset": "practice",   # named setting (PRESETS): "practice" (these defaults) or "paper"
            "depth": 10,            # octree depth; chosen on the dev split among 8/9/10 (docs/protocol.md)
            "full_depth": 5,        # complete octree below this depth (MeshLab default)
            "scale": 1.1,           # bounding cube / points' bounding box (MeshLab and PoissonRecon default)
            "samples_per_node": 1.5,  # minimum samples per node (PoissonRecon README: 1-5 for clean samples)
            "point_weight": 4.0,    # screening weight (MeshLab default; PoissonRecon's own is 2 at degree 1)
            "iters": 8,             # Gauss-Seidel iterations per level (MeshLab and PoissonRecon default)
            "trim_depth_offset": 2.0,  # trim value = depth - this; chosen on dev (docstring; PoissonRecon
                                       # README 10/7 and COLMAP 13/10 use 3); None: no density trimming
            "trim_median_margin": 0.7,  # the trim value at most this far below the median density (sparse
                                        # inputs; None: no cap); docstring
            "trim_support_ratio": 1.0,  # a vertex within this many local spacings of an input point is not
                                        # trimmed (non-uniform sampling; docstring); None: SurfaceTrimmer as is
            "trim_support_neighbours": 8,  # the local spacing: mean distance to this many nearest input points
            "trim_support_max_spacing": 4.0,  # ... counted only up to this x the median spacing (outliers)
            "trim_smooth": 5,       # smoothing passes over the densities before the cut (SurfaceTrimmer --smooth)
            "island_area_ratio": 0.001,  # pieces at the cut below this area fraction change side (--aRatio)
            "trim_quantile": 0.0,   # Open3D-tutorial style: also drop vertices below this density quantile
            "threads": 1,           # solver threads (OpenMP spin-waits make 2 much slower on a busy 2-core box)
        }

    def resolve_config(self, config) -> dict:
        """The defaults, then the preset named by `config["preset"]` (if any), then the other overrides."""
        overrides = dict(config or {})
        preset = overrides.get("preset", "practice")
        if preset not in PRESETS:
            raise ValueError(f"psr: unknown preset {preset!r}; choose from {', '.join(sorted(PRESETS))}")
        return super().resolve_config({**PRESETS[preset], **overrides})

    def prepare(self) -> None:
        require("pymeshlab")

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import trimesh

        pml = require("pymeshlab")
        pts, nrm = check_points(inputs, need_normals=True)
        if not 0.0 <= float(cfg["trim_quantile"]) < 1.0:
            raise ValueError(f"psr: trim_quantile must be in [0, 1), got {cfg['trim_quantile']}")
        if not 0.0 <= float(cfg["island_area_ratio"]) < 1.0:
            raise ValueError(f"psr: island_area_ratio must be in [0, 1), got {cfg['island_area_ratio']}")
        if int(cfg["trim_smooth"]) < 0:
            raise ValueError(f"psr: trim_smooth must be >= 0, got {cfg['trim_smooth']}")
        with sw.stage("poisson"):
            ms = pml.MeshSet()
            ms.add_mesh(pml.Mesh(vertex_matrix=pts, v_normals_matrix=nrm))
            ms.generate_surface_reconstruction_screened_poisson(
                depth=int(cfg["depth"]), fulldepth=int(cfg["full_depth"]), scale=float(cfg["scale"]),
                samplespernode=float(cfg["samples_per_node"]), pointweight=float(cfg["point_weight"]),
                iters=int(cfg["iters"]), preclean=False, threads=int(cfg["threads"]))
            out = ms.current_mesh()
            verts = np.asarray(out.vertex_matrix(), dtype=np.float64)
            faces = np.asarray(out.face_matrix(), dtype=np.int64)
            density = np.asarray(out.vertex_scalar_array(), dtype=np.float64)
        info = {"faces_untrimmed": int(len(faces))}
        if len(density):
            info.update({f"density_q{q:02d}": float(np.percentile(density, q)) for q in (0, 1, 5, 50)})
        with sw.stage("trim"):
            if cfg["trim_depth_offset"] is not None and len(faces):
                value = float(cfg["depth"]) - float(cfg["trim_depth_offset"])
                if cfg["trim_median_margin"] is not None:  # what the samples support (module docstring)
                    value = min(value, float(np.median(density)) - float(cfg["trim_median_margin"]))
                supported = None
                if cfg["trim_support_ratio"] is not None:
                    supported = sampled_vertices(verts, pts, float(cfg["trim_support_ratio"]),
                                                 int(cfg["trim_support_neighbours"]),
                                                 float(cfg["trim_support_max_spacing"]))
                verts, faces, density, trim_info = trim_surface(
                    verts, faces, density, value, int(cfg["trim_smooth"]), float(cfg["island_area_ratio"]),
                    supported)
                info.update(trim_info)
            mesh = trimesh.Trimesh(verts, faces, process=False)
            q = float(cfg["trim_quantile"])
            if q > 0 and len(faces):
                d = density  # per vertex of `mesh` (after a level trim: smoothed, cut vertices at the trim value)
                threshold = float(np.quantile(d, q))
                mesh.update_faces((d[mesh.faces] >= threshold).all(axis=1))
                mesh.remove_unreferenced_vertices()
                info["trim_density_threshold"] = threshold
        return mesh, info


# ----------------------------------------------------------------------------------------- SurfaceTrimmer

def sampled_vertices(verts: np.ndarray, points: np.ndarray, ratio: float, neighbours: int = 8,
                     max_spacing: float = 4.0) -> np.ndarray:
    """(V,) bool: the vertices an input point vouches for: within `ratio` of the nearest point's local spacing
    (its mean distance to its `neighbours` nearest points), that spacing at most `max_spacing` times the median
    one (a point far sparser than the rest, an outlier, vouches for nothing).

    Args:
        verts: (V, 3) mesh vertices. points: (N, 3) input points, N >= 2.
        ratio: distance limit in local spacings (> 0). neighbours: k of the spacing (>= 1).
        max_spacing: the largest spacing that counts, in median spacings (> 0).
    """
    from scipy.spatial import cKDTree

    if not (ratio > 0 and max_spacing > 0 and int(neighbours) >= 1):
        raise ValueError(f"psr: trim_support_ratio, trim_support_max_spacing and trim_support_neighbours must "
                         f"be positive, got {ratio}, {max_spacing}, {neighbours}")
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2 or not len(verts):
        return np.zeros(len(verts), dtype=bool)
    tree = cKDTree(points)
    k = min(int(neighbours), len(points) - 1)
    spacing = tree.query(points, k + 1)[0][:, 1:].mean(1)
    distance, nearest = tree.query(np.asarray(verts, dtype=np.float64))
    s = spacing[nearest]
    return (distance <= ratio * s) & (s <= max_spacing * float(np.median(spacing)))


def smooth_values(values: np.ndarray, faces: np.ndarray, passes: int) -> np.ndarray:
    """SurfaceTrimmer's value smoothing: `passes` times, each vertex becomes the mean of itself and its
    neighbours across every face edge (an edge shared by two faces counts twice).

    Args:
        values: (V,) float64 per-vertex values.
        faces: (F, 3) int64 indices into values.
        passes: smoothing passes (0: unchanged).
    Returns:
        (V,) float64 smoothed values.
    """
    v = np.asarray(values, dtype=np.float64).copy()
    if passes <= 0 or not len(faces):
        return v
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)          # edges (0,1), (1,2), (2,0) of every face
    count = np.bincount(a, minlength=len(v)) + np.bincount(b, minlength=len(v))
    for _ in range(passes):
        sums = np.bincount(a, weights=v[b], minlength=len(v)) + np.bincount(b, weights=v[a], minlength=len(v))
        v = (sums + v) / (count + 1)
    return v


def _face_components(faces: np.ndarray, n_verts: int) -> np.ndarray:
    """(F,) int component label of each face, faces joined when they share an edge."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = len(faces)
    if F == 0:
        return np.zeros(0, dtype=np.int64)
    e = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    _, edge_id = np.unique(e[:, 0] * np.int64(n_verts) + e[:, 1], return_inverse=True)
    face_of = np.repeat(np.arange(F), 3)
    # Bipartite graph faces - edges: faces sharing an edge land in one component.
    g = coo_matrix((np.ones(3 * F), (face_of, F + edge_id.reshape(-1))), shape=(F + edge_id.max() + 1,) * 2)
    _, labels = connected_components(g, directed=False)
    return labels[:F]


def _proper(faces: np.ndarray) -> np.ndarray:
    """(F,) bool: faces with three distinct vertex indices."""
    return (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])


def trim_surface(verts: np.ndarray, faces: np.ndarray, density: np.ndarray, trim: float, smooth: int = 5,
                 area_ratio: float = 0.001, supported: np.ndarray | None = None):
    """Cut a PSR mesh where its density falls below `trim`, as PoissonRecon's SurfaceTrimmer does.

    The densities are smoothed (`smooth_values`), each face crossing the level `trim` is split on it (a new
    vertex on each crossing edge, shared by both faces of the edge), and the pieces that touch the cut and
    hold less than `area_ratio` of the total area change side: small kept islands are dropped, small
    trimmed holes are kept. Faces with every vertex above `trim` stay; a vertex exactly at `trim` counts as
    below (SurfaceTrimmer keeps `value > trim`).

    Args:
        verts: (V, 3) float64 positions. faces: (F, 3) int64 indices into verts.
        density: (V,) float64 PoissonRecon density (estimated depth) per vertex.
        trim: the trim value, on the density's scale.
        smooth: smoothing passes before the cut.
        area_ratio: area fraction below which a piece touching the cut changes side (0: none does).
        supported: (V,) bool or None, vertices kept whatever their value (`sampled_vertices`): a supported
            vertex counts as above the trim, and the cut between it and an unsupported one passes through it
            (no new vertex: the surface ends at the last vertex a sample vouches for).
    Returns:
        verts (V', 3) float64, faces (F', 3) int64, values (V',) float64 the smoothed densities of the kept
        vertices (`trim` on the cut), and an info dict (trim_value, faces_cut_or_dropped,
        area_trimmed_fraction, islands_removed, holes_kept).
    """
    verts = np.asarray(verts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    val = smooth_values(density, faces, smooth)
    lift = np.zeros(len(val), dtype=bool)
    if supported is not None:
        lift = np.asarray(supported, dtype=bool) & (val <= trim)
        val = np.where(lift, trim + 1.0, val)                  # above the trim; its crossings snap to it below
    above = val[faces] > trim                                  # (F, 3)
    n_above = above.sum(axis=1)
    keep_full, low_full = faces[n_above == 3], faces[n_above == 0]
    mixed = (n_above == 1) | (n_above == 2)
    mf, ma, mn = faces[mixed], above[mixed], n_above[mixed]
    # Rotate each mixed face (keeping its winding) so the vertex alone on its side comes first.
    odd = np.where(mn == 1, np.argmax(ma, axis=1), np.argmin(ma, axis=1))
    cols = (odd[:, None] + np.arange(3)[None, :]) % 3
    r = np.take_along_axis(mf, cols, axis=1)                   # (M, 3): a (alone), b, c
    # One new vertex per crossing edge, shared between the two faces of the edge.
    V = len(verts)
    ends = np.concatenate([r[:, [0, 1]], r[:, [0, 2]]])        # edges a-b, a-c
    key = np.sort(ends, axis=1)
    uniq, inv = np.unique(key[:, 0] * np.int64(V) + key[:, 1], return_inverse=True)
    inv = inv.reshape(-1)
    i, j = uniq // V, uniq % V
    t = np.clip((trim - val[i]) / np.where(val[j] != val[i], val[j] - val[i], 1.0), 0.0, 1.0)
    new_verts = verts[i] + t[:, None] * (verts[j] - verts[i])
    # A crossing from a supported vertex ends at it: the surface stops at the last vertex a sample vouches for.
    index = np.where(lift[i], i, np.where(lift[j], j, V + np.arange(len(uniq))))
    M = len(r)
    pab, pac = index[inv[:M]], index[inv[M:]]
    a, b, c = r[:, 0], r[:, 1], r[:, 2]
    tri = np.stack([a, pab, pac], axis=1)                      # the lone vertex's corner
    quad = np.concatenate([np.stack([pab, b, c], axis=1), np.stack([pab, c, pac], axis=1)])
    lone_above = mn == 1
    kept_cut = np.concatenate([tri[lone_above], quad[np.tile(~lone_above, 2)]])
    low_cut = np.concatenate([tri[~lone_above], quad[np.tile(lone_above, 2)]])
    all_verts = np.concatenate([verts, new_verts])
    all_vals = np.concatenate([val, np.full(len(new_verts), trim)])
    kept_cut = kept_cut[_proper(kept_cut)]                    # faces collapsed onto a supported vertex go
    low_cut = low_cut[_proper(low_cut)]
    kept = np.concatenate([keep_full, kept_cut])
    low = np.concatenate([low_full, low_cut])
    kept_flag = np.concatenate([np.zeros(len(keep_full), bool), np.ones(len(kept_cut), bool)])
    low_flag = np.concatenate([np.zeros(len(low_full), bool), np.ones(len(low_cut), bool)])

    def area(f):
        return 0.5 * np.linalg.norm(np.cross(all_verts[f[:, 1]] - all_verts[f[:, 0]],
                                             all_verts[f[:, 2]] - all_verts[f[:, 0]]), axis=1)

    ak, al = area(kept), area(low)
    total = float(ak.sum() + al.sum())
    islands = holes = 0
    if area_ratio > 0 and total > 0:
        def small_at_cut(f, fa, flag):
            lab = _face_components(f, len(all_verts))
            if not len(lab):
                return np.zeros(0, bool), 0
            comp_area = np.bincount(lab, weights=fa)
            comp_cut = np.bincount(lab, weights=flag.astype(float)) > 0
            small = (comp_area < area_ratio * total) & comp_cut
            return small[lab], int(small.sum())

        drop_kept, islands = small_at_cut(kept, ak, kept_flag)
        back_low, holes = small_at_cut(low, al, low_flag)
        kept_area = float(ak[~drop_kept].sum() + al[back_low].sum())
        kept = np.concatenate([kept[~drop_kept], low[back_low]])
    else:
        kept_area = float(ak.sum())
    used, remap = np.unique(kept, return_inverse=True)
    info = {"trim_value": float(trim), "faces_cut_or_dropped": int(len(faces) - np.sum(n_above == 3)),
            "area_trimmed_fraction": (1.0 - kept_area / total) if total > 0 else 0.0,
            "islands_removed": islands, "holes_kept": holes, "supported_vertices": int(lift.sum())}
    return all_verts[used], remap.reshape(-1, 3).astype(np.int64), all_vals[used], info
