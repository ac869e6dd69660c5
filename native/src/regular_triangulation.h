// Weighted Delaunay (regular) triangulation of weighted points in 3D with CGAL.
//
// Letters: N input points, T finite tetrahedra.
#pragma once
#include <vector>
#include "types.h"

namespace dmesh {

struct RegularTriangulationResult {
  std::vector<index_t> tets;       // (T, 4) input indices of each finite tet, CGAL's (positive) orientation,
                                   // in canonical order (smallest id first; rows ascending), whatever the
                                   // insertion's thread schedule
  std::vector<index_t> neighbors;  // (T, 4) tet opposite vertex k of tet t, or kNone if that side is the hull
  std::vector<index_t> duplicate_of;  // (N,) index of the first exact duplicate kept, or kNone if unique
  index_t num_vertices = 0;        // points that own a power cell (appear in a tet)
  int dimension = -1;              // CGAL's dimension of the triangulation (3 when tets exist)
  double insert_seconds = 0.0;     // time of the CGAL range insertion alone
  double total_seconds = 0.0;      // time of the whole call (dedup, insertion, extraction)
  bool parallel = false;           // whether TBB-parallel insertion was used
};

// Triangulates points (N, 3) float64 row-major with weights (N,) float64 (power distance |x-p|^2 - w).
// Exact duplicate positions are merged first: the first index survives, later copies are hidden
// (reported in duplicate_of). Hidden points appear in no tet. parallel: 0 sequential, 1 TBB (if compiled
// in; silently sequential otherwise), -1 automatic (TBB above kParallelThreshold points).
// Throws std::invalid_argument for fewer than 4 affinely independent points or non-finite input.
RegularTriangulationResult regular_triangulation(const real_t* points, const real_t* weights, index_t n,
                                                 int parallel);

constexpr index_t kParallelThreshold = 20000;
bool have_tbb();

}  // namespace dmesh
