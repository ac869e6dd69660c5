"""`dmesh export-store`: write the compact export of a results store (`eval.export`), the file committed beside
the reports so that `dmesh reproduce-tables --report-only` regenerates them on a clone without the store."""
from __future__ import annotations

from pathlib import Path

NAME = "export-store"
HELP = "write the compact export of a results store (reports/store/runs.jsonl.gz) that --report-only reads"


def add_arguments(p) -> None:
    from eval.export import EXPORT_NAME

    p.add_argument("--work", default="runs/paper", help="work folder of the store (default: runs/paper)")
    p.add_argument("--db", help="SQLite results store (default: WORK/results.sqlite)")
    p.add_argument("-o", "--out", default=str(Path("reports") / EXPORT_NAME),
                   help=f"export file (default: reports/{EXPORT_NAME})")


def run(args) -> int:
    from eval.cli import check_output_file
    from eval.export import export_store

    db = Path(args.db) if args.db else Path(args.work) / "results.sqlite"
    out = check_output_file(args.out, "-o", suffixes=(".gz",), inputs=[db])
    if not db.is_file():
        raise FileNotFoundError(f"no results store at {db}: give --work or --db")
    n = export_store(db, out)
    print(f"wrote {n} runs of {db} to {out} ({out.stat().st_size / 1024:.1f} KiB)")
    return 0
