// Soft tile rasteriser: see soft_render.h for the model. All geometry is evaluated in double precision.
#include "soft_render.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <cstring>
#include <memory>
#include <utility>
#include <stdexcept>
#include <string>

namespace dmesh {
namespace render_detail {

View make_view(const RenderCamera& cam, const char* fn) {
  const std::string f(fn);
  if (cam.height < 1 || cam.width < 1 || cam.height > 16384 || cam.width > 16384) {
    throw std::invalid_argument(f + ": image size must be in [1, 16384], got " + std::to_string(cam.height) +
                                " x " + std::to_string(cam.width));
  }
  if (!(cam.fov_y > 0.0 && cam.fov_y < M_PI)) {
    throw std::invalid_argument(f + ": fov_y must be in (0, pi) radians, got " + std::to_string(cam.fov_y));
  }
  if (!(cam.near > 0.0) || !std::isfinite(cam.near)) {
    throw std::invalid_argument(f + ": near must be positive, got " + std::to_string(cam.near));
  }
  for (int k = 0; k < 12; ++k) {
    if (!std::isfinite(cam.world_to_camera[k])) {
      throw std::invalid_argument(f + ": world_to_camera must be finite");
    }
  }
  View v;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) v.R[3 * r + c] = cam.world_to_camera[4 * r + c];
    v.t[r] = cam.world_to_camera[4 * r + 3];
  }
  v.H = cam.height;
  v.W = cam.width;
  v.f = 0.5 * double(cam.height) / std::tan(0.5 * cam.fov_y);
  v.cx = 0.5 * double(cam.width);
  v.cy = 0.5 * double(cam.height);
  v.near = cam.near;
  return v;
}

int thread_count(int requested) {
  if (requested > 0) return std::min(requested, 256);
  const unsigned hc = std::thread::hardware_concurrency();
  return hc == 0 ? 1 : int(std::min(hc, 256u));
}

}  // namespace render_detail

