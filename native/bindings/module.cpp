// dmesh._native: the compiled core. Imported only by dmesh/native.py.
#include <nanobind/nanobind.h>

namespace nb = nanobind;

void bind_wdt(nb::module_& m);
void bind_power_diagram(nb::module_& m);
void bind_argmin(nb::module_& m);
void bind_delta(nb::module_& m);
void bind_render(nb::module_& m);
void bind_chamfer(nb::module_& m);
void bind_points(nb::module_& m);
void bind_keys(nb::module_& m);
void bind_mesh(nb::module_& m);

NB_MODULE(_native, m) {
  m.doc() = "DMesh native core (CGAL triangulation, power diagram, argmin searches, renderers, expected Chamfer, point smoothing, face-key sets, patch fairing).";
  bind_wdt(m);
  bind_power_diagram(m);
  bind_argmin(m);
  bind_delta(m);
  bind_render(m);
  bind_chamfer(m);
  bind_points(m);
  bind_keys(m);
  bind_mesh(m);
}
