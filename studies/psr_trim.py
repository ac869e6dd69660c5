"""Can any density trim bring screened Poisson within 3x of the best method on open and mixed shapes?

Issue 58 asks for screened Poisson's open and mixed class CD p2s within 3x of the best method's. With its
best-practice settings (depth 10, trimmed at depth - 3 as PoissonRecon's SurfaceTrimmer does, `baselines/psr.py`)
it is 5.9x / 6.3x on the dev split (`reports/table2_pointcloud.md`). A trim only removes faces, so this study
asks what the best possible removal gives, and whether a trim level chosen here cuts closed shapes (the issue
asks for the closed class no worse than depth 8 untrimmed). For each dev shape (point cloud, 100K samples, seed
0, the harness's input cache) the Poisson surface is solved once at `psr`'s settings, then:

- `untrimmed`: as solved (the `paper` row's rule, at depth 10);
- `trim depth - t`: SurfaceTrimmer's cut at depth - t for t = 3 (the default), 2.5, 2, 1.5, 1, with the
  median cap and island rule of `psr` (`baselines.psr.trim_surface`);
- `oracle r`: every face whose centroid lies farther than r from the GT removed (r = 1 and 2 mean
  nearest-neighbour spacings of the input). It reads the GT, so no rule can do better by removing faces: a
  lower bound of what trimming can reach, not a method.

CD p2s x1e-3 (`eval.metrics.compute_metrics`, 100K metric samples per side, GT frame), class means, and the
ratio of each to the best method's class mean on the dev split (read from `reports/table2_pointcloud.csv`).

Regenerate: `python -m studies psr_trim` (about 10 minutes on 2 cores; needs the input cache of `runs/paper`,
which `make reproduce-tables` fills; `--quick`: the bowl only).
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from eval.bench.common import markdown_table, write_report

SHAPES = {"closed": ("torus", "genus2", "trefoil", "closed/spot.obj"),
          "open": ("bowl", "wavy_sheet", "mobius", "open/face.off"),
          "mixed": ("plant", "mushroom", "flag_box", "mixed/suzanne.obj")}
OFFSETS = (3.0, 2.5, 2.0, 1.5, 1.0)
ORACLE = (1.0, 2.0)
WORK = Path("runs/paper")


def _best(category: str, table: Path = Path("reports/table2_pointcloud.csv")) -> tuple[str, float] | None:
    """(method, CD p2s) of the best dev row of `category` in the committed Table 2."""
    if not table.is_file():
        return None
    rows = [r for r in csv.DictReader(table.open()) if r["category"] == category and r.get("split") == "dev"
            and r.get("cd_p2s")]
    if not rows:
        return None
    best = min(rows, key=lambda r: float(r["cd_p2s"]))
    return best["method"], float(best["cd_p2s"])


def _solve(points: np.ndarray, normals: np.ndarray, cfg: dict):
    """(vertices, faces, density) of the screened Poisson solve at `cfg` (`ScreenedPoisson`'s settings)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals))
    ms.generate_surface_reconstruction_screened_poisson(
        depth=int(cfg["depth"]), fulldepth=int(cfg["full_depth"]), scale=float(cfg["scale"]),
        samplespernode=float(cfg["samples_per_node"]), pointweight=float(cfg["point_weight"]),
        iters=int(cfg["iters"]), preclean=False, threads=1)
    out = ms.current_mesh()
    return (np.asarray(out.vertex_matrix(), np.float64), np.asarray(out.face_matrix(), np.int64),
            np.asarray(out.vertex_scalar_array(), np.float64))


def run_shape(shape: str, category: str) -> list[dict]:
    import trimesh

    from baselines.psr import ScreenedPoisson, trim_surface
    from eval.inputs import load_gt, prepare_gt, prepare_input
    from eval.metrics import compute_metrics
    from eval.shapes import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK)
    gt = load_gt(gt_path)
    with np.load(prepare_input(ref, gt_path, "pointcloud", {"radius": 1.0, "n_points": 100_000}, 0, WORK)) as z:
        points, normals = np.asarray(z["points"], np.float64), np.asarray(z["normals"], np.float64)
    cfg = ScreenedPoisson().resolve_config({})
    verts, faces, density = _solve(points, normals, cfg)
    from scipy.spatial import cKDTree

    spacing = float(cKDTree(points).query(points, k=2)[0][:, 1].mean())
    variants = {"untrimmed": (verts, faces)}
    for t in OFFSETS:
        value = min(float(cfg["depth"]) - t, float(np.median(density)) - float(cfg["trim_median_margin"]))
        v, f, _, _ = trim_surface(verts, faces, density, value, int(cfg["trim_smooth"]),
                                  float(cfg["island_area_ratio"]))
        variants[f"trim depth - {t:g}"] = (v, f)
    centroid = verts[faces].mean(1)
    _, distance, _ = trimesh.proximity.closest_point(gt, centroid)
    for r in ORACLE:
        variants[f"oracle {r:g} spacings"] = (verts, faces[distance <= r * spacing])
    rows = []
    for name, (v, f) in variants.items():
        mesh = trimesh.Trimesh(v, f, process=False)
        m = compute_metrics(mesh, gt, n=100_000, seed=0) if len(f) else {"cd_p2s": float("nan")}
        rows.append({"class": category, "shape": shape, "variant": name, "faces": int(len(f)),
                     "cd_p2s": m["cd_p2s"]})
    return rows


def summary(rows: list[dict]) -> list[dict]:
    out = []
    for category in SHAPES:
        best = _best(category)
        for name in dict.fromkeys(r["variant"] for r in rows):
            cds = [r["cd_p2s"] for r in rows if r["class"] == category and r["variant"] == name]
            if not cds:
                continue
            mean = float(np.nanmean(cds)) * 1e3
            out.append({"class": category, "variant": name, "n": len(cds), "cd_p2s": mean,
                        "best_method": best[0] if best else "", "best_cd_p2s": best[1] * 1e3 if best else None,
                        "ratio_to_best": mean / (best[1] * 1e3) if best else None})
    return out


def main(out: str = "studies/reports", quick: bool = False) -> None:
    shapes = {"open": ("bowl",)} if quick else SHAPES
    rows = [r for category, names in shapes.items() for shape in names for r in run_shape(shape, category)]
    table = markdown_table(summary(rows), ["class", "variant", "n", "cd_p2s", "best_method", "best_cd_p2s",
                                           "ratio_to_best"],
                           {"cd_p2s": ".3f", "best_cd_p2s": ".4f", "ratio_to_best": ".1f"})
    per_shape = markdown_table([{**r, "cd_p2s": r["cd_p2s"] * 1e3} for r in rows],
                               ["class", "shape", "variant", "faces", "cd_p2s"], {"cd_p2s": ".3f"})
    write_report(out, "psr_trim", "Screened Poisson: how far can trimming go on open and mixed shapes?",
                 __doc__.split("\n\nRegenerate")[0] + "\n\nClass means (CD p2s x1e-3):",
                 table + "\nPer shape:\n\n" + per_shape, rows)
