"""DMesh as a point-cloud method of the harness (`dmesh.recon.pointcloud.reconstruct`).

Shape letters: N input points, F output faces.

The config is `dmesh.recon.pointcloud.PointCloudConfig` (a frozen dataclass): the default is the `fast`
preset. Pass an instance (e.g. `PointCloudConfig.paper()`), or a mapping of field overrides, optionally with
`"preset": "paper" | "fast" | "noisy" | "tiny"` naming the base they apply to. Normals go into the loss when
`lambda_normal` > 0, and always vote on the output's inside / outside and the side its open sheets face.
With `Inputs.checkpoint` the procedure saves its resumable state there (every `save_every` steps) and resumes
it; a resumed run's curve (`info["curve"]`) starts at the resume.
"""
from __future__ import annotations

import logging

from baselines.base import Inputs, Method, Stopwatch, check_points

log = logging.getLogger(__name__)

#: Steps between the points of a run's curve (`info["curve"]`: loss and, from the harness monitor, CD p2s).
CURVE_EVERY = 50


class DMeshPointCloud(Method):
    name = "dmesh"
    input_kind = "pointcloud"

    def default_config(self):
        from dmesh.recon.config import PointCloudConfig

        return PointCloudConfig.fast()

    def prepare(self) -> None:
        import dmesh.recon.pointcloud  # noqa: F401  (imports torch and the native module before timing)

    def _run(self, inputs: Inputs, cfg, sw: Stopwatch):
        import dataclasses

        from dmesh.recon.pointcloud import reconstruct

        pts, nrm = check_points(inputs, need_normals=cfg.lambda_normal > 0 or cfg.tangent_weight < 1.0)
        if inputs.seed != cfg.seed:
            cfg = dataclasses.replace(cfg, seed=int(inputs.seed))
        curve = []
        probe = self._probe(inputs.monitor, cfg, curve, sw) if cfg.steps_phase1 + cfg.steps_phase2 else None
        mesh, info = self._output(reconstruct(pts, nrm, cfg, probe=probe, state_path=inputs.checkpoint), cfg, sw)
        if curve:
            info["curve"] = curve
        return mesh, info

    @staticmethod
    def _probe(monitor, cfg, curve: list, sw: Stopwatch):
        """The `reconstruct` probe that records the curve: loss, and the harness monitor's figures (CD p2s
        against the GT) of the mesh extracted every CURVE_EVERY steps; its seconds go to the "monitor" stage."""
        import time

        import numpy as np

        from dmesh.recon.pointcloud import extract
        from dmesh.model import DMesh

        def probe(params, record):
            t0 = time.perf_counter()
            point = {"phase": int(record["phase"]), "step": int(record["step"]), "loss": float(record["loss"])}
            if monitor is not None:
                dm = DMesh(params["points"], params["weights"], params["reals"])
                mesh = extract(dm, cfg.threshold, None, cfg.extraction)
                # reconstruct's frame, of the filtered input (the raw input's own frame is off when outliers go)
                mesh.vertices = np.asarray(mesh.vertices) / params["scale"] + params["center"]
                point.update(monitor(mesh))
            curve.append(point)
            sw.timings["monitor"] = sw.timings.get("monitor", 0.0) + time.perf_counter() - t0

        return (CURVE_EVERY, probe)

    @staticmethod
    def _output(res, cfg, sw: Stopwatch):
        """(mesh, info) of a DMesh reconstruction result; its stage timings are added to `sw`."""
        import dataclasses

        for k, v in res.timings.items():
            if k != "total":
                sw.timings[k] = sw.timings.get(k, 0.0) + v
        if "resumed_from" in res.info:  # an interrupted attempt's state (`Inputs.checkpoint`) was resumed
            sw.timings["earlier_attempts"] = float(res.info["resumed_from"].get("seconds", 0.0))
        last = res.history[-1] if res.history else {}
        info = dict(res.info)
        info.update({"final_loss": last.get("loss"), "steps": len(res.history), "config": dataclasses.asdict(cfg)})
        return res.mesh, info


__all__ = ["DMeshPointCloud"]
