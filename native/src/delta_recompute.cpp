#include "delta_recompute.h"

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <cstdlib>
#include <memory>

#ifdef __linux__
#include <sys/mman.h>
#endif

#include "parallel.h"

namespace dmesh {
namespace {

constexpr real_t kInf = std::numeric_limits<real_t>::infinity();
constexpr index_t kSearch = -2;  // a hint asking for the full search

struct V {
  real_t x, y, z;
};
inline V load(const real_t* p) { return {p[0], p[1], p[2]}; }
inline V operator+(V a, V b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline V operator-(V a, V b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline V operator-(V a) { return {-a.x, -a.y, -a.z}; }
inline V operator*(V a, real_t s) { return {a.x * s, a.y * s, a.z * s}; }
inline real_t dot(V a, V b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline V cross(V a, V b) { return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x}; }
inline real_t sgn(real_t v) { return v > 0 ? 1.0 : (v < 0 ? -1.0 : 0.0); }
inline bool is_zero(V a) { return a.x == 0 && a.y == 0 && a.z == 0; }

// Uninitialised scratch of n elements. Large blocks are 2 MiB aligned and marked for transparent huge
// pages: the first touch of hundreds of MB of fresh 4 KiB pages (one fault each) costs more than the
// backward's arithmetic.
struct FreeDeleter {
  void operator()(void* p) const { std::free(p); }
};
template <class T>
std::unique_ptr<T[], FreeDeleter> scratch(std::size_t n) {
  constexpr std::size_t kHuge = std::size_t(2) << 20;
  const std::size_t bytes = std::max<std::size_t>(n * sizeof(T), 1);
  void* p = nullptr;
  if (bytes >= kHuge) {
    p = std::aligned_alloc(kHuge, (bytes + kHuge - 1) / kHuge * kHuge);
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    if (p) madvise(p, (bytes + kHuge - 1) / kHuge * kHuge, MADV_HUGEPAGE);
#endif
  } else {
    p = std::malloc(bytes);
  }
  if (!p) throw std::bad_alloc();
  return std::unique_ptr<T[], FreeDeleter>(static_cast<T*>(p));
}

// Gradient slots: a point id (kNone: empty) and d/dp (3), d/dw each. The storage is left uninitialised
// (zero-filling hundreds of MB costs more than the backward itself): the writer must set or clear every
// slot; values are read only where the id is set.
struct SlotArray {
  std::size_t n;
  std::unique_ptr<index_t[], FreeDeleter> ids;
  std::unique_ptr<real_t[], FreeDeleter> vals;  // 4 per slot
  explicit SlotArray(std::size_t count) : n(count), ids(scratch<index_t>(count)), vals(scratch<real_t>(4 * count)) {}
  void clear(std::size_t s, std::size_t count = 1) { std::fill_n(ids.get() + s, count, kNone); }
  void set(std::size_t s, index_t id, V gp, real_t gw) {
    ids[s] = id;
    real_t* v = vals.get() + 4 * s;
    v[0] = gp.x;
    v[1] = gp.y;
    v[2] = gp.z;
    v[3] = gw;
  }
};

// Sums the slots of `segments` (in that order) per point. Each thread owns a contiguous range of point ids
// and adds that range's slots in slot order: the result does not depend on the thread count.
PointGradient reduce_slots(index_t N, std::initializer_list<const SlotArray*> segments, int num_threads) {
  PointGradient out;
  out.points.assign(3 * static_cast<std::size_t>(N), 0.0);
  out.weights.assign(static_cast<std::size_t>(N), 0.0);
  std::size_t total = 0;
  for (const SlotArray* s : segments) total += s->n;
  const int nt = threads_for(num_threads, total, std::size_t(4) * kParallelMin);
  // Part `part` of `nt` owns the point ids [N part / nt, N (part + 1) / nt).
  parallel_ranges(nt, 1, nt, [&](std::int64_t part, std::int64_t) {
    const index_t lo = index_t(std::int64_t(N) * part / nt), hi = index_t(std::int64_t(N) * (part + 1) / nt);
    real_t* gp = out.points.data();
    real_t* gw = out.weights.data();
    for (const SlotArray* seg : segments) {
      const index_t* ids = seg->ids.get();
      const std::size_t S = seg->n;
      for (std::size_t s = 0; s < S; ++s) {
        const index_t i = ids[s];
        if (i < lo || i >= hi) continue;  // also skips kNone
        const real_t* v = seg->vals.get() + 4 * s;
        gp[3 * i] += v[0];
        gp[3 * i + 1] += v[1];
        gp[3 * i + 2] += v[2];
        gw[i] += v[3];
      }
    }
  });
  return out;
}

// Gradients of one row (face) with respect to at most M distinct points.
template <int M>
struct LocalGrad {
  index_t id[M];
  real_t g[M][4];
  int n = 0;
  void operator()(index_t i, V gp, real_t gw) {
    int k = 0;
    while (k < n && id[k] != i) ++k;
    if (k == n) {  // the callers' bounds keep n <= M on valid input
      if (n == M) return;
      id[n] = i;
      g[n][0] = g[n][1] = g[n][2] = g[n][3] = 0.0;
      ++n;
    }
    g[k][0] += gp.x;
    g[k][1] += gp.y;
    g[k][2] += gp.z;
    g[k][3] += gw;
  }
  void store(SlotArray& out, std::size_t first) const {  // fills (or clears) M slots from `first`
    for (int k = 0; k < n; ++k) out.set(first + k, id[k], {g[k][0], g[k][1], g[k][2]}, g[k][3]);
    out.clear(first + n, M - n);
  }
};

// The orthocentre c = p_0 + x of tet t from the points (the formula of the header).
struct Ortho {
  V p0, r[3], cof[3], x;
  real_t det;
  bool clamped;
};
inline Ortho orthocentre(const DiagramView& dv, index_t t) {
  const index_t* tet = dv.tets + 4 * static_cast<std::size_t>(t);
  Ortho o;
  o.p0 = load(dv.points + 3 * tet[0]);
  real_t b[3];
  for (int j = 0; j < 3; ++j) {
    o.r[j] = load(dv.points + 3 * tet[j + 1]) - o.p0;
    b[j] = dot(o.r[j], o.r[j]) - (dv.weights[tet[j + 1]] - dv.weights[tet[0]]);
  }
  o.cof[0] = cross(o.r[1], o.r[2]);
  o.cof[1] = cross(o.r[2], o.r[0]);
  o.cof[2] = cross(o.r[0], o.r[1]);
  o.det = dot(o.r[0], o.cof[0]);
  o.clamped = std::abs(o.det) < 1e-18;
  if (o.clamped) o.det = o.det < 0 ? -1e-18 : 1e-18;
  o.x = (o.cof[0] * b[0] + o.cof[1] * b[1] + o.cof[2] * b[2]) * (1.0 / (2.0 * o.det));
  return o;
}

// Calls sink(id, gp, gw) for the 4 vertices of tet t with gc . dc/d(p, w): lambda = A^-T gc with
// A = 2 D (rows d_j = p_j - p_0) and D^-1 = (cof_0 cof_1 cof_2) / det, so lambda_j = cof_j . gc / (2 det);
// dL/db_j = lambda_j, dL/dA = -lambda x^T, b_j = |d_j|^2 - (w_j - w_0): dL/dd_j = 2 lambda_j (d_j - x).
// No gradient for a degenerate (clamped) tet.
template <class Sink>
void orthocentre_backward(const DiagramView& dv, index_t t, V gc, Sink&& sink) {
  const Ortho o = orthocentre(dv, t);
  if (o.clamped) return;
  const index_t* tet = dv.tets + 4 * static_cast<std::size_t>(t);
  const real_t inv = 0.5 / o.det;
  V gp0 = gc;
  real_t gw0 = 0.0;
  for (int j = 0; j < 3; ++j) {
    const real_t lam = dot(o.cof[j], gc) * inv;
    const V gd = (o.r[j] - o.x) * (2.0 * lam);
    sink(tet[j + 1], gd, -lam);
    gp0 = gp0 - gd;
    gw0 += lam;
  }
  sink(tet[0], gp0, gw0);
}

// Writes (or clears) slots 4t .. 4t + 3 of `slots` with gc . dc(t)/d(p, w) for the tet's 4 vertices, in
// the tet's vertex order (no gradient for gc = 0 or a clamped tet).
inline void store_orthocentre_adjoint(const DiagramView& dv, index_t t, V gc, SlotArray& slots) {
  const std::size_t first = 4 * static_cast<std::size_t>(t);
  slots.clear(first, 4);
  if (is_zero(gc)) return;
  const index_t* tv = dv.tets + first;
  orthocentre_backward(dv, t, gc, [&](index_t id, V gp, real_t gw) {
    const int m = id == tv[0] ? 0 : (id == tv[1] ? 1 : (id == tv[2] ? 2 : 3));
    slots.set(first + m, id, gp, gw);
  });
}

// The outward ray direction of hull face f from the points: the unit normal (p_b - p_a) x (p_c - p_a) / |.|
// times the sign (returned in *sign) that makes it agree with hull_dirs[f].
inline V hull_direction(const DiagramView& dv, index_t f, real_t* sign) {
  const index_t* fv = dv.faces + 3 * static_cast<std::size_t>(f);
  const V pa = load(dv.points + 3 * fv[0]);
  const V n = cross(load(dv.points + 3 * fv[1]) - pa, load(dv.points + 3 * fv[2]) - pa);
  const real_t s = dot(n, load(dv.hull_dirs + 3 * static_cast<std::size_t>(f))) < 0 ? -1.0 : 1.0;
  if (sign) *sign = s;
  const real_t len2 = dot(n, n);
  return len2 > 0 ? n * (s / std::sqrt(len2)) : V{0.0, 0.0, 0.0};
}

// Calls sink for the 3 vertices of face f with gu . du/dp, u = sign n / |n|, n = (p_b - p_a) x (p_c - p_a).
template <class Sink>
void normal_backward(const DiagramView& dv, index_t f, real_t sign, V gu, Sink&& sink) {
  const index_t* fv = dv.faces + 3 * static_cast<std::size_t>(f);
  const V pa = load(dv.points + 3 * fv[0]);
  const V e1 = load(dv.points + 3 * fv[1]) - pa, e2 = load(dv.points + 3 * fv[2]) - pa;
  const V n = cross(e1, e2);
  const real_t len = std::sqrt(dot(n, n));
  if (!(len > 0)) return;
  const V nh = n * (1.0 / len);
  const V g = gu * sign;
  const V gn = (g - nh * dot(g, nh)) * (1.0 / len);
  const V ge1 = cross(e2, gn), ge2 = cross(gn, e1);
  sink(fv[0], -(ge1 + ge2), 0.0);
  sink(fv[1], ge1, 0.0);
  sink(fv[2], ge2, 0.0);
}

inline V centre(const DiagramView& dv, index_t t) { return load(dv.orthocentres + 3 * static_cast<std::size_t>(t)); }

// The dual-edge sample of WDT face f: the midpoint of its segment, or ray_length out along its hull ray.
inline V edge_sample(const DiagramView& dv, index_t f, real_t ray_length) {
  const index_t* ft = dv.face_tets + 2 * static_cast<std::size_t>(f);
  const V c0 = centre(dv, ft[0]);
  if (ft[1] == kNone) return c0 + hull_direction(dv, f, nullptr) * ray_length;
  return (c0 + centre(dv, ft[1])) * 0.5;
}

// The dual edge of WDT face g: start a, and end b (segment) or unit direction b (ray, returns true).
inline bool dual_edge(const DiagramView& dv, index_t g, V* a, V* b, real_t* sign) {
  const index_t* ft = dv.face_tets + 2 * static_cast<std::size_t>(g);
  *a = centre(dv, ft[0]);
  if (ft[1] == kNone) {
    *b = hull_direction(dv, g, sign);
    return true;
  }
  *b = centre(dv, ft[1]);
  return false;
}

// Squared distance between the line (o, u), |u| = 1, and the segment [a, b] (or the ray a + s b, s >= 0),
// and the parameter t of the nearest point on the edge (clamped to [0, 1], or to >= 0 for a ray).
inline real_t line_edge_dist2(V o, V u, V a, V b, bool ray, real_t* t_out) {
  V pa = a - o;
  pa = pa - u * dot(pa, u);
  V e;
  if (ray) {
    e = b - u * dot(b, u);
  } else {
    V pb = b - o;
    e = pb - u * dot(pb, u) - pa;
  }
  const real_t ee = dot(e, e);
  real_t t = ee > 0 ? -dot(pa, e) / ee : 0.0;
  t = std::max(t, 0.0);
  if (!ray) t = std::min(t, 1.0);
  const V q = pa + e * t;
  if (t_out) *t_out = t;
  return dot(q, q);
}

// The dual line of a candidate face (a, b, c): origin o, unit direction u, and what the backward needs.
struct DualLine {
  V pa, e1, e2, n, o, u;
  real_t e11, e12, e22, area2, alpha, beta;
  bool ok;  // false for collinear or coincident vertices (no dual line)
};

inline DualLine dual_line(const DiagramView& dv, const index_t* f) {
  const real_t* P = dv.points;
  const real_t* W = dv.weights;
  DualLine L;
  L.pa = load(P + 3 * f[0]);
  L.e1 = load(P + 3 * f[1]) - L.pa;
  L.e2 = load(P + 3 * f[2]) - L.pa;
  L.n = cross(L.e1, L.e2);
  L.area2 = dot(L.n, L.n);
  L.e11 = dot(L.e1, L.e1);
  L.e12 = dot(L.e1, L.e2);
  L.e22 = dot(L.e2, L.e2);
  L.ok = L.area2 > 1e-12 * L.e11 * L.e22;
  if (!L.ok) return L;
  const real_t rb = L.e11 - (W[f[1]] - W[f[0]]);
  const real_t rc = L.e22 - (W[f[2]] - W[f[0]]);
  const real_t den = 2.0 * L.area2;
  L.alpha = (rb * L.e22 - rc * L.e12) / den;
  L.beta = (rc * L.e11 - rb * L.e12) / den;
  L.o = L.pa + L.e1 * L.alpha + L.e2 * L.beta;
  L.u = L.n * (1.0 / std::sqrt(L.area2));
  return L;
}

// Calls sink for the 3 vertices of face f with go . do/d(p, w) + gu . du/dp of its dual line.
template <class Sink>
void dual_line_backward(const index_t* f, const DualLine& L, V go, V gu, Sink&& sink) {
  // u = n / |n|, n = e1 x e2.
  const real_t len = std::sqrt(L.area2);
  const V gn = (gu - L.u * dot(gu, L.u)) * (1.0 / len);
  V ge1 = cross(L.e2, gn), ge2 = cross(gn, L.e1);
  // o = p_a + alpha e1 + beta e2 with G (alpha, beta) = r / 2, G the Gram matrix of (e1, e2) and
  // r = (e11 - (w_b - w_a), e22 - (w_c - w_a)): lambda = G^-1 (go.e1, go.e2), dL/dr = lambda / 2,
  // dL/dG = -lambda (alpha, beta)^T.
  const real_t ga = dot(go, L.e1), gb = dot(go, L.e2);
  ge1 = ge1 + go * L.alpha;
  ge2 = ge2 + go * L.beta;
  const real_t lam0 = (L.e22 * ga - L.e12 * gb) / L.area2;
  const real_t lam1 = (L.e11 * gb - L.e12 * ga) / L.area2;
  const real_t gr0 = 0.5 * lam0, gr1 = 0.5 * lam1;
  const real_t g11 = gr0 - lam0 * L.alpha, g22 = gr1 - lam1 * L.beta, g12 = -(lam0 * L.beta + lam1 * L.alpha);
  ge1 = ge1 + L.e1 * (2.0 * g11) + L.e2 * g12;
  ge2 = ge2 + L.e2 * (2.0 * g22) + L.e1 * g12;
  sink(f[0], go - ge1 - ge2, gr0 + gr1);
  sink(f[1], ge1, -gr0);
  sink(f[2], ge2, -gr1);
}

// Rows to process in a backward: active, with a nonzero upstream gradient on a vertex that has one.
template <class Has>
std::vector<index_t> rows_to_process(index_t K, const real_t* grad, const std::uint8_t* active, Has has) {
  std::vector<index_t> rows;
  for (index_t k = 0; k < K; ++k) {
    if (active && !active[k]) continue;
    for (int v = 0; v < 3; ++v) {
      if (grad[3 * k + v] != 0 && has(k, v)) {
        rows.push_back(k);
        break;
      }
    }
  }
  return rows;
}

inline int vertex_slot(const index_t* fv, index_t i) { return fv[0] == i ? 0 : (fv[1] == i ? 1 : 2); }

// The power bisector of (i, j) as a unit normal n (towards j) and offset t along it from p_i:
// pl = (n, t), distance of s = |(s - p_i).n - t|. False for coincident points (no bisector).
inline bool bisector_plane(V pi, real_t wi, V pj, real_t wj, real_t* pl) {
  const V d = pj - pi;
  const real_t len2 = dot(d, d);
  if (!(len2 > 0)) return false;
  const real_t len = std::sqrt(len2);
  const V n = d * (1.0 / len);
  pl[0] = n.x;
  pl[1] = n.y;
  pl[2] = n.z;
  pl[3] = 0.5 * (len - (wj - wi) / len);
  return true;
}

// The edges of one power cell as seen by the candidate search, structure of arrays: start a (an
// orthocentre), end b (an orthocentre, or a hull ray's unit direction), seg (1 for a segment, 0 for a ray)
// and tmax (1 for a segment, infinity for a ray).
struct CellEdges {
  std::vector<real_t> ax, ay, az, bx, by, bz, seg, tmax, d2;
  void clear() {
    for (auto* v : {&ax, &ay, &az, &bx, &by, &bz, &seg, &tmax}) v->clear();
  }
  void push(V a, V b, bool ray) {
    ax.push_back(a.x);
    ay.push_back(a.y);
    az.push_back(a.z);
    bx.push_back(b.x);
    by.push_back(b.y);
    bz.push_back(b.z);
    seg.push_back(ray ? 0.0 : 1.0);
    tmax.push_back(ray ? kInf : 1.0);
  }
};

// d2[k] = squared distance between the line (o, u) and edge k, measured in the plane normal to u with the
// orthonormal basis (b1, b2): both ends are projected (a segment's end relative to o, a ray's direction
// without the shift), then the nearest point of the projected edge to the line's trace. Elementwise
// arithmetic with no data-dependent branch, so the compiler vectorises it; compiled for AVX2 too (without
// FMA, which would round differently) and chosen at run time: the values are the same either way.
// A degenerate edge (ee = 0, so ae = 0) gets t = 0 through the floor on the denominator; max(t, 0) is
// (t + |t|) / 2, exact.
#if defined(__x86_64__) && defined(__linux__) && defined(__GNUC__)
#define DMESH_AVX2_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define DMESH_AVX2_CLONES
#endif
DMESH_AVX2_CLONES void edge_distances(index_t ne, const CellEdges& e, V o, V b1, V b2, real_t* __restrict d2) {
  const real_t* __restrict ax = e.ax.data();
  const real_t* __restrict ay = e.ay.data();
  const real_t* __restrict az = e.az.data();
  const real_t* __restrict bx = e.bx.data();
  const real_t* __restrict by = e.by.data();
  const real_t* __restrict bz = e.bz.data();
  const real_t* __restrict sg = e.seg.data();
  const real_t* __restrict tm = e.tmax.data();
  for (index_t k = 0; k < ne; ++k) {
    const real_t rax = ax[k] - o.x, ray = ay[k] - o.y, raz = az[k] - o.z;
    const real_t pax = rax * b1.x + ray * b1.y + raz * b1.z;
    const real_t pay = rax * b2.x + ray * b2.y + raz * b2.z;
    const real_t s = sg[k];
    const real_t rbx = bx[k] - s * o.x, rby = by[k] - s * o.y, rbz = bz[k] - s * o.z;
    const real_t pbx = rbx * b1.x + rby * b1.y + rbz * b1.z;
    const real_t pby = rbx * b2.x + rby * b2.y + rbz * b2.z;
    const real_t ex = pbx - s * pax, ey = pby - s * pay;
    const real_t ee = ex * ex + ey * ey;
    real_t t = -(pax * ex + pay * ey) / (ee > 1e-300 ? ee : 1e-300);
    t = 0.5 * (t + std::abs(t));
    t = t < tm[k] ? t : tm[k];
    const real_t qx = pax + t * ex, qy = pay + t * ey;
    d2[k] = qx * qx + qy * qy;
  }
}

// The half-spaces of a point's power cell against its neighbours j, structure of arrays: d = p_j - p_i,
// c = |d|^2 - (w_j - w_i), and the tolerance 1e-12 (|d|^2 + 1).
struct HalfSpaces {
  std::vector<real_t> dx, dy, dz, c, tol;
};

// The points that own a cell, ordered by their first (lowest-id) tet. Tets come out of the triangulation in
// a spatially coherent order, point ids need not (a point cloud's ids are arbitrary): visiting points in
// this order keeps the faces, samples and orthocentres that consecutive points touch close in memory.
// Only the visiting order changes; every output slot is still written by exactly one point.
std::vector<index_t> points_in_tet_order(const DiagramView& dv) {
  std::vector<index_t> count(static_cast<std::size_t>(dv.T) + 1, 0);
  for (index_t i = 0; i < dv.N; ++i) {
    if (dv.pt_offsets[i] < dv.pt_offsets[i + 1]) ++count[dv.pt_indices[dv.pt_offsets[i]] + 1];
  }
  for (index_t t = 0; t < dv.T; ++t) count[t + 1] += count[t];
  std::vector<index_t> order(static_cast<std::size_t>(count[dv.T]));
  for (index_t i = 0; i < dv.N; ++i) {
    if (dv.pt_offsets[i] < dv.pt_offsets[i + 1]) order[count[dv.pt_indices[dv.pt_offsets[i]]]++] = i;
  }
  return order;
}

}  // namespace

std::vector<real_t> delta_orthocentres(const DiagramView& dv, int num_threads) {
  std::vector<real_t> out(3 * static_cast<std::size_t>(dv.T));
  const int nt = threads_for(num_threads, std::size_t(dv.T), kParallelMin);
  parallel_ranges(dv.T, grain_for(dv.T, nt, 1024), nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t t = index_t(lo); t < index_t(hi); ++t) {
      const Ortho o = orthocentre(dv, t);
      const V c = o.p0 + o.x;
      out[3 * static_cast<std::size_t>(t)] = c.x;
      out[3 * static_cast<std::size_t>(t) + 1] = c.y;
      out[3 * static_cast<std::size_t>(t) + 2] = c.z;
    }
  });
  return out;
}

PointGradient orthocentre_adjoint(const DiagramView& dv, const real_t* grad, int num_threads) {
  SlotArray tet(4 * static_cast<std::size_t>(dv.T));
  const int nt = threads_for(num_threads, std::size_t(dv.T), kParallelMin);
  parallel_ranges(dv.T, grain_for(dv.T, nt, 1024), nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t t = index_t(lo); t < index_t(hi); ++t) {
      store_orthocentre_adjoint(dv, t, load(grad + 3 * static_cast<std::size_t>(t)), tet);
    }
  });
  return reduce_slots(dv.N, {&tet}, num_threads);
}

