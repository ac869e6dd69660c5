// Soft tile rasteriser of semi-transparent triangles (DESIGN.md section 7, phase 1), forward and backward.
//
// Letters: N vertices, F faces, H x W pixels, K stored fragments (all pixels together).
//
// Conventions (those of datasets/capture.py): an OpenGL camera looking down -Z; pixel (i, j), row i from
// the top, samples the ray through its centre, camera-space direction d_ij = (x_ndc t_x, y_ndc t_y, -1)
// with t_y = tan(fov_y / 2), t_x = t_y W / H, x_ndc = 2 (j + 0.5) / W - 1, y_ndc = 1 - 2 (i + 0.5) / H.
// Continuous screen coordinates (u, v) put pixel (i, j)'s centre at (j + 0.5, i + 0.5); a pixel is 1 x 1.
//
// Per face f and pixel p:
//   coverage  cov = S(clamp(1 - dist(p, tri_f) / w, 0, 1)), S(s) = 3 s^2 - 2 s^3 (smoothstep), where dist
//             is the screen distance (pixels) from the pixel centre to the projected triangle (0 inside)
//             and w = edge_width: 1 inside, falling smoothly to 0 at w pixels outside the edges. The band
//             lies outside the triangle only, so an opaque closed surface has no cracks along its inner
//             edges; its silhouette grows by w/2 pixel on average.
//   alpha     a = opacity_f * cov
//   diffuse   c = |n_f . d_p| / (|n_f| |d_p|), flat face normal; a zero-area face (|n_f| <= 1e-12 |e1| |e2|)
//             has c = 0 and depth = its zmax
//   depth     z = the ray-plane depth (-z_cam of the hit on the face's plane) clamped into the face's
//             [min, max] vertex depth (so fragments outside the triangle stay inside its depth range).
// Fragments are composited front to back in per-pixel depth order (exact per pixel; see the sort key below):
//   C += c a T, Z += z a T, T *= (1 - a), stopping before a fragment when T < t_min (1e-4);
// outputs diffuse = C, depth = Z (not normalised by alpha: background 0, like the capture's depth),
// alpha = 1 - T.
//
// Exact ordering with early stop: faces are sorted once by their minimum vertex depth zmin (ties by id)
// and binned in that order, so each 16x16 tile's list (the faces whose band-grown screen bounding box
// touches it) is sorted by zmin; a tile splits its list into per-row lists. A pixel walks its row's list
// in order and keeps the covering fragments in a small priority queue keyed by depth (band fragments,
// cov < 1, are keyed one depth extent back, z + zmax - zmin, so that on a closed surface the face that
// covers the pixel centre is composited before its neighbours' bands); a fragment is composited once
// the next listed face's zmin is not smaller than its key (no later face can come in front of it). So
// the pixel stops as soon as T < t_min without visiting the rest of the list. The keys, not the output
// depths, decide the order; ties go to the smaller face id.
//
// Each row of a tile walks its list once for its 16 pixels together; a pixel only looks at the listed faces
// whose span in the row (narrowed by the face's edge lines) holds it, and compositing at exactly the
// points described above.
//
// Threads: tiles (forward) and blocks of 8 rows (backward) are shared among `num_threads` std::threads.
// Results are bit-for-bit the same for any thread count and schedule: every pixel's outputs and fragment
// list are computed by one thread, and the backward sums each block's gradients into records of that
// block, which a final pass adds in block order. The face and bin arrays (about 350 bytes per face) are
// kept per calling thread between calls, so repeated calls do not pay the page faults of fresh allocations.
//
// Faces with opacity <= min_opacity, with a vertex nearer than `near` to the camera plane, or with a
// non-finite vertex are not drawn (and get no gradient).
#pragma once
#include <cstdint>
#include <vector>

#include "types.h"

