#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>

#include <stdexcept>
#include <string>

#include "numpy_out.h"
#include "regular_triangulation.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

namespace {

void check_points(const In<double>& points, const In<double>& weights) {
  if (points.ndim() != 2 || points.shape(1) != 3) {
    throw std::invalid_argument("regular_triangulation: points must have shape (N, 3)");
  }
  if (weights.ndim() != 1 || weights.shape(0) != points.shape(0)) {
    throw std::invalid_argument("regular_triangulation: weights must have shape (N,) with N = " +
                                std::to_string(points.shape(0)) + ", got " +
                                std::to_string(weights.ndim() == 1 ? weights.shape(0) : -1));
  }
}

}  // namespace

void bind_wdt(nb::module_& m) {
  m.def(
      "regular_triangulation",
      [](In<double> points, In<double> weights, int parallel) {
        check_points(points, weights);
        const auto n = static_cast<index_t>(points.shape(0));
        RegularTriangulationResult r;
        {
          nb::gil_scoped_release release;
          r = regular_triangulation(points.data(), weights.data(), n, parallel);
        }
        const size_t T = r.tets.size() / 4;
        nb::dict stats;
        stats["insert_seconds"] = r.insert_seconds;
        stats["total_seconds"] = r.total_seconds;
        stats["num_vertices"] = r.num_vertices;
        stats["parallel"] = r.parallel;
        return nb::make_tuple(to_numpy(std::move(r.tets), {T, 4}), to_numpy(std::move(r.neighbors), {T, 4}),
                              to_numpy(std::move(r.duplicate_of), {size_t(n)}), stats);
      },
      nb::arg("points").noconvert(), nb::arg("weights").noconvert(), nb::arg("parallel") = -1,
      "regular_triangulation(points: (N,3) float64, weights: (N,) float64, parallel: int = -1)\n"
      "-> (tets (T,4) int32, neighbors (T,4) int32, duplicate_of (N,) int32, stats dict)\n\n"
      "CGAL Regular_triangulation_3 (exact predicates); power distance |x-p|^2 - w. parallel: 0 sequential,\n"
      "1 TBB, -1 automatic. neighbors[t,k] is the tet opposite vertex k, -1 on the hull. duplicate_of[i]\n"
      "is the first index with the same position (i is then hidden), else -1.");
  m.def("have_tbb", &have_tbb, "Whether TBB-parallel insertion was compiled in.");
  m.attr("PARALLEL_THRESHOLD") = kParallelThreshold;
}
