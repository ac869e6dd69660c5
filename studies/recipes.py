"""When do point-cloud gradient steps pay? Phase-1 steps on top of the `fast` start, clean and noisy input.

Each case reconstructs one shape from 100K samples of its surface (normalised to radius 1), clean or with
Gaussian noise of sigma 0.005 on every coordinate, with the `fast` preset plus 20 phase-1 steps at a few
learning rates (lr = per-step bound), moving all parameters or only the positions, and at two sample
counts. The table gives CD p2s of the output against the clean GT, output faces, wall time, and the
phase-1 loss at the first and last step; the `fast` row (no phase-1 step) is each group's reference.

Regenerate: `python -m studies recipes` (torus, bowl and plant at the fast preset's seeds; an hour or more
on 2 cores); `--quick`: torus at 10K seeds.
"""
from __future__ import annotations

import time

import numpy as np

from dmesh.recon.config import FAST_SEEDS
from eval.bench.common import markdown_table, write_report

#: Input noise levels (unit-radius frame).
NOISE = (0.0, 0.005)
#: (label, overrides of the fast preset).
CASES = (
    ("fast (no phase-1 step)", {}),
    ("+20 steps, lr 1e-5, all", {"steps_phase1": 20, "lr": 1e-5, "update_bound": 1e-5}),
    ("+20 steps, lr 1e-4, all", {"steps_phase1": 20, "lr": 1e-4, "update_bound": 1e-4}),
    ("+20 steps, lr 3e-4, all", {"steps_phase1": 20, "lr": 3e-4, "update_bound": 3e-4}),
    ("+20 steps, lr 3e-4, positions", {"steps_phase1": 20, "lr": 3e-4, "update_bound": 3e-4,
                                       "train_phase1": ("points",)}),
    ("+20 steps, lr 3e-4, positions, 100K samples", {"steps_phase1": 20, "lr": 3e-4, "update_bound": 3e-4,
                                                     "train_phase1": ("points",), "num_samples": 100_000,
                                                     "num_target": 100_000}),
)


def run(shape: str, noise: float, num_init: int | None) -> list[dict]:
    from datasets.normalize import normalize
    from datasets.sampling import sample_points
    from datasets.synthetic import generate
    from dmesh.recon.pointcloud import PointCloudConfig, reconstruct
    from eval.metrics import chamfer_l1_p2s

    gt, _ = normalize(generate(shape))
    pts, nrm = sample_points(gt, 100_000, 0)
    if noise:
        pts = pts + np.random.default_rng(1).normal(0.0, noise, pts.shape)
    rows = []
    for label, overrides in CASES:
        cfg = PointCloudConfig.fast(**overrides, **({"num_init": num_init} if num_init else {}))
        t0 = time.perf_counter()
        res = reconstruct(pts, nrm, cfg)
        wall = time.perf_counter() - t0
        steps = [h for h in res.history if h["phase"] == 1]
        rows.append({"shape": shape, "noise": noise, "case": label, "cd_p2s_e3": chamfer_l1_p2s(res.mesh, gt) * 1e3,
                     "faces": len(res.mesh.faces), "time_s": wall,
                     "loss_first": steps[0]["loss"] if steps else "", "loss_last": steps[-1]["loss"] if steps else ""})
        print(f"  {shape} noise {noise} {label}: CD p2s {rows[-1]['cd_p2s_e3']:.3f}e-3, {wall:.0f} s", flush=True)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    rows = []
    for shape in ("torus",) if quick else ("torus", "bowl", "plant"):
        for noise in NOISE:
            rows += run(shape, noise, 10_000 if quick else None)
    cols = ["shape", "noise", "case", "cd_p2s_e3", "faces", "time_s", "loss_first", "loss_last"]
    fmt = {"cd_p2s_e3": ".3f", "time_s": ".0f", "loss_first": ".5f", "loss_last": ".5f"}
    intro = (__doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip()
             + "\n\nSeeds: " + ("10K (--quick)" if quick else f"the fast preset's {FAST_SEEDS // 1000}K")
             + ". CD p2s in units of 1e-3.")
    write_report(out, "recipes", "When point-cloud gradient steps pay", intro,
                 markdown_table(rows, cols, fmt), rows)


if __name__ == "__main__":
    main()
