"""Same seed, same mesh on any thread count: whole point-cloud reconstructions hashed on 1 and 2 threads.

The tests check byte-identical kernels across thread counts and a tiny reconstruction
(`tests/test_pointcloud.py::test_same_seed_same_mesh_on_any_thread_count`); this bench checks full-size runs.
Each case runs in a fresh process capped at N threads (`eval.runner.limit_threads`), on 100K samples of the GT
with their normals (seed 0): the `fast` preset (no gradient step) and a cut-down `paper` preset (40 phase-1 +
20 phase-2 steps, so the steps' gathers and sums are exercised). `hash`: SHA-1 of the output's vertex and
face arrays (first 12 hex digits); `same`: whether every thread count gave that case the same hash.
"""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys

from eval.bench.common import markdown_table, write_report

CASES = (("torus", "fast"), ("mushroom", "fast"), ("torus", "paper, 40 + 20 steps"))
THREADS = (1, 2)


def _one(name: str, recipe: str, threads: int) -> dict:
    """One reconstruction in this process (already capped at `threads`)."""
    import time

    import numpy as np

    from datasets.sampling import sample_points
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct
    from eval.bench.quality import SAMPLES, _gt
    from eval.metrics import chamfer_l1_p2s

    gt = _gt(name)
    pts, nrm = sample_points(gt, SAMPLES, 0)
    cfg = (PointCloudConfig.preset("fast") if recipe == "fast"
           else PointCloudConfig.preset("paper", steps_phase1=40, steps_phase2=20))
    t0 = time.perf_counter()
    res = reconstruct(pts, nrm, cfg)
    seconds = time.perf_counter() - t0
    v, f = np.ascontiguousarray(res.mesh.vertices), np.ascontiguousarray(res.mesh.faces)
    return {"shape": name, "recipe": recipe, "threads": threads, "faces": int(len(f)),
            "hash": hashlib.sha1(v.tobytes() + f.tobytes()).hexdigest()[:12],
            "cd_p2s_1e3": 1e3 * float(chamfer_l1_p2s(res.mesh, gt)), "seconds": seconds}


def _in_subprocess(name: str, recipe: str, threads: int) -> dict:
    code = ("import json, sys; from eval.runner import limit_threads; limit_threads(%d); "
            "from eval.bench.threads import _one; print('RESULT ' + json.dumps(_one(%r, %r, %d)))"
            % (threads, name, recipe, threads))
    out = subprocess.run([sys.executable, "-c", code],  # option-safe: code is written here, after -c
                         capture_output=True, text=True, check=True).stdout
    return json.loads(next(line for line in out.splitlines() if line.startswith("RESULT "))[7:])


def main(out: str = "reports", quick: bool = False) -> None:
    rows = []
    for name, recipe in CASES[:1] if quick else CASES:
        case = [_in_subprocess(name, recipe, n) for n in THREADS]
        same = len({r["hash"] for r in case}) == 1
        rows += [{**r, "same": "yes" if same else "NO"} for r in case]
    columns = ["shape", "recipe", "threads", "faces", "hash", "cd_p2s_1e3", "seconds", "same"]
    table = markdown_table(rows, columns, {"cd_p2s_1e3": ".4g", "seconds": ".1f"})
    write_report(out, "bench_threads", "Same seed, same mesh on 1 and 2 threads", __doc__, table, rows)


if __name__ == "__main__":
    main()
