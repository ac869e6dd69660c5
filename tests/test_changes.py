"""`dmesh changes` (`eval.reports.changes`): which configurations' results moved between two sets of runs.
Hand-made runs, counted by hand."""
from __future__ import annotations

import csv

import pytest

from eval.export import export_store
from eval.reports.changes import compare_runs
from eval.store import Store


def _run(key, shape, cd, status="done", started="2026-01-02T00:00:00+00:00", corruption=None, version="new"):
    inputs = {"n_points": 1000, "metric_samples": 1000, **({"corruption": corruption} if corruption else {})}
    row = {"key": key, "method": "dmesh", "config_label": "", "shape": shape, "category": "closed",
           "input_kind": "pointcloud", "config_json": {}, "inputs_json": inputs, "seed": 0, "status": status,
           "gt_hash": "0" * 64, "code_version": f"0.1.0+src.{version}", "started_at": started,
           "finished_at": started}
    if status == "done":
        row.update(metrics_json={"cd_p2s": cd}, timings_json={"total": 1.0}, info_json={})
    else:
        row["error"] = "RuntimeError: boom"
    return row


OLD = "2026-01-01T00:00:00+00:00"
BEFORE = [_run("t0", "torus", 1e-3, started=OLD, version="old"), _run("g0", "genus2", 2e-3, started=OLD, version="old"),
          _run("b0", "bowl", 3e-3, started=OLD, version="old"), _run("p0", "plant", 4e-3, started=OLD, version="old"),
          _run("s0", "spot", None, status="failed", started=OLD, version="old"),
          _run("w0", "wavy_sheet", 1e-3, started=OLD, version="old", corruption={"noise": 0.01}),
          _run("gone", "mobius", 1e-3, started=OLD, version="old")]
AFTER = [_run("t1", "torus", 1.5e-3),            # worse by 50 %
         _run("g1", "genus2", 2.02e-3),          # within the tolerance
         _run("b1", "bowl", 1.5e-3),             # better by half
         _run("p1", "plant", None, status="failed"),
         _run("s1", "spot", 1e-3),               # failed before, done now
         _run("w1", "wavy_sheet", 1e-3, corruption={"noise": 0.02}),  # another input: not the same configuration
         _run("t2", "torus", 9e-3, started=OLD)]  # an older run of torus: the latest (t1) counts


def test_each_configuration_latest_run_against_its_latest_before():
    rows, counts = compare_runs(BEFORE, AFTER, tolerance=0.05)
    assert counts == {"compared": 5, "worse": 1, "better": 1, "failed now": 1, "done now": 1, "unchanged": 1,
                      "only before": 2, "only after": 1}
    assert [(r["change"], r["shape"]) for r in rows] == [("failed now", "plant"), ("worse", "torus"),
                                                          ("better", "bowl"), ("done now", "spot")]
    worse = rows[1]
    assert worse["ratio"] == pytest.approx(1.5) and worse["before"] == 1e-3 and worse["after"] == 1.5e-3
    assert (worse["code_before"], worse["code_after"]) == ("old", "new")
    assert rows[0]["error"] == "RuntimeError: boom"
    assert compare_runs(BEFORE, AFTER, tolerance=0.6)[1]["worse"] == 0   # 50 % is inside a 60 % tolerance
    with pytest.raises(ValueError, match="tolerance"):
        compare_runs(BEFORE, AFTER, tolerance=-1)


def test_changes_command_against_an_export_and_a_store(tmp_path, capsys):
    from eval.cli import main

    before, work = tmp_path / "before" / "results.sqlite", tmp_path / "work"
    with Store(before) as s:
        for r in BEFORE:
            s.upsert(r)
    with Store(work / "results.sqlite") as s:
        for r in AFTER:
            s.upsert(r)
    export = tmp_path / "before.jsonl.gz"
    export_store(before, export)
    out = tmp_path / "reports"
    assert main(["-q", "changes", "--before", str(export), "--work", str(work), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "worse: 1" in printed and "failed now" in printed
    text = (out / "changes.md").read_text()
    assert "| worse | dmesh |" in text and "1.5" in text and "| 1.500 |" in text
    with open(out / "changes.csv", newline="") as fh:
        assert [r["shape"] for r in csv.DictReader(fh)] == ["plant", "torus", "bowl", "spot"]
    assert main(["-q", "changes", "--before", str(export), "--work", str(tmp_path / "none"), "-o", str(out)]) != 0
    assert "no results store" in capsys.readouterr().err
