"""The robustness report (`eval.reports.robustness`) from a hand-made store, the compact store export
(`eval.export`) and `--report-only` on a clone without a store, and one tiny corrupted sweep end to end.

Means, counts and levels are checked against hand computations on the rows written here.
"""
from __future__ import annotations

import csv
import gzip
from pathlib import Path

import pytest

from eval.export import EXPORT_NAME, export_store, keep_tables, load_export, read_export
from eval.reports import robustness, robustness_figures, write_reports
from eval.reports.labels import method_label
from eval.store import Store

FAST = method_label("dmesh", "", "pointcloud")  # the default preset's row

REALISTIC = {"noise": 0.0025, "outliers": 0.01, "scan": 6, "normals": "estimated"}


def _row(key, method, shape, category, corruption, cd=None, time_s=1.0, faces=100, status="done", config="",
         started="2026-01-01T00:00:00+00:00", n_points=1000):
    inputs = {"radius": 1.0, "metric_samples": 1000, "n_points": n_points}
    if corruption is not None:
        inputs["corruption"] = corruption
    row = {"key": key, "method": method, "config_label": config, "shape": shape, "category": category,
           "input_kind": "pointcloud", "config_json": {}, "inputs_json": inputs, "seed": 0, "status": status,
           "gt_hash": "0" * 64, "code_version": "test", "started_at": started}
    if status == "done":
        row.update(metrics_json={"cd_p2s": cd, "cd_l1": 2 * cd, "faces": faces},
                   timings_json={"total": time_s}, info_json={}, peak_memory_mb=1.0, mesh_path=f"meshes/{key}.ply")
    else:
        row["error"] = "RuntimeError: boom"
    return row


ROWS = [
    # psr, closed: two shapes, clean and noise levels
    _row("a1", "psr", "torus", "closed", {}, 1e-3, faces=1000),
    _row("a2", "psr", "genus2", "closed", {}, 3e-3, faces=3000),
    _row("a3", "psr", "torus", "closed", {"noise": 0.005}, 5e-3),
    _row("a4", "psr", "genus2", "closed", {"noise": 0.005}, 7e-3),
    _row("a5", "psr", "torus", "closed", {"noise": 0.01}, status="failed"),
    _row("a6", "psr", "torus", "closed", {"density": 200}, 4e-3, faces=500),
    _row("a7", "psr", "torus", "closed", REALISTIC, 9e-3),
    _row("a8", "psr", "torus", "closed", {}, 2e-3, faces=200, config="depth=6"),  # a budget size: clean only
    # dmesh, closed
    _row("b1", "dmesh", "torus", "closed", {}, 1.5e-3),
    _row("b2", "dmesh", "torus", "closed", {"noise": 0.005}, 4e-3),
    # bpa, open
    _row("c1", "bpa", "bowl", "open", {}, 0.5e-3),
    _row("c2", "bpa", "bowl", "open", {"noise": 0.005}, 6e-3),
    # a plain run (no variant): Table 2's, not the robustness report's
    _row("p1", "psr", "torus", "closed", None, 1e-3),
]


@pytest.fixture
def db(tmp_path):
    path = tmp_path / "work" / "results.sqlite"
    with Store(path) as s:
        for r in ROWS:
            s.upsert(r)
    return path


def _df(db):
    from eval.reports import select_runs

    with Store(db) as s:
        return select_runs(s.dataframe())


