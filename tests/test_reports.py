"""Reports from a hand-made results store: per-class means, counts and failures match hand computations,
CSV keeps raw units, Markdown shows x1e-3, the paper's numbers sit beside our rows, Table 1 from an RE/FP row,
the whole report folder (with index.html) is written without temporary leftovers, DMesh recipes, the
training-curves figure, and the multi-view table's alias."""
from __future__ import annotations

import csv
import math

import pandas as pd
import pytest

from datasets.capture import gl_problem as _gl_problem
from eval.reports import paper_numbers, tables, write_reports
from eval.reports.labels import method_label
from eval.reports.recipes import recipe_markdown, recipe_rows
from eval.store import Store


#: The row names of the point-cloud DMesh presets (`eval.reports.labels`).
FAST = "dmesh [fast: crust + surface step, no gradient step]"
PAPER = "dmesh [paper: 1500 gradient steps]"

def _row(key, method, shape, category, status, cd_p2s=None, cd_l1=None, time_s=None, kind="pointcloud", seed=0,
         error=None, metrics=None, info=None):
    base = {"key": key, "method": method, "config_label": "", "shape": shape, "category": category,
            "input_kind": kind, "config_json": {}, "inputs_json": {"n_points": 1000, "metric_samples": 5000,
                                                                   "radius": 1.0},
            "seed": seed, "status": status, "error": error, "gt_hash": "0" * 64, "code_version": "test"}
    if status == "done":
        base.update(metrics_json=metrics or {"cd_p2s": cd_p2s, "cd_l1": cd_l1, "f_score": 0.5, "faces": 10},
                    timings_json={"total": time_s, "solve": time_s / 2}, info_json=info or {}, peak_memory_mb=1.0)
    return base


@pytest.fixture
def store_path(tmp_path):
    path = tmp_path / "work" / "results.sqlite"
    with Store(path) as s:
        for r in [
            _row("k1", "psr", "torus", "closed", "done", 1e-3, 7e-3, 2.0),
            _row("k2", "psr", "genus2", "closed", "done", 3e-3, 9e-3, 4.0),
            _row("k3", "psr", "trefoil", "closed", "failed", error="RuntimeError: boom"),
            _row("k4", "psr", "disc", "open", "done", 20e-3, 30e-3, 1.0),
            _row("k5", "udf_mc", "torus", "closed", "done", 2e-3, 8e-3, 0.5),
            _row("k6", "udf_mc", "disc", "open", "failed", error="ValueError: empty"),
            _row("k7", "tsdf", "torus", "closed", "done", 5e-3, 11e-3, 3.0, kind="multiview"),
        ]:
            s.upsert(r)
    return path


def test_store_round_trip_and_status_rules(tmp_path):
    with Store(tmp_path / "s.sqlite") as s:
        row = _row("a", "psr", "torus", "closed", "done", 1e-3, 2e-3, 1.0)
        identity = {k: v for k, v in row.items() if not k.endswith(("metrics_json", "timings_json", "info_json"))
                    and k not in ("status", "error", "peak_memory_mb")}
        s.mark_running(identity)
        assert s.status("a") == "running" and s.get("a")["started_at"]
        s.finish("a", status="done", metrics={"cd_p2s": 1e-3}, timings={"total": 1.0}, mesh_path="m.ply")
        got = s.get("a")
        assert got["status"] == "done" and got["metrics_json"] == {"cd_p2s": 1e-3} and got["finished_at"]
        assert s.counts() == {"done": 1} and s.status("zzz") is None
        with pytest.raises(ValueError):
            s.upsert({**identity, "status": "weird"})
        with pytest.raises(ValueError):
            s.finish("a", status="running")
        with pytest.raises(ValueError):
            s.upsert({**identity, "status": "done", "nope": 1})
    with Store(tmp_path / "s.sqlite") as s:  # persisted, WAL mode
        assert s.status("a") == "done"
        assert s._conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_table2_means_counts_and_paper_column(store_path):
    with Store(store_path) as s:
        df = s.dataframe()
    rows = {(r["method"], r["category"]): r for r in tables.table2(df, "pointcloud")}
    assert set(rows) == {("psr", "closed"), ("psr", "open"), ("udf_mc", "closed"), ("udf_mc", "open")}
    r = rows[("psr", "closed")]
    assert (r["n"], r["failed"]) == (2, 1)
    assert math.isclose(r["cd_p2s"], 2e-3) and math.isclose(r["cd_l1"], 8e-3) and math.isclose(r["time_s"], 3.0)
    assert math.isclose(r["fscore"], 0.5)
    assert r["paper_cd_l1"] == paper_numbers.TABLE2["pointcloud"]["PSR"]["closed"] == 7.15e-3
    assert r["paper_time_s"] == 10.61
    r = rows[("udf_mc", "open")]
    assert (r["n"], r["failed"], r["cd_p2s"], r["paper_cd_l1"]) == (0, 1, None, None)
    mv = tables.table2(df, "multiview")
    assert [(x["method"], x["category"], x["n"]) for x in mv] == [("tsdf", "closed", 1)]


