"""Bad input files and values (issue 57, defects 6, 7, 8c, 8d and 8e): no value reaches git as an option, no
capture deletes someone else's files, a capture's cameras are checked when read, a sweep file's duplicate key
is refused, and no name or message from data becomes HTML in a Markdown report.

The failures follow the CLI's contract (`tests/test_bad_input_cli.py`): exit status 2, one line on stderr
starting `dmesh <command>: error:`, nothing on stdout, and the case's folder byte-identical afterwards. The
CLI is called in-process (`eval.cli.main`); no test needs OpenGL (captures are `common.fake_views`)."""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from common import fake_views, refused

from eval.cli import main

_TETRA_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n"
HTML_NAME = "<img src=x onerror=alert(1)>"


def _bytes(d: Path) -> dict:
    """Every entry under `d` with its full contents (None for a folder)."""
    return {str(p.relative_to(d)): (p.read_bytes() if p.is_file() else None) for p in sorted(d.rglob("*"))}


def _fails(capsys, argv: list[str], command: str, *expect: str) -> str:
    """Runs `dmesh -q ARGV` and checks the bad-input contract (`common.refused`); returns the error line."""
    return refused(capsys, argv, command, *expect)


# ------------------------------------------------------------------------ defect 6: `changes --since`

def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout


@pytest.fixture
def repo(tmp_path, monkeypatch):
    """A git repository whose one commit holds `reports/store/runs.jsonl.gz` (the runs of test_changes'
    BEFORE), with the current folder in it; `after.jsonl.gz` beside it holds AFTER."""
    from test_changes import AFTER, BEFORE

    from eval.export import export_store
    from eval.store import Store

    repo = tmp_path / "repo"
    for name, runs in (("before", BEFORE), ("after", AFTER)):
        with Store(tmp_path / name / "results.sqlite") as s:
            for r in runs:
                s.upsert(r)
    (repo / "reports" / "store").mkdir(parents=True)
    export_store(tmp_path / "before" / "results.sqlite", repo / "reports" / "store" / "runs.jsonl.gz")
    export_store(tmp_path / "after" / "results.sqlite", repo / "after.jsonl.gz")
    _git(repo, "init", "-q")
    _git(repo, "add", "reports")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "runs")
    monkeypatch.chdir(repo)
    return repo


def test_changes_since_an_option_is_refused_and_git_writes_nothing(repo, capsys):
    # `git show --output=pw:reports/store/runs.jsonl.gz` wrote that file (its folders existing) before.
    (repo / "pw:reports" / "store").mkdir(parents=True)
    before = _bytes(repo)
    _fails(capsys, ["changes", "--since=--output=pw", "--after", "after.jsonl.gz", "-o", "out"], "changes",
           "--since '--output=pw': not a commit")
    assert _bytes(repo) == before


@pytest.mark.parametrize("rev", ["nosuch", "HEAD~5", "HEAD:reports", "-p", "--all"])
def test_changes_since_a_bad_revision_is_one_line(repo, capsys, rev):
    before = _bytes(repo)
    _fails(capsys, ["changes", f"--since={rev}", "--after", "after.jsonl.gz", "-o", "out"], "changes",
           f"--since {rev!r}: not a commit")
    assert _bytes(repo) == before


def test_changes_since_a_commit_without_the_export_is_one_line(repo, capsys):
    _git(repo, "rm", "-q", "-r", "reports")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "no runs")
    before = _bytes(repo)
    _fails(capsys, ["changes", "--since", "HEAD", "--after", "after.jsonl.gz", "-o", "out"], "changes",
           "--since HEAD: git has no HEAD:reports/store/runs.jsonl.gz (fatal: path")
    assert _bytes(repo) == before


def test_changes_since_a_commit_reads_its_export(repo, capsys):
    head = _git(repo, "rev-parse", "HEAD").strip()
    for rev in ("HEAD", head[:10]):
        assert main(["-q", "changes", "--since", rev, "--after", "after.jsonl.gz", "-o", "out"]) == 0
        assert "worse: 1" in capsys.readouterr().out
        assert f"the export at {rev} -> after.jsonl.gz" in (repo / "out" / "changes.md").read_text()


# ------------------------------------------------------------ defect 7: `capture -o` onto someone's folder

@pytest.fixture
def fake_capture(tmp_path, monkeypatch):
    """`dmesh capture` without OpenGL: `datasets.capture.capture` returns `fake_views` with the views asked
    for, after calling `during(out)` when set (files arriving while the views render)."""
    from datasets import capture as cap

    state = {"during": None}

    def capture(mesh, views=64, resolution=256, distance=2.0, seed=0, callback=None):
        if state["during"] is not None:
            state["during"]()
        return fake_views(v=views, res=resolution)

    monkeypatch.setattr(cap, "capture", capture)
    monkeypatch.setattr(cap, "gl_platform", lambda: "fake")
    (tmp_path / "mesh.obj").write_text(_TETRA_OBJ)
    return state