def _read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_rows_per_method_class_corruption_and_level(db):
    rows = robustness.robustness_rows(_df(db))
    psr = {(r["corruption"], str(r["level"])): r for r in rows if r["method"] == "psr"}
    # noise: the clean runs at level 0, then 0.005 (two shapes), then 0.01 (failed only)
    assert [str(r["level"]) for r in rows if r["method"] == "psr" and r["corruption"] == "noise"] == \
        ["0.0", "0.005", "0.01"]
    assert psr[("noise", "0.0")]["n"] == 2 and psr[("noise", "0.0")]["cd_p2s"] == pytest.approx(2e-3)
    assert psr[("noise", "0.005")]["cd_p2s"] == pytest.approx(6e-3) and psr[("noise", "0.005")]["n"] == 2
    assert psr[("noise", "0.01")]["n"] == 0 and psr[("noise", "0.01")]["failed"] == 1
    assert psr[("noise", "0.01")]["cd_p2s"] is None
    # density: clean level = n_points first, then the lower density
    assert [r["level"] for r in rows if r["method"] == "psr" and r["corruption"] == "density"] == [1000, 200]
    real = [r for r in rows if r["method"] == "psr" and r["corruption"] == "realistic_scan"]
    assert len(real) == 1 and real[0]["cd_p2s"] == pytest.approx(9e-3)
    assert real[0]["level"] == "noise=0.0025,normals=estimated,outliers=0.01,scan=6"
    # the budget config ran on clean input only: no corruption rows; the plain run is not counted
    assert not any(r["method"] == "psr [depth=6]" for r in rows)
    assert {r["method"] for r in rows} == {"psr", FAST, "bpa"}
    bpa = [r for r in rows if r["method"] == "bpa"]
    assert {r["category"] for r in bpa} == {"open"} and len(bpa) == 2


def test_plot_levels_are_in_severity_order_whichever_method_comes_first():
    """A method run on fewer levels (a study at one noise level) must not put its levels first on the x axis:
    clean first, then mildest to harshest (views: most first)."""
    def rows(method, levels, clean):
        return [{"method": method, "level": v, "setting": "clean" if v == clean else "x"} for v in levels]

    noise = rows("a", [0.0, 0.005], 0.0) + rows("b", [0.0, 0.0025, 0.005, 0.01], 0.0)
    assert robustness_figures.plot_levels(noise, "depth_noise") == [0.0, 0.0025, 0.005, 0.01]
    views = rows("a", [64, 8], 64) + rows("b", [64, 16, 8], 64)
    assert robustness_figures.plot_levels(views, "views") == [64, 16, 8]


def test_dmesh_ratio_against_the_best_other_method(db):
    """Each DMesh preset against the best of the other methods; a study's overrides get no row of their own."""
    with Store(db) as s:
        s.upsert(_row("b3", "dmesh", "torus", "closed", {"noise": 0.005}, 2e-3, config="preset=noisy"))
        s.upsert(_row("b4", "dmesh", "torus", "closed", {"noise": 0.005}, 1e-3, config="preset=noisy,smooth_k=60"))
    ratios = robustness.dmesh_ratios(robustness.robustness_rows(_df(db)))
    at = {x["dmesh"]: x for x in ratios if x["corruption"] == "noise" and x["level"] == 0.005}
    noisy = method_label("dmesh", "preset=noisy", "pointcloud")
    assert set(at) == {FAST, noisy}
    # DMesh ran on the torus only: psr is compared on the torus alone (5e-3), not on its class mean (6e-3)
    assert at[FAST]["best"] == "psr" and at[FAST]["best_cd_p2s"] == pytest.approx(5e-3)
    assert at[FAST]["n"] == 1 and at[FAST]["ratio"] == pytest.approx(4e-3 / 5e-3)
    assert at[noisy]["ratio"] == pytest.approx(2e-3 / 5e-3)
    assert robustness._DMESH_PRESET.match(method_label("dmesh_mv", "init_preset=noisy,preset=depth", "multiview"))
    r0 = next(x for x in ratios if x["corruption"] == "noise" and x["level"] == 0.0)
    assert r0["dmesh_cd_p2s"] == pytest.approx(1.5e-3) and r0["best"] == "psr"


def test_dmesh_is_compared_with_the_others_on_the_same_preprocessed_input():
    """A pre-processed DMesh row meets the best other method on the same pre-processed input, never a raw one."""
    def row(label, cd):
        return {"input": "pointcloud", "category": "closed", "corruption": "noise", "level": 0.01,
                "method": label, "per_shape": {"torus": cd}}

    raw, pre = FAST, method_label("dmesh", "+outliers+smooth", "pointcloud")
    assert robustness.preprocess_tag(pre) == "+outliers+smooth" and robustness.preprocess_tag(raw) == ""
    ratios = robustness.dmesh_ratios([row(raw, 4e-3), row("psr", 8e-3), row(pre, 2e-3),
                                      row("psr [+outliers+smooth]", 1e-3)])
    got = {r["dmesh"]: (r["best"], r["ratio"]) for r in ratios}
    assert got == {raw: ("psr", 0.5), pre: ("psr [+outliers+smooth]", 2.0)}


