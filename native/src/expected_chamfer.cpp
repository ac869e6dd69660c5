#include "expected_chamfer.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace dmesh {
namespace {

int thread_id() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

int team_size() {
#ifdef _OPENMP
  return omp_get_num_threads();
#else
  return 1;
#endif
}

// Threads for G rows of K candidates: one below kParallelMin candidates (start-up costs more than the work).
int thread_count(int requested, std::int64_t work) {
  if (work < kParallelMin) return 1;
#ifdef _OPENMP
  return requested > 0 ? std::min(requested, 256) : std::max(1, omp_get_max_threads());
#else
  (void)requested;
  return 1;
#endif
}

void check_sizes(const char* fn, index_t G, index_t S, index_t K) {
  if (G < 0 || S < 0 || K < 0) {
    throw std::invalid_argument(std::string(fn) + ": negative size (G " + std::to_string(G) + ", S " +
                                std::to_string(S) + ", K " + std::to_string(K) + ")");
  }
}

// Face ids usable as indices of a small stamp array: the input itself when its largest id is small
// compared with S, else ranks among the sorted distinct ids (the same masks either way). A stamp array
// (one int per face, per thread) measured faster than a small per-row hash set of faces (forward 0.044 s
// against 0.075 s at G = S = 100K, K = 95, one thread): it costs one load and one store per candidate.
struct FaceIds {
  const index_t* input = nullptr;
  std::vector<index_t> ranks;
  index_t count = 0;  // ids lie in [0, count)
  const index_t* ids() const { return ranks.empty() ? input : ranks.data(); }
};

FaceIds dense_face_ids(const char* fn, const index_t* face, index_t S) {
  FaceIds r;
  r.input = face;
  index_t largest = -1;
  for (index_t s = 0; s < S; ++s) {
    if (face[s] < 0) {
      throw std::invalid_argument(std::string(fn) + ": face[" + std::to_string(s) + "] is " +
                                  std::to_string(face[s]) + ", face ids must be >= 0");
    }
    largest = std::max(largest, face[s]);
  }
  if (std::int64_t(largest) < std::max<std::int64_t>(4 * std::int64_t(S), 1 << 16)) {
    r.count = largest + 1;
    return r;
  }
  std::vector<index_t> sorted(face, face + S);
  std::sort(sorted.begin(), sorted.end());
  sorted.erase(std::unique(sorted.begin(), sorted.end()), sorted.end());
  r.ranks.resize(size_t(S));
  for (index_t s = 0; s < S; ++s) {
    r.ranks[size_t(s)] = index_t(std::lower_bound(sorted.begin(), sorted.end(), face[s]) - sorted.begin());
  }
  r.count = index_t(sorted.size());
  return r;
}

template <class A, class B>
inline double distance(const A* a, const B* b) {
  const double dx = double(a[0]) - double(b[0]), dy = double(a[1]) - double(b[1]),
               dz = double(a[2]) - double(b[2]);
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

// The candidates of one target row in the order the row is taken, with their tangent-weighted distances
// (header), when the settings carry target normals; without them the kernels keep their inline Euclidean
// loop (no extra pass over the row).
struct RowDistances {
  const double* normals;  // null: Euclidean, in knn order
  double w2;              // tangent_weight^2
  std::vector<index_t> order;
  std::vector<double> dist, along, dist_in, along_in;  // *_in: in knn order, before the sort
  std::vector<std::pair<double, index_t>> key;

  RowDistances(const ExpectedChamferSettings& settings, index_t K)
      : normals(settings.target_normals),
        w2(settings.tangent_weight * settings.tangent_weight),
        order(static_cast<size_t>(K)),
        dist(static_cast<size_t>(K)),
        along(static_cast<size_t>(K)),
        dist_in(static_cast<size_t>(K)),
        along_in(static_cast<size_t>(K)),
        key(static_cast<size_t>(K)) {
    for (index_t i = 0; i < K; ++i) order[size_t(i)] = i;  // the knn order, kept without normals
  }

  // Fills order / dist / along (by position in the row's order) for row g; false on a bad sample id.
  template <class T, class P>
  bool compute(index_t g, const T* t, const index_t* row, index_t K, index_t S, const P* points, size_t stride) {
    const double* n = normals ? normals + 3 * size_t(g) : nullptr;
    for (index_t i = 0; i < K; ++i) {
      const index_t s = row[i];
      if (s < 0 || s >= S) return false;
      const P* x = points + stride * size_t(s);
      const double o[3] = {double(x[0]) - double(t[0]), double(x[1]) - double(t[1]), double(x[2]) - double(t[2])};
      const double oo = o[0] * o[0] + o[1] * o[1] + o[2] * o[2];
      if (n == nullptr) {
        dist[size_t(i)] = std::sqrt(oo);
      } else {
        const double a = o[0] * n[0] + o[1] * n[1] + o[2] * n[2];
        dist_in[size_t(i)] = std::sqrt(std::max(a * a + w2 * std::max(oo - a * a, 0.0), 0.0));
        along_in[size_t(i)] = a;
        key[size_t(i)] = {dist_in[size_t(i)], i};
      }
    }
    if (n != nullptr) {  // take the row in increasing weighted distance, ties in knn order
      std::sort(key.begin(), key.begin() + K);
      for (index_t i = 0; i < K; ++i) {
        const index_t j = key[size_t(i)].second;
        order[size_t(i)] = j;
        dist[size_t(i)] = dist_in[size_t(j)];
        along[size_t(i)] = along_in[size_t(j)];
      }
    }
    return true;
  }
};

// The candidates of a row: its entries up to the first kNone (shorter rows), or all K.
inline index_t row_length(const index_t* row, index_t K) {
  index_t L = 0;
  while (L < K && row[L] != kNone) ++L;
  return L;
}

[[noreturn]] void bad_knn(const char* fn, index_t S) {
  throw std::invalid_argument(std::string(fn) + ": knn holds a sample id outside [0, " + std::to_string(S) +
                              ")");
}

// Rank of every sample along a Morton (Z-order) curve of its position: contiguous rank ranges are compact
// regions of space, so a target row's candidates mostly fall in one range. Ties go to the smaller id.
template <class T>
std::vector<index_t> spatial_ranks(const T* points, index_t S) {
  double lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};
  for (index_t s = 0; s < S; ++s) {
    for (int k = 0; k < 3; ++k) {
      const double v = double(points[3 * size_t(s) + k]);
      if (s == 0 || v < lo[k]) lo[k] = v;
      if (s == 0 || v > hi[k]) hi[k] = v;
    }
  }
  auto spread = [](std::uint64_t v) {  // 21 bits to every third bit
    v &= 0x1fffff;
    v = (v | v << 32) & 0x1f00000000ffffULL;
    v = (v | v << 16) & 0x1f0000ff0000ffULL;
    v = (v | v << 8) & 0x100f00f00f00f00fULL;
    v = (v | v << 4) & 0x10c30c30c30c30c3ULL;
    v = (v | v << 2) & 0x1249249249249249ULL;
    return v;
  };
  std::vector<std::pair<std::uint64_t, index_t>> key(static_cast<size_t>(S));
  for (index_t s = 0; s < S; ++s) {
    std::uint64_t code = 0;
    for (int k = 0; k < 3; ++k) {
      const double ext = hi[k] - lo[k];
      const double u = ext > 0 ? (double(points[3 * size_t(s) + k]) - lo[k]) / ext : 0.0;
      const double q = std::isfinite(u) ? std::min(std::max(u, 0.0), 1.0) * 2097151.0 : 0.0;
      code |= spread(std::uint64_t(q)) << k;
    }
    key[size_t(s)] = {code, s};
  }
  std::sort(key.begin(), key.end());
  std::vector<index_t> rank(static_cast<size_t>(S));
  for (index_t r = 0; r < S; ++r) rank[size_t(key[size_t(r)].second)] = r;
  return rank;
}

}  // namespace

