"""`dmesh changes`: which configurations' results moved between two sets of runs (`eval.reports.changes`):
the export committed at a git revision (or an export file) against a work folder's store (or an export)."""
from __future__ import annotations

import subprocess
import tempfile
from pathlib import Path

NAME = "changes"
HELP = "list the runs whose metric moved (or that failed) since a git revision's committed results"


def add_arguments(p) -> None:
    from eval.reports.changes import TOLERANCE

    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--since", metavar="REV", help="git revision whose committed export is 'before'")
    where.add_argument("--before", metavar="EXPORT", help="an export file (runs.jsonl.gz) as 'before'")
    p.add_argument("--work", help="work folder whose store is 'after' (default: the working tree's export, "
                                  "reports/store/runs.jsonl.gz)")
    p.add_argument("--after", metavar="EXPORT", help="an export file as 'after' (instead of --work)")
    p.add_argument("--metric", default="cd_p2s", help="metric compared (default: cd_p2s)")
    p.add_argument("--tolerance", type=float, default=TOLERANCE,
                   help=f"relative change counted as a move (default: {TOLERANCE})")
    p.add_argument("-o", "--out", default="reports", help="report folder (default: reports)")
    p.add_argument("--top", type=int, default=10, help="rows printed (default: 10)")


def _commit_of(rev: str) -> str:
    """The commit id `rev` names, verified by `git rev-parse` with `rev` after `--end-of-options`, so a value
    such as `--output=PATH` is read as a revision (and refused), never as an option of git; ValueError (one
    line) when it names no commit."""
    got = subprocess.run(["git", "rev-parse", "--verify", "--quiet", "--end-of-options", f"{rev}^{{commit}}"],
                         capture_output=True)
    commit = got.stdout.decode().strip()
    if got.returncode != 0 or not commit:
        why = " ".join(got.stderr.decode().split())
        raise ValueError(f"--since {rev!r}: not a commit of this git repository" + (f" ({why})" if why else ""))
    return commit


def _export_at(rev: str) -> list[dict]:
    """The runs of `reports/store/runs.jsonl.gz` as committed at `rev`."""
    from eval.export import EXPORT_NAME, read_export

    committed = (Path("reports") / EXPORT_NAME).as_posix()
    got = subprocess.run(["git", "show", "--end-of-options", f"{_commit_of(rev)}:{committed}"], capture_output=True)
    if got.returncode != 0:
        raise ValueError(f"--since {rev}: git has no {rev}:{committed} "
                         f"({' '.join(got.stderr.decode().split()) or 'git failed'})")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "runs.jsonl.gz"
        path.write_bytes(got.stdout)
        return read_export(path)


def _store_runs(work: str) -> list[dict]:
    from eval.store import Store

    db = Path(work) / "results.sqlite"
    if not db.is_file():
        raise FileNotFoundError(f"no results store at {db}: give --work a folder with results.sqlite")
    with Store(db) as store:
        return store.rows()


def run(args) -> int:
    import pandas as pd

    from eval.cli import check_output_dir
    from eval.export import EXPORT_NAME, read_export
    from eval.io import atomic_path
    from eval.reports.changes import changes_markdown, compare_runs

    if args.work and args.after:
        raise ValueError("give --work or --after, not both")
    if not args.tolerance >= 0:
        raise ValueError(f"--tolerance must be >= 0, got {args.tolerance}")
    out = check_output_dir(args.out, "-o")
    before = _export_at(args.since) if args.since else read_export(args.before)
    before_name = f"the export at {args.since}" if args.since else args.before
    if args.work:
        after, after_name = _store_runs(args.work), f"the store of {args.work}"
    else:
        path = Path(args.after) if args.after else Path("reports") / EXPORT_NAME
        after, after_name = read_export(path), str(path)
    rows, counts = compare_runs(before, after, args.metric, args.tolerance)
    text = changes_markdown(rows, counts, args.metric, args.tolerance, before_name, after_name)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "changes.md") as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    with atomic_path(out / "changes.csv") as tmp:
        pd.DataFrame(rows, columns=None if rows else ["change"]).to_csv(tmp, index=False)
    print(", ".join(f"{k}: {v}" for k, v in counts.items()))
    for r in rows[: max(args.top, 0)]:
        ratio = "" if r["ratio"] is None else f" x{r['ratio']:.3f}"
        print(f"  {r['change']:<10} {r['method']} [{r['config']}] {r['shape']} ({r['input']}){ratio}")
    print(f"wrote {out / 'changes.md'} and {out / 'changes.csv'}")
    return 0