def _capture(tmp_path, out: Path, views: int) -> list[str]:
    return ["capture", str(tmp_path / "mesh.obj"), "-o", str(out), "--views", str(views), "--resolution", "8"]


def test_capture_onto_a_folder_with_other_files_is_refused(tmp_path, fake_capture, capsys):
    out = tmp_path / "cap"
    assert main(["-q", *_capture(tmp_path, out, 4)]) == 0
    capsys.readouterr()
    (out / "README.txt").write_text("my notes on this capture\n")
    np.save(out / "extra.npy", np.arange(5))
    (out / "images" / "mine.png").write_bytes(b"not a preview")
    before = _bytes(tmp_path)
    line = _fails(capsys, _capture(tmp_path, out, 2), "capture", "not a capture folder",
                  "README.txt, extra.npy, images/mine.png")
    assert str(out) in line
    assert _bytes(tmp_path) == before


def test_capture_replaces_an_earlier_capture_whole(tmp_path, fake_capture, capsys):
    from datasets.capture import MultiView, foreign_files

    out = tmp_path / "cap"
    assert main(["-q", *_capture(tmp_path, out, 4)]) == 0
    assert foreign_files(out) == []
    assert main(["-q", *_capture(tmp_path, out, 2)]) == 0  # fewer views: the old previews go too
    assert MultiView.load(out).views == 2
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{k}_{i}.png" for k in ("depth", "diffuse", "mask")
                                                                  for i in (0, 1)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "mesh.obj"]


def test_capture_keeps_files_that_came_while_it_rendered(tmp_path, fake_capture, capsys):
    out = tmp_path / "cap"
    assert main(["-q", *_capture(tmp_path, out, 2)]) == 0
    capsys.readouterr()
    fake_capture["during"] = lambda: (out / "late.txt").write_text("arrived mid-capture\n")
    _fails(capsys, _capture(tmp_path, out, 2), "capture", "late.txt")
    assert (out / "late.txt").read_text() == "arrived mid-capture\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "mesh.obj"]  # no temporary folder left


def test_foreign_files_counts_links_and_folders_as_foreign(tmp_path):
    from datasets.capture import foreign_files

    fake_views().save(tmp_path)
    assert foreign_files(tmp_path) == []
    (tmp_path / "sub").mkdir()
    (tmp_path / "capture.json").symlink_to(tmp_path / "views.npz")
    (tmp_path / "images" / "diffuse_9.png.bak").write_bytes(b"")
    assert foreign_files(tmp_path) == ["capture.json", "images/diffuse_9.png.bak", "sub/"]


# ------------------------------------------------------------- defect 8c: a capture's stored projection

@pytest.mark.parametrize("change,field", [
    (lambda p: p.__setitem__((0, 0), np.nan), "field 'projection' holds NaN"),
    (lambda p: p.__setitem__((2, 3), np.inf), "field 'projection' holds NaN"),
    (lambda p: p.__setitem__((1, 1), 2.0 * p[1, 1]), "field 'projection' disagrees with fov_y_degrees 65"),
])
def test_reconstruct_multiview_refuses_a_bad_stored_projection(tmp_path, capsys, monkeypatch, change, field):
    import dmesh.recon.multiview

    def reconstruct(*args, **kwargs):
        raise AssertionError("the capture's projection was not checked")

    monkeypatch.setattr(dmesh.recon.multiview, "reconstruct", reconstruct)
    views = fake_views()
    change(views.projection)
    views.save(tmp_path / "cap")
    before = _bytes(tmp_path)
    _fails(capsys, ["reconstruct", "multiview", str(tmp_path / "cap"), "-o", str(tmp_path / "out.obj")],
           "reconstruct", str(tmp_path / "cap" / "views.npz"), field)
    assert _bytes(tmp_path) == before


def test_capture_load_checks_fov_and_projection(tmp_path):
    from datasets.capture import MultiView

    fake_views().save(tmp_path / "ok")
    assert MultiView.load(tmp_path / "ok").fov_y_degrees == 65.0
    fake_views(fov_y_degrees=float("nan")).save(tmp_path / "fov")
    with pytest.raises(ValueError, match=r"views.npz: field 'fov_y_degrees' must be in \(0, 180\)"):
        MultiView.load(tmp_path / "fov")
    fake_views(projection=np.eye(3)).save(tmp_path / "shape")
    with pytest.raises(ValueError, match=r"field 'projection' must have shape \(4, 4\), got \(3, 3\)"):
        MultiView.load(tmp_path / "shape")


# ------------------------------------------------------------------ defect 8d: duplicate keys in YAML

