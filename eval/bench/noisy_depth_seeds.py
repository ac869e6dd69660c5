"""Seeds of the multi-view `depth` start on noisy depth maps: `MultiViewConfig.depth()` with the points
its pooled smoothing keeps (`init_smoothed_points`) at 100K (all the lifted pixels it takes: the start
before the cap) and at 20K (its default), on the robustness sweep's captures with Gaussian depth noise of
1 % of the object radius.

Why: the point-cloud `fast` preset's meshes of noisy clouds fell apart into thousands of pieces at 100K seeds
(`python -m eval.bench noisy_seeds`); the `depth` start is that preset on lifted pixels (smoothed from all the
pixels when they look noisy), and its meshes at 1 % depth noise fell apart the same way. For each shape the
preset (seed 0) runs on the capture of `eval/sweeps/robustness_multiview.yaml` (64 views, 256 pixels, made as
the sweep makes it, in `runs/paper`). Figures: CD p2s (x1e-3, 100K samples per side, as the tables), faces,
boundary edges, connected components, seconds.

Regenerate: `python -m eval.bench noisy_depth_seeds` (6 runs, about 4 minutes on one core; `--quick`: the
flag_box only).
"""
from __future__ import annotations

import time

from eval.bench.common import write_cd_report

WORK = "runs/paper"  # the input cache of the robustness sweeps
SHAPES = ("flag_box", "wavy_sheet", "plant")
DEPTH_NOISE = 0.01
SMOOTHED_POINTS = (100_000, 20_000)
SETTINGS = {"views": 64, "resolution": 256, "distance": 2.0, "radius": 1.0}


def _capture(shape: str):
    """(views, GT path, class) of the robustness sweep's noisy capture of `shape`."""
    from datasets.capture import MultiView
    from eval.runner import prepare_gt, prepare_input
    from eval.sweep import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK, SETTINGS["radius"])
    settings = {**SETTINGS, "corruption": {"depth_noise": DEPTH_NOISE}}
    return MultiView.load(prepare_input(ref, gt_path, "multiview", settings, 0, WORK)), gt_path, ref.category


def one_run(shape: str, smoothed_points: int) -> dict:
    """One row: the `depth` preset keeping `smoothed_points` of the noisy capture's pixels of `shape`."""
    from dmesh.recon.multiview import reconstruct
    from dmesh.recon.multiview_config import MultiViewConfig
    from eval.metrics import chamfer_l1_p2s, mesh_stats
    from eval.runner import load_gt

    views, gt_path, category = _capture(shape)
    t0 = time.perf_counter()
    res = reconstruct(views, MultiViewConfig.depth(init_smoothed_points=smoothed_points, seed=0))
    seconds = time.perf_counter() - t0
    stats = mesh_stats(res.mesh, self_intersections=False)
    return {"shape": shape, "class": category, "depth_noise": DEPTH_NOISE, "init_smoothed_points": smoothed_points,
            "cd_p2s": chamfer_l1_p2s(res.mesh, load_gt(gt_path), n=100_000), "faces": stats["faces"],
            "boundary_edges": stats["boundary_edges"], "components": stats["components"], "seconds": seconds}


def main(out: str = "reports", quick: bool = False) -> None:
    table = []
    for shape in SHAPES[:1] if quick else SHAPES:
        for n in SMOOTHED_POINTS:
            table.append(one_run(shape, n))
            r = table[-1]
            print(f"{shape}: {n} smoothed points: CD p2s {r['cd_p2s'] * 1e3:.3f} x1e-3, {r['components']} components, "
                  f"{r['boundary_edges']} boundary edges, {r['seconds']:.0f} s", flush=True)
    cols = ["shape", "class", "depth_noise", "init_smoothed_points", "cd_p2s", "faces", "boundary_edges", "components",
            "seconds"]
    write_cd_report(out, "bench_noisy_depth_seeds", "Seeds of the depth start on noisy depth maps", __doc__, table,
                    cols, {"seconds": ".0f"})
