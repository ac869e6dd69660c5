"""What recording a run's executed code costs (`eval.code_deps`), and what the record holds.

The sweep worker runs every method under `eval.code_deps.record` (a global trace function that notes each new
frame's code object), so a run's time includes the record. Here each case is a whole point-cloud
reconstruction, in one process on one thread, made alternately without and with the record after one
warm-up run: from 100K samples of the GT with their normals (seed 0), the `fast` preset (no gradient step)
and a cut-down `paper` preset (40 phase-1 + 20 phase-2 steps); from a 16-view capture at 96 pixels, the
multi-view `tiny` preset (image-loss steps on a small grid). `plain s` / `recorded s`: the median wall time of
the runs without / with the record; `ratio`: recorded / plain (the machine's noise is a few percent).
`code objects`: the distinct code objects the record saw (library code included); `def` / `outline` / `file`:
the entries of the run's `code_deps` by kind; `deps KB`: its JSON size (what the store keeps per run);
`deps_for s`: the time to hash them after the run (not part of the run's time).
"""
from __future__ import annotations

import json
import statistics
import time

from eval.bench.common import markdown_table, write_report

CASES = (("torus", "fast"), ("torus", "paper, 40 + 20 steps"), ("torus", "multi-view tiny"))


def _runner(name: str, recipe: str):
    """(method name, a function making the case's reconstruction once)."""
    from eval.bench.quality import SAMPLES, _gt

    gt = _gt(name)
    if recipe == "multi-view tiny":
        from datasets.capture import capture
        from dmesh.recon.multiview import reconstruct as from_views
        from dmesh.recon.multiview_config import MultiViewConfig

        views = capture(gt, views=16, resolution=96)
        return "dmesh_mv", lambda: from_views(views, MultiViewConfig.preset("tiny"))
    from datasets.sampling import sample_points
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct

    pts, nrm = sample_points(gt, SAMPLES, 0)
    cfg = (PointCloudConfig.preset("fast") if recipe == "fast"
           else PointCloudConfig.preset("paper", steps_phase1=40, steps_phase2=20))
    return "dmesh", lambda: reconstruct(pts, nrm, cfg)


def _case(name: str, recipe: str, repeats: int) -> dict:
    from eval import code_deps
    from eval.sweep import get_method

    method, run = _runner(name, recipe)
    run()  # warm-up: imports, first-call costs
    plain, recorded, executed = [], [], set()
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        plain.append(time.perf_counter() - t0)
        with code_deps.record() as seen:
            t0 = time.perf_counter()
            run()
            recorded.append(time.perf_counter() - t0)
        executed |= seen or set()
    t0 = time.perf_counter()
    deps = code_deps.deps_for(get_method(method), executed)
    deps_s = time.perf_counter() - t0
    kinds = [k.split(":", 1)[0] for k in deps["entries"]]
    p, r = statistics.median(plain), statistics.median(recorded)
    return {"shape": name, "recipe": recipe, "repeats": repeats, "plain_s": p, "recorded_s": r, "ratio": r / p,
            "code_objects": len(executed), "def": kinds.count("def"), "outline": kinds.count("outline"),
            "file": kinds.count("file"), "deps_kb": len(json.dumps(deps)) / 1024.0, "deps_for_s": deps_s}


def main(out: str = "reports", quick: bool = False) -> None:
    import torch

    torch.set_num_threads(1)
    rows = [_case(name, recipe, 1 if quick else 3) for name, recipe in (CASES[::2] if quick else CASES)]
    columns = ["shape", "recipe", "repeats", "plain_s", "recorded_s", "ratio", "code_objects", "def", "outline",
               "file", "deps_kb", "deps_for_s"]
    table = markdown_table(rows, columns, {"plain_s": ".1f", "recorded_s": ".1f", "ratio": ".3f",
                                           "deps_kb": ".1f", "deps_for_s": ".2f"})
    write_report(out, "bench_code_deps", "The cost of recording a run's executed code", __doc__, table, rows)


if __name__ == "__main__":
    main()
