"""`dmesh bench`: run a sweep (methods x shapes x input kinds x configs x seeds) into the results store.

A sweep comes from a YAML file (see `eval/sweeps/*.yaml`), from flags, or both (flags override the file).
Finished runs are never recomputed; an interrupted sweep resumes where it stopped.
"""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "bench"
HELP = "run a benchmark sweep (resumable; results in SQLite) and print per-class means"


def add_sweep_arguments(p: argparse.ArgumentParser, work_default: str) -> None:
    """Flags shared by `bench` and `reproduce-tables`."""
    p.add_argument("--methods", nargs="+", metavar="METHOD", help="registered method names")
    p.add_argument("--shapes", nargs="+", metavar="SHAPE",
                   help="synthetic shape names (name or name@seed) or mesh files (relative to --data-root)")
    p.add_argument("--inputs", nargs="+", choices=("pointcloud", "multiview", "mesh"), help="input kinds")
    p.add_argument("--seeds", nargs="+", type=int, metavar="SEED", help="run seeds")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                   help="override a sweep field (n_points=20000) or a method's config (psr.depth=7); repeatable")
    p.add_argument("--data-root", help="folder of real meshes (default: $DMESH_DATA, else ../shared/meshes)")
    p.add_argument("--work", default=work_default,
                   help=f"work folder: input cache, meshes, store (default: {work_default})")
    p.add_argument("--db", help="SQLite results store (default: WORK/results.sqlite)")
    p.add_argument("--jobs", type=int, default=1,
                   help="concurrent runs: worker processes, or Ray tasks in flight (default: 1)")
    p.add_argument("--threads", type=int, metavar="N",
                   help="local executor: threads per run (default: the machine's cores / --jobs)")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local process pool (default) or Ray tasks (needs pip install -e .[ray])")
    p.add_argument("--ray-address", metavar="HOST:PORT",
                   help="with --executor ray: join the running Ray cluster whose head is there (or auto: the "
                        "one started on this machine); default: $RAY_ADDRESS, else a local Ray of --jobs CPUs")
    p.add_argument("--timeout", type=float, help="per-run wall-clock limit in seconds (default: the sweep's)")
    p.add_argument("--retry-failed", action="store_true", help="rerun runs stored as failed")
    p.add_argument("--rerun", choices=("all", "stale-metrics"),
                   help="also rerun stored runs of the selection: all of them, or the done ones scored by an "
                        "earlier metric code (for runs without their mesh on disk, which `dmesh rescore` "
                        "cannot reach); a rerun replaces the stored result")
    p.add_argument("--plan", action="store_true",
                   help="run nothing: print the runs stored and to run, and how long the stored runs of the same "
                        "configurations (any code version) took")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sweep", nargs="?", help="sweep YAML file (optional when --methods and --shapes are given)")
    add_sweep_arguments(p, "runs/bench")
    p.add_argument("--report", metavar="DIR", help="also write reports (tables, figures, index.html) into DIR")
    p.add_argument("--preprocess", nargs="+", metavar="SPEC",
                   help="pre-processing of every point-cloud method's input, one row set per spec: none, or "
                        "stages joined by '+' (outliers[=STD], smooth[=K], autosmooth[=K]), e.g. --preprocess none "
                        "outliers+smooth (default: the sweep's, else none; docs/preprocessing.md)")


def build_sweep(args, path=None, strict: bool = True):
    """The `Sweep` of the YAML file `path` (default: `args.sweep`), or of the flags alone, with the flags
    applied on top (`strict`: see `Sweep.with_overrides`). ValueError (one line) for anything invalid."""
    from eval.sweep import Sweep

    path = path or getattr(args, "sweep", None)
    if path:
        sweep = Sweep.from_yaml(path)
    else:
        if not args.methods or not args.shapes:
            raise ValueError("give a sweep YAML file, or both --methods and --shapes")
        sweep = Sweep(methods=tuple(args.methods), shapes=tuple(args.shapes))
    d = sweep.to_dict()
    for flag, key in (("methods", "methods"), ("shapes", "shapes"), ("inputs", "inputs"), ("seeds", "seeds")):
        v = getattr(args, flag, None)
        if v:
            d[key] = list(v)
    if getattr(args, "data_root", None):
        d["data_root"] = args.data_root
    if getattr(args, "timeout", None) is not None:
        d["timeout_s"] = float(args.timeout)
    if getattr(args, "preprocess", None):
        d["preprocess"] = list(args.preprocess)
    return Sweep.from_dict(d).with_overrides(args.sets or [], strict=strict)


