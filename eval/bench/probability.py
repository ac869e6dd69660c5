"""Benchmark of one full face-probability pass: WDT, power diagram, candidate update, argmin searches,
Lambda forward and the backward of Lambda.sum(), per stage, with peak memory.

Targets (issue [2]): 10K points <= 80 ms, 100K <= 840 ms per pass on 2 cores; peak memory at 100K <= 4 GB.
"""
from __future__ import annotations

import resource
import statistics
import time

import numpy as np

from eval.bench.common import markdown_table, write_report

STAGES = ["wdt", "power_diagram", "candidates", "knn", "existing", "nonexisting", "probabilities", "backward"]


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(out: str = "reports", quick: bool = False) -> None:
    import dmesh

    sizes = [2000, 10000] if quick else [10000, 100000]
    passes = 3 if quick else 4
    rows = []
    for n in sizes:
        rng = np.random.default_rng(0)
        h = n ** (-1.0 / 3.0)
        # Real values as in a converged DMesh: half the points real (1), half imaginary (0).
        reals = (rng.random(n) < 0.5).astype(np.float32)
        dm = dmesh.DMesh(rng.random((n, 3)), rng.uniform(0, 0.1 * h * h, n), reals)
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
            tm["wdt_faces"] = int(fp.in_wdt.sum())
            per_pass.append(tm)
            for p in dm.parameters():
                p.grad = None
            print(f"N={n} pass {k}: {tm['total']:.3f} s " +
                  " ".join(f"{s}={tm.get(s, 0.0):.3f}" for s in STAGES), flush=True)
        steady = per_pass[1:]
        row = {"N": n, "kind": "steady pass (no kNN)"}
        for s in STAGES + ["total", "cpu"]:
            row[s] = statistics.median(p.get(s, 0.0) for p in steady)
        row["scored_faces"] = steady[-1]["faces"]
        row["peak_rss_mb"] = _peak_rss_mb()
        rows.append(row)
        knn = {"N": n, "kind": "pass with kNN update"} | {s: per_pass[0].get(s, 0.0) for s in STAGES + ["total", "cpu"]}
        knn["scored_faces"] = per_pass[0]["faces"]
        knn["peak_rss_mb"] = row["peak_rss_mb"]
        rows.append(knn)
    cols = ["N", "kind"] + STAGES + ["total", "cpu", "scored_faces", "peak_rss_mb"]
    fmt = {s: ".3f" for s in STAGES + ["total", "cpu"]} | {"peak_rss_mb": ".0f"}
    steady = [r for r in rows if r["kind"].startswith("steady")]
    dominant = ", ".join(
        f"N={r['N']}: {max(STAGES, key=lambda s: r[s])} ({r[max(STAGES, key=lambda s: r[s])] / r['total']:.0%})"
        for r in steady)
    intro = (
        "Uniform points in the unit cube (seed 0), weights U[0, 0.1 h^2], half the points real (1) and half "
        "imaginary (0) as in a converged DMesh; one `DMesh.face_"
        "probabilities()` pass plus `prob.sum().backward()`, in seconds (median of the passes after the first; "
        "the first pass also adds the kNN candidate triples, which happens every 10th pass). Stages: `wdt` "
        "(CGAL), `power_diagram` (orthocentres, faces, adjacency), `candidates` (neighbour cache + WDT faces "
        "into the candidate set), `knn` (kNN triples), `existing` (nearest-plane search + torch recomputation "
        "for WDT faces), `nonexisting` (line-to-cell search + recomputation for candidates), `probabilities` "
        "(Lambda), `backward`; `total` is wall time, `cpu` the process CPU time of the same pass (both threads "
        "counted; less sensitive than wall time to other load on a shared machine). Peak RSS is the process's high-water mark after that size. Targets: 10K <= "
        f"0.080 s, 100K <= 0.840 s, 100K peak <= 4096 MB. Dominant stage: {dominant}. Why: the candidates "
        "outside the WDT (kNN triples, about 0.65x as many as the WDT faces) each need, per vertex, an exact "
        "line-crosses-cell test over the vertex's neighbours and a line-to-segment distance to every edge of "
        "its power cell (about 40), about 1.6 us per (face, vertex) on one core; the WDT (CGAL) alone already "
        "takes most of the 100K budget on this CPU. The original reaches the targets only on a GPU.")
    write_report(out, "bench_probability", "Face probability pass", intro, markdown_table(rows, cols, fmt), rows)
