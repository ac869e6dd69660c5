"""README.md and docs/ hold no dated narrative and no path outside the repository, and name no code, file, command or
flag that does not exist; the README stays short, names only commands that exist, and its results section is what
`eval.reports.readme` makes of the committed CSVs."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MONTH = r"(?:January|February|March|April|May|June|July|August|September|October|November|December)"
#: "4 December", "December 4", "2026-12-03", "Session 12": history lives in git and reports/changes.md.
DATED = re.compile(rf"\b\d{{1,2}}(?:st|nd|rd|th)?\s+{MONTH}\b|\b{MONTH}\s+\d{{1,2}}\b|\bSession \d+"
                   r"|\b(?:19|20)\d\d-[01]\d-[0-3]\d\b", re.I)
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
    assert DATED.search("(report, 2026-12-03)")
    assert not DATED.search("December's rows") and not DATED.search("12 shapes") \
        and not DATED.search("pymeshlab 2025.7.post1")
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


# ------------------------------------------------------------------------------------ names the pages cite
#: What a page cites must exist now: a page names no code that is gone. Checked: in backticks, a file or folder of
#: the repository (`dmesh/recon/init.py`, `tests/test_x.py::test_y`; placeholders such as NAME or <module> are
#: skipped), a dotted name (`dmesh.recon.init.statistical_inliers`, `PointCloudConfig.fast`,
#: `topology.rim_edge_count`, a config key `lids.max_hole`; `np.ones` and other names not of this project are
#: skipped), a code identifier (`carve_far_faces`, `NOISY_RATIO`, `BoundedAdam`: a word of the project's sources),
#: and a command (`python -m studies NAME`, `python -m eval.bench NAME`, `dmesh CMD --flag`, `make TARGET`); in
#: fenced blocks, commands and `from PACKAGE import NAME`; anywhere, a repository path and a relative link.
CHECKED_PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PACKAGES = ("dmesh", "eval", "datasets", "baselines", "studies")
TOP = ("dmesh", "eval", "datasets", "baselines", "native", "tests", "studies", "reports", "tools", "docs")
SOURCE_DIRS = (*PACKAGES, "native", "tests", "tools")
#: Names a page may cite though no code has them any more: deliberately historical ones. None.
HISTORICAL: set[str] = set()
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
SPAN = re.compile(r"`([^`]+)`")
DOTTED = re.compile(r"^([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+)(?:\(.*\)|\[.*\])?$", re.S)
IDENTIFIER = re.compile(r"^(?:_?[a-z][a-z0-9]*(?:_[a-z0-9]+)+|[A-Z][A-Z0-9]*(?:_[A-Z0-9]+)+|[A-Z][a-z0-9]+"
                        r"(?:[A-Z][a-z0-9]*)+)(?:=.*)?$")
FILE = re.compile(r"^[\w.\-/{}*,<>]+(?:::\w+)?$")
SUFFIXES = (".py", ".pyi", ".md", ".yaml", ".csv", ".json", ".toml", ".html", ".h", ".cpp", ".gz", ".png")
PLAIN_PATH = re.compile(rf"(?<![\w/.\-])((?:{'|'.join(TOP)})/[\w./{{}}*\-]*\w)")
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
COMMAND = re.compile(r"(?:^|[\s`(;])((?:\.venv/bin/)?(?:python -m \S+|dmesh|make)(?: [^`;|&#)]*)?)")


def _resolve(parts: list[str]) -> bool:
    """Whether `parts` is an importable module, then attributes of it (a dataclass field counts)."""
    import dataclasses
    import importlib

    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except (ImportError, OSError):  # OSError: a module the import system still knows of, whose file is gone
            continue
        for name in parts[cut:]:
            field = getattr(obj, "__dataclass_fields__", {}).get(name)
            if field is not None and not hasattr(obj, name):  # a field without a default
                obj = field.default_factory() if field.default_factory is not dataclasses.MISSING else None
            elif hasattr(obj, name):
                obj = getattr(obj, name)
            else:
                return False
        return True
    return False


class _Index:
    """The project's modules, top-level classes, config keys, source words and file names, read once."""

    def __init__(self):
        import ast

        self.by_short: dict[str, list[str]] = {}
        self.classes: dict[str, list[str]] = {}
        for pkg in PACKAGES:
            for path in (ROOT / pkg).rglob("*.py"):
                parts = path.relative_to(ROOT).with_suffix("").parts
                name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
                self.by_short.setdefault(name.rsplit(".", 1)[-1], []).append(name)
                for node in ast.parse(path.read_text()).body:
                    if isinstance(node, ast.ClassDef):
                        self.classes.setdefault(node.name, []).append(name)
        self.words = set(re.findall(r"\w+", (ROOT / "Makefile").read_text() + (ROOT / "pyproject.toml").read_text()))
        for d in SOURCE_DIRS:
            for p in (ROOT / d).rglob("*"):
                if p.suffix in (".py", ".pyi", ".cpp", ".h", ".yaml") and "__pycache__" not in p.parts \
                        and p != Path(__file__):  # not this file: its lists would vouch for any name
                    self.words.update(re.findall(r"\w+", p.read_text(errors="replace")))
        self.files = {p.name for d in TOP for p in (ROOT / d).rglob("*") if "__pycache__" not in p.parts}
        from dmesh.recon.config import PointCloudConfig
        from dmesh.recon.depth_fit import DepthFitConfig
        from dmesh.recon.mesh_to_dmesh import MeshToDMeshConfig
        from dmesh.recon.multiview_config import MultiViewConfig
        from dmesh.surface.config import SurfaceConfig

        self.configs = [PointCloudConfig(), MultiViewConfig(), MeshToDMeshConfig(), SurfaceConfig(), DepthFitConfig()]
        from eval.cli import build_parser

        self.subcommands = build_parser()._subparsers._group_actions[0].choices
        self.makefile = (ROOT / "Makefile").read_text()

    def config_key(self, parts: list[str]) -> bool | None:
        """Whether `parts` walks the fields of a default config (None: its first part is no config's field)."""
        hit = None
        for cfg in self.configs:
            if hasattr(cfg, parts[0]):
                obj = cfg
                for name in parts:
                    obj = getattr(obj, name, _Index)
                hit = hit or obj is not _Index
        return hit

    def dotted(self, name: str) -> bool | None:
        """Whether a dotted name resolves (None: no name of this project's, e.g. `np.ones`, `probs.prob_wdt`)."""
        parts = name.split(".")
        if parts[0] in PACKAGES:
            return _resolve(parts)
        tries = [m.split(".") + parts[1:] for m in self.by_short.get(parts[0], [])]
        tries += [m.split(".") + parts for m in self.classes.get(parts[0], [])]
        as_key = self.config_key(parts)
        if not tries and as_key is None:
            return None
        return bool(as_key) or any(_resolve(t) for t in tries)

    def path(self, token: str) -> bool | None:
        """Whether a repository path exists (None: not a repository path, or a placeholder: `WORK/x`, `NAME`)."""
        token, _, test = token.partition("::")
        placeholder = "<" in token or re.search(r"(?:^|[/_.])[A-Z]{2,}(?:$|[/_.])", token)  # test_<x>.py, bench_NAME
        if "/" not in token or token.split("/", 1)[0] not in TOP or (placeholder and not (ROOT / token).exists()):
            if "/" not in token and token.endswith((".py", ".yaml")):
                return token in self.files
            return None
        names = [token]
        if m := re.search(r"\{([^}]*)\}", token):
            names = [token[:m.start()] + alt + token[m.end():] for alt in m.group(1).split(",")]
        for n in names:
            if not any(p.exists() for p in (ROOT.glob(n.rstrip("/")) if "*" in n else [ROOT / n])):
                return False
        if test:
            return re.search(rf"^\s*def {test}\(", (ROOT / token).read_text(), re.M) is not None
        return True

    def command(self, words: list[str]) -> list[str]:
        """What a command line (`python -m X ...`, `dmesh CMD ...`, `make T`) names that does not exist."""
        words = [w.removeprefix(".venv/bin/") for w in words]
        if words[0] == "python" and len(words) > 2:
            if words[2] in ("studies", "eval.bench"):
                folder = ROOT / words[2].replace(".", "/")
                return [f"python -m {words[2]} {w}" for w in words[3:]
                        if re.fullmatch(r"[a-z_]+", w) and w != "all" and not (folder / f"{w}.py").exists()]
            return [f"python -m {words[2]}"] if self.dotted(words[2]) is False else []
        if words[0] == "make" and len(words) > 1 and re.fullmatch(r"[a-z][a-z-]*", words[1]):
            return [] if re.search(rf"^{words[1]}:", self.makefile, re.M) else [f"make {words[1]}"]
        if words[0] == "dmesh" and len(words) > 1 and re.fullmatch(r"[a-z][a-z-]*", words[1]):
            sub = self.subcommands.get(words[1])
            if sub is None:
                return [f"dmesh {words[1]}"]
            flags = {w.split("=", 1)[0] for w in words[2:] if re.fullmatch(r"--[a-z][a-z-]*(=.*)?", w)}
            return [f"dmesh {words[1]} {f}" for f in sorted(flags - set(sub._option_string_actions))]
        return []

    def broken(self, page: Path) -> list[str]:
        """What `page` cites that does not exist."""
        text = page.read_text()
        blocks = FENCE.findall(text)
        prose = FENCE.sub("", text)
        spans = [" ".join(s.split()) for s in SPAN.findall(prose)]
        bad = []
        for span in spans:
            if FILE.match(span) and ("/" in span or span.endswith(SUFFIXES)):
                ok = self.path(span)
            elif m := DOTTED.match(span):
                ok = self.dotted(m.group(1))
            elif m := IDENTIFIER.match(span):
                ok = m.group(0).split("=", 1)[0] in self.words | HISTORICAL
            else:
                ok = None
            if ok is False:
                bad.append(span)
            for token in span.split():  # paths inside a command: `dmesh bench eval/sweeps/x.yaml --work runs/paper`
                if token != span and FILE.match(token) and "/" in token and self.path(token) is False:
                    bad.append(f"{token} (in `{span}`)")
        shell = [b for b in blocks if not b.startswith("```python")]
        for line in "\n".join(spans + shell).splitlines():
            for m in COMMAND.finditer(line):
                bad += self.command(m.group(1).split())
        for block in blocks:
            for mod, names in re.findall(r"^\s*from ([\w.]+) import ([\w, ]+)", block, re.M):
                if mod.split(".")[0] in PACKAGES:
                    bad += [f"from {mod} import {n.strip()}" for n in names.split(",")
                            if not _resolve(mod.split(".") + [n.strip()])]
        bad += [m.group(1) for m in PLAIN_PATH.finditer(SPAN.sub("", prose)) if self.path(m.group(1)) is False]
        bad += [f"link {t}" for t in LINK.findall(text) if "://" not in t and not (page.parent / t).exists()]
        return bad


