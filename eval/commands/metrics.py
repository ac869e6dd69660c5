"""`dmesh metrics PRED GT`: every metric of a predicted mesh against its ground truth.

Both meshes are mapped by the GT's normalisation (vertex mean 0, max vertex norm 1) before measuring; see
`eval.metrics` for the definitions, frames and units. The GT (never the prediction) is oriented at load
(`datasets.meshes.orient_outward`): an inside-out closed GT file is flipped outward with a warning, and a GT
that cannot be oriented gets `gt_orientable: false` and NaN (null) oriented figures.
"""
from __future__ import annotations

import json
import math

NAME = "metrics"
HELP = "compare a predicted mesh with its ground truth (Chamfer, F-score, normals, orientation, topology)"

#: Keys printed with a x1e-3 column (GT-radius units).
_MILLI = ("cd_l1", "cd_l1_gt_to_pred", "cd_l1_pred_to_gt", "cd_p2s", "cd_p2s_gt_to_pred", "cd_p2s_pred_to_gt")


def add_arguments(p):
    p.add_argument("pred", metavar="PRED", help="predicted mesh (OBJ, PLY, OFF, STL, GLB)")
    p.add_argument("gt", metavar="GT", help="ground-truth mesh")
    p.add_argument("--samples", type=int, default=100_000, help="surface samples per mesh (default: 100000)")
    p.add_argument("--seed", type=int, default=0,
                   help="metric sampling seed (each mesh draws from its own stream of it, never an input's)")
    p.add_argument("--no-self-intersections", action="store_true",
                   help="skip counting self-intersecting faces (the slowest statistic)")
    p.add_argument("--json", action="store_true", help="print one JSON object (non-finite values as null)")


def _jsonable(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def run(args) -> int:
    from datasets.meshes import load_mesh
    from eval.metrics import compute_metrics
    from eval.values import check_points, check_seed

    check_points("--samples", args.samples)
    check_seed("--seed", args.seed)
    pred = load_mesh(args.pred)
    gt = load_mesh(args.gt, orient=True)
    m = compute_metrics(pred, gt, n=args.samples, seed=args.seed,
                        self_intersections=not args.no_self_intersections)
    if args.json:
        out = {"pred": str(args.pred), "gt": str(args.gt), "frame": "GT vertex mean 0, max vertex norm 1",
               **{k: _jsonable(v) for k, v in m.items()}}
        print(json.dumps(out, indent=2))
        return 0
    width = max(len(k) for k in m)
    print(f"{'metric':<{width}}  {'value':>12}  {'x1e-3':>10}")
    for k, v in m.items():
        milli = f"{v * 1e3:>10.4f}" if k in _MILLI and math.isfinite(v) else ""
        print(f"{k:<{width}}  {_fmt(v):>12}  {milli}")
    print(f"frame: GT vertex mean 0, max vertex norm 1; {args.samples} samples per mesh; "
          "cd_l2_ndc, f_score (at 0.003) and normal_consistency in the NDC frame (GT bbox diagonal 1)")
    if not m["gt_orientable"]:
        print(f"the GT is {m['gt_orientation'].replace('_', '-')}: only the unsigned normal consistency applies")
    return 0
