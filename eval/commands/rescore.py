"""`dmesh rescore`: score the stored meshes of finished runs again with the current metric code.

A run's key hashes its method's code and its inputs, not the metrics (`eval.sweep.METRIC_MODULES`), so a new or
corrected metric reruns no method. Each run's metrics carry the `metrics_version` that computed them; this
command recomputes, for every done run whose mesh and GT are on disk, the metrics of an older version (or of
every run, with --all) and stores them in place. Runs without their mesh (loaded from a store export on
another machine) keep their metrics and are counted (`dmesh bench --rerun stale-metrics` runs them again); a
run that fails to score is reported and skipped.
"""
from __future__ import annotations

import logging
from pathlib import Path

NAME = "rescore"
HELP = "recompute the metrics of stored runs from their meshes with the current metric code"

log = logging.getLogger(__name__)


def add_arguments(p) -> None:
    p.add_argument("--work", default="runs/paper", help="work folder of the store (default: runs/paper)")
    p.add_argument("--db", help="SQLite results store (default: WORK/results.sqlite)")
    p.add_argument("--methods", nargs="+", help="only these methods (default: all)")
    p.add_argument("--shapes", nargs="+", help="only these shapes (default: all)")
    p.add_argument("--input-kind", choices=("pointcloud", "multiview", "mesh"), help="only this input kind")
    p.add_argument("--all", action="store_true", help="also runs already scored by the current metric code")
    p.add_argument("--plan", action="store_true", help="count the runs to score and stop")


def _gt_path(work: Path, row: dict) -> Path:
    from eval.inputs import shape_dir
    from eval.shapes import ShapeRef

    settings = row.get("inputs_json") or {}
    ref = ShapeRef(id=row["shape"], kind="file", source="", gt_hash=row.get("gt_hash") or "")
    return shape_dir(work, ref, float(settings.get("radius", 1.0))) / "gt.ply"


def run(args) -> int:
    import trimesh

    from eval.progress import progress
    from eval.execute import resolve_mesh_path, score, with_gt_figures
    from eval.inputs import load_gt
    from eval.store import Store, check_store
    from eval.code_hash import metrics_current, metrics_version

    work = Path(args.work)
    db = Path(args.db) if args.db else work / "results.sqlite"
    if not db.is_file():
        raise FileNotFoundError(f"no results store at {db}: give --work or --db")
    check_store(db, write=not args.plan)  # before any run is scored: a store it could not write back to
    todo, no_mesh, scored = [], 0, 0
    with Store(db, readonly=args.plan) as store:
        for row in store.rows(status="done"):
            if ((args.methods and row["method"] not in args.methods)
                    or (args.shapes and row["shape"] not in args.shapes)
                    or (args.input_kind and row["input_kind"] != args.input_kind)):
                continue
            if not args.all and metrics_current((row.get("metrics_json") or {}).get("metrics_version")):
                scored += 1
                continue
            mesh = resolve_mesh_path(row, db)
            gt = _gt_path(work, row)
            if mesh is None or not mesh.is_file() or not gt.is_file():
                no_mesh += 1
                continue
            todo.append((row, mesh, gt))
        print(f"metrics version {metrics_version()}: {len(todo)} runs to score, {scored} already scored by it, "
              f"{no_mesh} without their mesh or GT on disk (kept as they are"
              + ("; `dmesh bench SWEEP --rerun stale-metrics` runs them again)" if no_mesh else ")"))
        if args.plan:
            return 0
        failed = 0
        for row, mesh_file, gt_file in progress(todo, desc="rescore", unit="run"):
            try:
                mesh = trimesh.load(mesh_file, process=False, force="mesh")
                metrics = score(mesh, with_gt_figures(load_gt(gt_file), gt_file), row.get("inputs_json") or {}, row.get("info_json"))
            except Exception as exc:  # noqa: BLE001 - one bad mesh must not stop the others
                failed += 1
                log.warning("run %s (%s on %s): not rescored: %s", row["key"][:12], row["method"], row["shape"],
                            " ".join(str(exc).split()))
                continue
            store.set_metrics(row["key"], metrics)
    print(f"rescored {len(todo) - failed} runs" + (f"; {failed} failed (see the warnings)" if failed else ""))
    return 1 if failed else 0
