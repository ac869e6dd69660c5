"""The point-cloud outlier filter: what it drops, with and without its surface rescue.

`dmesh.recon.init.statistical_inliers` first flags points whose mean distance to their 16 nearest neighbours
is more than 2 standard deviations above the mean (statistical outlier removal, as PCL's and Open3D's). Alone,
that test also flags the sparsest few percent of any clean sample, and whole stretches of a scan where the rays
graze the surface. The rescue keeps a flagged point whose neighbours form a piece of surface that it lies on.
Outliers that fall within a few spacings of the surface pass the distance test; the off-surface test then drops a
point the distance test kept when its neighbours form a piece of surface and it lies more than
`dmesh.recon.init.OFF_SURFACE` (1) of their spacings off it. On the robustness sweep's inputs (the same cached files, 100K points, unit radius), this bench counts the true
outliers (`is_outlier`) and the surface samples each rule drops. Then it runs the `fast` preset on a few of
them without a filter and with each rule, and measures CD p2s (x1e-3,
`eval.metrics.chamfer_l1_p2s`, 100K samples).

Regenerate: `python -m studies outlier_filter` (about 35 minutes: the counts take seconds, each of the 24
reconstructions about a minute; `--quick`: the torus only, no reconstruction).
"""
from __future__ import annotations

import numpy as np

from eval.bench.common import markdown_table, write_report

WORK = "runs/paper"  # the input cache of `dmesh reproduce-tables` and `dmesh robustness`
SHAPES = ("torus", "genus2", "bowl", "wavy_sheet", "plant", "flag_box")  # eval/sweeps/robustness.yaml's
VARIANTS = ({}, {"outliers": 0.01}, {"outliers": 0.05}, {"outliers": 0.1}, {"nonuniform": 8}, {"scan": 6},
            {"scan": 6, "noise": 0.0025, "outliers": 0.01})
RECONSTRUCT = (("torus", {"outliers": 0.05}), ("flag_box", {"outliers": 0.05}), ("torus", {"scan": 6}),
               ("flag_box", {"scan": 6}), ("bowl", {"outliers": 0.1}), ("wavy_sheet", {"outliers": 0.1}))
#: (name, keep_surface, off_surface) of `statistical_inliers`: the distance test alone, with the rescue, and with
#: the off-surface test too (the presets').
RULES = (("distance", False, False), ("rescue", True, False), ("off_surface", True, True))
N_POINTS = 100_000


def _cloud(shape: str, variant: dict):
    """(points, normals, is_outlier, gt path) of one robustness input, made and cached as the sweep does."""
    from datasets.corrupt import canonical_variant
    from eval.runner import input_path, prepare_gt, prepare_input
    from eval.sweep import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK, 1.0)
    corruption = canonical_variant(variant, n_points=N_POINTS, views=64, resolution=256)
    settings = {"n_points": N_POINTS, "radius": 1.0, "corruption": corruption}
    prepare_input(ref, gt_path, "pointcloud", settings, 0, WORK)
    with np.load(input_path(WORK, ref, "pointcloud", settings, 0)) as z:
        outlier = z["is_outlier"] if "is_outlier" in z else np.zeros(len(z["points"]), bool)
        return z["points"], z["normals"], outlier, gt_path


def _name(variant: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in variant.items()) or "clean"


def counts(shapes) -> list[dict]:
    from dmesh.recon.init import statistical_inliers

    rows = []
    for shape in shapes:
        for variant in VARIANTS:
            pts, _, outlier, _ = _cloud(shape, variant)
            row = {"shape": shape, "input": _name(variant), "outliers": int(outlier.sum())}
            for rule, rescue, off in RULES:
                keep = statistical_inliers(pts, 2.0, keep_surface=rescue, off_surface=off)
                row[f"{rule}_outliers_dropped"] = int((~keep & outlier).sum())
                row[f"{rule}_surface_dropped"] = int((~keep & ~outlier).sum())
            rows.append(row)
            print(f"  {shape} {row['input']}: {row}", flush=True)
    return rows


def reconstructions() -> list[dict]:
    import trimesh

    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.init import statistical_inliers
    from dmesh.recon.pointcloud import reconstruct
    from eval.metrics import chamfer_l1_p2s

    rows = []
    for shape, variant in RECONSTRUCT:
        pts, nrm, _, gt_path = _cloud(shape, variant)
        gt = trimesh.load(gt_path, process=False, force="mesh")
        row = {"shape": shape, "input": _name(variant)}
        for rule, rescue, off in (("none", None, None), *RULES):
            # The preset's filter step, done here so each rule can run: the filtered cloud then goes to `fast`
            # with its own filter off (what `clean_input` would pass on).
            keep = (np.ones(len(pts), bool) if rescue is None
                    else statistical_inliers(pts, 2.0, keep_surface=rescue, off_surface=off))
            result = reconstruct(pts[keep], nrm[keep], PointCloudConfig.fast(outlier_std=0.0))
            row[f"cd_p2s_{rule}"] = 1e3 * chamfer_l1_p2s(result.mesh, gt)
            print(f"  {shape} {row['input']} filter {rule}: {row[f'cd_p2s_{rule}']:.3f}", flush=True)
        rows.append(row)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    rows = counts(SHAPES[:1] if quick else SHAPES)
    cols = ["shape", "input", "outliers"] + [f"{rule}_{what}_dropped" for rule, _, _ in RULES
                                              for what in ("outliers", "surface")]
    table = markdown_table(rows, cols)
    if not quick:
        recon = reconstructions()
        cd = [f"cd_p2s_{rule}" for rule in ("none", *(r[0] for r in RULES))]
        table += ("\nThe `fast` preset on some of them, CD p2s x1e-3, without a filter, with the distance test alone, "
                  "with the rescue, and with the off-surface test too (the preset's):\n\n"
                  + markdown_table(recon, ["shape", "input", *cd], {c: ".3f" for c in cd}))
        rows = rows + recon
    keys = list(dict.fromkeys(k for r in rows for k in r))  # one CSV for both tables
    rows = [{k: r.get(k, "") for k in keys} for r in rows]
    intro = __doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip()
    write_report(out, "outlier_filter", "The point-cloud outlier filter", intro, table, rows)


if __name__ == "__main__":
    main()