def test_budget_rows_hold_configs_and_densities(db):
    rows = robustness.budget_rows(_df(db))
    psr = {(r["config"], r["density"]): r for r in rows if r["method"] == "psr"}
    assert set(psr) == {("default", 1000), ("default", 200), ("depth=6", 1000)}
    assert psr[("default", 1000)]["faces"] == pytest.approx(2000) and psr[("depth=6", 1000)]["faces"] == 200
    # Size knobs join the method's line; another recipe is a series of its own.
    assert robustness._budget_method("dmesh", "num_init=5000") == "dmesh"
    assert robustness._budget_method("psr", "") == "psr"
    assert robustness._budget_method("dmesh", "preset=noisy") == "dmesh [preset=noisy]"
    assert robustness._budget_method("nie", "epochs=600,grid=96") == "nie"


def test_report_files_and_columns(db, tmp_path):
    out = tmp_path / "rep"
    paths, body = robustness.write_robustness(_df(db), out, db, db.parent, renders=False)
    rows = _read_csv(out / "robustness.csv")
    for col in ("method", "category", "corruption", "level", "cd_p2s", "time_s"):
        assert col in rows[0]
    noisy = next(r for r in rows if r["method"] == "psr" and r["corruption"] == "noise" and r["level"] == "0.005")
    assert float(noisy["cd_p2s"]) == pytest.approx(6e-3) and noisy["n"] == "2"
    assert (out / "figures" / "robustness_pointcloud.png").is_file()
    assert (out / "figures" / "robustness_budget_pointcloud.png").is_file()
    md = (out / "robustness.md").read_text()
    assert "| pointcloud | dev | psr | closed | noise | 0.005 | 2 | 0 | 6.00 |" in md and "DMesh / best" in md
    assert all(p.is_file() for p in paths) and "<img" in body
    assert not list(out.rglob("*.tmp"))


def test_write_reports_keeps_robustness_runs_out_of_table2(db, tmp_path):
    out = tmp_path / "rep"
    write_reports(db, out, renders=False)
    t2 = _read_csv(out / "table2_pointcloud.csv")
    assert [(r["method"], r["n"]) for r in t2] == [("psr", "1")]  # the plain run only
    assert (out / "robustness.csv").is_file() and "Robustness" in (out / "index.html").read_text()


def test_export_round_trip_latest_only_and_same_bytes(db, tmp_path):
    with Store(db) as s:  # an older run of a configuration the store holds again: not exported
        s.upsert(_row("old", "psr", "torus", "closed", {}, 9.9, started="2025-01-01T00:00:00+00:00"))
        s.upsert({**_row("run", "psr", "plant", "mixed", {}, 1.0), "status": "running"})
    a, b = tmp_path / "a.jsonl.gz", tmp_path / "b.jsonl.gz"
    assert export_store(db, a) == len(ROWS) and export_store(db, b) == len(ROWS)
    assert a.read_bytes() == b.read_bytes()
    runs = read_export(a)
    assert sorted(r["key"] for r in runs) == sorted(r["key"] for r in ROWS)
    copy = tmp_path / "copy" / "results.sqlite"
    load_export(a, copy, mesh_root=tmp_path / "work")
    with Store(db) as s1, Store(copy) as s2:
        for r in ROWS:
            x, y = s1.get(r["key"]), s2.get(r["key"])
            for col in ("status", "metrics_json", "timings_json", "inputs_json", "config_label", "category"):
                assert x[col] == y[col], col
        assert s2.get("a1")["mesh_path"] == str(tmp_path / "work" / "meshes" / "a1.ply")


