"""Differentiable face existence probabilities (DESIGN.md section 4; paper section 3.3 and Eq. 10).

Letters: N points, T tets, F faces of the current WDT, C candidate faces not in the WDT.

One pass: WDT -> power diagram -> neighbour cache and candidates -> native argmin searches (discrete,
no gradient) -> torch recomputation of the chosen distances (gradients reach positions and weights
through bisector planes, orthocentres and hull-ray directions) -> Delta -> Lambda.

- Faces of the WDT: Delta = mean over the 3 vertices i of the distance from the sample point of the face's
  dual edge (midpoint, or `ray_length` out along a hull ray) to the nearest bisector plane H(i, j) with j a
  cached neighbour of i not in the face (the boundary of i's reduced power cell). Delta >= 0.
- Candidates not in the WDT whose vertices all own a power cell: Delta = -mean over the 3 vertices of the
  distance between the face's dual line and the vertex's power cell (0 where the line crosses the cell).
- Faces with a hidden vertex: Delta = 0 and probability 0. Collinear or coincident candidates (no dual
  line): Delta = -ray_length (no gradient) and probability 0 in effect.
- Lambda_wdt = sigmoid(alpha_wdt * min(Delta, 10 / alpha_wdt)); Lambda_real = dmin of the three real values
  (softmin weights detached); Lambda = Lambda_wdt * Lambda_real. Optionally (paper Eq. 10) Lambda_wdt is
  multiplied by the power-cell existence factor min_i sigmoid(alpha_pc (sum_F delta_i(F) - eps_pc)).

Cost control (a deviation from upstream, `ProbabilityConfig.active_band`): every Delta is computed exactly
in the native searches, but only faces that can carry a gradient are recomputed in torch: WDT faces below
Lambda_wdt's clamp (Delta < 10/alpha) and non-WDT faces with Delta > -active_band/alpha (Lambda_wdt >
sigmoid(-10) = 4.5e-5 for the default band of 10). The others keep their exact values without a gradient.
`active_band=None` recomputes every face (exact gradients everywhere; `delta()` always does).
"""
from __future__ import annotations

from dataclasses import dataclass

import time
from contextlib import contextmanager

import numpy as np
import torch

from dmesh import geometry, native
from dmesh.candidates import CandidateFaces, NeighbourCache, knn_triples
from dmesh.wdt import Csr, PowerDiagram, face_keys, triangulate


