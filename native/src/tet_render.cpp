// Tetrahedral renderer: see tet_render.h. Geometry in double precision, camera space.
#include "tet_render.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace dmesh {
namespace {
using namespace render_detail;


// Ray (origin 0, direction d) against triangle (a, b, c): the ray parameter (= depth, as d_z = -1) of the
// crossing, or infinity when the ray misses. Barycentric tolerance 1e-12 so shared edges are not missed.
inline double ray_triangle(const double* a, const double* b, const double* c, const double d[3]) {
  double e1[3], e2[3], pv[3], tv[3], qv[3];
  for (int k = 0; k < 3; ++k) {
    e1[k] = b[k] - a[k];
    e2[k] = c[k] - a[k];
    tv[k] = -a[k];
  }
  cross3(d, e2, pv);
  const double det = dot3(e1, pv);
  if (det == 0.0 || !std::isfinite(det)) return std::numeric_limits<double>::infinity();
  const double inv = 1.0 / det;
  const double bu = dot3(tv, pv) * inv;
  if (bu < -1e-12 || bu > 1.0 + 1e-12) return std::numeric_limits<double>::infinity();
  cross3(tv, e1, qv);
  const double bv = dot3(d, qv) * inv;
  if (bv < -1e-12 || bu + bv > 1.0 + 1e-12) return std::numeric_limits<double>::infinity();
  const double s = dot3(e2, qv) * inv;
  return s > 0.0 ? s : std::numeric_limits<double>::infinity();
}

}  // namespace