ExistingDeltaResult existing_delta_forward(const DiagramView& dv, const index_t* face_ids, index_t K,
                                           const index_t* cache_offsets, const index_t* cache_indices,
                                           real_t ray_length, const index_t* hint, int num_threads) {
  const real_t* P = dv.points;
  const real_t* W = dv.weights;
  ExistingDeltaResult out;
  out.neighbour.assign(3 * static_cast<std::size_t>(K), kNone);
  out.dist.assign(3 * static_cast<std::size_t>(K), ray_length);
  // The row of each requested face; repeated faces are copied from their first row at the end.
  std::vector<index_t> row_of_face(static_cast<std::size_t>(dv.F), kNone);
  std::vector<std::pair<index_t, index_t>> repeats;
  for (index_t k = 0; k < K; ++k) {
    index_t& r = row_of_face[face_ids[k]];
    if (r == kNone) r = k;
    else repeats.push_back({k, r});
  }
  // Per row: the sample and the face's vertices in one 40-byte record (one cache line to fetch per
  // (point, face) visit below, instead of two random reads).
  struct Row {
    real_t s[3];
    index_t fv[3];
    index_t pad;
  };
  std::vector<Row> recs(static_cast<std::size_t>(K));
  const std::vector<index_t> order = points_in_tet_order(dv);
  const index_t n_order = index_t(order.size());
  const int nt = threads_for(num_threads, std::size_t(K), kParallelMin);
  parallel_ranges(K, grain_for(K, nt, 1024), nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t k = index_t(lo); k < index_t(hi); ++k) {
      const V s = edge_sample(dv, face_ids[k], ray_length);
      const index_t* fv = dv.faces + 3 * static_cast<std::size_t>(face_ids[k]);
      recs[k] = Row{{s.x, s.y, s.z}, {fv[0], fv[1], fv[2]}, 0};
    }
  });
  // Per point i: its cached bisector planes (unit normal n, offset t |d| along it from p_i, neighbour j),
  // then every requested face containing i: delta = min_j |(s - p_i).n_j - t_j| over j not in the face.
  parallel_ranges(n_order, 64, nt, [&](std::int64_t lo, std::int64_t hi) {
    std::vector<real_t> planes;
    std::vector<index_t> plane_j;
    for (index_t oi = index_t(lo); oi < index_t(hi); ++oi) {
      const index_t i = order[oi];
      const index_t fb = dv.pf_offsets[i], fe = dv.pf_offsets[i + 1];
      bool any = false;
      for (index_t e = fb; e < fe && !any; ++e) any = row_of_face[dv.pf_indices[e]] != kNone;
      if (!any) continue;
      const V pi = load(P + 3 * i);
      // Planes are built only when some slot of i searches (no hint, or a hint of kSearch).
      bool search = hint == nullptr;
      for (index_t e = fb; e < fe && !search; ++e) {
        const index_t k = row_of_face[dv.pf_indices[e]];
        if (k != kNone) search = hint[3 * static_cast<std::size_t>(k) + vertex_slot(recs[k].fv, i)] == kSearch;
      }
      planes.clear();
      plane_j.clear();
      for (index_t e = cache_offsets[i]; e < cache_offsets[i + 1] && search; ++e) {
        const index_t j = cache_indices[e];
        real_t pl[4];
        if (!bisector_plane(pi, W[i], load(P + 3 * j), W[j], pl)) continue;  // coincident: no bisector
        planes.insert(planes.end(), pl, pl + 4);
        plane_j.push_back(j);
      }
      const index_t np = index_t(plane_j.size());
      constexpr index_t kAhead = 4;
      for (index_t e = fb; e < fe; ++e) {
        if (e + kAhead < fe) {
          const index_t ka = row_of_face[dv.pf_indices[e + kAhead]];
          if (ka != kNone) __builtin_prefetch(&recs[ka]);
        }
        const index_t k = row_of_face[dv.pf_indices[e]];
        if (k == kNone) continue;
        const Row& rec = recs[k];
        const index_t* fv = rec.fv;
        const V rel = V{rec.s[0], rec.s[1], rec.s[2]} - pi;
        const std::size_t slot = 3 * static_cast<std::size_t>(k) + vertex_slot(fv, i);
        if (hint && hint[slot] != kSearch) {  // reuse the given neighbour, recompute the distance
          const index_t j = hint[slot];
          real_t pl[4];
          if (j != kNone && bisector_plane(pi, W[i], load(P + 3 * j), W[j], pl)) {
            out.neighbour[slot] = j;
            out.dist[slot] = std::abs(rel.x * pl[0] + rel.y * pl[1] + rel.z * pl[2] - pl[3]);
          }
          continue;
        }
        real_t best = kInf;
        index_t best_j = kNone;
        for (index_t q = 0; q < np; ++q) {
          const index_t j = plane_j[q];
          if (j == fv[0] || j == fv[1] || j == fv[2]) continue;
          const real_t* pl = planes.data() + 4 * static_cast<std::size_t>(q);
          const real_t dist = std::abs(rel.x * pl[0] + rel.y * pl[1] + rel.z * pl[2] - pl[3]);
          if (dist < best) {
            best = dist;
            best_j = j;
          }
        }
        if (best_j == kNone) continue;
        out.neighbour[slot] = best_j;
        out.dist[slot] = best;
      }
    }
  });
  for (const auto& [k, first] : repeats) {
    for (int v = 0; v < 3; ++v) {
      out.neighbour[3 * k + v] = out.neighbour[3 * first + v];
      out.dist[3 * k + v] = out.dist[3 * first + v];
    }
  }
  return out;
}

