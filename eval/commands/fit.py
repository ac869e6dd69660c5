"""`dmesh fit`: convert a mesh into a DMesh (the paper's Exp. 1) and report RE / FP."""
from __future__ import annotations

import json
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

NAME = "fit"
HELP = "recover MESH's connectivity as a DMesh (Exp. 1); writes the state, the mesh and RE/FP to OUT"


def add_arguments(p):
    p.add_argument("mesh", metavar="MESH", help="mesh file (OBJ, PLY, OFF, STL, GLB)")
    p.add_argument("-o", "--out", metavar="OUT", required=True, help="output folder (created or replaced)")
    p.add_argument("--preset", choices=["fast", "paper"], default="fast",
                   help="fast: a CPU budget (default); paper: the published settings (20K steps)")
    p.add_argument("--steps", type=int, default=None, help="maximum steps (default: the preset's)")
    p.add_argument("--seed", type=int, default=0)


def fit_mesh(path: str, preset: str = "fast", steps: int | None = None, seed: int = 0, callback=None) -> dict:
    """Loads, normalises (max vertex norm 0.8) and converts the mesh; returns the result and the mesh frame."""
    import numpy as np

    from datasets.meshes import load_mesh
    from datasets.normalize import normalize
    from dmesh.recon.mesh_to_dmesh import PRESETS, mesh_to_dmesh

    mesh = load_mesh(path, orient=True)
    if len(mesh.faces) == 0:
        raise ValueError(f"{path}: the mesh has no faces")
    mesh, transform = normalize(mesh, radius=0.8)
    overrides = {"seed": seed} | ({} if steps is None else {"steps": steps})
    cfg = PRESETS[preset](**overrides)
    t0 = time.perf_counter()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    result = mesh_to_dmesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), cfg, callback)
    return {"result": result, "mesh": mesh, "transform": transform, "time_s": time.perf_counter() - t0,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "peak_rss_growth_mb": (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024.0}


def run(args) -> int:
    import numpy as np
    import torch
    import trimesh

    import dmesh
    from eval.cli import check_output_dir
    from eval.progress import progress
    from eval.values import check_seed

    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be at least 1, got {args.steps}")
    check_seed("--seed", args.seed)
    out = check_output_dir(args.out, "-o", inputs=[args.mesh])  # the folder is replaced as a whole
    if out.is_dir() and any(out.iterdir()) and not (out / "result.json").is_file():
        raise ValueError(f"-o {out}: a folder that holds no earlier `dmesh fit` output (no result.json); it "
                         f"would be replaced: choose another -o")
    if Path(args.mesh).is_dir():
        raise ValueError(f"{args.mesh}: is a folder, not a mesh file")
    bar = progress(total=args.steps, desc="fit", unit="step")

    def callback(entry):
        bar.update(1)
        bar.set_postfix(RE=f"{100 * entry['re']:.2f}%", FP=f"{100 * entry['fp']:.2f}%", points=entry["points"])

    try:
        fitted = fit_mesh(args.mesh, args.preset, args.steps, args.seed, callback)
    finally:
        bar.close()
    r = fitted["result"]
    b = r.best  # the kept state (see MeshToDMeshResult.best); the final state's figures are reported too
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        from eval.io import honour_umask, write_mesh

        honour_umask(tmp)  # mkdtemp makes it 0o700
        g = len(fitted["mesh"].vertices)
        reals = np.r_[np.ones(g), np.zeros(len(b.points) - g)]  # GT vertices real, inserted points not
        state = dmesh.DMesh(b.points, b.weights, reals, dtype=torch.float64)
        state.save(tmp / "dmesh.npz")
        write_mesh(trimesh.Trimesh(b.points, b.faces, process=False), tmp / "mesh.ply")
        summary = {
            "mesh": str(args.mesh), "shape": Path(args.mesh).stem, "preset": args.preset, "seed": args.seed,
            "RE": 100 * b.re, "FP": 100 * b.fp, "state_step": b.step, "final_RE": 100 * r.re,
            "final_FP": 100 * r.fp, "best_RE": 100 * r.best_re.re, "best_RE_FP": 100 * r.best_re.fp,
            "best_FP": 100 * r.best_fp.fp, "best_FP_RE": 100 * r.best_fp.re, "steps": r.steps,
            "stopped_early": r.stopped_early, "time_s": fitted["time_s"], "peak_rss_mb": fitted["peak_rss_mb"],
            "points": len(r.points), "gt_vertices": len(fitted["mesh"].vertices),
            "gt_faces": int(len(fitted["mesh"].faces)), "timings": r.timings, "config": r.config,
            "frame": "vertex mean at the origin, max vertex norm 0.8", "units": "RE and FP in percent",
        }
        (tmp / "result.json").write_text(json.dumps(summary, indent=2) + "\n")
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    print(f"RE {summary['RE']:.2f}%  FP {summary['FP']:.2f}% (state of step {b.step})  steps {r.steps}  "
          f"time {fitted['time_s']:.1f} s  -> {out}")
    return 0