TetRenderResult tet_render_forward(const float* verts, index_t N, const index_t* tets, index_t T,
                                   const index_t* faces, const index_t* face_tets, index_t F,
                                   const float* opacity, const RenderCamera& cam, const TetRenderSettings& s) {
  const char* fn = "tet_render_forward";
  const std::string f(fn);
  const View view = make_view(cam, fn);
  if (!(s.t_min > 0.0 && s.t_min < 1.0)) throw std::invalid_argument(f + ": t_min must be in (0, 1)");
  if (!(s.min_opacity >= 0.0 && s.min_opacity < 1.0))
    throw std::invalid_argument(f + ": min_opacity must be in [0, 1)");
  for (std::int64_t k = 0; k < 4 * std::int64_t(T); ++k)
    if (tets[k] < 0 || tets[k] >= N)
      throw std::invalid_argument(f + ": tets holds " + std::to_string(tets[k]) + ", outside [0, " +
                                  std::to_string(N) + ")");
  for (std::int64_t k = 0; k < 3 * std::int64_t(F); ++k)
    if (faces[k] < 0 || faces[k] >= N)
      throw std::invalid_argument(f + ": faces holds " + std::to_string(faces[k]) + ", outside [0, " +
                                  std::to_string(N) + ")");
  for (index_t k = 0; k < F; ++k) {
    if (!(opacity[k] >= 0.0f && opacity[k] <= 1.0f))
      throw std::invalid_argument(f + ": opacity[" + std::to_string(k) + "] is outside [0, 1]");
    if (face_tets[2 * k] < 0 || face_tets[2 * k] >= T || face_tets[2 * k + 1] < -1 || face_tets[2 * k + 1] >= T)
      throw std::invalid_argument(f + ": face_tets row " + std::to_string(k) + " is not a tet pair (second may be -1)");
  }
  for (index_t n = 0; n < N; ++n)
    for (int k = 0; k < 3; ++k)
      if (!std::isfinite(verts[3 * std::int64_t(n) + k])) throw std::invalid_argument(f + ": verts must be finite");

  // tet -> its 4 faces; each face's vertices must be 3 of the tet's 4
  std::vector<index_t> tet_faces(size_t(T) * 4, kNone);
  std::vector<std::uint8_t> filled(size_t(T), 0);
  for (index_t k = 0; k < F; ++k) {
    for (int side = 0; side < 2; ++side) {
      const index_t t = face_tets[2 * k + side];
      if (t < 0) continue;
      if (filled[t] == 4)
        throw std::invalid_argument(f + ": tet " + std::to_string(t) + " has more than 4 faces in face_tets");
      const index_t* tv = tets + 4 * std::int64_t(t);
      for (int c = 0; c < 3; ++c) {
        const index_t vtx = faces[3 * k + c];
        if (vtx != tv[0] && vtx != tv[1] && vtx != tv[2] && vtx != tv[3])
          throw std::invalid_argument(f + ": face " + std::to_string(k) + " is not a face of tet " + std::to_string(t));
      }
      tet_faces[4 * size_t(t) + filled[t]++] = k;
    }
  }
  for (index_t t = 0; t < T; ++t)
    if (filled[t] != 4)
      throw std::invalid_argument(f + ": tet " + std::to_string(t) + " has " + std::to_string(int(filled[t])) +
                                  " faces in face_tets, expected 4");

  const int threads = thread_count(s.num_threads);
  std::vector<double> Pc(size_t(N) * 3);
  for (index_t n = 0; n < N; ++n) view.to_camera(verts + 3 * std::int64_t(n), &Pc[3 * size_t(n)]);

  // bin hull faces to tiles
  const index_t H = view.H, W = view.W;
  const index_t tiles_x = (W + kTile - 1) / kTile, tiles_y = (H + kTile - 1) / kTile;
  const std::int64_t tiles = std::int64_t(tiles_x) * tiles_y;
  std::vector<std::vector<index_t>> bins(static_cast<size_t>(tiles));
  std::vector<index_t> everywhere;
  for (index_t k = 0; k < F; ++k) {
    if (face_tets[2 * k + 1] >= 0) continue;
    double umin = 1e300, umax = -1e300, vmin = 1e300, vmax = -1e300;
    bool near_cam = false;
    for (int c = 0; c < 3; ++c) {
      const double* p = &Pc[3 * size_t(faces[3 * k + c])];
      const double depth = -p[2];
      if (!(depth >= view.near)) {
        near_cam = true;
        break;
      }
      const double u = view.cx + view.f * p[0] / depth, v = view.cy - view.f * p[1] / depth;
      umin = std::min(umin, u);
      umax = std::max(umax, u);
      vmin = std::min(vmin, v);
      vmax = std::max(vmax, v);
    }
    if (near_cam) {
      everywhere.push_back(k);
      continue;
    }
    // one pixel of margin so rays through edges are never lost to rounding
    const double lo_u = std::ceil(umin - 1.5), hi_u = std::floor(umax + 0.5);
    const double lo_v = std::ceil(vmin - 1.5), hi_v = std::floor(vmax + 0.5);
    if (hi_u < 0 || hi_v < 0 || lo_u > W - 1 || lo_v > H - 1) continue;
    const index_t x0 = index_t(std::max(lo_u, 0.0)), x1 = index_t(std::min(hi_u, double(W - 1)));
    const index_t y0 = index_t(std::max(lo_v, 0.0)), y1 = index_t(std::min(hi_v, double(H - 1)));
    for (index_t ty = y0 / kTile; ty <= y1 / kTile; ++ty)
      for (index_t tx = x0 / kTile; tx <= x1 / kTile; ++tx) bins[std::int64_t(ty) * tiles_x + tx].push_back(k);
  }

  TetRenderResult r;
  r.diffuse.assign(size_t(H) * W, 0.0f);
  r.depth.assign(size_t(H) * W, 0.0f);
  r.alpha.assign(size_t(H) * W, 0.0f);
  r.pix_range.assign(size_t(H) * W * 2, 0);
  struct Out {
    std::vector<index_t> face;
    std::vector<float> c, z;
  };
  std::vector<Out> tile_out(static_cast<size_t>(tiles));
  std::atomic<std::int64_t> steps{0};
  std::atomic<bool> inside_hull{false};
  const std::int64_t max_steps = 2 * std::int64_t(T) + 8;

  parallel_for(tiles, threads, [&](std::int64_t tile, int) {
    const index_t tx = index_t(tile % tiles_x), ty = index_t(tile / tiles_x);
    Out& out = tile_out[size_t(tile)];
    const std::vector<index_t>& list = bins[size_t(tile)];
    std::int64_t local_steps = 0;
    for (index_t i = ty * kTile; i < std::min<index_t>(H, (ty + 1) * kTile); ++i) {
      for (index_t j = tx * kTile; j < std::min<index_t>(W, (tx + 1) * kTile); ++j) {
        const size_t pix = size_t(i) * W + j;
        const size_t start = out.face.size();
        double d[3];
        view.ray(j + 0.5, i + 0.5, d);
        const double dlen = std::sqrt(dot3(d, d));
        double best = std::numeric_limits<double>::infinity();
        index_t hit = kNone;
        auto test = [&](index_t k) {
          const index_t* fv = faces + 3 * std::int64_t(k);
          const double sv = ray_triangle(&Pc[3 * size_t(fv[0])], &Pc[3 * size_t(fv[1])], &Pc[3 * size_t(fv[2])], d);
          if (sv < best || (sv == best && k < hit)) {
            best = sv;
            hit = k;
          }
        };
        for (index_t k : list) test(k);
        for (index_t k : everywhere) test(k);
        if (hit == kNone) continue;
        double Tr = 1.0, C = 0.0, Z = 0.0, s_cur = best;
        index_t face = hit, tet = face_tets[2 * hit];
        for (std::int64_t step = 0; step < max_steps; ++step) {
          // composite the face just crossed
          const index_t* fv = faces + 3 * std::int64_t(face);
          const double* a = &Pc[3 * size_t(fv[0])];
          const double* b = &Pc[3 * size_t(fv[1])];
          const double* c = &Pc[3 * size_t(fv[2])];
          const double op = opacity[face];
          if (op > s.min_opacity) {
            if (Tr < s.t_min) break;
            double e1[3], e2[3], n[3];
            for (int k = 0; k < 3; ++k) {
              e1[k] = b[k] - a[k];
              e2[k] = c[k] - a[k];
            }
            cross3(e1, e2, n);
            const double nl = std::sqrt(dot3(n, n));
            const double cv = nl > 0 ? std::fabs(dot3(n, d)) / (nl * dlen) : 0.0;
            C += cv * op * Tr;
            Z += s_cur * op * Tr;
            Tr *= 1.0 - op;
            out.face.push_back(face);
            out.c.push_back(float(cv));
            out.z.push_back(float(s_cur));
            if (Tr < s.t_min) break;
          }
          if (tet < 0) break;
          ++local_steps;
          // leave `tet` through its nearest outward-crossed face other than `face`
          const index_t* tv = tets + 4 * std::int64_t(tet);
          double s_exit = std::numeric_limits<double>::infinity();
          index_t exit_face = kNone;
          for (int q = 0; q < 4; ++q) {
            const index_t g = tet_faces[4 * size_t(tet) + q];
            if (g == face) continue;
            const index_t* gv = faces + 3 * std::int64_t(g);
            index_t opp = tv[0];
            for (int k = 0; k < 4; ++k)
              if (tv[k] != gv[0] && tv[k] != gv[1] && tv[k] != gv[2]) opp = tv[k];
            const double* ga = &Pc[3 * size_t(gv[0])];
            const double* gb = &Pc[3 * size_t(gv[1])];
            const double* gc = &Pc[3 * size_t(gv[2])];
            const double* go = &Pc[3 * size_t(opp)];
            double e1[3], e2[3], n[3], ao[3];
            for (int k = 0; k < 3; ++k) {
              e1[k] = gb[k] - ga[k];
              e2[k] = gc[k] - ga[k];
              ao[k] = go[k] - ga[k];
            }
            cross3(e1, e2, n);
            if (dot3(n, ao) > 0) n[0] = -n[0], n[1] = -n[1], n[2] = -n[2];  // outward
            const double nd = dot3(n, d);
            if (!(nd > 0)) continue;
            const double sv = dot3(n, ga) / nd;
            if (sv < s_exit || (sv == s_exit && g < exit_face)) {
              s_exit = sv;
              exit_face = g;
            }
          }
          if (exit_face == kNone) break;
          s_cur = std::max(s_cur, s_exit);
          face = exit_face;
          tet = face_tets[2 * face] == tet ? face_tets[2 * face + 1] : face_tets[2 * face];
        }
        // the first crossing must enter the hull: its tet lies beyond it along the ray
        {
          const index_t* fv = faces + 3 * std::int64_t(hit);
          const index_t* tv = tets + 4 * std::int64_t(face_tets[2 * hit]);
          index_t opp = tv[0];
          for (int k = 0; k < 4; ++k)
            if (tv[k] != fv[0] && tv[k] != fv[1] && tv[k] != fv[2]) opp = tv[k];
          const double* a = &Pc[3 * size_t(fv[0])];
          double e1[3], e2[3], n[3], ao[3];
          for (int k = 0; k < 3; ++k) {
            e1[k] = Pc[3 * size_t(fv[1]) + k] - a[k];
            e2[k] = Pc[3 * size_t(fv[2]) + k] - a[k];
            ao[k] = Pc[3 * size_t(opp) + k] - a[k];
          }
          cross3(e1, e2, n);
          if (dot3(n, ao) > 0) n[0] = -n[0], n[1] = -n[1], n[2] = -n[2];
          if (dot3(n, d) > 1e-12 * std::sqrt(dot3(n, n)) * dlen) inside_hull = true;
        }
        r.diffuse[pix] = float(C);
        r.depth[pix] = float(Z);
        r.alpha[pix] = float(1.0 - Tr);
        r.pix_range[2 * pix] = index_t(start);
        r.pix_range[2 * pix + 1] = index_t(out.face.size() - start);
      }
    }
    steps += local_steps;
  });
  if (inside_hull) {
    throw std::invalid_argument(f + ": the camera is inside the convex hull of the tetrahedralisation "
                                "(some ray's first hull crossing leaves the hull)");
  }
  std::vector<std::int64_t> base(size_t(tiles) + 1, 0);
  for (std::int64_t t = 0; t < tiles; ++t) base[t + 1] = base[t] + std::int64_t(tile_out[t].face.size());
  if (base[tiles] > std::int64_t(std::numeric_limits<index_t>::max()))
    throw std::invalid_argument(f + ": too many fragments for int32 offsets");
  r.frag_face.resize(size_t(base[tiles]));
  r.frag_diffuse.resize(size_t(base[tiles]));
  r.frag_depth.resize(size_t(base[tiles]));
  for (std::int64_t t = 0; t < tiles; ++t) {
    std::copy(tile_out[t].face.begin(), tile_out[t].face.end(), r.frag_face.begin() + base[t]);
    std::copy(tile_out[t].c.begin(), tile_out[t].c.end(), r.frag_diffuse.begin() + base[t]);
    std::copy(tile_out[t].z.begin(), tile_out[t].z.end(), r.frag_depth.begin() + base[t]);
  }
  for (index_t i = 0; i < H; ++i)
    for (index_t j = 0; j < W; ++j)
      r.pix_range[2 * (size_t(i) * W + j)] += index_t(base[std::int64_t(i / kTile) * tiles_x + j / kTile]);
  r.num_steps = steps;
  return r;
}

