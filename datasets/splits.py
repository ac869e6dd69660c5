"""The dev and test splits of the benchmark's shapes (DESIGN.md 8.5, issue 58).

- **dev**: the 12 shapes of Table 2 (`eval/sweeps/paper.yaml`), on which every constant and preset of the
  project was chosen (each surface-step constant was accepted by rescoring them).
- **test**: shapes no constant was tuned on, at least 5 per class: the synthetic shapes no table used, the
  shared real meshes no table used, and the families of `datasets.families`, which are smooth at the sampling
  scale. The rule: constants are chosen on dev; test is run, never tuned.

A shape is named as in a sweep: a synthetic generator name (`datasets.synthetic.SHAPES`) or a mesh file
relative to the data root (`../shared/meshes`, `$DMESH_DATA` or `--data-root`). Each entry carries its class
as `datasets.meshes.classify` finds it (checked in tests/test_splits.py), which for a real mesh is not always
its folder: mixed/beetle.obj classifies "open" (see `datasets.meshes`), so it counts as open here.

Closed shapes scanned with occlusion holes are not separate shapes: they are the closed test shapes under the
`scan` input corruption (`datasets.corrupt`: a simulated range scan, the GT kept closed), in
`eval/sweeps/test_scan.yaml`.

`edge_to_spacing` measures "smooth at the sampling scale": the longest edge of the normalised mesh over the
mean nearest-neighbour spacing of N area-uniform samples.
"""
from __future__ import annotations

import logging
from pathlib import PurePosixPath

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["SPLITS", "DEV", "TEST", "split_of", "shapes", "shape_class", "edge_to_spacing"]

CLASSES = ("closed", "open", "mixed")

#: The dev split: Table 2's shapes (paper.yaml), spec -> class.
DEV: dict[str, str] = {
    "torus": "closed", "genus2": "closed", "trefoil": "closed", "closed/spot.obj": "closed",
    "bowl": "open", "wavy_sheet": "open", "mobius": "open", "open/face.off": "open",
    "plant": "mixed", "mushroom": "mixed", "flag_box": "mixed", "mixed/suzanne.obj": "mixed",
}

#: The test split, spec -> class (as `datasets.meshes.classify` finds it).
TEST: dict[str, str] = {
    # closed: synthetic not in any table, the smooth families, shared real meshes
    "sphere": "closed", "csg": "closed", "thin_cup": "closed", "bracket": "closed",
    "closed/fandisk.obj": "closed", "closed/rocker_arm.obj": "closed", "closed/bunny_closed.obj": "closed",
    # open
    "disc": "open", "open_cylinder": "open", "leaf": "open", "vessel": "open",
    "open/teapot.obj": "open", "open/terrain.ply": "open", "open/planar_mesh.ply": "open",
    "open/beetle_alt.obj": "open", "mixed/beetle.obj": "open",
    # mixed
    "lamp": "mixed", "tablecloth": "mixed", "bracket_hose": "mixed", "tank_pipes": "mixed", "mixed/ogre.obj": "mixed",
}

SPLITS: dict[str, dict[str, str]] = {"dev": DEV, "test": TEST}


def _shape_id(spec: str) -> str:
    """The id a table shows for a shape spec: a file's stem, a synthetic name without its '@seed'."""
    spec = str(spec).strip()
    if "/" in spec or "." in PurePosixPath(spec).name:
        return PurePosixPath(spec).stem
    return spec.partition("@")[0]


def split_of(shape: str) -> str | None:
    """"dev", "test" or None (in neither) for a shape spec ("torus", "torus@3", "closed/spot.obj") or the id a
    table shows for it ("spot"). A synthetic shape at another generator seed is in its generator's split."""
    sid = _shape_id(shape)
    for name, members in SPLITS.items():
        if any(_shape_id(spec) == sid for spec in members):
            return name
    return None


def shapes(split: str, cls: str | None = None) -> list[str]:
    """The shape specs of `split` ("dev" or "test"), of class `cls` ("closed", "open", "mixed") or all, in
    order (closed, open, mixed)."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose from {', '.join(SPLITS)}")
    if cls is not None and cls not in CLASSES:
        raise ValueError(f"unknown shape class {cls!r}; choose from {', '.join(CLASSES)}")
    members = SPLITS[split]
    return [s for c in CLASSES if cls in (None, c) for s, sc in members.items() if sc == c]


def shape_class(shape: str) -> str | None:
    """The class the splits give a shape spec or table id, None when it is in neither split."""
    sid = _shape_id(shape)
    for members in SPLITS.values():
        for spec, cls in members.items():
            if _shape_id(spec) == sid:
                return cls
    return None


def edge_to_spacing(mesh, n: int = 100_000, seed: int = 0) -> tuple[float, float, float]:
    """How smooth a mesh is at the sampling scale of `n` input points.

    Args:
        mesh: a `trimesh.Trimesh` in any frame (it is normalised here, `datasets.normalize`).
        n: area-uniform samples (`datasets.sampling.sample_points`, seed `seed`).

    Returns:
        (ratio, max_edge, spacing): the longest edge of the normalised mesh, the mean distance from each sample
        to its nearest other sample, and their ratio; below 1 means facets smaller than the input's spacing.
    """
    from scipy.spatial import cKDTree

    from datasets.normalize import normalize
    from datasets.sampling import sample_points

    unit, _ = normalize(mesh)
    points, _ = sample_points(unit, n, seed=seed)
    dist, _ = cKDTree(points).query(points, k=2)
    spacing = float(dist[:, 1].mean())
    v = np.asarray(unit.vertices)
    f = np.asarray(unit.faces)
    max_edge = float(max(np.linalg.norm(v[f[:, i]] - v[f[:, (i + 1) % 3]], axis=1).max() for i in range(3)))
    return max_edge / spacing, max_edge, spacing