template <class T>
ExpectedChamferResult expected_chamfer_forward(const T* target, index_t G, const T* points, const T* prob,
                                               const index_t* face, index_t S, const index_t* knn, index_t K,
                                               const ExpectedChamferSettings& settings) {
  const char* fn = "expected_chamfer_forward";
  check_sizes(fn, G, S, K);
  const FaceIds fid = dense_face_ids(fn, face, S);
  const index_t* fids = fid.ids();
  ExpectedChamferResult r;
  r.expected.assign(size_t(G), 0.0);
  r.residual.assign(size_t(G), 1.0);
  std::atomic<bool> bad{false};
  const int threads = thread_count(settings.num_threads, std::int64_t(G) * K);
#pragma omp parallel num_threads(threads)
  {
    // stamp[f] == g: face f already appeared in row g (rows are unique, so no reset is needed).
    std::vector<index_t> stamp(size_t(fid.count), kNone);
    RowDistances rd(settings, K);
#pragma omp for schedule(dynamic, 256)
    for (index_t g = 0; g < G; ++g) {
      const index_t* row = knn + size_t(g) * size_t(K);
      const index_t L = row_length(row, K);
      const T* t = target + 3 * size_t(g);
      double before = 1.0, e = 0.0;
      // One loop per distance kind, chosen at compile time: the Euclidean one is the kernel's plain loop.
      auto walk = [&](auto weighted_tag) {
        constexpr bool weighted = decltype(weighted_tag)::value;
        for (index_t i = 0; i < L; ++i) {
          const index_t s = weighted ? row[rd.order[size_t(i)]] : row[i];
          if (s < 0 || s >= S) {
            bad.store(true, std::memory_order_relaxed);
            break;
          }
          index_t& seen = stamp[size_t(fids[s])];
          if (seen == g) continue;  // masked: p = 0, contributes nothing and leaves B unchanged
          seen = g;
          const double d = weighted ? rd.dist[size_t(i)] : distance(t, points + 3 * size_t(s));
          const double p = double(prob[s]);
          e += d * p * before;
          before *= 1.0 - p;
        }
      };
      if (rd.normals == nullptr) {
        walk(std::false_type{});
      } else if (rd.compute(g, t, row, L, S, points, 3)) {
        walk(std::true_type{});
      } else {
        bad.store(true, std::memory_order_relaxed);
        continue;
      }
      r.expected[size_t(g)] = e;
      r.residual[size_t(g)] = before;
    }
  }
  if (bad.load()) bad_knn(fn, S);
  return r;
}