std::vector<float> tet_render_backward(const float* opacity, index_t F, const index_t* frag_face,
                                       const float* frag_diffuse, const float* frag_depth, std::int64_t K,
                                       const index_t* pix_range, index_t H, index_t W,
                                       const float* grad_diffuse, const float* grad_depth,
                                       const float* grad_alpha, const TetRenderSettings& s) {
  const std::string f("tet_render_backward");
  for (std::int64_t k = 0; k < K; ++k)
    if (frag_face[k] < 0 || frag_face[k] >= F) throw std::invalid_argument(f + ": frag_face out of range");
  const std::int64_t P = std::int64_t(H) * W;
  for (std::int64_t k = 0; k < P; ++k) {
    const std::int64_t a = pix_range[2 * k], c = pix_range[2 * k + 1];
    if (a < 0 || c < 0 || a + c > K) throw std::invalid_argument(f + ": pix_range does not match frag_face");
  }
  const int threads = std::max(1, int(std::min<std::int64_t>(thread_count(s.num_threads), H)));
  std::vector<std::vector<double>> acc(static_cast<size_t>(threads));
  const std::int64_t rows_per = 8;
  parallel_for((std::int64_t(H) + rows_per - 1) / rows_per, threads, [&](std::int64_t rb, int tid) {
    std::vector<double>& g = acc[size_t(tid)];
    if (g.empty()) g.assign(size_t(F), 0.0);
    std::vector<double> Ts;
    for (index_t i = index_t(rb * rows_per); i < std::min<index_t>(H, index_t((rb + 1) * rows_per)); ++i) {
      for (index_t j = 0; j < W; ++j) {
        const std::int64_t pix = std::int64_t(i) * W + j;
        const index_t start = pix_range[2 * pix], cnt = pix_range[2 * pix + 1];
        const double gD = grad_diffuse[pix], gZ = grad_depth[pix], gA = grad_alpha[pix];
        if (cnt == 0 || (gD == 0.0 && gZ == 0.0 && gA == 0.0)) continue;
        Ts.resize(size_t(cnt));
        double T = 1.0;
        for (index_t k = 0; k < cnt; ++k) {
          Ts[size_t(k)] = T;
          T *= 1.0 - double(opacity[frag_face[start + k]]);
        }
        double S = 0.0;
        for (index_t k = cnt - 1; k >= 0; --k) {
          const index_t face = frag_face[start + k];
          const double a = opacity[face];
          const double val = gD * frag_diffuse[start + k] + gZ * frag_depth[start + k] + gA;
          g[size_t(face)] += Ts[size_t(k)] * (val - S);
          S = val * a + (1.0 - a) * S;
        }
      }
    }
  });
  std::vector<float> out(size_t(F), 0.0f);
  for (index_t k = 0; k < F; ++k) {
    double c = 0.0;
    for (auto& g : acc)
      if (!g.empty()) c += g[size_t(k)];
    out[size_t(k)] = float(c);
  }
  return out;
}

}  // namespace dmesh
