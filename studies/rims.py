"""Do the reconstructions keep the input's boundary? Boundary length of each stored mesh against the GT's.

Issue 59 asks that DMesh `fast` keep a boundary loop of the input (the cut end of a tube, the rim of a sheet) and
close only holes the input shows surface across. Its first figure was a boundary *edge count* within 25 % of the
GT's, but a count depends on the resolution: the test split's GTs are meshed finer than the input spacing (the
vessel's median edge is a third of a 100K-point reconstruction's), so a rim reproduced exactly has about a third
of the GT's boundary edges, and a shredded one many more. The length of the boundary does not depend on the
resolution: a rim kept is about the GT's length (ratio 1), a tube end capped removes its loop (below 1), a surface
in pieces or with holes adds loops (above 1).

Protocol: the runs of Table 2's point-cloud sweeps (`eval/sweeps/paper.yaml`, dev split, and `test.yaml`, test
split, 100K samples, 3 input seeds on test) as stored in the results store of `runs/paper` at the current code
(runs adopted from an earlier code version whose executed code is unchanged count as current), on the shapes
whose GT has a boundary (open and mixed classes). Per run: boundary edges and boundary length of the stored mesh
with its vertices merged by position (`eval.bench.surface_ablation._boundary`, the surface ablation's measure),
over the GT's (same frame: the harness's normalised GT frame). `rim_vs_gt` is that ratio; per shape the mean over
seeds, per class the mean over runs. A run not stored at the current code is left out (`n` says how many
counted).

Regenerate: `python -m studies rims` (a few minutes; needs the results store and meshes of `runs/paper`, which
`make reproduce-tables` fills; `--quick`: the test split's vessel only).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from eval.bench.common import markdown_table, write_report

SWEEPS = {"dev": "eval/sweeps/paper.yaml", "test": "eval/sweeps/test.yaml"}
WORK = Path("runs/paper")
METHODS = ("dmesh", "bpa", "psr", "alpha_wrap", "sdf_mc", "udf_mc", "voromesh")


def _runs(split: str, shapes: tuple[str, ...] | None) -> list:
    """The point-cloud runs of `split`'s sweep, each under its current key (adopted where its code is unchanged)."""
    from eval.inputs import resolve_and_prepare_shapes
    from eval.store import Store
    from eval.stored import adopt_current
    from eval.sweep import Sweep, expand

    sweep = Sweep.from_yaml(SWEEPS[split])
    refs, _ = resolve_and_prepare_shapes(sweep, WORK)  # a mesh file's class comes from its GT
    runs = [r for r in expand(sweep, refs) if r.input_kind == "pointcloud" and r.method in METHODS
            and r.shape.category in ("open", "mixed") and (shapes is None or r.shape.id in shapes)]
    with Store(WORK / "results.sqlite", readonly=True) as store:
        return [(r, store.get(r.key)) for r in adopt_current(runs, store)]


def rows_of(split: str, shapes: tuple[str, ...] | None = None) -> list[dict]:
    """One row per stored run of `split` on a shape with a boundary: its and its GT's boundary edges and length."""
    import trimesh

    from eval.bench.surface_ablation import _boundary
    from eval.execute import resolve_mesh_path
    from eval.inputs import load_gt, prepare_gt

    gts: dict[str, tuple[int, float]] = {}
    rows = []
    for spec, row in _runs(split, shapes):
        mesh_path = resolve_mesh_path(row, WORK / "results.sqlite") if row and row["status"] == "done" else None
        if mesh_path is None or not mesh_path.is_file():
            continue
        if spec.shape.id not in gts:
            gt = load_gt(prepare_gt(spec.shape, WORK)[1])
            gts[spec.shape.id] = _boundary(np.asarray(gt.vertices, np.float64), np.asarray(gt.faces, np.int64))
        gt_edges, gt_length = gts[spec.shape.id]
        mesh = trimesh.load(mesh_path, process=False, force="mesh")
        edges, length = _boundary(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64))
        label = spec.method + (f" [{spec.config_label}]" if spec.config_label else "")
        rows.append({"split": split, "class": spec.shape.category, "shape": spec.shape.id, "method": label,
                     "seed": spec.seed, "boundary_edges": edges, "gt_boundary_edges": gt_edges,
                     "boundary_length": round(length, 6), "gt_boundary_length": round(gt_length, 6),
                     "rim_vs_gt": length / gt_length if gt_length > 0 else float("nan")})
    return rows


def _means(rows: list[dict], keys: tuple[str, ...]) -> list[dict]:
    """Mean of boundary edges and `rim_vs_gt` over the rows sharing `keys`, in first-seen order."""
    out = []
    for group in dict.fromkeys(tuple(r[k] for k in keys) for r in rows):
        sel = [r for r in rows if tuple(r[k] for k in keys) == group]
        ratio = np.array([r["rim_vs_gt"] for r in sel], float)
        out.append({**dict(zip(keys, group)), "n": len(sel),
                    "boundary_edges": float(np.mean([r["boundary_edges"] for r in sel])),
                    "gt_boundary_edges": float(np.mean([r["gt_boundary_edges"] for r in sel])),
                    "rim_vs_gt": float(np.nanmean(ratio)), "rim_vs_gt_max": float(np.nanmax(ratio))})
    return out


def main(out: str = "studies/reports", quick: bool = False) -> None:
    rows = rows_of("test", ("vessel",)) if quick else rows_of("dev") + rows_of("test")
    columns = ["split", "class", "method", "n", "boundary_edges", "gt_boundary_edges", "rim_vs_gt", "rim_vs_gt_max"]
    formats = {"boundary_edges": ".0f", "gt_boundary_edges": ".0f", "rim_vs_gt": ".2f", "rim_vs_gt_max": ".2f"}
    by_class = markdown_table(_means(rows, ("split", "class", "method")), columns, formats)
    by_shape = markdown_table(_means(rows, ("split", "class", "shape", "method")),
                              columns[:2] + ["shape"] + columns[2:], formats)
    write_report(out, "rims", "Boundary length against the GT's: which methods keep the input's rims",
                 __doc__.split("\n\nRegenerate")[0] + "\n\nClass means:", by_class + "\nPer shape (mean over seeds):\n\n"
                 + by_shape, rows)
