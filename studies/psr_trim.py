"""Can any density trim bring screened Poisson within 3x of the best method on open and mixed shapes?

Issue 58 asks for screened Poisson's open and mixed class CD p2s within 3x of the best method's. Its row in the
tables (`psr`, `baselines/psr.py`) solves at depth 10 and trims at depth - 3 as PoissonRecon's SurfaceTrimmer
does, capped by the median density and keeping every vertex an input point vouches for (`python -m studies
psr_support`). A trim only removes faces, so this study asks what the best possible removal gives. For each
shape (point cloud, 100K samples, seed 0, the harness's input cache; the dev split, and the test split's open
and mixed shapes: a bound measured there, nothing chosen) the Poisson surface is solved once at `psr`'s
settings, then:

- `untrimmed`: as solved (the `psr [paper]` row's rule, at depth 10);
- `psr`: the row's own trim (`baselines.psr`: depth - 3, median cap, support, islands);
- `trim depth - t`: the same with the cut at depth - t for t = 2 and 1 (a deeper trim: more removed);
- `oracle r`: every face whose centroid lies farther than r from the GT removed (r = 1 and 2 mean
  nearest-neighbour spacings of the input). It reads the GT: no trim rule removes faces much better, so it
  bounds what trimming can reach; it is not a method.

CD p2s x1e-3 (`eval.metrics.compute_metrics`, 100K metric samples per side, GT frame), class means, and the
ratio of each to the best method's class mean on the same split (read from `reports/table2_pointcloud.csv`,
whose rows are means over 3 input seeds; the study's over seed 0).

Regenerate: `python -m studies psr_trim` (about 50 minutes on one core; needs the input cache of `runs/paper`,
which `make reproduce-tables` fills; `--quick`: the bowl only).
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from eval.bench.common import markdown_table, write_report

#: (split, class) -> shapes: the dev split whole (closed as the control a trim must not cut), the test split's
#: open and mixed shapes.
CLASSES = {"dev": ("closed", "open", "mixed"), "test": ("open", "mixed")}
OFFSETS = (2.0, 1.0)
ORACLE = (1.0, 2.0)


def shapes() -> dict:
    from datasets import splits

    return {(split, c): tuple(s for s, k in splits.SPLITS[split].items() if k == c)
            for split, classes in CLASSES.items() for c in classes}
WORK = Path("runs/paper")


def _best(category: str, split: str, table: Path = Path("reports/table2_pointcloud.csv")
          ) -> tuple[str, float] | None:
    """(method, CD p2s) of the best `split` row of `category` in the committed Table 2."""
    if not table.is_file():
        return None
    rows = [r for r in csv.DictReader(table.open()) if r["category"] == category and r.get("split") == split
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


def run_shape(shape: str, category: str, split: str = "dev") -> list[dict]:
    import trimesh

    from baselines.psr import ScreenedPoisson, sampled_vertices, trim_surface
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
    supported = sampled_vertices(verts, points, float(cfg["trim_support_ratio"]), int(cfg["trim_support_neighbours"]),
                                 float(cfg["trim_support_max_spacing"]))
    variants = {"untrimmed": (verts, faces)}
    for t in (float(cfg["trim_depth_offset"]),) + OFFSETS:
        value = min(float(cfg["depth"]) - t, float(np.median(density)) - float(cfg["trim_median_margin"]))
        v, f, _, _ = trim_surface(verts, faces, density, value, int(cfg["trim_smooth"]),
                                  float(cfg["island_area_ratio"]), supported)
        variants["psr" if t == float(cfg["trim_depth_offset"]) else f"trim depth - {t:g}"] = (v, f)
    centroid = verts[faces].mean(1)
    _, distance, _ = trimesh.proximity.closest_point(gt, centroid)
    for r in ORACLE:
        variants[f"oracle {r:g} spacings"] = (verts, faces[distance <= r * spacing])
    rows = []
    for name, (v, f) in variants.items():
        mesh = trimesh.Trimesh(v, f, process=False)
        m = compute_metrics(mesh, gt, n=100_000, seed=0) if len(f) else {"cd_p2s": float("nan")}
        rows.append({"split": split, "class": category, "shape": shape, "variant": name, "faces": int(len(f)),
                     "cd_p2s": m["cd_p2s"]})
    return rows


def summary(rows: list[dict]) -> list[dict]:
    out = []
    for split, category in dict.fromkeys((r["split"], r["class"]) for r in rows):
        best = _best(category, split)
        for name in dict.fromkeys(r["variant"] for r in rows):
            cds = [r["cd_p2s"] for r in rows if (r["split"], r["class"], r["variant"]) == (split, category, name)]
            if not cds:
                continue
            mean = float(np.nanmean(cds)) * 1e3
            out.append({"split": split, "class": category, "variant": name, "n": len(cds), "cd_p2s": mean,
                        "best_method": best[0] if best else "", "best_cd_p2s": best[1] * 1e3 if best else None,
                        "ratio_to_best": mean / (best[1] * 1e3) if best else None})
    return out


def main(out: str = "studies/reports", quick: bool = False) -> None:
    todo = {("dev", "open"): ("bowl",)} if quick else shapes()
    rows = [r for (split, category), names in todo.items() for shape in names
            for r in run_shape(shape, category, split)]
    table = markdown_table(summary(rows), ["split", "class", "variant", "n", "cd_p2s", "best_method", "best_cd_p2s",
                                           "ratio_to_best"],
                           {"cd_p2s": ".3f", "best_cd_p2s": ".4f", "ratio_to_best": ".1f"})
    per_shape = markdown_table([{**r, "cd_p2s": r["cd_p2s"] * 1e3} for r in rows],
                               ["split", "class", "shape", "variant", "faces", "cd_p2s"], {"cd_p2s": ".3f"})
    write_report(out, "psr_trim", "Screened Poisson: how far can trimming go on open and mixed shapes?",
                 __doc__.split("\n\nRegenerate")[0] + "\n\nClass means (CD p2s x1e-3):",
                 table + "\nPer shape:\n\n" + per_shape, rows)
