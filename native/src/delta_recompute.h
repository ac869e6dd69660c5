// Fused argmin search and differentiable per-vertex distances behind Delta (DESIGN.md section 4), with an
// analytic backward. Replaces "native argmin, then recompute the chosen distances in torch".
//
// Letters: N points, T tets, F faces of the current WDT, K WDT faces scored, C candidate faces (not in the
// WDT), M CSR entries.
//
// Orthocentres: c(t) = p_0 + x solves A x = b with rows A_j = 2 (p_j - p_0), b_j = |p_j - p_0|^2 - (w_j - w_0)
// (Cramer's rule relative to p_0 as in dmesh.geometry.orthocentres, including its floor |det| >= 1e-18),
// recomputed from points and weights once per diagram (delta_orthocentres).
// Existing faces (a WDT face f = (a, b, c), sorted ids, tets t0 and t1, or t0 only on the hull):
//   s = (c(t0) + c(t1)) / 2, or for a hull face s = c(t0) + R u with u = +-(b - a) x (c - a) / |.| the
//   outward normal (the sign of hull_dirs[f]).
//   For each vertex i of f: delta_i = min over cached neighbours j of i, j not in f, of the distance of s
//   to the power bisector H(i, j): | (s - p_i).d / |d| - (|d| - (w_j - w_i) / |d|) / 2 |, d = p_j - p_i.
//   R where i has no admissible neighbour (no gradient).
// Candidate faces (g = (a, b, c) not in the WDT, every vertex owning a power cell):
//   the dual line o + s u: u = (b - a) x (c - a) / |.|, o = a + alpha e1 + beta e2 (e1 = b - a,
//   e2 = c - a) with [e1.e1 e1.e2; e1.e2 e2.e2] [alpha beta] = [e1.e1 - (w_b - w_a), e2.e2 - (w_c - w_a)] / 2.
//   For each vertex i: 0 when the line crosses i's power cell (half-spaces against the current WDT
//   neighbours; no gradient), else the minimum over the dual edges of i's WDT faces (segments between
//   orthocentres, or rays c(t0) + s u_f, s >= 0, along a hull face's outward normal) of the line-to-edge
//   distance |P (a_e - o + t (b_e - a_e))| (P the projection orthogonal to u, t in [0, 1] or t >= 0 for a
//   ray). Collinear or coincident candidates (|e1 x e2|^2 <= 1e-12 |e1|^2 |e2|^2) and vertices without a
//   cell edge get R without gradient.
// Everything is computed from points and weights (the diagram contributes only its combinatorics and the
// sign of each hull direction), so for fixed argmin indices the forward is the function the backward
// differentiates.
//
// Search order: slots (face, vertex) are processed per point, so the point's cached bisector planes (or
// its cell, projected along the candidate's dual line) are built once and stay in cache.
//
// Backward: the argmin indices are constants (as the torch reference treats them). Gradients are written
// per element into fixed slots (point id, d/dp (3), d/dw): existing faces write the bisector terms per face
// (their vertices and chosen neighbours), then each tet gathers the sample-point gradients of its four faces
// (tet_faces) and writes its orthocentre's adjoint once (with lambda = A^-T g_c: dL/db = lambda,
// dL/dA = -lambda x^T); candidates write up to 18 distinct points per face. The slots are then summed per
// point: every point is owned by exactly one thread (contiguous ranges of point ids), which adds its slots
// in increasing slot order, so the sums are bit-for-bit the same for any thread count (no float atomics, no
// per-thread partial sums). The line-to-edge distance is differentiated with its projection parameter t
// held fixed (exact: at an interior minimum the distance is stationary in t, and a clamped t is locally
// constant). Degenerate (clamped) tets pass no gradient.
//
// num_threads: 0 uses the thread budget (OpenMP's maximum, which torch.set_num_threads sets) above a size
// threshold and one thread below it; n > 0 forces n threads (tests). The loops run on TBB when it is compiled
// in (parallel.h: its idle threads do not spin for milliseconds as OpenMP's do). Results are bit-for-bit the
// same for any thread count.
#pragma once
#include <cstdint>
#include <vector>

#include "types.h"