namespace {
using namespace render_detail;


// Everything about one drawn face that the per-pixel loops need.
struct alignas(32) Face {
  // hot: read by every coverage test
  double ea[3], eb[3], ec[3];  // normalised edge lines: sd_e = ea u + eb v + ec, >= 0 on the inner side
  double area2;     // signed doubled screen area
  // warm: read for covered pixels
  double q[3][2];   // screen corners (u, v)
  double n[3];      // unnormalised normal (P1 - P0) x (P2 - P0)
  double nlen;      // |n|
  double num;       // n . P0 = det(P0, P1, P2)
  double zmin, zmax;
  double opacity;
  index_t id;       // input face index
  int imin, imax;   // corners with the smallest / largest depth
  index_t x0, x1, y0, y1;  // pixel bounding box (inclusive), band included
};

using Corners = std::array<double, 9>;  // camera-space corners P0, P1, P2 (backward only)

struct BinEntry {  // what a tile keeps per listed face (16 bytes)
  std::int16_t x0, x1, y0, y1;
  float zmin;       // rounded down: a lower bound of the face's zmin
  index_t slot;     // face id: index into Prepared::faces
};

// A face's pixel span in one row, as bounds linear in the row's centre v (forward binning only): for
// each edge e with |ea_e| >= kLinearEa, the pixels j (centre u = j + 0.5) where sd_e > -w satisfy
// j > k_e v + m_e when ea_e > 0 (a lower bound) or j < k_e v + m_e when ea_e < 0 (an upper bound). Edges
// nearer to horizontal are bounded from the Face's edge line per row, as a division would lose too much.
// The bounds only pre-filter the pixels that get a coverage test, so a rounding error below a pixel
// changes nothing (the row bucketing in soft_render_forward keeps a pixel of slack).
constexpr double kLinearEa = 1e-3;
// Loops that visit faces in depth order (random in memory) prefetch this many entries ahead.
constexpr std::int64_t kAhead = 16;
struct alignas(64) RowSpan {
  double k[3], m[3];
  std::int8_t kind[3];  // 0: lower bound, 1: upper bound, 2: per-row test from the Face's edge line
};

void setup_row_span(const Face& fc, double w, RowSpan& rs) {
  for (int e = 0; e < 3; ++e) {
    const double ea = fc.ea[e];
    rs.kind[e] = ea >= kLinearEa ? 0 : ea <= -kLinearEa ? 1 : 2;
    // sd_e + w at pixel j of row v: ea j + (eb v + ec + w + ea / 2), zero at j = -(eb v + ec + w + ea / 2) / ea
    rs.k[e] = rs.kind[e] == 2 ? 0.0 : -fc.eb[e] / ea;
    rs.m[e] = rs.kind[e] == 2 ? 0.0 : -(fc.ec[e] + w + 0.5 * ea) / ea;
  }
}

struct RowEntry {  // a tile's faces whose box spans one pixel row
  std::int16_t x0, x1;
  float zmin;
  index_t slot;
};

// Fills Face from the corners; returns false when the face is culled.
bool setup_face(const View& view, const float* verts, const index_t* tri, double opacity, double w, Face& fc,
                Corners* corners = nullptr) {
  fc.id = kNone;
  struct {
    double P[3][3];
  } fcP;
  for (int i = 0; i < 3; ++i) {
    const float* x = verts + 3 * std::int64_t(tri[i]);
    if (!std::isfinite(x[0]) || !std::isfinite(x[1]) || !std::isfinite(x[2])) return false;
    view.to_camera(x, fcP.P[i]);
    const double depth = -fcP.P[i][2];
    if (!(depth >= view.near)) return false;
    fc.q[i][0] = view.cx + view.f * fcP.P[i][0] / depth;
    fc.q[i][1] = view.cy - view.f * fcP.P[i][1] / depth;
  }
  double e1[3], e2[3];
  for (int k = 0; k < 3; ++k) {
    e1[k] = fcP.P[1][k] - fcP.P[0][k];
    e2[k] = fcP.P[2][k] - fcP.P[0][k];
  }
  cross3(e1, e2, fc.n);
  fc.nlen = std::sqrt(dot3(fc.n, fc.n));
  // A (numerically) zero-area face has no normal: diffuse 0 and depth zmax (its normal would be noise).
  if (fc.nlen <= 1e-12 * std::sqrt(dot3(e1, e1) * dot3(e2, e2))) {
    fc.n[0] = fc.n[1] = fc.n[2] = 0.0;
    fc.nlen = 0.0;
  }
  fc.num = dot3(fc.n, fcP.P[0]);
  fc.imin = fc.imax = 0;
  for (int i = 1; i < 3; ++i) {
    if (-fcP.P[i][2] < -fcP.P[fc.imin][2]) fc.imin = i;
    if (-fcP.P[i][2] > -fcP.P[fc.imax][2]) fc.imax = i;
  }
  fc.zmin = -fcP.P[fc.imin][2];
  fc.zmax = -fcP.P[fc.imax][2];
  if (corners)
    for (int i = 0; i < 3; ++i)
      for (int k = 0; k < 3; ++k) (*corners)[3 * i + k] = fcP.P[i][k];
  fc.area2 = (fc.q[1][0] - fc.q[0][0]) * (fc.q[2][1] - fc.q[0][1]) -
             (fc.q[2][0] - fc.q[0][0]) * (fc.q[1][1] - fc.q[0][1]);
  const double sgn = fc.area2 >= 0 ? 1.0 : -1.0;
  for (int e = 0; e < 3; ++e) {
    const double* a = fc.q[e];
    const double* b = fc.q[(e + 1) % 3];
    const double dx = b[0] - a[0], dy = b[1] - a[1];
    const double len = std::sqrt(dx * dx + dy * dy);
    if (len > 0) {  // cross((b - a), (p - a)) / len, oriented to be >= 0 inside
      fc.ea[e] = -sgn * dy / len;
      fc.eb[e] = sgn * dx / len;
      fc.ec[e] = sgn * (dy * a[0] - dx * a[1]) / len;
    } else {
      fc.ea[e] = fc.eb[e] = 0.0;
      fc.ec[e] = std::numeric_limits<double>::infinity();
    }
  }
  fc.opacity = opacity;
  double umin = fc.q[0][0], umax = umin, vmin = fc.q[0][1], vmax = vmin;
  for (int i = 1; i < 3; ++i) {
    umin = std::min(umin, fc.q[i][0]);
    umax = std::max(umax, fc.q[i][0]);
    vmin = std::min(vmin, fc.q[i][1]);
    vmax = std::max(vmax, fc.q[i][1]);
  }
  // pixel j is hit when its centre j + 0.5 lies in [umin - w, umax + w]
  const double lo_u = std::ceil(umin - w - 0.5), hi_u = std::floor(umax + w - 0.5);
  const double lo_v = std::ceil(vmin - w - 0.5), hi_v = std::floor(vmax + w - 0.5);
  if (hi_u < 0 || hi_v < 0 || lo_u > view.W - 1 || lo_v > view.H - 1 || lo_u > hi_u || lo_v > hi_v) return false;
  fc.x0 = index_t(std::max(lo_u, 0.0));
  fc.x1 = index_t(std::min(hi_u, double(view.W - 1)));
  fc.y0 = index_t(std::max(lo_v, 0.0));
  fc.y1 = index_t(std::min(hi_v, double(view.H - 1)));
  return true;
}

inline double smoothstep(double s) { return s * s * (3.0 - 2.0 * s); }

// Coverage of the pixel centre (u, v); when grad is given, also d cov / d q (3 x 2).
inline double coverage(const Face& fc, double u, double v, double w, double* grad) {
  double sd[3];
  bool inside = fc.area2 != 0.0;
  for (int e = 0; e < 3; ++e) {
    sd[e] = fc.ea[e] * u + fc.eb[e] * v + fc.ec[e];
    if (sd[e] <= -w) return 0.0;
    inside = inside && sd[e] >= 0.0;
  }
  if (inside) {
    if (grad) std::fill(grad, grad + 6, 0.0);
    return 1.0;
  }
  // distance to the triangle = the smallest distance to its three edge segments
  double best = std::numeric_limits<double>::infinity(), bt = 0.0, bx = 0.0, by = 0.0;
  int be = 0;
  for (int e = 0; e < 3; ++e) {
    const double* a = fc.q[e];
    const double* b = fc.q[(e + 1) % 3];
    const double dx = b[0] - a[0], dy = b[1] - a[1];
    const double l2 = dx * dx + dy * dy;
    double t = l2 > 0 ? ((u - a[0]) * dx + (v - a[1]) * dy) / l2 : 0.0;
    t = std::min(1.0, std::max(0.0, t));
    const double rx = u - (a[0] + t * dx), ry = v - (a[1] + t * dy);
    const double d2 = rx * rx + ry * ry;
    if (d2 < best) {
      best = d2;
      bt = t;
      bx = rx;
      by = ry;
      be = e;
    }
  }
  const double dist = std::sqrt(best);
  if (dist >= w) return 0.0;
  const double s = 1.0 - dist / w;
  if (grad) {
    std::fill(grad, grad + 6, 0.0);
    if (dist > 0) {
      // d cov / d dist = -S'(s) / w; d dist / d a = -(1 - t) r / dist, d dist / d b = -t r / dist
      const double g = -6.0 * s * (1.0 - s) / w / dist;
      const int ia = be, ib = (be + 1) % 3;
      grad[2 * ia] += -g * (1.0 - bt) * bx;
      grad[2 * ia + 1] += -g * (1.0 - bt) * by;
      grad[2 * ib] += -g * bt * bx;
      grad[2 * ib + 1] += -g * bt * by;
    }
  }
  return smoothstep(s);
}

// Ray-plane depth clamped into [zmin, zmax]; `which` = -1 when unclamped, else the clamping corner.
inline double frag_depth(const Face& fc, const double d[3], double* den_out, int* which) {
  const double den = dot3(fc.n, d);
  double z = den != 0.0 ? fc.num / den : std::numeric_limits<double>::quiet_NaN();
  *den_out = den;
  if (!std::isfinite(z)) {
    *which = fc.imax;
    return fc.zmax;
  }
  if (z < fc.zmin) {
    *which = fc.imin;
    return fc.zmin;
  }
  if (z > fc.zmax) {
    *which = fc.imax;
    return fc.zmax;
  }
  *which = -1;
  return z;
}

inline double frag_diffuse(const Face& fc, const double d[3]) {
  if (fc.nlen == 0.0) return 0.0;
  return std::fabs(dot3(fc.n, d)) / (fc.nlen * std::sqrt(dot3(d, d)));
}

struct Frag {
  double key;  // sort depth: z inside the triangle, z + (zmax - zmin) in the soft band
  double z;
  index_t face;
  double a;
  const struct Face* fc;  // diffuse is evaluated only when the fragment is composited
};

// Large per-call arrays are kept per calling thread and reused: fresh allocations of tens of MB come
// from new pages each call, and the page faults cost as much as the setup itself. (Memory held: the
// largest call's face and bin arrays, about 350 bytes per face.)
template <class T>
struct Reusable {
  std::unique_ptr<T[]> data;
  size_t cap = 0;
  T* get(size_t n) {
    if (n > cap) {
      data.reset(new T[n]);  // not zero-filled
      cap = n;
    }
    return data.get();
  }
};
thread_local Reusable<Face> tl_faces, tl_bwd_faces;
thread_local Reusable<BinEntry> tl_bins, tl_box;
thread_local Reusable<RowSpan> tl_span;
thread_local Reusable<std::pair<double, index_t>> tl_order, tl_order_tmp;
thread_local Reusable<Corners> tl_corners;
thread_local Reusable<double> tl_acc, tl_gv;
thread_local Reusable<index_t> tl_loc;

// Sorts (zmin, id) pairs given in increasing id order by (zmin, id): a stable LSD radix sort on the bits
// of zmin, which order like the values since every zmin is positive (>= near) and finite. Bytes that all
// keys share are skipped. tmp: scratch of n pairs.
void sort_by_depth(std::pair<double, index_t>* a, std::int64_t n, std::pair<double, index_t>* tmp) {
  if (n < 2) return;
  auto bits = [](const std::pair<double, index_t>& x) {
    std::uint64_t b;
    std::memcpy(&b, &x.first, sizeof b);
    return b;
  };
  std::int64_t hist[8][256] = {};
  for (std::int64_t k = 0; k < n; ++k) {
    const std::uint64_t b = bits(a[k]);
    for (int d = 0; d < 8; ++d) ++hist[d][(b >> (8 * d)) & 0xff];
  }
  std::pair<double, index_t>* src = a;
  std::pair<double, index_t>* dst = tmp;
  for (int d = 0; d < 8; ++d) {
    std::int64_t* h = hist[d];
    if (h[(bits(a[0]) >> (8 * d)) & 0xff] == n) continue;  // every key has this byte
    std::int64_t sum = 0;
    for (int v = 0; v < 256; ++v) {
      const std::int64_t c = h[v];
      h[v] = sum;
      sum += c;
    }
    for (std::int64_t k = 0; k < n; ++k) dst[h[(bits(src[k]) >> (8 * d)) & 0xff]++] = src[k];
    std::swap(src, dst);
  }
  if (src != a) std::copy(src, src + n, a);
}

struct Prepared {
  Face* faces = nullptr;            // (F,) by face id, valid where drawn
  std::vector<std::int64_t> tile_start;  // (tiles + 1,)
  BinEntry* bins = nullptr;         // per tile, sorted by (zmin, face id)
  RowSpan* spans = nullptr;         // (F,) by face id, valid where drawn
  std::int64_t num_drawn = 0, num_bins = 0;
  index_t tiles_x = 0, tiles_y = 0;
};

void validate(const index_t* faces, index_t F, index_t N, const float* opacity, const SoftRenderSettings& s,
              const char* fn) {
  const std::string f(fn);
  if (!(s.edge_width > 0.0) || !std::isfinite(s.edge_width)) {
    throw std::invalid_argument(f + ": edge_width must be positive, got " + std::to_string(s.edge_width));
  }
  if (!(s.t_min > 0.0 && s.t_min < 1.0)) {
    throw std::invalid_argument(f + ": t_min must be in (0, 1), got " + std::to_string(s.t_min));
  }
  if (!(s.min_opacity >= 0.0 && s.min_opacity < 1.0)) {
    throw std::invalid_argument(f + ": min_opacity must be in [0, 1), got " + std::to_string(s.min_opacity));
  }
  for (std::int64_t k = 0; k < 3 * std::int64_t(F); ++k) {
    if (faces[k] < 0 || faces[k] >= N) {
      throw std::invalid_argument(f + ": faces holds " + std::to_string(faces[k]) + ", outside [0, " +
                                  std::to_string(N) + ")");
    }
  }
  for (index_t k = 0; k < F; ++k) {
    if (!(opacity[k] >= 0.0f && opacity[k] <= 1.0f)) {
      throw std::invalid_argument(f + ": opacity[" + std::to_string(k) + "] = " + std::to_string(opacity[k]) +
                                  " is outside [0, 1]");
    }
  }
}

Prepared prepare(const View& view, const float* verts, const index_t* faces, index_t F, const float* opacity,
                 const SoftRenderSettings& s, int threads) {
  Prepared p;
  // 1. full setup in input order (sequential reads and writes, stored by face id), 2. order the drawn
  // faces by (zmin, id), 3. bin them in that order, so that every tile's list is sorted.
  p.faces = tl_faces.get(size_t(std::max<index_t>(F, 1)));
  BinEntry* box = tl_box.get(size_t(std::max<index_t>(F, 1)));  // compact copy of each face's bin entry
  p.spans = tl_span.get(size_t(std::max<index_t>(F, 1)));
  std::pair<double, index_t>* order = tl_order.get(size_t(std::max<index_t>(F, 1)));
  const std::int64_t chunk = 8192;
  const std::int64_t nchunks = (std::int64_t(F) + chunk - 1) / chunk;
  std::vector<std::int64_t> chunk_drawn(size_t(nchunks) + 1, 0);
  parallel_for(nchunks, threads, [&](std::int64_t c, int) {
    const std::int64_t end = std::min<std::int64_t>(F, (c + 1) * chunk);
    std::int64_t drawn = 0;
    for (std::int64_t f = c * chunk; f < end; ++f) {
      if (!(double(opacity[f]) > s.min_opacity)) continue;
      Face& fc = p.faces[f];
      if (!setup_face(view, verts, faces + 3 * f, double(opacity[f]), s.edge_width, fc)) continue;
      fc.id = index_t(f);
      setup_row_span(fc, s.edge_width, p.spans[f]);
      float zlo = float(fc.zmin);
      if (double(zlo) > fc.zmin) zlo = std::nextafter(zlo, -std::numeric_limits<float>::infinity());
      box[f] = BinEntry{std::int16_t(fc.x0), std::int16_t(fc.x1), std::int16_t(fc.y0), std::int16_t(fc.y1), zlo,
                        index_t(f)};
      order[c * chunk + drawn++] = {fc.zmin, index_t(f)};  // compacted within the chunk, in id order
    }
    chunk_drawn[size_t(c) + 1] = drawn;
  });
  std::int64_t D = 0;
  for (std::int64_t c = 0; c < nchunks; ++c) {  // close the gaps between chunks, keeping id order
    if (D != c * chunk) std::copy(order + c * chunk, order + c * chunk + chunk_drawn[size_t(c) + 1], order + D);
    D += chunk_drawn[size_t(c) + 1];
  }
  sort_by_depth(order, D, tl_order_tmp.get(size_t(std::max<std::int64_t>(D, 1))));

  p.tiles_x = (view.W + kTile - 1) / kTile;
  p.tiles_y = (view.H + kTile - 1) / kTile;
  const std::int64_t tiles = std::int64_t(p.tiles_x) * p.tiles_y;
  std::vector<std::int64_t> count(static_cast<size_t>(tiles) + 1, 0);
  p.num_drawn = D;
  for (std::int64_t k = 0; k < D; ++k) {
    if (k + kAhead < D) __builtin_prefetch(&box[order[k + kAhead].second]);
    const index_t f = order[k].second;
    const BinEntry& b = box[f];
    for (index_t ty = b.y0 / kTile; ty <= b.y1 / kTile; ++ty)
      for (index_t tx = b.x0 / kTile; tx <= b.x1 / kTile; ++tx) ++count[std::int64_t(ty) * p.tiles_x + tx];
  }
  p.tile_start.assign(size_t(tiles) + 1, 0);
  for (std::int64_t t = 0; t < tiles; ++t) p.tile_start[t + 1] = p.tile_start[t] + count[t];
  p.bins = tl_bins.get(size_t(std::max<std::int64_t>(p.tile_start[tiles], 1)));
  p.num_bins = p.tile_start[tiles];
  std::vector<std::int64_t> fill(p.tile_start.begin(), p.tile_start.end() - 1);
  for (std::int64_t k = 0; k < D; ++k) {  // in (zmin, id) order, so every tile's list is sorted
    if (k + kAhead < D) __builtin_prefetch(&box[order[k + kAhead].second]);
    const BinEntry b = box[order[k].second];
    for (index_t ty = b.y0 / kTile; ty <= b.y1 / kTile; ++ty)
      for (index_t tx = b.x0 / kTile; tx <= b.x1 / kTile; ++tx) p.bins[fill[std::int64_t(ty) * p.tiles_x + tx]++] = b;
  }
  return p;
}

// Heap order: a sorted vector with the nearest fragment at the back.
inline bool farther(const Frag& a, const Frag& b) { return a.key > b.key || (a.key == b.key && a.face > b.face); }

}  // namespace