def test_table2_puts_dev_and_test_apart_and_side_by_side(tmp_path):
    """Runs on dev shapes (Table 2's), test shapes and a user's own each make their own row per method and
    class, with n, mean and spread over shape-seed runs; the Markdown sets dev and test side by side."""
    with Store(tmp_path / "s.sqlite") as s:
        for key, shape, seed, cd in [("a", "torus", 0, 1e-3), ("b", "torus", 1, 3e-3), ("c", "sphere", 0, 5e-3),
                                     ("d", "csg", 0, 7e-3), ("e", "mine", 0, 9e-3)]:
            s.upsert(_row(key, "psr", shape, "closed", "done", cd, cd, 1.0, seed=seed))
        df = s.dataframe()
    rows = {r["split"]: r for r in tables.table2(df, "pointcloud")}
    assert set(rows) == {"dev", "test", "other"}
    assert rows["dev"]["n"] == 2 and math.isclose(rows["dev"]["cd_p2s"], 2e-3)
    assert math.isclose(rows["dev"]["cd_p2s_sd"], math.sqrt(2) * 1e-3)
    assert rows["test"]["n"] == 2 and math.isclose(rows["test"]["cd_p2s"], 6e-3)
    assert rows["other"]["n"] == 1 and rows["other"]["cd_p2s_sd"] is None
    wide = tables.side_by_side(list(rows.values()))
    assert len(wide) == 1 and math.isclose(wide[0]["dev_cd_p2s"], 2e-3) and wide[0]["test_n"] == 2
    md, _ = tables.write_table2(df, tmp_path / "rep", "pointcloud", n_samples=5000)
    text = md.read_text()
    assert "## Dev and test side by side" in text and "| psr | closed | 2 | 2.00 | 1.41 | 2 | 6.00 | 1.41 |" in text


def test_table2_shows_cpu_seconds_when_runs_recorded_them(tmp_path):
    """CPU seconds: the method's own `total_cpu` timing, else the worker's count in the run's info; the column
    appears once a row has them (means over the done runs that have them)."""
    with Store(tmp_path / "s.sqlite") as s:
        own = _row("a", "dmesh", "torus", "closed", "done", cd_p2s=1e-3, cd_l1=1e-3, time_s=10.0)
        own["timings_json"]["total_cpu"] = 7.0
        s.upsert(own)
        s.upsert(_row("b", "dmesh", "genus2", "closed", "done", cd_p2s=1e-3, cd_l1=1e-3, time_s=10.0,
                      seed=1, info={"method_cpu_s": 9.0}))
        s.upsert(_row("c", "psr", "torus", "closed", "done", cd_p2s=1e-3, cd_l1=1e-3, time_s=2.0))
        df = s.dataframe()
    rows = {r["method"]: r for r in tables.table2(df, "pointcloud")}
    assert rows[FAST]["cpu_s"] == 8.0 and rows["psr"]["cpu_s"] is None
    md, csv_path = tables.write_table2(df, tmp_path / "rep", "pointcloud", n_samples=5000)
    text = md.read_text()
    assert "| time (s) | CPU (s) |" in text and f"| {FAST} | closed | dev | 2 | 0 | 1.00 | 0 | 1.00 | 10.0 | 8.00 |" in text
    with open(csv_path) as fh:
        assert next(csv.DictReader(fh))["cpu_s"] == "8.0"


def test_table2_files_raw_csv_and_scaled_markdown(store_path, tmp_path):
    with Store(store_path) as s:
        df = s.dataframe()
    md, csv_path = tables.write_table2(df, tmp_path / "rep", "pointcloud", n_samples=5000)
    with open(csv_path) as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[:8] == ["method", "category", "split", "n", "failed", "cd_p2s", "cd_p2s_sd", "cd_l1"]
    psr_closed = next(r for r in rows if r["method"] == "psr" and r["category"] == "closed")
    assert math.isclose(float(psr_closed["cd_p2s"]), 2e-3) and psr_closed["failed"] == "1"
    assert float(psr_closed["paper_cd_l1"]) == 7.15e-3
    text = md.read_text()
    assert "| psr | closed | dev | 2 | 1 | 2.00 | 1.41 | 8.00 | 3.00 |" in text     # x1e-3 in the Markdown
    assert "x1e-3" in text and "max vertex norm 1" in text and "N = 5000" in text
    assert "| PSR | 7.15 | 26.94 | 67.18 | 10.61 |" in text            # the paper's Table 2, verbatim
    assert "RuntimeError: boom" in text                                # failures are listed, not dropped


