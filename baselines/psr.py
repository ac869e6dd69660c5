"""Screened Poisson surface reconstruction (Kazhdan and Hoppe 2013) through pymeshlab.

Shape letters: N input points, V output vertices, F output faces.

Always yields a closed surface; for open or mixed shapes set `trim_quantile` > 0 to cut away the vertices of
lowest sample density (pymeshlab leaves the Poisson density as the per-vertex scalar), the usual way to get
open PSR surfaces.
"""
from __future__ import annotations

import logging

import numpy as np

from baselines.base import Inputs, Method, Stopwatch, check_points, require

log = logging.getLogger(__name__)


class ScreenedPoisson(Method):
    name = "psr"
    input_kind = "pointcloud"

    def default_config(self) -> dict:
        return {
            "depth": 8,             # octree depth (resolution 2^depth over the padded bounding cube)
            "full_depth": 5,        # depth below which the octree is complete
            "scale": 1.1,           # bounding cube / points' bounding box
            "samples_per_node": 1.5,  # minimum samples per octree node (higher: smoother)
            "point_weight": 4.0,    # screening weight (0: unscreened Poisson)
            "iters": 8,             # Gauss-Seidel iterations per level
            "trim_quantile": 0.0,   # drop vertices whose density is below this quantile (0: no trimming)
            "threads": 1,           # solver threads (OpenMP spin-waits make 2 much slower on a busy 2-core box)
        }

    def prepare(self) -> None:
        require("pymeshlab")

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import trimesh

        pml = require("pymeshlab")
        pts, nrm = check_points(inputs, need_normals=True)
        if not 0.0 <= float(cfg["trim_quantile"]) < 1.0:
            raise ValueError(f"psr: trim_quantile must be in [0, 1), got {cfg['trim_quantile']}")
        with sw.stage("poisson"):
            ms = pml.MeshSet()
            ms.add_mesh(pml.Mesh(vertex_matrix=pts, v_normals_matrix=nrm))
            ms.generate_surface_reconstruction_screened_poisson(
                depth=int(cfg["depth"]), fulldepth=int(cfg["full_depth"]), scale=float(cfg["scale"]),
                samplespernode=float(cfg["samples_per_node"]), pointweight=float(cfg["point_weight"]),
                iters=int(cfg["iters"]), preclean=False, threads=int(cfg["threads"]))
            out = ms.current_mesh()
            verts = np.asarray(out.vertex_matrix(), dtype=np.float64)
            faces = np.asarray(out.face_matrix(), dtype=np.int64)
            density = np.asarray(out.vertex_scalar_array(), dtype=np.float64)
        info = {"density_min": float(density.min()) if len(density) else float("nan"),
                "density_max": float(density.max()) if len(density) else float("nan")}
        with sw.stage("trim"):
            mesh = trimesh.Trimesh(verts, faces, process=False)
            q = float(cfg["trim_quantile"])
            if q > 0 and len(verts):
                threshold = float(np.quantile(density, q))
                keep = density >= threshold
                mesh.update_faces(keep[faces].all(axis=1))
                mesh.remove_unreferenced_vertices()
                info["trim_density_threshold"] = threshold
        return mesh, info
