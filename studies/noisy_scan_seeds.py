"""Seeds and smoothing on the realistic scan: the point-cloud `fast` preset (which smooths only input that
looks noisy, and makes a mesh that comes out in shreds again from the smoothed input) and `noisy` (always
smoothed), each as it is (20K seeds of a smoothed input) and as it was before the seed cap and the redo
(`smoothed_seeds` 100K, `redo_fragmented` 0), on the robustness sweep's realistic scan (6 cameras, range
noise 0.25 % of the radius, 1 % outliers, estimated normals).

Why: `fast` measures this scan under its noise threshold (`noise_ratio`), so one pass does not smooth it and
its mesh falls apart; `python -m studies noisy_seeds` shows fewer seeds mending smoothed clouds. For each
shape the preset (`PointCloudConfig.preset(name, ...)`, seed 0, with the scan's estimated normals, as the
harness runs it) runs on the cached input of `eval/sweeps/robustness.yaml` (made as the sweep makes it, in
`runs/paper`). Figures: the input's `noise_ratio`, whether the run smoothed (`smooth_k`) and whether it was
made again (`redone`), CD p2s (x1e-3, 100K samples per side), faces, boundary edges, connected components,
seconds.

Regenerate: `python -m studies noisy_scan_seeds` (24 runs, about 10 minutes on one core; `--quick`: the
torus only).
"""
from __future__ import annotations

import time

import numpy as np

from eval.bench.common import mesh_figures, run_mesh_rows, write_cd_report

WORK = "runs/paper"  # the input cache of the robustness sweep
SHAPES = ("torus", "genus2", "bowl", "wavy_sheet", "plant", "flag_box")
SCAN = {"noise": 0.0025, "normals": "estimated", "outliers": 0.01, "scan": 6}
#: (preset, variant, overrides): each preset as it is and as it was before the cap and the redo.
BEFORE = {"smoothed_seeds": 100_000, "redo_fragmented": 0.0}
RUNS = (("fast", "before", BEFORE), ("fast", "now", {}), ("noisy", "before", BEFORE), ("noisy", "now", {}))


def _cloud(shape: str):
    """(points, normals, GT path, class) of the robustness sweep's realistic scan of `shape`."""
    from eval.runner import prepare_gt, prepare_input
    from eval.sweep import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK, 1.0)
    settings = {"n_points": 100_000, "radius": 1.0, "corruption": dict(SCAN)}
    with np.load(prepare_input(ref, gt_path, "pointcloud", settings, 0, WORK)) as z:
        return z["points"], z["normals"], gt_path, ref.category


def one_run(shape: str, preset: str, variant: str, overrides: dict) -> dict:
    """One row: `preset` with `overrides` on the realistic scan of `shape`."""
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct

    points, normals, gt_path, category = _cloud(shape)
    t0 = time.perf_counter()
    res = reconstruct(points, normals, PointCloudConfig.preset(preset, **overrides, seed=0))
    seconds = time.perf_counter() - t0
    return {"shape": shape, "class": category, "preset": preset, "variant": variant,
            "noise_ratio": res.info.get("noise_ratio"), "smooth_k": res.info.get("smooth_k"),
            "redone": "fragmented_attempt" in res.info, "real_seeds": res.info["real_seeds"],
            **mesh_figures(res.mesh, gt_path), "seconds": seconds}


def main(out: str = "reports", quick: bool = False) -> None:
    grid = [(shape, preset, variant, overrides) for shape in (SHAPES[:1] if quick else SHAPES)
            for preset, variant, overrides in RUNS]
    table = run_mesh_rows(grid, one_run, lambda shape, preset, variant, overrides: f"{shape}: {preset} ({variant})")
    cols = ["shape", "class", "preset", "variant", "noise_ratio", "smooth_k", "redone", "real_seeds", "cd_p2s",
            "faces", "boundary_edges", "components", "seconds"]
    write_cd_report(out, "noisy_scan_seeds", "Seeds and smoothing on the realistic scan", __doc__, table, cols,
                    {"noise_ratio": ".3f", "seconds": ".0f"})
