"""Differentiable face existence probabilities (DESIGN.md section 4; paper section 3.3 and Eq. 10).

Letters: N points, T tets, F faces of the current WDT, C candidate faces not in the WDT.

One pass: WDT -> power diagram -> neighbour cache and candidates -> per-vertex distances -> Delta ->
Lambda. The per-vertex distances come from `dmesh.deltas`: one fused native kernel per kind of face
(argmin search and distance in one forward call, analytic gradient in one backward call,
`native/src/delta_recompute.h`); the argmin indices are constants and gradients reach positions and weights
through bisector planes, orthocentres, dual lines and hull-ray directions. `ProbabilityConfig.impl =
"reference"` selects the torch recomputation of `dmesh.reference.probability` instead (same values and
gradients, several times slower).

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

Cost control (deviations from upstream):
- `ProbabilityConfig.active_band`: every Delta is computed exactly, but only faces that can carry a
  gradient get one: WDT faces below Lambda_wdt's clamp (Delta < 10/alpha) and non-WDT faces with
  Delta > -active_band/alpha (Lambda_wdt > sigmoid(-10) = 4.5e-5 for the default band of 10). The others
  keep their exact values without a gradient. `active_band=None` differentiates every face (`delta()`
  always does).
- `ProbabilityConfig.full_search_every` = k > 1 (the coherent pass, native only): the argmin searches run
  every k passes; in between, argmins whose neighbourhood did not change are reused and only their
  distances recomputed (see `_Coherence`). Values then drift from a full search where an argmin would
  have switched; k = 1 (the default) always searches.
- Lambda is computed from the per-vertex distances in one NumPy pass (`_Lambda`), not a dozen
  multi-threaded torch ops over every face.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from dmesh import geometry, native
from dmesh.candidates import CandidateFaces, NeighbourCache, knn_triples
from dmesh.checks import require_positive
# The per-vertex distances live in dmesh.deltas; their names stay importable from here.
from dmesh.deltas import (IMPLS, check_impl, delta_diagram, existing_deltas, nonexisting_deltas,  # noqa: F401
                          orthocentres, row_mean)
from dmesh.reference.probability import dual_edges  # noqa: F401 (kept importable from here)
from dmesh.timing import stage
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
    impl: str = "native"           # per-vertex distances: "native" (fused kernels) or "reference" (torch)
    # native: search argmins every k passes, reuse them in between (1: always). 1 by measurement: in the
    # point-cloud phase 1 (62K points, lr 3e-4) over half the points change WDT neighbours every step, so
    # reuse covers 1-4% of the vertex slots, saves no time and drifts (issue 13).
    full_search_every: int = 1

    def __post_init__(self):
        require_positive(self, ("alpha_wdt", "alpha_real", "ray_length", "domain_scale", "alpha_pc"))
        check_impl(self.impl)
        if self.full_search_every < 1:
            raise ValueError(f"ProbabilityConfig.full_search_every must be >= 1, got {self.full_search_every}")
        if self.knn_interval < 0 or self.knn_k < 2:
            raise ValueError("ProbabilityConfig: knn_interval must be >= 0 and knn_k >= 2")

    @property
    def alpha(self) -> float:
        return self.alpha_wdt / self.domain_scale

    @property
    def ray(self) -> float:
        return self.ray_length * self.domain_scale


def dmin(values: torch.Tensor, alpha: float) -> torch.Tensor:
    """Differentiable minimum over the last axis: sum softmax(-alpha x)_k x_k, softmax weights detached."""
    with torch.no_grad():
        wts = torch.softmax(-alpha * values, dim=-1)
    return (wts * values).sum(-1)


def lambda_wdt(delta: torch.Tensor, alpha: float) -> torch.Tensor:
    """sigmoid(alpha * min(delta, 10 / alpha)): saturates at sigmoid(10) for faces that surely exist."""
    return torch.sigmoid(alpha * delta.clamp_max(10.0 / alpha))


class _Lambda(torch.autograd.Function):
    """Delta, Lambda_wdt, Lambda_real and Lambda of the scored faces (WDT faces, then candidates) from the
    per-vertex distances, in one NumPy pass: the same values as `lambda_wdt` and `dmin` in torch, without a
    dozen multi-threaded torch ops (and their thread barriers) over every face, forward and backward."""

    @staticmethod
    def forward(ctx, pv_wdt, pv_non, reals, faces, alpha, alpha_real, dtype):
        # Column arithmetic throughout: NumPy's reductions along a length-3 axis are several times slower.
        nw = len(pv_wdt)
        delta = np.concatenate([row_mean(pv_wdt.detach().numpy()), -row_mean(pv_non.detach().numpy())])
        upper = 10.0 / alpha
        passes = delta <= upper                              # where the clamp lets the gradient through
        with np.errstate(over="ignore"):  # z <= 10; exp(-z) overflows to inf only where sigmoid(z) is 0
            s = 1.0 / (1.0 + np.exp(-alpha * np.minimum(delta, upper)))
        if reals is None:
            wts = None
            p_real = np.ones_like(s)
        else:
            rv = reals.detach().numpy().astype(np.float64)
            r = [rv[faces[:, k]] for k in range(3)]
            rmin = np.minimum(np.minimum(r[0], r[1]), r[2])
            e = [np.exp(-alpha_real * (rk - rmin)) for rk in r]       # softmin weights (no gradient)
            total = e[0] + e[1] + e[2]
            wts = [ek / total for ek in e]
            p_real = wts[0] * r[0] + wts[1] * r[1] + wts[2] * r[2]
        ctx.saved = (nw, passes, s, p_real, wts, faces, None if reals is None else (len(reals), reals.dtype),
                     alpha, pv_wdt.dtype, pv_non.dtype)
        # Outputs that nothing differentiates (usually all but Lambda) get None, not a tensor of zeros.
        ctx.set_materialize_grads(False)
        outs = (delta, s, p_real, s * p_real)
        return tuple(torch.from_numpy(np.ascontiguousarray(o, dtype=_numpy_dtype(dtype))) for o in outs)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_delta, g_wdt, g_real, g_prob):
        # One gradient per forward input: pv_wdt, pv_non, reals, then None for faces, alpha, alpha_real,
        # dtype.
        nw, passes, s, p_real, wts, faces, reals_info, alpha, dt_w, dt_n = ctx.saved
        g_delta, g_wdt, g_real, g_prob = (None if g is None else g.numpy().astype(np.float64)
                                          for g in (g_delta, g_wdt, g_real, g_prob))
        # d/dDelta of Lambda_wdt's two uses (itself, and Lambda = Lambda_wdt Lambda_real); a missing gradient
        # is zero.
        g_s = g_wdt if g_prob is None else (g_prob * p_real if g_wdt is None else g_wdt + g_prob * p_real)
        if g_s is None:
            gd = np.zeros(len(s)) if g_delta is None else g_delta
        else:
            gd = np.where(passes, g_s * (alpha * s * (1.0 - s)), 0.0)
            if g_delta is not None:
                gd = g_delta + gd
        gd3 = gd / 3.0
        g_pv_w = np.empty((nw, 3))
        g_pv_w[:] = gd3[:nw, None]
        g_pv_n = np.empty((len(gd3) - nw, 3))
        g_pv_n[:] = -gd3[nw:, None]
        g_reals = None
        if reals_info is not None and ctx.needs_input_grad[2] and (g_real is not None or g_prob is not None):
            n, r_dtype = reals_info
            gr = g_prob * s if g_real is None else (g_real if g_prob is None else g_real + g_prob * s)
            # One bincount (a fixed, sequential order: deterministic) over the three vertex columns.
            ids = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
            g_reals = torch.from_numpy(np.bincount(ids, np.concatenate([gr * w for w in wts]), minlength=n))
            g_reals = g_reals.to(r_dtype)
        return (torch.from_numpy(g_pv_w).to(dt_w), torch.from_numpy(g_pv_n).to(dt_n), g_reals, None, None, None,
                None)


def _numpy_dtype(dtype: torch.dtype):
    return torch.empty(0, dtype=dtype).numpy().dtype


@dataclass
class FaceProbabilities:
    """Probabilities of the scored faces: the WDT faces first, then the candidates not in the WDT.

    Attributes:
        faces: (F + C, 3) int64 sorted vertex triples.
        in_wdt: (F + C,) bool, True for faces of the current WDT.
        delta: (F + C,) float signed distance Delta (>= 0 in the WDT, <= 0 outside).
        prob_wdt: (F + C,) Lambda_wdt; prob_real: (F + C,) Lambda_real; prob: (F + C,) Lambda.
        power_diagram: the `PowerDiagram` of this pass.
        diagram: the native `delta_diagram` handle of this pass (impl "native"), else None; with it,
            `orthocentres(points, weights, diagram)` gives the pass's orthocentres without recomputing them.
    """

    faces: torch.Tensor
    in_wdt: torch.Tensor
    delta: torch.Tensor
    prob_wdt: torch.Tensor
    prob_real: torch.Tensor
    prob: torch.Tensor
    power_diagram: PowerDiagram
    diagram: object = None


class ProbabilityState:
    """Candidate faces and the neighbour cache of one optimisation phase, a pass counter, and the last pass's
    argmins for the coherent pass."""

    def __init__(self, num_points: int, config: ProbabilityConfig | None = None):
        self.config = config or ProbabilityConfig()
        self.cache = NeighbourCache(num_points)
        self.candidates = CandidateFaces(num_points)
        self.passes = 0
        self.coherence = _Coherence()

    @property
    def num_points(self) -> int:
        return self.cache.num_points


class _Coherence:
    """The coherent pass (`ProbabilityConfig.full_search_every` = k > 1): between full searches, every
    per-vertex argmin whose neighbourhood did not change is reused and only its distance recomputed.

    Reused: for a WDT face still in the WDT (same key) whose vertices kept their WDT neighbours, the bisector
    neighbour of each vertex whose cached neighbour list is unchanged; for a scored candidate seen last pass
    whose vertices kept their WDT neighbours (so their cells' combinatorics), each vertex's nearest cell
    edge, when that edge's face still exists.
    Searched: everything else, and everything on every k-th pass. Argmins are keyed by face keys, so they
    survive the renumbering of faces between triangulations. The crossing test always runs.
    """

    def __init__(self):
        self.age = 0                # passes since the last full search
        self.wdt_keys = None        # (F',) sorted int64 keys of last pass's WDT faces
        self.wdt_j = None           # (F', 3) int32 their chosen neighbours, rows in key order
        self.cand_keys = None       # (C',) sorted int64 keys of last pass's scored candidates
        self.cand_edges = None      # (C', 3) int64 key of each vertex's nearest cell edge (a face), -1: none
        self.nbrs = None            # last pass's WDT neighbour lists (Csr)
        self.cache_lengths = None   # (N,) last pass's cache row lengths

    def hints(self, every: int, pd: PowerDiagram, cache: Csr, sorted_keys: np.ndarray, order: np.ndarray,
              cand: np.ndarray, cand_keys: np.ndarray):
        """((F, 3), (C, 3)) int32 hints for this pass's WDT faces and candidates, or (None, None) to search."""
        if every <= 1 or self.wdt_keys is None or self.age + 1 >= every or len(sorted_keys) == 0:
            return None, None
        changed = native.csr_rows_changed(pd.point_neighbors.offsets, pd.point_neighbors.indices,
                                          self.nbrs.offsets, self.nbrs.indices)
        grown = np.diff(cache.offsets) != self.cache_lengths  # the cache only grows: same length, same row
        fs = pd.faces[order]                                   # WDT faces in key order
        pos = np.searchsorted(self.wdt_keys, sorted_keys).clip(max=len(self.wdt_keys) - 1)
        near = changed[fs[:, 0]] | changed[fs[:, 1]] | changed[fs[:, 2]] | (self.wdt_keys[pos] != sorted_keys)
        h = self.wdt_j[pos]
        h[near[:, None] | grown[fs]] = native.SEARCH
        hint_wdt = np.empty_like(h)
        hint_wdt[order] = h
        pos = np.searchsorted(self.cand_keys, cand_keys).clip(max=max(len(self.cand_keys) - 1, 0))
        if len(self.cand_keys) == 0:
            return hint_wdt, np.full(cand.shape, native.SEARCH, np.int32)
        edge_keys = self.cand_edges[pos]
        at = np.searchsorted(sorted_keys, edge_keys).clip(max=len(sorted_keys) - 1)
        ok = (self.cand_keys[pos] == cand_keys)[:, None] & (edge_keys >= 0) & (sorted_keys[at] == edge_keys)
        # The dual line depends on all three vertices: a change around any of them searches the whole face.
        near = changed[cand[:, 0]] | changed[cand[:, 1]] | changed[cand[:, 2]]
        hint_cand = np.where(ok & ~near[:, None], order[at], native.SEARCH).astype(np.int32)
        return hint_wdt, hint_cand

    def record(self, searched: bool, pd: PowerDiagram, cache: Csr, keys: np.ndarray, order: np.ndarray,
               neighbour: np.ndarray, cand_keys: np.ndarray, edge: np.ndarray) -> None:
        """Keeps this pass's argmins (neighbour (F, 3) by face id, edge (C, 3) WDT face ids)."""
        self.age = 0 if searched else self.age + 1
        self.wdt_keys = keys[order]
        self.wdt_j = neighbour[order]
        self.cand_keys = cand_keys
        self.cand_edges = np.where(edge >= 0, keys[np.maximum(edge, 0)], -1)
        self.nbrs = pd.point_neighbors
        self.cache_lengths = np.diff(cache.offsets)


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
    with stage(timings, "wdt"):
        tri = triangulate(points, weights)
    with stage(timings, "power_diagram"):
        pd = PowerDiagram(points, weights, tri.tets, tri.neighbors)
    coherent = cfg.impl == "native" and cfg.full_search_every > 1
    with stage(timings, "candidates"):
        cache = state.cache.update(pd.point_neighbors)
        keys = face_keys(pd.faces, n)
        # kind="stable" is NumPy's radix sort for integers: about 2x faster here than the default quicksort.
        order = np.argsort(keys, kind="stable") if coherent else None  # the coherent pass needs each key's face
        wdt_keys = keys[order] if coherent else np.sort(keys, kind="stable")
        state.candidates.add_sorted_keys(wdt_keys)
        if extra_candidates is not None:
            state.candidates.add(extra_candidates)
    if cfg.knn_interval and state.passes % cfg.knn_interval == 0:
        with stage(timings, "knn"):
            r = None if reals is None else reals.detach().cpu().numpy()
            state.candidates.add(knn_triples(pd.points, r, ~pd.hidden, cfg.knn_k, cfg.knn_thresholds))
    state.passes += 1

    with stage(timings, "candidates"):
        # Candidates not in the WDT with all three vertices owning a power cell (sorted by key).
        cand, cand_keys = state.candidates.off_wdt(wdt_keys, pd.hidden)
        hint_wdt = hint_cand = None
        if coherent:
            hint_wdt, hint_cand = state.coherence.hints(cfg.full_search_every, pd, cache, wdt_keys, order, cand,
                                                        cand_keys)
        found = {} if coherent else None

    with stage(timings, "existing"):
        # Above 10/alpha Lambda_wdt's clamp stops gradients; the power-cell factor needs them all.
        upper = None if cfg.power_cell_factor or cfg.active_band is None else 10.0 / cfg.alpha
        diagram = delta_diagram(points, weights, pd) if cfg.impl == "native" else None
        per_vertex = existing_deltas(points, weights, pd, cache, cfg.ray, upper, impl=cfg.impl, diagram=diagram,
                                     hint=hint_wdt, record=found)

    with stage(timings, "nonexisting"):
        band = None if cfg.active_band is None else cfg.active_band / cfg.alpha
        per_vertex_non = nonexisting_deltas(points, weights, pd, cand, cfg.ray, band, cfg.impl, diagram,
                                            hint=hint_cand, record=found)
    if coherent:
        state.coherence.record(hint_wdt is None, pd, cache, keys, order, found["neighbour"], cand_keys,
                               found.get("edge", np.zeros((0, 3), np.int32)))

    with stage(timings, "probabilities"):
        faces_np = np.concatenate([pd.faces.astype(np.int64), cand])
        faces = torch.from_numpy(faces_np)
        # In NumPy: torch would fill these 1e5-1e6 entries in an OpenMP loop, whose idle threads then spin.
        in_wdt = np.zeros(len(faces_np), dtype=bool)
        in_wdt[: len(pd.faces)] = True
        in_wdt = torch.from_numpy(in_wdt)
        dtype = points.dtype
        if cfg.impl == "native" and not cfg.power_cell_factor:
            delta, p_wdt, p_real, prob = _Lambda.apply(per_vertex, per_vertex_non, reals, faces_np, cfg.alpha,
                                                       cfg.alpha_real, dtype)
            out = FaceProbabilities(faces, in_wdt, delta, p_wdt, p_real, prob, pd, diagram)
        else:
            delta = torch.cat([per_vertex.mean(1), -per_vertex_non.mean(1)])
            p_wdt = lambda_wdt(delta, cfg.alpha)
            if cfg.power_cell_factor:
                p_wdt = p_wdt * _power_cell_factor(per_vertex, pd, faces, n, cfg)
            if reals is None:
                p_real = torch.ones_like(p_wdt)
            else:
                p_real = dmin(geometry.gather(reals, faces).double(), cfg.alpha_real)
            out = FaceProbabilities(faces, in_wdt, delta.to(dtype), p_wdt.to(dtype), p_real.to(dtype),
                                    (p_wdt * p_real).to(dtype), pd, diagram)
    return out


def _power_cell_factor(per_vertex: torch.Tensor, pd: PowerDiagram, faces: torch.Tensor, n: int,
                       cfg: ProbabilityConfig) -> torch.Tensor:
    """(F + C,) min over each face's vertices of sigmoid(alpha_pc (sum of the point's deltas over its WDT
    faces - eps_pc)) (paper Eq. 10); points without a cell get factor sigmoid(-alpha_pc eps_pc)."""
    wdt_faces = torch.from_numpy(pd.faces).long().reshape(-1)
    total = torch.zeros(n, dtype=per_vertex.dtype).index_add(0, wdt_faces, per_vertex.reshape(-1))
    a_pc = torch.sigmoid(cfg.alpha_pc * (total - cfg.eps_pc))
    return a_pc[faces].min(dim=1).values


def delta(points, weights, faces, impl: str = "native") -> torch.Tensor:
    """Delta(F) of the given faces for the current configuration.

    Triangulates internally; the neighbour cache is the current WDT's edges.

    Args:
        points: (N, 3) float32 or float64 tensor (or array); weights: (N,) tensor (or array, or None).
        faces: (M, 3) ints, any vertex order.
        impl: "native" (fused kernels) or "reference" (torch recomputation).
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
        per_vertex = existing_deltas(points, weights, pd, pd.point_neighbors, cfg.ray, face_ids=ids[in_wdt],
                                     impl=impl)
        out = out.index_put((torch.from_numpy(in_wdt),), per_vertex.mean(1))
    other = np.flatnonzero((ids < 0) & ~pd.hidden[faces].any(1))
    if len(other):
        d = -nonexisting_deltas(points, weights, pd, faces[other], cfg.ray, impl=impl).mean(1)
        out = out.index_put((torch.from_numpy(other),), d)
    return out.to(points.dtype)


__all__ = ["ProbabilityConfig", "ProbabilityState", "FaceProbabilities", "face_probabilities", "delta",
           "dmin", "lambda_wdt", "dual_edges", "existing_deltas", "nonexisting_deltas", "orthocentres"]