@pytest.fixture(scope="module")
def index():
    return _Index()


@pytest.mark.parametrize("page", CHECKED_PAGES, ids=lambda p: p.name)
def test_every_name_a_page_cites_exists(page, index):
    bad = index.broken(page)
    assert not bad, sorted(set(bad))


def test_the_name_check_catches_what_it_should(index, tmp_path):
    gone = ["`dmesh/repair.py`", "`repair.py`", "`dmesh.extract.surface`", "`dmesh.repair.fill_holes`",
            "`surface_of_mesh`", "`extract_filtered`", "`_surface_mesh`", "`PointCloudConfig.nope`",
            "`lids.nope`", "`topology.nope`", "`tests/test_pointcloud.py::test_nope`", "`python -m studies nope`",
            "`python -m eval.bench nope`", "`dmesh bench --nope`", "`dmesh nope`", "`make nope`",
            "`carve=5` but `nope_field=3`", "docs/nope.md", "[a link](nope.md)"]
    page = tmp_path / "page.md"
    for cite in gone:
        page.write_text(f"A page citing {cite}.\n")
        assert index.broken(page), cite
    page.write_text("```python\nfrom dmesh.surface import surface_of_mesh\n```\n")
    assert index.broken(page)
    page.write_text("`dmesh/recon/init.py`, `dmesh.surface.run(pd, walls)`, `PointCloudConfig.fast`, "
                    "`topology.rim_edge_count`, `surface.lids.max_hole`, `carve_far_faces`, `NOISY_RATIO`, "
                    "`tests/test_<module>.py`, `reports/bench_*.md`, `np.ones`, `python -m studies depth_fit`, "
                    "`dmesh bench --plan --work runs/paper`, `make bench`, docs/surface.md, "
                    f"[surface]({ROOT / 'docs' / 'surface.md'})\n"
                    "```python\nfrom dmesh.surface import SurfaceConfig\n```\n")
    assert not index.broken(page), index.broken(page)


def test_readme_ratios_compare_dmesh_with_the_best_method_over_the_same_runs(tmp_path):
    """A method with fewer done runs (failures) is not the best other method: its mean is over other shapes."""
    from eval.reports.readme import ratios

    path = tmp_path / "t.csv"
    path.write_text("method,category,split,n,failed,cd_p2s\n"
                    "dmesh [fast],closed,dev,4,0,0.001\n"
                    "psr,closed,dev,4,0,0.002\n"
                    "bpa,closed,dev,4,0,0.004\n"
                    "voromesh,closed,dev,3,1,0.0001\n"
                    "dmesh [fast],open,test,6,0,0.003\n"
                    "psr,open,test,6,0,0.002\n")
    assert ratios(path).splitlines()[-1] == "- `dmesh [fast]`: closed dev 0.5x (psr), open test 1.5x (psr)"
    path.write_text("method,category,split,n,failed,cd_p2s\npsr,closed,dev,4,0,0.002\n")
    assert ratios(path) == ""
