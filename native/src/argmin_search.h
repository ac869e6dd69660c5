// Discrete argmin searches behind the face existence probabilities (no gradients; the distances are
// recomputed differentiably in torch from the indices chosen here).
//
// Letters: N points, F faces of the current WDT (power-diagram edges), C candidate faces, M CSR entries.
#pragma once
#include <cstdint>
#include <vector>
#include "power_diagram.h"
#include "types.h"

namespace dmesh {

// For every face (F, 3) and each of its 3 vertices i: the neighbour j of i (from the CSR neighbour lists
// nbr_offsets (N+1,), nbr_indices (M,)), with j not a vertex of the face, whose power bisector plane
// H(i, j) is nearest to the face's sample point samples (F, 3). Returns (F, 3) point ids, kNone where i has
// no admissible neighbour, and in dist (F, 3) that distance (infinity where kNone).
struct NearestPlaneResult {
  std::vector<index_t> neighbour;  // (F, 3)
  std::vector<real_t> dist;        // (F, 3)
};
NearestPlaneResult nearest_planes(const real_t* points, const real_t* weights, index_t N,
                                    const index_t* faces, const real_t* samples, index_t F,
                                    const index_t* nbr_offsets, const index_t* nbr_indices);

struct CellEdgeResult {
  std::vector<index_t> edge;     // (C, 3) id of the nearest power-diagram edge (a WDT face id), or kNone
  std::vector<std::uint8_t> crosses;  // (C, 3) 1 where the dual line passes through the power cell
  std::vector<real_t> dist;       // (C, 3) the line-to-cell distance (0 where crosses, inf without edges)
};

// For every candidate face (C, 3) with dual line (origin (C, 3), unit direction (C, 3)) and each vertex
// i: whether the line crosses i's power cell (then the distance is 0), else the power-diagram edge of i's
// cell nearest to the line. Cell edges of i are the dual edges of the WDT faces containing i
// (point_faces CSR); edge g runs from edge_start[g] to edge_end[g], or is the ray edge_start[g] +
// s * edge_end[g] (s >= 0, edge_end a direction) where is_ray[g]. The crossing test intersects the line
// with the half-spaces of i against its neighbours (nbr CSR). Vertices with no cell edge get kNone.
CellEdgeResult nearest_cell_edges(const real_t* points, const real_t* weights, index_t N,
                                  const index_t* faces, const real_t* line_origin, const real_t* line_dir,
                                  index_t C, const index_t* pf_offsets, const index_t* pf_indices,
                                  const real_t* edge_start, const real_t* edge_end, const std::uint8_t* is_ray,
                                  const index_t* nbr_offsets, const index_t* nbr_indices);

// Row-wise union of two CSR lists over the same rows, each row sorted ascending and unique.
Csr merge_csr(const index_t* off_a, const index_t* idx_a, const index_t* off_b, const index_t* idx_b,
              index_t rows);

}  // namespace dmesh
