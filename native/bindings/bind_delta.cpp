// Bindings of the fused Delta kernels (delta_recompute.h): a validated diagram handle, then forward
// (search + distances) and backward per kind of face.
#include <nanobind/nanobind.h>

#include <cstdint>
#include <stdexcept>
#include <string>
#include <utility>

#include "delta_recompute.h"
#include "numpy_out.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

namespace {

// Every entry of a in [lo, hi); the error names the function, the argument and the first bad entry.
void require_range(const char* fn, const char* name, const index_t* a, std::size_t count, long lo, long hi) {
  bool bad = false;
#pragma omp parallel for reduction(|| : bad) if (count > 1000000)
  for (std::int64_t k = 0; k < std::int64_t(count); ++k) bad = bad || a[k] < lo || a[k] >= hi;
  if (!bad) return;
  for (std::size_t k = 0; k < count; ++k) {
    if (a[k] < lo || a[k] >= hi) {
      throw std::invalid_argument(std::string(fn) + ": " + name + " holds " + std::to_string(a[k]) + " at " +
                                  std::to_string(k) + ", outside [" + std::to_string(lo) + ", " +
                                  std::to_string(hi) + ")");
    }
  }
}

void require_csr(const char* fn, const char* name, const In<index_t>& off, const In<index_t>& idx, long rows,
                 long max_value) {
  require(fn, name, off, rows + 1, -1);
  require(fn, name, idx, -1, -1);
  const index_t* o = off.data();
  if (o[0] != 0 || long(o[rows]) != long(idx.shape(0))) {
    throw std::invalid_argument(std::string(fn) + ": " + name + " CSR offsets do not match the indices");
  }
  for (long r = 0; r < rows; ++r) {
    if (o[r + 1] < o[r]) throw std::invalid_argument(std::string(fn) + ": " + name + " offsets decrease");
  }
  require_range(fn, name, idx.data(), idx.shape(0), 0, max_value);
}

void require_threads(const char* fn, int num_threads) {
  if (num_threads < 0 || num_threads > 1024) {
    throw std::invalid_argument(std::string(fn) + ": num_threads must be in [0, 1024], got " +
                                std::to_string(num_threads));
  }
}

// Optional (K, 3) hints: an empty array means "search everywhere"; entries kNone - 1 (search), kNone or
// an id in [0, hi).
const index_t* optional_hint(const char* fn, const In<index_t>& hint, long K, long hi) {
  if (hint.ndim() == 1 && hint.shape(0) == 0) return nullptr;
  require(fn, "hint", hint, K, 3);
  require_range(fn, "hint", hint.data(), hint.size(), kNone - 1, hi);
  return hint.data();
}

// Optional (K,) uint8 mask: an empty array means "all rows".
const std::uint8_t* optional_mask(const char* fn, const In<std::uint8_t>& active, long K) {
  if (active.ndim() == 1 && active.shape(0) == 0 && K != 0) return nullptr;
  require(fn, "active", active, K, -1);
  return active.data();
}

// A power diagram validated once, with its orthocentres recomputed from the points; holds references to
// the arrays it views.
struct DeltaDiagram {
  In<double> points, weights, hull_dirs;
  In<index_t> tets, tet_faces, faces, face_tets, pt_offsets, pt_indices, pf_offsets, pf_indices, nb_offsets,
      nb_indices;
  std::vector<real_t> orthocentres;
  DiagramView view;
};

DeltaDiagram* make_diagram(In<double> points, In<double> weights, In<index_t> tets, In<index_t> tet_faces,
                           In<index_t> faces, In<index_t> face_tets, In<double> hull_dirs, In<index_t> pt_offsets,
                           In<index_t> pt_indices, In<index_t> pf_offsets, In<index_t> pf_indices,
                           In<index_t> nb_offsets, In<index_t> nb_indices, int num_threads) {
  const char* fn = "delta_diagram";
  require_threads(fn, num_threads);
  require(fn, "points", points, -1, 3);
  const long N = long(points.shape(0));
  require(fn, "weights", weights, N, -1);
  require(fn, "tets", tets, -1, 4);
  const long T = long(tets.shape(0));
  require(fn, "tet_faces", tet_faces, T, 4);
  require(fn, "faces", faces, -1, 3);
  const long F = long(faces.shape(0));
  require(fn, "face_tets", face_tets, F, 2);
  require(fn, "hull_dirs", hull_dirs, F, 3);
  require_range(fn, "tets", tets.data(), tets.size(), 0, N);
  require_range(fn, "tet_faces", tet_faces.data(), tet_faces.size(), 0, F);
  require_range(fn, "faces", faces.data(), faces.size(), 0, N);
  require_range(fn, "face_tets", face_tets.data(), face_tets.size(), kNone, T);
  const index_t* ft = face_tets.data();
  for (long f = 0; f < F; ++f) {
    if (ft[2 * f] < 0) {
      throw std::invalid_argument(std::string(fn) + ": face_tets row " + std::to_string(f) +
                                  " has no first tet");
    }
  }
  require_csr(fn, "point_tets", pt_offsets, pt_indices, N, T);
  require_csr(fn, "point_faces", pf_offsets, pf_indices, N, F);
  require_csr(fn, "point_neighbors", nb_offsets, nb_indices, N, N);
  auto* d = new DeltaDiagram{points,   weights,    hull_dirs,  tets,       tet_faces,  faces,      face_tets,
                             pt_offsets, pt_indices, pf_offsets, pf_indices, nb_offsets, nb_indices, {}, {}};
  DiagramView& v = d->view;
  v.points = points.data();
  v.weights = weights.data();
  v.N = index_t(N);
  v.tets = tets.data();
  v.tet_faces = tet_faces.data();
  v.T = index_t(T);
  v.faces = faces.data();
  v.face_tets = face_tets.data();
  v.hull_dirs = hull_dirs.data();
  v.F = index_t(F);
  v.pt_offsets = pt_offsets.data();
  v.pt_indices = pt_indices.data();
  v.pf_offsets = pf_offsets.data();
  v.pf_indices = pf_indices.data();
  v.nb_offsets = nb_offsets.data();
  v.nb_indices = nb_indices.data();
  {
    nb::gil_scoped_release release;
    d->orthocentres = delta_orthocentres(v, num_threads);
  }
  v.orthocentres = d->orthocentres.data();
  return d;
}

}  // namespace