def test_table1_from_an_re_fp_row(tmp_path):
    path = tmp_path / "s.sqlite"
    with Store(path) as s:
        s.upsert(_row("t1", "dmesh_mesh", "bun_zipper_res4_948", "mixed", "done", kind="mesh",
                      metrics={"re": 0.995, "fp": 0.002, "cd_p2s": 0.0}, info={"steps": 2000}, time_s=12.0))
        s.upsert(_row("t2", "psr", "torus", "closed", "done", 1e-3, 2e-3, 1.0))  # no RE/FP: not in Table 1
        df = s.dataframe()
    rows = tables.table1(df)
    assert rows == [{"shape": "bun_zipper_res4_948", "method": "dmesh_mesh", "RE": 0.995, "FP": 0.002,
                     "steps": 2000, "time_s": 12.0, "paper_RE": 0.9978, "paper_FP": 0.0}]
    md, csv_path = tables.write_table1(df, tmp_path / "rep")
    lines = csv_path.read_text().splitlines()
    assert lines[0] == "shape,method,RE,FP,steps,time_s,paper_RE,paper_FP"
    re_, fp = (float(x) for x in lines[1].split(",")[2:4])
    assert re_ == pytest.approx(99.5) and fp == pytest.approx(0.2)  # percent, as the issue asks
    text = md.read_text()
    assert "| bun_zipper_res4_948 | dmesh_mesh | 99.50 | 0.20 | 2000 | 12.0 | 99.78 | 0.00 |" in text
    assert "| Dragon | 99.72 | 0.55 |" in text


def test_empty_store_gives_empty_tables_not_errors(tmp_path):
    path = tmp_path / "s.sqlite"
    Store(path).close()
    written = write_reports(path, tmp_path / "rep", renders=False)
    names = sorted(p.name for p in written)
    assert names == sorted(["table2_pointcloud.md", "table2_pointcloud.csv", "table2_multiview.md",
                            "table2_multiview.csv", "table1.md", "table1.csv", "index.html", "ablation_weight.md",
                            "ablation_weight.csv", "ablation_quality.md", "ablation_quality.csv",
                            "recipes_size.md", "recipes_size.csv", "compact.md", "compact.csv", "checks.md",
                            "checks.csv"])
    assert "No point cloud runs" in (tmp_path / "rep" / "table2_pointcloud.md").read_text()
    assert "Runs with a monitored curve: 0; over 1.25x: 0." in (tmp_path / "rep" / "checks.md").read_text()


def test_write_reports_writes_everything_it_links(store_path, tmp_path):
    out = tmp_path / "rep"
    written = write_reports(store_path, out, renders=False)
    assert all(p.is_file() for p in written)
    assert (out / "figures" / "bars_pointcloud.png").is_file() and (out / "figures" / "bars_multiview.png").is_file()
    html = (out / "index.html").read_text()
    for p in written:
        if p.name != "index.html":
            assert str(p.relative_to(out)) in html, p
    assert "7.15" in html and "RuntimeError: boom" in html
    assert not list(out.rglob("*.tmp"))
    with pytest.raises(FileNotFoundError):
        write_reports(tmp_path / "missing.sqlite", tmp_path / "rep2")
    assert not (tmp_path / "rep2").exists()


def test_fmt_fixed_significant_digits():
    assert [tables.fmt(v) for v in (7.4213, 0.52709, 110.37, 1234.5, 0.0, None, float("nan"))] == \
        ["7.42", "0.527", "110", "1234", "0", "", ""]


@pytest.mark.skipif(_gl_problem() is not None, reason="no offscreen OpenGL (OSMesa / EGL) for pyrender")
def test_render_shows_the_object_both_sides():
    import numpy as np
    import trimesh

    from eval.reports import figures

    img = figures.render(mesh=trimesh.creation.icosphere(subdivisions=2), size=96)
    assert img.shape == (96, 96, 3) and img.dtype == np.uint8
    assert (img.min(axis=2) < 250).mean() > 0.3                      # the sphere covers the frame centre
    # An open sheet seen from its back is drawn (in the back-face colour), not culled away.
    sheet = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 2, 1], [0, 3, 2]])
    back = figures.render(mesh=sheet, size=96)
    assert (back.min(axis=2) < 250).mean() > 0.2


