"""DMesh as a point-cloud method of the harness (`dmesh.recon.pointcloud.reconstruct`).

Shape letters: N input points, F output faces.

The config is `dmesh.recon.pointcloud.PointCloudConfig` (a frozen dataclass): the default is the `fast`
preset. Pass an instance (e.g. `PointCloudConfig.paper()`), or a mapping of field overrides, optionally with
`"preset": "paper" | "fast" | "noisy" | "tiny"` naming the base they apply to. Normals go into the loss when
`lambda_normal` > 0, and always vote on the output's inside / outside and the side its open sheets face.
With `Inputs.checkpoint` the procedure saves its resumable state there (every `save_every` steps) and resumes
it; a resumed run's curve (`info["curve"]`) starts at the resume.

No private filter (DESIGN.md 8.5): the procedure's own input filters (`PRIVATE_FILTERS`: outlier removal,
jet smoothing, its noise-triggered smoothing and the redo of a shredded mesh from smoothed input) are turned
off in every config this method resolves (`harness_config`), whatever the preset. Outlier removal and
smoothing are the harness's pre-processing stage instead (`eval.preprocess`, `preprocess:` in a sweep), which
every point-cloud method gets alike. Asking this method for one of those filters (a non-zero field, or the
`noisy` preset, which is `fast` plus smoothing) is a ValueError naming the stage to use. The library and
`dmesh reconstruct` keep the filters and the presets as they are. One rule of the presets stays, because it
is a setting of DMesh's, not a filter: on input the harness smoothed (`Inputs.preprocess["smoothed"]`) at
most `smoothed_seeds` real seeds, as the presets take on input they smoothed themselves.
"""
from __future__ import annotations

import logging

from baselines.base import Inputs, Method, Stopwatch, check_points

log = logging.getLogger(__name__)

#: The `PointCloudConfig` fields of DMesh's own input filters, at the values that turn them off, and the
#: harness's pre-processing stage that does each one's work for every method (`eval.preprocess`).
PRIVATE_FILTERS = {"outlier_std": 0.0, "smooth_k": 0, "auto_smooth_k": 0, "redo_fragmented": 0.0}
_STAGE_OF = {"outlier_std": "outliers", "smooth_k": "smooth", "auto_smooth_k": "autosmooth",
             "redo_fragmented": "smooth or autosmooth"}


def harness_config(cfg):
    """`cfg` (a `PointCloudConfig`) with DMesh's own input filters off (`PRIVATE_FILTERS`)."""
    import dataclasses

    return dataclasses.replace(cfg, **PRIVATE_FILTERS)


def _refuse_private_filters(owner: str, overrides) -> None:
    """ValueError when config overrides ask this harness method for a private filter (module docstring)."""
    if overrides.get("preset") == "noisy":
        raise ValueError(f"{owner}: the noisy preset is fast plus DMesh's own smoothing, which the harness's rows "
                         f"do not take; give every method the smoothing instead: preprocess: [outliers+smooth] "
                         f"in the sweep (--preprocess outliers+smooth)")
    asked = sorted(k for k, off in PRIVATE_FILTERS.items() if k in overrides and overrides[k] != off)
    if asked:
        stages = ", ".join(f"{k} -> {_STAGE_OF[k]}" for k in asked)
        raise ValueError(f"{owner}: {', '.join(asked)} would filter DMesh's input by itself; in the harness that is "
                         f"the pre-processing stage every method gets ({stages}): preprocess: [...] in the sweep")


def seeds_for_input(cfg, preprocess: dict | None):
    """(config, capped): `cfg` with at most `smoothed_seeds` real seeds when the harness smoothed the input
    (`preprocess["smoothed"]`, `eval.preprocess.apply`'s record), as the presets take on input they smoothed
    themselves; capped says whether it changed."""
    import dataclasses

    capped = bool((preprocess or {}).get("smoothed")) and 0 < cfg.smoothed_seeds < cfg.num_init
    return (dataclasses.replace(cfg, num_init=cfg.smoothed_seeds) if capped else cfg), capped


#: Steps between the points of a run's curve (`info["curve"]`: loss and, from the harness monitor, CD p2s).
CURVE_EVERY = 50


class DMeshPointCloud(Method):
    name = "dmesh"
    input_kind = "pointcloud"

    def default_config(self):
        from dmesh.recon.config import PointCloudConfig

        return harness_config(PointCloudConfig.fast())

    def resolve_config(self, config):
        """`Method.resolve_config` with DMesh's own input filters off (`harness_config`); a mapping of overrides
        that asks for one (or for the `noisy` preset) is a ValueError naming the harness stage to use."""
        import dataclasses

        if config is not None and not dataclasses.is_dataclass(config):
            _refuse_private_filters(self.name, dict(config))
        return harness_config(super().resolve_config(config))

    def prepare(self) -> None:
        import dmesh.recon.pointcloud  # noqa: F401  (imports torch and the native module before timing)

    def _run(self, inputs: Inputs, cfg, sw: Stopwatch):
        import dataclasses

        from dmesh.recon.pointcloud import reconstruct

        pts, nrm = check_points(inputs, need_normals=cfg.lambda_normal > 0 or cfg.tangent_weight < 1.0)
        if inputs.seed != cfg.seed:
            cfg = dataclasses.replace(cfg, seed=int(inputs.seed))
        cfg, capped = seeds_for_input(cfg, inputs.preprocess)
        curve = []
        probe = self._probe(inputs.monitor, cfg, curve, sw) if cfg.steps_phase1 + cfg.steps_phase2 else None
        mesh, info = self._output(reconstruct(pts, nrm, cfg, probe=probe, state_path=inputs.checkpoint), cfg, sw)
        if curve:
            info["curve"] = curve
        if capped:
            info["seeds_capped_on_smoothed_input"] = int(cfg.smoothed_seeds)
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
