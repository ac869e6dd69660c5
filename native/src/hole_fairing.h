// Smooth patches in a triangle mesh with CGAL's refine and fair (Polygon_mesh_processing), the refine-and-fair
// steps of Liepa's hole filling ("Filling holes in meshes", SGP 2003) applied to given faces.
//
// Letters: V vertices, F faces, P patch faces.
#pragma once
#include <cstdint>
#include <vector>
#include "types.h"

namespace dmesh {

struct FairedMesh {
  std::vector<real_t> vertices;  // (V', 3): the V input vertices (faired ones moved), then the new ones
  std::vector<index_t> faces;    // (F', 3)
  std::vector<std::uint8_t> patch;  // (F',) 1 for faces of the refined patches
  bool faired = false;           // false: the fairing system could not be solved (vertices left as refined)
};

// mesh: vertices (V, 3) float64 and faces (F, 3) int32, a consistently oriented 2-manifold (with or without
// boundary); patch (F,) uint8 marks the faces to replace. The patch faces are refined (CGAL::Polygon_mesh_
// processing::refine: new vertices until the density of the surrounding mesh, `density` its control factor)
// and every vertex with only patch faces around it, new or not, is moved to minimise the fairing energy of
// the given `continuity` (0: membrane, 1: thin plate, 2: minimum curvature variation; CGAL::Polygon_mesh_
// processing::fair) with the others held, and so are the input vertices marked in `hold` (V,) uint8 (nullptr:
// none): only new vertices move around them. Throws std::invalid_argument for bad indices, non-finite
// vertices or a face that does not fit a consistently oriented 2-manifold.
FairedMesh refine_and_fair(const real_t* vertices, index_t n_vertices, const index_t* faces, index_t n_faces,
                           const std::uint8_t* patch, double density, int continuity,
                           const std::uint8_t* hold = nullptr);

}  // namespace dmesh