PointGradient existing_delta_backward(const DiagramView& dv, const index_t* face_ids, index_t K,
                                      const index_t* neighbour, const real_t* grad, const std::uint8_t* active,
                                      real_t ray_length, int num_threads) {
  const real_t* P = dv.points;
  const real_t* W = dv.weights;
  const std::vector<index_t> rows =
      rows_to_process(K, grad, active, [&](index_t k, int v) { return neighbour[3 * k + v] != kNone; });
  const index_t R = index_t(rows.size());
  // Processed rows of each face, in increasing order (a face may be requested more than once).
  std::vector<index_t> first(static_cast<std::size_t>(dv.F), kNone), next(static_cast<std::size_t>(R), kNone);
  for (index_t r = R - 1; r >= 0; --r) {
    const index_t f = face_ids[rows[r]];
    next[r] = first[f];
    first[f] = r;
  }
  SlotArray bis(6 * static_cast<std::size_t>(R));   // per row: its 3 vertices i, then the 3 chosen j
  SlotArray tet(4 * static_cast<std::size_t>(dv.T)); // per tet: its 4 vertices
  std::vector<V> gsample(static_cast<std::size_t>(R));
  const int nt = threads_for(num_threads, std::size_t(R), kParallelMin);
  // 1. Bisector terms and the gradient with respect to each row's sample point.
  parallel_ranges(R, grain_for(R, nt, 1024), nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t r = index_t(lo); r < index_t(hi); ++r) {
      const index_t k = rows[r];
      const index_t f = face_ids[k];
      const index_t* fv = dv.faces + 3 * static_cast<std::size_t>(f);
      const V s = edge_sample(dv, f, ray_length);
      V gs = {0.0, 0.0, 0.0};
      bis.clear(6 * static_cast<std::size_t>(r), 6);
      for (int v = 0; v < 3; ++v) {
        const index_t j = neighbour[3 * k + v];
        const real_t gv = grad[3 * k + v];
        if (j == kNone || gv == 0) continue;
        const index_t i = fv[v];
        const V pi = load(P + 3 * i), d = load(P + 3 * j) - pi, rel = s - pi;
        const real_t len2 = dot(d, d);
        if (!(len2 > 0)) continue;
        const real_t len = std::sqrt(len2), dw = W[j] - W[i];
        const real_t a = dot(rel, d);
        // sigma = (s - p_i).d / |d| - (|d| - dw / |d|) / 2 and delta = |sigma|.
        const real_t sigma = a / len - 0.5 * (len - dw / len);
        const real_t g = gv * sgn(sigma);
        if (g == 0) continue;
        const V n = d * (1.0 / len);
        // d sigma / d d = rel / |d| - (a / |d|^2 + 1/2 + dw / (2 |d|^2)) n; d sigma / d s = n.
        const V gd = (rel * (1.0 / len) - n * (a / len2 + 0.5 + 0.5 * dw / len2)) * g;
        gs = gs + n * g;
        bis.set(6 * static_cast<std::size_t>(r) + v, i, -(gd + n * g), -0.5 * g / len);
        bis.set(6 * static_cast<std::size_t>(r) + 3 + v, j, gd, 0.5 * g / len);
      }
      gsample[r] = gs;
    }
  });
  // 2. Each tet gathers the sample gradients of its faces (half of a segment's midpoint, all of a ray's
  // start) and writes its orthocentre's adjoint once.
  parallel_ranges(dv.T, grain_for(dv.T, nt, 1024), nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t t = index_t(lo); t < index_t(hi); ++t) {
      V gc = {0.0, 0.0, 0.0};
      for (int m = 0; m < 4; ++m) {
        const index_t f = dv.tet_faces[4 * static_cast<std::size_t>(t) + m];
        const real_t share = dv.face_tets[2 * static_cast<std::size_t>(f) + 1] == kNone ? 1.0 : 0.5;
        for (index_t r = first[f]; r != kNone; r = next[r]) gc = gc + gsample[r] * share;
      }
      store_orthocentre_adjoint(dv, t, gc, tet);
    }
  });
  // 3. Hull rows: the ray direction's dependence on the face's vertices (few rows, in row order).
  std::vector<index_t> hull_rows;
  for (index_t r = 0; r < R; ++r) {
    if (dv.face_tets[2 * static_cast<std::size_t>(face_ids[rows[r]]) + 1] == kNone) hull_rows.push_back(r);
  }
  SlotArray hull(3 * hull_rows.size());
  hull.clear(0, hull.n);
  for (std::size_t h = 0; h < hull_rows.size(); ++h) {
    const index_t r = hull_rows[h];
    const index_t f = face_ids[rows[r]];
    real_t sign = 1.0;
    hull_direction(dv, f, &sign);
    int m = 0;
    normal_backward(dv, f, sign, gsample[r] * ray_length,
                    [&](index_t id, V gp, real_t gw) { hull.set(3 * h + m++, id, gp, gw); });
  }
  return reduce_slots(dv.N, {&bis, &tet, &hull}, num_threads);
}

