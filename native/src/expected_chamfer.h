// Expected Chamfer distance, target -> DMesh term (paper appendix 8.2, Eq. 12), forward and backward.
//
// Letters: G target points, S samples drawn on the DMesh, K candidates per target row.
//
// Row g lists knn[g, 0..K), the ids of its K nearest samples sorted by distance (the caller's k-d tree
// query; the order is taken as given). For candidate i of row g, s = knn[g, i]:
//   d_i = |t_g - x_s|,   p_i = prob[s], or 0 where face[s] already appeared earlier in the row
//                         (first-occurrence masking: at most one sample per face),
//   B_i = prod_{j<i} (1 - p_j)                 (exclusive cumulative product),
//   expected_g = sum_i d_i p_i B_i,   residual_g = prod_i (1 - p_i)   (mass beyond the K candidates).
// Backward, for an upstream gradient w_g of expected_g (the residual gets none):
//   dE/dd_i = p_i B_i,   dE/dp_i = B_i (d_i - T_{i+1}),   T_i = p_i d_i + (1 - p_i) T_{i+1},  T_K = 0,
//   (the suffix recursion needs no division by 1 - p_i, so p_i = 1 is fine), zero for masked candidates;
//   dd_i/dx_s = (x_s - t_g) / d_i (0 where d_i = 0, as torch's norm). The gradients reach the sample
//   positions (S, 3) and the sample probabilities (S,); target and face ids get none.
//
// Element type T (float or double) is that of target, points and prob and of the gradients; distances,
// row sums and products and the gradient sums are computed in double for either.
//
// Threads and determinism: `num_threads` OpenMP threads (0: the OpenMP default). Results are bit-for-bit
// the same for any thread count. The forward shares the rows among the threads, one thread per row. The
// backward gives every sample to exactly one thread (contiguous ranges of samples sorted along a Z-order
// curve, so that a row's candidates mostly belong to one thread); each thread walks all rows in order,
// recomputes those that hold one of its samples (rows across a range boundary are recomputed by each
// owner, the same way) and adds their contributions to its own samples. Every sample's gradient is thus
// summed in increasing (g, i) order, the serial order, whatever the thread count: no float atomics, no
// per-thread partial sums. Rows in a spatial order (nearby targets next to each other) run faster.
//
// Face ids are any non-negative int32 values; they are compacted to dense ids when sparse. knn entries
// must lie in [0, S), except that a row may end early: its candidates are the entries before its first
// kNone (-1), for rows of different lengths in one (G, K) array; a bad entry raises std::invalid_argument.
#pragma once
#include <cstdint>
#include <memory>
#include <vector>

#include "types.h"

namespace dmesh {

// With target normals n_g (unit, (G, 3) double) and a tangent weight w in [0, 1), the distance of candidate i
// is d_i = sqrt(a^2 + w^2 (|o|^2 - a^2)), o = x_s - t_g, a = o . n_g (the tangential part of the offset
// scaled by w; w = 1 is |o|), and each row is taken in increasing d_i (ties: knn order) rather than as given;
// dd_i/dx_s = ((1 - w^2) a n_g + w^2 o) / d_i. Not upstream: it lowers the loss's sampling floor.
struct ExpectedChamferSettings {
  int num_threads = 0;                    // 0: the OpenMP default (OMP_NUM_THREADS or the hardware)
  const double* target_normals = nullptr;  // (G, 3) unit normals, or null: Euclidean distances
  double tangent_weight = 1.0;            // w, used with target_normals
};

struct ExpectedChamferResult {
  std::vector<double> expected;  // (G,) expected nearest distance of each target point
  std::vector<double> residual;  // (G,) probability mass beyond the K candidates
};

template <class T>
struct ExpectedChamferGrad {
  std::vector<T> grad_points;  // (S, 3)
  std::vector<T> grad_prob;    // (S,)
};

// target (G, 3), points (S, 3), prob (S,), face (S,) face id of each sample, knn (G, K) sample ids per row
// sorted by distance. Returns expected and residual per row.
template <class T>
ExpectedChamferResult expected_chamfer_forward(const T* target, index_t G, const T* points, const T* prob,
                                               const index_t* face, index_t S, const index_t* knn, index_t K,
                                               const ExpectedChamferSettings& settings);

// The same inputs plus grad_expected (G,), the upstream gradient of each row's expected distance.
template <class T>
ExpectedChamferGrad<T> expected_chamfer_backward(const T* target, index_t G, const T* points, const T* prob,
                                                 const index_t* face, index_t S, const index_t* knn, index_t K,
                                                 const double* grad_expected,
                                                 const ExpectedChamferSettings& settings);

// ------------------------------------------------------------------------------------ k nearest neighbours
// Letters: D data points, Q query points.

struct KnnSettings {
  int num_threads = 0;  // 0: the OpenMP default
};

// For every query (Q, 3), the ids of its K nearest data points (D, 3), nearest first: (Q, K), exact, ties
// broken by the smaller id, so the result does not depend on the thread count. Needs K <= D and finite
// coordinates (std::invalid_argument otherwise). Distances are computed in double for either T. Written by
// hand (k-d trees, queries in groups); the method and its timings against SciPy are in expected_chamfer.cpp.
template <class T>
std::vector<index_t> knn_search(const T* data, index_t D, const T* queries, index_t Q, index_t K,
                                const KnnSettings& settings);

struct KdTree;  // expected_chamfer.cpp

// A k-d tree of n points (ids 0..n-1), built once and searched many times, on either side of a search: as
// the data side, or as the query side, whose leaves (at most leaf_size queries) are the search's groups.
// The expected Chamfer term searches a fixed target both ways every step, so its tree is built once.
// Immutable after construction; copies share the tree. Needs finite coordinates.
class PointTree {
 public:
  PointTree() = default;
  template <class T>
  PointTree(const T* points, index_t n, index_t leaf_size);
  index_t size() const;
  std::shared_ptr<const KdTree> tree;
};

// knn_search over two built trees: for every point of `queries`, the ids of its K nearest points of `data`,
// (Q, K), the same ids as knn_search of their coordinates (for any leaf sizes).
std::vector<index_t> knn_search(const PointTree& data, const PointTree& queries, index_t K,
                                const KnnSettings& settings);

}  // namespace dmesh
