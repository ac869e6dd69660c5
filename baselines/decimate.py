"""Reconstruct, then decimate: a classical method's mesh reduced by quadric edge collapse to a face budget.

Shape letters: N input points, F output faces.

`psr_qem` runs `psr`, `bpa_qem` runs `bpa` and `sdf_mc_qem` runs `sdf_mc` (each with its own config keys and
defaults), then reduce the mesh to `faces` faces with MeshLab's quadric edge collapse (Garland and Heckbert
1997; pymeshlab `meshing_decimation_quadric_edge_collapse`) at MeshLab's defaults: quality threshold 0.3,
optimal vertex placement, boundaries not locked (boundary weight 1), normals and topology not preserved, no
planar quadric, auto-clean. This is the usual way to get a compact mesh from a classical reconstruction, so a
matched-budget table compares a compact DMesh mesh with it at the same face count (rows `psr_qem
[faces=5000]`). `gt_qem` reduces the GT itself the same way: the table's floor.
"""
from __future__ import annotations

import logging

import numpy as np

from baselines.base import Inputs, Method, Stopwatch, require
from baselines.bpa import BallPivoting
from baselines.psr import ScreenedPoisson
from baselines.sdf_mc import SignedDistanceMC

log = logging.getLogger(__name__)

#: The decimation's own keys and MeshLab's defaults for them.
QEM_DEFAULTS = {
    "faces": 5000,               # target face count (the matched budget)
    "qem_quality_threshold": 0.3,  # penalise collapses that make faces worse than this (MeshLab default)
    "qem_preserve_boundary": False,  # lock boundary edges (MeshLab default: off)
    "qem_boundary_weight": 1.0,  # weight of the boundary-preserving quadrics (MeshLab default)
    "qem_optimal_placement": True,  # place each new vertex at the quadric's minimum (MeshLab default)
    "qem_preserve_topology": False,  # refuse collapses that change the topology (MeshLab default: off)
}


def decimate(mesh, faces: int, quality_threshold: float = 0.3, preserve_boundary: bool = False,
             boundary_weight: float = 1.0, optimal_placement: bool = True, preserve_topology: bool = False):
    """`mesh` (trimesh.Trimesh) reduced to about `faces` faces by pymeshlab's quadric edge collapse.

    A mesh that already has no more than `faces` faces is returned unchanged. Returns a trimesh.Trimesh.
    """
    import trimesh

    if int(faces) < 4:
        raise ValueError(f"decimate: faces must be >= 4, got {faces}")
    if len(mesh.faces) <= int(faces):
        return mesh
    pml = require("pymeshlab")
    ms = pml.MeshSet()
    ms.add_mesh(pml.Mesh(vertex_matrix=np.asarray(mesh.vertices, dtype=np.float64),
                         face_matrix=np.asarray(mesh.faces, dtype=np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(faces), qualitythr=float(quality_threshold), preserveboundary=bool(preserve_boundary),
        boundaryweight=float(boundary_weight), optimalplacement=bool(optimal_placement),
        preservetopology=bool(preserve_topology), preservenormal=False, planarquadric=False, autoclean=True)
    out = ms.current_mesh()
    return trimesh.Trimesh(np.asarray(out.vertex_matrix(), dtype=np.float64),
                           np.asarray(out.face_matrix(), dtype=np.int64), process=False)


class Decimated(Method):
    """`base`'s reconstruction, then quadric edge collapse to `faces` faces."""

    input_kind = "pointcloud"

    def __init__(self, base: Method, name: str) -> None:
        self.base = base
        self.name = name
        self.input_kind = base.input_kind

    def default_config(self) -> dict:
        return {**self.base.default_config(), **QEM_DEFAULTS}

    def resolve_config(self, config) -> dict:
        overrides = dict(config or {})
        own = {k: overrides.pop(k) for k in list(overrides) if k in QEM_DEFAULTS}
        return {**self.base.resolve_config(overrides), **QEM_DEFAULTS, **own}

    def prepare(self) -> None:
        self.base.prepare()
        require("pymeshlab")

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        base_cfg = {k: v for k, v in cfg.items() if k not in QEM_DEFAULTS}
        mesh, info = self.base._run(inputs, base_cfg, sw)
        info = dict(info)
        info["faces_before_decimation"] = int(len(mesh.faces))
        with sw.stage("decimate"):
            mesh = decimate(mesh, int(cfg["faces"]), cfg["qem_quality_threshold"], cfg["qem_preserve_boundary"],
                            cfg["qem_boundary_weight"], cfg["qem_optimal_placement"],
                            cfg["qem_preserve_topology"])
        return mesh, info


class DecimatedGT(Method):
    """The GT itself reduced by the same quadric edge collapse to `faces` faces: the floor of a matched-budget
    table, what the field's decimation makes of the exact surface. A reference rather than a bound: reducing a
    2M-face GT 400x can lose thin parts, where a reconstruction reduced from 200K faces does better
    (reports/compact.md). Input kind "mesh": `inputs.mesh` is the
    normalised GT (`eval.inputs.load_inputs`); a GT with no more faces than the budget is returned as it is."""

    name = "gt_qem"
    input_kind = "mesh"

    def default_config(self) -> dict:
        return dict(QEM_DEFAULTS)

    def prepare(self) -> None:
        require("pymeshlab")

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        mesh = getattr(inputs, "mesh", None)
        if mesh is None or not len(mesh.faces):
            raise ValueError("gt_qem: needs the GT mesh as input (input kind 'mesh')")
        with sw.stage("decimate"):
            out = decimate(mesh, int(cfg["faces"]), cfg["qem_quality_threshold"], cfg["qem_preserve_boundary"],
                           cfg["qem_boundary_weight"], cfg["qem_optimal_placement"], cfg["qem_preserve_topology"])
        return out, {"faces_before_decimation": int(len(mesh.faces))}


def psr_qem() -> Decimated:
    return Decimated(ScreenedPoisson(), "psr_qem")


def bpa_qem() -> Decimated:
    return Decimated(BallPivoting(), "bpa_qem")


def sdf_mc_qem() -> Decimated:
    return Decimated(SignedDistanceMC(), "sdf_mc_qem")
