"""Benchmark of the weighted Delaunay triangulation: our Python call versus CGAL's raw insertion time.

Targets (issue [1]): 100K points in at most 0.45 s sequential, 0.35 s with TBB on 2 cores; our call at
most 1.25x the raw CGAL insertion time measured inside the same native call.
"""
from __future__ import annotations

import statistics
import time

import numpy as np

from dmesh import native, wdt
from eval.bench.common import markdown_table, write_report


def _case(n: int, weights: str, rng) -> tuple[np.ndarray, np.ndarray]:
    p = rng.random((n, 3))
    h = n ** (-1.0 / 3.0)
    w = rng.uniform(0.0, 0.1 * h * h, n) if weights == "spacing" else np.zeros(n)
    return p, w


def main(out: str = "reports", quick: bool = False) -> None:
    sizes = [1000, 10000] if quick else [1000, 10000, 100000]
    repeats = {1000: 20, 10000: 7, 100000: 5}
    rng = np.random.default_rng(0)
    modes = [False, True] if native.have_tbb() else [False]
    rows = []
    for n in sizes:
        for weights in ("spacing", "equal"):
            p, w = _case(n, weights, rng)
            for parallel in modes:
                wdt.triangulate(p, w, parallel=parallel)  # warm-up
                call, insert = [], []
                for _ in range(repeats[n] if not quick else 3):
                    t0 = time.perf_counter()
                    tri = wdt.triangulate(p, w, parallel=parallel)
                    call.append(time.perf_counter() - t0)
                    insert.append(tri.insert_seconds)
                rows.append({
                    "N": n, "weights": "U[0, 0.1 h^2]" if weights == "spacing" else "equal",
                    "mode": "TBB" if parallel else "sequential", "tets": len(tri.tets),
                    "call_median_s": statistics.median(call), "call_min_s": min(call), "call_max_s": max(call),
                    "cgal_insert_median_s": statistics.median(insert),
                    "call_over_insert": statistics.median(np.divide(call, insert)),
                })
                r = rows[-1]
                print(f"N={n:>6} {r['weights']:<14} {r['mode']:<10} call {r['call_median_s']:.4f} s  "
                      f"insert {r['cgal_insert_median_s']:.4f} s  ratio {r['call_over_insert']:.3f}", flush=True)
    cols = ["N", "weights", "mode", "tets", "call_median_s", "call_min_s", "call_max_s", "cgal_insert_median_s",
            "call_over_insert"]
    fmt = {c: ".4f" for c in cols if c.endswith("_s")} | {"call_over_insert": ".3f"}
    intro = ("Uniform points in the unit cube (seed 0), weights either U[0, 0.1 h^2] with h = N^(-1/3) or all "
             "equal. `call` is `dmesh.wdt.triangulate` from Python (conversion, duplicate merge, insertion, "
             "extraction of tets and adjacency); `cgal_insert` is CGAL's range insertion alone, timed inside the "
             "same native call; `call_over_insert` is the median of their per-run ratio. Targets: 100K in <= "
             "0.45 s sequential and <= 0.35 s with TBB on 2 cores; ratio <= 1.25.")
    write_report(out, "bench_wdt", "Weighted Delaunay triangulation", intro, markdown_table(rows, cols, fmt), rows)
