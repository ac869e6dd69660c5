"""Benchmark of one full face-probability pass: WDT, power diagram, candidate update, argmin searches,
Lambda forward and the backward of Lambda.sum(), per stage, with peak memory.

Targets (issue [2]): 10K points <= 80 ms, 100K <= 840 ms per pass on 2 cores; peak memory at 100K <= 4 GB.
Issue [step]: the pass with backward at 10K points <= 2.5x one WDT of the same points. Both implementations
(`ProbabilityConfig.impl`) run in one process, so their ratio is measured under the same load.
"""
from __future__ import annotations

import resource
import statistics
import time

import numpy as np

from eval.bench.common import markdown_table, write_report

IMPLS = ("reference", "native")
STAGES = ["wdt", "power_diagram", "candidates", "knn", "existing", "nonexisting", "probabilities", "backward"]


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(out: str = "reports", quick: bool = False) -> None:
    import dmesh
    from dmesh import wdt
    from dmesh.probability import ProbabilityConfig

    sizes = [2000, 10000] if quick else [10000, 100000]
    passes = 3 if quick else 4
    rows = []
    for n in sizes:
        rng = np.random.default_rng(0)
        h = n ** (-1.0 / 3.0)
        # Real values as in a converged DMesh: half the points real (1), half imaginary (0).
        reals = (rng.random(n) < 0.5).astype(np.float32)
        points, weights = rng.random((n, 3)), rng.uniform(0, 0.1 * h * h, n)
        wdt_times = []
        for _ in range(3):
            t0 = time.perf_counter()
            wdt.triangulate(points, weights)
            wdt_times.append(time.perf_counter() - t0)
        wdt_s = statistics.median(wdt_times)
        for impl in IMPLS:
            dm = dmesh.DMesh(points, weights, reals, ProbabilityConfig(impl=impl))
            per_pass = []
            for k in range(passes):  # pass 0 adds kNN triples (every 10th pass does); the others do not
                tm: dict[str, float] = {}
                c0 = time.process_time()
                t0 = time.perf_counter()
                fp = dm.face_probabilities(timings=tm)
                t1 = time.perf_counter()
                fp.prob.sum().backward()
                tm["backward"] = time.perf_counter() - t1
                tm["total"] = time.perf_counter() - t0
                tm["cpu"] = time.process_time() - c0
                tm["faces"] = len(fp.faces)
                per_pass.append(tm)
                for p in dm.parameters():
                    p.grad = None
                print(f"N={n} {impl} pass {k}: {tm['total']:.3f} s " +
                      " ".join(f"{s}={tm.get(s, 0.0):.3f}" for s in STAGES), flush=True)
            steady = per_pass[1:]
            row = {"N": n, "impl": impl, "kind": "steady pass (no kNN)"}
            for s in STAGES + ["total", "cpu"]:
                row[s] = statistics.median(p.get(s, 0.0) for p in steady)
            row["wdt_alone"] = wdt_s
            row["total_over_wdt"] = row["total"] / wdt_s
            row["scored_faces"] = steady[-1]["faces"]
            row["peak_rss_mb"] = _peak_rss_mb()
            rows.append(row)
            knn = {"N": n, "impl": impl, "kind": "pass with kNN update"}
            knn |= {s: per_pass[0].get(s, 0.0) for s in STAGES + ["total", "cpu"]}
            knn |= {"wdt_alone": wdt_s, "total_over_wdt": knn["total"] / wdt_s, "scored_faces": per_pass[0]["faces"],
                    "peak_rss_mb": row["peak_rss_mb"]}
            rows.append(knn)
    cols = ["N", "impl", "kind"] + STAGES + ["total", "cpu", "wdt_alone", "total_over_wdt", "scored_faces",
                                             "peak_rss_mb"]
    fmt = {s: ".3f" for s in STAGES + ["total", "cpu", "wdt_alone"]} | {"peak_rss_mb": ".0f", "total_over_wdt": ".1f"}
    steady = [r for r in rows if r["kind"].startswith("steady") and r["impl"] == "native"]
    dominant = ", ".join(
        f"N={r['N']}: {max(STAGES, key=lambda s: r[s])} ({r[max(STAGES, key=lambda s: r[s])] / r['total']:.0%})"
        for r in steady)
    ratio = ", ".join(f"N={r['N']}: {r['total_over_wdt']:.1f}x" for r in steady)
    intro = (
        "Uniform points in the unit cube (seed 0), weights U[0, 0.1 h^2], half the points real (1) and half "
        "imaginary (0) as in a converged DMesh; one `DMesh.face_probabilities()` pass plus "
        "`prob.sum().backward()`, in seconds (median of the passes after the first; the first pass also adds "
        "the kNN candidate triples, which happens every 10th pass), with `ProbabilityConfig.impl` = "
        "`reference` (the torch recomputation of the chosen distances, `dmesh/reference/probability.py`: the "
        "code before the native kernels) and `native` (fused native search + distances, analytic native "
        "backward), in one process. Stages: `wdt` "
        "(CGAL), `power_diagram` (orthocentres, faces, adjacency), `candidates` (neighbour cache + WDT faces "
        "into the candidate set), `knn` (kNN triples), `existing` (nearest-plane search + distances "
        "for WDT faces), `nonexisting` (line-to-cell search + distances for candidates), `probabilities` "
        "(Lambda), `backward`; `total` is wall time, `cpu` the process CPU time of the same pass (both threads "
        "counted; less sensitive than wall time to other load on a shared machine); `wdt_alone` is one "
        "triangulation of the same points (median of 3) and `total_over_wdt` the pass against it. Peak RSS is "
        "the process's high-water mark after that size. Targets: 10K <= 0.080 s, 100K <= 0.840 s, 100K peak "
        f"<= 4096 MB; issue [step]: the full pass with backward at 10K <= 2.5x one WDT (native, steady: {ratio}). "
        f"Dominant stage (native): {dominant}.")
    write_report(out, "bench_probability", "Face probability pass", intro, markdown_table(rows, cols, fmt), rows)
