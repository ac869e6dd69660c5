"""The results store: one tidy SQLite table `runs`, one row per method x shape x input x config x seed.

Rows are keyed by the run key of `eval.sweep.run_key` (a SHA-256 hex string). A row's `status` is
`running` while a process works on it, then `done` (with metrics) or `failed` (with the error message). The
store uses the standard library's sqlite3 in WAL mode so readers (reports) never block the writers. In each
sweep only the parent process writes; workers return their results to it.

Sharing a store (DESIGN.md 8.5). Several sweeps (processes) may use one store at once. A run is claimed with
a lease (`Store.claim`): the claiming process's id and host, a random token of the claiming sweep and a
heartbeat time, written in one `BEGIN IMMEDIATE` transaction that also checks that the row is not `done`, not
`failed` (unless the claimer asks to retry it) and not held by a live lease. A lease is live while its
heartbeat is younger than `stale_s` seconds and, when it was taken on this host, its process still exists
(a zombie counts as gone; `eval.leases`); a run whose lease is not live was interrupted and may be taken
over. The holder refreshes its heartbeat (`Store.heartbeat`) while it works, stores the outcome only while it
still holds the lease (`Store.finish(..., lease=)`), and frees what it holds when it stops (`Store.release`).
`done` is never downgraded: every write that could replace a result is guarded by a status condition.

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
    info_json      TEXT  the method's extra information (e.g. optimisation steps) and `worker_threads`, the
                         threads its worker allowed (`eval.execute.limit_threads`)
    peak_memory_mb REAL  peak memory of the method
    mesh_path      TEXT  output mesh, relative to the store's folder when inside it
    gt_hash        TEXT  hash of the GT mesh (file bytes or generated arrays)
    started_at     TEXT  ISO-8601 UTC
    finished_at    TEXT  ISO-8601 UTC
    code_version   TEXT  package version + source hash (see `eval.sweep.code_version`)
    base_key       TEXT  the run key without the code version (`eval.sweep.RunSpec.base_key`); NULL in rows
                         of older stores
    code_deps      TEXT  JSON: the hashes of the code the run executed (`eval.code_deps.deps_for`), by which
                         a later sweep adopts it when its code version is an earlier one; NULL when unknown
    lease_pid      INT   process id of the sweep that claimed the run last
    lease_host     TEXT  host name of that process
    lease_token    TEXT  random id of that sweep (one per `Lease`)
    heartbeat_at   REAL  Unix time of the holder's last heartbeat (NULL once released)
    attempts       INT   how many times the run was claimed
"""
from __future__ import annotations

import json
import logging
import os
import sqlite3
import time
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable

from eval.leases import LEASE_S, Lease, _process_lease, lease_live, pid_alive  # noqa: F401 - pid_alive re-exported

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
    "base_key": "TEXT",
    "code_deps": "TEXT",
    "lease_pid": "INTEGER",
    "lease_host": "TEXT",
    "lease_token": "TEXT",
    "heartbeat_at": "REAL",
    "attempts": "INTEGER NOT NULL DEFAULT 0",
}
COLUMNS = tuple(_COLUMNS)
_JSON_COLUMNS = ("config_json", "inputs_json", "metrics_json", "timings_json", "info_json", "code_deps")
#: What a run produces (cleared when it is claimed again).
_RESULT_COLUMNS = ("status", "error", "metrics_json", "timings_json", "info_json", "peak_memory_mb", "mesh_path",
                   "started_at", "finished_at", "code_deps")


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


def _reader(path: Path) -> sqlite3.Connection:
    """A connection that reads the SQLite file `path` and writes nothing, not even a file beside it.

    SQLite's own read-only mode (`mode=ro`) still creates the `-wal` and `-shm` files of a WAL store, and
    leaves them behind because it may not delete them. While no process has the store open (no `-wal` or
    `-journal` beside it) the file alone holds every committed run, so it is read as immutable: no locks, no
    files. While one has, its `-wal` holds runs not yet copied into the file, and `mode=ro` reads them
    through the files that process keeps.
    """
    busy = any(Path(f"{path}{suffix}").exists() for suffix in ("-wal", "-journal"))
    uri = path.absolute().as_uri() + ("?mode=ro" if busy else "?immutable=1")
    return sqlite3.connect(uri, uri=True, timeout=30.0, isolation_level=None)


