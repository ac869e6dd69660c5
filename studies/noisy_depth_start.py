"""The multi-view `depth` start on noisy depth maps: `MultiViewConfig.depth()` with the point-cloud preset
that takes its pooled points (`init_pooled_preset`) at "fast" (the default: it smooths them again only when
they still look noisy or its mesh comes out in shreds) and at "noisy" (always smoothed again, 20K seeds), on
the robustness sweep's captures with Gaussian depth noise of 0.25 % and 1 % of the object radius.

Why: the point-cloud `fast` preset's meshes of noisy clouds fell apart into thousands of pieces at 100K seeds
(`python -m studies noisy_seeds`), and so did the `depth` start's at 1 % depth noise, though its points are
first fitted from all the lifted pixels (`init_pool_k`). For each shape, level and preset the start (seed 0)
runs on the capture of `eval/sweeps/robustness_multiview.yaml` (64 views, 256 pixels, made as the sweep makes
it, in `runs/paper`). Figures: whether the point-cloud fit was made again after a shredded first mesh
(`redone`), CD p2s (x1e-3, 100K samples per side, as the tables), faces, boundary edges, connected components,
seconds.

Regenerate: `python -m studies noisy_depth_start` (16 runs, about 15 minutes on one core; `--quick`: the
flag_box at 1 % only).
"""
from __future__ import annotations

import time

from eval.bench.common import mesh_figures, run_mesh_rows, write_cd_report

WORK = "runs/paper"  # the input cache of the robustness sweeps
SHAPES = ("torus", "wavy_sheet", "plant", "flag_box")
DEPTH_NOISE = (0.0025, 0.01)
POOLED_PRESETS = ("fast", "noisy")
SETTINGS = {"views": 64, "resolution": 256, "distance": 2.0, "radius": 1.0}


def _capture(shape: str, noise: float):
    """(views, GT path, class) of the robustness sweep's capture of `shape` with depth noise `noise`."""
    from datasets.capture import MultiView
    from eval.runner import prepare_gt, prepare_input
    from eval.sweep import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK, SETTINGS["radius"])
    settings = {**SETTINGS, "corruption": {"depth_noise": noise}}
    return MultiView.load(prepare_input(ref, gt_path, "multiview", settings, 0, WORK)), gt_path, ref.category


def one_run(shape: str, noise: float, pooled_preset: str) -> dict:
    """One row: the `depth` preset with `init_pooled_preset=pooled_preset` on the noisy capture of `shape`."""
    from dmesh.recon.multiview import reconstruct
    from dmesh.recon.multiview_config import MultiViewConfig

    views, gt_path, category = _capture(shape, noise)
    t0 = time.perf_counter()
    res = reconstruct(views, MultiViewConfig.depth(init_pooled_preset=pooled_preset, seed=0))
    seconds = time.perf_counter() - t0
    start = res.info["init_depth"]
    return {"shape": shape, "class": category, "depth_noise": noise, "pooled_preset": pooled_preset,
            "redone": bool(start.get("redone")), **mesh_figures(res.mesh, gt_path), "seconds": seconds}


def main(out: str = "reports", quick: bool = False) -> None:
    grid = [("flag_box", 0.01, p) for p in POOLED_PRESETS] if quick else \
        [(shape, noise, p) for noise in DEPTH_NOISE for shape in SHAPES for p in POOLED_PRESETS]
    table = run_mesh_rows(grid, one_run, lambda shape, noise, preset:
                          f"{shape} depth noise {noise}: pooled points to {preset}")
    cols = ["shape", "class", "depth_noise", "pooled_preset", "redone", "cd_p2s", "faces", "boundary_edges",
            "components", "seconds"]
    write_cd_report(out, "noisy_depth_start", "The depth start on noisy depth maps", __doc__, table,
                    cols, {"seconds": ".0f"})
