"""Regularisers of the reconstruction procedures (paper section 3.4; DESIGN.md section 5).

Letters: N points, T tets, M scored faces, E finite power-diagram edges.

- Weight: sum over finite power-diagram edges of min(length, 1); gradients reach positions and weights
  through the orthocentres. Favours fewer, larger cells (a simpler mesh).
- Real: on faces weighted by detached Lambda_wdt (normalised by their sum), the mean |r_i - mean(r)| over
  a face's vertices (face mean detached: smoothness), plus, on faces whose max r > 0.8, the mean of
  (1 - r_i) (growth next to real points, closing holes).
- Quality: sum of aspect ratio (clamped to [1, 20]) x max edge length x Lambda over the faces, divided by
  the detached sum of Lambda. Aspect ratio = max edge / (min height * 2 / sqrt(3)) (1 for equilateral).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from dmesh import geometry
from dmesh.deltas import orthocentres
from dmesh.tolerances import DIVISION_FLOOR
from dmesh.wdt import PowerDiagram


def weight_regularizer(points: torch.Tensor, weights: torch.Tensor, pd: PowerDiagram,
                       max_length: float = 1.0, diagram=None) -> torch.Tensor:
    """Sum of the finite power-diagram edge lengths, each clamped at `max_length` (float64, 0-dim).

    diagram: optional native handle of `pd` for these points and weights (`FaceProbabilities.diagram`):
    the orthocentres it already holds are used, with the native adjoint, instead of recomputing them in
    torch (same values and gradients; several times faster at ~10^5 tets)."""
    inner = np.flatnonzero(~pd.is_hull)
    if len(inner) == 0:
        return torch.zeros((), dtype=torch.float64)
    if diagram is not None:
        cc = orthocentres(points, weights, diagram)
    else:
        cc = geometry.orthocentres(points, weights, torch.from_numpy(pd.tets).long())
    ft = torch.from_numpy(pd.face_tets[inner]).long()
    length = (cc[ft[:, 0]] - cc[ft[:, 1]]).norm(dim=1)
    return length.clamp_max(max_length).sum()


def real_regularizer(reals: torch.Tensor, faces: torch.Tensor, face_weights: torch.Tensor,
                     smooth: bool = True, grow: bool = True, grow_threshold: float = 0.8) -> torch.Tensor:
    """Smoothness + growth of real values over faces (float64, 0-dim).

    Args:
        reals: (N,) real values; faces: (M, 3) int64; face_weights: (M,) (detached inside), e.g. Lambda_wdt.
        smooth: include mean |r_i - mean(r)| per face; grow: include mean (1 - r_i) on faces with
            max r > grow_threshold.
    """
    if len(faces) == 0:
        return torch.zeros((), dtype=torch.float64)
    # One column per vertex: torch's reductions along a length-3 axis are several times slower than the
    # column arithmetic (there are ~10^5-10^6 scored faces every step).
    rv = reals.double()
    r0, r1, r2 = (geometry.gather(rv, faces[:, k]) for k in range(3))
    w = face_weights.detach().double()
    total = w.sum().clamp_min(DIVISION_FLOOR)
    out = torch.zeros((), dtype=torch.float64)
    if smooth:
        m = ((r0 + r1 + r2) / 3.0).detach()
        out = out + (w * ((r0 - m).abs() + (r1 - m).abs() + (r2 - m).abs()) / 3.0).sum() / total
    if grow:
        with torch.no_grad():
            near = (torch.maximum(torch.maximum(r0, r1), r2) > grow_threshold).double()
        out = out + (w * near * ((1.0 - r0) + (1.0 - r1) + (1.0 - r2)) / 3.0).sum() / total
    return out


def aspect_ratios(points: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(M,) aspect ratio max edge / (min height * 2/sqrt(3)) (unclamped) and (M,) max edge length (float64)."""
    p = points.double()
    a, b, c = (geometry.gather(p, faces[:, k]) for k in range(3))
    edges = torch.stack([(b - a).norm(dim=1), (c - b).norm(dim=1), (a - c).norm(dim=1)], dim=1)
    longest = edges.max(1).values
    area2 = torch.linalg.cross(b - a, c - a).norm(dim=1)           # twice the area
    min_height = area2 / longest.clamp_min(DIVISION_FLOOR)
    ratio = longest / (min_height * (2.0 / math.sqrt(3.0))).clamp_min(DIVISION_FLOOR)
    return ratio, longest


def quality_regularizer(points: torch.Tensor, faces: torch.Tensor, prob: torch.Tensor,
                        max_ratio: float = 20.0, min_prob: float = 0.0) -> torch.Tensor:
    """sum(clamp(AR, 1, max_ratio) * max edge * Lambda) / sum(Lambda).detach() (float64, 0-dim).

    Faces with Lambda <= `min_prob` are left out of both sums (each would add at most min_prob * 20 * its
    edge to the numerator): with 1e-4, the graph shrinks several times early in an optimisation, where most
    scored faces have an imaginary vertex."""
    if min_prob > 0:
        keep = torch.nonzero(prob.detach() > min_prob).squeeze(1)
        faces, prob = faces[keep], prob[keep]
    if len(faces) == 0:
        return torch.zeros((), dtype=torch.float64)
    ratio, longest = aspect_ratios(points, faces)
    lam = prob.double()
    return (ratio.clamp(1.0, max_ratio) * longest * lam).sum() / lam.detach().sum().clamp_min(DIVISION_FLOOR)


def ramp(step: int, start: float, end: float, steps: int) -> float:
    """Linear interpolation from `start` (step 0) to `end` (step >= steps)."""
    if steps <= 0 or step >= steps:
        return float(end)
    return float(start + (end - start) * step / steps)


def add_phase1_regularizers(loss, dm, probs, pd, cfg, step: int):
    """`loss` plus the regularisers of a phase-1 step, added in a fixed order: weight (`cfg.lambda_weight`,
    over the power diagram `pd`), real (ramped from `cfg.lambda_real_start` to `cfg.lambda_real_end` over
    `cfg.real_ramp_steps`) and quality (`cfg.lambda_quality`); a zero weight skips its term.

    Args:
        loss: scalar tensor (the data term); dm: `DMesh`; probs: its `face_probabilities` (faces, prob_wdt,
        prob); pd: the `PowerDiagram` of this step; cfg: a `PointCloudConfig` or `MultiViewConfig` (any object
        with those fields); step: the phase-1 step (for the ramp).
    """
    if cfg.lambda_weight > 0:
        diagram = probs.diagram if pd is probs.power_diagram else None  # the pass's native orthocentres
        loss = loss + cfg.lambda_weight * weight_regularizer(dm.points, dm.weights, pd, diagram=diagram)
    coef = ramp(step, cfg.lambda_real_start, cfg.lambda_real_end, cfg.real_ramp_steps)
    if coef > 0:
        loss = loss + coef * real_regularizer(dm.reals, probs.faces, probs.prob_wdt)
    if cfg.lambda_quality > 0:
        loss = loss + cfg.lambda_quality * quality_regularizer(dm.points, probs.faces, probs.prob, min_prob=1e-4)
    return loss


__all__ = ["add_phase1_regularizers", "weight_regularizer", "real_regularizer", "quality_regularizer",
           "aspect_ratios", "ramp"]
