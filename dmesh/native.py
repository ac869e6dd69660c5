"""The one module that imports the compiled core `dmesh._native`.

Every function here converts its inputs to the fixed dtypes of the native boundary (float64 geometry,
int32 indices, C-contiguous), validates shapes with messages that name the argument, and returns NumPy
arrays. Letters: N points, T tets, F faces.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

try:
    from dmesh import _native
except ImportError as exc:  # pragma: no cover - only without a build
    raise ImportError(
        "dmesh._native is not built; run `make setup` (or `pip install --no-build-isolation -e .`)"
    ) from exc

#: dtype of every index array crossing the native boundary (see native/src/types.h).
INDEX_DTYPE = np.int32
#: dtype of geometry that decides combinatorics (positions, weights, orthocentres).
GEOMETRY_DTYPE = np.float64


def as_points(points, name: str = "points") -> np.ndarray:
    """(N, 3) float64 C-contiguous copy-free view where possible; raises ValueError on bad shape/values."""
    if hasattr(points, "detach"):
        points = points.detach().cpu().numpy()
    arr = np.ascontiguousarray(points, dtype=GEOMETRY_DTYPE)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
        raise ValueError(f"{name} must be finite; row {bad} is {arr[bad].tolist()}")
    return arr


def as_weights(weights, n: int, name: str = "weights") -> np.ndarray:
    """(N,) float64; None gives zeros. Raises ValueError on bad shape or non-finite values."""
    if weights is None:
        return np.zeros(n, dtype=GEOMETRY_DTYPE)
    if hasattr(weights, "detach"):
        weights = weights.detach().cpu().numpy()
    arr = np.ascontiguousarray(weights, dtype=GEOMETRY_DTYPE)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},) to match the points, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite; index {int(np.flatnonzero(~np.isfinite(arr))[0])} is not")
    return arr


def as_index(array, cols: int, name: str) -> np.ndarray:
    """(R, cols) int32 C-contiguous; raises ValueError on a bad shape."""
    if hasattr(array, "detach"):
        array = array.detach().cpu().numpy()
    arr = np.ascontiguousarray(array, dtype=INDEX_DTYPE)
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise ValueError(f"{name} must have shape (rows, {cols}), got {arr.shape}")
    return arr


class RawTriangulation(NamedTuple):
    tets: np.ndarray          # (T, 4) int32
    neighbors: np.ndarray     # (T, 4) int32, -1 on the hull
    duplicate_of: np.ndarray  # (N,) int32, -1 when unique
    stats: dict               # insert_seconds, total_seconds, num_vertices, parallel


def regular_triangulation(points, weights, parallel: int = -1) -> RawTriangulation:
    """CGAL regular triangulation; see `dmesh.wdt.regular_triangulation` for the contract."""
    p = as_points(points)
    w = as_weights(weights, len(p))
    return RawTriangulation(*_native.regular_triangulation(p, w, int(parallel)))


def have_tbb() -> bool:
    return bool(_native.have_tbb())


PARALLEL_THRESHOLD: int = int(_native.PARALLEL_THRESHOLD)


def jet_smooth(points, k: int, degree: int = 2, parallel: int = 0) -> np.ndarray:
    """(N, 3) float64: each point moved onto the degree-`degree` jet fitted to its `k` nearest neighbours
    (CGAL's `jet_smooth_point_set`); see `dmesh.recon.init.smooth_points`. ValueError for bad k or degree."""
    return _native.jet_smooth(as_points(points), int(k), int(degree), int(degree), int(parallel))


def refine_and_fair(vertices, faces, patch, density: float = 2.0 ** 0.5, continuity: int = 1,
                    hold=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """A smooth surface over the `patch` faces of a mesh (CGAL's `refine` and `fair`, the last two steps of
    Liepa's hole filling).

    Args:
        vertices: (V, 3) float; faces: (F, 3) int, a consistently oriented 2-manifold; patch: (F,) bool.
        density: `refine`'s density control factor (larger: more new vertices; CGAL's default sqrt(2)).
        continuity: fairing continuity at the patch's rim: 0 membrane, 1 thin plate, 2 curvature variation.
        hold: None, or (V,) bool: input vertices that stay where they are even with only patch faces around them.
    Returns:
        (V', 3) float64 vertices (the input's first, those with only patch faces around them and not held
        moved), (F', 3)
        int64 faces, (F',) bool patch faces, and whether the fairing system was solved.
    Raises:
        ValueError: faces that do not make a consistently oriented 2-manifold, bad indices or settings.
    """
    f = as_index(faces, 3, "faces")
    mask = np.ascontiguousarray(np.asarray(patch, dtype=bool).reshape(-1).view(np.uint8))
    if len(mask) != len(f):
        raise ValueError(f"patch has {len(mask)} entries for {len(f)} faces")
    v = as_points(vertices, "vertices")
    held = np.zeros(len(v), bool) if hold is None else np.asarray(hold, dtype=bool).reshape(-1)
    if len(held) != len(v):
        raise ValueError(f"hold has {len(held)} entries for {len(v)} vertices")
    held = np.ascontiguousarray(held.view(np.uint8))
    v, f, flag, solved = _native.refine_and_fair(v, f, mask, float(density), int(continuity), held)
    return v, f.astype(np.int64), flag.astype(bool), bool(solved)


def tet_neighbors(tets) -> np.ndarray:
    """(T, 4) int32 tet opposite each vertex, or -1 on the hull."""
    return _native.tet_neighbors(as_index(tets, 4, "tets"))


class RawPowerDiagram(NamedTuple):
    orthocentres: np.ndarray  # (T, 3) float64
    faces: np.ndarray         # (F, 3) int32, sorted rows
    face_tets: np.ndarray     # (F, 2) int32, -1 second for hull faces
    hull_dirs: np.ndarray     # (F, 3) float64
    tet_faces: np.ndarray     # (T, 4) int32
    point_tets: tuple         # (offsets (N+1,), indices)
    point_faces: tuple
    point_neighbors: tuple


def power_diagram(points, weights, tets, neighbors) -> RawPowerDiagram:
    p = as_points(points)
    w = as_weights(weights, len(p))
    t = as_index(tets, 4, "tets")
    nb = as_index(neighbors, 4, "neighbors")
    if len(nb) != len(t):
        raise ValueError(f"neighbors must have {len(t)} rows like tets, got {len(nb)}")
    return RawPowerDiagram(*_native.power_diagram(p, w, t, nb))


def nearest_planes_raw(points, weights, faces, samples, nbr_offsets, nbr_indices):
    """((F, 3) int32 nearest bisector neighbour per face vertex (-1: none), (F, 3) float64 its distance
    (inf where none)). Arrays as in `_native`."""
    return _native.nearest_planes(points, weights, as_index(faces, 3, "faces"),
                                  np.ascontiguousarray(samples, dtype=GEOMETRY_DTYPE),
                                  np.ascontiguousarray(nbr_offsets, dtype=INDEX_DTYPE),
                                  np.ascontiguousarray(nbr_indices, dtype=INDEX_DTYPE))


def nearest_cell_edges_raw(points, weights, faces, line_origin, line_dir, pf_offsets, pf_indices,
                           edge_start, edge_end, is_ray, nbr_offsets, nbr_indices):
    """((C, 3) int32 nearest power-cell edge per vertex (-1: none), (C, 3) uint8 line-crosses-cell,
    (C, 3) float64 line-to-cell distance (0 where it crosses))."""
    f64 = lambda a: np.ascontiguousarray(a, dtype=GEOMETRY_DTYPE)  # noqa: E731
    i32 = lambda a: np.ascontiguousarray(a, dtype=INDEX_DTYPE)  # noqa: E731
    return _native.nearest_cell_edges(points, weights, as_index(faces, 3, "faces"), f64(line_origin),
                                      f64(line_dir), i32(pf_offsets), i32(pf_indices), f64(edge_start),
                                      f64(edge_end), np.ascontiguousarray(is_ray, dtype=np.uint8),
                                      i32(nbr_offsets), i32(nbr_indices))


def merge_csr(off_a, idx_a, off_b, idx_b):
    """Row-wise sorted union of two CSR lists: (offsets, indices) int32."""
    i32 = lambda a: np.ascontiguousarray(a, dtype=INDEX_DTYPE)  # noqa: E731
    return _native.merge_csr(i32(off_a), i32(idx_a), i32(off_b), i32(idx_b))


# ----------------------------------------------------------------------------------------------------------
# Face-key sets (native/src/face_keys.h): linear merges of sorted int64 keys (`dmesh.wdt.face_keys`) for the
# per-phase candidate faces (`dmesh.candidates`).
# ----------------------------------------------------------------------------------------------------------

def union_sorted_keys(a, b) -> np.ndarray:
    """(U,) int64 sorted union of two sorted unique int64 key arrays; ValueError if either is not."""
    i64 = lambda x: np.ascontiguousarray(x, dtype=np.int64)  # noqa: E731
    return _native.union_sorted_keys(i64(a), i64(b))


def off_wdt_candidates(cand, wdt, hidden) -> tuple[np.ndarray, np.ndarray]:
    """((C', 3) int64 sorted triples, (C',) int64 keys) of the candidate keys `cand` (sorted unique) that are
    not in `wdt` (sorted keys) and whose three points are not `hidden` ((n,) bool over the n points the keys
    count)."""
    i64 = lambda x: np.ascontiguousarray(x, dtype=np.int64)  # noqa: E731
    return _native.off_wdt_candidates(i64(cand), i64(wdt), np.ascontiguousarray(hidden, dtype=np.uint8))


# ----------------------------------------------------------------------------------------------------------
# Fused Delta kernels (native/src/delta_recompute.h): argmin search and per-vertex distances in one forward
# call, their analytic gradient in one backward call, on a `DeltaDiagram` handle (validated once per pass).
# ----------------------------------------------------------------------------------------------------------

def delta_diagram(points, weights, pd, num_threads: int = 0):
    """The `_native.DeltaDiagram` of `pd` (a `dmesh.wdt.PowerDiagram`, duck-typed) for the points (N, 3)
    and weights (N,) (float64 arrays; the diagram's combinatorics, geometry recomputed from these)."""
    i32 = lambda a: np.ascontiguousarray(a, dtype=INDEX_DTYPE)  # noqa: E731
    return _native.delta_diagram(
        np.ascontiguousarray(points, dtype=GEOMETRY_DTYPE), np.ascontiguousarray(weights, dtype=GEOMETRY_DTYPE),
        i32(pd.tets), i32(pd.tet_faces), i32(pd.faces), i32(pd.face_tets),
        np.ascontiguousarray(pd.ray_dirs, dtype=GEOMETRY_DTYPE), i32(pd.point_tets.offsets),
        i32(pd.point_tets.indices), i32(pd.point_faces.offsets), i32(pd.point_faces.indices),
        i32(pd.point_neighbors.offsets), i32(pd.point_neighbors.indices), int(num_threads))


def orthocentre_backward(diagram, grad, num_threads: int = 0):
    """((N, 3), (N,)) float64 gradients of sum(grad * diagram.orthocentres) for grad (T, 3) (degenerate,
    clamped tets pass none); reduced per point in a fixed order (bit-for-bit the same for any thread count)."""
    return _native.orthocentre_backward(diagram, np.ascontiguousarray(grad, dtype=GEOMETRY_DTYPE), int(num_threads))


def _mask(active) -> np.ndarray:
    return np.zeros(0, np.uint8) if active is None else np.ascontiguousarray(active, dtype=np.uint8)


#: Hint entry asking the Delta kernels for the full search (others are reused: the coherent pass).
SEARCH: int = -2


def _hint(hint) -> np.ndarray:
    return np.zeros(0, INDEX_DTYPE) if hint is None else _i32(hint)


def existing_delta_forward(diagram, face_ids, cache_offsets, cache_indices, ray_length: float, hint=None,
                           num_threads: int = 0):
    """((K, 3) int32 chosen neighbour per face vertex (-1: none), (K, 3) float64 delta (ray_length where
    none)) for the WDT faces face_ids (K,). hint: None, or (K, 3) ints, SEARCH or the neighbour to reuse.
    num_threads: 0 = OpenMP default above a size threshold."""
    return _native.existing_delta_forward(diagram, _i32(face_ids).reshape(-1), _i32(cache_offsets),
                                          _i32(cache_indices), float(ray_length), _hint(hint), int(num_threads))


def existing_delta_backward(diagram, face_ids, neighbour, grad, active, ray_length: float, num_threads: int = 0):
    """((N, 3), (N,)) float64 gradients of sum(grad * delta) over the rows with active (K,) bool set (None:
    all rows); neighbour (K, 3) from the forward."""
    return _native.existing_delta_backward(diagram, _i32(face_ids).reshape(-1), _i32(neighbour),
                                           np.ascontiguousarray(grad, dtype=GEOMETRY_DTYPE), _mask(active),
                                           float(ray_length), int(num_threads))


def candidate_delta_forward(diagram, cand, ray_length: float, hint=None, num_threads: int = 0):
    """((C, 3) int32 nearest cell edge (a WDT face id, -1: none), (C, 3) uint8 line crosses the cell,
    (C, 3) float64 delta) for candidate faces cand (C, 3) not in the WDT. hint: None, or (C, 3) ints,
    SEARCH or the edge to reuse."""
    return _native.candidate_delta_forward(diagram, _i32(cand), float(ray_length), _hint(hint), int(num_threads))


def csr_rows_changed(a_offsets, a_indices, b_offsets, b_indices) -> np.ndarray:
    """(rows,) bool, True where row r of CSR a differs from row r of CSR b."""
    return _native.csr_rows_changed(_i32(a_offsets), _i32(a_indices), _i32(b_offsets), _i32(b_indices)).astype(bool)


def candidate_delta_backward(diagram, cand, edge, crosses, grad, active, num_threads: int = 0):
    """((N, 3), (N,)) float64 gradients of sum(grad * delta) over the rows with active (C,) bool set (None:
    all rows); edge and crosses (C, 3) from the forward."""
    return _native.candidate_delta_backward(diagram, _i32(cand), _i32(edge),
                                            np.ascontiguousarray(crosses, dtype=np.uint8),
                                            np.ascontiguousarray(grad, dtype=GEOMETRY_DTYPE), _mask(active),
                                            int(num_threads))


# ----------------------------------------------------------------------------------------------------------
# Renderers (dmesh/render.py). Letters: N vertices, F faces, T tets, H x W pixels, K fragments.
# ----------------------------------------------------------------------------------------------------------

def _f32(a) -> np.ndarray:
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.ascontiguousarray(a, dtype=np.float32)


def _i32(a) -> np.ndarray:
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.ascontiguousarray(a, dtype=INDEX_DTYPE)


#: The fields both renderers' outputs start with: diffuse, depth and alpha (H, W) float32 images, and
#: frag_face (K,) int32, the face of each composited fragment.
_IMAGE_FIELDS = [("diffuse", np.ndarray), ("depth", np.ndarray), ("alpha", np.ndarray), ("frag_face", np.ndarray)]
#: The soft rasteriser's output: the images, pix_range (H, W, 2) int32 (first fragment, count) per pixel,
#: stats (num_drawn, num_bins, num_fragments).
RawSoftRender = NamedTuple("RawSoftRender", _IMAGE_FIELDS + [("pix_range", np.ndarray), ("stats", dict)])
#: The tet renderer's output: the images, frag_diffuse and frag_depth (K,) float32, pix_range as above,
#: stats (num_steps, num_fragments).
RawTetRender = NamedTuple("RawTetRender", _IMAGE_FIELDS + [
    ("frag_diffuse", np.ndarray), ("frag_depth", np.ndarray), ("pix_range", np.ndarray), ("stats", dict)])


def soft_render_forward(verts, faces, opacity, world_to_camera, fov_y: float, height: int, width: int,
                        near: float, edge_width: float, min_opacity: float, t_min: float,
                        num_threads: int) -> RawSoftRender:
    """Soft tile rasteriser forward (native/src/soft_render.h); fov_y in radians."""
    return RawSoftRender(*_native.soft_render_forward(
        _f32(verts), _i32(faces), _f32(opacity),
        np.ascontiguousarray(world_to_camera, dtype=np.float64), float(fov_y), int(height), int(width),
        float(near), float(edge_width), float(min_opacity), float(t_min), int(num_threads)))


def soft_render_backward(verts, faces, opacity, world_to_camera, fov_y: float, height: int, width: int,
                         near: float, edge_width: float, min_opacity: float, t_min: float, num_threads: int,
                         frag_face, pix_range, grad_diffuse, grad_depth, grad_alpha):
    """((N, 3) float32 vertex gradient, (F,) float32 opacity gradient) for the forward's fragments."""
    return _native.soft_render_backward(
        _f32(verts), _i32(faces), _f32(opacity),
        np.ascontiguousarray(world_to_camera, dtype=np.float64), float(fov_y), int(height), int(width),
        float(near), float(edge_width), float(min_opacity), float(t_min), int(num_threads), _i32(frag_face),
        _i32(pix_range), _f32(grad_diffuse), _f32(grad_depth),
        _f32(grad_alpha))


def tet_render_forward(verts, tets, faces, face_tets, opacity, world_to_camera, fov_y: float, height: int,
                       width: int, near: float, min_opacity: float, t_min: float,
                       num_threads: int) -> RawTetRender:
    """Tetrahedral walk renderer forward (native/src/tet_render.h); fov_y in radians."""
    return RawTetRender(*_native.tet_render_forward(
        _f32(verts), _i32(tets), _i32(faces), _i32(face_tets), _f32(opacity),
        np.ascontiguousarray(world_to_camera, dtype=np.float64), float(fov_y), int(height), int(width),
        float(near), float(min_opacity), float(t_min), int(num_threads)))


def tet_render_backward(opacity, frag_face, frag_diffuse, frag_depth, pix_range, grad_diffuse, grad_depth,
                        grad_alpha, num_threads: int) -> np.ndarray:
    """(F,) float32 opacity gradient for the forward's fragments."""
    return _native.tet_render_backward(
        _f32(opacity), _i32(frag_face), _f32(frag_diffuse),
        _f32(frag_depth), _i32(pix_range), _f32(grad_diffuse),
        _f32(grad_depth), _f32(grad_alpha), int(num_threads))


# ----------------------------------------------------------------------------------------------------------
# Expected Chamfer, target -> DMesh term (dmesh/losses/chamfer.py). Letters: G target points, S samples on
# the DMesh, K candidates per target row. Geometry goes in as float64 or float32 (the `dtype` argument).
# ----------------------------------------------------------------------------------------------------------

def _as_array(a) -> np.ndarray:
    return a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a)


def _rows3(fn: str, name: str, letter: str, a, dtype) -> np.ndarray:
    """(R, 3) C-contiguous array of `dtype`; ValueError naming `fn` and the argument otherwise."""
    out = np.ascontiguousarray(_as_array(a), dtype=dtype)
    if out.ndim != 2 or out.shape[1] != 3:
        raise ValueError(f"{fn}: {name} must have shape ({letter}, 3), got {out.shape}")
    return out


def _chamfer_inputs(fn: str, target, points, prob, face, knn, dtype) -> tuple:
    dtype = np.dtype(dtype)
    if dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"{fn}: dtype must be float32 or float64, got {dtype}")
    t = _rows3(fn, "target", "G", target, dtype)
    p = _rows3(fn, "points", "S", points, dtype)
    pr = np.ascontiguousarray(_as_array(prob), dtype=dtype)
    if pr.shape != (len(p),):
        raise ValueError(f"{fn}: prob must have shape ({len(p)},) like points, got {pr.shape}")
    f = _as_array(face)
    if f.shape != (len(p),):
        raise ValueError(f"{fn}: face must have shape ({len(p)},) like points, got {f.shape}")
    if f.dtype != INDEX_DTYPE and len(f) and (f.min() < 0 or f.max() > np.iinfo(INDEX_DTYPE).max):
        raise ValueError(f"{fn}: face ids must lie in [0, 2^31), got [{f.min()}, {f.max()}]")
    f = np.ascontiguousarray(f, dtype=INDEX_DTYPE)
    # knn values are checked against [0, S) by the kernel, -1 ending a row (int64 ids from a k-d tree are below
    # S < 2^31).
    k = np.ascontiguousarray(_as_array(knn), dtype=INDEX_DTYPE)
    if k.ndim != 2 or len(k) != len(t):
        raise ValueError(f"{fn}: knn must have shape ({len(t)}, K) like target, got {k.shape}")
    return t, p, pr, f, k


