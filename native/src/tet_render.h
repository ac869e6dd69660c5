// Tetrahedral renderer (DESIGN.md section 7, phase 2): every pixel ray walks a fixed tetrahedralisation
// and composites the faces it crosses, in exact depth order. Forward and backward (opacities only).
//
// Letters: N vertices, T tets, F faces, H x W pixels, K stored fragments (all pixels together).
//
// Camera and pixel conventions: soft_render.h (rays through pixel centres, depth = -z_cam).
// Per pixel ray: the first hit is the nearest convex-hull face (a face with face_tets[f][1] == -1) that
// the ray crosses (exact ray-triangle test in double precision, hull faces binned to 16x16 tiles by
// their screen bounding box); from its tet the ray leaves through the exit face (the nearest plane among
// the tet's other faces that the ray crosses outwards), moves to the tet on the other side, and so on
// until it leaves the hull or the transmittance falls below t_min. Each crossed face f with
// opacity_f > min_opacity is composited with alpha = opacity_f (no coverage term: the walk is exact),
// diffuse c = |n_f . d| / (|n_f| |d|) and depth = the crossing's depth:
//   C += c a T, Z += z a T, T *= (1 - a), stopping before a fragment when T < t_min;
// outputs diffuse = C, depth = Z (not normalised by alpha), alpha = 1 - T.
// The camera must be outside the convex hull (a ray whose first hull crossing leaves the hull raises).
// Hull faces with a corner nearer than `near` are tested by every pixel rather than binned.
#pragma once
#include <cstdint>
#include <vector>

#include "soft_render.h"
#include "types.h"

namespace dmesh {

struct TetRenderSettings {
  double min_opacity = 1e-3;  // faces with opacity <= this are crossed but not composited
  double t_min = 1e-4;        // early stop on the transmittance
  int num_threads = 0;        // 0: std::thread::hardware_concurrency()
};

struct TetRenderResult {
  std::vector<float> diffuse;       // (H, W)
  std::vector<float> depth;         // (H, W)
  std::vector<float> alpha;         // (H, W)
  std::vector<index_t> frag_face;   // (K,) composited faces per pixel, front to back
  std::vector<float> frag_diffuse;  // (K,) their diffuse value at the pixel
  std::vector<float> frag_depth;    // (K,) their depth at the pixel
  std::vector<index_t> pix_range;   // (H, W, 2) start in the fragment arrays and count, per pixel
  std::int64_t num_steps = 0;       // tets visited, all pixels together
};

// verts (N, 3) float32 world space; tets (T, 4) int32 into verts; faces (F, 3) int32 into verts, every face
// of the tets once; face_tets (F, 2) int32, the tets on both sides of each face, -1 second for a hull face;
// opacity (F,) float32 in [0, 1]. Every tet must own exactly 4 faces. Throws std::invalid_argument.
TetRenderResult tet_render_forward(const float* verts, index_t N, const index_t* tets, index_t T,
                                   const index_t* faces, const index_t* face_tets, index_t F,
                                   const float* opacity, const RenderCamera& cam, const TetRenderSettings& s);

// Gradient of sum(grad_diffuse * diffuse + grad_depth * depth + grad_alpha * alpha) with respect to the
// face opacities (F,) float32, from the fragments of the forward call with the same opacities.
std::vector<float> tet_render_backward(const float* opacity, index_t F, const index_t* frag_face,
                                       const float* frag_diffuse, const float* frag_depth, std::int64_t K,
                                       const index_t* pix_range, index_t H, index_t W,
                                       const float* grad_diffuse, const float* grad_depth,
                                       const float* grad_alpha, const TetRenderSettings& s);

}  // namespace dmesh
