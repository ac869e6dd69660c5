"""`DMesh`: weighted points with real values, the differentiable mesh representation.

Letters: N points, F scored faces.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from dmesh import native
from dmesh.probability import FaceProbabilities, ProbabilityConfig, ProbabilityState, face_probabilities
from dmesh.wdt import PowerDiagram


class DMesh:
    """Points with position, weight and real value, all torch parameters (float32 by default).

    Args:
        points: (N, 3) float array or tensor.
        weights: (N,) float, or None for ones (equal weights: the plain Delaunay triangulation).
        reals: (N,) float in [0, 1], or None for ones (every point real).
        config: `ProbabilityConfig` for the face probabilities.
        dtype: torch dtype of the parameters.

    Attributes:
        points: (N, 3) parameter; weights: (N,) parameter; reals: (N,) parameter.
        state: the current phase's `ProbabilityState` (candidate faces and neighbour cache only grow
            within a phase; `new_phase()` starts another).
    """

    def __init__(self, points, weights=None, reals=None, config: ProbabilityConfig | None = None,
                 dtype: torch.dtype = torch.float32):
        # A copy: the parameters move in place, and must not move the caller's array (or another DMesh).
        p = torch.tensor(np.asarray(points.detach() if torch.is_tensor(points) else points), dtype=dtype)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {tuple(p.shape)}")
        if len(p) < 4:
            raise ValueError(f"a DMesh needs at least 4 points, got {len(p)}")
        if not torch.isfinite(p).all():
            raise ValueError("points must be finite")
        n = len(p)
        w = torch.ones(n, dtype=dtype) if weights is None else self._vector(weights, n, "weights", dtype)
        r = torch.ones(n, dtype=dtype) if reals is None else self._vector(reals, n, "reals", dtype)
        if ((r < 0) | (r > 1)).any():
            raise ValueError("reals must lie in [0, 1]")
        self.points = torch.nn.Parameter(p)
        self.weights = torch.nn.Parameter(w)
        self.reals = torch.nn.Parameter(r)
        self.config = config or ProbabilityConfig()
        self.state = ProbabilityState(n, self.config)

    @staticmethod
    def _vector(v, n: int, name: str, dtype) -> torch.Tensor:
        """(n,) tensor of `dtype`: a copy of v after `native.as_weights` checked its shape and values."""
        return torch.tensor(native.as_weights(v, n, name), dtype=dtype)

    def __len__(self) -> int:
        return len(self.points)

    def parameters(self) -> list[torch.nn.Parameter]:
        return [self.points, self.weights, self.reals]

    def new_phase(self) -> None:
        """Starts a new optimisation phase: empty candidate set and neighbour cache."""
        self.state = ProbabilityState(len(self), self.config)

    def face_probabilities(self, extra_candidates: np.ndarray | None = None,
                           timings: dict | None = None) -> FaceProbabilities:
        """Lambda of every scored face (WDT faces, then candidates); differentiable in all parameters.

        `timings`, when a dict, receives seconds per stage (see `probability.face_probabilities`)."""
        return face_probabilities(self.points, self.weights, self.reals, self.state, extra_candidates, timings)

    def power_diagram(self) -> PowerDiagram:
        return PowerDiagram.from_points(self.points.detach(), self.weights.detach())

    def extract_mesh(self, threshold: float = 0.5, mode: str = "all", *, surface=None, pd=None, normals=None,
                     samples=None):
        """The mesh of the current WDT: its faces whose 3 points have real value > threshold, filtered by `mode`
        ("all", "no_interior" or "sheet"; `dmesh.extract.mesh_faces`), as a `trimesh.Trimesh` over the points
        they use (float64).

        Args:
            surface: None: those faces as they are (sorted triples, no winding; `dmesh.extract.extract`); a
                `dmesh.surface.SurfaceConfig`: the surface step with those settings made of them (oriented,
                closed where the shape is; `dmesh.surface.surface_mesh`), its counts in `metadata["surface"]`.
            pd: the WDT's `PowerDiagram`, if one is built already.
            normals, samples: the surface step's input normals and samples (`dmesh.surface.run`).
        """
        from dmesh.extract import extract, mesh_faces

        pd = pd if pd is not None else self.power_diagram()
        if surface is None:
            return extract(self, threshold, pd, mode)
        from dmesh.surface import surface_mesh

        walls = mesh_faces(pd, self.reals.detach().numpy() > threshold, mode)
        return surface_mesh(pd, walls, normals, samples, surface)

    def save(self, path: str | os.PathLike) -> None:
        """Writes points, weights, reals and the config to an `.npz` (atomically)."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        np.savez(tmp, points=self.points.detach().numpy(), weights=self.weights.detach().numpy(),
                 reals=self.reals.detach().numpy(),
                 config=np.array(json.dumps({k: v for k, v in vars(self.config).items()})))
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "DMesh":
        """Reads a DMesh written by `save`."""
        try:
            data = np.load(path, allow_pickle=False)
            cfg = json.loads(str(data["config"]))
            cfg["knn_thresholds"] = tuple(cfg.get("knn_thresholds", ()))
            return cls(data["points"], data["weights"], data["reals"], ProbabilityConfig(**cfg),
                       dtype=torch.from_numpy(data["points"][:0]).dtype)
        except (OSError, KeyError, ValueError) as exc:
            raise ValueError(f"cannot read a DMesh from {path}: {exc}") from exc
