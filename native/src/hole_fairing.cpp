#include "hole_fairing.h"

#include <CGAL/Polygon_mesh_processing/fair.h>
#include <CGAL/Polygon_mesh_processing/refine.h>
#include <CGAL/Simple_cartesian.h>
#include <CGAL/Surface_mesh.h>

#include <cmath>
#include <iterator>
#include <stdexcept>
#include <string>

namespace dmesh {

namespace {
using Kernel = CGAL::Simple_cartesian<double>;
using Point = Kernel::Point_3;
using Mesh = CGAL::Surface_mesh<Point>;
using VertexIndex = Mesh::Vertex_index;
using FaceIndex = Mesh::Face_index;
namespace PMP = CGAL::Polygon_mesh_processing;
}  // namespace

FairedMesh refine_and_fair(const real_t* vertices, index_t n_vertices, const index_t* faces, index_t n_faces,
                           const std::uint8_t* patch, double density, int continuity, const std::uint8_t* hold) {
  if (continuity < 0 || continuity > 2) {
    throw std::invalid_argument("refine_and_fair: continuity must be 0, 1 or 2, got " + std::to_string(continuity));
  }
  if (!(density > 0.0) || !std::isfinite(density)) {
    throw std::invalid_argument("refine_and_fair: density must be a positive number");
  }
  Mesh mesh;
  for (index_t i = 0; i < n_vertices; ++i) {
    const real_t* p = vertices + 3 * size_t(i);
    if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
      throw std::invalid_argument("refine_and_fair: vertex " + std::to_string(i) + " is not finite");
    }
    mesh.add_vertex(Point(p[0], p[1], p[2]));
  }
  auto in_patch = mesh.add_property_map<FaceIndex, bool>("f:patch", false).first;
  std::vector<FaceIndex> patch_faces;
  for (index_t f = 0; f < n_faces; ++f) {
    const index_t* t = faces + 3 * size_t(f);
    for (int k = 0; k < 3; ++k) {
      if (t[k] < 0 || t[k] >= n_vertices) {
        throw std::invalid_argument("refine_and_fair: face " + std::to_string(f) + " has a vertex out of range");
      }
    }
    const FaceIndex added = mesh.add_face(VertexIndex(t[0]), VertexIndex(t[1]), VertexIndex(t[2]));
    if (added == Mesh::null_face()) {
      throw std::invalid_argument("refine_and_fair: face " + std::to_string(f) +
                                  " does not fit a consistently oriented 2-manifold");
    }
    if (patch[f]) {
      in_patch[added] = true;
      patch_faces.push_back(added);
    }
  }
  // Vertices with only patch faces around them (and not on a border or held) move with the new ones.
  std::vector<VertexIndex> movable;
  for (VertexIndex v : mesh.vertices()) {
    if (mesh.is_isolated(v) || mesh.is_border(v, false) || (hold != nullptr && hold[std::size_t(v)])) continue;
    bool all = true;
    for (FaceIndex f : CGAL::faces_around_target(mesh.halfedge(v), mesh)) {
      if (f == Mesh::null_face() || !in_patch[f]) {
        all = false;
        break;
      }
    }
    if (all) movable.push_back(v);
  }
  std::vector<FaceIndex> new_faces;
  std::vector<VertexIndex> new_vertices;
  if (!patch_faces.empty()) {
    PMP::refine(mesh, patch_faces, std::back_inserter(new_faces), std::back_inserter(new_vertices),
                CGAL::parameters::density_control_factor(density));
  }
  for (FaceIndex f : new_faces) in_patch[f] = true;
  movable.insert(movable.end(), new_vertices.begin(), new_vertices.end());
  FairedMesh out;
  out.faired = movable.empty() ||
               PMP::fair(mesh, movable, CGAL::parameters::fairing_continuity(unsigned(continuity)));
  // No element was removed, so the indices are 0..n-1 in order, the input's first.
  out.vertices.reserve(3 * mesh.number_of_vertices());
  for (VertexIndex v : mesh.vertices()) {
    const Point& p = mesh.point(v);
    out.vertices.insert(out.vertices.end(), {p.x(), p.y(), p.z()});
  }
  out.faces.reserve(3 * mesh.number_of_faces());
  out.patch.reserve(mesh.number_of_faces());
  for (FaceIndex f : mesh.faces()) {
    for (VertexIndex v : CGAL::vertices_around_face(mesh.halfedge(f), mesh)) out.faces.push_back(index_t(v));
    out.patch.push_back(in_patch[f] ? 1 : 0);
  }
  return out;
}

}  // namespace dmesh
