// Bindings of the expected Chamfer kernel and its kNN search (expected_chamfer.h), for float32 and float64.
#include <nanobind/nanobind.h>
#include <nanobind/stl/optional.h>

#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "expected_chamfer.h"
#include "numpy_out.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

namespace {

struct Shapes {
  index_t G, S, K;
};

template <class T>
Shapes check_inputs(const char* fn, const In<T>& target, const In<T>& points, const In<T>& prob,
                    const In<index_t>& face, const In<index_t>& knn) {
  require(fn, "target", target, -1, 3);
  require(fn, "points", points, -1, 3);
  const long G = long(target.shape(0)), S = long(points.shape(0));
  require(fn, "prob", prob, S, -1);
  require(fn, "face", face, S, -1);
  if (knn.ndim() != 2 || long(knn.shape(0)) != G) {
    std::string got = "(";
    for (size_t k = 0; k < knn.ndim(); ++k) got += (k ? ", " : "") + std::to_string(knn.shape(k));
    throw std::invalid_argument(std::string(fn) + ": knn must have shape (" + std::to_string(G) +
                                ", K) like target, got " + got + ")");
  }
  return {index_t(G), index_t(S), index_t(knn.shape(1))};
}

// The kernel settings; target normals must be (G, 3) like target, the tangent weight in [0, 1].
ExpectedChamferSettings chamfer_settings(const char* fn, const Shapes& n, int num_threads,
                                         const std::optional<In<double>>& target_normals, double tangent_weight) {
  ExpectedChamferSettings settings{num_threads};
  if (!(tangent_weight >= 0.0 && tangent_weight <= 1.0)) {
    throw std::invalid_argument(std::string(fn) + ": tangent_weight must be in [0, 1], got " +
                                std::to_string(tangent_weight));
  }
  if (target_normals) {
    require(fn, "target_normals", *target_normals, long(n.G), 3);
    settings.target_normals = target_normals->data();
    settings.tangent_weight = tangent_weight;
  }
  return settings;
}

template <class T>
void bind_typed(nb::module_& m) {
  m.def(
      "expected_chamfer_forward",
      [](In<T> target, In<T> points, In<T> prob, In<index_t> face, In<index_t> knn, int num_threads,
         std::optional<In<double>> target_normals, double tangent_weight) {
        const char* fn = "expected_chamfer_forward";
        const Shapes n = check_inputs(fn, target, points, prob, face, knn);
        const ExpectedChamferSettings settings = chamfer_settings(fn, n, num_threads, target_normals, tangent_weight);
        ExpectedChamferResult r;
        {
          nb::gil_scoped_release release;
          r = expected_chamfer_forward<T>(target.data(), n.G, points.data(), prob.data(), face.data(), n.S,
                                          knn.data(), n.K, settings);
        }
        return nb::make_tuple(to_numpy(std::move(r.expected), {size_t(n.G)}),
                              to_numpy(std::move(r.residual), {size_t(n.G)}));
      },
      nb::arg("target").noconvert(), nb::arg("points").noconvert(), nb::arg("prob").noconvert(),
      nb::arg("face").noconvert(), nb::arg("knn").noconvert(), nb::arg("num_threads"),
      nb::arg("target_normals").noconvert() = nb::none(), nb::arg("tangent_weight") = 1.0,
      "expected_chamfer_forward(target (G,3), points (S,3), prob (S,) all f32 or all f64, face (S,) i32,\n"
      "                         knn (G,K) i32, num_threads, target_normals (G,3) f64 or None,\n"
      "                         tangent_weight) -> (expected (G,) f64, residual (G,) f64)\n\n"
      "Per target row: the expected distance to its first existing candidate, knn sorted by distance,\n"
      "one sample per face; with target normals, tangent-weighted distances (native/src/expected_chamfer.h).");

  m.def(
      "expected_chamfer_backward",
      [](In<T> target, In<T> points, In<T> prob, In<index_t> face, In<index_t> knn, In<double> grad_expected,
         int num_threads, std::optional<In<double>> target_normals, double tangent_weight) {
        const char* fn = "expected_chamfer_backward";
        const Shapes n = check_inputs(fn, target, points, prob, face, knn);
        require(fn, "grad_expected", grad_expected, n.G, -1);
        const ExpectedChamferSettings settings = chamfer_settings(fn, n, num_threads, target_normals, tangent_weight);
        ExpectedChamferGrad<T> g;
        {
          nb::gil_scoped_release release;
          g = expected_chamfer_backward<T>(target.data(), n.G, points.data(), prob.data(), face.data(), n.S,
                                           knn.data(), n.K, grad_expected.data(), settings);
        }
        return nb::make_tuple(to_numpy(std::move(g.grad_points), {size_t(n.S), 3}),
                              to_numpy(std::move(g.grad_prob), {size_t(n.S)}));
      },
      nb::arg("target").noconvert(), nb::arg("points").noconvert(), nb::arg("prob").noconvert(),
      nb::arg("face").noconvert(), nb::arg("knn").noconvert(), nb::arg("grad_expected").noconvert(),
      nb::arg("num_threads"), nb::arg("target_normals").noconvert() = nb::none(), nb::arg("tangent_weight") = 1.0,
      "expected_chamfer_backward(<forward inputs>, grad_expected (G,) f64, num_threads)\n"
      "  -> (grad_points (S,3), grad_prob (S,)) in the inputs' float type\n\n"
      "Gradients of sum_g grad_expected[g] * expected[g]; byte-identical on any thread count.");

  m.def(
      "knn_search",
      [](In<T> data, In<T> queries, long k, int num_threads) {
        const char* fn = "knn_search";
        require(fn, "data", data, -1, 3);
        require(fn, "queries", queries, -1, 3);
        const long D = long(data.shape(0)), Q = long(queries.shape(0));
        if (k < 0 || k > D) {
          throw std::invalid_argument(std::string(fn) + ": k must be in [0, " + std::to_string(D) +
                                      "] (the number of data points), got " + std::to_string(k));
        }
        std::vector<index_t> ids;
        {
          nb::gil_scoped_release release;
          ids = knn_search<T>(data.data(), index_t(D), queries.data(), index_t(Q), index_t(k),
                              KnnSettings{num_threads});
        }
        return to_numpy(std::move(ids), {size_t(Q), size_t(k)});
      },
      nb::arg("data").noconvert(), nb::arg("queries").noconvert(), nb::arg("k"), nb::arg("num_threads"),
      "knn_search(data (D,3), queries (Q,3) both f32 or both f64, k, num_threads) -> ids (Q,k) i32\n\n"
      "Exact k nearest data points of every query, nearest first, ties to the smaller id.");
}

}  // namespace