template <class T>
ExpectedChamferGrad<T> expected_chamfer_backward(const T* target, index_t G, const T* points, const T* prob,
                                                 const index_t* face, index_t S, const index_t* knn, index_t K,
                                                 const double* grad_expected,
                                                 const ExpectedChamferSettings& settings) {
  const char* fn = "expected_chamfer_backward";
  check_sizes(fn, G, S, K);
  const FaceIds fid = dense_face_ids(fn, face, S);
  const index_t* fids = fid.ids();
  // pack[8 s .. 8 s + 7]: position and probability of sample s, then the gradient of both, summed in
  // (g, i) order: a sample's reads and writes share one cache line (10% faster than separate arrays).
  std::vector<double> pack(8 * size_t(S), 0.0);
  for (index_t q = 0; q < S; ++q) {
    for (int k = 0; k < 3; ++k) pack[8 * size_t(q) + k] = double(points[3 * size_t(q) + k]);
    pack[8 * size_t(q) + 3] = double(prob[q]);
  }
  std::atomic<bool> bad{false};
  const int threads = thread_count(settings.num_threads, std::int64_t(G) * K);
  const std::vector<index_t> rank = threads > 1 ? spatial_ranks(points, S) : std::vector<index_t>();
#pragma omp parallel num_threads(threads)
  {
    const int tid = thread_id(), nth = team_size();
    // This thread owns the samples of Morton ranks [lo, hi) (all of them on one thread).
    const index_t lo = index_t(std::int64_t(S) * tid / nth), hi = index_t(std::int64_t(S) * (tid + 1) / nth);
    const std::uint32_t span = std::uint32_t(hi - lo);
    auto owned = [&](index_t s) { return nth == 1 || std::uint32_t(rank[size_t(s)] - lo) < span; };
    std::vector<index_t> stamp(size_t(fid.count), kNone);
    std::vector<double> dist(static_cast<size_t>(K)), p(static_cast<size_t>(K)), before(static_cast<size_t>(K)),
        coef(static_cast<size_t>(K)), dprob(static_cast<size_t>(K));
    std::vector<char> masked(static_cast<size_t>(K));
    RowDistances rd(settings, K);
    for (index_t g = 0; g < G; ++g) {
      const index_t* row = knn + size_t(g) * size_t(K);
      const index_t L = row_length(row, K);
      // Skip rows with none of this thread's samples. A row found to be ours is checked in full below.
      bool mine = false, broken = false;
      for (index_t i = 0; i < L && !mine; ++i) {
        const index_t s = row[i];
        if (s < 0 || s >= S) {
          broken = true;
          break;
        }
        mine = owned(s);
      }
      if (broken) bad.store(true, std::memory_order_relaxed);
      if (!mine) continue;
      // Forward again: distances, masks and B_i.
      const T* t = target + 3 * size_t(g);
      double b = 1.0;
      const bool weighted = rd.normals != nullptr;
      if (weighted && !rd.compute(g, t, row, L, S, pack.data(), 8)) {
        bad.store(true, std::memory_order_relaxed);
        continue;
      }
      bool valid = true;
      for (index_t i = 0; i < L; ++i) {
        const index_t s = weighted ? row[rd.order[size_t(i)]] : row[i];
        if (s < 0 || s >= S) {
          valid = false;
          break;
        }
        index_t& seen = stamp[size_t(fids[s])];
        masked[size_t(i)] = seen == g;
        before[size_t(i)] = b;
        if (masked[size_t(i)]) continue;
        seen = g;
        const double* xs = pack.data() + 8 * size_t(s);
        dist[size_t(i)] = weighted ? rd.dist[size_t(i)] : distance(t, xs);
        p[size_t(i)] = xs[3];
        b *= 1.0 - p[size_t(i)];
      }
      if (!valid) {
        bad.store(true, std::memory_order_relaxed);
        continue;
      }
      // Backward through the suffix recursion (tail = T_{i+1}).
      const double w = grad_expected[g];
      double tail = 0.0;
      for (index_t i = L - 1; i >= 0; --i) {
        if (masked[size_t(i)]) continue;
        const double d = dist[size_t(i)], pi = p[size_t(i)], bi = before[size_t(i)];
        coef[size_t(i)] = d > 0.0 ? w * pi * bi / d : 0.0;  // dE/dd_i / d_i
        dprob[size_t(i)] = w * bi * (d - tail);
        tail = pi * d + (1.0 - pi) * tail;
      }
      // This thread's samples, in candidate order. dd/dx = o / d, or ((1 - w^2) a n + w^2 o) / d (header).
      const double* n = rd.normals ? rd.normals + 3 * size_t(g) : nullptr;
      for (index_t i = 0; i < L; ++i) {
        const index_t s = weighted ? row[rd.order[size_t(i)]] : row[i];
        if (masked[size_t(i)] || !owned(s)) continue;
        double* x = pack.data() + 8 * size_t(s);
        double* a = x + 4;
        if (n == nullptr) {
          for (int k = 0; k < 3; ++k) a[k] += coef[size_t(i)] * (x[k] - double(t[k]));
        } else {
          const double c_along = coef[size_t(i)] * (1.0 - rd.w2) * rd.along[size_t(i)], c_off = coef[size_t(i)] * rd.w2;
          for (int k = 0; k < 3; ++k) a[k] += c_along * n[k] + c_off * (x[k] - double(t[k]));
        }
        a[3] += dprob[size_t(i)];
      }
    }
  }
  if (bad.load()) bad_knn(fn, S);
  ExpectedChamferGrad<T> r;
  r.grad_points.resize(3 * size_t(S));
  r.grad_prob.resize(size_t(S));
  for (index_t s = 0; s < S; ++s) {
    for (int k = 0; k < 3; ++k) r.grad_points[3 * size_t(s) + k] = T(pack[8 * size_t(s) + 4 + k]);
    r.grad_prob[size_t(s)] = T(pack[8 * size_t(s) + 7]);
  }
  return r;
}

