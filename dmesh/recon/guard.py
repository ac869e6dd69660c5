"""Phase-1 safeguards of the point-cloud reconstruction (not upstream): the best state kept, and a stop when the
mesh collapses.

Letters: G target points, N DMesh points, F mesh faces, S uniform samples on the mesh.

Why: the expected Chamfer loss is a figure of the probabilistic surface, and the mesh a user gets is the set of
faces whose three real values exceed the threshold. The two can part: the mesh can empty while the loss keeps
falling (an empty mesh's loss is 0 by definition; docs/presets.md, `compact_steps`, has the case). So the mesh itself is scored against the input every `best_every` steps:
the Chamfer L1 distance between the Chamfer target and S area-uniform samples of the mesh's faces
(`input_chamfer`; no GT is used, only the input). The state of the best score is kept and phase 2 starts from
it; and a phase-1 mesh that falls below `collapse_share` of its faces at the first step ends the phase there.
"""
from __future__ import annotations

import numpy as np
import torch

from dmesh import native

#: Uniform samples drawn on the mesh to score it against the input.
SCORE_SAMPLES = 20_000
_LEAF = 32


def input_chamfer(points: np.ndarray, faces: np.ndarray, target_tree, target: np.ndarray,
                  rng: np.random.Generator, samples: int = SCORE_SAMPLES, workers: int = 1) -> float:
    """Chamfer L1 (the two directions' mean nearest distances, summed) between the input `target` ((G, 3),
    with its `native.point_tree` `target_tree`) and `samples` area-uniform points on the mesh (points (N, 3),
    faces (F, 3)); inf for a mesh without area."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(faces):
        return float("inf")
    tri = points[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(area.sum())
    if not total > 0:
        return float("inf")
    pick = rng.choice(len(faces), int(samples), p=area / total)
    u, v = rng.random(int(samples)), rng.random(int(samples))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[pick]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    tree = native.point_tree(pts, _LEAF)
    to_mesh = native.knn_search_trees(tree, target_tree, 1, workers)[:, 0]
    to_input = native.knn_search_trees(target_tree, tree, 1, workers)[:, 0]
    return float(np.linalg.norm(target - pts[to_mesh], axis=1).mean()
                 + np.linalg.norm(pts - target[to_input], axis=1).mean())


class BestState:
    """The phase-1 state of the best `input_chamfer` score seen.

    Args:
        target: (G, 3) float64 Chamfer target (unit frame); seed: of the scoring samples' generator (its own
            stream, so scoring draws nothing from the run's generator); workers: k-d tree threads.
    Attributes:
        score, step: the best score and the step whose state it is (inf, -1 before any); params: that state's
            {"points", "weights", "reals"} tensors (detached copies), or None.
    """

    def __init__(self, target: np.ndarray, seed: int, workers: int = 1):
        self.target = np.ascontiguousarray(target, dtype=np.float64)
        self.tree = native.point_tree(self.target, _LEAF)
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C0E]))
        self.workers = int(workers)
        self.score, self.step, self.params = float("inf"), -1, None

    def offer(self, step: int, points: torch.Tensor, weights: torch.Tensor, reals: torch.Tensor,
              faces: np.ndarray) -> float:
        """Scores the mesh `faces` ((F, 3) indices of `points`) and keeps this state if it is the best; returns
        the score."""
        score = input_chamfer(points.detach().numpy(), faces, self.tree, self.target, self.rng,
                              workers=self.workers)
        if score < self.score:
            self.score, self.step = score, int(step)
            self.params = {"points": points.detach().clone(), "weights": weights.detach().clone(),
                           "reals": reals.detach().clone()}
        return score

    def state(self) -> dict:
        """What a resumable state keeps of it."""
        return {"score": self.score, "step": self.step, "params": self.params,
                "rng": self.rng.bit_generator.state}

    def restore(self, saved: dict | None) -> None:
        """Takes back `state()`'s entries (None: nothing saved)."""
        if saved:
            self.score, self.step, self.params = float(saved["score"]), int(saved["step"]), saved["params"]
            self.rng.bit_generator.state = saved["rng"]


def collapsed(faces: int, first: int | None, share: float) -> bool:
    """Whether a phase-1 mesh of `faces` faces has fallen below `share` of the `first` step's (share 0: never)."""
    return share > 0 and first is not None and first > 0 and faces < share * first


__all__ = ["BestState", "SCORE_SAMPLES", "collapsed", "input_chamfer"]
