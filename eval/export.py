"""A compact export of the results store, committed beside the reports it regenerates (DESIGN.md 8.5).

The SQLite store and the output meshes stay in the work folder (`runs/`, not committed). What the tables and
plots need fits in one small file, `reports/store/runs.jsonl.gz`: gzip-compressed JSON lines, first a header

    {"format": "dmesh-harness runs", "version": 1, "runs": N, "columns": [...]}

then one run per line with the columns of `EXPORT_COLUMNS` (the store's identity, status, metrics, timings,
info and timestamps; the JSON columns as objects; no lease columns). Only finished runs (done or failed), and
of each configuration (method, config, shape, input kind, input settings, seed) only the latest, like the
reports select them (`eval.reports.select_runs`). Rows are sorted by key and the gzip header carries no time,
so the same runs give the same bytes.

- `export_store(db, path)` writes it (`dmesh export-store`; `dmesh reproduce-tables` and `dmesh robustness`
  refresh it after their sweeps);
- `load_export(path, db)` loads it into a store (`dmesh import-store`: a new machine's sweeps then skip every
  run the export holds, so long sweeps continue across machines from the committed export);
- `report_store(db, out, work)` is what `--report-only` reads: the SQLite store when there is one, else the
  export under `out` loaded into a temporary store, with mesh paths resolved against the work folder;
- `keep_tables(out)` restores any table whose CSV had rows before a report pass and has none after it, so a
  report pass never replaces a committed table by an empty one (renders with missing meshes are kept by the
  report writers themselves).
"""
from __future__ import annotations

import contextlib
import gzip
import io
import json
import logging
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = ["EXPORT_NAME", "EXPORT_COLUMNS", "FORMAT", "export_store", "read_export", "load_export",
           "report_store", "keep_tables", "latest_by_configuration"]

#: Where the export sits inside a report folder.
EXPORT_NAME = Path("store") / "runs.jsonl.gz"
FORMAT, VERSION = "dmesh-harness runs", 1
EXPORT_COLUMNS = ("key", "method", "config_label", "shape", "category", "input_kind", "config_json", "inputs_json",
                  "seed", "status", "error", "metrics_json", "timings_json", "info_json", "peak_memory_mb",
                  "mesh_path", "gt_hash", "started_at", "finished_at", "code_version", "base_key", "code_deps")


def latest_by_configuration(rows: list[dict]) -> dict[str, dict]:
    """The latest finished (done or failed) row of every configuration (method, config, shape, input kind,
    input settings, seed: the identity of `eval.reports.select_runs`), by that identity."""
    best: dict[str, dict] = {}
    for r in rows:
        if r["status"] not in ("done", "failed"):
            continue
        ident = json.dumps([r["method"], r["config_label"], r["shape"], r["input_kind"], r["inputs_json"],
                            int(r["seed"])], sort_keys=True, default=str)
        if ident not in best or (r["started_at"] or "") >= (best[ident]["started_at"] or ""):
            best[ident] = r
    return best


def _latest(rows: list[dict]) -> list[dict]:
    """`latest_by_configuration`'s rows, sorted by key."""
    return sorted(latest_by_configuration(rows).values(), key=lambda r: r["key"])


def export_store(db: str | Path, path: str | Path) -> int:
    """Writes the export of the store `db` to `path` (atomically); returns the number of runs written.

    Raises:
        FileNotFoundError: no store at `db`.
    """
    from eval.io import atomic_path
    from eval.store import Store

    db = Path(db)
    if not db.is_file():
        raise FileNotFoundError(f"results store {db} not found")
    with Store(db) as store:
        rows = _latest(store.rows())
    text = io.StringIO()
    header = {"format": FORMAT, "version": VERSION, "runs": len(rows), "columns": list(EXPORT_COLUMNS)}
    text.write(json.dumps(header, sort_keys=True) + "\n")
    for r in rows:
        text.write(json.dumps({c: r.get(c) for c in EXPORT_COLUMNS}, sort_keys=True, default=str) + "\n")
    with atomic_path(Path(path)) as tmp:
        with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0, filename="") as gz:
            gz.write(text.getvalue().encode())
    return len(rows)


