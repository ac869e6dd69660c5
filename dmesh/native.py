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

from dmesh.typing import GEOMETRY_DTYPE, INDEX_DTYPE


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


class RawSoftRender(NamedTuple):
    diffuse: np.ndarray    # (H, W) float32
    depth: np.ndarray      # (H, W) float32
    alpha: np.ndarray      # (H, W) float32
    frag_face: np.ndarray  # (K,) int32
    pix_range: np.ndarray  # (H, W, 2) int32
    stats: dict            # num_drawn, num_bins, num_fragments


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


class RawTetRender(NamedTuple):
    diffuse: np.ndarray       # (H, W) float32
    depth: np.ndarray         # (H, W) float32
    alpha: np.ndarray         # (H, W) float32
    frag_face: np.ndarray     # (K,) int32
    frag_diffuse: np.ndarray  # (K,) float32
    frag_depth: np.ndarray    # (K,) float32
    pix_range: np.ndarray     # (H, W, 2) int32
    stats: dict               # num_steps, num_fragments


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
