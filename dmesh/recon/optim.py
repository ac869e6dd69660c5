"""The bounded Adam update shared by the reconstruction procedures (DESIGN.md section 6).

Letters: N points.

One step: NaN gradients are zeroed; per-point gradient clipping (the position gradient of a point as a
3-vector, its weight and real gradients as scalars) to norm `grad_clip`; Adam; then every coordinate is
kept within +-bound of its value before the step (positions and weights: `update_bound`; reals:
`real_bound`), weights and reals are clamped to [0, 1], and frozen points keep real value 1.

Real values live in [0, 1] here, whereas upstream stores them scaled by `max_real` = 3e-3 and shares one
learning rate and bound; so the reals' learning rate and bound are the positions' divided by `max_real`.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from dmesh.checks import require_positive
from dmesh.tolerances import GRAD_NORM_FLOOR


@dataclass(frozen=True)
class StepConfig:
    """Settings of `BoundedAdam`."""

    lr: float = 3e-4               # Adam learning rate of positions and weights
    update_bound: float = 3e-4     # per-step bound on each position / weight coordinate
    max_real: float = 3e-3         # upstream's real-value scale: reals' lr and bound are divided by it
    grad_clip: float | None = None  # per-point gradient norm clip; None: update_bound / lr (upstream)

    def __post_init__(self):
        require_positive(self, ("lr", "update_bound", "max_real"))

    @property
    def real_lr(self) -> float:
        return self.lr / self.max_real

    @property
    def real_bound(self) -> float:
        return self.update_bound / self.max_real

    @property
    def clip(self) -> float:
        return self.update_bound / self.lr if self.grad_clip is None else self.grad_clip


def clip_per_point(grad: torch.Tensor, max_norm: float) -> torch.Tensor:
    """grad with NaN/inf zeroed and each row ((N, 3) rows, or (N,) scalars) scaled to norm <= max_norm."""
    g = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
    norm = g.norm(dim=1, keepdim=True) if g.ndim == 2 else g.abs()
    factor = (max_norm / norm.clamp_min(GRAD_NORM_FLOOR)).clamp_max(1.0)
    return g * factor


class BoundedAdam:
    """Adam over (points, weights, reals) with clipping, per-step bounds, clamps and real freezing.

    Args:
        points: (N, 3) parameter; weights: (N,) parameter; reals: (N,) parameter.
        config: `StepConfig`.
        train: which of "points", "weights", "reals" move (others get no update at all).
    Attributes:
        frozen: (N,) bool, points whose real value stays 1.
    """

    def __init__(self, points, weights, reals, config: StepConfig, train=("points", "weights", "reals")):
        self.config = config
        self.params = {"points": points, "weights": weights, "reals": reals}
        unknown = set(train) - set(self.params)
        if unknown:
            raise ValueError(f"BoundedAdam: unknown parameters {sorted(unknown)}")
        self.train = tuple(train)
        groups = []
        for name in self.train:
            lr = config.real_lr if name == "reals" else config.lr
            groups.append({"params": [self.params[name]], "lr": lr, "name": name})
        self.optimizer = torch.optim.Adam(groups)
        self.frozen = torch.zeros(len(points), dtype=torch.bool)

    def freeze(self, mask: torch.Tensor) -> None:
        """Adds points (N,) bool to the frozen set and sets their real value to 1 now."""
        self.frozen |= torch.as_tensor(mask, dtype=torch.bool)
        with torch.no_grad():
            self.params["reals"][self.frozen] = 1.0

    def step(self) -> None:
        cfg = self.config
        before = {}
        for name in self.train:
            p = self.params[name]
            if p.grad is not None:
                bound_norm = cfg.clip
                p.grad = clip_per_point(p.grad, bound_norm)
                if name == "reals":
                    p.grad[self.frozen] = 0.0
            before[name] = p.detach().clone()
        self.optimizer.step()
        with torch.no_grad():
            for name in self.train:
                p = self.params[name]
                bound = cfg.real_bound if name == "reals" else cfg.update_bound
                p.copy_(torch.maximum(torch.minimum(p, before[name] + bound), before[name] - bound))
                if name in ("weights", "reals"):
                    p.clamp_(0.0, 1.0)
                if name == "reals":
                    p[self.frozen] = 1.0

    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def state_dict(self) -> dict:
        return {"optimizer": self.optimizer.state_dict(), "frozen": self.frozen.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        self.frozen = state["frozen"].clone()


__all__ = ["StepConfig", "BoundedAdam", "clip_per_point"]