def test_ablation_tables_average_per_value_and_stay_out_of_table2(tmp_path):
    from eval.reports.ablation import ablation_rows

    path = tmp_path / "s.sqlite"
    with Store(path) as s:
        s.upsert(_row("p", "psr", "torus", "closed", "done", 1e-3, 7e-3, 2.0))
        for i, (lw, lq, shape, cd, faces) in enumerate([(1e-6, 0.0, "torus", 2e-3, 100),
                                                        (1e-6, 0.0, "bowl", 4e-3, 300),
                                                        (1e-4, 0.0, "torus", 9e-3, 50),
                                                        (0.0, 1e-2, "torus", 1e-3, 400)]):
            r = _row(f"a{i}", "dmesh", shape, "closed", "done", cd, cd, 10.0,
                     metrics={"cd_p2s": cd, "cd_l1": cd, "faces": faces, "aspect_ratio_mean": 1.5})
            r.update(config_label=f"lambda_quality={lq},lambda_weight={lw},steps_phase1=40",
                     config_json={"lambda_weight": lw, "lambda_quality": lq})
            s.upsert(r)
        df = s.dataframe()
    weight = ablation_rows(df, "weight")
    assert [(r["value"], r["n"]) for r in weight] == [(1e-6, 2), (1e-4, 1)]
    assert weight[0]["cd_p2s"] == pytest.approx(3e-3) and weight[0]["faces"] == pytest.approx(200)
    assert weight[0]["paper_cd"] == 7.48 and weight[1]["paper_faces"] == 1786
    quality = ablation_rows(df, "quality")
    assert [(r["value"], r["n"], r["paper_aspect_ratio"]) for r in quality] == [(1e-2, 1, 1.55)]
    write_reports(path, tmp_path / "rep", renders=False)
    assert [r["method"] for r in csv.DictReader(open(tmp_path / "rep" / "table2_pointcloud.csv"))] == ["psr"]
    assert "1e-06" in (tmp_path / "rep" / "ablation_weight.md").read_text()


def test_size_study_puts_runs_with_steps_on_the_fast_size_curve_and_stays_out_of_table2(tmp_path):
    from eval.reports.size import interpolate, size_rows

    path = tmp_path / "s.sqlite"
    with Store(path) as s:
        # The fast start on the torus at 2K, 8K and 80K faces, CD falling as 1 / sqrt(faces); the paper preset at
        # 4K faces and the fast start + steps at 2K; a plant with a paper run only (no size curve).
        for i, (label, faces, cd) in enumerate([("num_init=1000", 2000, 8e-3), ("num_init=4000", 8000, 4e-3),
                                                ("", 80000, 0.4e-3), ("preset=paper", 4000, 1e-3),
                                                ("num_init=1000,steps_phase1=200", 2000, 2e-3),
                                                ("num_init=1000,steps_phase1=200,tangent_weight=0.2", 2000, 1e-3)]):
            r = _row(f"t{i}", "dmesh", "torus", "closed", "done", metrics={"cd_p2s": cd, "cd_l1": cd, "faces": faces},
                     time_s=100.0 if label == "preset=paper" else 10.0)
            r.update(config_label=label)
            s.upsert(r)
        r = _row("pl", "dmesh", "plant", "mixed", "done", metrics={"cd_p2s": 2e-3, "faces": 1000}, time_s=50.0)
        r.update(config_label="preset=paper")
        s.upsert(r)
        r = _row("pf", "dmesh", "plant", "mixed", "failed", error="ValueError: the method returned an empty mesh")
        r.update(config_label="num_init=1000,steps_phase1=200")
        s.upsert(r)
        df = s.dataframe()
    assert interpolate([(2000, 8e-3), (8000, 4e-3)], 4000) == pytest.approx(8e-3 / math.sqrt(2))
    assert interpolate([(2000, 8e-3), (8000, 4e-3)], 1000) is None
    rows = {(r["shape"], r["recipe"]): r for r in size_rows(df)}
    assert sorted(rows) == [("plant", "paper preset"), ("torus", "fast start, 1000 seeds + 200 steps"),
                            ("torus", "fast start, 1000 seeds + 200 steps, tangent weight 0.2"),
                            ("torus", "paper preset")]
    assert rows["torus", "fast start, 1000 seeds + 200 steps, tangent weight 0.2"]["ratio"] == pytest.approx(8.0)
    paper = rows["torus", "paper preset"]
    assert paper["fast_cd_p2s_at_faces"] == pytest.approx(8e-3 / math.sqrt(2))
    assert paper["ratio"] == pytest.approx(8 / math.sqrt(2))
    assert paper["fast_sizes"] == "2000 8000 80000" and paper["fast_default_cd_p2s"] == pytest.approx(0.4e-3)
    assert rows["torus", "fast start, 1000 seeds + 200 steps"]["ratio"] == pytest.approx(4.0)
    assert rows["plant", "paper preset"]["ratio"] is None
    write_reports(path, tmp_path / "rep", renders=False)
    table2 = list(csv.DictReader(open(tmp_path / "rep" / "table2_pointcloud.csv")))
    assert sorted(r["method"] for r in table2) == [FAST, PAPER, PAPER]
    text = (tmp_path / "rep" / "recipes_size.md").read_text()
    assert ("| paper preset | closed | 1 | 5.66 |" in text
            and (tmp_path / "rep" / "figures" / "recipes_size.png").is_file())
    # A failed run has no CD: listed on its own, with its error.
    assert ("| plant | mixed | fast start, 1000 seeds + 200 steps | ValueError: the method returned an empty mesh |"
            in text.split("## Failed runs")[1])


