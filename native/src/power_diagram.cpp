#include "power_diagram.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <stdexcept>
#include <string>

#include "parallel.h"

namespace dmesh {
namespace {

// Vertex ids of the face opposite vertex k of a tet, in ascending order.
std::array<index_t, 3> face_opposite(const index_t* tet, int k) {
  std::array<index_t, 3> f;
  int m = 0;
  for (int j = 0; j < 4; ++j) {
    if (j != k) f[m++] = tet[j];
  }
  std::sort(f.begin(), f.end());
  return f;
}

// Counting-sort CSR from (row, value) pairs; rows ascending, values kept in insertion order.
template <class Emit>
Csr build_csr(index_t rows, std::size_t count_hint, Emit emit) {
  Csr csr;
  csr.offsets.assign(rows + 1, 0);
  emit([&](index_t r, index_t) { ++csr.offsets[r + 1]; });
  for (index_t r = 0; r < rows; ++r) csr.offsets[r + 1] += csr.offsets[r];
  csr.indices.resize(csr.offsets[rows]);
  std::vector<index_t> cursor(csr.offsets.begin(), csr.offsets.end() - 1);
  (void)count_hint;
  emit([&](index_t r, index_t v) { csr.indices[cursor[r]++] = v; });
  return csr;
}

void orthocentre(const real_t* P, const real_t* W, const index_t* tet, real_t* out) {
  // Solve 2 (p_j - p_0) . x = |p_j - p_0|^2 - (w_j - w_0), j = 1..3, then c = p_0 + x (relative to p_0
  // for precision), by Cramer's rule.
  const real_t* p0 = P + 3 * tet[0];
  real_t A[3][3], b[3];
  for (int j = 0; j < 3; ++j) {
    const real_t* pj = P + 3 * tet[j + 1];
    real_t d2 = 0;
    for (int k = 0; k < 3; ++k) {
      A[j][k] = 2 * (pj[k] - p0[k]);
      d2 += (pj[k] - p0[k]) * (pj[k] - p0[k]);
    }
    b[j] = d2 - (W[tet[j + 1]] - W[tet[0]]);
  }
  const real_t c00 = A[1][1] * A[2][2] - A[1][2] * A[2][1];
  const real_t c01 = A[1][2] * A[2][0] - A[1][0] * A[2][2];
  const real_t c02 = A[1][0] * A[2][1] - A[1][1] * A[2][0];
  const real_t det = A[0][0] * c00 + A[0][1] * c01 + A[0][2] * c02;
  // x = A^-1 b via the adjugate.
  const real_t inv = 1.0 / det;
  const real_t x0 = (b[0] * c00 + b[1] * (A[0][2] * A[2][1] - A[0][1] * A[2][2]) +
                     b[2] * (A[0][1] * A[1][2] - A[0][2] * A[1][1])) * inv;
  const real_t x1 = (b[0] * c01 + b[1] * (A[0][0] * A[2][2] - A[0][2] * A[2][0]) +
                     b[2] * (A[0][2] * A[1][0] - A[0][0] * A[1][2])) * inv;
  const real_t x2 = (b[0] * c02 + b[1] * (A[0][1] * A[2][0] - A[0][0] * A[2][1]) +
                     b[2] * (A[0][0] * A[1][1] - A[0][1] * A[1][0])) * inv;
  out[0] = p0[0] + x0;
  out[1] = p0[1] + x1;
  out[2] = p0[2] + x2;
}

}  // namespace

std::vector<index_t> tet_neighbors(const index_t* tets, index_t T) {
  struct Key {
    std::array<index_t, 3> f;
    index_t tet;
    int k;
  };
  std::vector<Key> keys;
  keys.reserve(4 * static_cast<std::size_t>(T));
  for (index_t t = 0; t < T; ++t) {
    for (int k = 0; k < 4; ++k) keys.push_back({face_opposite(tets + 4 * t, k), t, k});
  }
  std::sort(keys.begin(), keys.end(), [](const Key& a, const Key& b) { return a.f < b.f; });
  std::vector<index_t> nb(4 * static_cast<std::size_t>(T), kNone);
  for (std::size_t i = 0; i + 1 < keys.size(); ++i) {
    if (keys[i].f == keys[i + 1].f) {
      nb[4 * keys[i].tet + keys[i].k] = keys[i + 1].tet;
      nb[4 * keys[i + 1].tet + keys[i + 1].k] = keys[i].tet;
      ++i;
    }
  }
  return nb;
}

PowerDiagramResult power_diagram(const real_t* P, const real_t* W, index_t N, const index_t* tets,
                                 const index_t* neighbors, index_t T) {
  for (std::size_t i = 0; i < 4 * static_cast<std::size_t>(T); ++i) {
    if (tets[i] < 0 || tets[i] >= N) {
      throw std::invalid_argument("power_diagram: tets must index points in [0, " + std::to_string(N) +
                                  "); found " + std::to_string(tets[i]));
    }
  }
  PowerDiagramResult out;
  out.orthocentres.resize(3 * static_cast<std::size_t>(T));
  const int nt_t = threads_for(0, std::size_t(T), kParallelMin);
  parallel_ranges(T, grain_for(T, nt_t, 1024), nt_t, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t t = index_t(lo); t < index_t(hi); ++t) {
      orthocentre(P, W, tets + 4 * t, out.orthocentres.data() + 3 * t);
    }
  });

  // Faces: each interior face once (from its lower-id tet), each hull face from its only tet.
  out.tet_faces.assign(4 * static_cast<std::size_t>(T), kNone);
  std::size_t F = 0;
  for (index_t t = 0; t < T; ++t) {
    for (int k = 0; k < 4; ++k) {
      const index_t n = neighbors[4 * t + k];
      if (n == kNone || t < n) ++F;
    }
  }
  out.faces.resize(3 * F);
  out.face_tets.resize(2 * F);
  out.hull_dirs.assign(3 * F, 0.0);
  index_t f = 0;
  for (index_t t = 0; t < T; ++t) {
    const index_t* tet = tets + 4 * t;
    for (int k = 0; k < 4; ++k) {
      const index_t n = neighbors[4 * t + k];
      if (n != kNone && n < t) {
        // Already emitted by n: find the side of n that faces t.
        for (int j = 0; j < 4; ++j) {
          if (neighbors[4 * n + j] == t) {
            out.tet_faces[4 * t + k] = out.tet_faces[4 * n + j];
            break;
          }
        }
        continue;
      }
      const auto fv = face_opposite(tet, k);
      for (int j = 0; j < 3; ++j) out.faces[3 * f + j] = fv[j];
      out.face_tets[2 * f] = t;
      out.face_tets[2 * f + 1] = n;
      out.tet_faces[4 * t + k] = f;
      if (n == kNone) {
        // Outward normal of the hull face: away from the tet's fourth vertex.
        const real_t *a = P + 3 * fv[0], *b = P + 3 * fv[1], *c = P + 3 * fv[2], *d = P + 3 * tet[k];
        real_t u[3], v[3], nrm[3];
        for (int j = 0; j < 3; ++j) {
          u[j] = b[j] - a[j];
          v[j] = c[j] - a[j];
        }
        nrm[0] = u[1] * v[2] - u[2] * v[1];
        nrm[1] = u[2] * v[0] - u[0] * v[2];
        nrm[2] = u[0] * v[1] - u[1] * v[0];
        const real_t side = nrm[0] * (d[0] - a[0]) + nrm[1] * (d[1] - a[1]) + nrm[2] * (d[2] - a[2]);
        const real_t len = std::sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]);
        const real_t s = (side > 0 ? -1.0 : 1.0) / (len > 0 ? len : 1.0);
        for (int j = 0; j < 3; ++j) out.hull_dirs[3 * f + j] = s * nrm[j];
      }
      ++f;
    }
  }

  out.point_tets = build_csr(N, 4 * static_cast<std::size_t>(T), [&](auto put) {
    for (index_t t = 0; t < T; ++t)
      for (int k = 0; k < 4; ++k) put(tets[4 * t + k], t);
  });
  out.point_faces = build_csr(N, 3 * F, [&](auto put) {
    for (index_t g = 0; g < static_cast<index_t>(F); ++g)
      for (int k = 0; k < 3; ++k) put(out.faces[3 * g + k], g);
  });
  // Neighbours: the other vertices of each point's tets, sorted and made unique per row.
  Csr raw = build_csr(N, 12 * static_cast<std::size_t>(T), [&](auto put) {
    for (index_t t = 0; t < T; ++t)
      for (int k = 0; k < 4; ++k)
        for (int j = 0; j < 4; ++j)
          if (j != k) put(tets[4 * t + k], tets[4 * t + j]);
  });
  // A row lists each neighbour once per tet the two points share (about 5 times): drop the repeats first
  // with a per-thread mark (kept across calls, cleared after each row), then sort the unique ids: several
  // times cheaper than sorting the whole row.
  std::vector<index_t> row_len(N, 0);
  parallel_ranges(N, 256, threads_for(0, std::size_t(N), kParallelMin), [&](std::int64_t lo, std::int64_t hi) {
    static thread_local std::vector<index_t> mark;
    if (mark.size() < static_cast<std::size_t>(N)) mark.assign(N, kNone);
    for (index_t i = index_t(lo); i < index_t(hi); ++i) {
      index_t* row = raw.indices.data() + raw.offsets[i];
      const index_t len = raw.offsets[i + 1] - raw.offsets[i];
      index_t m = 0;
      for (index_t k = 0; k < len; ++k) {
        const index_t j = row[k];
        if (mark[j] != i) {
          mark[j] = i;
          row[m++] = j;
        }
      }
      std::sort(row, row + m);
      for (index_t k = 0; k < m; ++k) mark[row[k]] = kNone;
      row_len[i] = m;
    }
  });
  Csr& nb = out.point_neighbors;
  nb.offsets.assign(N + 1, 0);
  for (index_t i = 0; i < N; ++i) nb.offsets[i + 1] = nb.offsets[i] + row_len[i];
  nb.indices.resize(nb.offsets[N]);
  for (index_t i = 0; i < N; ++i) {
    std::copy_n(raw.indices.begin() + raw.offsets[i], row_len[i], nb.indices.begin() + nb.offsets[i]);
  }
  return out;
}

}  // namespace dmesh
