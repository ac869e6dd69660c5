#include <nanobind/nanobind.h>

#include "numpy_out.h"
#include "point_smoothing.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

void bind_points(nb::module_& m) {
  m.def(
      "jet_smooth",
      [](In<double> points, int k, int degree_fitting, int degree_monge, int parallel) {
        require("jet_smooth", "points", points, -1, 3);
        const auto n = static_cast<index_t>(points.shape(0));
        std::vector<real_t> out;
        {
          nb::gil_scoped_release release;
          out = jet_smooth(points.data(), n, index_t(k), degree_fitting, degree_monge, parallel);
        }
        return to_numpy(std::move(out), {size_t(n), 3});
      },
      nb::arg("points").noconvert(), nb::arg("k"), nb::arg("degree_fitting") = 2, nb::arg("degree_monge") = 2,
      nb::arg("parallel") = 0,
      "jet_smooth(points: (N,3) float64, k: int, degree_fitting: int = 2, degree_monge: int = 2, parallel: int = 0)\n"
      "-> (N,3) float64\n\n"
      "CGAL::jet_smooth_point_set: each point moved onto the jet fitted to its k nearest neighbours.\n"
      "parallel: 0 sequential, 1 TBB (when compiled in).");
}