def test_reports_take_the_latest_finished_run_over_a_rerun_left_running(tmp_path):
    from eval.reports import select_runs

    path = tmp_path / "s.sqlite"
    with Store(path) as s:
        old = _row("old", "psr", "torus", "closed", "done", 1e-3, 7e-3, 2.0)
        new = _row("new", "psr", "torus", "closed", "done", 2e-3, 8e-3, 2.0)
        left = _row("left", "psr", "torus", "closed", "running")
        for r, when in ((old, "2026-01-01T00:00:00"), (new, "2026-01-02T00:00:00"), (left, "2026-01-03T00:00:00")):
            r["started_at"] = when
            s.upsert(r)
        df = s.dataframe()
    assert select_runs(df)["key"].tolist() == ["new"]
    only_running = df[df["key"] == "left"]
    assert select_runs(only_running)["key"].tolist() == ["left"]
    assert tables.table2(only_running, "pointcloud") == []   # no class row of n = 0 for a run still going
    # In the list of runs it shows as unfinished: the report outlives the process that was running it.
    assert [r["status"] for r in tables.per_shape(only_running, "pointcloud")] == ["unfinished"]


def test_text_fields_show_empty_for_missing_values():
    from eval.reports.tables import text

    assert text("boom") == "boom"
    assert text(None) == "" and text(float("nan")) == ""  # pandas fills an empty text column with NaN


def test_recipe_rows_name_preset_kind_and_overrides():
    df = pd.DataFrame([
        {"method": "dmesh", "config_label": "", "input_kind": "pointcloud"},
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud"},
        {"method": "dmesh", "config_label": "lr=1e-05,preset=paper", "input_kind": "pointcloud"},
        {"method": "psr", "config_label": "", "input_kind": "pointcloud"},
        {"method": "dmesh_mv", "config_label": "preset=depth", "input_kind": "multiview"},
    ]).assign(status="done")
    rows = {r["method"]: r for r in recipe_rows(df, "pointcloud")}
    assert set(rows) == {FAST, PAPER, "dmesh [paper: 1500 gradient steps; lr=1e-05]"}
    assert rows[FAST]["preset"] == "fast" and rows[FAST]["kind"] == "initialisation"
    assert rows[PAPER]["kind"] == "gradient steps"
    assert rows["dmesh [paper: 1500 gradient steps; lr=1e-05]"]["recipe"].endswith("Overrides: lr=1e-05.")
    mv = recipe_rows(df, "multiview")
    assert [(r["method"], r["kind"]) for r in mv] == [(method_label("dmesh_mv", "preset=depth", "multiview"),
                                                       "initialisation")]
    md = recipe_markdown(mv)
    assert md.startswith("## DMesh recipes") and f"| {method_label('dmesh_mv', 'preset=depth', 'multiview')} | depth | initialisation |" in md
    assert recipe_markdown([]) == "" and recipe_rows(df.iloc[:0], "pointcloud") == []


def test_curves_figure_from_stored_run_info(tmp_path):
    from eval.reports.curves import curve_figure, curve_runs

    curve = [{"phase": 1, "step": 49, "loss": 0.02, "cd_p2s": 2e-3}, {"phase": 1, "step": 99, "loss": 0.015,
              "cd_p2s": 1.5e-3}, {"phase": 2, "step": 49, "loss": 0.014, "cd_p2s": 1.4e-3}]
    df = pd.DataFrame([
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud", "status": "done",
         "shape": "torus", "category": "closed", "info": {"curve": curve}},
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud", "status": "done",
         "shape": "zz", "category": "closed", "info": {"curve": curve}},     # second closed shape: not drawn
        {"method": "dmesh", "config_label": "", "input_kind": "pointcloud", "status": "done",
         "shape": "torus", "category": "closed", "info": {"curve": curve[:1]}},  # one point: no line
    ])
    runs = curve_runs(df)
    assert [(r["label"], r["shape"]) for r in runs] == [(PAPER, "torus")]
    from eval.reports.curves import _x

    assert _x(curve) == [50, 100, 150]
    out = curve_figure(runs, tmp_path / "c.png", "t")
    assert out.is_file() and out.stat().st_size > 1000
    assert curve_figure([], tmp_path / "none.png", "t") is None and not (tmp_path / "none.png").exists()


