"""Type stubs of the compiled core `dmesh._native` (native/bindings/bind_*.cpp).

Every array crosses the boundary C-contiguous with the dtype named here (float64 geometry, int32 indices,
uint8 flags; float32 for the renderers); `dmesh.native` converts and validates the inputs. Letters: N
points, T tets, F faces, C candidate faces, K rows or fragments, G target points, S samples, H x W pixels.
"""
from typing import overload

import numpy as np
from numpy.typing import NDArray

_F32 = NDArray[np.float32]
_F64 = NDArray[np.float64]
_I32 = NDArray[np.int32]
_I64 = NDArray[np.int64]
_U8 = NDArray[np.uint8]
#: CSR lists: (offsets (rows + 1,), indices) int32.
_Csr = tuple[_I32, _I32]

#: Point count above which `regular_triangulation(parallel=-1)` inserts in parallel (with TBB).
PARALLEL_THRESHOLD: int

# ---------------------------------------------------------------------------------- triangulation (bind_wdt)
def regular_triangulation(points: _F64, weights: _F64, parallel: int = -1) -> tuple[_I32, _I32, _I32, dict]:
    """(tets (T, 4), neighbors (T, 4) -1 on the hull, duplicate_of (N,) -1 when unique, stats) of the CGAL
    regular triangulation; parallel: 0 sequential, 1 TBB, -1 automatic."""

def have_tbb() -> bool:
    """Whether TBB-parallel insertion was compiled in."""

def tet_neighbors(tets: _I32) -> _I32:
    """(T, 4) tet opposite each vertex, -1 on the hull."""

# ------------------------------------------------------------------------ power diagram (bind_power_diagram)
def power_diagram(points: _F64, weights: _F64, tets: _I32,
                  neighbors: _I32) -> tuple[_F64, _I32, _I32, _F64, _I32, _Csr, _Csr, _Csr]:
    """(orthocentres (T, 3), faces (F, 3) sorted, face_tets (F, 2) -1 for hull rays, hull_dirs (F, 3),
    tet_faces (T, 4), point_tets, point_faces, point_neighbors)."""

def merge_csr(off_a: _I32, idx_a: _I32, off_b: _I32, idx_b: _I32) -> _Csr:
    """Row-wise sorted union of two CSR lists."""

def union_sorted_keys(a: _I64, b: _I64) -> _I64:
    """Sorted union of two sorted unique face-key arrays (native/src/face_keys.h)."""

def off_wdt_candidates(cand: _I64, wdt: _I64, hidden: _U8) -> tuple[_I64, _I64]:
    """(faces (C', 3) sorted triples, keys (C',)): candidate keys not in the WDT's, no point hidden."""

def csr_rows_changed(off_a: _I32, idx_a: _I32, off_b: _I32, idx_b: _I32) -> _U8:
    """(rows,) 1 where the two CSR lists' rows differ."""

# ------------------------------------------------------------------------------- argmin searches (bind_argmin)
def nearest_planes(points: _F64, weights: _F64, faces: _I32, samples: _F64, nbr_offsets: _I32,
                   nbr_indices: _I32) -> tuple[_I32, _F64]:
    """(neighbour (F, 3) -1 where none, dist (F, 3)): per face vertex the bisector plane nearest the sample."""

def nearest_cell_edges(points: _F64, weights: _F64, faces: _I32, line_origin: _F64, line_dir: _F64, pf_offsets: _I32,
                       pf_indices: _I32, edge_start: _F64, edge_end: _F64, is_ray: _U8, nbr_offsets: _I32,
                       nbr_indices: _I32) -> tuple[_I32, _U8, _F64]:
    """(edge (C, 3) -1 where none, crosses (C, 3), dist (C, 3)): per candidate vertex the nearest power-cell
    edge to the dual line, or a crossing (distance 0)."""

# ------------------------------------------------------------------------------- fused Delta (bind_delta)
class DeltaDiagram:
    """A power diagram validated once for the Delta kernels (`delta_diagram`); keeps its arrays alive."""

    @property
    def num_points(self) -> int: ...
    @property
    def num_faces(self) -> int: ...
    @property
    def orthocentres(self) -> _F64:
        """(T, 3) orthocentres recomputed from the points (a copy)."""

def delta_diagram(points: _F64, weights: _F64, tets: _I32, tet_faces: _I32, faces: _I32, face_tets: _I32,
                  hull_dirs: _F64, pt_offsets: _I32, pt_indices: _I32, pf_offsets: _I32, pf_indices: _I32,
                  nb_offsets: _I32, nb_indices: _I32, num_threads: int = 0) -> DeltaDiagram: ...

def orthocentre_backward(diagram: DeltaDiagram, grad: _F64, num_threads: int = 0) -> tuple[_F64, _F64]:
    """(grad_points (N, 3), grad_weights (N,)) of sum(grad * diagram.orthocentres)."""

def existing_delta_forward(diagram: DeltaDiagram, face_ids: _I32, cache_offsets: _I32, cache_indices: _I32,
                           ray_length: float, hint: _I32, num_threads: int = 0) -> tuple[_I32, _F64]:
    """(neighbour (K, 3), dist (K, 3)) of the WDT faces face_ids; hint (K, 3) or empty, -2: search."""

def existing_delta_backward(diagram: DeltaDiagram, face_ids: _I32, neighbour: _I32, grad: _F64, active: _U8,
                            ray_length: float, num_threads: int = 0) -> tuple[_F64, _F64]:
    """(grad_points (N, 3), grad_weights (N,)); active (K,) or empty (all rows)."""