void bind_delta(nb::module_& m) {
  // A DeltaDiagram lives in the autograd graph of the pass that made it; graphs alive at interpreter exit
  // are not collected before nanobind's leak check, which would then report them. Nothing leaks.
  nb::set_leak_warnings(false);
  nb::class_<DeltaDiagram>(m, "DeltaDiagram",
                           "A power diagram validated for the Delta kernels (see delta_diagram).")
      .def_prop_ro("num_points", [](const DeltaDiagram& d) { return long(d.view.N); })
      .def_prop_ro("num_faces", [](const DeltaDiagram& d) { return long(d.view.F); })
      .def_prop_ro(
          "orthocentres",
          [](const DeltaDiagram& d) { return to_numpy(std::vector<real_t>(d.orthocentres), {size_t(d.view.T), 3}); },
          nb::rv_policy::move, "(T, 3) f64 orthocentres recomputed from the points (a copy)");

  m.def("delta_diagram", &make_diagram, nb::arg("points").noconvert(), nb::arg("weights").noconvert(),
        nb::arg("tets").noconvert(), nb::arg("tet_faces").noconvert(), nb::arg("faces").noconvert(),
        nb::arg("face_tets").noconvert(), nb::arg("hull_dirs").noconvert(), nb::arg("pt_offsets").noconvert(),
        nb::arg("pt_indices").noconvert(), nb::arg("pf_offsets").noconvert(), nb::arg("pf_indices").noconvert(),
        nb::arg("nb_offsets").noconvert(), nb::arg("nb_indices").noconvert(), nb::arg("num_threads") = 0,
        nb::rv_policy::take_ownership,
        "delta_diagram(points (N,3) f64, weights (N,) f64, tets (T,4) i32, tet_faces (T,4) i32, faces (F,3) i32,\n"
        "    face_tets (F,2) i32, hull_dirs (F,3) f64, pt_offsets, pt_indices, pf_offsets, pf_indices,\n"
        "    nb_offsets, nb_indices (CSR, i32), num_threads=0) -> DeltaDiagram\n\n"
        "Validates the arrays once (the handle keeps them alive) and recomputes the orthocentres from the\n"
        "points; the Delta kernels take the handle.");

  m.def(
      "orthocentre_backward",
      [](const DeltaDiagram& d, In<double> grad, int num_threads) {
        const char* fn = "orthocentre_backward";
        require_threads(fn, num_threads);
        require(fn, "grad", grad, d.view.T, 3);
        PointGradient g;
        {
          nb::gil_scoped_release release;
          g = orthocentre_adjoint(d.view, grad.data(), num_threads);
        }
        const size_t N = size_t(d.view.N);
        return nb::make_tuple(to_numpy(std::move(g.points), {N, 3}), to_numpy(std::move(g.weights), {N}));
      },
      nb::arg("diagram"), nb::arg("grad").noconvert(), nb::arg("num_threads") = 0,
      "orthocentre_backward(diagram, grad (T,3) f64, num_threads=0)\n"
      "    -> (grad_points (N,3) f64, grad_weights (N,) f64)\n\n"
      "Gradient of sum(grad * diagram.orthocentres) (no gradient through clamped, degenerate tets).");

  m.def(
      "existing_delta_forward",
      [](const DeltaDiagram& d, In<index_t> face_ids, In<index_t> cache_offsets, In<index_t> cache_indices,
         double ray_length, In<index_t> hint, int num_threads) {
        const char* fn = "existing_delta_forward";
        require_threads(fn, num_threads);
        require(fn, "face_ids", face_ids, -1, -1);
        const long K = long(face_ids.shape(0));
        require_range(fn, "face_ids", face_ids.data(), face_ids.size(), 0, d.view.F);
        require_csr(fn, "cache", cache_offsets, cache_indices, d.view.N, d.view.N);
        const index_t* h = optional_hint(fn, hint, K, d.view.N);
        ExistingDeltaResult r;
        {
          nb::gil_scoped_release release;
          r = existing_delta_forward(d.view, face_ids.data(), index_t(K), cache_offsets.data(),
                                     cache_indices.data(), ray_length, h, num_threads);
        }
        return nb::make_tuple(to_numpy(std::move(r.neighbour), {size_t(K), 3}),
                              to_numpy(std::move(r.dist), {size_t(K), 3}));
      },
      nb::arg("diagram"), nb::arg("face_ids").noconvert(), nb::arg("cache_offsets").noconvert(),
      nb::arg("cache_indices").noconvert(), nb::arg("ray_length"), nb::arg("hint").noconvert(),
      nb::arg("num_threads") = 0,
      "existing_delta_forward(diagram, face_ids (K,) i32, cache_offsets (N+1,) i32, cache_indices (M,) i32,\n"
      "    ray_length, hint (K,3) i32 or empty, num_threads=0) -> (neighbour (K,3) i32, dist (K,3) f64)\n\n"
      "Per WDT face and vertex, the nearest cached bisector plane to the dual-edge sample and its distance\n"
      "(-1 and ray_length where none). A hint other than -2 is used instead of searching.");

  m.def(
      "existing_delta_backward",
      [](const DeltaDiagram& d, In<index_t> face_ids, In<index_t> neighbour, In<double> grad,
         In<std::uint8_t> active, double ray_length, int num_threads) {
        const char* fn = "existing_delta_backward";
        require_threads(fn, num_threads);
        require(fn, "face_ids", face_ids, -1, -1);
        const long K = long(face_ids.shape(0));
        require_range(fn, "face_ids", face_ids.data(), face_ids.size(), 0, d.view.F);
        require(fn, "neighbour", neighbour, K, 3);
        require_range(fn, "neighbour", neighbour.data(), neighbour.size(), kNone, d.view.N);
        require(fn, "grad", grad, K, 3);
        const std::uint8_t* mask = optional_mask(fn, active, K);
        PointGradient g;
        {
          nb::gil_scoped_release release;
          g = existing_delta_backward(d.view, face_ids.data(), index_t(K), neighbour.data(), grad.data(), mask,
                                      ray_length, num_threads);
        }
        const size_t N = size_t(d.view.N);
        return nb::make_tuple(to_numpy(std::move(g.points), {N, 3}), to_numpy(std::move(g.weights), {N}));
      },
      nb::arg("diagram"), nb::arg("face_ids").noconvert(), nb::arg("neighbour").noconvert(),
      nb::arg("grad").noconvert(), nb::arg("active").noconvert(), nb::arg("ray_length"),
      nb::arg("num_threads") = 0,
      "existing_delta_backward(diagram, face_ids (K,) i32, neighbour (K,3) i32, grad (K,3) f64,\n"
      "    active (K,) u8 or empty (all rows), ray_length, num_threads=0)\n"
      "    -> (grad_points (N,3) f64, grad_weights (N,) f64)");

  m.def(
      "candidate_delta_forward",
      [](const DeltaDiagram& d, In<index_t> cand, double ray_length, In<index_t> hint, int num_threads) {
        const char* fn = "candidate_delta_forward";
        require_threads(fn, num_threads);
        require(fn, "cand", cand, -1, 3);
        const long C = long(cand.shape(0));
        require_range(fn, "cand", cand.data(), cand.size(), 0, d.view.N);
        const index_t* h = optional_hint(fn, hint, C, d.view.F);
        CandidateDeltaResult r;
        {
          nb::gil_scoped_release release;
          r = candidate_delta_forward(d.view, cand.data(), index_t(C), ray_length, h, num_threads);
        }
        return nb::make_tuple(to_numpy(std::move(r.edge), {size_t(C), 3}),
                              to_numpy(std::move(r.crosses), {size_t(C), 3}),
                              to_numpy(std::move(r.dist), {size_t(C), 3}));
      },
      nb::arg("diagram"), nb::arg("cand").noconvert(), nb::arg("ray_length"), nb::arg("hint").noconvert(),
      nb::arg("num_threads") = 0,
      "candidate_delta_forward(diagram, cand (C,3) i32, ray_length, hint (C,3) i32 or empty, num_threads=0)\n"
      "    -> (edge (C,3) i32, crosses (C,3) u8, dist (C,3) f64)\n\n"
      "Per candidate face and vertex, the distance between the face's dual line and the vertex's power cell:\n"
      "0 where the line crosses it, else to the nearest cell edge (its WDT face id in `edge`); -1 and\n"
      "ray_length for collinear candidates or vertices without a cell edge. A hint other than -2 is measured\n"
      "instead of searching the cell's edges (the crossing test always runs).");

  m.def(
      "csr_rows_changed",
      [](In<index_t> off_a, In<index_t> idx_a, In<index_t> off_b, In<index_t> idx_b) {
        const char* fn = "csr_rows_changed";
        require(fn, "off_a", off_a, -1, -1);
        const long rows = long(off_a.shape(0)) - 1;
        if (rows < 0) throw std::invalid_argument("csr_rows_changed: off_a must have at least one entry");
        require(fn, "off_b", off_b, rows + 1, -1);
        for (const auto* pair : {&off_a, &off_b}) {
          const index_t* o = pair->data();
          if (o[0] != 0) throw std::invalid_argument("csr_rows_changed: offsets must start at 0");
          for (long r = 0; r < rows; ++r) {
            if (o[r + 1] < o[r]) throw std::invalid_argument("csr_rows_changed: offsets decrease");
          }
        }
        if (long(off_a.data()[rows]) != long(idx_a.shape(0)) || long(off_b.data()[rows]) != long(idx_b.shape(0))) {
          throw std::invalid_argument("csr_rows_changed: CSR offsets do not match the indices");
        }
        std::vector<std::uint8_t> out;
        {
          nb::gil_scoped_release release;
          out = csr_rows_changed(off_a.data(), idx_a.data(), off_b.data(), idx_b.data(), index_t(rows));
        }
        return to_numpy(std::move(out), {size_t(rows)});
      },
      nb::arg("off_a").noconvert(), nb::arg("idx_a").noconvert(), nb::arg("off_b").noconvert(),
      nb::arg("idx_b").noconvert(),
      "csr_rows_changed(off_a, idx_a, off_b, idx_b) -> (rows,) u8: 1 where the two CSR lists' rows differ.");

  m.def(
      "candidate_delta_backward",
      [](const DeltaDiagram& d, In<index_t> cand, In<index_t> edge, In<std::uint8_t> crosses, In<double> grad,
         In<std::uint8_t> active, int num_threads) {
        const char* fn = "candidate_delta_backward";
        require_threads(fn, num_threads);
        require(fn, "cand", cand, -1, 3);
        const long C = long(cand.shape(0));
        require_range(fn, "cand", cand.data(), cand.size(), 0, d.view.N);
        require(fn, "edge", edge, C, 3);
        require_range(fn, "edge", edge.data(), edge.size(), kNone, d.view.F);
        require(fn, "crosses", crosses, C, 3);
        require(fn, "grad", grad, C, 3);
        const std::uint8_t* mask = optional_mask(fn, active, C);
        PointGradient g;
        {
          nb::gil_scoped_release release;
          g = candidate_delta_backward(d.view, cand.data(), index_t(C), edge.data(), crosses.data(), grad.data(),
                                       mask, num_threads);
        }
        const size_t N = size_t(d.view.N);
        return nb::make_tuple(to_numpy(std::move(g.points), {N, 3}), to_numpy(std::move(g.weights), {N}));
      },
      nb::arg("diagram"), nb::arg("cand").noconvert(), nb::arg("edge").noconvert(), nb::arg("crosses").noconvert(),
      nb::arg("grad").noconvert(), nb::arg("active").noconvert(), nb::arg("num_threads") = 0,
      "candidate_delta_backward(diagram, cand (C,3) i32, edge (C,3) i32, crosses (C,3) u8, grad (C,3) f64,\n"
      "    active (C,) u8 or empty (all rows), num_threads=0) -> (grad_points (N,3) f64, grad_weights (N,) f64)");
}
