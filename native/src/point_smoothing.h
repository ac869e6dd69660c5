// Denoising of point clouds with CGAL's jet smoothing (Point_set_processing_3).
//
// Letters: N points, K neighbours.
#pragma once
#include <vector>
#include "types.h"

namespace dmesh {

// Moves every point of points (N, 3) float64 row-major onto the jet (a local polynomial height field, of
// degree `degree_fitting`, in the frame of its K nearest neighbours' principal axes) fitted to its K
// nearest neighbours, the neighbours taken at the input positions (Cazals and Pouget 2005;
// CGAL::jet_smooth_point_set). Returns the (N, 3) moved points. parallel: 0 sequential, 1 TBB (if compiled
// in; silently sequential otherwise). Throws std::invalid_argument for k < 2, k >= N, degrees outside 1..4
// or non-finite input.
std::vector<real_t> jet_smooth(const real_t* points, index_t n, index_t k, int degree_fitting, int degree_monge,
                               int parallel);

}  // namespace dmesh