def read_export(path: str | Path) -> list[dict]:
    """The runs of the export `path`; ValueError (one line) for a file that is not a complete export."""
    path = Path(path)
    try:
        with gzip.open(path, "rt", encoding="utf-8") as fh:
            lines = fh.read().splitlines()
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise ValueError(f"store export {path}: cannot be read ({exc})") from None
    try:
        header = json.loads(lines[0]) if lines else None
        runs = [json.loads(x) for x in lines[1:]]
    except json.JSONDecodeError as exc:
        raise ValueError(f"store export {path}: not JSON lines ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ValueError(f"store export {path}: no '{FORMAT}' header on its first line")
    if header.get("version") != VERSION:
        raise ValueError(f"store export {path}: version {header.get('version')!r}, this code reads {VERSION}")
    if header.get("runs") != len(runs):
        raise ValueError(f"store export {path}: the header says {header.get('runs')} runs, the file holds "
                         f"{len(runs)} (truncated?)")
    bad = [i for i, r in enumerate(runs) if not isinstance(r, dict) or not {"key", "status"} <= set(r)]
    if bad:
        raise ValueError(f"store export {path}: line {bad[0] + 2} is not a run")
    return runs


def load_export(path: str | Path, db: str | Path, mesh_root: str | Path | None = None,
                keep_existing: bool = False, runs: list[dict] | None = None) -> int:
    """Loads the export `path` into the store `db` (created); returns the number of runs loaded.

    Mesh paths stored relative to their store's folder are made absolute against `mesh_root` (the work folder
    whose `meshes/` they name), so renders find the meshes when they exist there. With `keep_existing`, runs
    whose key the store already holds are left as the store has them (`dmesh import-store`). `runs`: the
    export's runs when the caller has read them already (`read_export`)."""
    from eval.store import Store
    from eval.stored import migrate_records

    runs = read_export(path) if runs is None else runs
    loaded = 0
    with Store(db) as store:
        for r in runs:
            if keep_existing and store.status(r["key"]) is not None:
                continue
            loaded += 1
            row = {c: r.get(c) for c in EXPORT_COLUMNS if c in r}
            mp = row.get("mesh_path")
            if mesh_root is not None and isinstance(mp, str) and mp and not Path(mp).is_absolute():
                row["mesh_path"] = str(Path(mesh_root) / mp)
            store.upsert(row)
        migrate_records(store)  # an export written before the inputs were versioned by INPUT_VERSION
    return loaded


@contextlib.contextmanager
def report_store(db: str | Path, out: str | Path, work: str | Path):
    """The store a report-only pass reads (a context manager yielding its path): `db` when it exists, else
    the export `out/store/runs.jsonl.gz` loaded into a temporary store (removed afterwards).

    Raises:
        FileNotFoundError: neither exists.
    """
    db, export = Path(db), Path(out) / EXPORT_NAME
    if db.is_file():
        yield db
        return
    if not export.is_file():
        raise FileNotFoundError(f"no results store at {db} and no store export at {export}: run the sweeps first "
                                f"(`dmesh reproduce-tables`), or give --db / --work")
    with tempfile.TemporaryDirectory(prefix="dmesh-export-") as tmp:
        n = load_export(export, Path(tmp) / "results.sqlite", mesh_root=work)
        log.info("read %d runs from the store export %s", n, export)
        yield Path(tmp) / "results.sqlite"


def _has_rows(csv: Path) -> bool:
    try:
        return csv.is_file() and len([x for x in csv.read_text().splitlines() if x.strip()]) > 1
    except (OSError, UnicodeDecodeError):
        return False


@contextlib.contextmanager
def keep_tables(out: str | Path):
    """Around a report pass into `out`: every table (a CSV, with the Markdown file of the same name) that had
    rows before and has none after is put back as it was, with a warning."""
    from eval.io import atomic_path

    out = Path(out)
    saved: dict[Path, bytes] = {}
    for csv in sorted(out.glob("*.csv")) if out.is_dir() else []:
        if _has_rows(csv):
            for p in (csv, csv.with_suffix(".md")):
                if p.is_file():
                    saved[p] = p.read_bytes()
    yield
    for csv in [p for p in saved if p.suffix == ".csv"]:
        if _has_rows(csv):
            continue
        log.warning("%s: the store holds no runs for this table; the committed table is kept", csv)
        for p in (csv, csv.with_suffix(".md")):
            if p in saved:
                with atomic_path(p) as tmp:
                    Path(tmp).write_bytes(saved[p])
