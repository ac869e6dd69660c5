#include <nanobind/nanobind.h>

#include <stdexcept>
#include <string>

#include "numpy_out.h"
#include "power_diagram.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

namespace {

template <class T>
void check_rows(const char* fn, const char* name, const In<T>& a, size_t cols) {
  if (a.ndim() != 2 || a.shape(1) != cols) {
    throw std::invalid_argument(std::string(fn) + ": " + name + " must have shape (rows, " +
                                std::to_string(cols) + ")");
  }
}

nb::tuple csr_tuple(Csr&& c) {
  const size_t rows = c.offsets.size(), nnz = c.indices.size();
  return nb::make_tuple(to_numpy(std::move(c.offsets), {rows}), to_numpy(std::move(c.indices), {nnz}));
}

}  // namespace

void bind_power_diagram(nb::module_& m) {
  m.def(
      "tet_neighbors",
      [](In<index_t> tets) {
        check_rows("tet_neighbors", "tets", tets, 4);
        const auto T = static_cast<index_t>(tets.shape(0));
        std::vector<index_t> nbrs;
        {
          nb::gil_scoped_release release;
          nbrs = tet_neighbors(tets.data(), T);
        }
        return to_numpy(std::move(nbrs), {size_t(T), 4});
      },
      nb::arg("tets").noconvert(),
      "tet_neighbors(tets: (T,4) int32) -> (T,4) int32: tet opposite vertex k, or -1 on the hull.");

  m.def(
      "power_diagram",
      [](In<double> points, In<double> weights, In<index_t> tets, In<index_t> neighbors) {
        check_rows("power_diagram", "points", points, 3);
        check_rows("power_diagram", "tets", tets, 4);
        check_rows("power_diagram", "neighbors", neighbors, 4);
        if (weights.ndim() != 1 || weights.shape(0) != points.shape(0)) {
          throw std::invalid_argument("power_diagram: weights must have shape (N,) matching points");
        }
        if (neighbors.shape(0) != tets.shape(0)) {
          throw std::invalid_argument("power_diagram: neighbors must have the same rows as tets");
        }
        const auto N = static_cast<index_t>(points.shape(0));
        const auto T = static_cast<index_t>(tets.shape(0));
        PowerDiagramResult r;
        {
          nb::gil_scoped_release release;
          r = power_diagram(points.data(), weights.data(), N, tets.data(), neighbors.data(), T);
        }
        const size_t F = r.faces.size() / 3;
        return nb::make_tuple(to_numpy(std::move(r.orthocentres), {size_t(T), 3}),
                              to_numpy(std::move(r.faces), {F, 3}), to_numpy(std::move(r.face_tets), {F, 2}),
                              to_numpy(std::move(r.hull_dirs), {F, 3}),
                              to_numpy(std::move(r.tet_faces), {size_t(T), 4}),
                              csr_tuple(std::move(r.point_tets)), csr_tuple(std::move(r.point_faces)),
                              csr_tuple(std::move(r.point_neighbors)));
      },
      nb::arg("points").noconvert(), nb::arg("weights").noconvert(), nb::arg("tets").noconvert(),
      nb::arg("neighbors").noconvert(),
      "power_diagram(points (N,3) f64, weights (N,) f64, tets (T,4) i32, neighbors (T,4) i32)\n"
      "-> (orthocentres (T,3) f64, faces (F,3) i32 sorted, face_tets (F,2) i32 (-1 = hull ray),\n"
      "    hull_dirs (F,3) f64 unit outward (0 for interior faces), tet_faces (T,4) i32,\n"
      "    (point_tets offsets, indices), (point_faces offsets, indices), (point_neighbors offsets, indices))");
}