DUPLICATES = [
    ("top", "methods: [psr]\nshapes: [torus]\nshapes: [nosuch]\n", "duplicate key 'shapes' (first on line 2)",
     "line 3, column 1"),
    ("nested", "methods: [psr]\nshapes: [torus]\nconfigs:\n  psr:\n    - {nope: 6, nope: 7}\n",
     "duplicate key 'nope' (first on line 5)", "line 5, column 17"),
]  # each fails fast without the check too (an unknown shape, an unknown config key), for another reason


@pytest.mark.parametrize("text,problem,where", [d[1:] for d in DUPLICATES], ids=[d[0] for d in DUPLICATES])
def test_sweep_yaml_with_a_duplicate_key_is_refused(tmp_path, capsys, monkeypatch, text, problem, where):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "dup.yaml").write_text(text)
    before = _bytes(tmp_path)
    _fails(capsys, ["bench", "dup.yaml", "--work", "w"], "bench", "sweep file dup.yaml: not valid YAML",
           where, problem)
    assert _bytes(tmp_path) == before


def test_yaml_loader_stays_safe_and_keeps_merge_keys():
    from eval.sweep import load_yaml

    assert load_yaml("base: &b {k: 1, j: 2}\nother:\n  <<: *b\n  k: 3\n", "t")["other"] == {"k": 3, "j": 2}
    with pytest.raises(ValueError, match=r"duplicate key 1\.0 \(first on line 1\)"):
        load_yaml("1: a\n1.0: b\n", "t")  # equal keys, written differently
    with pytest.raises(ValueError, match="could not determine a constructor"):
        load_yaml("!!python/object/apply:os.system [echo hi]", "t")
    with pytest.raises(ValueError, match="--set 'x={a: 1, a: 2}': not valid YAML"):
        load_yaml("{a: 1, a: 2}", "--set 'x={a: 1, a: 2}'")


# ---------------------------------------------------------------- defect 8e: HTML in Markdown reports

def test_markdown_cells_show_html_as_text():
    from eval.reports.tables import markdown

    text = markdown([{"shape": HTML_NAME, "error": "ValueError: <script>alert(1)</script>\nat | line 2"}],
                    [("shape", "shape", None), ("error", "error", None)])
    lines = text.splitlines()
    assert len(lines) == 3 and "<" not in text and ">" not in text
    assert lines[2] == ("| &lt;img src=x onerror=alert(1)&gt; | ValueError: &lt;script&gt;alert(1)&lt;/script&gt; "
                        "at \\| line 2 |")


def test_reports_carry_no_html_from_the_store(tmp_path):
    from test_reports import _row

    from eval.reports import write_reports
    from eval.store import Store

    path = tmp_path / "work" / "results.sqlite"
    html_label = "preset=paper,note=<b>x</b>"
    with Store(path) as s:
        s.upsert(_row("a", "psr", HTML_NAME, "closed", "done", 1e-3, 7e-3, 2.0))
        s.upsert(_row("b", "psr", "<script>x</script>", "closed", "failed", error="ValueError: <iframe src=y>"))
        s.upsert({**_row("c", "dmesh", HTML_NAME, "closed", "done", 1e-3, 7e-3, 2.0), "config_label": html_label})
        s.upsert({**_row("d", "dmesh", HTML_NAME, "closed", "done", 1e-3, 7e-3, 2.0),
                  "config_label": "lambda_weight=1e-4,lambda_quality=0", "config_json": {"lambda_weight": 1e-4,
                                                                                        "lambda_quality": 0}})
    written = write_reports(path, tmp_path / "rep", renders=False)
    reports = [p for p in written if p.suffix == ".md"]
    assert reports
    for p in reports:
        text = p.read_text()
        for tag in ("<img", "<script", "<iframe", "<b>"):
            assert tag not in text, (p.name, tag)
    assert "&lt;img src=x onerror=alert(1)&gt;" in (tmp_path / "rep" / "table2_pointcloud.md").read_text()


def test_changes_report_carries_no_html(tmp_path, capsys):
    from test_changes import AFTER, BEFORE

    from eval.export import export_store
    from eval.store import Store

    for name, runs in (("before", BEFORE), ("after", AFTER)):
        with Store(tmp_path / name / "results.sqlite") as s:
            for r in runs:
                s.upsert({**r, "shape": HTML_NAME} if r["shape"] == "torus" else r)
    export_store(tmp_path / "before" / "results.sqlite", tmp_path / "b.jsonl.gz")
    out = tmp_path / "rep"
    assert main(["-q", "changes", "--before", str(tmp_path / "b.jsonl.gz"), "--work", str(tmp_path / "after"),
                 "-o", str(out)]) == 0
    text = (out / "changes.md").read_text()
    assert "<img" not in text and "| worse | dmesh |  | &lt;img src=x onerror=alert(1)&gt; |" in text