def check_work(work, db, *, write: bool = True) -> None:
    """Checks, before anything is written, that the work folder `work` can be used and that the results store
    `db` (WORK/results.sqlite unless --db) is absent or a store that can be read whole and, with `write` (a
    command that may add or change runs), written (`eval.store.check_store`); ValueError naming the problem."""
    from eval.cli import check_output_dir, check_output_file
    from eval.store import check_store

    check_output_dir(work, "--work")
    check_store(check_output_file(db, "--db"), write=write)


def summary_text(db, kinds=None, keys=None) -> str:
    """Per (method, class) means of the runs `keys` (None: the latest of each) as a plain-text table."""
    from eval.reports import select_runs, tables
    from eval.store import Store

    with Store(db) as store:
        df = select_runs(store.dataframe(), keys)
    lines = []
    for kind in kinds or ("pointcloud", "multiview", "mesh"):
        rows = tables.table2(df, kind)
        if not rows:
            continue
        w = max(12, max(len(r["method"]) for r in rows))
        lines.append(f"{kind} input (normalised frame, max |v| = 1; CD x1e-3, means over n done runs)")
        lines.append(f"{'method':<{w}}  {'class':<7} {'split':<5} {'n':>3} {'fail':>4} {'CD p2s':>9} {'CD L1':>9} "
                     f"{'time s':>9} {'paper CD':>9}")
        for r in rows:
            def c(v, s=1.0):
                return tables.fmt(v * s) if v is not None else "-"
            lines.append(f"{r['method']:<{w}}  {r['category']:<7} {r['split']:<5} {r['n']:>3} {r['failed']:>4} "
                         f"{c(r['cd_p2s'], 1e3):>9} {c(r['cd_l1'], 1e3):>9} {c(r['time_s']):>9} "
                         f"{c(r['paper_cd_l1'], 1e3):>9}")
        lines.append("")
    return "\n".join(lines)


def print_plans(sweeps, runner) -> int:
    """`--plan`: one line per sweep (`eval.plan.plan_sweep`), its pending runs per method and config, and the
    total; returns 0."""
    from eval.plan import plan_sweep

    plans = [plan_sweep(s, runner) for s in sweeps]
    for plan in plans:
        print(plan.line(runner.jobs))
        for line in plan.breakdown():
            print(line)
    if len(plans) > 1:
        known_s, unknown = sum(p.known_s for p in plans), sum(p.pending - p.known for p in plans)
        print(f"all: {sum(p.pending for p in plans)} runs to run; the stored ones took {known_s / 3600:.2f} h "
              f"({known_s / 3600 / max(1, runner.jobs):.2f} h at {max(1, runner.jobs)} jobs)"
              + (f", {unknown} never ran" if unknown else ""))
    return 0


def run(args) -> int:
    from eval.runner import RunnerConfig, run_sweep

    sweep = build_sweep(args)
    runner = RunnerConfig(work=args.work, db=args.db, jobs=args.jobs, executor=args.executor,
                          retry_failed=args.retry_failed, ray_address=args.ray_address, threads=args.threads,
                          rerun=args.rerun)
    check_work(args.work, runner.db_path, write=not args.plan)
    if args.plan:
        return print_plans([sweep], runner)
    if args.report:
        from eval.cli import check_output_dir

        check_output_dir(args.report, "--report")
    summary = run_sweep(sweep, runner)
    print(summary_text(runner.db_path, sweep.inputs, summary.keys), end="")
    print(f"{summary.line()}; store {runner.db_path}")
    if args.report:
        from eval.reports import write_reports

        paths = write_reports(runner.db_path, args.report, work=Path(args.work), keys=summary.keys)
        print(f"wrote {len(paths)} report files; open {Path(args.report) / 'index.html'}")
    return 0
