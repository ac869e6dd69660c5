"""`dmesh import-store`: load the committed export of the results store (`eval.export`) into a work folder's
store, so that sweeps on a new machine skip every run it holds and go on from there. Runs the store already has
are kept as they are."""
from __future__ import annotations

from pathlib import Path

NAME = "import-store"
HELP = "load the committed store export (reports/store/runs.jsonl.gz) into a work folder's results store"


def add_arguments(p) -> None:
    from eval.export import EXPORT_NAME

    p.add_argument("--work", default="runs/paper", help="work folder of the store (default: runs/paper)")
    p.add_argument("--db", help="SQLite results store (default: WORK/results.sqlite)")
    p.add_argument("-i", "--input", default=str(Path("reports") / EXPORT_NAME),
                   help=f"export file (default: reports/{EXPORT_NAME})")


def run(args) -> int:
    from eval.export import load_export, read_export

    src = Path(args.input)
    if not src.is_file():
        raise FileNotFoundError(f"no store export at {src}: give -i")
    runs = read_export(src)
    total = len(runs)
    from eval.cli import check_output_file

    db = check_output_file(Path(args.db) if args.db else Path(args.work) / "results.sqlite", "--db", inputs=[src])
    db.parent.mkdir(parents=True, exist_ok=True)
    n = load_export(src, db, mesh_root=args.work, keep_existing=True, runs=runs)
    print(f"loaded {n} runs of {src} into {db} ({total - n} the store already had were kept)")
    return 0
