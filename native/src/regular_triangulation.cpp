#include "regular_triangulation.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Regular_triangulation_3.h>
#include <CGAL/Triangulation_cell_base_with_info_3.h>
#include <CGAL/Triangulation_vertex_base_with_info_3.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <stdexcept>
#include <string>

#include "parallel.h"

namespace dmesh {
namespace {

using K = CGAL::Exact_predicates_inexact_constructions_kernel;
using Vb0 = CGAL::Regular_triangulation_vertex_base_3<K>;
using Vb = CGAL::Triangulation_vertex_base_with_info_3<index_t, K, Vb0>;
using Cb0 = CGAL::Regular_triangulation_cell_base_3<K, CGAL::Triangulation_cell_base_3<K>,
                                                    CGAL::Discard_hidden_points>;
using Cb = CGAL::Triangulation_cell_base_with_info_3<index_t, K, Cb0>;  // info = dense cell id
using TdsSeq = CGAL::Triangulation_data_structure_3<Vb, Cb, CGAL::Sequential_tag>;
using RtSeq = CGAL::Regular_triangulation_3<K, TdsSeq>;
#ifdef DMESH_HAVE_TBB
using TdsPar = CGAL::Triangulation_data_structure_3<Vb, Cb, CGAL::Parallel_tag>;
using RtPar = CGAL::Regular_triangulation_3<K, TdsPar>;
#endif
using WPoint = K::Weighted_point_3;
using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// Marks exact duplicate positions: duplicate_of[i] = first index with the same coordinates, or kNone.
std::vector<index_t> find_duplicates(const real_t* p, index_t n) {
  std::vector<index_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  auto less = [p](index_t a, index_t b) {
    for (int k = 0; k < 3; ++k) {
      if (p[3 * a + k] != p[3 * b + k]) return p[3 * a + k] < p[3 * b + k];
    }
    return a < b;  // equal positions: lower index first, so it is the one kept
  };
  std::sort(order.begin(), order.end(), less);
  std::vector<index_t> dup(n, kNone);
  for (index_t r = 1; r < n; ++r) {
    const index_t a = order[r - 1], b = order[r];
    if (p[3 * a] == p[3 * b] && p[3 * a + 1] == p[3 * b + 1] && p[3 * a + 2] == p[3 * b + 2]) {
      dup[b] = dup[a] == kNone ? a : dup[a];
    }
  }
  return dup;
}

template <class Rt>
void extract(Rt& rt, RegularTriangulationResult& out) {
  out.dimension = rt.dimension();
  if (rt.dimension() < 3) return;
  const std::size_t T = rt.number_of_finite_cells();
  out.tets.resize(4 * T);
  out.neighbors.resize(4 * T);
  // Dense ids for finite cells in the cell's info field; infinite cells keep kNone.
  for (auto c = rt.all_cells_begin(); c != rt.all_cells_end(); ++c) c->info() = kNone;
  index_t t = 0;
  for (auto c = rt.finite_cells_begin(); c != rt.finite_cells_end(); ++c) c->info() = t++;
  t = 0;
  for (auto c = rt.finite_cells_begin(); c != rt.finite_cells_end(); ++c, ++t) {
    for (int k = 0; k < 4; ++k) {
      out.tets[4 * t + k] = c->vertex(k)->info();
      out.neighbors[4 * t + k] = c->neighbor(k)->info();
    }
  }
  out.num_vertices = static_cast<index_t>(rt.number_of_vertices());
}

// Puts the tets in a canonical order, so the output depends only on the triangulation and not on how it
// was built: TBB's parallel insertion hands out cells (and each cell's vertex order) in an order that
// depends on the thread schedule, and everything downstream (faces, candidates, sampling) inherits it.
// Within a tet: the even permutation (orientation kept) that puts the smallest id first and the smallest
// of the other three second. Across tets: ascending (v0, v1, v2, v3). Neighbours follow their vertices.
void canonicalise(RegularTriangulationResult& out) {
  const std::size_t T = out.tets.size() / 4;
  // Even permutations taking position m to the front: identity or a double transposition.
  static const int kFront[4][4] = {{0, 1, 2, 3}, {1, 0, 3, 2}, {2, 3, 0, 1}, {3, 2, 1, 0}};
  std::vector<index_t> tets(4 * T), nbrs(4 * T);
  // The loops below write disjoint entries only, so their result does not depend on the thread count.
  const int nt = threads_for(0, T, kParallelMin);
  const std::int64_t grain = grain_for(std::int64_t(T), nt, 1024);
  parallel_ranges(std::int64_t(T), grain, nt, [&](std::int64_t lo, std::int64_t hi) {
    for (std::size_t t = std::size_t(lo); t < std::size_t(hi); ++t) {
      const index_t* v = &out.tets[4 * t];
      const index_t* nb = &out.neighbors[4 * t];
      const int m = static_cast<int>(std::min_element(v, v + 4) - v);
      int p[4] = {kFront[m][0], kFront[m][1], kFront[m][2], kFront[m][3]};
      // A cyclic rotation of the last three (even) puts their smallest id second.
      int r = 1;
      if (v[p[2]] < v[p[r]]) r = 2;
      if (v[p[3]] < v[p[r]]) r = 3;
      const int q[4] = {p[0], p[1 + (r - 1) % 3], p[1 + r % 3], p[1 + (r + 1) % 3]};
      for (int k = 0; k < 4; ++k) {
        tets[4 * t + k] = v[q[k]];
        nbrs[4 * t + k] = nb[q[k]];
      }
    }
  });
  // Rows ascending: a counting sort on v0 (the smallest id: few tets share one), then a small sort of each
  // bucket on (v1, v2, v3); about 3x faster than one comparison sort of all rows.
  struct Row {
    index_t v[4];
    index_t old;
  };
  index_t n = 0;
  for (std::size_t t = 0; t < T; ++t) n = std::max(n, tets[4 * t] + 1);
  std::vector<index_t> start(static_cast<std::size_t>(n) + 1, 0);
  for (std::size_t t = 0; t < T; ++t) ++start[tets[4 * t] + 1];
  for (index_t i = 0; i < n; ++i) start[i + 1] += start[i];
  std::vector<Row> rows(T);
  {
    std::vector<index_t> fill(start.begin(), start.end() - 1);
    for (std::size_t t = 0; t < T; ++t) {
      const index_t* v = &tets[4 * t];
      rows[fill[v[0]]++] = {{v[0], v[1], v[2], v[3]}, static_cast<index_t>(t)};
    }
  }
  parallel_ranges(n, 4096, nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t i = index_t(lo); i < index_t(hi); ++i) {
      std::sort(rows.begin() + start[i], rows.begin() + start[i + 1], [](const Row& a, const Row& b) {
        return std::lexicographical_compare(a.v + 1, a.v + 4, b.v + 1, b.v + 4);
      });
    }
  });
  std::vector<index_t> new_id(T);
  parallel_ranges(std::int64_t(T), grain, nt, [&](std::int64_t lo, std::int64_t hi) {
    for (std::size_t i = std::size_t(lo); i < std::size_t(hi); ++i) new_id[rows[i].old] = static_cast<index_t>(i);
  });
  parallel_ranges(std::int64_t(T), grain, nt, [&](std::int64_t lo, std::int64_t hi) {
    for (std::size_t i = std::size_t(lo); i < std::size_t(hi); ++i) {
      const index_t t = rows[i].old;
      for (int k = 0; k < 4; ++k) {
        out.tets[4 * i + k] = rows[i].v[k];
        const index_t n = nbrs[4 * t + k];
        out.neighbors[4 * i + k] = n == kNone ? kNone : new_id[n];
      }
    }
  });
}

}  // namespace

