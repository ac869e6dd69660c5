"""The results store: one tidy SQLite table `runs`, one row per method x shape x input x config x seed.

Rows are keyed by the run key of `eval.sweep.run_key` (a SHA-256 hex string). A row's `status` is
`running` while a process works on it, then `done` (with metrics) or `failed` (with the error message). The
store uses the standard library's sqlite3 in WAL mode so readers (reports) never block the writer (runner).
Only the parent process of a sweep writes; workers return their results to it.

Columns (all JSON columns hold UTF-8 JSON text):
    key            TEXT  run key, primary key
    method         TEXT  method name as registered in `baselines.registry.METHODS`
    config_label   TEXT  short label of the config overrides ("" for the method's defaults)
    shape          TEXT  shape id (synthetic name, or file stem of a real mesh)
    category       TEXT  closed | open | mixed
    input_kind     TEXT  pointcloud | multiview | mesh
    config_json    TEXT  the full method config
    inputs_json    TEXT  input settings (points, views, resolution, ...)
    seed           INT   run seed
    status         TEXT  done | failed | running
    error          TEXT  one-line error message of a failed run
    metrics_json   TEXT  flat dict from `eval.metrics.compute_metrics` (raw units, normalised GT frame)
    timings_json   TEXT  method timings in seconds, including "total"
    info_json      TEXT  the method's extra information (e.g. optimisation steps)
    peak_memory_mb REAL  peak memory of the method
    mesh_path      TEXT  output mesh, relative to the store's folder when inside it
    gt_hash        TEXT  hash of the GT mesh (file bytes or generated arrays)
    started_at     TEXT  ISO-8601 UTC
    finished_at    TEXT  ISO-8601 UTC
    code_version   TEXT  package version + source hash (see `eval.sweep.code_version`)
"""
from __future__ import annotations

import json
import logging
import sqlite3
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable

log = logging.getLogger(__name__)

STATUSES = ("done", "failed", "running")

_COLUMNS = {
    "key": "TEXT PRIMARY KEY",
    "method": "TEXT NOT NULL",
    "config_label": "TEXT NOT NULL DEFAULT ''",
    "shape": "TEXT NOT NULL",
    "category": "TEXT NOT NULL",
    "input_kind": "TEXT NOT NULL",
    "config_json": "TEXT NOT NULL DEFAULT '{}'",
    "inputs_json": "TEXT NOT NULL DEFAULT '{}'",
    "seed": "INTEGER NOT NULL",
    "status": "TEXT NOT NULL CHECK (status IN ('done', 'failed', 'running'))",
    "error": "TEXT",
    "metrics_json": "TEXT",
    "timings_json": "TEXT",
    "info_json": "TEXT",
    "peak_memory_mb": "REAL",
    "mesh_path": "TEXT",
    "gt_hash": "TEXT",
    "started_at": "TEXT",
    "finished_at": "TEXT",
    "code_version": "TEXT",
}
COLUMNS = tuple(_COLUMNS)
_JSON_COLUMNS = ("config_json", "inputs_json", "metrics_json", "timings_json", "info_json")