void bind_chamfer(nb::module_& m) {
  bind_typed<double>(m);
  bind_typed<float>(m);

  nb::class_<PointTree>(m, "PointTree", "A k-d tree of 3D points for repeated knn_search_trees calls.")
      .def(
          "__init__",
          [](PointTree* self, In<double> points, long leaf_size) {
            require("PointTree", "points", points, -1, 3);
            if (leaf_size < 1) {
              throw std::invalid_argument("PointTree: leaf_size must be >= 1, got " + std::to_string(leaf_size));
            }
            nb::gil_scoped_release release;
            new (self) PointTree(points.data(), index_t(points.shape(0)), index_t(leaf_size));
          },
          nb::arg("points").noconvert(), nb::arg("leaf_size"),
          "PointTree(points (n,3) f64, leaf_size): the tree of the points (ids 0..n-1); as the query side of a\n"
          "search its leaves of at most leaf_size points are the groups.")
      .def_prop_ro("size", &PointTree::size);

  m.def(
      "knn_search_trees",
      [](const PointTree& data, const PointTree& queries, long k, int num_threads) {
        const char* fn = "knn_search_trees";
        const long D = data.size(), Q = queries.size();
        if (k < 0 || k > D) {
          throw std::invalid_argument(std::string(fn) + ": k must be in [0, " + std::to_string(D) +
                                      "] (the number of data points), got " + std::to_string(k));
        }
        std::vector<index_t> ids;
        {
          nb::gil_scoped_release release;
          ids = knn_search(data, queries, index_t(k), KnnSettings{num_threads});
        }
        return to_numpy(std::move(ids), {size_t(Q), size_t(k)});
      },
      nb::arg("data"), nb::arg("queries"), nb::arg("k"), nb::arg("num_threads"),
      "knn_search_trees(data PointTree, queries PointTree, k, num_threads) -> ids (Q,k) i32\n\n"
      "knn_search of the trees' points: the same ids, without building the trees again.");
}
