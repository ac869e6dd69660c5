#include <nanobind/nanobind.h>

#include <stdexcept>
#include <string>

#include "argmin_search.h"
#include "numpy_out.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

namespace {


template <class T>
void require_csr(const char* fn, const In<index_t>& off, const In<index_t>& idx, long rows, long max_value) {
  require(fn, "offsets", off, rows + 1, -1);
  require(fn, "indices", idx, -1, -1);
  const index_t* o = off.data();
  if (o[0] != 0 || long(o[rows]) != long(idx.shape(0))) {
    throw std::invalid_argument(std::string(fn) + ": CSR offsets do not match the indices");
  }
  const index_t* ix = idx.data();
  for (size_t k = 0; k < idx.shape(0); ++k) {
    if (ix[k] < 0 || ix[k] >= max_value) {
      throw std::invalid_argument(std::string(fn) + ": CSR index " + std::to_string(ix[k]) + " out of range");
    }
  }
}

template <class T>
void require_index_range(const char* fn, const char* name, const In<T>& a, long n) {
  const T* d = a.data();
  for (size_t k = 0; k < a.size(); ++k) {
    if (d[k] < 0 || d[k] >= n) {
      throw std::invalid_argument(std::string(fn) + ": " + name + " holds " + std::to_string(d[k]) +
                                  ", outside [0, " + std::to_string(n) + ")");
    }
  }
}

}  // namespace

void bind_argmin(nb::module_& m) {
  m.def(
      "nearest_planes",
      [](In<double> points, In<double> weights, In<index_t> faces, In<double> samples, In<index_t> nbr_offsets,
         In<index_t> nbr_indices) {
        const char* fn = "nearest_planes";
        require(fn, "points", points, -1, 3);
        const long N = long(points.shape(0));
        require(fn, "weights", weights, N, -1);
        require(fn, "faces", faces, -1, 3);
        const long F = long(faces.shape(0));
        require(fn, "samples", samples, F, 3);
        require_index_range(fn, "faces", faces, N);
        require_csr<index_t>(fn, nbr_offsets, nbr_indices, N, N);
        NearestPlaneResult out;
        {
          nb::gil_scoped_release release;
          out = nearest_planes(points.data(), weights.data(), index_t(N), faces.data(), samples.data(),
                               index_t(F), nbr_offsets.data(), nbr_indices.data());
        }
        return nb::make_tuple(to_numpy(std::move(out.neighbour), {size_t(F), 3}),
                              to_numpy(std::move(out.dist), {size_t(F), 3}));
      },
      nb::arg("points").noconvert(), nb::arg("weights").noconvert(), nb::arg("faces").noconvert(),
      nb::arg("samples").noconvert(), nb::arg("nbr_offsets").noconvert(), nb::arg("nbr_indices").noconvert(),
      "nearest_planes(points (N,3) f64, weights (N,) f64, faces (F,3) i32, samples (F,3) f64,\n"
      "               nbr_offsets (N+1,) i32, nbr_indices (M,) i32) -> (neighbour (F,3) i32, dist (F,3) f64)\n\n"
      "Per face and vertex i, the neighbour j (not in the face) whose bisector plane is nearest to the\n"
      "face's sample point; -1 where there is none.");

  m.def(
      "nearest_cell_edges",
      [](In<double> points, In<double> weights, In<index_t> faces, In<double> line_origin, In<double> line_dir,
         In<index_t> pf_offsets, In<index_t> pf_indices, In<double> edge_start, In<double> edge_end,
         In<std::uint8_t> is_ray, In<index_t> nbr_offsets, In<index_t> nbr_indices) {
        const char* fn = "nearest_cell_edges";
        require(fn, "points", points, -1, 3);
        const long N = long(points.shape(0));
        require(fn, "weights", weights, N, -1);
        require(fn, "faces", faces, -1, 3);
        const long C = long(faces.shape(0));
        require(fn, "line_origin", line_origin, C, 3);
        require(fn, "line_dir", line_dir, C, 3);
        require(fn, "edge_start", edge_start, -1, 3);
        const long E = long(edge_start.shape(0));
        require(fn, "edge_end", edge_end, E, 3);
        require(fn, "is_ray", is_ray, E, -1);
        require_index_range(fn, "faces", faces, N);
        require_csr<index_t>(fn, pf_offsets, pf_indices, N, E);
        require_csr<index_t>(fn, nbr_offsets, nbr_indices, N, N);
        CellEdgeResult r;
        {
          nb::gil_scoped_release release;
          r = nearest_cell_edges(points.data(), weights.data(), index_t(N), faces.data(), line_origin.data(),
                                 line_dir.data(), index_t(C), pf_offsets.data(), pf_indices.data(),
                                 edge_start.data(), edge_end.data(), is_ray.data(), nbr_offsets.data(),
                                 nbr_indices.data());
        }
        return nb::make_tuple(to_numpy(std::move(r.edge), {size_t(C), 3}),
                              to_numpy(std::move(r.crosses), {size_t(C), 3}),
                              to_numpy(std::move(r.dist), {size_t(C), 3}));
      },
      nb::arg("points").noconvert(), nb::arg("weights").noconvert(), nb::arg("faces").noconvert(),
      nb::arg("line_origin").noconvert(), nb::arg("line_dir").noconvert(), nb::arg("pf_offsets").noconvert(),
      nb::arg("pf_indices").noconvert(), nb::arg("edge_start").noconvert(), nb::arg("edge_end").noconvert(),
      nb::arg("is_ray").noconvert(), nb::arg("nbr_offsets").noconvert(), nb::arg("nbr_indices").noconvert(),
      "nearest_cell_edges(points, weights, faces (C,3) i32, line_origin (C,3) f64, line_dir (C,3) f64,\n"
      "                   pf_offsets, pf_indices, edge_start (E,3) f64, edge_end (E,3) f64, is_ray (E,) u8,\n"
      "                   nbr_offsets, nbr_indices) -> (edge (C,3) i32, crosses (C,3) u8, dist (C,3) f64)\n\n"
      "Per candidate face and vertex: 1 in `crosses` where the dual line passes through the vertex's power\n"
      "cell (distance 0), else the id of the cell's nearest edge (-1 if the cell has none).");

  m.def(
      "merge_csr",
      [](In<index_t> off_a, In<index_t> idx_a, In<index_t> off_b, In<index_t> idx_b) {
        if (off_a.ndim() != 1 || off_b.ndim() != 1 || off_a.shape(0) != off_b.shape(0) || off_a.shape(0) == 0) {
          throw std::invalid_argument("merge_csr: offsets must be 1-D with the same number of rows");
        }
        const index_t rows = index_t(off_a.shape(0) - 1);
        if (long(off_a.data()[rows]) != long(idx_a.shape(0)) || long(off_b.data()[rows]) != long(idx_b.shape(0))) {
          throw std::invalid_argument("merge_csr: CSR offsets do not match the indices");
        }
        Csr c;
        {
          nb::gil_scoped_release release;
          c = merge_csr(off_a.data(), idx_a.data(), off_b.data(), idx_b.data(), rows);
        }
        const size_t r1 = c.offsets.size(), nnz = c.indices.size();
        return nb::make_tuple(to_numpy(std::move(c.offsets), {r1}), to_numpy(std::move(c.indices), {nnz}));
      },
      nb::arg("off_a").noconvert(), nb::arg("idx_a").noconvert(), nb::arg("off_b").noconvert(),
      nb::arg("idx_b").noconvert(),
      "merge_csr(off_a, idx_a, off_b, idx_b) -> (offsets, indices): row-wise sorted union of two CSR lists.");
}
