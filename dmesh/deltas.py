"""Per-vertex distances of the face existence probability, differentiable (DESIGN.md section 4).

Letters: N points, T tets, F faces of the WDT, K scored WDT faces, C candidate faces not in the WDT.

`existing_deltas` (WDT faces: dual-edge sample to the nearest cached bisector plane) and
`nonexisting_deltas` (candidates: dual line to the power cell) run one fused native kernel each: argmin
search and distance in one forward call, analytic gradient in one backward call
(`native/src/delta_recompute.h`). The argmin indices are constants; gradients reach positions and weights
through bisector planes, orthocentres, dual lines and hull-ray directions. `orthocentres` returns the
orthocentres a pass's `delta_diagram` computed, with the native adjoint as backward. Each is one autograd
Function; they share `_NativeFunction`'s backward: one native call that returns the gradients of points
and weights. `impl = "reference"` selects the torch recomputation of `dmesh.reference.probability` (same
values and gradients, several times slower).
"""
from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from dmesh import native
from dmesh.reference import probability as ref_prob
from dmesh.wdt import Csr, PowerDiagram

#: Implementations of the per-vertex distances: fused native kernels, or the torch reference.
IMPLS = ("native", "reference")


def check_impl(impl: str) -> None:
    """ValueError unless `impl` is one of `IMPLS`."""
    if impl not in IMPLS:
        raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")


def row_mean(a: np.ndarray) -> np.ndarray:
    """(M,) mean of the rows of a (M, 3) array: (a0 + a1 + a2) / 3, the order torch's mean(1) adds in."""
    return (a[:, 0] + a[:, 1] + a[:, 2]) / 3.0


class _NativeFunction(torch.autograd.Function):
    """Base of the Functions whose backward is one native call giving the gradients of points and weights.

    The forward ends with `_finish`; `backward` then returns the native call's ((N, 3), (N,)) float64
    gradients in the dtypes of points and weights, and None for every other input."""

    @staticmethod
    def _finish(ctx, points, weights, constants: int, out: np.ndarray, backward, limit: float | None = None,
                record: dict | None = None, argmins: dict | None = None) -> torch.Tensor:
        """Saves `backward` ((gradient of out, active rows) -> native gradients) and returns out as a tensor.

        constants: how many forward inputs follow points and weights. Rows of out whose mean reaches
        `limit` keep their value without a gradient (active rows: None, all). `record`, when a dict,
        receives `argmins`."""
        if record is not None:
            record.update(argmins)
        active = None if limit is None else row_mean(out) < limit
        ctx.native_backward = lambda grad: backward(grad, active)
        ctx.saved = (constants, points.dtype, weights.dtype)
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        constants, p_dtype, w_dtype = ctx.saved
        gp, gw = ctx.native_backward(grad.numpy())
        return (torch.from_numpy(gp).to(p_dtype), torch.from_numpy(gw).to(w_dtype), *([None] * constants))


class _ExistingDeltas(_NativeFunction):
    """(K, 3) float64 per-vertex delta of WDT faces: fused native search and distances, native backward."""

    @staticmethod
    def forward(ctx, points, weights, diagram, neighbours, face_ids, ray_length, upper, hint, record):
        j, dist = native.existing_delta_forward(diagram, face_ids, neighbours.offsets, neighbours.indices,
                                                ray_length, hint)
        # Rows whose mean delta reaches `upper` keep their value without a gradient (see existing_deltas).
        return _NativeFunction._finish(
            ctx, points, weights, 7, dist, lambda grad, active: native.existing_delta_backward(
                diagram, face_ids, j, grad, active, ray_length), upper, record, {"neighbour": j})


class _CandidateDeltas(_NativeFunction):
    """(C, 3) float64 per-vertex line-to-cell distance of candidates: fused native search and distances,
    native backward."""

    @staticmethod
    def forward(ctx, points, weights, diagram, cand, ray_length, band, hint, record):
        edge, crosses, dist = native.candidate_delta_forward(diagram, cand, ray_length, hint)
        return _NativeFunction._finish(
            ctx, points, weights, 6, dist, lambda grad, active: native.candidate_delta_backward(
                diagram, cand, edge, crosses, grad, active), band, record, {"edge": edge})


class _Orthocentres(_NativeFunction):
    """(T, 3) float64 orthocentres of a `delta_diagram` handle's tets: the forward returns those the handle
    computed (no recomputation), the backward applies the native orthocentre adjoint."""

    @staticmethod
    def forward(ctx, points, weights, diagram):
        return _NativeFunction._finish(ctx, points, weights, 1, diagram.orthocentres,
                                       lambda grad, _: native.orthocentre_backward(diagram, grad))


