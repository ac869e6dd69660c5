"""DMesh as a multi-view method of the harness (`dmesh.recon.multiview.reconstruct`).

Shape letters: V views, H x W pixels, F output faces.

The config is `dmesh.recon.multiview.MultiViewConfig` (a frozen dataclass): the default is the `fast`
preset. Pass an instance (e.g. `MultiViewConfig.paper()`), or a mapping of field overrides, optionally with
`"preset": "paper" | "fast" | "depth" | "tiny"` naming the base they apply to (as for `DMeshPointCloud`). The
reports show this method as `dmesh` in the multi-view table (`eval.reports.tables.DISPLAY_NAMES`), and its
`depth` preset (DMesh's point-cloud fit to the lifted depth pixels) as `dmesh [preset=depth]`.

No private filter (DESIGN.md 8.5), as for the point-cloud method: the depth start's own input filters (the
point-cloud preset's outlier removal and smoothing, the smoothing of noisy pixels from the pool of all pixels, the
redo of a shredded mesh) are off in every config this method resolves (`MultiViewConfig.init_filters` False), so
the `depth` and `refine` rows start from the pixels as lifted, like every point-cloud method's `[lifted-depth]` row
(`lift_depth: true` in a sweep). Filtered pixels are the harness's stage: the rows `dmesh [lifted-depth,
+outliers+smooth]` run DMesh's point-cloud fit on the lifted pixels after it. Asking this method for the filters
(`init_filters: true`, `init_preset: noisy`) is a ValueError naming that row. The library and `dmesh reconstruct`
keep them.
"""
from __future__ import annotations

import logging

from baselines.base import Inputs, Method, Stopwatch
from baselines.dmesh_pointcloud import DMeshPointCloud

log = logging.getLogger(__name__)


class DMeshMultiView(DMeshPointCloud):
    name = "dmesh_mv"
    input_kind = "multiview"

    def default_config(self):
        from dmesh.recon.multiview_config import MultiViewConfig

        return MultiViewConfig.fast()

    def resolve_config(self, config):
        """`Method.resolve_config` with the depth start's own input filters off (`init_filters` False); a mapping
        of overrides that asks for them is a ValueError (module docstring)."""
        import dataclasses

        if config is not None and not dataclasses.is_dataclass(config):
            overrides = dict(config)
            if overrides.get("init_filters", False) or overrides.get("init_preset") == "noisy":
                raise ValueError(f"{self.name}: init_filters / init_preset=noisy would filter the lifted depth pixels "
                                 f"by DMesh itself; in the harness that is the pre-processing stage every method "
                                 f"gets: lift_depth: true and preprocess: [outliers+smooth] in the sweep (rows "
                                 f"dmesh [lifted-depth,+outliers+smooth])")
        return dataclasses.replace(Method.resolve_config(self, config), init_filters=False)

    def prepare(self) -> None:
        import dmesh.recon.multiview  # noqa: F401  (imports torch and the native module before timing)

    def _run(self, inputs: Inputs, cfg, sw: Stopwatch):
        import dataclasses

        from dmesh.recon.multiview import reconstruct

        if inputs.views is None:
            raise ValueError("this method needs a multi-view capture (inputs.views is None)")
        if inputs.seed != cfg.seed:
            cfg = dataclasses.replace(cfg, seed=int(inputs.seed))
        epochs: dict[int, dict] = {}
        callback = self._epoch_monitor(inputs.monitor, epochs, sw) if inputs.monitor is not None else None
        res = reconstruct(inputs.views, cfg, callback=callback, state_path=inputs.checkpoint)
        mesh, info = self._output(res, cfg, sw)
        for record in info.get("epochs", []):
            record.update(epochs.get(record.get("epoch"), {}))
        return mesh, info

    @staticmethod
    def _epoch_monitor(monitor, epochs: dict, sw: Stopwatch):
        """The `reconstruct` callback that measures each epoch's mesh with the harness monitor (CD p2s against the
        GT, as `monitor_cd_p2s` in `info["epochs"]`), so a run shows what every epoch gave, not only the one
        `select_best` returned; its seconds go to the "monitor" stage."""
        import time

        import trimesh

        def callback(event: dict) -> None:
            stage = event.get("stage", "")
            if not (stage.startswith("epoch") and stage.endswith("_end")) or "triangles" not in event \
                    or len(event["triangles"]) == 0:
                return
            t0 = time.perf_counter()
            mesh = trimesh.Trimesh(event["vertices"], event["triangles"], process=False)
            epochs[int(event["epoch"])] = {f"monitor_{k}": v for k, v in monitor(mesh).items()}
            sw.timings["monitor"] = sw.timings.get("monitor", 0.0) + time.perf_counter() - t0

        return callback


__all__ = ["DMeshMultiView"]
