"""DMesh as a multi-view method of the harness (`dmesh.recon.multiview.reconstruct`).

Shape letters: V views, H x W pixels, F output faces.

The config is `dmesh.recon.multiview.MultiViewConfig` (a frozen dataclass): the default is the `fast`
preset. Pass an instance (e.g. `MultiViewConfig.paper()`), or a mapping of field overrides, optionally with
`"preset": "paper" | "fast" | "depth" | "tiny"` naming the base they apply to (as for `DMeshPointCloud`). The
reports show this method as `dmesh` in the multi-view table (`eval.reports.tables.DISPLAY_NAMES`), and its
`depth` preset (DMesh's point-cloud fit to the lifted depth pixels) as `dmesh [preset=depth]`.
"""
from __future__ import annotations

import logging

from baselines.base import Inputs, Stopwatch
from baselines.dmesh_pointcloud import DMeshPointCloud

log = logging.getLogger(__name__)


class DMeshMultiView(DMeshPointCloud):
    name = "dmesh_mv"
    input_kind = "multiview"

    def default_config(self):
        from dmesh.recon.config import MultiViewConfig

        return MultiViewConfig.fast()

    def prepare(self) -> None:
        import dmesh.recon.multiview  # noqa: F401  (imports torch and the native module before timing)

    def _run(self, inputs: Inputs, cfg, sw: Stopwatch):
        import dataclasses

        from dmesh.recon.multiview import reconstruct

        if inputs.views is None:
            raise ValueError("this method needs a multi-view capture (inputs.views is None)")
        if inputs.seed != cfg.seed:
            cfg = dataclasses.replace(cfg, seed=int(inputs.seed))
        return self._output(reconstruct(inputs.views, cfg), cfg, sw)


__all__ = ["DMeshMultiView"]