// ------------------------------------------------------------------------------------ k nearest neighbours
//
// Written by hand because it is measurably faster than SciPy's cKDTree for the large K of the expected
// Chamfer term: at G = S = 100K, K = 95 it took 0.33-0.42 s on one thread against cKDTree's 1.1-1.8 s
// (0.18-0.42 s against 1.0-1.4 s on two), with identical ids; it also skips cKDTree's float64 distance and
// int64 index outputs (150 MB). CGAL's Orthogonal_k_neighbor_search was not tried: it is a per-query heap
// search like cKDTree's.
//
// Both point sets go into k-d trees (median splits along the widest side, tight boxes). Queries are handled
// in groups, the leaves of the query tree (8 queries). For a group with box centre c, take K data points
// near c (the K nearest of c among the points within the radius of the thread's previous group, else from
// a heap search); for each query q, b_q = the largest distance from q to those K points bounds q's K-th
// distance, so q's K nearest lie within R = max_q (b_q + |q - c|) of c. One range search gathers the
// group's candidates; each query keeps those within b_q (about 1.3 K of them) and ranks them by
// (squared distance, id): keys of the float32 squared distance, a counting-sort pass into equal-width
// buckets and an insertion sort (4x faster than std::sort of (double, int) pairs here), then an exact
// re-sort of runs of equal float32 keys. The output is exact and does not depend on the groups' radii,
// hence not on the schedule or the thread count. K = 1 takes a plain depth-first search per query instead.
// The trees can be built once and searched many times (PointTree): the expected Chamfer term searches its
// fixed target both ways every step.
struct KdNode {
  double lo[3], hi[3];  // tight bounding box of the node's points
  index_t begin, end;   // the node's points are order[begin, end)
  index_t child;        // first child (the second is child + 1); kNone for a leaf
};

struct KdTree {
  std::vector<KdNode> nodes;   // nodes[0] is the root (absent when there are no points)
  std::vector<index_t> order;  // point ids grouped by node
  std::vector<index_t> where;  // where[id]: the point's position in `order`
  std::vector<double> xyz;     // (n, 3) coordinates, in `order`
  index_t leaf_size = 0;       // largest leaf; as the query side of a search, its leaves are the groups
};

