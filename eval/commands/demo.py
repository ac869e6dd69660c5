"""`dmesh demo`: the main job on an embedded default shape."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

NAME = "demo"
HELP = "run DMesh on a built-in synthetic shape and write a summary and meshes under OUT"


def add_arguments(p):
    p.add_argument("-o", "--out", default="out", help="output folder (default: out)")
    p.add_argument("--shape", default="torus", help="built-in synthetic shape (default: torus)")
    p.add_argument("--points", type=int, default=4000, help="surface samples (real points)")
    p.add_argument("--seed", type=int, default=0)


def run(args) -> int:
    import trimesh

    from datasets import synthetic
    from dmesh import wdt
    from eval.io import atomic_path, write_text

    out = Path(args.out)
    rng = np.random.default_rng(args.seed)
    mesh = synthetic.generate(args.shape, seed=args.seed)
    mesh.apply_translation(-mesh.vertices.mean(0))
    mesh.apply_scale(1.0 / np.linalg.norm(mesh.vertices, axis=1).max())
    surface, _ = trimesh.sample.sample_surface(mesh, args.points, seed=args.seed)
    # Imaginary points fill the domain around the surface; real points lie on it.
    extra = rng.uniform(-1.1, 1.1, size=(args.points // 2, 3))
    points = np.concatenate([surface, extra])
    real = np.r_[np.ones(len(surface), bool), np.zeros(len(extra), bool)]
    h = len(points) ** (-1.0 / 3.0) * 2.2
    weights = rng.uniform(0.0, 0.1 * h * h, len(points))

    t0 = time.perf_counter()
    tri = wdt.triangulate(points, weights)
    pd = wdt.PowerDiagram(points, weights, tri.tets, tri.neighbors)
    elapsed = time.perf_counter() - t0
    faces = pd.faces[real[pd.faces].all(axis=1)]
    surf = trimesh.Trimesh(points, faces, process=False)
    surf.remove_unreferenced_vertices()

    summary = {
        "shape": args.shape, "seed": args.seed, "points": len(points), "real_points": int(real.sum()),
        "hidden_points": int(pd.hidden.sum()), "tets": len(tri.tets), "wdt_faces": len(pd.faces),
        "hull_faces": int(pd.is_hull.sum()), "faces_on_real_points": len(faces),
        "triangulation_s": round(tri.total_seconds, 4), "cgal_insert_s": round(tri.insert_seconds, 4),
        "triangulation_and_power_diagram_s": round(elapsed, 4), "tbb": tri.parallel,
    }
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "demo_wdt_faces.ply") as tmp:
        surf.export(tmp, file_type="ply")
    write_text(out / "demo_summary.json", json.dumps(summary, indent=2) + "\n")
    width = max(len(k) for k in summary)
    for k, v in summary.items():
        print(f"{k:<{width}}  {v}")
    print(f"wrote {out / 'demo_summary.json'} and {out / 'demo_wdt_faces.ply'}")
    return 0
