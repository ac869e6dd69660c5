"""Seeded, parameterised synthetic shapes, by class: closed, open and mixed surfaces.

Every generator takes a seed (for its random parameters) and returns a `trimesh.Trimesh` in its own
frame; normalise with `datasets.normalize` before use. `SHAPES` maps a name to (class, generator).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh


def torus(seed: int = 0, major: float = 0.7, minor: float = 0.25, sections: int = 48) -> trimesh.Trimesh:
    """A closed genus-1 torus, slightly squashed by the seed."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.torus(major_radius=major, minor_radius=minor, major_sections=sections,
                               minor_sections=sections // 2)
    m.apply_scale([1.0, 1.0, 1.0 + 0.1 * rng.uniform(-1, 1)])
    return m


def sphere(seed: int = 0, subdivisions: int = 3) -> trimesh.Trimesh:
    """A closed unit icosphere, stretched by the seed into an ellipsoid."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    m.apply_scale(1.0 + 0.15 * rng.uniform(-1, 1, 3))
    return m


#: name -> (class, generator)
SHAPES: dict[str, tuple[str, Callable[..., trimesh.Trimesh]]] = {
    "torus": ("closed", torus),
    "sphere": ("closed", sphere),
}


def generate(name: str, seed: int = 0, **params) -> trimesh.Trimesh:
    """The synthetic shape `name` (see `SHAPES`) for `seed`; raises ValueError for an unknown name."""
    if name not in SHAPES:
        raise ValueError(f"unknown synthetic shape {name!r}; choose from {', '.join(SHAPES)}")
    return SHAPES[name][1](seed=seed, **params)
