// Bindings of the CPU renderers (soft_render.h, tet_render.h).
#include <nanobind/nanobind.h>

#include <cmath>
#include <stdexcept>
#include <string>

#include "numpy_out.h"
#include "soft_render.h"
#include "tet_render.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

namespace {


void require_image(const char* fn, const char* name, const In<float>& a, index_t H, index_t W) {
  if (a.ndim() != 2 || long(a.shape(0)) != H || long(a.shape(1)) != W) {
    throw std::invalid_argument(std::string(fn) + ": " + name + " must have shape (" + std::to_string(H) + ", " +
                                std::to_string(W) + ")");
  }
}

RenderCamera make_camera(const char* fn, const In<double>& w2c, double fov_y, long height, long width,
                         double near) {
  if (w2c.ndim() != 2 || w2c.shape(0) != 4 || w2c.shape(1) != 4) {
    throw std::invalid_argument(std::string(fn) + ": world_to_camera must have shape (4, 4)");
  }
  RenderCamera cam;
  for (int k = 0; k < 16; ++k) cam.world_to_camera[k] = w2c.data()[k];
  cam.fov_y = fov_y;
  cam.height = index_t(height);
  cam.width = index_t(width);
  cam.near = near;
  if (height < 1 || width < 1 || height > 16384 || width > 16384) {
    throw std::invalid_argument(std::string(fn) + ": height and width must be in [1, 16384]");
  }
  return cam;
}

}  // namespace

