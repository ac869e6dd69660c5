#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include <cstdint>

#include "hole_fairing.h"
#include "numpy_out.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

void bind_mesh(nb::module_& m) {
  m.def(
      "refine_and_fair",
      [](In<double> vertices, In<index_t> faces, In<std::uint8_t> patch, double density, int continuity,
         In<std::uint8_t> hold) {
        require("refine_and_fair", "vertices", vertices, -1, 3);
        require("refine_and_fair", "faces", faces, -1, 3);
        require("refine_and_fair", "patch", patch, long(faces.shape(0)), -1);
        require("refine_and_fair", "hold", hold, long(vertices.shape(0)), -1);
        FairedMesh out;
        {
          nb::gil_scoped_release release;
          out = refine_and_fair(vertices.data(), index_t(vertices.shape(0)), faces.data(), index_t(faces.shape(0)),
                                patch.data(), density, continuity, hold.data());
        }
        const size_t nv = out.vertices.size() / 3, nf = out.patch.size();
        return std::make_tuple(to_numpy(std::move(out.vertices), {nv, 3}), to_numpy(std::move(out.faces), {nf, 3}),
                               to_numpy(std::move(out.patch), {nf}), out.faired);
      },
      nb::arg("vertices").noconvert(), nb::arg("faces").noconvert(), nb::arg("patch").noconvert(),
      nb::arg("density"), nb::arg("continuity"), nb::arg("hold").noconvert(),
      "refine_and_fair(vertices: (V,3) float64, faces: (F,3) int32, patch: (F,) uint8, density: float,\n"
      "continuity: int, hold: (V,) uint8) -> ((V',3) float64, (F',3) int32, (F',) uint8, bool)\n\n"
      "CGAL's Polygon_mesh_processing::refine of the patch faces, then fair of every vertex with only patch\n"
      "faces around it and not held; the input vertices keep their indices, new ones follow. The bool: fairing\n"
      "solved.");
}
