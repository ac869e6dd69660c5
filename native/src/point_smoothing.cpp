#include "point_smoothing.h"

#include <CGAL/Simple_cartesian.h>
#include <CGAL/jet_smooth_point_set.h>

#include <cmath>
#include <stdexcept>
#include <string>

namespace dmesh {

namespace {
using Kernel = CGAL::Simple_cartesian<double>;
using Point = Kernel::Point_3;
}  // namespace

std::vector<real_t> jet_smooth(const real_t* points, index_t n, index_t k, int degree_fitting, int degree_monge,
                               int parallel) {
  if (k < 2 || k >= n) {
    throw std::invalid_argument("jet_smooth: k must be in [2, N - 1] = [2, " + std::to_string(n - 1) + "], got " +
                                std::to_string(k));
  }
  if (degree_fitting < 1 || degree_fitting > 4 || degree_monge < 1 || degree_monge > degree_fitting) {
    throw std::invalid_argument("jet_smooth: degrees must satisfy 1 <= degree_monge <= degree_fitting <= 4");
  }
  // A jet of degree d has (d + 1)(d + 2) / 2 coefficients; fewer neighbours leave it underdetermined.
  if (k < (degree_fitting + 1) * (degree_fitting + 2) / 2) {
    throw std::invalid_argument("jet_smooth: k = " + std::to_string(k) + " is too few neighbours for a jet of degree " +
                                std::to_string(degree_fitting));
  }
  std::vector<Point> pts;
  pts.reserve(size_t(n));
  for (index_t i = 0; i < n; ++i) {
    const real_t* p = points + 3 * size_t(i);
    if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
      throw std::invalid_argument("jet_smooth: point " + std::to_string(i) + " is not finite");
    }
    pts.emplace_back(p[0], p[1], p[2]);
  }
  const auto np = CGAL::parameters::degree_fitting(unsigned(degree_fitting)).degree_monge(unsigned(degree_monge));
#ifdef DMESH_HAVE_TBB
  if (parallel == 1) {
    CGAL::jet_smooth_point_set<CGAL::Parallel_tag>(pts, unsigned(k), np);
  } else {
    CGAL::jet_smooth_point_set<CGAL::Sequential_tag>(pts, unsigned(k), np);
  }
#else
  (void)parallel;
  CGAL::jet_smooth_point_set<CGAL::Sequential_tag>(pts, unsigned(k), np);
#endif
  std::vector<real_t> out(3 * size_t(n));
  for (index_t i = 0; i < n; ++i) {
    out[3 * size_t(i)] = pts[size_t(i)].x();
    out[3 * size_t(i) + 1] = pts[size_t(i)].y();
    out[3 * size_t(i) + 2] = pts[size_t(i)].z();
  }
  return out;
}

}  // namespace dmesh