def test_broken_exports_are_one_line_errors(tmp_path):
    p = tmp_path / "x.jsonl.gz"
    for content, match in ((b"not gzip", "cannot be read"), (gzip.compress(b'{"format": "other"}\n'), "header"),
                           (gzip.compress(b'{"format": "dmesh-harness runs", "version": 1, "runs": 2}\n{"key": "a", '
                                          b'"status": "done"}\n'), "truncated")):
        p.write_bytes(content)
        with pytest.raises(ValueError, match=match) as info:
            read_export(p)
        assert "\n" not in str(info.value)


def test_report_only_on_a_clone_reads_the_export_and_keeps_figures(db, tmp_path, capsys):
    from eval.cli import main

    reports = tmp_path / "reports"
    export_store(db, reports / EXPORT_NAME)
    figure = reports / "figures" / "renders_pointcloud_torus.png"
    figure.parent.mkdir(parents=True)
    figure.write_bytes(b"committed render")  # its meshes are not on this clone: it must stay as it is
    rc = main(["-q", "reproduce-tables", "--report-only", "--work", str(tmp_path / "fresh"), "-o", str(reports)])
    assert rc == 0, capsys.readouterr().err
    assert [r["method"] for r in _read_csv(reports / "table2_pointcloud.csv")] == ["psr"]
    assert len(_read_csv(reports / "robustness.csv")) > 5
    assert figure.read_bytes() == b"committed render"
    assert not (tmp_path / "fresh" / "results.sqlite").exists()
    # A second pass gives the same files, index.html included (it names the export and the newest run's time,
    # not the temporary store or the time of the pass): a fresh clone reproduces the committed reports.
    first = {p: p.read_bytes() for p in sorted(reports.rglob("*")) if p.is_file()}
    assert f"from <code>{reports / EXPORT_NAME}</code>" in (reports / "index.html").read_text()
    rc = main(["-q", "reproduce-tables", "--report-only", "--work", str(tmp_path / "fresh"), "-o", str(reports)])
    assert rc == 0, capsys.readouterr().err
    assert {p: p.read_bytes() for p in sorted(reports.rglob("*")) if p.is_file()} == first