def test_multiview_table_shows_dmesh_mv_as_dmesh(tmp_path):
    from eval.reports import tables
    from eval.store import Store

    def row(key, method, kind, cd):
        return {"key": key, "method": method, "config_label": "", "shape": "torus", "category": "closed",
                "input_kind": kind, "config_json": {}, "inputs_json": {"views": 64, "metric_samples": 1000},
                "seed": 0, "status": "done", "error": None, "gt_hash": "0" * 64, "code_version": "test",
                "metrics_json": {"cd_p2s": cd, "cd_l1": cd}, "timings_json": {"total": 1.0}, "info_json": {},
                "peak_memory_mb": 1.0}

    with Store(tmp_path / "s.sqlite") as s:
        s.upsert(row("a", "dmesh_mv", "multiview", 2e-3))
        s.upsert(row("b", "tsdf", "multiview", 1e-3))
        s.upsert(row("c", "dmesh", "pointcloud", 3e-3))
        df = s.dataframe()
    mv = {r["method"]: r for r in tables.table2(df, "multiview")}
    fast = method_label("dmesh_mv", "", "multiview")
    assert fast == "dmesh [fast: 510 gradient steps]"  # dmesh_mv shows as dmesh
    assert set(mv) == {fast, "tsdf"} and mv[fast]["cd_p2s"] == 2e-3
    assert mv[fast]["paper_cd_l1"] is None   # the paper's "Ours" figures stand beside the paper preset only
    assert [r["method"] for r in tables.table2(df, "pointcloud")] == [FAST]
    md, _ = tables.write_table2(df, tmp_path / "rep", "multiview")
    assert "dmesh_mv" not in md.read_text() and f"| {fast} |" in md.read_text()


def test_multiview_settings_study_leaves_table2_for_its_own_report(tmp_path):
    """dmesh_mv runs with overrides beyond a preset are a settings study: out of Table 2, listed per shape beside
    the shape's fast run, with CD over TSDF fusion's on that shape."""
    from eval.reports.mv_settings import is_mv_settings_study, settings_rows, write_mv_settings

    def row(key, method, label, cd, shape="torus", category="closed"):
        return {**_row(key, method, shape, category, "done", cd, 2 * cd, 10.0, kind="multiview"),
                "config_label": label}

    with Store(tmp_path / "s.sqlite") as s:
        for r in [row("a", "dmesh_mv", "", 4e-3), row("b", "dmesh_mv", "preset=depth", 0.2e-3),
                  row("c", "dmesh_mv", "refine_seeds=[1000, 6000],steps_phase1=[150, 150, 150]", 2e-3),
                  row("d", "tsdf", "", 1e-3), row("e", "dmesh_mv", "", 6e-3, "plant", "mixed"),
                  row("f", "tsdf", "", 8e-3, "plant", "mixed")]:
            s.upsert(r)
        df = s.dataframe()
    assert list(df[is_mv_settings_study(df)]["key"]) == ["c"]
    rows = settings_rows(df)   # only the studied shape; its preset runs and the study run, best first
    assert [(r["shape"], r["settings"], r["over_tsdf"]) for r in rows] == [
        ("torus", "depth preset (as now)", pytest.approx(0.2)),
        ("torus", "refine_seeds=[1000, 6000],steps_phase1=[150, 150, 150]", pytest.approx(2.0)),
        ("torus", "fast preset (as now)", pytest.approx(4.0))]
    md, _ = write_mv_settings(df, tmp_path / "rep")
    assert "| torus | closed | refine_seeds=[1000, 6000],steps_phase1=[150, 150, 150] |" in md.read_text()
    write_reports(tmp_path / "s.sqlite", tmp_path / "all", renders=False)
    table2 = (tmp_path / "all" / "table2_multiview.md").read_text()
    assert "refine_seeds" not in table2 and "| dmesh [depth: crust of the lifted depth pixels + surface step, no " \
        "gradient step] | closed |" in table2
    assert (tmp_path / "all" / "multiview_fast.md").is_file()
    assert write_mv_settings(df[df["key"] != "c"], tmp_path / "none") == []