def check_store(path: str | Path, *, write: bool) -> None:
    """Checks, writing nothing, that `path` is absent (a new store is made there) or a results store that can
    be read whole (SQLite's quick_check) and, with `write`, written: the file and its folder (where SQLite
    keeps the `-wal` and `-shm` files) writable. An empty SQLite file counts as a new store.

    Raises:
        ValueError: the problem, naming the store.
    """
    path = Path(path)
    if not path.exists():
        return
    try:
        con = _reader(path)
        try:
            tables = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
            problems = [r[0] for r in con.execute("PRAGMA quick_check(1)")]
        finally:
            con.close()
    except sqlite3.Error as exc:
        raise ValueError(f"results store {path}: cannot be read ({exc}); move it away or give another --db") from None
    if problems != ["ok"]:
        what = " ".join(" ".join(problems).replace("*** in database main ***", "").split())
        raise ValueError(f"results store {path}: cannot be read (damaged: {what}); move it away or give another --db")
    if tables and "runs" not in tables:
        raise ValueError(f"results store {path}: a SQLite database of something else (tables {', '.join(tables)}, "
                         f"no runs); give another --db")
    if write and not os.access(path, os.W_OK):
        raise ValueError(f"results store {path}: the store file is not writable; give another --db")
    folder = path.absolute().parent
    if write and not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"results store {path}: folder {folder} is not writable (SQLite keeps the store's -wal "
                         f"and -shm files there); give another --db")


