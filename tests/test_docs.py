"""README.md and docs/ hold no dated narrative and no path outside the repository; the README stays short, names
only commands that exist, and its results section is what `eval.reports.readme` makes of the committed CSVs."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MONTH = r"(?:January|February|March|April|May|June|July|August|September|October|November|December)"
#: "4 December", "December 4", "Session 12": history lives in git and reports/changes.md.
DATED = re.compile(rf"\b\d{{1,2}}(?:st|nd|rd|th)?\s+{MONTH}\b|\b{MONTH}\s+\d{{1,2}}\b|\bSession \d+", re.I)
#: An absolute path ("/work/x", "`/tmp/y`"), not a URL's "//" nor a ratio ("a/b"), nor a "/" between words.
ABSOLUTE = re.compile(r"(?<![\w.~/:\-])/[A-Za-z_][\w.\-]*/")
#: Any "../" but the data root's.
UPWARD = re.compile(r"\.\./(?!shared/meshes)")


def _hits(pattern: re.Pattern, text: str) -> list[str]:
    return [f"line {text.count(chr(10), 0, m.start()) + 1}: {m.group(0)!r}" for m in pattern.finditer(text)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_dated_phrase(page):
    assert not _hits(DATED, page.read_text()), _hits(DATED, page.read_text())


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_path_outside_the_repository(page):
    text = page.read_text()
    hits = _hits(ABSOLUTE, text) + _hits(UPWARD, text)
    assert not hits, hits


def test_the_checks_catch_what_they_should():
    assert DATED.search("the rerun of 5 December") and DATED.search("December 5") and DATED.search("Session 12")
    assert not DATED.search("December's rows") and not DATED.search("12 shapes")
    assert ABSOLUTE.search("scratch `/work/prof/s34/fc.py`") and ABSOLUTE.search("--work /tmp/x/y")
    assert not ABSOLUTE.search("https://github.com/a/b") and not ABSOLUTE.search("closed / open") \
        and not ABSOLUTE.search("reports/table2.md")
    assert UPWARD.search("cd ../wt") and not UPWARD.search("../shared/meshes")


def test_readme_is_at_most_200_lines():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 200


def test_docs_pages_are_at_most_400_lines():
    long = {p.name: n for p in PAGES[1:] if (n := len(p.read_text().splitlines())) > 400}
    assert not long, long


def test_every_dmesh_command_in_the_readme_exists():
    commands = {p.stem.replace("_", "-") for p in (ROOT / "eval" / "commands").glob("*.py")
                if p.stem != "__init__"}
    named = set(re.findall(r"(?:`|bin/)dmesh ([a-z][a-z-]*)", (ROOT / "README.md").read_text()))
    assert named, "the README names no dmesh command"
    assert named <= commands, sorted(named - commands)
    table = set(re.findall(r"^\| `dmesh ([a-z-]+)` \|", (ROOT / "README.md").read_text(), re.M))
    assert table == commands, (sorted(commands - table), sorted(table - commands))


def test_readme_results_are_what_the_generator_makes_of_the_committed_csvs():
    from eval.reports.readme import render

    readme = (ROOT / "README.md").read_text()
    assert render(readme, ROOT / "reports") == readme, "README's results are stale: run `make readme`"


def test_readme_results_show_dev_and_test_side_by_side(tmp_path):
    from eval.reports.readme import table

    csv = tmp_path / "t.csv"
    csv.write_text("method,category,split,n,failed,cd_p2s\n"
                   "psr,closed,dev,4,0,0.001\npsr,closed,test,5,1,0.002\npsr,open,dev,4,0,0.003\n")
    text = table(csv)
    assert "| method | closed dev | closed test | open dev | open test | mixed dev | mixed test |" in text
    assert "| psr | 1.00 (4) | 2.00 (5, 1 failed) | 3.00 (4) | - | - | - |" in text