namespace dmesh {

// One pinhole camera (OpenGL conventions above).
struct RenderCamera {
  double world_to_camera[16];  // row-major 4x4 (the last row is ignored)
  double fov_y;                // vertical field of view, radians, in (0, pi)
  index_t height;              // H >= 1
  index_t width;               // W >= 1
  double near;                 // faces with a vertex at depth < near are culled, > 0
};

struct SoftRenderSettings {
  double edge_width = 1.0;     // w, width (pixels) of the soft band outside each triangle, > 0
  double min_opacity = 1e-3;   // faces with opacity <= this are skipped
  double t_min = 1e-4;         // early stop: a pixel stops once its transmittance is below this
  int num_threads = 0;         // 0: std::thread::hardware_concurrency()
};

struct SoftRenderResult {
  std::vector<float> diffuse;      // (H, W)
  std::vector<float> depth;        // (H, W)
  std::vector<float> alpha;        // (H, W)
  std::vector<index_t> frag_face;  // (K,) face id of every composited fragment, per pixel front to back
  std::vector<index_t> pix_range;  // (H, W, 2) start in frag_face and count, per pixel
  std::int64_t num_drawn = 0;      // faces drawn (after culling)
  std::int64_t num_bins = 0;       // (face, tile) pairs
  std::int64_t num_scanned = 0;    // tile-list entries visited by pixels, all pixels together
  std::int64_t num_tested = 0;     // of those, coverage tests (the pixel lies in the face's box)
};

// verts (N, 3) float32 world space; faces (F, 3) int32 into verts; opacity (F,) float32 in [0, 1].
// Throws std::invalid_argument on bad camera or settings (indices are checked by the binding).
SoftRenderResult soft_render_forward(const float* verts, index_t N, const index_t* faces, index_t F,
                                     const float* opacity, const RenderCamera& cam,
                                     const SoftRenderSettings& s);

struct SoftRenderGrad {
  std::vector<float> grad_verts;    // (N, 3) world space
  std::vector<float> grad_opacity;  // (F,)
};

// Gradients of sum(grad_diffuse * diffuse + grad_depth * depth + grad_alpha * alpha) with respect to the
// vertex positions and the face opacities, for the fragments stored by the forward call with the same
// inputs (frag_face (K,), pix_range (H, W, 2)). grad_* are (H, W) float32.
SoftRenderGrad soft_render_backward(const float* verts, index_t N, const index_t* faces, index_t F,
                                    const float* opacity, const RenderCamera& cam, const SoftRenderSettings& s,
                                    const index_t* frag_face, std::int64_t K, const index_t* pix_range,
                                    const float* grad_diffuse, const float* grad_depth,
                                    const float* grad_alpha);

namespace render_detail {
// Shared by both renderers: camera-space rotation/translation and the screen mapping.
struct View {
  double R[9], t[3];
  double f;          // pixels per unit of x/(-z) (square pixels)
  double cx, cy;     // W / 2, H / 2
  index_t H, W;
  double near;
  // camera-space direction (z = -1) of the ray through screen point (u, v)
  void ray(double u, double v, double d[3]) const {
    d[0] = (u - cx) / f;
    d[1] = -(v - cy) / f;
    d[2] = -1.0;
  }
  void to_camera(const float* x, double p[3]) const {
    for (int r = 0; r < 3; ++r)
      p[r] = R[3 * r] * double(x[0]) + R[3 * r + 1] * double(x[1]) + R[3 * r + 2] * double(x[2]) + t[r];
  }
};
View make_view(const RenderCamera& cam, const char* fn);
int thread_count(int requested);
// Runs body(item) for item in [0, n) on `threads` std::threads (dynamic scheduling); body(item, thread).
template <class Body>
void parallel_for(std::int64_t n, int threads, Body&& body);
}  // namespace render_detail

}  // namespace dmesh

#include <algorithm>
#include <atomic>
#include <thread>

namespace dmesh::render_detail {
// Shared by the soft and the tetrahedral renderer: screen tile side and small vector helpers.
constexpr int kTile = 16;

inline void cross3(const double a[3], const double b[3], double out[3]) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}
inline double dot3(const double a[3], const double b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

template <class Body>
void parallel_for(std::int64_t n, int threads, Body&& body) {
  if (n <= 0) return;
  if (threads <= 1 || n == 1) {
    for (std::int64_t i = 0; i < n; ++i) body(i, 0);
    return;
  }
  std::atomic<std::int64_t> next{0};
  auto work = [&](int tid) {
    for (;;) {
      const std::int64_t i = next.fetch_add(1);
      if (i >= n) break;
      body(i, tid);
    }
  };
  std::vector<std::thread> pool;
  const int extra = int(std::min<std::int64_t>(threads, n)) - 1;
  for (int k = 0; k < extra; ++k) pool.emplace_back(work, k + 1);
  work(0);
  for (auto& th : pool) th.join();
}
}  // namespace dmesh::render_detail
