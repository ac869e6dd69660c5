"""How many pixels the noisy depth start fits each point from (`MultiViewConfig.init_pool_k`).

With depth noise, the multi-view `depth` start (`dmesh.recon.multiview.depth_init`) moves each of its 100K
lifted pixels onto the quadratic jet fitted to its k nearest of all the lifted pixels
(`dmesh.recon.views.smooth_from_pool`), then runs the point-cloud `fast` fit. k = 0 is the start before the
pool: the point-cloud `noisy` preset, which jet-smooths the 100K points from 120 of themselves. One shape per
class (torus, bowl, plant), normalised to radius 1, captured in 64 views at 256 pixels, Gaussian depth noise
as a fraction of the radius (`datasets.corrupt.add_depth_noise`). The table gives the mean distance of the
100K points to the GT before and after the smoothing (every fifth point), the start's CD p2s against the GT,
its wall time (one thread) and the number of lifted pixels.

Regenerate: `python -m studies depth_pool` (about 30 minutes on one core; `--quick`: the torus at 0.5 %
noise, k 0 and 500).
"""
from __future__ import annotations

import time

import numpy as np

from eval.bench.common import markdown_table, write_report

SHAPES = ("torus", "bowl", "plant")
LEVELS = (0.0025, 0.005, 0.01)
POOL_K = (0, 200, 500, 1000)
QUICK = (("torus",), (0.005,), (0, 500))


def off_surface(gt, points: np.ndarray) -> float:
    """Mean distance of every fifth point to the GT's surface."""
    import trimesh

    return float(np.abs(trimesh.proximity.closest_point(gt, points[::5])[1]).mean())


def run(shape: str, levels, pool_ks) -> list[dict]:
    import torch

    from datasets.capture import capture
    from datasets.corrupt import add_depth_noise
    from dmesh.recon import multiview
    from dmesh.recon.multiview import MultiViewConfig, reconstruct
    from dmesh.recon.views import check_views, normalisation
    from studies.depth_noise import load_shape
    from eval.metrics import chamfer_l1_p2s

    torch.set_num_threads(1)
    gt = load_shape(shape)
    clean = capture(gt, 64, 256)
    rows = []
    for level in levels:
        views = add_depth_noise(clean, level, 0)
        for k in pool_ks:
            seen = {}
            smooth = multiview.smooth_from_pool

            def spy(points, pool, kk, workers=1):  # the start's points before and after, in its frame
                out = smooth(points, pool, kk, workers)
                seen["before"], seen["after"] = points, out
                return out

            multiview.smooth_from_pool = spy
            try:
                t0 = time.perf_counter()
                res = reconstruct(views, MultiViewConfig.depth(init_pool_k=k))
                wall = time.perf_counter() - t0
            finally:
                multiview.smooth_from_pool = smooth
            start = res.info["init_depth"]
            row = {"shape": shape, "depth_noise": level, "pool_k": k, "preset": start["preset"],
                   "pixels": start["pixels"], "cd_p2s_e3": chamfer_l1_p2s(res.mesh, gt) * 1e3, "time_s": wall,
                   "off_before_e3": "", "off_after_e3": ""}
            if seen:  # the start's points are in the reconstruction's normalised frame
                center, scale = normalisation(check_views(views))[:2]
                row["off_before_e3"] = off_surface(gt, seen["before"] / scale + center) * 1e3
                row["off_after_e3"] = off_surface(gt, seen["after"] / scale + center) * 1e3
            rows.append(row)
            print(f"  {shape} noise {level:g} k {k}: CD p2s {row['cd_p2s_e3']:.3f}e-3, {wall:.0f} s", flush=True)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    shapes, levels, pool_ks = QUICK if quick else (SHAPES, LEVELS, POOL_K)
    rows = []
    for shape in shapes:
        rows += run(shape, levels, pool_ks)
    cols = ["shape", "depth_noise", "pool_k", "preset", "pixels", "off_before_e3", "off_after_e3", "cd_p2s_e3",
            "time_s"]
    fmt = {"depth_noise": "g", "off_before_e3": ".3f", "off_after_e3": ".3f", "cd_p2s_e3": ".3f", "time_s": ".0f"}
    intro = (__doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip()
             + "\n\nDistances and CD p2s in units of 1e-3; off_before / off_after are blank for k = 0 (no pool).")
    write_report(out, "depth_pool", "Noisy depth start: pixels per fitted point", intro,
                 markdown_table(rows, cols, fmt), rows)


if __name__ == "__main__":
    main()