def test_report_only_without_store_or_export_is_one_line_error(tmp_path, capsys):
    from eval.cli import main

    rc = main(["-q", "reproduce-tables", "--report-only", "--work", str(tmp_path / "w"), "-o", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "no store export" in err and len(err.splitlines()) == 1


def test_a_report_pass_never_empties_a_committed_table(tmp_path):
    out = tmp_path / "reports"
    out.mkdir()
    (out / "table1.csv").write_text("shape,method,RE\nbunny,dmesh_fit,99.0\n")
    (out / "table1.md").write_text("# committed\n")
    with keep_tables(out):
        write_reports(_empty_store(tmp_path), out, renders=False)
    assert (out / "table1.md").read_text() == "# committed\n" and "bunny" in (out / "table1.csv").read_text()
    assert (out / "table2_pointcloud.csv").is_file()  # tables that had no rows before are written as usual


def _empty_store(tmp_path) -> Path:
    path = tmp_path / "empty" / "results.sqlite"
    with Store(path):
        pass
    return path


def test_tiny_corrupted_sweep_end_to_end(tmp_path):
    """A real sweep: ball pivoting on 2000-point clouds of a sphere, clean, noisy and with outliers."""
    pytest.importorskip("open3d")
    import numpy as np

    from eval.runner import RunnerConfig, input_path, prepare_gt, run_sweep
    from eval.sweep import Sweep, resolve_shape

    sweep = Sweep(methods=("bpa",), shapes=("sphere",), n_points=2000, metric_samples=2000,
                  variants=[{}, {"noise": 0.01}, {"outliers": 0.05}])
    summary = run_sweep(sweep, RunnerConfig(work=str(tmp_path / "w")))
    assert summary.done == 3 and summary.failed == 0
    with Store(summary.db) as s:
        rows = {r["key"]: r for r in s.rows()}
    specs = {k: rows[k] for k in summary.keys}
    clean = next(r for r in specs.values() if r["inputs_json"]["corruption"] == {})
    noisy = next(r for r in specs.values() if r["inputs_json"]["corruption"] == {"noise": 0.01})
    assert noisy["metrics_json"]["cd_p2s"] > clean["metrics_json"]["cd_p2s"]
    shape, _ = prepare_gt(resolve_shape("sphere"), tmp_path / "w")
    with np.load(input_path(tmp_path / "w", shape, "pointcloud", noisy["inputs_json"], 0)) as z, \
            np.load(input_path(tmp_path / "w", shape, "pointcloud", clean["inputs_json"], 0)) as c:
        d = z["points"].astype(np.float64) - c["points"]  # the noisy cloud is the clean one, displaced
        assert len(d) == 2000 and abs(d.std() / 0.01 - 1) < 0.05
    robustness.write_robustness(_df(Path(summary.db)), tmp_path / "rep", summary.db, tmp_path / "w", renders=False)
    got = _read_csv(tmp_path / "rep" / "robustness.csv")
    assert {(r["corruption"], r["level"]) for r in got} == {("noise", "0"), ("noise", "0.01"), ("outliers", "0"),
                                                            ("outliers", "0.05")}


def test_the_ci_subset_runs_every_method_on_every_corruption_and_each_one_costs_accuracy(tmp_path):
    """`dmesh robustness --quick` (eval/sweeps/robustness_small.yaml), the robustness sweeps' CI subset, end to
    end: every run finishes; the report has a row per method, class, corruption and level, its line plots and
    the realistic-scan renders; and every corruption makes every method's mesh farther from the GT than the
    clean input's (so the corrupted inputs reach the methods)."""
    pytest.importorskip("open3d")
    import subprocess
    import sys

    from eval.sweep import Sweep

    repo = Path(__file__).resolve().parents[1]
    sweep = Sweep.from_yaml(repo / "eval" / "sweeps" / "robustness_small.yaml")
    work, rep = tmp_path / "w", tmp_path / "rep"
    # Its own process, as a user runs it: the local pool forks its workers, and a fork of this long-lived
    # test process (with the threads of every library the earlier tests started) can hang or crash.
    done = subprocess.run([sys.executable, "-m", "eval.cli", "-q", "robustness", "--quick", "--jobs", "2",
                           "--work", str(work), "-o", str(rep)], cwd=repo, capture_output=True, text=True,
                          timeout=1800)
    assert done.returncode == 0, done.stderr[-2000:]
    with Store(work / "results.sqlite") as s:
        statuses = [r["status"] for r in s.rows()]
    assert statuses and set(statuses) == {"done"}
    got = _read_csv(rep / "robustness.csv")
    cd = {(r["method"], r["category"], r["corruption"], r["level"]): float(r["cd_p2s"]) for r in got}
    methods = {"dmesh": method_label("dmesh", "preset=tiny", "pointcloud")}
    for name in sweep.methods:
        label = methods.get(name, name)
        kinds = ("depth_noise",) if name == "tsdf" else ("noise", "outliers")
        for category in ("closed", "open"):
            for kind in kinds:
                clean = cd[(label, category, kind, "0")]
                worse = [v for (m, c, k, lv), v in cd.items() if (m, c, k) == (label, category, kind) and lv != "0"]
                assert worse and min(worse) > clean, (label, category, kind)
            if name != "tsdf":
                scan = [v for (m, c, k, _), v in cd.items() if (m, c, k) == (label, category, "realistic_scan")]
                assert len(scan) == 1 and scan[0] > cd[(label, category, "noise", "0")], (label, category)
    for name in ("robustness_pointcloud", "robustness_multiview", "robustness_scan_torus", "robustness_scan_bowl"):
        assert (rep / "figures" / f"{name}.png").stat().st_size > 0, name


def test_import_store_loads_the_export_and_keeps_what_the_store_has(db, tmp_path, capsys):
    """`dmesh import-store`: a fresh work folder gets every exported run; a second import adds nothing, and a
    run the store already holds is not overwritten by the export's."""
    from eval.cli import main

    export = tmp_path / "runs.jsonl.gz"
    export_store(db, export)
    work = tmp_path / "fresh"
    assert main(["-q", "import-store", "--work", str(work), "-i", str(export)]) == 0
    assert f"loaded {len(ROWS)} runs" in capsys.readouterr().out
    with Store(work / "results.sqlite") as s:
        assert sorted(r["key"] for r in s.rows()) == sorted(r["key"] for r in ROWS)
        s.upsert({**s.get(ROWS[0]["key"]), "metrics_json": {"cd_p2s": 42.0}})
    assert main(["-q", "import-store", "--work", str(work), "-i", str(export)]) == 0
    assert "loaded 0 runs" in capsys.readouterr().out
    with Store(work / "results.sqlite") as s:
        assert s.get(ROWS[0]["key"])["metrics_json"] == {"cd_p2s": 42.0}
    assert main(["-q", "import-store", "--work", str(work), "-i", str(tmp_path / "missing.gz")]) != 0
    assert "no store export" in capsys.readouterr().err


def test_noise_rows_show_what_the_default_presets_measured_and_chose(db, tmp_path):
    """The calibration section: per corruption and level, the noise ratio DMesh's default runs recorded (min,
    max), how many smoothed and how many were made again after a shredded first mesh; runs without the figure
    (older code) and other presets are left out."""
    def dm(key, shape, corruption, info, config=""):
        row = _row(key, "dmesh", shape, "closed", corruption, 1e-3, config=config)
        return {**row, "info_json": info}

    with Store(db) as s:
        s.upsert({**dm("n1", "torus", {"noise": 0.005}, {"noise_ratio": 0.2, "smooth_k": 120}),
                  "metrics_json": {"cd_p2s": 1e-3, "faces": 100, "components": 3}})
        s.upsert(dm("n2", "genus2", {"noise": 0.005}, {"noise_ratio": 0.08, "smooth_k": 120,
                                                       "fragmented_attempt": {"boundary_edges_per_face": 0.4}}))
        s.upsert(dm("n3", "torus", {"density": 200}, {"noise_ratio": 0.05, "smooth_k": 0}))
        s.upsert(dm("n4", "genus2", {"density": 200}, {"noise_ratio": 0.07}))  # older code: no choice recorded
        s.upsert(dm("n5", "torus", {"noise": 0.01}, {"noise_ratio": 0.3, "smooth_k": 120}, config="preset=noisy"))
    rows = {(r["corruption"], r["level"]): r for r in robustness.noise_rows(_df(db))}
    assert set(rows) == {("noise", 0.005), ("density", 200)}
    assert (rows[("noise", 0.005)]["ratio_min"], rows[("noise", 0.005)]["ratio_max"]) == (0.08, 0.2)
    assert rows[("noise", 0.005)]["smoothed"] == "2 of 2" and rows[("density", 200)]["smoothed"] == "0 of 1"
    assert rows[("noise", 0.005)]["redone"] == "1 of 2" and rows[("density", 200)]["redone"] == "0 of 1"
    assert rows[("density", 200)]["n"] == 2
    robustness.write_robustness(_df(db), tmp_path / "rep", db, db.parent, renders=False)
    md = (tmp_path / "rep" / "robustness.md").read_text()
    assert "## How noisy DMesh found each input" in md
    assert "| pointcloud | noise | 0.005 | 2 | 0.080 | 0.200 | 2 of 2 | 1 of 2 |" in md
    # The main table shows the mean components of the runs that counted them.
    import pandas as pd

    table = pd.read_csv(tmp_path / "rep" / "robustness.csv")
    noisy = table[(table["corruption"] == "noise") & (table["level"].astype(str) == "0.005")
                  & (table["method"] == FAST)]
    assert list(noisy["components"]) == [3]
    # The multi-view depth start smooths from the pool (preset "fast", pool_k > 0), or with `noisy` before it.
    assert robustness._measured_noise("multiview", {"init_depth": {"noise_ratio": 0.2, "preset": "fast",
                                                                   "pool_k": 500}}) == (0.2, True)
    assert robustness._measured_noise("multiview", {"init_depth": {"noise_ratio": 0.2, "preset": "noisy"}}) \
        == (0.2, True)
    assert robustness._measured_noise("multiview", {"init_depth": {"noise_ratio": 0.01, "preset": "fast",
                                                                   "pool_k": 0}}) == (0.01, False)
    assert robustness._made_again("multiview", {"init_depth": {"redone": True}}) is True
    assert robustness._made_again("multiview", {"init_depth": {"redone": False}}) is False
    assert robustness._made_again("multiview", {"init_depth": {"preset": "fast"}}) is None  # older code
    assert robustness._made_again("pointcloud", {"smooth_k": 120}) is False


def test_capture_size_levels_take_the_clean_level_from_a_clean_run_whatever_the_store_order(tmp_path):
    """A views variant's own input settings hold its views; the clean level (and the row labelled clean) must come
    from the clean run even when a variant was stored first (as after an import)."""
    rows = []
    for key, views, corruption, cd in (("v8", 8, {"views": 8}, 3e-3), ("v16", 16, {"views": 16}, 2e-3),
                                       ("v64", 64, {}, 1e-3)):
        r = _row(key, "tsdf", "torus", "closed", corruption, cd)
        r["input_kind"] = "multiview"
        r["inputs_json"]["views"] = views
        rows.append(r)
    path = tmp_path / "results.sqlite"
    with Store(path) as s:
        for r in rows:
            s.upsert(r)
    got = [r for r in robustness.robustness_rows(_df(path)) if r["corruption"] == "views"]
    assert [r["level"] for r in got] == [64, 16, 8]
    assert [r["setting"] for r in got] == ["clean", "views=16", "views=8"]


def test_plot_panels_compare_methods_on_the_shapes_they_all_ran():
    """A study on one shape beside a sweep on two: the panel compares both on the shared shape only."""
    two = {"method": "depth", "level": 0.005, "cd_p2s": 2.0, "per_shape": {"torus": 1.0, "genus2": 3.0}}
    one = {"method": "refine", "level": 0.005, "cd_p2s": 0.8, "per_shape": {"torus": 0.8}}
    value, common = robustness_figures.matched_values([two, one])
    assert common == ["torus"] and value[id(two)] == 1.0 and value[id(one)] == 0.8
    same = {"method": "tsdf", "level": 0.005, "cd_p2s": 5.0, "per_shape": {"torus": 4.0, "genus2": 6.0}}
    value, common = robustness_figures.matched_values([two, same])
    assert common is None and value[id(two)] == 2.0 and value[id(same)] == 5.0   # same shapes: the means


def test_test_split_shapes_get_rows_of_their_own(tmp_path):
    """A scan of a test-split shape (eval/sweeps/test_scan.yaml) is not averaged into the dev shapes' row of its
    class: the rows and the DMesh ratios carry the split."""
    path = tmp_path / "work" / "results.sqlite"
    extra = [_row("t1", "psr", "sphere", "closed", {"scan": 6}, 8e-3), _row("t2", "dmesh", "sphere", "closed",
                                                                           {"scan": 6}, 2e-3),
             _row("d1", "psr", "torus", "closed", {"scan": 6}, 4e-3), _row("d2", "dmesh", "torus", "closed",
                                                                          {"scan": 6}, 3e-3)]
    with Store(path) as s:
        for r in extra:
            s.upsert(r)
    rows = [r for r in robustness.robustness_rows(_df(path)) if r["corruption"] == "scan" and r["level"] == 6]
    by = {(r["split"], r["method"]): r for r in rows}
    assert by[("test", "psr")]["cd_p2s"] == 8e-3 and by[("dev", "psr")]["cd_p2s"] == 4e-3
    assert by[("test", "psr")]["n"] == 1 == by[("dev", "psr")]["n"]
    ratios = {r["split"]: r["ratio"] for r in robustness.dmesh_ratios(rows)}
    assert ratios == {"dev": 0.75, "test": 0.25}