namespace dmesh {

// The arrays of a power diagram (dmesh.wdt.PowerDiagram) that the kernels read; all C-contiguous and
// validated by the caller (the binding).
struct DiagramView {
  const real_t* points = nullptr;        // (N, 3)
  const real_t* weights = nullptr;       // (N,)
  index_t N = 0;
  const index_t* tets = nullptr;         // (T, 4)
  const index_t* tet_faces = nullptr;    // (T, 4) face opposite vertex k of tet t
  index_t T = 0;
  const index_t* faces = nullptr;        // (F, 3) sorted vertex ids
  const index_t* face_tets = nullptr;    // (F, 2), second kNone on the hull
  const real_t* hull_dirs = nullptr;     // (F, 3) outward direction of hull faces (only its sign is used)
  index_t F = 0;
  const index_t* pt_offsets = nullptr;   // (N + 1,) point -> its tets (rows ascending)
  const index_t* pt_indices = nullptr;
  const index_t* pf_offsets = nullptr;   // (N + 1,) point -> its faces
  const index_t* pf_indices = nullptr;
  const index_t* nb_offsets = nullptr;   // (N + 1,) point -> its WDT neighbours
  const index_t* nb_indices = nullptr;
  const real_t* orthocentres = nullptr;  // (T, 3) from delta_orthocentres
};

// (T, 3) orthocentres of every tet recomputed from points and weights (the formula above).
std::vector<real_t> delta_orthocentres(const DiagramView& d, int num_threads = 0);

struct PointGradient {
  std::vector<real_t> points;   // (N, 3)
  std::vector<real_t> weights;  // (N,)
};

// Gradient of sum_t grad[t] . c(t) (grad (T, 3), c the orthocentres above) with respect to points and
// weights: the orthocentre adjoint of existing_delta_backward, reduced per point in the same fixed order.
PointGradient orthocentre_adjoint(const DiagramView& d, const real_t* grad, int num_threads = 0);

struct ExistingDeltaResult {
  std::vector<index_t> neighbour;  // (K, 3) the chosen neighbour j per vertex, or kNone
  std::vector<real_t> dist;        // (K, 3) delta_i (ray_length where kNone)
};

// Per WDT face face_ids[k] (K,) (repeats allowed) and vertex: the nearest bisector plane among the cached
// neighbour lists (cache_offsets (N+1,), cache_indices (M,)) and its distance to the dual-edge sample.
// hint (K, 3) or null (search everywhere): per slot kSearch (-2) to search, else the neighbour to use
// (kNone: none) without searching; the distance is recomputed either way (the coherent pass).
ExistingDeltaResult existing_delta_forward(const DiagramView& d, const index_t* face_ids, index_t K,
                                           const index_t* cache_offsets, const index_t* cache_indices,
                                           real_t ray_length, const index_t* hint = nullptr,
                                           int num_threads = 0);

// Gradient of sum_k,v grad[k, v] * delta_v(face k) with respect to points and weights, for the rows with
// active[k] != 0 (active may be null: all rows); neighbour is the forward's (K, 3).
PointGradient existing_delta_backward(const DiagramView& d, const index_t* face_ids, index_t K,
                                      const index_t* neighbour, const real_t* grad, const std::uint8_t* active,
                                      real_t ray_length, int num_threads = 0);

struct CandidateDeltaResult {
  std::vector<index_t> edge;          // (C, 3) the nearest cell edge (a WDT face id), or kNone
  std::vector<std::uint8_t> crosses;  // (C, 3) 1 where the dual line crosses the vertex's power cell
  std::vector<real_t> dist;           // (C, 3) delta_i: 0 where crosses, ray_length without an edge
};

// Per candidate cand[k] (C, 3) and vertex: the line-to-cell distance. hint (C, 3) or null: per slot
// kSearch (-2) to search the cell's edges, else the edge (a WDT face id; kNone: none) to measure without
// searching. The crossing test runs for every slot either way.
CandidateDeltaResult candidate_delta_forward(const DiagramView& d, const index_t* cand, index_t C,
                                             real_t ray_length, const index_t* hint = nullptr,
                                             int num_threads = 0);

// (rows,) 1 where row r of CSR a differs from row r of CSR b (length or any entry); both over `rows` rows.
std::vector<std::uint8_t> csr_rows_changed(const index_t* off_a, const index_t* idx_a, const index_t* off_b,
                                           const index_t* idx_b, index_t rows);

// Gradient of sum_k,v grad[k, v] * delta_v(cand k), rows with active[k] != 0 (null: all); edge and
// crosses are the forward's.
PointGradient candidate_delta_backward(const DiagramView& d, const index_t* cand, index_t C,
                                       const index_t* edge, const std::uint8_t* crosses, const real_t* grad,
                                       const std::uint8_t* active, int num_threads = 0);

}  // namespace dmesh
