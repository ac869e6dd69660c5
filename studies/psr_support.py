"""Does screened Poisson's density trim need the input's support on non-uniform and scanned input?

PoissonRecon's density is the octree depth the local sampling supports, and SurfaceTrimmer cuts every vertex
below one value. `baselines/psr.py` picks that value on the dev split's clean, uniform clouds (depth - 2, capped
at the median density - 0.7). On a cloud whose density varies (a density contrast, a scanner's grazing angles),
the sparse side of a closed shape falls below the value and is cut. The harness's rule against it
(`baselines.psr.sampled_vertices`): a vertex below the value stays when an input point lies within
`trim_support_ratio` of that point's local spacings, the spacing counting only up to
`trim_support_max_spacing` times the median one (so an outlier vouches for nothing). This study solves the
Poisson surface once per input and cuts it three ways:

- `untrimmed`: as solved;
- `trim`: SurfaceTrimmer's cut alone (`trim_support_ratio` None);
- `trim + support r`: the cut with the support rule at r = 1 (the default) and 2 local spacings, K = 4.

Inputs: the robustness sweep's dev shapes that show the cases (`eval/sweeps/robustness.yaml`, 100K points,
seed 0, the harness's input cache): closed torus and open bowl, clean, with an 8x density contrast
(`nonuniform: 8`), scanned by 6 cameras (normals estimated), and with 5 % outliers; wavy_sheet, plant and
flag_box clean (the other open and mixed dev shapes the trim must still cut). CD p2s x1e-3
(`eval.metrics.compute_metrics`, 100K metric samples per side, GT frame) and the area share cut.

Regenerate: `python -m studies psr_support` (about 15 minutes on 2 cores; needs the input cache of
`runs/paper`, which `make reproduce-tables` and `dmesh robustness` fill, or prepares what is missing;
`--quick`: the non-uniform torus only).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from eval.bench.common import markdown_table, write_report

CASES = (("torus", {}), ("torus", {"nonuniform": 8.0}), ("torus", {"scan": 6, "normals": "estimated"}),
         ("torus", {"outliers": 0.05}),
         ("bowl", {}), ("bowl", {"nonuniform": 8.0}), ("bowl", {"scan": 6, "normals": "estimated"}),
         ("bowl", {"outliers": 0.05}),
         ("wavy_sheet", {}), ("plant", {}), ("flag_box", {}))
RATIOS = (1.0, 2.0)
WORK = Path("runs/paper")


def _label(corruption: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in corruption.items() if k != "normals") or "clean"


def run_case(shape: str, corruption: dict) -> list[dict]:
    import trimesh

    from baselines.psr import ScreenedPoisson, sampled_vertices, trim_surface
    from eval.inputs import load_gt, prepare_gt, prepare_input
    from eval.metrics import compute_metrics
    from eval.shapes import resolve_shape
    from studies.psr_trim import _solve

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK)
    gt = load_gt(gt_path)
    settings = {"radius": 1.0, "n_points": 100_000, **({"corruption": corruption} if corruption else {})}
    with np.load(prepare_input(ref, gt_path, "pointcloud", settings, 0, WORK)) as z:
        points, normals = np.asarray(z["points"], np.float64), np.asarray(z["normals"], np.float64)
    cfg = ScreenedPoisson().resolve_config({})
    verts, faces, density = _solve(points, normals, cfg)
    value = min(float(cfg["depth"]) - float(cfg["trim_depth_offset"]),
                float(np.median(density)) - float(cfg["trim_median_margin"]))
    variants = {"untrimmed": (verts, faces, 0.0)}
    cuts = {"trim": None, **{f"trim + support {r:g}": r for r in RATIOS}}
    for name, ratio in cuts.items():
        supported = None if ratio is None else sampled_vertices(
            verts, points, ratio, int(cfg["trim_support_neighbours"]), float(cfg["trim_support_max_spacing"]))
        v, f, _, info = trim_surface(verts, faces, density, value, int(cfg["trim_smooth"]),
                                     float(cfg["island_area_ratio"]), supported)
        variants[name] = (v, f, info["area_trimmed_fraction"])
    rows = []
    for name, (v, f, cut) in variants.items():
        m = compute_metrics(trimesh.Trimesh(v, f, process=False), gt, n=100_000, seed=0) if len(f) else {}
        rows.append({"shape": shape, "input": _label(corruption), "variant": name, "trim_value": value,
                     "area_cut": cut, "cd_p2s": m.get("cd_p2s", float("nan")) * 1e3,
                     "watertight": bool(m.get("watertight", False))})
    return rows


def main(out: str = "studies/reports", quick: bool = False) -> None:
    cases = CASES[1:2] if quick else CASES
    rows = [r for shape, corruption in cases for r in run_case(shape, corruption)]
    table = markdown_table(rows, ["shape", "input", "variant", "trim_value", "area_cut", "cd_p2s", "watertight"],
                           {"trim_value": ".2f", "area_cut": ".3f", "cd_p2s": ".3f"})
    write_report(out, "psr_support", "Screened Poisson: the density trim with the input's support",
                 __doc__.split("\n\nRegenerate")[0] + "\n\nPer input (CD p2s x1e-3):", table, rows)