@dataclass(frozen=True)
class ProbabilityConfig:
    """Settings of the face existence probability (defaults: the paper's, for a unit-scale domain)."""

    alpha_wdt: float = 1000.0      # sigmoid sharpness of Lambda_wdt for a unit domain
    alpha_real: float = 100.0      # softmin sharpness of Lambda_real
    ray_length: float = 500.0      # distance out along a hull ray to its sample point, unit domain
    domain_scale: float = 1.0      # domain size: alpha_wdt is divided by it, ray_length multiplied
    knn_interval: int = 10         # add kNN candidate triples every this many passes (0: never)
    knn_k: int = 8                 # neighbours per point for kNN triples
    knn_thresholds: tuple = (0.0, 0.2, 0.4, 0.6, 0.8)  # real-value thresholds of the kNN passes
    active_band: float | None = 10.0  # non-WDT faces with Delta < -active_band/alpha get no gradient
    power_cell_factor: bool = False  # multiply by the power-cell existence factor (paper Eq. 10)
    alpha_pc: float = 1000.0       # sigmoid sharpness of the power-cell factor
    eps_pc: float = 1e-4           # threshold of the power-cell factor

    def __post_init__(self):
        for name in ("alpha_wdt", "alpha_real", "ray_length", "domain_scale", "alpha_pc"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ProbabilityConfig.{name} must be positive, got {getattr(self, name)}")
        if self.knn_interval < 0 or self.knn_k < 2:
            raise ValueError("ProbabilityConfig: knn_interval must be >= 0 and knn_k >= 2")

    @property
    def alpha(self) -> float:
        return self.alpha_wdt / self.domain_scale

    @property
    def ray(self) -> float:
        return self.ray_length * self.domain_scale


@dataclass
class DualEdges:
    """Power-diagram edges of some WDT faces, recomputed in torch (float64, differentiable).

    Attributes:
        start: (K, 3) orthocentre of the face's first tet.
        end: (K, 3) orthocentre of the second tet, or the unit outward ray direction for hull faces.
        sample: (K, 3) midpoint of a segment, or start + ray_length * direction for a ray.
        is_ray: (K,) bool.
    """

    start: torch.Tensor
    end: torch.Tensor
    sample: torch.Tensor
    is_ray: torch.Tensor


def dual_edges(points: torch.Tensor, weights: torch.Tensor, pd: PowerDiagram, face_ids: np.ndarray,
               ray_length: float) -> DualEdges:
    """Recomputes the dual edges of WDT faces `face_ids` ((K,) ints) in torch from (points, weights) and the
    diagram's combinatorics; only the orthocentres of their tets are computed."""
    face_ids = np.asarray(face_ids, dtype=np.int64)
    ft = pd.face_tets[face_ids]
    tets, inverse = np.unique(np.maximum(ft, 0), return_inverse=True)
    inverse = torch.from_numpy(inverse.reshape(-1, 2))
    cc = geometry.orthocentres(points, weights, torch.from_numpy(pd.tets[tets]).long())
    is_ray = torch.from_numpy(pd.is_hull[face_ids])
    start = cc[inverse[:, 0]]
    end = cc[inverse[:, 1]]
    hull = np.flatnonzero(pd.is_hull[face_ids])
    if len(hull):
        n = geometry.face_normals(points, torch.from_numpy(pd.faces[face_ids[hull]]).long())
        sign = torch.sign((n.detach() * torch.from_numpy(pd.ray_dirs[face_ids[hull]])).sum(-1))
        sign = torch.where(sign == 0, torch.ones_like(sign), sign)
        end = end.index_put((torch.from_numpy(hull),), n * sign[:, None])
    sample = torch.where(is_ray[:, None], start + ray_length * end, 0.5 * (start + end))
    return DualEdges(start, end, sample, is_ray)


def _numpy_edges(pd: PowerDiagram, ray_length: float):
    """(F, 3) start, (F, 3) end (ray direction for hull faces), (F, 3) sample of every dual edge (float64)."""
    start = pd.orthocentres[pd.face_tets[:, 0]]
    hull = pd.is_hull[:, None]
    end = np.where(hull, pd.ray_dirs, pd.orthocentres[np.maximum(pd.face_tets[:, 1], 0)])
    sample = np.where(hull, start + ray_length * end, 0.5 * (start + end))
    return start, end, sample


def existing_deltas(points: torch.Tensor, weights: torch.Tensor, pd: PowerDiagram, neighbours: Csr,
                    ray_length: float, upper: float | None = None,
                    face_ids: np.ndarray | None = None) -> torch.Tensor:
    """(K, 3) float64 per-vertex delta of WDT faces `face_ids` ((K,) ints; None: all F faces): distance of
    the face's dual-edge sample to the nearest cached bisector plane of the vertex's reduced cell;
    `ray_length` where a vertex has no such plane.

    Faces whose mean delta is at least `upper` (where Lambda_wdt's clamp stops every gradient) keep the
    native value without a gradient; the others are recomputed in torch.
    """
    p = native.as_points(points)
    w = native.as_weights(weights, len(p))
    ids = np.arange(len(pd.faces)) if face_ids is None else np.asarray(face_ids, dtype=np.int64)
    faces_np = pd.faces if face_ids is None else pd.faces[ids]
    start = pd.orthocentres[pd.face_tets[ids, 0]]
    hull = pd.is_hull[ids, None]
    other = pd.orthocentres[np.maximum(pd.face_tets[ids, 1], 0)]
    sample = np.where(hull, start + ray_length * pd.ray_dirs[ids], 0.5 * (start + other))
    j, dist = native.nearest_planes_raw(p, w, faces_np, sample, neighbours.offsets, neighbours.indices)
    dist = np.where(j >= 0, dist, ray_length)
    out = torch.from_numpy(dist)
    active = np.arange(len(ids)) if upper is None else np.flatnonzero(dist.mean(1) < upper)
    if len(active) == 0:
        return out
    edges = dual_edges(points, weights, pd, ids[active], ray_length)
    faces = torch.from_numpy(faces_np[active]).long()
    jt = torch.from_numpy(j[active]).long()
    valid = jt >= 0
    jj = torch.where(valid, jt, faces)  # a harmless stand-in index where there is none, masked below
    d = geometry.bisector_distance(points[faces], weights[faces], points[jj], weights[jj],
                                   edges.sample[:, None, :].expand(-1, 3, -1))
    d = torch.where(valid, d, torch.full_like(d, ray_length))
    return out.index_put((torch.from_numpy(active),), d)


def nonexisting_deltas(points: torch.Tensor, weights: torch.Tensor, pd: PowerDiagram, faces: np.ndarray,
                       ray_length: float, band: float | None = None) -> torch.Tensor:
    """(C, 3) float64 per-vertex distance between each candidate's dual line and the vertex's power cell
    (0 where the line crosses it). Candidates must not be WDT faces and their vertices must own cells.
    Collinear or coincident candidates get `ray_length` (no gradient). Faces whose mean distance is at
    least `band` keep the native value without a gradient (Lambda_wdt < sigmoid(-alpha band) there)."""
    out = torch.full((len(faces), 3), float(ray_length), dtype=torch.float64)
    if len(faces) == 0:
        return out
    p64 = native.as_points(points)
    w64 = native.as_weights(weights, len(p64))
    e1 = p64[faces[:, 1]] - p64[faces[:, 0]]
    e2 = p64[faces[:, 2]] - p64[faces[:, 0]]
    area2 = (np.cross(e1, e2) ** 2).sum(1)
    good = np.flatnonzero(area2 > 1e-12 * (e1 ** 2).sum(1) * (e2 ** 2).sum(1))
    if len(good) == 0:
        return out
    fg = np.ascontiguousarray(faces[good], dtype=np.int32)
    with torch.no_grad():
        origin, direction, _ = geometry.dual_lines(torch.from_numpy(p64), torch.from_numpy(w64),
                                                   torch.from_numpy(fg).long())
    start, end, _ = _numpy_edges(pd, ray_length)
    edge, crosses, dist = native.nearest_cell_edges_raw(
        p64, w64, fg, origin.numpy(), direction.numpy(), pd.point_faces.offsets, pd.point_faces.indices,
        start, end, pd.is_hull.astype(np.uint8), pd.point_neighbors.offsets, pd.point_neighbors.indices)
    dist = np.where((edge >= 0) | (crosses > 0), dist, ray_length)
    out = out.index_put((torch.from_numpy(good),), torch.from_numpy(dist))
    sel = np.arange(len(good)) if band is None else np.flatnonzero(dist.mean(1) < band)
    # Only elements with a gradient are recomputed: an edge was chosen and the line misses the cell.
    sel = sel[((edge[sel] >= 0) & (crosses[sel] == 0)).any(1)]
    if len(sel) == 0:
        return out
    o, u, _ = geometry.dual_lines(points, weights, torch.from_numpy(fg[sel]).long())
    et = edge[sel]
    has_edge = et >= 0
    used, inverse = np.unique(np.maximum(et, 0), return_inverse=True)
    edges = dual_edges(points, weights, pd, used, ray_length)
    inv = torch.from_numpy(inverse.reshape(-1, 3))
    d = geometry.line_segment_distance(o[:, None, :].expand(-1, 3, -1), u[:, None, :].expand(-1, 3, -1),
                                       edges.start[inv], edges.end[inv], edges.is_ray[inv])
    keep = torch.from_numpy(has_edge & (crosses[sel] == 0))
    d = torch.where(keep, d, torch.from_numpy(dist[sel]))
    return out.index_put((torch.from_numpy(good[sel]),), d)


def dmin(values: torch.Tensor, alpha: float) -> torch.Tensor:
    """Differentiable minimum over the last axis: sum softmax(-alpha x)_k x_k, softmax weights detached."""
    with torch.no_grad():
        wts = torch.softmax(-alpha * values, dim=-1)
    return (wts * values).sum(-1)


def lambda_wdt(delta: torch.Tensor, alpha: float) -> torch.Tensor:
    """sigmoid(alpha * min(delta, 10 / alpha)): saturates at sigmoid(10) for faces that surely exist."""
    return torch.sigmoid(alpha * delta.clamp_max(10.0 / alpha))


@dataclass
class FaceProbabilities:
    """Probabilities of the scored faces: the WDT faces first, then the candidates not in the WDT.

    Attributes:
        faces: (F + C, 3) int64 sorted vertex triples.
        in_wdt: (F + C,) bool, True for faces of the current WDT.
        delta: (F + C,) float signed distance Delta (>= 0 in the WDT, <= 0 outside).
        prob_wdt: (F + C,) Lambda_wdt; prob_real: (F + C,) Lambda_real; prob: (F + C,) Lambda.
        power_diagram: the `PowerDiagram` of this pass.
    """

    faces: torch.Tensor
    in_wdt: torch.Tensor
    delta: torch.Tensor
    prob_wdt: torch.Tensor
    prob_real: torch.Tensor
    prob: torch.Tensor
    power_diagram: PowerDiagram


class ProbabilityState:
    """Candidate faces and the neighbour cache of one optimisation phase, plus a pass counter."""

    def __init__(self, num_points: int, config: ProbabilityConfig | None = None):
        self.config = config or ProbabilityConfig()
        self.cache = NeighbourCache(num_points)
        self.candidates = CandidateFaces(num_points)
        self.passes = 0

    @property
    def num_points(self) -> int:
        return self.cache.num_points


@contextmanager
def _stage(timings: dict | None, name: str):
    """Adds the wall time of the block to timings[name] (seconds) when timings is a dict."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        if timings is not None:
            timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0


def face_probabilities(points: torch.Tensor, weights: torch.Tensor, reals: torch.Tensor | None,
                       state: ProbabilityState, extra_candidates: np.ndarray | None = None,
                       timings: dict | None = None) -> FaceProbabilities:
    """One full differentiable pass; updates `state` (cache and candidates grow).

    Args:
        points: (N, 3) float tensor; weights: (N,) float tensor; reals: (N,) float tensor in [0, 1], or
            None to score existence only (prob_real = 1).
        state: the phase's `ProbabilityState` over the same N points.
        extra_candidates: optional (M, 3) ints added to the candidates before scoring.
        timings: optional dict that receives the seconds spent per stage (wdt, power_diagram, candidates,
            knn, existing, nonexisting, probabilities).
    """
    cfg = state.config
    n = len(points)
    if n != state.num_points:
        raise ValueError(f"the phase state was made for {state.num_points} points, got {n}; start a new phase")
    with _stage(timings, "wdt"):
        tri = triangulate(points, weights)
    with _stage(timings, "power_diagram"):
        pd = PowerDiagram(points, weights, tri.tets, tri.neighbors)
    with _stage(timings, "candidates"):
        cache = state.cache.update(pd.point_neighbors)
        wdt_keys = np.sort(face_keys(pd.faces, n))
        state.candidates.add_sorted_keys(wdt_keys)
        if extra_candidates is not None:
            state.candidates.add(extra_candidates)
    if cfg.knn_interval and state.passes % cfg.knn_interval == 0:
        with _stage(timings, "knn"):
            r = None if reals is None else reals.detach().cpu().numpy()
            state.candidates.add(knn_triples(pd.points, r, ~pd.hidden, cfg.knn_k, cfg.knn_thresholds))
    state.passes += 1

    with _stage(timings, "existing"):
        # Above 10/alpha Lambda_wdt's clamp stops gradients; the power-cell factor needs them all.
        upper = None if cfg.power_cell_factor or cfg.active_band is None else 10.0 / cfg.alpha
        per_vertex = existing_deltas(points, weights, pd, cache, cfg.ray, upper)
        delta_wdt = per_vertex.mean(1)

    with _stage(timings, "nonexisting"):
        # Candidates not in the WDT with all three vertices owning a power cell.
        ck = state.candidates.keys
        pos = np.searchsorted(wdt_keys, ck).clip(max=len(wdt_keys) - 1)
        cand = state.candidates.faces_of(ck[wdt_keys[pos] != ck])
        cand = cand[~pd.hidden[cand].any(1)]
        band = None if cfg.active_band is None else cfg.active_band / cfg.alpha
        delta_non = -nonexisting_deltas(points, weights, pd, cand, cfg.ray, band).mean(1)

    t_prob = time.perf_counter()
    faces = torch.from_numpy(np.concatenate([pd.faces.astype(np.int64), cand]))
    delta = torch.cat([delta_wdt, delta_non])
    in_wdt = torch.zeros(len(faces), dtype=torch.bool)
    in_wdt[: len(pd.faces)] = True
    p_wdt = lambda_wdt(delta, cfg.alpha)
    if cfg.power_cell_factor:
        p_wdt = p_wdt * _power_cell_factor(per_vertex, pd, faces, n, cfg)
    if reals is None:
        p_real = torch.ones_like(p_wdt)
    else:
        p_real = dmin(reals[faces].double(), cfg.alpha_real)
    dtype = points.dtype
    out = FaceProbabilities(faces, in_wdt, delta.to(dtype), p_wdt.to(dtype), p_real.to(dtype),
                            (p_wdt * p_real).to(dtype), pd)
    if timings is not None:
        timings["probabilities"] = timings.get("probabilities", 0.0) + time.perf_counter() - t_prob
    return out


def _power_cell_factor(per_vertex: torch.Tensor, pd: PowerDiagram, faces: torch.Tensor, n: int,
                       cfg: ProbabilityConfig) -> torch.Tensor:
    """(F + C,) min over each face's vertices of sigmoid(alpha_pc (sum of the point's deltas over its WDT
    faces - eps_pc)) (paper Eq. 10); points without a cell get factor sigmoid(-alpha_pc eps_pc)."""
    wdt_faces = torch.from_numpy(pd.faces).long().reshape(-1)
    total = torch.zeros(n, dtype=per_vertex.dtype).index_add(0, wdt_faces, per_vertex.reshape(-1))
    a_pc = torch.sigmoid(cfg.alpha_pc * (total - cfg.eps_pc))
    return a_pc[faces].min(dim=1).values


def delta(points, weights, faces) -> torch.Tensor:
    """Delta(F) of the given faces for the current configuration.

    Triangulates internally; the neighbour cache is the current WDT's edges.

    Args:
        points: (N, 3) float32 or float64 tensor (or array); weights: (N,) tensor (or array, or None).
        faces: (M, 3) ints, any vertex order.
    Returns:
        (M,) tensor of the points' dtype, differentiable in points and weights: > 0 for faces of the WDT,
        <= 0 for other faces whose vertices own power cells, 0 for faces with a hidden vertex, and
        -ray_length for collinear or coincident triples (see the module docstring).
    """
    points = torch.as_tensor(points)
    if not points.is_floating_point():
        points = points.double()
    weights = torch.zeros(len(points), dtype=points.dtype) if weights is None else torch.as_tensor(weights)
    faces = np.sort(np.asarray(faces, dtype=np.int64).reshape(-1, 3), axis=1)
    n = len(points)
    if len(faces) and (faces.min() < 0 or faces.max() >= n):
        raise ValueError(f"faces must index points in [0, {n})")
    cfg = ProbabilityConfig()
    tri = triangulate(points, weights)
    pd = PowerDiagram(points, weights, tri.tets, tri.neighbors)
    ids = pd.face_ids(faces)
    out = torch.zeros(len(faces), dtype=torch.float64)
    in_wdt = np.flatnonzero(ids >= 0)
    if len(in_wdt):
        per_vertex = existing_deltas(points, weights, pd, pd.point_neighbors, cfg.ray, face_ids=ids[in_wdt])
        out = out.index_put((torch.from_numpy(in_wdt),), per_vertex.mean(1))
    other = np.flatnonzero((ids < 0) & ~pd.hidden[faces].any(1))
    if len(other):
        d = -nonexisting_deltas(points, weights, pd, faces[other], cfg.ray).mean(1)
        out = out.index_put((torch.from_numpy(other),), d)
    return out.to(points.dtype)


__all__ = ["ProbabilityConfig", "ProbabilityState", "FaceProbabilities", "face_probabilities", "delta",
           "dmin", "lambda_wdt", "dual_edges", "existing_deltas", "nonexisting_deltas"]
