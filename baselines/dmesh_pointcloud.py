"""DMesh as a point-cloud method of the harness (`dmesh.recon.pointcloud.reconstruct`).

Shape letters: N input points, F output faces.

The config is `dmesh.recon.pointcloud.PointCloudConfig` (a frozen dataclass): the default is the `fast`
preset. Pass an instance (e.g. `PointCloudConfig.paper()`), or a mapping of field overrides, optionally with
`"preset": "paper" | "fast" | "tiny"` naming the base they apply to. Normals are used only when
`lambda_normal` > 0.
"""
from __future__ import annotations

import logging

from baselines.base import Inputs, Method, Stopwatch, check_points

log = logging.getLogger(__name__)


class DMeshPointCloud(Method):
    name = "dmesh"
    input_kind = "pointcloud"

    def default_config(self):
        from dmesh.recon.pointcloud import PointCloudConfig

        return PointCloudConfig.fast()

    def config_class(self):
        """The config dataclass (with `preset(name, **overrides)`); subclasses for other inputs override it."""
        from dmesh.recon.pointcloud import PointCloudConfig

        return PointCloudConfig

    def resolve_config(self, config):
        import dataclasses

        cls = self.config_class()
        if config is not None and not dataclasses.is_dataclass(config) and "preset" in config:
            overrides = dict(config)
            preset = overrides.pop("preset")
            names = {f.name for f in dataclasses.fields(cls)}
            unknown = sorted(set(overrides) - names)
            if unknown:
                raise ValueError(f"{self.name}: unknown config keys {unknown}; known: {sorted(names | {'preset'})}")
            return cls.preset(str(preset), **overrides)
        return super().resolve_config(config)

    def prepare(self) -> None:
        import dmesh.recon.pointcloud  # noqa: F401  (imports torch and the native module before timing)

    def _run(self, inputs: Inputs, cfg, sw: Stopwatch):
        import dataclasses

        from dmesh.recon.pointcloud import reconstruct

        pts, nrm = check_points(inputs, need_normals=cfg.lambda_normal > 0)
        if inputs.seed != cfg.seed:
            cfg = dataclasses.replace(cfg, seed=int(inputs.seed))
        return self._output(reconstruct(pts, nrm, cfg), cfg, sw)

    @staticmethod
    def _output(res, cfg, sw: Stopwatch):
        """(mesh, info) of a DMesh reconstruction result; its stage timings are added to `sw`."""
        import dataclasses

        for k, v in res.timings.items():
            if k != "total":
                sw.timings[k] = sw.timings.get(k, 0.0) + v
        last = res.history[-1] if res.history else {}
        info = dict(res.info)
        info.update({"final_loss": last.get("loss"), "steps": len(res.history), "config": dataclasses.asdict(cfg)})
        return res.mesh, info


__all__ = ["DMeshPointCloud"]
