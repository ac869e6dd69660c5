"""Benchmark of the CPU renderers: forward and backward time per view at 256x256.

Targets (issue [6]): soft renderer with 2e5 faces, forward <= 150 ms and backward <= 300 ms per view on 2
cores. Scenes: a random triangle soup filling the unit ball (opacity 0.5), sized like the faces of a
Delaunay tetrahedralisation of the same number of faces (about 13 faces per point, so edge length
h = (4.19 * 13 / F)^(1/3)); cameras of the capture rig at distance 2, fov 65 degrees. The tet renderer
walks the Delaunay tetrahedralisation of random points in the unit ball (opacity 0.1 on every face).
The naive reference (`dmesh.reference.render`, torch, O(pixels x faces)) is timed on a small case only.
"""
from __future__ import annotations

import os
import time

import numpy as np
import torch

from datasets.capture import camera_rig
from eval.bench.common import markdown_table, time_call, write_report


def triangle_soup(num_faces: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(3F, 3) float32 vertices and (F, 3) int32 faces of random triangles inside the unit ball."""
    rng = np.random.default_rng(seed)
    h = (4.19 * 13.0 / num_faces) ** (1.0 / 3.0)
    c = rng.normal(size=(num_faces, 3))
    c *= (rng.random(num_faces) ** (1.0 / 3.0) / np.linalg.norm(c, axis=1))[:, None] * (1.0 - h)
    v = c[:, None, :] + h * rng.uniform(-0.6, 0.6, (num_faces, 3, 3))
    return v.reshape(-1, 3).astype(np.float32), np.arange(3 * num_faces, dtype=np.int32).reshape(-1, 3)


def _soft_case(num_faces: int, res: int, repeats: int, views: int, num_threads: int | None = None):
    from dmesh.render import Camera, soft_render

    v, f = triangle_soup(num_faces)
    cams = Camera.from_views(camera_rig(4)[0][:views], resolution=res)
    vt = torch.tensor(v, requires_grad=True)
    ot = torch.full((len(f),), 0.5, requires_grad=True)
    ft = torch.tensor(f)
    fwd, bwd, frags = [], [], []
    for cam in cams:
        t = _cpu_and_wall(lambda: soft_render(vt, ft, ot, cam, num_threads=num_threads), repeats)
        fwd.append(t)
        holder = {}

        def forward_then_keep():
            out = soft_render(vt, ft, ot, cam, num_threads=num_threads)
            holder["loss"] = out["diffuse"].sum() + out["depth"].sum() + out["alpha"].sum()

        def backward():
            forward_then_keep()  # not timed: a fresh graph for each backward call
            c0, t0 = time.process_time(), time.perf_counter()
            holder["loss"].backward()
            holder["t"].append(time.perf_counter() - t0)
            holder["c"].append(time.process_time() - c0)

        holder["t"], holder["c"] = [], []
        backward()  # warm-up
        holder["t"], holder["c"] = [], []
        for _ in range(repeats):
            backward()
        ts = holder["t"]
        bwd.append({"median": float(np.median(ts)), "min": min(ts), "max": max(ts),
                    "cpu": float(np.median(holder["c"]))})
        out = soft_render(vt, ft, ot, cam)
        frags.append(float(out["alpha"].detach().mean()))
    return fwd, bwd, frags


def _cpu_and_wall(fn, repeats: int) -> dict:
    """time_call's statistics plus "cpu": the median process CPU time (all threads) of one call."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"median": float(np.median(wall)), "min": min(wall), "max": max(wall), "cpu": float(np.median(cpu))}


def _tet_case(num_points: int, res: int, repeats: int, views: int):
    from dmesh.render import Camera, tet_render
    from dmesh.wdt import PowerDiagram

    rng = np.random.default_rng(0)
    p = rng.normal(size=(num_points, 3))
    p *= (rng.random(num_points) ** (1.0 / 3.0) / np.linalg.norm(p, axis=1))[:, None]
    pd = PowerDiagram.from_points(p)
    cams = Camera.from_views(camera_rig(4, distance=2.5)[0][:views], resolution=res)
    ot = torch.full((len(pd.faces),), 0.1, requires_grad=True)
    fwd, bwd = [], []
    for cam in cams:
        fwd.append(_cpu_and_wall(lambda: tet_render(p, pd.tets, pd.faces, pd.face_tets, ot, cam), repeats))
        out = tet_render(p, pd.tets, pd.faces, pd.face_tets, ot, cam)
        loss = out["diffuse"].sum() + out["depth"].sum()
        bwd.append(_cpu_and_wall(lambda: torch.autograd.grad(loss, ot, retain_graph=True), repeats))
    return len(pd.faces), fwd, bwd


def _reference_case(num_faces: int, res: int):
    from dmesh.reference.render import soft_render_naive
    from dmesh.render import Camera, soft_render

    v, f = triangle_soup(num_faces)
    cam = Camera.from_views(camera_rig(4)[0][:1], resolution=res)[0]
    o = torch.full((len(f),), 0.5)
    vt = torch.tensor(v, dtype=torch.float64, requires_grad=True)

    def ref():
        out = soft_render_naive(vt, torch.tensor(f), o, cam, chunk=256)
        (out["diffuse"].sum() + out["depth"].sum()).backward()

    vn = torch.tensor(v, requires_grad=True)

    def nat():
        out = soft_render(vn, torch.tensor(f), o, cam)
        (out["diffuse"].sum() + out["depth"].sum()).backward()

    return time_call(ref, 2), time_call(nat, 5)


def _row(renderer, faces, res, fwd, bwd, extra=""):
    med = lambda xs: float(np.median([x["median"] for x in xs]))  # noqa: E731
    return {"renderer": renderer, "faces": faces, "pixels": f"{res}x{res}", "views": len(fwd),
            "forward_ms": 1e3 * med(fwd), "forward_min_ms": 1e3 * min(x["min"] for x in fwd),
            "forward_max_ms": 1e3 * max(x["max"] for x in fwd),
            "backward_ms": 1e3 * med(bwd), "backward_min_ms": 1e3 * min(x["min"] for x in bwd),
            "backward_max_ms": 1e3 * max(x["max"] for x in bwd),
            "forward_cpu_ms": 1e3 * float(np.median([x["cpu"] for x in fwd])),
            "backward_cpu_ms": 1e3 * float(np.median([x["cpu"] for x in bwd])), "note": extra}


def main(out: str = "reports", quick: bool = False) -> None:
    load_start = os.getloadavg()[0]
    repeats = 2 if quick else 5
    views = 1 if quick else 2
    rows = []
    threads = torch.get_num_threads()
    for faces, nt in ([(20000, None)] if quick else [(20000, None), (200000, None), (200000, 1)]):
        fwd, bwd, cover = _soft_case(faces, 256, repeats, views, nt)
        rows.append(_row(f"soft (native, {nt or threads} threads)", faces, 256, fwd, bwd,
                         f"opacity 0.5, mean alpha {np.mean(cover):.2f}"))
        print(f"soft F={faces}: forward {rows[-1]['forward_ms']:.1f} ms, backward {rows[-1]['backward_ms']:.1f} ms",
              flush=True)
    nf, fwd, bwd = _tet_case(2000 if quick else 15000, 256, repeats, views)
    rows.append(_row(f"tet walk (native, {threads} threads)", nf, 256, fwd, bwd,
                     "Delaunay of random points, opacity 0.1"))
    print(f"tet F={nf}: forward {rows[-1]['forward_ms']:.1f} ms, backward {rows[-1]['backward_ms']:.1f} ms", flush=True)
    ref, nat = _reference_case(500, 32)
    for name, t in (("soft reference (torch, naive)", ref), (f"soft (native, {threads} threads)", nat)):
        r = {"renderer": name, "faces": 500, "pixels": "32x32", "views": 1,
             "forward_ms": float("nan"), "forward_min_ms": float("nan"), "forward_max_ms": float("nan"),
             "backward_ms": float("nan"), "backward_min_ms": float("nan"), "backward_max_ms": float("nan"),
             "forward_cpu_ms": float("nan"), "backward_cpu_ms": float("nan"),
             "note": f"forward + backward together: {1e3 * t['median']:.1f} ms (min {1e3 * t['min']:.1f}, "
                     f"max {1e3 * t['max']:.1f})"}
        rows.append(r)
    cols = ["renderer", "faces", "pixels", "views", "forward_ms", "forward_min_ms", "forward_max_ms", "backward_ms",
            "backward_min_ms", "backward_max_ms", "forward_cpu_ms", "backward_cpu_ms", "note"]
    fmt = {c: ".1f" for c in cols if c.endswith("_ms")}
    intro = (__doc__.split("\n", 2)[2].strip() + "\n\nTimes are per view, median over views of the median of "
             f"{repeats} runs after one warm-up (min and max over all runs), through the public Python functions "
             "(`dmesh.render.soft_render` / `tet_render`; backward = `loss.backward()` of diffuse + depth + alpha "
             "sums, the forward not included). `*_cpu_ms` is the process CPU time of one call, all threads "
             "together (median): on an idle machine the wall time with 2 threads is at least half of it. "
             "Native threads = torch.get_num_threads() unless the row says otherwise. The machine is shared "
             f"with other jobs, so times are noisy upwards: 1-minute load average {load_start:.1f} at the start "
             f"and {os.getloadavg()[0]:.1f} at the end of this run, on {os.cpu_count()} cores.")
    write_report(out, "bench_render", "CPU renderers", intro, markdown_table(rows, cols, fmt), rows)