namespace {

template <class T>
KdTree build_kdtree(const T* pts, index_t n, index_t leaf_size) {
  KdTree t;
  t.leaf_size = leaf_size;
  t.order.resize(size_t(n));
  for (index_t i = 0; i < n; ++i) t.order[size_t(i)] = i;
  if (n == 0) return t;
  t.nodes.reserve(size_t(4 * (n / leaf_size + 1)));
  t.nodes.push_back(KdNode{{0, 0, 0}, {0, 0, 0}, 0, n, kNone});
  std::vector<index_t> todo{0};
  while (!todo.empty()) {
    const index_t id = todo.back();
    todo.pop_back();
    const index_t b = t.nodes[size_t(id)].begin, e = t.nodes[size_t(id)].end;
    double lo[3], hi[3];
    for (int k = 0; k < 3; ++k) lo[k] = hi[k] = double(pts[3 * size_t(t.order[size_t(b)]) + k]);
    for (index_t j = b + 1; j < e; ++j) {
      const T* x = pts + 3 * size_t(t.order[size_t(j)]);
      for (int k = 0; k < 3; ++k) {
        lo[k] = std::min(lo[k], double(x[k]));
        hi[k] = std::max(hi[k], double(x[k]));
      }
    }
    KdNode& nd = t.nodes[size_t(id)];
    for (int k = 0; k < 3; ++k) {
      nd.lo[k] = lo[k];
      nd.hi[k] = hi[k];
    }
    if (e - b <= leaf_size) continue;
    int dim = 0;
    for (int k = 1; k < 3; ++k) {
      if (hi[k] - lo[k] > hi[dim] - lo[dim]) dim = k;
    }
    const index_t mid = b + (e - b) / 2;
    std::nth_element(t.order.begin() + b, t.order.begin() + mid, t.order.begin() + e, [&](index_t u, index_t v) {
      const T cu = pts[3 * size_t(u) + dim], cv = pts[3 * size_t(v) + dim];
      return cu < cv || (cu == cv && u < v);
    });
    const index_t child = index_t(t.nodes.size());
    t.nodes[size_t(id)].child = child;
    t.nodes.push_back(KdNode{{0, 0, 0}, {0, 0, 0}, b, mid, kNone});
    t.nodes.push_back(KdNode{{0, 0, 0}, {0, 0, 0}, mid, e, kNone});
    todo.push_back(child + 1);
    todo.push_back(child);
  }
  t.xyz.resize(3 * size_t(n));
  t.where.resize(size_t(n));
  for (index_t j = 0; j < n; ++j) {
    for (int k = 0; k < 3; ++k) t.xyz[3 * size_t(j) + k] = double(pts[3 * size_t(t.order[size_t(j)]) + k]);
    t.where[size_t(t.order[size_t(j)])] = j;
  }
  return t;
}

inline double box_distance2(const KdNode& nd, const double* q) {
  double s = 0.0;
  for (int k = 0; k < 3; ++k) {
    const double v = std::max(std::max(nd.lo[k] - q[k], q[k] - nd.hi[k]), 0.0);
    s += v * v;
  }
  return s;
}

inline double distance2(const double* a, const double* b) {
  const double dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
  return dx * dx + dy * dy + dz * dz;
}

using Neighbour = std::pair<double, index_t>;  // (squared distance, id): the order that ranks neighbours

// The K nearest points of q as a max-heap (heap.front() is the K-th nearest). Needs K <= the tree's size.
void nearest_heap(const KdTree& t, const double* q, index_t K, std::vector<Neighbour>& heap, index_t node) {
  const KdNode& nd = t.nodes[size_t(node)];
  if (index_t(heap.size()) == K && box_distance2(nd, q) > heap.front().first) return;
  if (nd.child == kNone) {
    for (index_t j = nd.begin; j < nd.end; ++j) {
      const Neighbour c{distance2(q, t.xyz.data() + 3 * size_t(j)), t.order[size_t(j)]};
      if (index_t(heap.size()) < K) {
        heap.push_back(c);
        std::push_heap(heap.begin(), heap.end());
      } else if (c < heap.front()) {
        std::pop_heap(heap.begin(), heap.end());
        heap.back() = c;
        std::push_heap(heap.begin(), heap.end());
      }
    }
    return;
  }
  const index_t a = nd.child, b = nd.child + 1;
  const bool a_first = box_distance2(t.nodes[size_t(a)], q) <= box_distance2(t.nodes[size_t(b)], q);
  nearest_heap(t, q, K, heap, a_first ? a : b);
  nearest_heap(t, q, K, heap, a_first ? b : a);
}

// Appends the tree positions j (into order / xyz) of the points within sqrt(r2) of q; false (and stops)
// once out holds more than `limit` points.
bool in_ball(const KdTree& t, const double* q, double r2, std::vector<index_t>& out, size_t limit,
             index_t node) {
  const KdNode& nd = t.nodes[size_t(node)];
  if (box_distance2(nd, q) > r2) return true;
  if (nd.child == kNone) {
    for (index_t j = nd.begin; j < nd.end; ++j) {
      if (distance2(q, t.xyz.data() + 3 * size_t(j)) <= r2) out.push_back(j);
    }
    return out.size() <= limit;
  }
  return in_ball(t, q, r2, out, limit, nd.child) && in_ball(t, q, r2, out, limit, nd.child + 1);
}

template <class T>
void check_finite(const char* fn, const char* name, const T* x, index_t n) {
  for (size_t j = 0; j < 3 * size_t(n); ++j) {
    if (!std::isfinite(double(x[j]))) {
      throw std::invalid_argument(std::string(fn) + ": " + name + " row " + std::to_string(j / 3) +
                                  " is not finite");
    }
  }
}

// Writes to out the ids of the K smallest (d2, id) pairs, in that order (K <= d2.size()). Sorts 64-bit keys
// (float32 of d2, position): a counting-sort pass by d2 into about n / 2 equal-width buckets over
// [min, max] (d2 is close to uniform for points on a surface), then each bucket on its own (insertion sort
// when small, std::sort otherwise, so a skewed distribution costs n log n, not n^2). Bucket and float32
// orders agree with the d2 order up to ties, so runs of equal float32 keys (near ties) are contiguous; they
// are then re-sorted exactly.
void k_smallest(const std::vector<double>& d2, const std::vector<index_t>& id, index_t K,
                std::vector<std::uint64_t>& key, std::vector<index_t>& start, index_t* out) {
  const size_t n = d2.size();
  key.resize(n);
  double lo = d2[0], top = d2[0];
  for (size_t m = 1; m < n; ++m) {
    lo = std::min(lo, d2[m]);
    top = std::max(top, d2[m]);
  }
  const size_t buckets = std::max<size_t>(1, n / 2);
  const double scale = top > lo ? double(buckets) / (top - lo) : 0.0;
  auto bucket = [&](size_t m) { return std::min(buckets - 1, size_t((d2[m] - lo) * scale)); };
  start.assign(buckets + 1, 0);
  for (size_t m = 0; m < n; ++m) ++start[bucket(m) + 1];
  for (size_t b = 0; b < buckets; ++b) start[b + 1] += start[b];
  for (size_t m = 0; m < n; ++m) {  // start[b] ends as the end of bucket b
    const float f = float(d2[m]);   // rounding is monotone: float order agrees with double order up to ties
    std::uint32_t bits;
    std::memcpy(&bits, &f, sizeof bits);
    key[size_t(start[bucket(m)]++)] = (std::uint64_t(bits) << 32) | std::uint64_t(m);
  }
  for (size_t b = 0, begin = 0; b < buckets && begin < size_t(K); begin = size_t(start[b++])) {
    const size_t end = size_t(start[b]);
    if (end - begin > 32) {
      std::sort(key.begin() + begin, key.begin() + end);
      continue;
    }
    for (size_t m = begin + 1; m < end; ++m) {
      const std::uint64_t v = key[m];
      size_t j = m;
      for (; j > begin && key[j - 1] > v; --j) key[j] = key[j - 1];
      key[j] = v;
    }
  }
  // Near ties: a run of equal float32 keys that starts before K may continue into buckets not sorted
  // above; gather it right after position K - 1, then order every run exactly.
  auto hi = [](std::uint64_t k) { return std::uint32_t(k >> 32); };
  size_t end = size_t(K);
  const std::uint32_t last = hi(key[size_t(K) - 1]);
  for (size_t m = size_t(K); m < n; ++m) {
    if (hi(key[m]) == last) std::swap(key[m], key[end++]);
  }
  auto exact = [&](std::uint64_t a, std::uint64_t b) {
    const size_t u = size_t(std::uint32_t(a)), v = size_t(std::uint32_t(b));
    return d2[u] < d2[v] || (d2[u] == d2[v] && id[u] < id[v]);
  };
  for (size_t i = 0; i < size_t(K);) {
    size_t j = i + 1;
    while (j < end && hi(key[j]) == hi(key[i])) ++j;
    if (j - i > 1) std::sort(key.begin() + i, key.begin() + j, exact);
    i = j;
  }
  for (index_t i = 0; i < K; ++i) out[i] = id[size_t(std::uint32_t(key[size_t(i)]))];
}

constexpr index_t kDataLeaf = 16;   // points per leaf of the data tree
constexpr index_t kQueryLeaf = 8;   // queries per group
constexpr double kSlack = 1e-9;     // relative widening of the search radii against rounding

}  // namespace