SoftRenderResult soft_render_forward(const float* verts, index_t N, const index_t* faces, index_t F,
                                     const float* opacity, const RenderCamera& cam,
                                     const SoftRenderSettings& s) {
  const char* fn = "soft_render_forward";
  const View view = make_view(cam, fn);
  validate(faces, F, N, opacity, s, fn);
  const int threads = thread_count(s.num_threads);
  Prepared p = prepare(view, verts, faces, F, opacity, s, threads);

  const index_t H = view.H, W = view.W;
  SoftRenderResult r;
  r.diffuse.assign(size_t(H) * W, 0.0f);
  r.depth.assign(size_t(H) * W, 0.0f);
  r.alpha.assign(size_t(H) * W, 0.0f);
  r.pix_range.assign(size_t(H) * W * 2, 0);
  r.num_drawn = p.num_drawn;
  r.num_bins = p.num_bins;
  const std::int64_t tiles = std::int64_t(p.tiles_x) * p.tiles_y;
  std::vector<std::vector<index_t>> tile_frags(static_cast<size_t>(tiles));
  std::atomic<std::int64_t> n_scanned{0}, n_tested{0};
  const double w = s.edge_width, t_min = s.t_min;

  // per worker thread: the tile's row lists and each pixel's pending fragments and output list
  struct Scratch {
    std::vector<RowEntry> rows;
    std::vector<Frag> heap[kTile];
    std::vector<index_t> frags[kTile];
  };
  std::vector<Scratch> scratch(static_cast<size_t>(threads));

  parallel_for(tiles, threads, [&](std::int64_t t, int tid) {
    const index_t tx = index_t(t % p.tiles_x), ty = index_t(t / p.tiles_x);
    const BinEntry* list = p.bins + p.tile_start[t];
    const std::int64_t len = p.tile_start[t + 1] - p.tile_start[t];
    std::vector<index_t>& out = tile_frags[size_t(t)];
    if (len == 0) return;
    Scratch& sc = scratch[size_t(tid)];
    // bucket the tile's list by pixel row (each row keeps the slot order), narrowing each face's span in
    // the row to the pixels where all three edge distances exceed -w (a necessary condition for cov > 0)
    const index_t i0 = ty * kTile, i1 = std::min<index_t>(H, (ty + 1) * kTile);
    const index_t j0 = tx * kTile, j1 = std::min<index_t>(W, (tx + 1) * kTile) - 1;
    std::int64_t row_start[kTile + 1] = {0};
    for (std::int64_t k = 0; k < len; ++k) {
      const index_t a = std::max<index_t>(list[k].y0, i0), b = std::min<index_t>(list[k].y1, i1 - 1);
      for (index_t i = a; i <= b; ++i) ++row_start[i - i0 + 1];
    }
    for (int r = 0; r < kTile; ++r) row_start[r + 1] += row_start[r];
    if (sc.rows.size() < size_t(row_start[kTile])) sc.rows.resize(size_t(row_start[kTile]));
    RowEntry* rows = sc.rows.data();
    std::int64_t row_fill[kTile];
    std::copy(row_start, row_start + kTile, row_fill);
    for (std::int64_t k = 0; k < len; ++k) {
      const BinEntry& e = list[k];
      if (k + kAhead < len) {  // the list is in depth order, so its faces lie all over memory
        const index_t ahead = list[k + kAhead].slot;
        __builtin_prefetch(&p.spans[ahead]);
        __builtin_prefetch(&p.faces[ahead]);  // the edge lines, read by the coverage tests below
        __builtin_prefetch(reinterpret_cast<const char*>(&p.faces[ahead]) + 64);
      }
      const RowSpan& rs = p.spans[e.slot];
      const index_t a = std::max<index_t>(e.y0, i0), b = std::min<index_t>(e.y1, i1 - 1);
      const double xl = std::max<double>(e.x0, j0), xh = std::min<double>(e.x1, j1);
      for (index_t i = a; i <= b; ++i) {
        const double v = i + 0.5;
        double lo = xl, hi = xh;  // in pixel-index units: centre u = j + 0.5
        bool empty = false;
        for (int q = 0; q < 3; ++q) {
          if (rs.kind[q] == 0) {
            lo = std::max(lo, rs.k[q] * v + rs.m[q]);
          } else if (rs.kind[q] == 1) {
            hi = std::min(hi, rs.k[q] * v + rs.m[q]);
          } else {  // nearly horizontal edge: bound it from its line
            const Face& fc = p.faces[e.slot];
            const double c = fc.eb[q] * v + fc.ec[q] + w + fc.ea[q] * 0.5;  // sd_q + w at pixel j: ea j + c
            if (fc.ea[q] > 0) {
              lo = std::max(lo, -c / fc.ea[q]);
            } else if (fc.ea[q] < 0) {
              hi = std::min(hi, -c / fc.ea[q]);
            } else if (!(c > 0)) {
              empty = true;
            }
          }
        }
        // floor / ceil keep a pixel of slack beyond the bounds: no pixel with cov > 0 is dropped
        if (empty || !(lo <= hi + 1.0)) continue;
        const index_t ja = index_t(std::max(xl, std::floor(lo))), jb = index_t(std::min(xh, std::ceil(hi)));
        if (ja > jb) continue;
        rows[row_fill[i - i0]++] = RowEntry{std::int16_t(ja), std::int16_t(jb), e.zmin, e.slot};
      }
    }
    // Each row walks its list once for all its pixels together (a pixel only looks at the faces whose span
    // holds it). A pixel's pending fragments are composited when a listed face that spans it has a zmin
    // not smaller than their keys, or at the end: the same fragments in the same order as a walk that
    // checked every listed face, since only faces that span the pixel add fragments to it.
    const int nj = int(j1 - j0 + 1);
    std::int64_t scanned = 0, tested = 0;
    for (index_t i = i0; i < i1; ++i) {
      const RowEntry* row = rows + row_start[i - i0];
      const std::int64_t rlen = row_fill[i - i0] - row_start[i - i0];
      const double v = i + 0.5;
      double T[kTile], C[kTile], Z[kTile], dir[kTile][3];
      for (int jj = 0; jj < nj; ++jj) {
        T[jj] = 1.0;
        C[jj] = Z[jj] = 0.0;
        view.ray(j0 + jj + 0.5, v, dir[jj]);
        sc.heap[jj].clear();
        sc.frags[jj].clear();
      }
      // pops pixel jj's pending fragments with key <= limit; returns true once T < t_min (pixel done)
      auto composite_until = [&](int jj, double limit) {
        std::vector<Frag>& heap = sc.heap[jj];
        while (!heap.empty() && heap.back().key <= limit) {
          if (T[jj] < t_min) return true;
          const Frag& fr = heap.back();
          C[jj] += frag_diffuse(*fr.fc, dir[jj]) * fr.a * T[jj];
          Z[jj] += fr.z * fr.a * T[jj];
          T[jj] *= 1.0 - fr.a;
          sc.frags[jj].push_back(fr.face);
          heap.pop_back();
        }
        return T[jj] < t_min;
      };
      std::uint32_t active = (1u << nj) - 1u;  // pixels not done yet
      for (std::int64_t k = 0; k < rlen && active; ++k) {
        const RowEntry& b = row[k];
        ++scanned;
        std::uint32_t m = ((2u << (b.x1 - j0)) - (1u << (b.x0 - j0))) & active;
        while (m) {
          const int jj = __builtin_ctz(m);
          m &= m - 1;
          if (!sc.heap[jj].empty() && sc.heap[jj].back().key <= double(b.zmin) &&
              composite_until(jj, double(b.zmin))) {
            active &= ~(1u << jj);
            continue;
          }
          ++tested;
          const Face& fc = p.faces[b.slot];
          const double cov = coverage(fc, j0 + jj + 0.5, v, w, nullptr);
          if (cov <= 0.0) continue;
          double den;
          int which;
          const double z = frag_depth(fc, dir[jj], &den, &which);
          Frag fr{cov < 1.0 ? z + (fc.zmax - fc.zmin) : z, z, fc.id, fc.opacity * cov, &fc};
          std::vector<Frag>& heap = sc.heap[jj];
          heap.insert(std::upper_bound(heap.begin(), heap.end(), fr, farther), fr);
        }
      }
      for (int jj = 0; jj < nj; ++jj) {
        if (active & (1u << jj)) composite_until(jj, std::numeric_limits<double>::infinity());
        const size_t pix = size_t(i) * W + j0 + jj;
        r.diffuse[pix] = float(C[jj]);
        r.depth[pix] = float(Z[jj]);
        r.alpha[pix] = float(1.0 - T[jj]);
        r.pix_range[2 * pix] = index_t(out.size());  // local for now, made global below
        r.pix_range[2 * pix + 1] = index_t(sc.frags[jj].size());
        out.insert(out.end(), sc.frags[jj].begin(), sc.frags[jj].end());
      }
    }
    n_scanned += scanned;
    n_tested += tested;
  });
  r.num_scanned = n_scanned;
  r.num_tested = n_tested;

  std::vector<std::int64_t> base(size_t(tiles) + 1, 0);
  for (std::int64_t t = 0; t < tiles; ++t) base[t + 1] = base[t] + std::int64_t(tile_frags[t].size());
  if (base[tiles] > std::int64_t(std::numeric_limits<index_t>::max())) {
    throw std::invalid_argument(std::string(fn) + ": too many fragments for int32 offsets");
  }
  r.frag_face.resize(size_t(base[tiles]));
  for (std::int64_t t = 0; t < tiles; ++t)
    std::copy(tile_frags[t].begin(), tile_frags[t].end(), r.frag_face.begin() + base[t]);
  for (index_t i = 0; i < H; ++i)
    for (index_t j = 0; j < W; ++j) {
      const std::int64_t t = std::int64_t(i / kTile) * p.tiles_x + j / kTile;
      r.pix_range[2 * (size_t(i) * W + j)] += index_t(base[t]);
    }
  return r;
}

