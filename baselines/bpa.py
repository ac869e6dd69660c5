"""Ball pivoting (Bernardini et al. 1999) through open3d.

Shape letters: N input points, F output faces.

Interpolates the input points, so it handles open surfaces but leaves holes where the sampling is sparser than
the largest ball. Ball radii are multiples of the mean nearest-neighbour spacing of the points.
"""
from __future__ import annotations

import logging

import numpy as np

from baselines.base import Inputs, Method, Stopwatch, check_points, mean_spacing, require

log = logging.getLogger(__name__)


class BallPivoting(Method):
    name = "bpa"
    input_kind = "pointcloud"

    def default_config(self) -> dict:
        return {
            "radii": [1.5, 3.0, 6.0],  # ball radii, as multiples of the mean nearest-neighbour spacing
            "normal_k": 16,            # neighbours for normal estimation when the inputs have no normals
        }

    def prepare(self) -> None:
        require("open3d")

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import trimesh

        o3d = require("open3d")
        pts, nrm = check_points(inputs, need_normals=False)
        radii = [float(r) for r in cfg["radii"]]
        if not radii or min(radii) <= 0:
            raise ValueError(f"bpa: radii must be positive multiples of the spacing, got {cfg['radii']}")
        with sw.stage("spacing"):
            h = mean_spacing(pts)
        with sw.stage("pivot"):
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            if nrm is None:
                pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(int(cfg["normal_k"])))
            else:
                pcd.normals = o3d.utility.Vector3dVector(nrm)
            tm = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
                pcd, o3d.utility.DoubleVector([r * h for r in radii]))
            mesh = trimesh.Trimesh(np.asarray(tm.vertices), np.asarray(tm.triangles, dtype=np.int64),
                                   process=False)
            mesh.remove_unreferenced_vertices()
        return mesh, {"mean_spacing": h, "radii_abs": [r * h for r in radii]}