namespace {

// The K nearest data points of every query of `qt`, written to out[(query id) * K ..] (see the method above).
// The nearest point of q, (squared distance, id) smallest, improving on the bound (best2, best) given.
void nearest_one(const KdTree& t, const double* q, double& best2, index_t& best, index_t node) {
  const KdNode& nd = t.nodes[size_t(node)];
  if (box_distance2(nd, q) > best2) return;
  if (nd.child == kNone) {
    for (index_t j = nd.begin; j < nd.end; ++j) {
      const double d2 = distance2(q, t.xyz.data() + 3 * size_t(j));
      const index_t id = t.order[size_t(j)];
      if (d2 < best2 || (d2 == best2 && id < best)) {
        best2 = d2;
        best = id;
      }
    }
    return;
  }
  const index_t a = nd.child, b = nd.child + 1;
  const bool a_first = box_distance2(t.nodes[size_t(a)], q) <= box_distance2(t.nodes[size_t(b)], q);
  nearest_one(t, q, best2, best, a_first ? a : b);
  nearest_one(t, q, best2, best, a_first ? b : a);
}

void knn_trees(const KdTree& dt, const KdTree& qt, index_t K, int threads, index_t* out) {
  if (K == 1) {
    // One neighbour: a depth-first search per query, from the previous query's nearest point, beats the groups
    // below (their bounds from one point near the group centre are loose); `python -m eval.bench step` times it.
    const index_t Q = index_t(qt.order.size()), chunk = 1024;
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (index_t c = 0; c < (Q + chunk - 1) / chunk; ++c) {
      index_t best = dt.order[0];
      for (index_t j = c * chunk; j < std::min(Q, (c + 1) * chunk); ++j) {
        const double* q = qt.xyz.data() + 3 * size_t(j);
        // Start from the previous query's nearest point (queries in tree order are near each other).
        double best2 = distance2(q, dt.xyz.data() + 3 * size_t(dt.where[size_t(best)]));
        nearest_one(dt, q, best2, best, 0);
        out[size_t(qt.order[size_t(j)])] = best;
      }
    }
    return;
  }
  std::vector<index_t> groups;
  for (index_t n = 0; n < index_t(qt.nodes.size()); ++n) {
    if (qt.nodes[size_t(n)].child == kNone) groups.push_back(n);
  }
#pragma omp parallel num_threads(threads)
  {
    std::vector<Neighbour> heap;
    std::vector<index_t> cand, cand_id, sel_id;
    std::vector<double> sel_d2;
    std::vector<std::uint64_t> key;
    std::vector<index_t> start;
    std::vector<double> cxyz, kxyz, bound2;
    double guess = 0.0;  // search radius of this thread's previous group (no effect on the results)
    // Candidates per group beyond which its queries fall back to one heap search each (typically about
    // 2 K candidates per group of 8 queries on a surface).
    const size_t limit = std::max<size_t>(256, 16 * size_t(K));
#pragma omp for schedule(dynamic, 16)
    for (index_t gi = 0; gi < index_t(groups.size()); ++gi) {
      const KdNode& leaf = qt.nodes[size_t(groups[size_t(gi)])];
      double c[3];
      for (int k = 0; k < 3; ++k) c[k] = 0.5 * (leaf.lo[k] + leaf.hi[k]);
      // K points near c: the K nearest among the points within the last group's radius (this thread's
      // previous group, usually a neighbour) when there are that many, else by a heap search. Any K points
      // give valid bounds below; near ones give tight bounds.
      kxyz.resize(3 * size_t(K));
      cand.clear();
      const bool near = guess > 0.0 && in_ball(dt, c, guess * guess, cand, limit, 0) &&
                        index_t(cand.size()) >= K;
      if (near) {
        key.resize(cand.size());
        for (size_t m = 0; m < cand.size(); ++m) {
          const float f = float(distance2(c, dt.xyz.data() + 3 * size_t(cand[m])));
          std::uint32_t bits;
          std::memcpy(&bits, &f, sizeof bits);
          key[m] = (std::uint64_t(bits) << 32) | std::uint64_t(m);
        }
        std::nth_element(key.begin(), key.begin() + (K - 1), key.end());
        for (index_t i = 0; i < K; ++i) {
          const double* x = dt.xyz.data() + 3 * size_t(cand[size_t(std::uint32_t(key[size_t(i)]))]);
          for (int k = 0; k < 3; ++k) kxyz[3 * size_t(i) + k] = x[k];
        }
      } else {
        heap.clear();
        nearest_heap(dt, c, K, heap, 0);
        for (index_t i = 0; i < K; ++i) {
          const double* x = dt.xyz.data() + 3 * size_t(dt.where[size_t(heap[size_t(i)].second)]);
          for (int k = 0; k < 3; ++k) kxyz[3 * size_t(i) + k] = x[k];
        }
      }
      // b_q: the largest distance from query q to those K points, an upper bound on q's K-th distance; every
      // point among q's K nearest lies within b_q + |q - c| <= R of c.
      const index_t nq = leaf.end - leaf.begin;
      bound2.resize(size_t(nq));
      double R = 0.0;
      for (index_t j = 0; j < nq; ++j) {
        const double* q = qt.xyz.data() + 3 * size_t(leaf.begin + j);
        double b2 = 0.0;
        for (index_t i = 0; i < K; ++i) b2 = std::max(b2, distance2(q, kxyz.data() + 3 * size_t(i)));
        const double b = std::sqrt(b2) * (1.0 + kSlack);
        bound2[size_t(j)] = b * b;
        R = std::max(R, (b + std::sqrt(distance2(c, q))) * (1.0 + kSlack));
      }
      bool gathered = near && R <= guess;
      if (!gathered) {
        cand.clear();
        gathered = in_ball(dt, c, R * R, cand, limit, 0);
      }
      guess = 1.1 * R;
      if (!gathered) {
        // Too many candidates (queries far from the data compared with its extent, where the bounds are
        // loose): one heap search per query instead.
        for (index_t j = leaf.begin; j < leaf.end; ++j) {
          heap.clear();
          nearest_heap(dt, qt.xyz.data() + 3 * size_t(j), K, heap, 0);
          std::sort_heap(heap.begin(), heap.end());
          index_t* row = out + size_t(qt.order[size_t(j)]) * size_t(K);
          for (index_t i = 0; i < K; ++i) row[i] = heap[size_t(i)].second;
        }
        continue;
      }
      cxyz.resize(3 * cand.size());
      cand_id.resize(cand.size());
      for (size_t m = 0; m < cand.size(); ++m) {
        for (int k = 0; k < 3; ++k) cxyz[3 * m + k] = dt.xyz[3 * size_t(cand[m]) + k];
        cand_id[m] = dt.order[size_t(cand[m])];
      }
      for (index_t j = leaf.begin; j < leaf.end; ++j) {
        const double* q = qt.xyz.data() + 3 * size_t(j);
        const double b2 = bound2[size_t(j - leaf.begin)];
        sel_d2.resize(cand.size());
        sel_id.resize(cand.size());
        size_t n = 0;
        for (size_t m = 0; m < cand.size(); ++m) {  // branch-free filter
          const double d2 = distance2(q, cxyz.data() + 3 * m);
          sel_d2[n] = d2;
          sel_id[n] = cand_id[m];
          n += d2 <= b2;
        }
        sel_d2.resize(n);
        sel_id.resize(n);
        // The selection holds the K nearest of c, so at least K points.
        k_smallest(sel_d2, sel_id, K, key, start, out + size_t(qt.order[size_t(j)]) * size_t(K));
      }
    }
  }
}

void check_k(const char* fn, index_t D, index_t Q, index_t K) {
  if (D < 0 || Q < 0 || K < 0) throw std::invalid_argument(std::string(fn) + ": negative size");
  if (K > D) {
    throw std::invalid_argument(std::string(fn) + ": k = " + std::to_string(K) + " exceeds the " +
                                std::to_string(D) + " data points");
  }
}

}  // namespace

