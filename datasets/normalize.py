"""Normalisation into the evaluation frame: vertex mean at the origin, max vertex norm = radius.

Shape letters: N points, V vertices. Every input derived from a ground-truth mesh (point clouds, images,
cameras) and every prediction lives in the frame `normalize` returns (DESIGN.md 8.1): radius 1.0 in
general, 0.8 for mesh-to-DMesh.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import trimesh

log = logging.getLogger(__name__)

__all__ = ["Transform", "normalize", "DEFAULT_RADIUS", "MESH_TO_DMESH_RADIUS"]

#: Max vertex norm after normalisation (point-cloud and multi-view experiments).
DEFAULT_RADIUS = 1.0
#: Max vertex norm for mesh-to-DMesh (exp. 1).
MESH_TO_DMESH_RADIUS = 0.8


@dataclass(frozen=True, eq=False)
class Transform:
    """A similarity without rotation: x -> (x - center) * scale.

    Attributes:
        center: (3,) float64, read-only; the point sent to the origin.
        scale: positive float.
    """

    center: np.ndarray  # (3,) float64, subtracted first
    scale: float  # multiplied after subtracting the centre

    def __post_init__(self):
        c = np.array(self.center, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.isfinite(c).all():
            raise ValueError(f"Transform.center must be 3 finite numbers, got {self.center!r}")
        s = float(self.scale)
        if not np.isfinite(s) or s <= 0:
            raise ValueError(f"Transform.scale must be a positive finite number, got {self.scale!r}")
        c.flags.writeable = False
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "scale", s)

    def __eq__(self, other) -> bool:
        return (isinstance(other, Transform) and bool(np.array_equal(self.center, other.center))
                and self.scale == other.scale)

    def __hash__(self) -> int:
        return hash((tuple(self.center.tolist()), self.scale))

    def apply(self, points) -> np.ndarray:
        """Map points into the normalised frame.

        Args:
            points: (N, 3) or (3,) float array.

        Returns:
            Same shape, float64 (float32 input stays float32).
        """
        p = np.asarray(points)
        dtype = np.float32 if p.dtype == np.float32 else np.float64
        return ((p.astype(np.float64) - self.center) * self.scale).astype(dtype, copy=False)

    def inverse(self, points) -> np.ndarray:
        """Map points from the normalised frame back to the original one (same shapes and dtypes as apply)."""
        p = np.asarray(points)
        dtype = np.float32 if p.dtype == np.float32 else np.float64
        return (p.astype(np.float64) / self.scale + self.center).astype(dtype, copy=False)

    def apply_mesh(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        """A new mesh with vertices mapped by `apply` (faces shared by value, not modified)."""
        return trimesh.Trimesh(self.apply(np.asarray(mesh.vertices, np.float64)),
                               np.array(mesh.faces, dtype=np.int64), process=False)

    def to_dict(self) -> dict:
        """JSON-ready form: {"center": [x, y, z], "scale": s}."""
        return {"center": self.center.tolist(), "scale": self.scale}

    @classmethod
    def from_dict(cls, d: dict) -> "Transform":
        return cls(center=np.asarray(d["center"], np.float64), scale=float(d["scale"]))


def normalize(mesh: trimesh.Trimesh, radius: float = DEFAULT_RADIUS) -> tuple[trimesh.Trimesh, Transform]:
    """Centre a mesh at its vertex mean and scale it so its max vertex norm is `radius`.

    Args:
        mesh: vertices (V, 3), at least one vertex away from the mean.
        radius: target max vertex norm (1.0, or 0.8 for mesh-to-DMesh).

    Returns:
        (new mesh with vertices (V, 3) float64, the `Transform` that maps the input frame to it).

    Raises:
        ValueError: no vertices, non-finite vertices, all vertices at one point, or radius <= 0.
    """
    if not np.isfinite(radius) or radius <= 0:
        raise ValueError(f"radius must be positive, got {radius!r}")
    v = np.asarray(mesh.vertices, np.float64)
    if len(v) == 0:
        raise ValueError("cannot normalise a mesh without vertices")
    if not np.isfinite(v).all():
        raise ValueError("cannot normalise a mesh with NaN or infinite vertices")
    center = v.mean(axis=0)
    extent = float(np.linalg.norm(v - center, axis=1).max())
    if extent == 0.0:
        raise ValueError("cannot normalise a mesh whose vertices all coincide")
    t = Transform(center=center, scale=radius / extent)
    return t.apply_mesh(mesh), t