CandidateDeltaResult candidate_delta_forward(const DiagramView& dv, const index_t* cand, index_t C,
                                             real_t ray_length, const index_t* hint, int num_threads) {
  const real_t* P = dv.points;
  const real_t* W = dv.weights;
  const index_t N = dv.N;
  CandidateDeltaResult r;
  r.edge.assign(3 * static_cast<std::size_t>(C), kNone);
  r.crosses.assign(3 * static_cast<std::size_t>(C), 0);
  r.dist.assign(3 * static_cast<std::size_t>(C), ray_length);

  // 1. The dual line of every candidate, and an orthonormal basis (b1, b2) of the plane normal to it.
  struct Line {
    V o, u, b1, b2;
    bool ok;
  };
  std::vector<Line> lines(static_cast<std::size_t>(C));
  const int nt_lines = threads_for(num_threads, std::size_t(C), kParallelMin);
  parallel_ranges(C, grain_for(C, nt_lines, 1024), nt_lines, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t c = index_t(lo); c < index_t(hi); ++c) {
      const DualLine L = dual_line(dv, cand + 3 * static_cast<std::size_t>(c));
      Line& ln = lines[c];
      ln.ok = L.ok;
      if (!L.ok) continue;
      ln.o = L.o;
      ln.u = L.u;
      const real_t ax = std::abs(L.u.x), ay = std::abs(L.u.y), az = std::abs(L.u.z);
      const V axis = (ax <= ay && ax <= az) ? V{1, 0, 0} : (ay <= az ? V{0, 1, 0} : V{0, 0, 1});
      const V b1 = cross(L.u, axis);
      ln.b1 = b1 * (1.0 / std::sqrt(dot(b1, b1)));
      ln.b2 = cross(L.u, ln.b1);
    }
  });

  // 2. The (candidate, vertex) slots of each point, in slot order (counting sort).
  std::vector<index_t> slot_off(static_cast<std::size_t>(N) + 1, 0);
  for (index_t c = 0; c < C; ++c) {
    if (!lines[c].ok) continue;
    for (int v = 0; v < 3; ++v) ++slot_off[cand[3 * static_cast<std::size_t>(c) + v] + 1];
  }
  for (index_t i = 0; i < N; ++i) slot_off[i + 1] += slot_off[i];
  std::vector<index_t> slots(static_cast<std::size_t>(slot_off[N]));
  {
    std::vector<index_t> cursor(slot_off.begin(), slot_off.end() - 1);
    for (index_t c = 0; c < C; ++c) {
      if (!lines[c].ok) continue;
      for (int v = 0; v < 3; ++v) slots[cursor[cand[3 * static_cast<std::size_t>(c) + v]]++] = 3 * c + v;
    }
  }

  // 3. Per point: its cell (the dual edges of its faces, in face order: a segment between two orthocentres
  // of its tets, or a ray from one along a hull face's direction, as CellEdges) and the half-spaces against
  // its neighbours, loaded once; then per slot the crossing test and the nearest edge, measured in the 2D
  // projection along the line (the same distance as in 3D; edge_distances), the first edge in face order
  // on a tie. The chosen edge's distance is recomputed in 3D (what the backward differentiates).
  const int nt = threads_for(num_threads, std::size_t(slot_off[N]), kParallelMin / 4);
  parallel_ranges(N, 64, nt, [&](std::int64_t lo, std::int64_t hi) {
    // Per tet, its position in the current point's tet list while the cell is built (kNone otherwise): kept
    // by the thread across ranges and calls, so it is filled once.
    static thread_local std::vector<index_t> local_tet;
    if (local_tet.size() < static_cast<std::size_t>(dv.T)) local_tet.assign(dv.T, kNone);
    std::vector<V> cell_v;
    std::vector<index_t> eg;
    CellEdges edges;
    HalfSpaces half;
    for (index_t i = index_t(lo); i < index_t(hi); ++i) {
      if (slot_off[i] == slot_off[i + 1]) continue;
      const V pi = load(P + 3 * i);
      const index_t* tb = dv.pt_indices + dv.pt_offsets[i];
      const index_t nt_i = dv.pt_offsets[i + 1] - dv.pt_offsets[i];
      // The cell is built on the first slot of i that searches (with hints, most slots do not).
      bool cell_built = false;
      auto build_cell = [&]() {
        cell_built = true;
        cell_v.resize(nt_i);
        for (index_t k = 0; k < nt_i; ++k) {
          cell_v[k] = centre(dv, tb[k]);
          local_tet[tb[k]] = k;
        }
        eg.clear();
        edges.clear();
        for (index_t e = dv.pf_offsets[i]; e < dv.pf_offsets[i + 1]; ++e) {
          const index_t g = dv.pf_indices[e];
          const index_t* ft = dv.face_tets + 2 * static_cast<std::size_t>(g);
          const index_t a = local_tet[ft[0]];
          if (a == kNone) continue;  // inconsistent input: the face's tet is not the point's
          index_t b;
          if (ft[1] == kNone) {
            b = index_t(cell_v.size());
            cell_v.push_back(hull_direction(dv, g, nullptr));
          } else {
            b = local_tet[ft[1]];
            if (b == kNone) continue;
          }
          eg.push_back(g);
          edges.push(cell_v[a], cell_v[b], ft[1] == kNone);
        }
        edges.d2.resize(eg.size());
        for (index_t k = 0; k < nt_i; ++k) local_tet[tb[k]] = kNone;
      };
      const index_t nn = dv.nb_offsets[i + 1] - dv.nb_offsets[i];
      for (auto* v : {&half.dx, &half.dy, &half.dz, &half.c, &half.tol}) v->resize(nn);
      for (index_t k = 0; k < nn; ++k) {
        const index_t j = dv.nb_indices[dv.nb_offsets[i] + k];
        const V d = load(P + 3 * j) - pi;
        const real_t dd = dot(d, d);
        half.dx[k] = d.x;
        half.dy[k] = d.y;
        half.dz[k] = d.z;
        half.c[k] = dd - (W[j] - W[i]);
        half.tol[k] = 1e-12 * (dd + 1.0);
      }
      for (index_t sl = slot_off[i]; sl < slot_off[i + 1]; ++sl) {
        // Slots visit their candidates' lines in random order: fetch a few slots ahead.
        constexpr index_t kAhead = 6;
        if (sl + kAhead < slot_off[N]) {
          const char* next = reinterpret_cast<const char*>(&lines[slots[sl + kAhead] / 3]);
          __builtin_prefetch(next);
          __builtin_prefetch(next + sizeof(Line) - 1);
        }
        const index_t s = slots[sl];
        const Line& ln = lines[s / 3];
        // Crossing test (as argmin_search.cpp's line_crosses_cell): the interval of the line where
        // pow(x, i) <= pow(x, j) for every neighbour j must be non-empty. The loop stops as soon as it is
        // empty (a branch-free pass over every neighbour was measured slower: the line misses almost every
        // cell, after a few neighbours).
        {
          const V rel = ln.o - pi;
          real_t lo = -kInf, hi = kInf;
          bool crosses = true;
          for (index_t k = 0; k < nn && crosses; ++k) {
            const V d = {half.dx[k], half.dy[k], half.dz[k]};
            const real_t g = 2 * dot(rel, d) - half.c[k];
            const real_t hh = 2 * dot(ln.u, d);
            if (std::abs(hh) <= half.tol[k]) {
              if (g > half.tol[k]) crosses = false;
              continue;
            }
            const real_t t = -g / hh;
            if (hh > 0) hi = std::min(hi, t);
            else lo = std::max(lo, t);
            if (lo >= hi) crosses = false;
          }
          if (crosses && lo < hi) {
            r.crosses[s] = 1;
            r.dist[s] = 0.0;
            continue;
          }
        }
        if (hint && hint[s] != kSearch) {  // reuse the given edge, recompute the distance
          const index_t g = hint[s];
          if (g != kNone) {
            V a, b;
            const bool ray = dual_edge(dv, g, &a, &b, nullptr);
            r.edge[s] = g;
            r.dist[s] = std::sqrt(line_edge_dist2(ln.o, ln.u, a, b, ray, nullptr));
          }
          continue;
        }
        if (!cell_built) build_cell();
        const index_t ne = index_t(eg.size());
        edge_distances(ne, edges, ln.o, ln.b1, ln.b2, edges.d2.data());
        real_t best = kInf;
        index_t best_e = kNone;
        for (index_t k = 0; k < ne; ++k) {
          if (edges.d2[k] < best) {
            best = edges.d2[k];
            best_e = k;
          }
        }
        if (best_e == kNone) continue;
        const index_t best_g = eg[best_e];
        V a, b;
        const bool ray = dual_edge(dv, best_g, &a, &b, nullptr);
        r.edge[s] = best_g;
        r.dist[s] = std::sqrt(line_edge_dist2(ln.o, ln.u, a, b, ray, nullptr));
      }
    }
  });
  return r;
}