template <class T>
std::vector<index_t> knn_search(const T* data, index_t D, const T* queries, index_t Q, index_t K,
                                const KnnSettings& settings) {
  const char* fn = "knn_search";
  check_k(fn, D, Q, K);
  check_finite(fn, "data", data, D);
  check_finite(fn, "queries", queries, Q);
  std::vector<index_t> out(size_t(Q) * size_t(K));
  if (K == 0 || Q == 0) return out;
  const int threads = thread_count(settings.num_threads, std::int64_t(Q) * std::max<index_t>(K, 8));
  KdTree dt, qt;
#pragma omp parallel sections num_threads(std::min(threads, 2))
  {
#pragma omp section
    dt = build_kdtree(data, D, kDataLeaf);
#pragma omp section
    qt = build_kdtree(queries, Q, kQueryLeaf);
  }
  knn_trees(dt, qt, K, threads, out.data());
  return out;
}

template <class T>
PointTree::PointTree(const T* points, index_t n, index_t leaf_size) {
  if (n < 0) throw std::invalid_argument("PointTree: negative size");
  if (leaf_size < 1) throw std::invalid_argument("PointTree: leaf_size must be >= 1, got " + std::to_string(leaf_size));
  check_finite("PointTree", "points", points, n);
  tree = std::make_shared<const KdTree>(build_kdtree(points, n, leaf_size));
}