def test_recipe_rows_say_when_runs_are_older_than_the_recipe():
    """The recipe text is the current code's: finished rows whose code version is not the method's current one
    are counted beside it."""
    from eval.sweep import code_version, get_method

    now = code_version(get_method("dmesh"))
    df = pd.DataFrame([
        {"method": "dmesh", "config_label": "", "input_kind": "pointcloud", "code_version": now, "status": "done"},
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud", "code_version": now,
         "status": "done"},
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud", "code_version": "0.1+src.old",
         "status": "failed"},
        # left running by an interrupted sweep: neither in the tables nor in the count
        {"method": "dmesh", "config_label": "preset=paper", "input_kind": "pointcloud", "code_version": "0.1+src.old",
         "status": "running"},
    ])
    rows = {r["method"]: r for r in recipe_rows(df, "pointcloud")}
    assert "earlier code" not in rows[FAST]["recipe"]
    assert rows[PAPER]["recipe"].endswith(
        "(1 of its 2 runs were made by earlier code of the method, which may predate part of this recipe.)")
    one = recipe_rows(df.iloc[2:], "pointcloud")[0]["recipe"]
    assert one.endswith("(its one run was made by earlier code of the method, which may predate part of this recipe.)")


def test_checks_list_runs_that_lost_accuracy_after_their_last_step(tmp_path):
    """A run whose final CD is 2x its last monitored one is listed (in checks.md and index.html); one at 1.05x,
    one without a monitored CD and a failed run are checked or skipped, not listed."""
    from eval.reports.checks import GAP_RATIO, gap_rows, monitor_gap

    def curve(*cds):
        return [{"phase": 1, "step": 50 * i + 49, "loss": 0.01, "cd_p2s": c} for i, c in enumerate(cds)]

    path = tmp_path / "work" / "results.sqlite"
    with Store(path) as s:
        for r in [_row("bad", "dmesh", "mushroom", "mixed", "done", 2e-3, 5e-3, 9.0,
                       info={"curve": curve(3e-3, 1e-3)}),          # last monitored 1e-3, final 2e-3
                  _row("ok", "dmesh", "torus", "closed", "done", 1.05e-3, 5e-3, 9.0,
                       info={"curve": curve(1e-3)}),
                  _row("nomon", "dmesh", "bowl", "open", "done", 9e-3, 9e-3, 9.0,
                       info={"curve": [{"phase": 1, "step": 49, "loss": 0.01, "cd_p2s": None}]}),
                  _row("psr", "psr", "torus", "closed", "done", 1e-3, 5e-3, 1.0),
                  _row("failed", "dmesh", "plant", "mixed", "failed", error="RuntimeError: x")]:
            s.upsert(r)
        df = s.dataframe()
    rows, ratios = gap_rows(df)
    assert sorted(ratios) == pytest.approx([1.05, 2.0]) and [r["key"] for r in rows] == ["bad"]
    assert rows[0]["ratio"] == pytest.approx(2.0) and rows[0]["monitor_cd_p2s"] == pytest.approx(1e-3)
    assert monitor_gap({"curve": curve(1e-3)}, None) is None and monitor_gap({}, 1e-3) is None
    assert monitor_gap({"curve": curve(1e-3)}, GAP_RATIO * 1e-3)[0] == pytest.approx(GAP_RATIO)
    out = tmp_path / "rep"
    write_reports(path, out, renders=False)
    md = (out / "checks.md").read_text()
    assert "Runs with a monitored curve: 2; over 1.25x: 1. The others: 1.05-1.05." in md
    assert "mushroom" in md and "torus" not in md
    assert "| 2.00 |" in md
    assert list(csv.DictReader((out / "checks.csv").open()))[0]["key"] == "bad"
    assert "checks.md" in (out / "index.html").read_text()