PointGradient candidate_delta_backward(const DiagramView& dv, const index_t* cand, index_t C,
                                       const index_t* edge, const std::uint8_t* crosses, const real_t* grad,
                                       const std::uint8_t* active, int num_threads) {
  constexpr int M = 18;  // 3 face vertices, and per vertex the 3 vertices and 2 apexes of its edge's face
  const std::vector<index_t> rows = rows_to_process(
      C, grad, active, [&](index_t k, int v) { return edge[3 * k + v] != kNone && !crosses[3 * k + v]; });
  const index_t R = index_t(rows.size());
  SlotArray slots(static_cast<std::size_t>(R) * M);
  const int nt = threads_for(num_threads, std::size_t(R), kParallelMin / 4);
  parallel_ranges(R, 512, nt, [&](std::int64_t lo, std::int64_t hi) {
    for (index_t r = index_t(lo); r < index_t(hi); ++r) {
      const index_t k = rows[r];
      const index_t* f = cand + 3 * static_cast<std::size_t>(k);
      const DualLine L = dual_line(dv, f);
      LocalGrad<M> G;
      if (!L.ok) {
        G.store(slots, static_cast<std::size_t>(r) * M);
        continue;
      }
      V go = {0.0, 0.0, 0.0}, gu = {0.0, 0.0, 0.0};
      for (int v = 0; v < 3; ++v) {
        const index_t g = edge[3 * k + v];
        const real_t gv = grad[3 * k + v];
        if (g == kNone || crosses[3 * k + v] || gv == 0) continue;
        const index_t* ft = dv.face_tets + 2 * static_cast<std::size_t>(g);
        V a, b;
        real_t sign = 1.0;
        const bool ray = dual_edge(dv, g, &a, &b, &sign);
        real_t t = 0.0;
        line_edge_dist2(L.o, L.u, a, b, ray, &t);
        // q = P_u r with r = a - o + t (b - a) (segment) or a - o + t b (ray), t held fixed.
        const V rr = ray ? a - L.o + b * t : a - L.o + (b - a) * t;
        const real_t ru = dot(rr, L.u);
        const V q = rr - L.u * ru;
        const real_t D = std::sqrt(dot(q, q));
        if (!(D > 0)) continue;
        const V gq = q * (gv / D);
        const real_t gqu = dot(gq, L.u);
        const V gr = gq - L.u * gqu;
        gu = gu - rr * gqu - gq * ru;
        go = go - gr;
        orthocentre_backward(dv, ft[0], ray ? gr : gr * (1.0 - t), G);
        if (ray) normal_backward(dv, g, sign, gr * t, G);
        else orthocentre_backward(dv, ft[1], gr * t, G);
      }
      dual_line_backward(f, L, go, gu, G);
      G.store(slots, static_cast<std::size_t>(r) * M);
    }
  });
  return reduce_slots(dv.N, {&slots}, num_threads);
}

std::vector<std::uint8_t> csr_rows_changed(const index_t* off_a, const index_t* idx_a, const index_t* off_b,
                                           const index_t* idx_b, index_t rows) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(rows));
  for (index_t r = 0; r < rows; ++r) {
    const index_t la = off_a[r + 1] - off_a[r];
    out[r] = la != off_b[r + 1] - off_b[r] || !std::equal(idx_a + off_a[r], idx_a + off_a[r + 1], idx_b + off_b[r]);
  }
  return out;
}

}  // namespace dmesh