def utc_now() -> str:
    """The current UTC time as ISO-8601 text with seconds."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _json(value: Any) -> str | None:
    if value is None or isinstance(value, str):
        return value
    return json.dumps(value, sort_keys=True, default=_json_default)


def _json_default(obj):
    # numpy scalars and arrays reach us from metrics dicts; store them as plain numbers / lists.
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if hasattr(obj, "item"):
        return obj.item()
    return str(obj)


class Store:
    """The `runs` table of one SQLite file.

    Args:
        path: the database file; its folder is created. ":memory:" works for tests.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path) if str(path) != ":memory:" else None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._conn = sqlite3.connect(str(path), timeout=30.0, isolation_level=None)
        self._conn.row_factory = sqlite3.Row
        if self.path is not None:
            self._conn.execute("PRAGMA journal_mode=WAL")
        self._conn.execute("PRAGMA synchronous=NORMAL")
        cols = ", ".join(f"{k} {v}" for k, v in _COLUMNS.items())
        self._conn.execute(f"CREATE TABLE IF NOT EXISTS runs ({cols})")
        have = {r["name"] for r in self._conn.execute("PRAGMA table_info(runs)")}
        for name, decl in _COLUMNS.items():  # older stores gain new columns
            if name not in have:
                self._conn.execute(f"ALTER TABLE runs ADD COLUMN {name} {decl.replace('PRIMARY KEY', '')}")
        self._conn.execute("CREATE INDEX IF NOT EXISTS runs_status ON runs(status)")

    # -- context management
    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @contextmanager
    def _tx(self):
        self._conn.execute("BEGIN IMMEDIATE")
        try:
            yield
            self._conn.execute("COMMIT")
        except BaseException:
            self._conn.execute("ROLLBACK")
            raise

    # -- writing
    def upsert(self, row: dict) -> None:
        """Inserts or replaces the row with `row["key"]`; JSON columns accept dicts."""
        unknown = set(row) - set(COLUMNS)
        if unknown:
            raise ValueError(f"Store.upsert: unknown columns {sorted(unknown)}")
        if row.get("status") not in STATUSES:
            raise ValueError(f"Store.upsert: status must be one of {STATUSES}, got {row.get('status')!r}")
        values = {k: (_json(v) if k in _JSON_COLUMNS else v) for k, v in row.items()}
        names = ", ".join(values)
        marks = ", ".join(f":{k}" for k in values)
        with self._tx():
            self._conn.execute(f"INSERT OR REPLACE INTO runs ({names}) VALUES ({marks})", values)

    def mark_running(self, row: dict) -> None:
        """Records that `row` (identity columns) has started now; clears any previous result."""
        self.upsert({**row, "status": "running", "started_at": utc_now(), "finished_at": None, "error": None,
                     "metrics_json": None, "timings_json": None, "info_json": None, "peak_memory_mb": None,
                     "mesh_path": None})

    def finish(self, key: str, *, status: str, error: str | None = None, metrics: dict | None = None,
               timings: dict | None = None, info: dict | None = None, peak_memory_mb: float | None = None,
               mesh_path: str | None = None) -> None:
        """Stores the outcome of the run `key` (status done or failed)."""
        if status not in ("done", "failed"):
            raise ValueError(f"Store.finish: status must be 'done' or 'failed', got {status!r}")
        with self._tx():
            cur = self._conn.execute(
                "UPDATE runs SET status=?, error=?, metrics_json=?, timings_json=?, info_json=?, "
                "peak_memory_mb=?, mesh_path=?, finished_at=? WHERE key=?",
                (status, error, _json(metrics), _json(timings), _json(info), peak_memory_mb, mesh_path,
                 utc_now(), key))
            if cur.rowcount != 1:
                raise ValueError(f"Store.finish: no run with key {key}")

    def delete(self, keys: Iterable[str]) -> int:
        """Deletes the given runs; returns how many were removed."""
        keys = list(keys)
        with self._tx():
            return sum(self._conn.execute("DELETE FROM runs WHERE key=?", (k,)).rowcount for k in keys)

    # -- reading
    def status(self, key: str) -> str | None:
        """The status of run `key`, or None if the store has no such run."""
        r = self._conn.execute("SELECT status FROM runs WHERE key=?", (key,)).fetchone()
        return None if r is None else r["status"]

    def get(self, key: str) -> dict | None:
        """Run `key` as a dict with JSON columns decoded, or None."""
        r = self._conn.execute("SELECT * FROM runs WHERE key=?", (key,)).fetchone()
        return None if r is None else _decode(r)

    def rows(self, **where) -> list[dict]:
        """All runs matching the equality filters (e.g. status="done"), JSON columns decoded."""
        bad = set(where) - set(COLUMNS)
        if bad:
            raise ValueError(f"Store.rows: unknown columns {sorted(bad)}")
        sql = "SELECT * FROM runs"
        if where:
            sql += " WHERE " + " AND ".join(f"{k}=?" for k in where)
        sql += " ORDER BY input_kind, category, shape, method, config_label, seed"
        return [_decode(r) for r in self._conn.execute(sql, tuple(where.values()))]

    def counts(self) -> dict[str, int]:
        """Number of runs per status."""
        return {r[0]: r[1] for r in self._conn.execute("SELECT status, COUNT(*) FROM runs GROUP BY status")}

    def dataframe(self):
        """The whole table as a pandas DataFrame, with metric and timing dicts flattened into columns.

        Metric columns keep their names (e.g. `cd_p2s`); timing columns are prefixed `time_` and
        `time_s` is the method's total wall time in seconds. `config_json`, `inputs_json` and `info_json`
        hold decoded dicts (`config` and `info` are aliases).
        """
        import pandas as pd

        records = []
        for r in self.rows():
            rec = {k: v for k, v in r.items() if k not in ("metrics_json", "timings_json")}
            rec["config"] = r["config_json"]
            rec["info"] = r["info_json"] or {}
            rec.update(r["metrics_json"] or {})
            for k, v in (r["timings_json"] or {}).items():
                rec[f"time_{k}"] = v
            rec["time_s"] = (r["timings_json"] or {}).get("total")
            records.append(rec)
        return pd.DataFrame.from_records(records, columns=None if records else list(COLUMNS) + ["time_s"])


def _decode(row: sqlite3.Row) -> dict:
    out = dict(row)
    for k in _JSON_COLUMNS:
        if out.get(k) is not None:
            out[k] = json.loads(out[k])
    return out