def test_provenance_counts_runs_of_earlier_code_and_earlier_metrics(tmp_path):
    """Per table row: finished runs, those whose code version is not the method's now, and the done runs whose
    metrics version is not the metric code's now (or missing); the Table 2 Markdown carries the section."""
    from eval.reports.provenance import provenance_rows
    from eval.sweep import code_version, get_method, metrics_version

    code, metrics = code_version(get_method("psr")), metrics_version()
    rows = [
        _row("a", "psr", "torus", "closed", "done", 1e-3, 2e-3, 1.0,
             metrics={"cd_p2s": 1e-3, "metrics_version": metrics}),
        _row("b", "psr", "bowl", "open", "done", 1e-3, 2e-3, 1.0, metrics={"cd_p2s": 1e-3, "metrics_version": "old"}),
        _row("c", "psr", "plant", "mixed", "done", 1e-3, 2e-3, 1.0, metrics={"cd_p2s": 1e-3}),
        _row("d", "psr", "genus2", "closed", "failed", error="boom"),
        _row("e", "psr", "trefoil", "closed", "running"),
        _row("f", "tsdf", "torus", "closed", "done", 1e-3, 2e-3, 1.0, kind="multiview"),
    ]
    for r in rows[:4]:
        r["code_version"] = code
    path = tmp_path / "results.sqlite"
    with Store(path) as s:
        for r in rows:
            s.upsert(r)
        df = s.dataframe()
    got = provenance_rows(df, "pointcloud")
    assert got == [{"method": "psr", "runs": 4, "earlier_code": 0, "earlier_metrics": 2}]
    df.loc[df["key"] == "a", "code_version"] = "0+src.old"
    assert provenance_rows(df, "pointcloud")[0]["earlier_code"] == 1
    assert provenance_rows(df, "multiview") == [{"method": "tsdf", "runs": 1, "earlier_code": 1,
                                                  "earlier_metrics": 1}]
    md, _ = tables.write_table2(df, tmp_path / "rep", "pointcloud")
    text = md.read_text()
    assert "## Provenance" in text and "| psr | 4 | 1 | 2 |" in text


def test_compact_report_ratios_against_the_best_classical_row_and_stays_out_of_table2(tmp_path):
    """Matched budgets (`eval.reports.compact`): per split, class and budget, DMesh `compact`'s mean CD over
    the best classical row's; the floor beside it; none of these runs in Table 2 or Table 1."""
    from eval.reports.compact import budget_of, compact_rows, ratio_rows

    path = tmp_path / "s.sqlite"
    runs = [("d0", "dmesh", "faces=5000,preset=compact_steps", "torus", 1e-3, 0),
            ("d1", "dmesh", "faces=5000,preset=compact_steps", "torus", 3e-3, 1),
            ("p0", "psr_qem", "faces=5000", "torus", 4e-3, 0), ("p1", "psr_qem", "faces=5000", "torus", 4e-3, 1),
            ("b0", "bpa_qem", "faces=5000", "torus", 5e-3, 0),
            ("g0", "gt_qem", "faces=5000", "torus", 0.1e-3, 0), ("f0", "psr", "", "torus", 0.2e-3, 0)]
    with Store(path) as s:
        for key, method, label, shape, cd, seed in runs:
            r = _row(key, method, shape, "closed", "done", metrics={"cd_p2s": cd, "cd_l1": cd, "faces": 5000,
                                                                     "watertight": True, "components": 1},
                     time_s=10.0, seed=seed, kind="mesh" if method == "gt_qem" else "pointcloud")
            r.update(config_label=label)
            s.upsert(r)
        df = s.dataframe()
    assert budget_of("faces=5000,preset=compact_steps") == 5000 and budget_of("preset=paper") is None
    rows = compact_rows(df)
    assert [r["key"] for r in rows] == ["dmesh", "bpa_qem", "psr_qem", "gt_qem"]
    assert rows[0]["n"] == 2 and rows[0]["cd_p2s"] == pytest.approx(2e-3) and rows[0]["watertight"] == 2
    (ratio,) = ratio_rows(df)
    assert ratio["best_classical"] == "psr_qem [faces=5000]" and ratio["ratio"] == pytest.approx(0.5)
    assert ratio["floor_cd_p2s"] == pytest.approx(0.1e-3) and ratio["split"] == "dev" and ratio["n"] == 2
    # A classical row with fewer runs is compared on the runs both have: bpa_qem's seed 0 (5e-3) against
    # DMesh's seed 0 (1e-3), not against DMesh's mean over both seeds.
    only_bpa = df[df["method"] != "psr_qem"]
    (ratio,) = ratio_rows(only_bpa)
    assert ratio["best_classical"] == "bpa_qem [faces=5000]" and ratio["n"] == 1
    assert ratio["ratio"] == pytest.approx(0.2) and ratio["dmesh_cd_p2s"] == pytest.approx(1e-3)
    write_reports(path, tmp_path / "rep", renders=False)
    table2 = list(csv.DictReader(open(tmp_path / "rep" / "table2_pointcloud.csv")))
    assert [r["method"] for r in table2] == ["psr"]
    assert not list(csv.DictReader(open(tmp_path / "rep" / "table1.csv")))
    text = (tmp_path / "rep" / "compact.md").read_text()
    assert ("| dev | closed | 5000 | dmesh [compact_steps: 200 gradient steps; faces=5000] | 2 | 2.00 | "
            "psr_qem [faces=5000] | 4.00 | 0.50 | 0.100 |") in text, text
    assert (tmp_path / "rep" / "figures" / "compact.png").is_file()
