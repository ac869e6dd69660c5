"""Seeds on noisy point clouds: the point-cloud `fast` preset (which smooths an input that looks noisy by
itself) with the seeds of a smoothed input capped at 100K (every point: the preset before the cap), 20K (its
default, `smoothed_seeds`) and 10K, on the robustness sweep's noisy clouds.

Why: on noisy clouds `fast`'s meshes came out in many pieces while their CD held: after the jet smoothing
the points may still lie off the surface by about a seed spacing, so the one-sheet extraction finds no
coherent sheet. Fewer seeds, farther apart than the remaining noise, give a sheet. For each shape and noise
level the preset (`PointCloudConfig.fast(smoothed_seeds=...)`, seed 0, with the input normals, as the harness
runs it) runs on the cached input of `eval/sweeps/robustness.yaml` (100K points, Gaussian noise of sigma x
the unit radius; made as the sweep makes it, in `runs/paper`). Figures: the input's `noise_ratio` (before
smoothing: distance to the local plane in neighbour spacings), whether the run smoothed (`smooth_k`), CD p2s
(x1e-3, 100K samples per side, as the tables), faces, boundary edges, connected components, and seconds.

Regenerate: `python -m studies noisy_seeds` (54 runs, about 20 minutes on one core; `--quick`: the wavy
sheet at 1 % only).
"""
from __future__ import annotations

import time

import numpy as np

from eval.bench.common import mesh_figures, run_mesh_rows, write_cd_report

WORK = "runs/paper"  # the input cache of the robustness sweep
SHAPES = ("torus", "genus2", "bowl", "wavy_sheet", "plant", "flag_box")
NOISE = (0.0025, 0.005, 0.01)
SEEDS = (100_000, 20_000, 10_000)


def _cloud(shape: str, noise: float):
    """(points, normals, GT path, class) of the robustness sweep's noisy cloud of `shape`."""
    from eval.runner import prepare_gt, prepare_input
    from eval.sweep import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK, 1.0)
    settings = {"n_points": 100_000, "radius": 1.0, "corruption": {"noise": noise}}
    with np.load(prepare_input(ref, gt_path, "pointcloud", settings, 0, WORK)) as z:
        return z["points"], z["normals"], gt_path, ref.category


def one_run(shape: str, noise: float, seeds: int) -> dict:
    """One row: `fast` with `smoothed_seeds=seeds` on the noisy cloud of `shape`."""
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.init import noise_ratio
    from dmesh.recon.pointcloud import reconstruct

    points, normals, gt_path, category = _cloud(shape, noise)
    t0 = time.perf_counter()
    res = reconstruct(points, normals, PointCloudConfig.fast(smoothed_seeds=seeds, seed=0))
    seconds = time.perf_counter() - t0
    return {"shape": shape, "class": category, "noise": noise, "noise_ratio": noise_ratio(points),
            "smoothed_seeds": seeds, "smooth_k": res.info["smooth_k"], **mesh_figures(res.mesh, gt_path),
            "seconds": seconds}


def main(out: str = "reports", quick: bool = False) -> None:
    grid = [("wavy_sheet", 0.01, s) for s in SEEDS] if quick else \
        [(shape, noise, s) for shape in SHAPES for noise in NOISE for s in SEEDS]
    table = run_mesh_rows(grid, one_run, lambda shape, noise, seeds:
                          f"{shape} noise {noise}: smoothed_seeds {seeds}")
    cols = ["shape", "class", "noise", "noise_ratio", "smooth_k", "smoothed_seeds", "cd_p2s", "faces",
            "boundary_edges", "components", "seconds"]
    write_cd_report(out, "noisy_seeds", "Seeds on noisy point clouds", __doc__, table, cols,
                    {"noise_ratio": ".3f", "seconds": ".0f"})