def orthocentres(points: torch.Tensor, weights: torch.Tensor, diagram) -> torch.Tensor:
    """(T, 3) float64 orthocentres of the tets of `diagram` (from `delta_diagram(points, weights, pd)`, whose
    points and weights these must be), differentiable with respect to points and weights; equal to
    `dmesh.geometry.orthocentres(points, weights, pd.tets)` except that degenerate tets (|det| < 1e-18)
    pass no gradient."""
    if diagram.num_points != len(points):
        raise ValueError(f"the diagram has {diagram.num_points} points, got {len(points)}")
    return _Orthocentres.apply(points, weights, diagram)


def delta_diagram(points: torch.Tensor, weights: torch.Tensor, pd: PowerDiagram):
    """The native handle the fused kernels share in one pass: `pd`'s combinatorics with the geometry
    recomputed from (points, weights)."""
    p = native.as_points(points)
    return native.delta_diagram(p, native.as_weights(weights, len(p)), pd)


def existing_deltas(points: torch.Tensor, weights: torch.Tensor, pd: PowerDiagram, neighbours: Csr,
                    ray_length: float, upper: float | None = None,
                    face_ids: np.ndarray | None = None, impl: str = "native", diagram=None, hint=None,
                    record: dict | None = None) -> torch.Tensor:
    """(K, 3) float64 per-vertex delta of WDT faces `face_ids` ((K,) ints; None: all F faces): distance of
    the face's dual-edge sample to the nearest cached bisector plane of the vertex's reduced cell;
    `ray_length` where a vertex has no such plane.

    `pd` must be the power diagram of (points, weights). Faces whose mean delta is at least `upper` (where
    Lambda_wdt's clamp stops every gradient) keep their value without a gradient. `impl`: "native" (fused
    kernel) or "reference" (native search, torch recomputation; `dmesh.reference.probability`). Native only:
    `diagram`, this pass's `delta_diagram` (made here when None); `hint`, None or (K, 3) ints, per vertex
    `native.SEARCH` or the neighbour to reuse without searching (the coherent pass); `record`, a dict that
    receives the chosen neighbours as record["neighbour"] ((K, 3) int32, -1: none).
    """
    check_impl(impl)
    if impl == "reference":
        return ref_prob.existing_deltas(points, weights, pd, neighbours, ray_length, upper, face_ids)
    ids = np.arange(len(pd.faces), dtype=np.int32) if face_ids is None else np.asarray(face_ids)
    diagram = delta_diagram(points, weights, pd) if diagram is None else diagram
    return _ExistingDeltas.apply(points, weights, diagram, neighbours, ids.astype(np.int32, copy=False),
                                 float(ray_length), upper, hint, record)


def nonexisting_deltas(points: torch.Tensor, weights: torch.Tensor, pd: PowerDiagram, faces: np.ndarray,
                       ray_length: float, band: float | None = None, impl: str = "native",
                       diagram=None, hint=None, record: dict | None = None) -> torch.Tensor:
    """(C, 3) float64 per-vertex distance between each candidate's dual line and the vertex's power cell
    (0 where the line crosses it). Candidates must not be WDT faces and their vertices must own cells.
    Collinear or coincident candidates get `ray_length` (no gradient). Faces whose mean distance is at
    least `band` keep their value without a gradient (Lambda_wdt < sigmoid(-alpha band) there). `impl` as in
    `existing_deltas`; so are `diagram`, `hint` (per vertex the cell edge, a WDT face id, to reuse) and
    `record` (receives record["edge"], (C, 3) int32 nearest cell edges, -1 where none or crossing)."""
    check_impl(impl)
    if impl == "reference":
        return ref_prob.nonexisting_deltas(points, weights, pd, faces, ray_length, band)
    faces = np.asarray(faces).reshape(-1, 3)
    if len(faces) == 0:
        return torch.full((0, 3), float(ray_length), dtype=torch.float64)
    diagram = delta_diagram(points, weights, pd) if diagram is None else diagram
    return _CandidateDeltas.apply(points, weights, diagram, faces.astype(np.int32, copy=False),
                                  float(ray_length), band, hint, record)


__all__ = ["IMPLS", "check_impl", "delta_diagram", "existing_deltas", "nonexisting_deltas", "orthocentres",
           "row_mean"]