bool have_tbb() {
#ifdef DMESH_HAVE_TBB
  return true;
#else
  return false;
#endif
}

RegularTriangulationResult regular_triangulation(const real_t* points, const real_t* weights, index_t n,
                                                 int parallel) {
  const auto t_total = Clock::now();
  for (index_t i = 0; i < n; ++i) {
    if (!std::isfinite(points[3 * i]) || !std::isfinite(points[3 * i + 1]) ||
        !std::isfinite(points[3 * i + 2]) || !std::isfinite(weights[i])) {
      throw std::invalid_argument("regular_triangulation: points and weights must be finite; row " +
                                  std::to_string(i) + " is not");
    }
  }
  RegularTriangulationResult out;
  out.duplicate_of = find_duplicates(points, n);

  std::vector<std::pair<WPoint, index_t>> input;
  input.reserve(n);
  real_t lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (index_t i = 0; i < n; ++i) {
    if (out.duplicate_of[i] != kNone) continue;
    const real_t* p = points + 3 * i;
    for (int k = 0; k < 3; ++k) {
      lo[k] = std::min(lo[k], p[k]);
      hi[k] = std::max(hi[k], p[k]);
    }
    input.emplace_back(WPoint(K::Point_3(p[0], p[1], p[2]), weights[i]), i);
  }
  if (input.size() < 4) {
    throw std::invalid_argument("regular_triangulation: need at least 4 distinct points, got " +
                                std::to_string(input.size()));
  }

  bool use_parallel = have_tbb() && (parallel == 1 || (parallel < 0 && n >= kParallelThreshold));
#ifdef DMESH_HAVE_TBB
  if (use_parallel) {
    typename RtPar::Lock_data_structure lock(CGAL::Bbox_3(lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]), 50);
    RtPar rt(&lock);
    const auto t0 = Clock::now();
    rt.insert(input.begin(), input.end());
    out.insert_seconds = seconds_since(t0);
    extract(rt, out);
  }
#endif
  if (!use_parallel) {
    RtSeq rt;
    const auto t0 = Clock::now();
    rt.insert(input.begin(), input.end());
    out.insert_seconds = seconds_since(t0);
    extract(rt, out);
  }
  out.parallel = use_parallel;
  if (out.dimension == 3) canonicalise(out);
  if (out.dimension < 3) {
    throw std::invalid_argument(
        "regular_triangulation: the points are not affinely independent in 3D (the triangulation has "
        "dimension " + std::to_string(out.dimension) + "); need at least 4 non-coplanar points");
  }
  out.total_seconds = seconds_since(t_total);
  return out;
}

}  // namespace dmesh
