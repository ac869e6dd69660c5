"""The multi-view `fast` preset's last stage, `depth_fit` (`dmesh.recon.depth_fit`), on the Table 2 meshes made
without it: CD p2s before and after, against TSDF fusion's.

The store of `make reproduce-tables` (`runs/paper`, or `$DMESH_WORK`) keeps every run's mesh and input. For each
shape, the latest done `dmesh_mv` run of the `fast` preset (config label empty) that did not fit its vertices
yet (no "depth_fit" in its info) is taken with its capture (64 views at 256 pixels): its mesh is fitted to the
captured depth maps as the preset's last stage does, once to the clean maps and once to maps with Gaussian
noise of 0.5 % of the object radius on every covered pixel (`studies.refine.noisy`), and its CD p2s is
measured before and after (100K samples per side, as Table 2). The fitted rows of Table 2 itself come from the
sweep (`make reproduce-tables`); this table shows what the stage alone does, on the same meshes.

Regenerate: `python -m studies depth_fit` (`--quick`: torus, bowl and plant only).
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from eval.bench.common import markdown_table, write_report

QUICK_SHAPES = ("torus", "bowl", "plant")
#: Depth noise of the noisy maps, as a fraction of the object radius (as studies.refine).
NOISE = 0.005


def _latest(rows, **match) -> dict | None:
    best = None
    for r in rows:
        if all(r[k] == v for k, v in match.items()) and (best is None or r["finished_at"] > best["finished_at"]):
            best = r
    return best


def fit_row(row: dict, work: Path, db: Path, tsdf: dict | None, noise: float) -> dict:
    """One stored run's mesh fitted to its capture's depth maps (with `noise`); CD p2s before and after."""
    import trimesh

    from datasets.capture import MultiView
    from dmesh.recon.depth_fit import DepthFitConfig, fit_to_depth
    from dmesh.recon.views import check_views, normalisation
    from studies.refine import noisy
    from eval.metrics import chamfer_l1_p2s
    from eval.runner import input_path, load_gt, resolve_mesh_path, shape_dir

    settings = row["inputs_json"]
    shape = SimpleNamespace(id=row["shape"], gt_hash=row["gt_hash"])
    views = MultiView.load(input_path(work, shape, "multiview", settings, int(row["seed"])))
    gt = load_gt(shape_dir(work, shape, settings["radius"]) / "gt.ply")
    mesh = trimesh.load(resolve_mesh_path(row, db), process=False)
    if noise > 0:
        views = noisy(views, noise * settings["radius"], seed=int(row["seed"]))
    vw = check_views(views)
    center, scale, w2c, _ = normalisation(vw)
    t0 = time.perf_counter()
    v, info = fit_to_depth((np.asarray(mesh.vertices) - center) * scale, mesh.faces, w2c, vw.fov_y_degrees,
                           vw.depth.astype(np.float64) * scale, vw.mask, DepthFitConfig(seed=int(row["seed"])))
    seconds = time.perf_counter() - t0
    fitted = trimesh.Trimesh(v / scale + center, mesh.faces, process=False)
    n = int(settings.get("metric_samples", 100_000))
    before = row["metrics_json"]["cd_p2s"]
    after = chamfer_l1_p2s(fitted, gt, n=n)
    tsdf_cd = tsdf["metrics_json"]["cd_p2s"] if tsdf else None
    return {"shape": row["shape"], "class": row["category"], "depth_noise": noise, "faces": len(mesh.faces),
            "cd_p2s_before": before, "cd_p2s_after": after, "after_over_before": after / before,
            "tsdf_cd_p2s": tsdf_cd, "after_over_tsdf": after / tsdf_cd if tsdf_cd else None,
            "measured_samples": info["fit_samples"], "median_offset": info["median_offset"], "fit_s": seconds}


def main(out: str = "reports", quick: bool = False) -> None:
    from eval.store import Store

    work = Path(os.environ.get("DMESH_WORK", "runs/paper"))
    db = work / "results.sqlite"
    if not db.is_file():
        raise SystemExit(f"studies depth_fit: no results store at {db}: run `make reproduce-tables` first "
                         f"(or set DMESH_WORK)")
    with Store(db) as store:
        rows = [dict(r) for r in store.rows()]
    done = [r for r in rows if r["status"] == "done" and r["input_kind"] == "multiview"]
    fast = [r for r in done if r["method"] == "dmesh_mv" and r["config_label"] == ""
            and "depth_fit" not in (r["info_json"] or {}) and r["inputs_json"].get("views") == 64]
    shapes = sorted({r["shape"] for r in fast} & set(QUICK_SHAPES)) if quick else sorted({r["shape"] for r in fast})
    if not shapes:
        raise SystemExit(f"studies depth_fit: the store {db} holds no multi-view `fast` run without the fit")
    table = []
    for shape in shapes:
        row = _latest(fast, shape=shape)
        tsdf = _latest([r for r in done if r["method"] == "tsdf"], shape=shape, inputs_json=row["inputs_json"])
        for noise in (0.0, NOISE):
            table.append(fit_row(row, work, db, tsdf, noise))
            print(f"{shape} noise {noise}: CD p2s {table[-1]['cd_p2s_before'] * 1e3:.3f} -> "
                  f"{table[-1]['cd_p2s_after'] * 1e3:.3f} (x1e-3)", flush=True)
    order = {"closed": 0, "open": 1, "mixed": 2}
    table.sort(key=lambda r: (r["depth_noise"], order.get(r["class"], 3), r["shape"]))
    shown = [{**r, **{k: (None if r[k] is None else r[k] * 1e3) for k in ("cd_p2s_before", "cd_p2s_after",
                                                                        "tsdf_cd_p2s", "median_offset")}}
             for r in table]
    cols = ["shape", "class", "depth_noise", "faces", "cd_p2s_before", "cd_p2s_after", "after_over_before",
            "tsdf_cd_p2s", "after_over_tsdf", "measured_samples", "median_offset", "fit_s"]
    intro = (__doc__.split("\n\n")[1] + "\n\nCD p2s and the median vertex offset in the table are x1e-3 (the CSV "
             "holds raw distances); `measured_samples` is the share of face samples some view measured; "
             "`fit_s` the fit's wall seconds.")
    write_report(out, "depth_fit", "The depth fit of the multi-view fast preset", intro,
                 markdown_table(shown, cols, {"cd_p2s_before": ".3f", "cd_p2s_after": ".3f", "after_over_before": ".2f",
                                               "tsdf_cd_p2s": ".3f", "after_over_tsdf": ".2f",
                                               "measured_samples": ".3f", "median_offset": ".2f", "fit_s": ".1f"}),
                 table)