SoftRenderGrad soft_render_backward(const float* verts, index_t N, const index_t* faces, index_t F,
                                    const float* opacity, const RenderCamera& cam, const SoftRenderSettings& s,
                                    const index_t* frag_face, std::int64_t K, const index_t* pix_range,
                                    const float* grad_diffuse, const float* grad_depth,
                                    const float* grad_alpha) {
  const char* fn = "soft_render_backward";
  const View view = make_view(cam, fn);
  validate(faces, F, N, opacity, s, fn);
  const index_t H = view.H, W = view.W;
  const std::int64_t P = std::int64_t(H) * W;
  for (std::int64_t k = 0; k < K; ++k) {
    if (frag_face[k] < 0 || frag_face[k] >= F) {
      throw std::invalid_argument(std::string(fn) + ": frag_face holds " + std::to_string(frag_face[k]) +
                                  ", outside [0, " + std::to_string(F) + ")");
    }
  }
  for (std::int64_t k = 0; k < P; ++k) {
    const std::int64_t a = pix_range[2 * k], c = pix_range[2 * k + 1];
    if (a < 0 || c < 0 || a + c > K) {
      throw std::invalid_argument(std::string(fn) + ": pix_range does not match frag_face");
    }
  }
  const int threads = thread_count(s.num_threads);
  // Only the faces that own fragments need their setup (reusing the forward's culling rules); they get
  // compact slots in order of first appearance, which keeps the per-thread accumulators local.
  std::vector<index_t> slot_of(static_cast<size_t>(F), kNone);
  std::vector<index_t> face_of;
  std::vector<index_t> frag_slot(static_cast<size_t>(K));
  for (std::int64_t k = 0; k < K; ++k) {
    index_t& sl = slot_of[frag_face[k]];
    if (sl == kNone) {
      sl = index_t(face_of.size());
      face_of.push_back(frag_face[k]);
    }
    frag_slot[k] = sl;
  }
  const std::int64_t S_ = std::int64_t(face_of.size());
  Face* fdata = tl_bwd_faces.get(size_t(std::max<std::int64_t>(S_, 1)));
  Corners* corners = tl_corners.get(size_t(std::max<std::int64_t>(S_, 1)));
  std::vector<std::uint8_t> bad(static_cast<size_t>(std::max<std::int64_t>(S_, 1)), 0);
  const std::int64_t chunk = 4096;
  parallel_for((S_ + chunk - 1) / chunk, threads, [&](std::int64_t c, int) {
    const std::int64_t end = std::min<std::int64_t>(S_, (c + 1) * chunk);
    for (std::int64_t k = c * chunk; k < end; ++k) {
      const index_t f = face_of[k];
      bad[k] = double(opacity[f]) <= s.min_opacity ||
               !setup_face(view, verts, faces + 3 * std::int64_t(f), double(opacity[f]), s.edge_width, fdata[k],
                          &corners[k]);
    }
  });
  for (std::int64_t k = 0; k < S_; ++k) {
    if (bad[k]) {
      throw std::invalid_argument(std::string(fn) + ": fragment of face " + std::to_string(face_of[k]) +
                                  " which the forward would not draw (inputs changed since the forward?)");
    }
  }

  // Deterministic accumulation: the rows are cut into fixed blocks (independent of the thread count);
  // each block sums its fragments' gradients, pixel by pixel in a fixed order, into records of its own
  // (one per slot it touches: d L / d (P0, P1, P2) in camera space (9) and d L / d opacity (1)); a final
  // pass adds the blocks' records in block order. So the result does not depend on the threads or their
  // schedule.
  const std::int64_t rows_per = 8;
  const std::int64_t nblocks = (std::int64_t(H) + rows_per - 1) / rows_per;
  const int nthreads = std::max(1, int(std::min<std::int64_t>(threads, nblocks)));
  // kept per calling thread between calls (capacity reuse); the workers use the caller's through references
  thread_local std::vector<std::vector<index_t>> tl_blk_slot;
  thread_local std::vector<std::vector<double>> tl_blk_acc;
  std::vector<std::vector<index_t>>& blk_slot = tl_blk_slot;
  std::vector<std::vector<double>>& blk_acc = tl_blk_acc;
  if (blk_slot.size() < size_t(nblocks)) {
    blk_slot.resize(size_t(nblocks));
    blk_acc.resize(size_t(nblocks));
  }
  // per worker thread and slot: the slot's record in the current block, -1 when it has none yet
  index_t* loc_all = tl_loc.get(size_t(nthreads) * size_t(S_) + 1);
  std::fill(loc_all, loc_all + size_t(nthreads) * size_t(S_), kNone);
  const double w = s.edge_width;
  parallel_for(nblocks, nthreads, [&](std::int64_t rb, int tid) {
    index_t* loc = loc_all + size_t(tid) * size_t(S_);
    std::vector<index_t>& bslot = blk_slot[size_t(rb)];
    std::vector<double>& bacc = blk_acc[size_t(rb)];
    bslot.clear();
    bacc.clear();
    auto record = [&](index_t slot) {
      if (loc[slot] == kNone) {
        loc[slot] = index_t(bslot.size());
        bslot.push_back(slot);
        bacc.resize(bacc.size() + 10, 0.0);
      }
      return bacc.data() + 10 * size_t(loc[slot]);
    };
    struct Rec {
      double a, T, cov, c, z, den;
      double dq[6];  // d cov / d (screen corners)
      int which;
      index_t slot;
    };
    std::vector<Rec> recs;
    for (index_t i = index_t(rb * rows_per); i < std::min<index_t>(H, index_t((rb + 1) * rows_per)); ++i) {
      for (index_t j = 0; j < W; ++j) {
        const std::int64_t pix = std::int64_t(i) * W + j;
        const index_t start = pix_range[2 * pix], cnt = pix_range[2 * pix + 1];
        if (cnt == 0) continue;
        const double gD = grad_diffuse[pix], gZ = grad_depth[pix], gA = grad_alpha[pix];
        if (gD == 0.0 && gZ == 0.0 && gA == 0.0) continue;
        const double u = j + 0.5, v = i + 0.5;
        double d[3];
        view.ray(u, v, d);
        const double inv_dl = 1.0 / std::sqrt(dot3(d, d));
        recs.resize(size_t(cnt));
        double T = 1.0;
        for (index_t k = 0; k < cnt; ++k) {
          Rec& rc = recs[size_t(k)];
          rc.slot = frag_slot[start + k];
          const Face& fc = fdata[rc.slot];
          rc.cov = coverage(fc, u, v, w, rc.dq);
          if (!(rc.cov > 0.0)) std::fill(rc.dq, rc.dq + 6, 0.0);  // coverage() leaves it unset then
          rc.a = fc.opacity * rc.cov;
          rc.T = T;
          rc.c = frag_diffuse(fc, d);
          rc.z = frag_depth(fc, d, &rc.den, &rc.which);
          T *= 1.0 - rc.a;
        }
        double S = 0.0;
        for (index_t k = cnt - 1; k >= 0; --k) {
          const Rec& rc = recs[size_t(k)];
          const Face& fc = fdata[rc.slot];
          const double(&FP)[3][3] = *reinterpret_cast<const double(*)[3][3]>(corners[rc.slot].data());
          const double val = gD * rc.c + gZ * rc.z + gA;
          const double g_a = rc.T * (val - S);
          S = val * rc.a + (1.0 - rc.a) * S;
          const double w_frag = rc.a * rc.T;
          double* gs = record(rc.slot);  // valid until the next record() call
          gs[9] += g_a * rc.cov;
          double g[3][3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};  // d L / d P_i (camera space)
          // coverage -> screen corners -> camera-space corners
          const double g_cov = g_a * fc.opacity;
          if (g_cov != 0.0 && rc.cov < 1.0) {
            const double* dq = rc.dq;
            for (int c = 0; c < 3; ++c) {
              const double gu = g_cov * dq[2 * c], gv = g_cov * dq[2 * c + 1];
              if (gu == 0.0 && gv == 0.0) continue;
              const double* Pc = FP[c];
              const double z = Pc[2];
              // u = cx - f x / z, v = cy + f y / z
              const double fz = view.f / z;
              g[c][0] -= gu * fz;
              g[c][1] += gv * fz;
              g[c][2] += (gu * Pc[0] - gv * Pc[1]) * (fz / z);
            }
          }
          // depth
          const double g_z = gZ * w_frag;
          if (g_z != 0.0) {
            if (rc.which >= 0) {
              g[rc.which][2] += -g_z;
            } else {
              // z = det(P0, P1, P2) / (n . d)
              const double* P0 = FP[0];
              const double* P1 = FP[1];
              const double* P2 = FP[2];
              double dn[3][3], dd[3][3], diff[3];
              cross3(P1, P2, dn[0]);
              cross3(P2, P0, dn[1]);
              cross3(P0, P1, dn[2]);
              for (int k2 = 0; k2 < 3; ++k2) diff[k2] = P1[k2] - P2[k2];
              cross3(diff, d, dd[0]);
              for (int k2 = 0; k2 < 3; ++k2) diff[k2] = P2[k2] - P0[k2];
              cross3(diff, d, dd[1]);
              for (int k2 = 0; k2 < 3; ++k2) diff[k2] = P0[k2] - P1[k2];
              cross3(diff, d, dd[2]);
              const double gz_den = g_z / rc.den;
              for (int c = 0; c < 3; ++c)
                for (int k2 = 0; k2 < 3; ++k2) g[c][k2] += gz_den * (dn[c][k2] - rc.z * dd[c][k2]);
            }
          }
          // diffuse = |n . d| / (|n| |d|)
          const double g_c = gD * w_frag;
          if (g_c != 0.0 && fc.nlen > 0.0) {
            const double nd = dot3(fc.n, d);
            const double inv_n = 1.0 / fc.nlen;
            const double cosv = nd * inv_n * inv_dl;
            const double scale = (nd >= 0 ? g_c : -g_c) * inv_n;
            double gn[3];  // d L / d n
            for (int k2 = 0; k2 < 3; ++k2) gn[k2] = scale * (d[k2] * inv_dl - cosv * fc.n[k2] * inv_n);
            double e1[3], e2[3], g1[3], g2[3];
            for (int k2 = 0; k2 < 3; ++k2) {
              e1[k2] = FP[1][k2] - FP[0][k2];
              e2[k2] = FP[2][k2] - FP[0][k2];
            }
            cross3(e2, gn, g1);
            cross3(gn, e1, g2);
            for (int k2 = 0; k2 < 3; ++k2) {
              g[1][k2] += g1[k2];
              g[2][k2] += g2[k2];
              g[0][k2] -= g1[k2] + g2[k2];
            }
          }
          for (int c = 0; c < 3; ++c)
            for (int k2 = 0; k2 < 3; ++k2) gs[3 * c + k2] += g[c][k2];
        }
      }
    }
    for (const index_t sl : bslot) loc[sl] = kNone;  // clean for the thread's next block
  });

  SoftRenderGrad out;
  double* acc = tl_acc.get(size_t(S_) * 10 + 1);
  std::fill(acc, acc + size_t(S_) * 10, 0.0);
  for (std::int64_t rb = 0; rb < nblocks; ++rb) {
    const std::vector<index_t>& bslot = blk_slot[size_t(rb)];
    const double* bacc = blk_acc[size_t(rb)].data();
    for (size_t r = 0; r < bslot.size(); ++r) {
      double* gs = acc + 10 * size_t(bslot[r]);
      for (int c = 0; c < 10; ++c) gs[c] += bacc[10 * r + c];
    }
  }
  double* gv = tl_gv.get(size_t(N) * 3 + 1);
  std::fill(gv, gv + size_t(N) * 3, 0.0);
  out.grad_opacity.assign(size_t(F), 0.0f);
  for (std::int64_t k = 0; k < S_; ++k) {
    const index_t* tri = faces + 3 * std::int64_t(face_of[k]);
    const double* gs = acc + size_t(k) * 10;
    for (int c = 0; c < 3; ++c)
      for (int k2 = 0; k2 < 3; ++k2) gv[3 * size_t(tri[c]) + k2] += gs[3 * c + k2];
    out.grad_opacity[size_t(face_of[k])] = float(gs[9]);
  }
  // camera = R world + t, so d L / d world = R^T d L / d camera
  out.grad_verts.assign(size_t(N) * 3, 0.0f);
  for (index_t n = 0; n < N; ++n) {
    const double* c = &gv[3 * size_t(n)];
    for (int k = 0; k < 3; ++k)
      out.grad_verts[3 * size_t(n) + k] = float(view.R[k] * c[0] + view.R[3 + k] * c[1] + view.R[6 + k] * c[2]);
  }
  return out;
}

}  // namespace dmesh
