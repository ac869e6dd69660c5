"""Which ball radii should ball pivoting pivot when the input's density varies?

`baselines/bpa.py` pivots radii {1, 2, 4} x the input's mean nearest-neighbour spacing (Open3D's advice: radii
from the point density, doubling). On a cloud whose density varies (an 8x contrast, a scanner's grazing
angles and distances) the mean spacing is the dense side's, and the balls fall through the sparse side:
its surface is left out. Longer doubling lists are the candidates. (A list carried on until its largest
ball spans a high quantile of the local spacing cannot tell these inputs apart: the 95th percentile of the
nearest-neighbour spacing is 1.95-1.96 mean spacings on every clean dev input and 1.99-2.16 on the non-uniform and
scanned ones, so such a rule gives every input the same list.)

Variants per input, each pivoting the same points (`bpa` as the harness runs it, the input normals used):

- `{1,2,4}`: the list before this study;
- `{1,2,4,8}` (the default since), `{1,2,4,8,16}`: longer lists.

Inputs: the robustness sweep's dev shapes (`eval/sweeps/robustness.yaml`, 100K points, seed 0, the harness's
input cache), two per class: closed torus, genus2; open bowl, wavy_sheet; mixed plant, flag_box; each clean,
with an 8x density contrast (`nonuniform: 8`) and scanned by 6 cameras (normals estimated). CD p2s x1e-3
(`eval.metrics.compute_metrics`, 100K metric samples per side, GT frame, metric seed 0), the radii in mean
spacings, and the pivot's seconds.

Regenerate: `python -m studies bpa_radii` (about 20 minutes on 2 cores; needs the input cache of `runs/paper`,
which `make reproduce-tables` and `dmesh robustness` fill, or prepares what is missing; `--quick`: the
non-uniform torus only).
"""
from __future__ import annotations

import time
import numpy as np

from eval.bench.common import markdown_table, write_report

SHAPES = ("torus", "genus2", "bowl", "wavy_sheet", "plant", "flag_box")
INPUTS = ({}, {"nonuniform": 8.0}, {"scan": 6, "normals": "estimated"})
LISTS = {"{1,2,4}": (1.0, 2.0, 4.0), "{1,2,4,8}": (1.0, 2.0, 4.0, 8.0), "{1,2,4,8,16}": (1.0, 2.0, 4.0, 8.0, 16.0)}


def _label(corruption: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in corruption.items() if k != "normals") or "clean"


def run_case(shape: str, corruption: dict) -> list[dict]:
    import open3d as o3d
    import trimesh

    from baselines.base import mean_spacing
    from eval.inputs import load_gt
    from eval.metrics import compute_metrics
    from studies.surface_variants import cloud

    points, normals, gt_path, _ = cloud(shape, corruption)
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    gt = load_gt(gt_path)
    h = mean_spacing(points)
    rows = []
    for name, radii in LISTS.items():
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.normals = o3d.utility.Vector3dVector(normals)
        t0 = time.perf_counter()
        tm = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
            pcd, o3d.utility.DoubleVector([r * h for r in radii]))
        seconds = time.perf_counter() - t0
        mesh = trimesh.Trimesh(np.asarray(tm.vertices), np.asarray(tm.triangles, dtype=np.int64), process=False)
        m = compute_metrics(mesh, gt, n=100_000, seed=0) if len(mesh.faces) else {}
        rows.append({"shape": shape, "input": _label(corruption), "variant": name,
                     "radii": ",".join(f"{r:g}" for r in radii), "cd_p2s": m.get("cd_p2s", float("nan")) * 1e3,
                     "faces": len(mesh.faces), "seconds": seconds})
    return rows


def main(out: str = "studies/reports", quick: bool = False) -> None:
    cases = [("torus", INPUTS[1])] if quick else [(s, c) for s in SHAPES for c in INPUTS]
    rows = [r for shape, corruption in cases for r in run_case(shape, corruption)]
    table = markdown_table(rows, ["shape", "input", "variant", "radii", "cd_p2s", "faces", "seconds"],
                           {"cd_p2s": ".3f", "seconds": ".1f"})
    write_report(out, "bpa_radii", "Ball pivoting: radii that span the sparse side",
                 __doc__.split("\n\nRegenerate")[0] + "\n\nPer input (CD p2s x1e-3):", table, rows)
