"""`dmesh robustness`: run the robustness sweeps (corrupted inputs, simulated scans, matched budgets) and write
the robustness report (`eval.reports.robustness`).

By default three sweeps run into the store of `dmesh reproduce-tables` (runs/paper), so that one store (and its
committed export, `reports/store/runs.jsonl.gz`) is behind every report: `eval/sweeps/robustness.yaml` (point
clouds: each corruption level by itself, and a realistic scan), `robustness_budget.yaml` (each method at
several output sizes on the clean input), `robustness_multiview.yaml` (depth noise, fewer views, fewer
pixels) and `test_scan.yaml` (the test split's closed shapes scanned with occlusion holes, 3 seeds: rows of split
"test"). DMesh filters nothing by itself in the harness; the sweep that gives every method the harness's
smoothing on every noisy input (`robustness_noisy.yaml`) is a study, run with `--sweep`. `--quick` runs
`robustness_small.yaml` instead (the CI subset, a few minutes) into runs/robustness_quick and
out/robustness_quick. Methods a sweep names that are not registered are left out with a warning. Resumable like
every sweep; `--report-only` runs nothing.
"""
from __future__ import annotations

import logging
from pathlib import Path

NAME = "robustness"
HELP = "run the robustness sweeps (corrupted inputs, scans, matched budgets) and write reports/robustness.*"

SWEEPS = Path(__file__).resolve().parents[1] / "sweeps"
DEFAULT_SWEEPS = [str(SWEEPS / n) for n in ("robustness.yaml", "robustness_budget.yaml", "robustness_multiview.yaml",
                                             "test_scan.yaml")]
QUICK_SWEEPS = [str(SWEEPS / "robustness_small.yaml")]

log = logging.getLogger(__name__)


def add_arguments(p) -> None:
    from eval.commands.bench import add_sweep_arguments

    p.add_argument("-o", "--out", help="report folder (default: reports; with --quick: out/robustness_quick)")
    p.add_argument("--sweep", nargs="+", metavar="YAML",
                   help="sweep files (default: eval/sweeps/robustness.yaml, robustness_budget.yaml, "
                        "robustness_multiview.yaml, test_scan.yaml)")
    p.add_argument("--quick", action="store_true",
                   help="the CI subset: eval/sweeps/robustness_small.yaml into runs/robustness_quick")
    add_sweep_arguments(p, "runs/paper")
    p.set_defaults(work=None)  # resolved in run(): runs/paper, or runs/robustness_quick with --quick
    for action in p._actions:  # argparse has no public way to reword a shared flag's help
        if "--work" in action.option_strings:
            action.help = ("work folder: input cache, meshes, store (default: runs/paper; --quick: "
                           "runs/robustness_quick)")
    p.add_argument("--no-renders", action="store_true", help="skip the realistic-scan renders")
    p.add_argument("--report-only", action="store_true", help="run nothing: report every robustness run in the store")


def run(args) -> int:
    from eval.cli import check_output_dir
    from eval.commands.bench import build_sweep, check_work
    from eval.commands.reproduce_tables import _runnable
    from eval.export import EXPORT_NAME, export_store
    from eval.reports import select_runs
    from eval.reports.robustness import write_robustness
    from eval.runner import RunnerConfig, run_sweep
    from eval.store import Store

    out = Path(args.out or ("out/robustness_quick" if args.quick else "reports"))
    args.work = args.work or ("runs/robustness_quick" if args.quick else "runs/paper")
    check_output_dir(out, "-o")
    runner = RunnerConfig(work=args.work, db=args.db, jobs=args.jobs, executor=args.executor,
                          retry_failed=args.retry_failed, ray_address=args.ray_address,
                          rerun=args.rerun)
    check_work(args.work, runner.db_path, write=not (args.plan or args.report_only))
    keys = None
    if not args.report_only:
        sweeps = [build_sweep(args, path, strict=False) for path in
                  (args.sweep or (QUICK_SWEEPS if args.quick else DEFAULT_SWEEPS))]
        sweeps = [s for s in (_runnable(s, bool(args.methods)) for s in sweeps) if s is not None]
        if not sweeps:
            raise ValueError("no robustness sweep has runs: check --methods / --inputs and the registered methods")
        if args.plan:
            from eval.commands.bench import print_plans

            return print_plans(sweeps, runner)
        keys = []
        for sweep in sweeps:
            summary = run_sweep(sweep, runner)
            keys += summary.keys
            print(f"sweep {sweep.name}: {summary.line()}")
    elif not runner.db_path.is_file():
        raise FileNotFoundError(f"no results store at {runner.db_path}: run `dmesh robustness` first, or give "
                                f"--db / --work")
    with Store(runner.db_path) as store:
        df = select_runs(store.dataframe(), keys)
    paths, _ = write_robustness(df, out, runner.db_path, args.work, renders=not args.no_renders)
    n = export_store(runner.db_path, out / EXPORT_NAME)
    print(f"wrote {len(paths)} report files and the store export ({n} runs) into {out}; "
          f"`dmesh reproduce-tables --report-only` adds them to index.html")
    return 0
