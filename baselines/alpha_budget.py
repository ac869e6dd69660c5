"""Alpha wrapping at a face budget: the alpha that gives a wrap of about `faces` faces, found by search.

Shape letters: N input points, F output faces.

A matched-budget table (`reports/compact.md`) compares methods at equal face counts. The quadric-decimation
rows reach a count by collapsing edges; alpha wrapping (Portaneri et al. 2022, `baselines/alpha_wrap.py`) has
its own size control instead: the ball radius alpha sets the wrap's resolution, and its face count falls
about as 1 / alpha^2. So this method runs the wrap with the alpha that gives `faces` faces: from the
automatic alpha, each try scales alpha by sqrt(F / faces) (the 1 / alpha^2 law), at most `max_tries` tries,
ending once F is within `tolerance` of the budget; the try closest to the budget is returned. The offset
follows alpha as in `alpha_wrap` (alpha / 30, CGAL's example ratio). One alpha per shape, as a user with a
budget would choose it; the search's seconds count in the run's time.
"""
from __future__ import annotations

import math

from baselines.alpha_wrap import AlphaWrap
from baselines.base import Inputs, Stopwatch, check_points, mean_spacing


class AlphaWrapBudget(AlphaWrap):
    name = "alpha_wrap_budget"
    input_kind = "pointcloud"

    def default_config(self) -> dict:
        return {**super().default_config(),
                "faces": 5000,        # the face budget
                "tolerance": 0.05,    # a try within this share of the budget ends the search
                "max_tries": 8}       # wraps run at most

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import numpy as np

        faces, tolerance, tries = int(cfg["faces"]), float(cfg["tolerance"]), int(cfg["max_tries"])
        if faces < 4 or not 0 < tolerance < 1 or tries < 1:
            raise ValueError(f"alpha_wrap_budget: need faces >= 4, tolerance in (0, 1), max_tries >= 1; got "
                             f"{faces}, {tolerance}, {tries}")
        pts, _ = check_points(inputs, need_normals=False)
        wrap_cfg = {k: cfg[k] for k in super().default_config()}
        alpha = wrap_cfg["alpha"]
        if alpha is None:
            diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
            alpha = max(diag / float(wrap_cfg["relative_alpha"]), float(wrap_cfg["spacing_factor"]) * mean_spacing(pts))
        best, history = None, []
        for _ in range(tries):
            mesh, info = super()._run(inputs, {**wrap_cfg, "alpha": float(alpha), "offset": float(alpha) / 30.0}, sw)
            count = int(len(mesh.faces))
            history.append((round(float(alpha), 6), count))
            if best is None or abs(count - faces) < abs(len(best[0].faces) - faces):
                best = (mesh, info)
            if count == 0 or abs(count - faces) <= tolerance * faces:
                break
            alpha *= math.sqrt(count / faces)
        mesh, info = best
        return mesh, {**info, "alpha_tries": history}