def _plane_inputs(fn: str, target_normals, tangent_weight: float, G: int):
    """(normals (G, 3) float64 or None, weight) for the kernel; None when the weight is 1 or there are none."""
    w = float(tangent_weight)
    if not 0.0 <= w <= 1.0:
        raise ValueError(f"{fn}: tangent_weight must be in [0, 1], got {tangent_weight}")
    if target_normals is None or w == 1.0:
        return None, 1.0
    n = np.ascontiguousarray(_as_array(target_normals), dtype=np.float64)
    if n.shape != (G, 3):
        raise ValueError(f"{fn}: target_normals must have shape ({G}, 3) like target, got {n.shape}")
    return n, w


def expected_chamfer_forward(target, points, prob, face, knn, num_threads: int = 0, dtype=np.float64,
                             target_normals=None, tangent_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Expected nearest distance per target row (native/src/expected_chamfer.h).

    Args:
        target: (G, 3); points: (S, 3); prob: (S,) floats, converted to `dtype` (float64 or float32).
        face: (S,) ints >= 0, face id of each sample; knn: (G, K) ints in [0, S), each row's sample ids sorted
            by distance; a row ends early at its first -1 (rows of different lengths). num_threads: OpenMP
            threads (0: the OpenMP default).
        target_normals: (G, 3) unit normals, or None; with a tangent_weight w below 1 the distances are
            sqrt(a^2 + w^2 (|o|^2 - a^2)) of the offset o and its normal part a, and each row is taken in
            increasing distance (not upstream; `dmesh.reference.chamfer.plane_weighted_distance`).
    Returns:
        (expected (G,) float64, residual (G,) float64).
    """
    fn = "expected_chamfer_forward"
    t, p, pr, f, k = _chamfer_inputs(fn, target, points, prob, face, knn, dtype)
    n, w = _plane_inputs(fn, target_normals, tangent_weight, len(t))
    return _native.expected_chamfer_forward(t, p, pr, f, k, int(num_threads), n, w)


def expected_chamfer_backward(target, points, prob, face, knn, grad_expected, num_threads: int = 0,
                              dtype=np.float64, target_normals=None,
                              tangent_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of sum_g grad_expected[g] * expected[g] for the forward's inputs.

    Args: as `expected_chamfer_forward`, plus grad_expected: (G,) floats.
    Returns:
        (grad_points (S, 3), grad_prob (S,)) in `dtype`; byte-identical for any num_threads.
    """
    fn = "expected_chamfer_backward"
    t, p, pr, f, k = _chamfer_inputs(fn, target, points, prob, face, knn, dtype)
    w = np.ascontiguousarray(_as_array(grad_expected), dtype=np.float64)
    if w.shape != (len(t),):
        raise ValueError(f"{fn}: grad_expected must have shape ({len(t)},) like target, got {w.shape}")
    n, tw = _plane_inputs(fn, target_normals, tangent_weight, len(t))
    return _native.expected_chamfer_backward(t, p, pr, f, k, w, int(num_threads), n, tw)


def point_tree(points, leaf_size: int):
    """A `_native.PointTree` of (n, 3) points (float64) for repeated `knn_search_trees` calls: built once, on
    either side of a search (as the query side, its leaves of at most `leaf_size` points are the groups)."""
    return _native.PointTree(_rows3("point_tree", "points", "n", points, np.float64), int(leaf_size))


def knn_search_trees(data, queries, k: int, num_threads: int = 0) -> np.ndarray:
    """`knn_search` of two `point_tree`s: (Q, k) int32 ids of the k nearest `data` points of every `queries`
    point, nearest first, the same ids as `knn_search` of their coordinates."""
    return _native.knn_search_trees(data, queries, int(k), int(num_threads))


def knn_search(data, queries, k: int, num_threads: int = 0, dtype=np.float64) -> np.ndarray:
    """(Q, k) int32 ids of the k nearest data points of every query, nearest first, exact, ties to the smaller
    id (independent of num_threads). data: (D, 3), queries: (Q, 3) floats, converted to `dtype`; k <= D."""
    fn = "knn_search"
    d = _rows3(fn, "data", "D", data, dtype)
    q = _rows3(fn, "queries", "Q", queries, dtype)
    if not 0 <= int(k) <= len(d):
        raise ValueError(f"{fn}: k must be in [0, {len(d)}] (the number of data points), got {k}")
    return _native.knn_search(d, q, int(k), int(num_threads))
