"""The bad-input matrix of the results store (issue 57, items 5 and 8): a damaged or read-only
`results.sqlite`, and `--plan`, which writes nothing.

Each refused case holds to the contract of `tests/test_bad_input_cli.py`: exit status 2, one non-empty line on
stderr naming the problem, nothing on stdout, and the case's folder byte-identical afterwards (the same files
with the same bytes: no `-wal` / `-shm` beside the store, no `WORK/inputs/`). The CLI is called in-process.

Placeholders in the argument lists: `{d}` is the case's folder, set up by the `d` fixture: `store/` holds a
real store (runs stored by `eval.store.Store`), `trunc/` a copy cut to half its bytes, `ro/` a copy whose file
is read-only and `rodir/` a copy in a read-only folder (as root, whom modes do not stop, `os.access` is made
to report them so, which is what the checks ask).
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from common import refused

from eval.cli import main
from eval.store import Store


def _write_store(path: Path, n: int = 300) -> None:
    """A store of `n` done runs, large enough to span many pages."""
    with Store(path) as store:
        for i in range(n):
            store.upsert({"key": f"{i:064x}", "method": "psr", "shape": "torus", "category": "closed",
                          "input_kind": "pointcloud", "seed": i, "status": "done", "inputs_json": {"n_points": 2000},
                          "metrics_json": {"cd_p2s": 1e-3 * i, "metrics_version": "old", "pad": "x" * 400},
                          "mesh_path": f"meshes/{i}.ply", "gt_hash": "ab" * 32})


def _make_files(d: Path) -> None:
    (d / "ok.yaml").write_text("methods: [psr]\nshapes: [torus]\nn_points: 2000\nmetric_samples: 2000\n")
    (d / "store").mkdir()
    _write_store(d / "store" / "results.sqlite")
    data = (d / "store" / "results.sqlite").read_bytes()
    for name in ("trunc", "ro", "rodir"):
        (d / name).mkdir()
    (d / "trunc" / "results.sqlite").write_bytes(data[:len(data) // 2])
    (d / "ro" / "results.sqlite").write_bytes(data)
    (d / "rodir" / "results.sqlite").write_bytes(data)


def _snapshot(d: Path) -> dict:
    """Every path under `d` with its full bytes (None for a folder)."""
    return {str(p.relative_to(d)): (p.read_bytes() if p.is_file() else None) for p in sorted(d.rglob("*"))}


@pytest.fixture
def d(tmp_path, monkeypatch):
    d = tmp_path / "case"
    d.mkdir()
    _make_files(d)
    monkeypatch.chdir(d)
    ro_file, ro_dir = d / "ro" / "results.sqlite", d / "rodir"
    ro_file.chmod(0o444)
    ro_dir.chmod(0o555)
    if os.access(ro_file, os.W_OK) or os.access(ro_dir, os.W_OK):
        real = os.access

        def access(path, mode, *a, **k):
            p = Path(path).absolute()
            if mode & os.W_OK and (p == ro_file or p == ro_dir):
                return False
            return real(path, mode, *a, **k)

        monkeypatch.setattr(os, "access", access)
    yield d
    ro_dir.chmod(0o755)
    ro_file.chmod(0o644)


def case(id_, argv, expect):
    return pytest.param(argv, (expect,) if isinstance(expect, str) else expect, id=id_)


CASES = [
    # a real store cut to half its bytes
    case("rescore-truncated-store", ["rescore", "--work", "{d}/trunc"],
         "results store {d}/trunc/results.sqlite: cannot be read (database disk image is malformed)"),
    case("rescore-all-truncated-store", ["rescore", "--all", "--work", "{d}/trunc"], "cannot be read"),
    case("rescore-plan-truncated-store", ["rescore", "--plan", "--db", "{d}/trunc/results.sqlite"], "cannot be read"),
    case("bench-truncated-store", ["bench", "{d}/ok.yaml", "--work", "{d}/trunc"],
         "trunc/results.sqlite: cannot be read"),
    case("bench-plan-truncated-store", ["bench", "{d}/ok.yaml", "--work", "{d}/trunc", "--plan"], "cannot be read"),
    case("reproduce-tables-report-only-truncated-store",
         ["reproduce-tables", "--report-only", "--work", "{d}/trunc", "-o", "{d}/rep"], "cannot be read"),
    # a read-only store file, or one in a read-only folder (SQLite writes -wal and -shm beside it)
    case("bench-read-only-store", ["bench", "{d}/ok.yaml", "--work", "{d}/ro"],
         "results store {d}/ro/results.sqlite: the store file is not writable"),
    case("bench-db-read-only-store", ["bench", "{d}/ok.yaml", "--work", "{d}/w", "--db", "{d}/ro/results.sqlite"],
         "the store file is not writable"),
    case("rescore-all-read-only-store", ["rescore", "--all", "--work", "{d}/ro"],
         "results store {d}/ro/results.sqlite: the store file is not writable"),
    case("rescore-read-only-store", ["rescore", "--work", "{d}/ro"], "the store file is not writable"),
    case("rescore-store-in-read-only-folder", ["rescore", "--all", "--work", "{d}/rodir"],
         "results store {d}/rodir/results.sqlite: folder {d}/rodir is not writable"),
    case("reproduce-tables-read-only-store",
         ["reproduce-tables", "--sweep", "{d}/ok.yaml", "--work", "{d}/ro", "-o", "{d}/rep"],
         "the store file is not writable"),
]


@pytest.mark.parametrize("argv,expect", CASES)
def test_bad_store_is_one_line_exit_2_and_changes_nothing(d, capsys, argv, expect):
    argv = [a.replace("{d}", str(d)) for a in argv]
    expect = [e.replace("{d}", str(d)) for e in expect]
    before = _snapshot(d)
    refused(capsys, argv, argv[0], *expect)
    assert _snapshot(d) == before, "the refused command changed the folder"


@pytest.mark.parametrize("work", ["w", "store", "ro"])
def test_bench_plan_writes_nothing(d, capsys, work):
    """`bench --plan` runs nothing and writes nothing: no GT cache under WORK/inputs/, no store, no -wal/-shm;
    a read-only store is fine for it."""
    before = _snapshot(d)
    assert main(["-q", "bench", str(d / "ok.yaml"), "--work", str(d / work), "--plan"]) == 0
    out = capsys.readouterr().out
    assert "1 runs, 0 stored, 1 to run" in out
    assert ("psr: 1 to run" in out) == (work != "w")  # per-method lines come from a store
    assert _snapshot(d) == before


def test_rescore_plan_reads_a_read_only_store(d, capsys):
    before = _snapshot(d)
    assert main(["-q", "rescore", "--work", str(d / "ro"), "--plan"]) == 0
    assert "300 without their mesh or GT on disk" in capsys.readouterr().out
    assert _snapshot(d) == before


def test_check_store_reads_a_store_another_process_holds_open(tmp_path):
    """While a sweep holds the store open (its -wal and -shm exist), the check reads it through SQLite's WAL,
    sees the runs committed there, and adds no file."""
    from eval.store import check_store

    db = tmp_path / "results.sqlite"
    _write_store(db, n=3)
    with Store(db) as held:
        held.upsert({"key": "f" * 64, "method": "psr", "shape": "torus", "category": "closed",
                     "input_kind": "pointcloud", "seed": 9, "status": "done"})
        names = sorted(p.name for p in tmp_path.iterdir())
        assert names == ["results.sqlite", "results.sqlite-shm", "results.sqlite-wal"]
        check_store(db, write=True)
        with Store(db, readonly=True) as reader:
            assert reader.status("f" * 64) == "done" and len(reader.rows()) == 4
        assert sorted(p.name for p in tmp_path.iterdir()) == names


def test_read_only_store_of_an_older_schema_reads_as_a_current_one(tmp_path):
    """`Store(readonly=True)` migrates nothing: a store without the newer columns, or an empty SQLite file,
    reads as a current store would (missing columns NULL, no runs) and its bytes stay as they were."""
    import sqlite3

    old = tmp_path / "old.sqlite"
    con = sqlite3.connect(old)
    con.execute("CREATE TABLE runs (key TEXT PRIMARY KEY, method TEXT, config_label TEXT, shape TEXT, "
                "category TEXT, input_kind TEXT, seed INTEGER, status TEXT)")
    con.execute("INSERT INTO runs VALUES ('k', 'psr', '', 'torus', 'closed', 'pointcloud', 0, 'done')")
    con.commit()
    con.close()
    empty = tmp_path / "empty.sqlite"
    empty.write_bytes(b"")
    before = _snapshot(tmp_path)
    with Store(old, readonly=True) as store:
        (row,) = store.rows()
        assert row["status"] == "done" and row["base_key"] is None and row["metrics_json"] is None
        assert store.twins("anything") == []
    with Store(empty, readonly=True) as store:
        assert store.rows() == [] and store.counts() == {}
    assert _snapshot(tmp_path) == before


def test_a_store_damaged_past_its_schema_is_refused(tmp_path):
    """The check reads the whole store (SQLite's quick_check), so damage past the schema is found too."""
    from eval.store import check_store

    db = tmp_path / "results.sqlite"
    _write_store(db)
    check_store(db, write=True)
    cut = tmp_path / "cut.sqlite"
    shutil.copyfile(db, cut)
    with open(cut, "r+b") as fh:  # garbage over a page in the middle: the schema on page 1 stays readable
        fh.seek(os.path.getsize(cut) // 2 // 4096 * 4096)
        fh.write(b"\xff" * 4096)
    with pytest.raises(ValueError, match="cut.sqlite: cannot be read"):
        check_store(cut, write=False)