class Store:
    """The `runs` table of one SQLite file.

    Args:
        path: the database file; its folder is created. ":memory:" works for tests.
        readonly: only read `path`, an existing file, and write nothing (`_reader`): no folder, no migration of
            an older store (its missing columns read as NULL), no `-wal` or `-shm` file left behind.
    """

    def __init__(self, path: str | Path, *, readonly: bool = False):
        self.path = Path(path) if str(path) != ":memory:" else None
        if readonly:
            if self.path is None:
                raise ValueError("Store: readonly needs a file, not ':memory:'")
            self._conn = _reader(self.path)
            self._conn.row_factory = sqlite3.Row
            self._shadow_older_schema()
            return
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._conn = sqlite3.connect(str(path), timeout=30.0, isolation_level=None)
        self._conn.row_factory = sqlite3.Row
        if self.path is not None:
            self._set_wal()
        self._conn.execute("PRAGMA synchronous=NORMAL")
        cols = ", ".join(f"{k} {v}" for k, v in _COLUMNS.items())
        # One transaction, so that two processes opening a new (or older) store at once do not both migrate.
        with self._tx():
            self._conn.execute(f"CREATE TABLE IF NOT EXISTS runs ({cols})")
            have = {r["name"] for r in self._conn.execute("PRAGMA table_info(runs)")}
            for name, decl in _COLUMNS.items():  # older stores gain new columns
                if name not in have:
                    self._conn.execute(f"ALTER TABLE runs ADD COLUMN {name} {decl.replace('PRIMARY KEY', '')}")
            self._conn.execute("CREATE INDEX IF NOT EXISTS runs_status ON runs(status)")
            self._conn.execute("CREATE INDEX IF NOT EXISTS runs_base_key ON runs(base_key)")

    def _shadow_older_schema(self) -> None:
        # A read-only store cannot be migrated; a temporary table or view named runs (which SQLite finds before
        # the file's own) gives it the current columns instead, in memory.
        have = [r["name"] for r in self._conn.execute("PRAGMA main.table_info(runs)")]
        if not have:
            cols = ", ".join(f"{k} {v}" for k, v in _COLUMNS.items())
            self._conn.execute(f"CREATE TEMP TABLE runs ({cols})")
        elif set(COLUMNS) - set(have):
            cols = ", ".join(name if name in have else f"NULL AS {name}" for name in COLUMNS)
            self._conn.execute(f"CREATE TEMP VIEW runs AS SELECT {cols} FROM main.runs")

    def _set_wal(self) -> None:
        # Switching to WAL needs a moment alone with the file; a second process opening the store at the
        # same time can get "database is locked" at once (no busy wait for this pragma), so retry briefly.
        deadline = time.monotonic() + 30.0
        while True:
            try:
                if self._conn.execute("PRAGMA journal_mode").fetchone()[0] != "wal":
                    self._conn.execute("PRAGMA journal_mode=WAL")
                return
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

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
    def upsert(self, row: dict) -> bool:
        """Inserts or replaces the row with `row["key"]`; JSON columns accept dicts.

        A `done` row is only ever replaced by another `done` row. Returns whether the row was written.
        """
        unknown = set(row) - set(COLUMNS)
        if unknown:
            raise ValueError(f"Store.upsert: unknown columns {sorted(unknown)}")
        if row.get("status") not in STATUSES:
            raise ValueError(f"Store.upsert: status must be one of {STATUSES}, got {row.get('status')!r}")
        values = {k: (_json(v) if k in _JSON_COLUMNS else v) for k, v in row.items()}
        names = ", ".join(values)
        marks = ", ".join(f":{k}" for k in values)
        with self._tx():
            if row["status"] != "done" and self._status(row.get("key")) == "done":
                log.warning("Store.upsert: run %s is done; not replacing it with a %s row", row.get("key"),
                            row["status"])
                return False
            self._conn.execute(f"INSERT OR REPLACE INTO runs ({names}) VALUES ({marks})", values)
        return True

    def claim(self, row: dict, lease: Lease, *, stale_s: float = LEASE_S,
              retry_attempts: int | None = None) -> str:
        """Claims run `row["key"]` for `lease` in one transaction, unless it is finished or held elsewhere.

        Args:
            row: the run's identity columns (key, method, shape, ...); used when the run is new.
            lease: the claiming sweep.
            stale_s: a lease whose heartbeat is older than this many seconds is taken over.
            retry_attempts: reclaim a finished row (`failed`, or `done` for a sweep that reruns stored runs),
                but only if its `attempts` still equals this value (the value the caller saw when it decided to
                run it again), so that an outcome another sweep stored meanwhile is not run twice. None: a
                finished row stays as it is.

        Returns:
            "claimed" (new or retried run, now `running` under `lease`), "resumed" (a `running` row whose
            lease was not live, taken over), "held" (a live lease of another sweep holds it), "done" or
            "failed" (finished; untouched).
        """
        if not isinstance(lease, Lease):
            raise TypeError(f"Store.claim: lease must be a Lease, got {type(lease).__name__}")
        key = row["key"]
        # A cheap read first: polling sweeps ask again and again about runs another sweep holds, and
        # should not queue for the write lock each time. The decision is made again under the lock.
        outcome = self._claim_outcome(self._lease_row(key), lease, stale_s, retry_attempts)
        if outcome in ("held", "done", "failed"):
            return outcome
        with self._tx():
            cur = self._lease_row(key)
            outcome = self._claim_outcome(cur, lease, stale_s, retry_attempts)
            if outcome in ("held", "done", "failed"):
                return outcome
            now, started = time.time(), utc_now()
            lease_cols = {"lease_pid": lease.pid, "lease_host": lease.host, "lease_token": lease.token,
                          "heartbeat_at": now}
            if cur is None:
                ident = {k: (_json(v) if k in _JSON_COLUMNS else v) for k, v in row.items()
                         if k in COLUMNS and k not in _RESULT_COLUMNS and k not in lease_cols and k != "attempts"}
                ident.update(lease_cols, status="running", started_at=started, attempts=1)
                names, marks = ", ".join(ident), ", ".join(f":{k}" for k in ident)
                self._conn.execute(f"INSERT INTO runs ({names}) VALUES ({marks})", ident)
            else:
                cleared = ", ".join(f"{c}=NULL" for c in _RESULT_COLUMNS if c not in ("status", "started_at"))
                n = self._conn.execute(
                    f"UPDATE runs SET status='running', started_at=:started, {cleared}, lease_pid=:lease_pid, "
                    "lease_host=:lease_host, lease_token=:lease_token, heartbeat_at=:heartbeat_at, "
                    "base_key=COALESCE(base_key, :base_key), "
                    "attempts=attempts+1 WHERE key=:key AND (status!='done' OR attempts=:again)",
                    {**lease_cols, "started": started, "key": key, "base_key": row.get("base_key"),
                     "again": -1 if retry_attempts is None else retry_attempts}).rowcount
                if n != 1:  # cannot happen under the lock; the guard is what keeps done rows done
                    return "done"
        return outcome

    def _lease_row(self, key: str):
        return self._conn.execute("SELECT status, lease_pid, lease_host, lease_token, heartbeat_at, attempts "
                                  "FROM runs WHERE key=?", (key,)).fetchone()

    @staticmethod
    def _claim_outcome(cur, lease: Lease, stale_s: float, retry_attempts: int | None) -> str:
        if cur is None:
            return "claimed"
        if cur["status"] in ("done", "failed"):
            again = retry_attempts is not None and cur["attempts"] == retry_attempts
            return "claimed" if again else cur["status"]
        if cur["lease_token"] == lease.token:
            return "claimed"  # already ours
        return "held" if lease_live(cur, lease, stale_s) else "resumed"

    def heartbeat(self, lease: Lease) -> int:
        """Refreshes the heartbeat of every run `lease` holds; returns how many it holds."""
        with self._tx():
            return self._conn.execute("UPDATE runs SET heartbeat_at=? WHERE lease_token=? AND status='running'",
                                      (time.time(), lease.token)).rowcount

    def release(self, lease: Lease) -> int:
        """Frees the runs `lease` still holds (they stay `running`, for any sweep to take over at once)."""
        with self._tx():
            return self._conn.execute("UPDATE runs SET heartbeat_at=NULL WHERE lease_token=? AND status='running'",
                                      (lease.token,)).rowcount

    def mark_running(self, row: dict) -> str:
        """Claims `row` (identity columns) for this process (`claim` with one lease per process).

        Kept for callers without a lease of their own; a `done` row stays done.
        """
        return self.claim(row, _process_lease())

    def finish(self, key: str, *, status: str, error: str | None = None, metrics: dict | None = None,
               timings: dict | None = None, info: dict | None = None, peak_memory_mb: float | None = None,
               mesh_path: str | None = None, lease: Lease | None = None, code_deps: dict | None = None) -> bool:
        """Stores the outcome of the run `key` (status done or failed), with the hashes of the code it executed
        (`code_deps`) when known.

        Never replaces a `done` row. With `lease`, stores only while the run is `running` under that lease
        (a sweep whose run was taken over keeps out). Returns whether the outcome was stored.

        Raises:
            ValueError: bad status, or no run `key` in the store.
        """
        if status not in ("done", "failed"):
            raise ValueError(f"Store.finish: status must be 'done' or 'failed', got {status!r}")
        sql = ("UPDATE runs SET status=?, error=?, metrics_json=?, timings_json=?, info_json=?, "
               "peak_memory_mb=?, mesh_path=?, finished_at=?, code_deps=?, heartbeat_at=NULL "
               "WHERE key=? AND status!='done'")
        args = [status, error, _json(metrics), _json(timings), _json(info), peak_memory_mb, mesh_path, utc_now(),
                _json(code_deps), key]
        if lease is not None:
            sql += " AND status='running' AND lease_token=?"
            args.append(lease.token)
        with self._tx():
            if self._conn.execute(sql, args).rowcount == 1:
                return True
            current = self._status(key)
        if current is None:
            raise ValueError(f"Store.finish: no run with key {key}")
        log.warning("Store.finish: run %s is %s%s; not storing this %s outcome", key[:12], current,
                    " under another sweep's lease" if current == "running" else "", status)
        return False

    def set_metrics(self, key: str, metrics: dict) -> bool:
        """Replaces the metrics of the done run `key` (a rescore of its stored mesh); False if it is not done."""
        with self._tx():
            return self._conn.execute("UPDATE runs SET metrics_json=? WHERE key=? AND status='done'",
                                      (_json(metrics), key)).rowcount == 1

    def set_code_deps(self, key: str, deps: dict) -> bool:
        """Replaces the `code_deps` of run `key` (`eval.stored.migrate_records`); False if there is no such run."""
        with self._tx():
            return self._conn.execute("UPDATE runs SET code_deps=? WHERE key=?", (_json(deps), key)).rowcount == 1

    def delete(self, keys: Iterable[str]) -> int:
        """Deletes the given runs; returns how many were removed."""
        keys = list(keys)
        with self._tx():
            return sum(self._conn.execute("DELETE FROM runs WHERE key=?", (k,)).rowcount for k in keys)

    # -- reading
    def status(self, key: str) -> str | None:
        """The status of run `key`, or None if the store has no such run."""
        return self._status(key)

    def _status(self, key) -> str | None:
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

    def twins(self, base_key: str) -> list[dict]:
        """The done runs with `base_key` that carry `code_deps` (the same run under other code versions),
        latest first, JSON columns decoded."""
        sql = ("SELECT * FROM runs WHERE base_key=? AND status='done' AND code_deps IS NOT NULL "
               "ORDER BY finished_at DESC")
        return [_decode(r) for r in self._conn.execute(sql, (base_key,))]

    def code_deps_without(self, entry: str) -> list[dict]:
        """(key, method, code_deps) of the done runs whose `code_deps` do not name `entry`, JSON decoded."""
        sql = ("SELECT key, method, code_deps FROM runs WHERE status='done' AND code_deps IS NOT NULL "
               "AND instr(code_deps, ?) = 0")
        return [_decode(r) for r in self._conn.execute(sql, (json.dumps(entry),))]

    def code_deps_with(self, entry: str) -> list[dict]:
        """(key, method, code_deps) of the done runs whose `code_deps` name `entry`, JSON decoded."""
        sql = ("SELECT key, method, code_deps FROM runs WHERE status='done' AND code_deps IS NOT NULL "
               "AND instr(code_deps, ?) > 0")
        return [_decode(r) for r in self._conn.execute(sql, (json.dumps(entry),))]

    def counts(self) -> dict[str, int]:
        """Number of runs per status."""
        return {r[0]: r[1] for r in self._conn.execute("SELECT status, COUNT(*) FROM runs GROUP BY status")}

    def dataframe(self):
        """The whole table as a pandas DataFrame, with metric and timing dicts flattened into columns.

        Metric columns keep their names (e.g. `cd_p2s`); timing columns are prefixed `time_` and
        `time_s` is the method's total wall time in seconds; `cpu_s` its CPU seconds (all threads): the method's
        own `total_cpu` timing, else the worker's count (`info["method_cpu_s"]`), else None. `config_json`,
        `inputs_json` and `info_json` hold decoded dicts (`config` and `info` are aliases).
        """
        import pandas as pd

        records = []
        for r in self.rows():
            rec = {k: v for k, v in r.items() if k not in ("metrics_json", "timings_json")}
            rec["config"] = r["config_json"]
            rec["info"] = r["info_json"] or {}
            # A metric named like a run column (the metrics' own "seed", their sampling seed) must not replace
            # it: it is kept as metric_NAME.
            rec.update({f"metric_{k}" if k in r else k: v for k, v in (r["metrics_json"] or {}).items()})
            for k, v in (r["timings_json"] or {}).items():
                rec[f"time_{k}"] = v
            rec["time_s"] = (r["timings_json"] or {}).get("total")
            rec["cpu_s"] = (r["timings_json"] or {}).get("total_cpu", rec["info"].get("method_cpu_s"))
            records.append(rec)
        return pd.DataFrame.from_records(records, columns=None if records else list(COLUMNS) + ["time_s", "cpu_s"])


def _decode(row: sqlite3.Row) -> dict:
    out = dict(row)
    for k in _JSON_COLUMNS:
        if out.get(k) is not None:
            out[k] = json.loads(out[k])
    return out
