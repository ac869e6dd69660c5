"""Alpha wrapping of a point cloud (Portaneri et al. 2022) through the PyPI `cgal` bindings.

Shape letters: N input points, F output faces.

The wrap is a closed, 2-manifold surface that stays outside the input at distance `offset` and cannot enter
cavities narrower than `alpha`; open surfaces come out as a thin closed shell around them. pymeshlab's
`generate_alpha_wrap` is not used: it crashes (segfault) on face-less point clouds.
"""
from __future__ import annotations

import logging
import os
import tempfile

import numpy as np

from baselines.base import Inputs, Method, Stopwatch, check_points, mean_spacing, require

log = logging.getLogger(__name__)


class AlphaWrap(Method):
    name = "alpha_wrap"
    input_kind = "pointcloud"

    def default_config(self) -> dict:
        return {
            "alpha": None,           # ball radius in input units; None: max(diag / relative_alpha, 5 h)
            "relative_alpha": 100.0,  # bounding-box diagonal / alpha for the automatic alpha
            "spacing_factor": 5.0,   # automatic alpha >= this many mean NN spacings h (3 lets the wrap slip inside)
            "offset": None,          # distance of the wrap from the points; None: alpha / 30
        }

    def prepare(self) -> None:
        require("CGAL.CGAL_Alpha_wrap_3", package="cgal")

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import trimesh

        from CGAL import CGAL_Alpha_wrap_3, CGAL_Kernel, CGAL_Polyhedron_3

        pts, _ = check_points(inputs, need_normals=False)
        with sw.stage("parameters"):
            diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
            alpha = cfg["alpha"]
            if alpha is None:
                alpha = max(diag / float(cfg["relative_alpha"]), float(cfg["spacing_factor"]) * mean_spacing(pts))
            offset = cfg["offset"] if cfg["offset"] is not None else alpha / 30.0
            alpha, offset = float(alpha), float(offset)
            if alpha <= 0 or offset <= 0:
                raise ValueError(f"alpha_wrap: alpha and offset must be positive, got {alpha}, {offset}")
        with sw.stage("convert"):
            vec = CGAL_Alpha_wrap_3.Point_3_Vector()
            vec.reserve(len(pts))
            for x, y, z in pts.tolist():
                vec.append(CGAL_Kernel.Point_3(x, y, z))
        with sw.stage("wrap"):
            poly = CGAL_Polyhedron_3.Polyhedron_3()
            CGAL_Alpha_wrap_3.alpha_wrap_3(vec, alpha, offset, poly)
        with sw.stage("export"):
            # The bindings give no array access; OFF through a temporary file is the fast way out.
            fd, path = tempfile.mkstemp(suffix=".off")
            os.close(fd)
            try:
                poly.write_to_file(path)
                mesh = trimesh.load(path, file_type="off", process=False, force="mesh")
            finally:
                os.unlink(path)
        return mesh, {"alpha": alpha, "offset": offset}
