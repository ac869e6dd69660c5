"""When is a point-cloud mesh in shreds? Boundary edges per face against boundary edges per root face.

The `fast` preset makes an unsmoothed run again from the smoothed input when its mesh looks shredded
(`redo_fragmented`, `dmesh.recon.pointcloud.reconstruct`): noise the input's `noise_ratio` missed. Shreds have
boundary in proportion to their faces; an intact surface's rim grows with the square root of its face count.
So boundary edges per face alone (`FRAGMENTED_BOUNDARY`) also flags a small intact mesh of a shape with much rim
(suzanne's eyes and ears at 2K faces); the preset also asks for more than `FRAGMENTED_RIM` boundary edges per
root face (boundary / sqrt(faces)). Both count the oriented surface before the clean-up of its sheets
(info["surface"]'s `rim_edges` and `rim_faces`, the rim stage's: `dmesh.surface.topology.rim_edge_count`, an edge
with more than two faces counting once per face), whose hole fills would hide shreds.

Part 1, fresh runs: the `fast` preset with the redo off, on 20K area-uniform samples (seed 0) of a shape at a
given seed count, clean or with Gaussian noise of sigma x the unit radius (generator seed 2). `per face`: boundary
edges / faces; `per root face`: boundary edges / sqrt(faces); `before` / `now`: whether the redo fires by the
per-face test alone / by both tests.

Part 2, the results store (`runs/paper`, when present): the newest point-cloud `dmesh` run of each key there
(a row of the input and settings, whatever the code version), by group. `clean`:
done runs on clean input (no noise, outliers or scan), their largest figures (the surface before the sheets'
clean-up where the run recorded it, else the mesh's boundary); `first attempts`: the first
pass of every run that was made again (`info["fragmented_attempt"]`), by shape and input.
"""
from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

from eval.bench.common import markdown_table, write_report

CASES = (("mixed/suzanne.obj", 500, 0.0), ("mixed/suzanne.obj", 1000, 0.0), ("mixed/suzanne.obj", 2000, 0.0),
         ("plant", 1000, 0.0), ("flag_box", 1000, 0.0), ("wavy_sheet", 1000, 0.0), ("torus", 100_000, 0.003),
         ("wavy_sheet", 100_000, 0.001))
STORE = Path("runs/paper/results.sqlite")


def _gt(name: str):
    import trimesh

    from datasets import normalize, synthetic
    from eval.sweep import default_data_root

    mesh = (trimesh.load(default_data_root() / name, force="mesh") if "/" in name
            else synthetic.generate(name, seed=0))
    return normalize.normalize(mesh)[0]


def _fresh(name: str, seeds: int, noise: float) -> dict:
    import numpy as np

    from datasets import sampling
    from dmesh.recon.config import FRAGMENTED_BOUNDARY, FRAGMENTED_RIM, PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct

    pts, nrm = sampling.sample_points(_gt(name), 20_000, seed=0)
    if noise:
        pts = pts + np.random.default_rng(2).normal(scale=noise, size=pts.shape)
    res = reconstruct(pts, nrm, PointCloudConfig.fast(redo_fragmented=0.0, num_init=seeds))
    faces, b = res.info["surface"]["rim_faces"], res.info["surface"]["rim_edges"]
    before = b / faces > FRAGMENTED_BOUNDARY and res.info["smooth_k"] == 0
    return {"shape": Path(name).stem, "seeds": seeds, "noise": noise, "faces": faces, "boundary": b,
            "per_face": b / faces, "per_root_face": b / math.sqrt(faces), "before": "redo" if before else "",
            "now": "redo" if before and b > FRAGMENTED_RIM * math.sqrt(faces) else ""}


def _stored(db: Path) -> list[dict]:
    if not db.is_file():
        return []
    con = sqlite3.connect(str(db))
    # The newest done run of each base key (the store keeps the runs of earlier code versions beside it).
    rows = con.execute("SELECT shape, config_label, inputs_json, metrics_json, info_json FROM runs r WHERE "
                       "method='dmesh' AND input_kind='pointcloud' AND status='done' AND finished_at = "
                       "(SELECT MAX(finished_at) FROM runs s WHERE s.base_key = r.base_key AND s.status='done')"
                       ).fetchall()
    con.close()
    clean: dict[str, list] = {}
    out = []
    for shape, label, inputs, metrics, info in rows:
        corruption = json.loads(inputs or "{}").get("corruption") or {}
        met, info = json.loads(metrics or "{}"), json.loads(info or "{}")
        first = info.get("fragmented_attempt")
        if first:
            out.append({"group": "first attempt", "shape": shape, "input": json.dumps(corruption, sort_keys=True),
                        "runs": 1, "faces": first["faces"], "per_face": first["boundary_edges_per_face"],
                        "per_root_face": first["boundary_edges_per_face"] * math.sqrt(first["faces"])})
        faces, b = met.get("faces"), met.get("boundary_edges")
        surface = info.get("surface") or {}
        if "rim_edges" in surface:  # what the test reads (runs since 6 December); else the mesh's boundary
            faces, b = surface["rim_faces"], surface["rim_edges"]
        if faces and b is not None and not {"noise", "outliers", "scan"} & set(corruption):
            clean.setdefault(shape, []).append((b / faces, b / math.sqrt(faces), faces))
    for shape, figures in sorted(clean.items()):
        worst = max(figures, key=lambda x: x[1])
        out.append({"group": "clean (largest per root face)", "shape": shape, "input": "", "runs": len(figures),
                    "faces": worst[2], "per_face": max(f[0] for f in figures), "per_root_face": worst[1]})
    return out


def main(out: str = "reports", quick: bool = False) -> None:
    import torch

    torch.set_num_threads(1)
    fresh = [_fresh(*case) for case in (CASES[1:2] if quick else CASES)]
    stored = _stored(STORE)
    table = markdown_table(fresh, ["shape", "seeds", "noise", "faces", "boundary", "per_face", "per_root_face",
                                   "before", "now"], {"per_face": ".4f", "per_root_face": ".1f"})
    if stored:
        table += ("\n\nThe results store (`runs/paper`; per face: the largest of the group's runs):\n\n"
                  + markdown_table(stored, ["group", "shape", "input", "runs", "faces", "per_face", "per_root_face"],
                                   {"per_face": ".4f", "per_root_face": ".1f"}))
    rows = [{"part": "fresh run", **r} for r in fresh] + [{"part": "store", **r} for r in stored]
    keys = list(dict.fromkeys(k for r in rows for k in r))
    write_report(out, "fragmented_rim", "When is a point-cloud mesh in shreds?", __doc__, table,
                 [{k: r.get(k, "") for k in keys} for r in rows])


if __name__ == "__main__":
    main()