def candidate_delta_forward(diagram: DeltaDiagram, cand: _I32, ray_length: float, hint: _I32,
                            num_threads: int = 0) -> tuple[_I32, _U8, _F64]:
    """(edge (C, 3), crosses (C, 3), dist (C, 3)) of candidates cand (C, 3); hint (C, 3) or empty, -2: search."""

def candidate_delta_backward(diagram: DeltaDiagram, cand: _I32, edge: _I32, crosses: _U8, grad: _F64, active: _U8,
                             num_threads: int = 0) -> tuple[_F64, _F64]:
    """(grad_points (N, 3), grad_weights (N,)); active (C,) or empty (all rows)."""

# ----------------------------------------------------------------------------------- renderers (bind_render)
def soft_render_forward(verts: _F32, faces: _I32, opacity: _F32, world_to_camera: _F64, fov_y: float, height: int,
                        width: int, near: float, edge_width: float, min_opacity: float, t_min: float,
                        num_threads: int) -> tuple[_F32, _F32, _F32, _I32, _I32, dict]:
    """(diffuse, depth, alpha (H, W), frag_face (K,), pix_range (H, W, 2), stats); fov_y in radians."""

def soft_render_backward(verts: _F32, faces: _I32, opacity: _F32, world_to_camera: _F64, fov_y: float, height: int,
                         width: int, near: float, edge_width: float, min_opacity: float, t_min: float,
                         num_threads: int, frag_face: _I32, pix_range: _I32, grad_diffuse: _F32, grad_depth: _F32,
                         grad_alpha: _F32) -> tuple[_F32, _F32]:
    """(grad_verts (N, 3), grad_opacity (F,))."""

def tet_render_forward(verts: _F32, tets: _I32, faces: _I32, face_tets: _I32, opacity: _F32, world_to_camera: _F64,
                       fov_y: float, height: int, width: int, near: float, min_opacity: float, t_min: float,
                       num_threads: int) -> tuple[_F32, _F32, _F32, _I32, _F32, _F32, _I32, dict]:
    """(diffuse, depth, alpha (H, W), frag_face, frag_diffuse, frag_depth (K,), pix_range (H, W, 2), stats)."""

def tet_render_backward(opacity: _F32, frag_face: _I32, frag_diffuse: _F32, frag_depth: _F32, pix_range: _I32,
                        grad_diffuse: _F32, grad_depth: _F32, grad_alpha: _F32, num_threads: int) -> _F32:
    """grad_opacity (F,)."""

# ------------------------------------------------------------------------- expected Chamfer (bind_chamfer)
@overload
def expected_chamfer_forward(target: _F64, points: _F64, prob: _F64, face: _I32, knn: _I32,
                             num_threads: int, target_normals: _F64 | None = None,
                             tangent_weight: float = 1.0) -> tuple[_F64, _F64]: ...
@overload
def expected_chamfer_forward(target: _F32, points: _F32, prob: _F32, face: _I32, knn: _I32,
                             num_threads: int, target_normals: _F64 | None = None,
                             tangent_weight: float = 1.0) -> tuple[_F64, _F64]:
    """(expected (G,), residual (G,)); target, points and prob all float32 or all float64; target normals
    (G, 3) with a tangent weight below 1: tangent-weighted distances, rows sorted by them."""

@overload
def expected_chamfer_backward(target: _F64, points: _F64, prob: _F64, face: _I32, knn: _I32, grad_expected: _F64,
                              num_threads: int, target_normals: _F64 | None = None,
                              tangent_weight: float = 1.0) -> tuple[_F64, _F64]: ...
@overload
def expected_chamfer_backward(target: _F32, points: _F32, prob: _F32, face: _I32, knn: _I32, grad_expected: _F64,
                              num_threads: int, target_normals: _F64 | None = None,
                              tangent_weight: float = 1.0) -> tuple[_F32, _F32]:
    """(grad_points (S, 3), grad_prob (S,)) in the inputs' float type."""

class PointTree:
    """A k-d tree of 3D points for repeated knn_search_trees calls."""
    def __init__(self, points: _F64, leaf_size: int) -> None: ...
    @property
    def size(self) -> int: ...

def knn_search_trees(data: PointTree, queries: PointTree, k: int, num_threads: int) -> _I32:
    """knn_search of the trees' points: the same ids, without building the trees again."""

@overload
def knn_search(data: _F64, queries: _F64, k: int, num_threads: int) -> _I32: ...
@overload
def knn_search(data: _F32, queries: _F32, k: int, num_threads: int) -> _I32:
    """(Q, k) ids of the k nearest data points of every query, nearest first, ties to the smaller id."""

# ---------------------------------------------------------------------- points and meshes (bind_points, bind_mesh)
def jet_smooth(points: _F64, k: int, degree_fitting: int = 2, degree_monge: int = 2, parallel: int = 0) -> _F64:
    """(N, 3) each point moved onto the jet fitted to its k nearest neighbours (CGAL::jet_smooth_point_set)."""

def refine_and_fair(vertices: _F64, faces: _I32, patch: _U8, density: float,
                    continuity: int) -> tuple[_F64, _I32, _U8, bool]:
    """(vertices (V', 3), faces (F', 3), patch (F',), solved) after CGAL's refine of the patch faces of a
    consistently oriented 2-manifold and fair of every vertex with only patch faces around it; the input's
    vertices keep their indices, new ones follow."""
