"""`dmesh reproduce-tables`: run the paper-style sweeps and write `reports/`.

Two sets of sweeps run into one store:

- the tables (default, `make reproduce-tables`): `eval/sweeps/paper.yaml` (Table 2's dev split: point cloud and
  multi-view reconstruction by class, every method's default preset, DMesh's `fast` presets and the multi-view
  `depth` start), `eval/sweeps/test.yaml` (Table 2's test split, point clouds at 3 seeds) and
  `eval/sweeps/table1.yaml` (Table 1: mesh to DMesh);
- the recipes (`--recipes`, `make reproduce-recipes`): DMesh's long gradient-step recipes,
  `eval/sweeps/recipes.yaml` (the point-cloud `paper` and multi-view `refine` presets on the Table 2 shapes),
  `eval/sweeps/recipes_size.yaml` (the fast start at the paper preset's mesh sizes: `reports/recipes_size.md`),
  `eval/sweeps/compact_floor.yaml` and `compact.yaml` (matched budgets: DMesh `compact` against
  reconstruct-then-decimate, `reports/compact.md`), `eval/sweeps/test_multiview.yaml` (Table 2's test split from
  images, 1 seed: the multi-view `fast` preset takes about 9 min a shape) and `eval/sweeps/multiview_paper.yaml`
  (the multi-view `paper` preset, hours per shape).

Either set then writes the reports from every configuration in the store (its latest run, as `--report-only`),
so the recipes' rows stay in Table 2 after a run of the tables and the other way round; `--sweep FILES` runs
those files and reports only their runs. Methods a sweep file names
that are not registered (yet) are left out with a warning, and a sweep left without runs is skipped; methods
named by `--methods` must exist. `--inputs` selects among each sweep's own input kinds; the other flags apply
to every sweep. Resumable: finished runs are read from the store, so a second run with
nothing changed only regenerates the reports (renders are cached too). After the sweeps the store's compact
export is written to OUT/store/runs.jsonl.gz (`eval.export`), which `--report-only` reads when there is no store.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

NAME = "reproduce-tables"
HELP = "run the paper-style sweeps and regenerate reports/ (tables, figures, index.html)"

SWEEPS = Path(__file__).resolve().parents[1] / "sweeps"
DEFAULT_SWEEPS = [str(SWEEPS / name) for name in ("paper.yaml", "test.yaml", "table1.yaml")]
#: `--recipes`: DMesh's long gradient-step recipes (hours; resumable), the multi-view paper preset last.
RECIPE_SWEEPS = [str(SWEEPS / name) for name in ("recipes.yaml", "recipes_size.yaml", "compact_floor.yaml",
                                                  "compact.yaml", "test_multiview.yaml", "multiview_paper.yaml")]

log = logging.getLogger(__name__)


def add_arguments(p) -> None:
    from eval.commands.bench import add_sweep_arguments

    p.add_argument("-o", "--out", default="reports", help="report folder (default: reports)")
    p.add_argument("--sweep", nargs="+", default=None, metavar="YAML",
                   help="sweep files, reported alone (default: eval/sweeps/paper.yaml, test.yaml and table1.yaml)")
    p.add_argument("--recipes", action="store_true",
                   help="run DMesh's long gradient-step recipes instead (eval/sweeps/recipes.yaml, recipes_size.yaml, "
                        "compact_floor.yaml, compact.yaml, test_multiview.yaml, multiview_paper.yaml: many hours on 2 "
                        "cores, resumable)")
    add_sweep_arguments(p, "runs/paper")
    p.add_argument("--no-renders", action="store_true", help="skip the rendered figures (tables and plots only)")
    p.add_argument("--report-only", action="store_true",
                   help="run nothing: regenerate the reports from every run in the store (the latest of each "
                        "configuration, whatever code version produced it), or without a store from its "
                        "committed export OUT/store/runs.jsonl.gz (dmesh export-store)")


def _runnable(sweep, explicit_methods: bool):
    """`sweep` restricted to registered methods (unless the user named them), or None when it has no runs."""
    from baselines import registry

    from eval.sweep import expand

    if not explicit_methods:
        missing = [m for m in sweep.methods if m not in registry.METHODS]
        if missing:
            log.warning("sweep %s: methods %s are not registered; left out", sweep.name, ", ".join(missing))
            kept = tuple(m for m in sweep.methods if m in registry.METHODS)
            if not kept:
                return None
            sweep = dataclasses.replace(sweep, methods=kept)
    if not expand(sweep):
        log.warning("sweep %s has no runs with these settings; skipped", sweep.name)
        return None
    return sweep


def run(args) -> int:
    from eval.cli import check_output_dir
    from eval.commands.bench import build_sweep, check_work, summary_text
    from eval.reports import write_reports
    from eval.runner import RunnerConfig, run_sweep
    from eval.values import parse_sets

    check_output_dir(args.out, "-o")
    if args.report_only:
        from eval.export import EXPORT_NAME, keep_tables, report_store

        db = Path(args.db) if args.db else RunnerConfig(work=args.work).db_path
        check_work(args.work, db, write=False)
        # No SQLite store (a fresh clone): the committed export OUT/store/runs.jsonl.gz; no table goes empty.
        with report_store(db, args.out, args.work) as source, keep_tables(args.out):
            paths = write_reports(source, args.out, work=Path(args.work), title="DMesh harness: stored runs",
                                  renders=not args.no_renders, keys=None,
                                  source=str(db) if db.is_file() else str(Path(args.out) / EXPORT_NAME))
        print(f"wrote {len(paths)} report files from {db if db.is_file() else 'the store export'}; "
              f"open {Path(args.out) / 'index.html'}")
        return 0

    if args.sweep and args.recipes:
        raise ValueError("--sweep and --recipes both choose the sweeps: give one of them")
    files = args.sweep or (RECIPE_SWEEPS if args.recipes else DEFAULT_SWEEPS)
    # --inputs selects among each sweep's own input kinds (Table 1 keeps its mesh input and frame).
    wanted, args.inputs = args.inputs, None
    sweeps, named = [], set()
    for path in files:
        sweep = build_sweep(args, path, strict=False)  # every file is validated before anything runs
        named.update(sweep.methods)
        if wanted:
            kinds = tuple(k for k in sweep.inputs if k in wanted)
            if not kinds:
                continue
            sweep = dataclasses.replace(sweep, inputs=kinds)
        sweeps.append(sweep)
    for key in parse_sets(args.sets):
        if "." in key and key.split(".", 1)[0] not in named:
            raise ValueError(f"--set {key}=...: {key.split('.', 1)[0]!r} is not a method of any sweep "
                             f"(methods: {', '.join(sorted(named))})")
    sweeps = [s for s in (_runnable(s, bool(args.methods)) for s in sweeps) if s is not None]
    if not sweeps:
        raise ValueError("no sweep has runs: check --methods / --inputs and the registered methods")
    runner = RunnerConfig(work=args.work, db=args.db, jobs=args.jobs, executor=args.executor,
                          retry_failed=args.retry_failed, ray_address=args.ray_address,
                          rerun=args.rerun)
    check_work(args.work, runner.db_path, write=not args.plan)
    if args.plan:
        from eval.commands.bench import print_plans

        return print_plans(sweeps, runner)
    keys, kinds = [], []
    for sweep in sweeps:
        summary = run_sweep(sweep, runner)
        keys += summary.keys
        kinds += [k for k in sweep.inputs if k not in kinds]
        print(f"sweep {sweep.name}: {summary.line()}")
    print(summary_text(runner.db_path, kinds, keys), end="")
    print(f"store {runner.db_path}")
    title = "DMesh harness: " + ", ".join(s.name for s in sweeps)
    if args.sweep:  # the user's own sweep files: their runs alone
        paths = write_reports(runner.db_path, args.out, work=Path(args.work), title=title,
                              renders=not args.no_renders, keys=keys)
    else:  # the built-in sets: every configuration in the store, so neither set's rows drop out of Table 2
        from eval.export import keep_tables

        with keep_tables(args.out):
            paths = write_reports(runner.db_path, args.out, work=Path(args.work), title=title,
                                  renders=not args.no_renders, keys=None)
    from eval.export import EXPORT_NAME, export_store

    n = export_store(runner.db_path, Path(args.out) / EXPORT_NAME)  # what --report-only reads on a clone
    print(f"wrote {len(paths)} report files and the store export ({n} runs); open {Path(args.out) / 'index.html'}")
    return 0
