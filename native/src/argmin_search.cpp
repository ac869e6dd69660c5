#include "argmin_search.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "parallel.h"

namespace dmesh {
namespace {

inline real_t dot3(const real_t* a, const real_t* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

// Distance from the line (o, u), |u| = 1, to the segment [a, b] (or the ray a + s b, s >= 0): the distance
// of the origin to the segment's projection onto the plane normal to u.
real_t line_segment_distance(const real_t* o, const real_t* u, const real_t* a, const real_t* b, bool ray) {
  real_t pa[3], pb[3], e[3];
  for (int k = 0; k < 3; ++k) pa[k] = a[k] - o[k];
  const real_t sa = dot3(pa, u);
  for (int k = 0; k < 3; ++k) pa[k] -= sa * u[k];
  if (ray) {
    const real_t sb = dot3(b, u);
    for (int k = 0; k < 3; ++k) e[k] = b[k] - sb * u[k];
  } else {
    for (int k = 0; k < 3; ++k) pb[k] = b[k] - o[k];
    const real_t sb = dot3(pb, u);
    for (int k = 0; k < 3; ++k) e[k] = pb[k] - sb * u[k] - pa[k];
  }
  const real_t ee = dot3(e, e);
  real_t t = ee > 0 ? -dot3(pa, e) / ee : 0.0;
  t = std::max(t, 0.0);
  if (!ray) t = std::min(t, 1.0);
  real_t q[3];
  for (int k = 0; k < 3; ++k) q[k] = pa[k] + t * e[k];
  return std::sqrt(dot3(q, q));
}

// Whether the line o + t u meets the power cell of i: pow(x, i) <= pow(x, j) for every neighbour j, each
// a half-line condition g + t h <= 0 on t. The interval must be non-empty by a relative margin.
bool line_crosses_cell(const real_t* P, const real_t* W, index_t i, const real_t* o, const real_t* u,
                       const index_t* nb_begin, const index_t* nb_end) {
  real_t lo = -std::numeric_limits<real_t>::infinity(), hi = std::numeric_limits<real_t>::infinity();
  const real_t* pi = P + 3 * i;
  for (const index_t* it = nb_begin; it != nb_end; ++it) {
    const real_t* pj = P + 3 * *it;
    real_t d[3] = {pj[0] - pi[0], pj[1] - pi[1], pj[2] - pi[2]};
    // 2 x.d <= |pj|^2 - |pi|^2 - (wj - wi), written relative to pi for precision:
    // 2 (x - pi).d <= |d|^2 - (wj - wi).
    real_t rel[3] = {o[0] - pi[0], o[1] - pi[1], o[2] - pi[2]};
    const real_t dd = dot3(d, d);
    const real_t g = 2 * dot3(rel, d) - (dd - (W[*it] - W[i]));
    const real_t h = 2 * dot3(u, d);
    const real_t tol = 1e-12 * (dd + 1.0);
    if (std::abs(h) <= tol) {
      if (g > tol) return false;
      continue;
    }
    const real_t t = -g / h;
    if (h > 0) hi = std::min(hi, t);
    else lo = std::max(lo, t);
    if (lo >= hi) return false;
  }
  return lo < hi;
}

}  // namespace

NearestPlaneResult nearest_planes(const real_t* P, const real_t* W, index_t N, const index_t* faces,
                                  const real_t* samples, index_t F, const index_t* nbr_offsets,
                                  const index_t* nbr_indices) {
  (void)N;
  NearestPlaneResult out;
  out.neighbour.assign(3 * static_cast<std::size_t>(F), kNone);
  out.dist.assign(3 * static_cast<std::size_t>(F), std::numeric_limits<real_t>::infinity());
#pragma omp parallel for schedule(dynamic, 1024) if (F > kParallelMin)
  for (index_t f = 0; f < F; ++f) {
    const index_t* fv = faces + 3 * f;
    const real_t* s = samples + 3 * f;
    for (int v = 0; v < 3; ++v) {
      const index_t i = fv[v];
      const real_t* pi = P + 3 * i;
      real_t best = std::numeric_limits<real_t>::infinity();
      index_t best_j = kNone;
      for (index_t e = nbr_offsets[i]; e < nbr_offsets[i + 1]; ++e) {
        const index_t j = nbr_indices[e];
        if (j == fv[0] || j == fv[1] || j == fv[2]) continue;
        const real_t* pj = P + 3 * j;
        real_t d[3] = {pj[0] - pi[0], pj[1] - pi[1], pj[2] - pi[2]};
        const real_t len2 = dot3(d, d);
        if (!(len2 > 0)) continue;
        const real_t len = std::sqrt(len2);
        const real_t t = 0.5 * (1.0 - (W[j] - W[i]) / len2);
        real_t rel[3] = {s[0] - pi[0], s[1] - pi[1], s[2] - pi[2]};
        const real_t dist = std::abs(dot3(rel, d) / len - t * len);
        if (dist < best) {
          best = dist;
          best_j = j;
        }
      }
      out.neighbour[3 * f + v] = best_j;
      out.dist[3 * f + v] = best;
    }
  }
  return out;
}

CellEdgeResult nearest_cell_edges(const real_t* P, const real_t* W, index_t N, const index_t* faces,
                                  const real_t* line_origin, const real_t* line_dir, index_t C,
                                  const index_t* pf_offsets, const index_t* pf_indices,
                                  const real_t* edge_start, const real_t* edge_end, const std::uint8_t* is_ray,
                                  const index_t* nbr_offsets, const index_t* nbr_indices) {
  (void)N;
  CellEdgeResult r;
  r.edge.assign(3 * static_cast<std::size_t>(C), kNone);
  r.crosses.assign(3 * static_cast<std::size_t>(C), 0);
  r.dist.assign(3 * static_cast<std::size_t>(C), 0.0);
#pragma omp parallel for schedule(dynamic, 1024) if (C > kParallelMin)
  for (index_t c = 0; c < C; ++c) {
    const real_t* o = line_origin + 3 * c;
    const real_t* u = line_dir + 3 * c;
    for (int v = 0; v < 3; ++v) {
      const index_t i = faces[3 * c + v];
      if (line_crosses_cell(P, W, i, o, u, nbr_indices + nbr_offsets[i], nbr_indices + nbr_offsets[i + 1])) {
        r.crosses[3 * c + v] = 1;
        continue;
      }
      real_t best = std::numeric_limits<real_t>::infinity();
      index_t best_g = kNone;
      for (index_t e = pf_offsets[i]; e < pf_offsets[i + 1]; ++e) {
        const index_t g = pf_indices[e];
        const real_t d = line_segment_distance(o, u, edge_start + 3 * g, edge_end + 3 * g, is_ray[g] != 0);
        if (d < best) {
          best = d;
          best_g = g;
        }
      }
      r.edge[3 * c + v] = best_g;
      r.dist[3 * c + v] = best;
    }
  }
  return r;
}

Csr merge_csr(const index_t* off_a, const index_t* idx_a, const index_t* off_b, const index_t* idx_b,
              index_t rows) {
  std::vector<index_t> len(rows);
  std::vector<index_t> tmp(static_cast<std::size_t>(off_a[rows]) + off_b[rows]);
  // Merge each row into tmp at offset off_a[r] + off_b[r], then compact.
  const int nt = threads_for(0, std::size_t(rows), kParallelMin);
  parallel_ranges(rows, 512, nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t r = index_t(lo); r < index_t(hi); ++r) {
      index_t* dst = tmp.data() + off_a[r] + off_b[r];
      index_t* end =
          std::set_union(idx_a + off_a[r], idx_a + off_a[r + 1], idx_b + off_b[r], idx_b + off_b[r + 1], dst);
      len[r] = static_cast<index_t>(end - dst);
    }
  });
  Csr out;
  out.offsets.assign(rows + 1, 0);
  for (index_t r = 0; r < rows; ++r) out.offsets[r + 1] = out.offsets[r] + len[r];
  out.indices.resize(out.offsets[rows]);
  parallel_ranges(rows, 512, nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t r = index_t(lo); r < index_t(hi); ++r) {
      std::copy_n(tmp.data() + off_a[r] + off_b[r], len[r], out.indices.data() + out.offsets[r]);
    }
  });
  return out;
}

}  // namespace dmesh
