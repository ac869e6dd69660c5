// Power diagram (the dual of a weighted Delaunay triangulation) and per-point adjacency.
//
// Letters: N points, T tets, F faces (triangles of the triangulation), E directed edges.
#pragma once
#include <vector>
#include "types.h"

namespace dmesh {

// CSR list: row i is indices[offsets[i] .. offsets[i+1]).
struct Csr {
  std::vector<index_t> offsets;  // (rows + 1,)
  std::vector<index_t> indices;  // (offsets.back(),)
};

struct PowerDiagramResult {
  std::vector<real_t> orthocentres;  // (T, 3) power-diagram vertex of each tet (weighted circumcentre)
  std::vector<index_t> faces;        // (F, 3) sorted vertex ids of each triangulation face
  std::vector<index_t> face_tets;    // (F, 2) the two tets of the face; second is kNone on the hull
  std::vector<real_t> hull_dirs;     // (F, 3) unit outward ray direction for hull faces, zeros otherwise
  std::vector<index_t> tet_faces;    // (T, 4) face opposite vertex k of tet t
  Csr point_tets;                    // per point, its tets (ascending)
  Csr point_faces;                   // per point, its faces (ascending)
  Csr point_neighbors;               // per point, the other ends of its triangulation edges (ascending)
};

// Tet adjacency from the tets alone: (T, 4) tet opposite vertex k, or kNone. O(T log T).
std::vector<index_t> tet_neighbors(const index_t* tets, index_t T);

// Builds the power diagram from points (N, 3), weights (N,), tets (T, 4) and their adjacency (T, 4).
// Throws std::invalid_argument when a tet references a point outside [0, N).
PowerDiagramResult power_diagram(const real_t* points, const real_t* weights, index_t N,
                                 const index_t* tets, const index_t* neighbors, index_t T);

}  // namespace dmesh