index_t PointTree::size() const { return tree ? index_t(tree->order.size()) : 0; }

std::vector<index_t> knn_search(const PointTree& data, const PointTree& queries, index_t K,
                                const KnnSettings& settings) {
  const char* fn = "knn_search";
  const index_t D = data.size(), Q = queries.size();
  check_k(fn, D, Q, K);
  std::vector<index_t> out(size_t(Q) * size_t(K));
  if (K == 0 || Q == 0) return out;
  const int threads = thread_count(settings.num_threads, std::int64_t(Q) * std::max<index_t>(K, 8));
  knn_trees(*data.tree, *queries.tree, K, threads, out.data());
  return out;
}

#define DMESH_INSTANTIATE(T)                                                                                   \
  template ExpectedChamferResult expected_chamfer_forward<T>(const T*, index_t, const T*, const T*,            \
                                                             const index_t*, index_t, const index_t*, index_t, \
                                                             const ExpectedChamferSettings&);                  \
  template ExpectedChamferGrad<T> expected_chamfer_backward<T>(const T*, index_t, const T*, const T*,          \
                                                               const index_t*, index_t, const index_t*,        \
                                                               index_t, const double*,                         \
                                                               const ExpectedChamferSettings&);      \
  template std::vector<index_t> knn_search<T>(const T*, index_t, const T*, index_t, index_t, const KnnSettings&); \
  template PointTree::PointTree(const T*, index_t, index_t);
DMESH_INSTANTIATE(float)
DMESH_INSTANTIATE(double)
#undef DMESH_INSTANTIATE

}  // namespace dmesh