void bind_render(nb::module_& m) {
  m.def(
      "soft_render_forward",
      [](In<float> verts, In<index_t> faces, In<float> opacity, In<double> world_to_camera, double fov_y,
         long height, long width, double near, double edge_width, double min_opacity, double t_min,
         int num_threads) {
        const char* fn = "soft_render_forward";
        require(fn, "verts", verts, -1, 3);
        require(fn, "faces", faces, -1, 3);
        const long F = long(faces.shape(0));
        require(fn, "opacity", opacity, F, -1);
        const RenderCamera cam = make_camera(fn, world_to_camera, fov_y, height, width, near);
        SoftRenderSettings s{edge_width, min_opacity, t_min, num_threads};
        SoftRenderResult r;
        {
          nb::gil_scoped_release release;
          r = soft_render_forward(verts.data(), index_t(verts.shape(0)), faces.data(), index_t(F), opacity.data(),
                                  cam, s);
        }
        const size_t H = size_t(height), W = size_t(width), K = r.frag_face.size();
        nb::dict stats;
        stats["num_drawn"] = r.num_drawn;
        stats["num_bins"] = r.num_bins;
        stats["num_scanned"] = r.num_scanned;
        stats["num_tested"] = r.num_tested;
        stats["num_fragments"] = std::int64_t(K);
        return nb::make_tuple(to_numpy(std::move(r.diffuse), {H, W}), to_numpy(std::move(r.depth), {H, W}),
                              to_numpy(std::move(r.alpha), {H, W}), to_numpy(std::move(r.frag_face), {K}),
                              to_numpy(std::move(r.pix_range), {H, W, 2}), stats);
      },
      nb::arg("verts").noconvert(), nb::arg("faces").noconvert(), nb::arg("opacity").noconvert(),
      nb::arg("world_to_camera").noconvert(), nb::arg("fov_y"), nb::arg("height"), nb::arg("width"),
      nb::arg("near"), nb::arg("edge_width"), nb::arg("min_opacity"), nb::arg("t_min"), nb::arg("num_threads"),
      "soft_render_forward(verts (N,3) f32, faces (F,3) i32, opacity (F,) f32, world_to_camera (4,4) f64,\n"
      "                    fov_y (radians), height, width, near, edge_width, min_opacity, t_min, num_threads)\n"
      "  -> (diffuse (H,W) f32, depth (H,W) f32, alpha (H,W) f32, frag_face (K,) i32, pix_range (H,W,2) i32,\n"
      "      stats dict)\n\n"
      "Soft tile rasteriser with exact per-pixel depth order (model in native/src/soft_render.h).\n"
      "frag_face lists each pixel's composited faces front to back, from pix_range[i, j, 0], count\n"
      "pix_range[i, j, 1]; the backward call takes them back.");

  m.def(
      "soft_render_backward",
      [](In<float> verts, In<index_t> faces, In<float> opacity, In<double> world_to_camera, double fov_y,
         long height, long width, double near, double edge_width, double min_opacity, double t_min,
         int num_threads, In<index_t> frag_face, In<index_t> pix_range, In<float> grad_diffuse,
         In<float> grad_depth, In<float> grad_alpha) {
        const char* fn = "soft_render_backward";
        require(fn, "verts", verts, -1, 3);
        require(fn, "faces", faces, -1, 3);
        const long F = long(faces.shape(0));
        require(fn, "opacity", opacity, F, -1);
        require(fn, "frag_face", frag_face, -1, -1);
        const RenderCamera cam = make_camera(fn, world_to_camera, fov_y, height, width, near);
        if (pix_range.ndim() != 3 || long(pix_range.shape(0)) != height || long(pix_range.shape(1)) != width ||
            pix_range.shape(2) != 2) {
          throw std::invalid_argument(std::string(fn) + ": pix_range must have shape (height, width, 2)");
        }
        require_image(fn, "grad_diffuse", grad_diffuse, cam.height, cam.width);
        require_image(fn, "grad_depth", grad_depth, cam.height, cam.width);
        require_image(fn, "grad_alpha", grad_alpha, cam.height, cam.width);
        SoftRenderSettings s{edge_width, min_opacity, t_min, num_threads};
        SoftRenderGrad g;
        {
          nb::gil_scoped_release release;
          g = soft_render_backward(verts.data(), index_t(verts.shape(0)), faces.data(), index_t(F), opacity.data(),
                                   cam, s, frag_face.data(), std::int64_t(frag_face.shape(0)), pix_range.data(),
                                   grad_diffuse.data(), grad_depth.data(), grad_alpha.data());
        }
        return nb::make_tuple(to_numpy(std::move(g.grad_verts), {size_t(verts.shape(0)), 3}),
                              to_numpy(std::move(g.grad_opacity), {size_t(F)}));
      },
      nb::arg("verts").noconvert(), nb::arg("faces").noconvert(), nb::arg("opacity").noconvert(),
      nb::arg("world_to_camera").noconvert(), nb::arg("fov_y"), nb::arg("height"), nb::arg("width"),
      nb::arg("near"), nb::arg("edge_width"), nb::arg("min_opacity"), nb::arg("t_min"), nb::arg("num_threads"),
      nb::arg("frag_face").noconvert(), nb::arg("pix_range").noconvert(), nb::arg("grad_diffuse").noconvert(),
      nb::arg("grad_depth").noconvert(), nb::arg("grad_alpha").noconvert(),
      "soft_render_backward(<forward inputs>, frag_face (K,) i32, pix_range (H,W,2) i32, grad_diffuse (H,W) f32,\n"
      "                     grad_depth (H,W) f32, grad_alpha (H,W) f32) -> (grad_verts (N,3) f32,\n"
      "                     grad_opacity (F,) f32)");

  m.def(
      "tet_render_forward",
      [](In<float> verts, In<index_t> tets, In<index_t> faces, In<index_t> face_tets, In<float> opacity,
         In<double> world_to_camera, double fov_y, long height, long width, double near, double min_opacity,
         double t_min, int num_threads) {
        const char* fn = "tet_render_forward";
        require(fn, "verts", verts, -1, 3);
        require(fn, "tets", tets, -1, 4);
        require(fn, "faces", faces, -1, 3);
        const long F = long(faces.shape(0));
        require(fn, "face_tets", face_tets, F, 2);
        require(fn, "opacity", opacity, F, -1);
        const RenderCamera cam = make_camera(fn, world_to_camera, fov_y, height, width, near);
        TetRenderSettings s{min_opacity, t_min, num_threads};
        TetRenderResult r;
        {
          nb::gil_scoped_release release;
          r = tet_render_forward(verts.data(), index_t(verts.shape(0)), tets.data(), index_t(tets.shape(0)),
                                 faces.data(), face_tets.data(), index_t(F), opacity.data(), cam, s);
        }
        const size_t H = size_t(height), W = size_t(width), K = r.frag_face.size();
        nb::dict stats;
        stats["num_steps"] = r.num_steps;
        stats["num_fragments"] = std::int64_t(K);
        return nb::make_tuple(to_numpy(std::move(r.diffuse), {H, W}), to_numpy(std::move(r.depth), {H, W}),
                              to_numpy(std::move(r.alpha), {H, W}), to_numpy(std::move(r.frag_face), {K}),
                              to_numpy(std::move(r.frag_diffuse), {K}), to_numpy(std::move(r.frag_depth), {K}),
                              to_numpy(std::move(r.pix_range), {H, W, 2}), stats);
      },
      nb::arg("verts").noconvert(), nb::arg("tets").noconvert(), nb::arg("faces").noconvert(),
      nb::arg("face_tets").noconvert(), nb::arg("opacity").noconvert(), nb::arg("world_to_camera").noconvert(),
      nb::arg("fov_y"), nb::arg("height"), nb::arg("width"), nb::arg("near"), nb::arg("min_opacity"),
      nb::arg("t_min"), nb::arg("num_threads"),
      "tet_render_forward(verts (N,3) f32, tets (T,4) i32, faces (F,3) i32, face_tets (F,2) i32, opacity (F,) f32,\n"
      "                   world_to_camera (4,4) f64, fov_y, height, width, near, min_opacity, t_min, num_threads)\n"
      "  -> (diffuse, depth, alpha (H,W) f32, frag_face (K,) i32, frag_diffuse (K,) f32, frag_depth (K,) f32,\n"
      "      pix_range (H,W,2) i32, stats dict)\n\n"
      "Walks each pixel ray through the tetrahedralisation (model in native/src/tet_render.h).");

  m.def(
      "tet_render_backward",
      [](In<float> opacity, In<index_t> frag_face, In<float> frag_diffuse, In<float> frag_depth,
         In<index_t> pix_range, In<float> grad_diffuse, In<float> grad_depth, In<float> grad_alpha,
         int num_threads) {
        const char* fn = "tet_render_backward";
        require(fn, "opacity", opacity, -1, -1);
        require(fn, "frag_face", frag_face, -1, -1);
        const long K = long(frag_face.shape(0));
        require(fn, "frag_diffuse", frag_diffuse, K, -1);
        require(fn, "frag_depth", frag_depth, K, -1);
        if (pix_range.ndim() != 3 || pix_range.shape(2) != 2) {
          throw std::invalid_argument(std::string(fn) + ": pix_range must have shape (H, W, 2)");
        }
        const index_t H = index_t(pix_range.shape(0)), W = index_t(pix_range.shape(1));
        require_image(fn, "grad_diffuse", grad_diffuse, H, W);
        require_image(fn, "grad_depth", grad_depth, H, W);
        require_image(fn, "grad_alpha", grad_alpha, H, W);
        TetRenderSettings s;
        s.num_threads = num_threads;
        std::vector<float> g;
        {
          nb::gil_scoped_release release;
          g = tet_render_backward(opacity.data(), index_t(opacity.shape(0)), frag_face.data(), frag_diffuse.data(),
                                  frag_depth.data(), K, pix_range.data(), H, W, grad_diffuse.data(),
                                  grad_depth.data(), grad_alpha.data(), s);
        }
        const size_t F = g.size();
        return to_numpy(std::move(g), {F});
      },
      nb::arg("opacity").noconvert(), nb::arg("frag_face").noconvert(), nb::arg("frag_diffuse").noconvert(),
      nb::arg("frag_depth").noconvert(), nb::arg("pix_range").noconvert(), nb::arg("grad_diffuse").noconvert(),
      nb::arg("grad_depth").noconvert(), nb::arg("grad_alpha").noconvert(), nb::arg("num_threads"),
      "tet_render_backward(opacity (F,) f32, frag_face (K,) i32, frag_diffuse (K,) f32, frag_depth (K,) f32,\n"
      "                    pix_range (H,W,2) i32, grad_diffuse, grad_depth, grad_alpha (H,W) f32, num_threads)\n"
      "  -> grad_opacity (F,) f32");
}
