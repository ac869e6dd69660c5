"""The bad-input matrix of the `dmesh` CLI (issue 15, items 3, 5 and 6): one case a row.

Every case must exit with status 2, print exactly one non-empty line on stderr that names the problem (no
traceback, no usage block), print nothing on stdout and leave no file behind: the folder the case works in
holds exactly what it held before. Each case fails before any heavy computation, so the whole matrix runs
in seconds; the CLI is called in-process (`eval.cli.main`).

Placeholders in the argument lists: `{d}` is the case's folder, set up by the `d` fixture with the files
named in `_make_files`.
"""
from __future__ import annotations

import hashlib
import os
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from common import refused


SEED_2_70 = str(2**70)
HUGE = "100000000000"  # 1e11 points: 4.4 TiB of positions and normals

_TETRA_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n"


def _make_files(d: Path) -> None:
    (d / "mesh.obj").write_text(_TETRA_OBJ)
    np.save(d / "pts.npy", np.random.default_rng(0).random((200, 3)))
    (d / "ok.yaml").write_text("methods: [psr]\nshapes: [torus]\nn_points: 2000\nmetric_samples: 2000\n")
    (d / "bad.yaml").write_text("methods: [psr\nshapes: [torus]\n")
    (d / "str.yaml").write_text("methods: psr\nshapes: [torus]\n")
    (d / "unk.yaml").write_text("methods: [psr]\nshapes: [torus]\nfoo: 1\n")
    (d / "list.yaml").write_text("- psr\n- torus\n")
    (d / "empty.yaml").write_text("")
    (d / "empty.obj").write_text("")
    (d / "garbage.obj").write_bytes(np.random.default_rng(1).integers(0, 256, 300, dtype=np.uint8).tobytes())
    (d / "notes.txt").write_text("not a mesh\n")
    (d / "afile").write_text("a file where a folder is expected\n")
    (d / "adir").mkdir()
    (d / "adir" / "keep.txt").write_text("someone's file\n")
    (d / "emptydir").mkdir()
    (d / "corrupt").mkdir()
    (d / "corrupt" / "results.sqlite").write_bytes(b"this is not a database " * 50)
    con = sqlite3.connect(d / "other.sqlite")
    con.execute("CREATE TABLE photos (name TEXT)")
    con.commit()
    con.close()
    (d / "ro").mkdir()
    (d / "link.npy").symlink_to(d / "pts.npy")
    os.link(d / "mesh.obj", d / "hard.obj")
    (d / "fitted").mkdir()
    (d / "fitted" / "result.json").write_text("{}\n")
    (d / "fitted" / "mesh.obj").write_text(_TETRA_OBJ)
    (d / "big.obj").write_text(_TETRA_OBJ.replace("v 0 0 1", "v 0 0 1e300"))


def _snapshot(d: Path) -> dict:
    """Every path under `d` with its bytes' digest (None for a folder): a failed command changes none."""
    return {str(p.relative_to(d)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None)
            for p in sorted(d.rglob("*"))}


@pytest.fixture
def d(tmp_path, monkeypatch):
    """The case folder, with `ro/` read-only: by its mode, or (as root, whom modes do not stop) by making
    `os.access` report it so, which is what the CLI's output checks ask."""
    d = tmp_path / "case"
    d.mkdir()
    _make_files(d)
    monkeypatch.chdir(d)
    ro = d / "ro"
    ro.chmod(0o555)
    if os.access(ro, os.W_OK):
        real = os.access

        def access(path, mode, *a, **k):
            inside = Path(path).absolute() == ro or ro in Path(path).absolute().parents
            return False if inside and mode & os.W_OK else real(path, mode, *a, **k)

        monkeypatch.setattr(os, "access", access)
    yield d
    ro.chmod(0o755)


def case(id_, argv, expect):
    """One row: its pytest id, the arguments after `dmesh -q`, and the text (or texts) the error must hold."""
    return pytest.param(argv, (expect,) if isinstance(expect, str) else expect, id=id_)


CASES = [
    # ---- issue 15 item 3: tracebacks before
    case("bench-yaml-syntax-error", ["bench", "{d}/bad.yaml"], "not valid YAML (line 2"),
    case("reproduce-tables-yaml-syntax-error", ["reproduce-tables", "--sweep", "{d}/bad.yaml", "-o", "{d}/rep"],
         "not valid YAML"),
    case("bench-set-yaml-syntax-error", ["bench", "{d}/ok.yaml", "--set", "psr.depth=[1"],
         "--set 'psr.depth=[1': not valid YAML"),
    case("reconstruct-set-yaml-syntax-error",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--set", "num_init=[1"], "not valid YAML"),
    case("bench-yaml-methods-string", ["bench", "{d}/str.yaml"], "Sweep.methods: expected a list, got str"),
    case("bench-set-methods-string", ["bench", "{d}/ok.yaml", "--set", "methods=psr"],
         "Sweep.methods: expected a list"),
    case("bench-set-configs-int", ["bench", "{d}/ok.yaml", "--set", "configs=5"], "Sweep.configs: expected a mapping"),
    case("bench-set-seeds-int", ["bench", "{d}/ok.yaml", "--set", "seeds=5"], "Sweep.seeds: expected a list"),
    case("bench-work-is-a-file", ["bench", "{d}/ok.yaml", "--work", "{d}/afile"], "is a file, not a folder"),
    case("bench-corrupt-store-before-gt-cache", ["bench", "{d}/ok.yaml", "--work", "{d}/corrupt"],
         "results.sqlite: cannot be read (file is not a database)"),
    case("reproduce-tables-corrupt-store",
         ["reproduce-tables", "--sweep", "{d}/ok.yaml", "--work", "{d}/corrupt", "-o", "{d}/rep"], "cannot be read"),
    case("reproduce-tables-report-only-corrupt-store",
         ["reproduce-tables", "--report-only", "--work", "{d}/corrupt", "-o", "{d}/rep"], "cannot be read"),
    case("bench-db-of-something-else", ["bench", "{d}/ok.yaml", "--work", "{d}/w", "--db", "{d}/other.sqlite"],
         "a SQLite database of something else"),
    case("fit-out-existing-file", ["fit", "{d}/mesh.obj", "-o", "{d}/afile"], "-o {d}/afile: is a file, not a folder"),
    case("reconstruct-state-read-only-folder",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--state", "{d}/ro/s.pt"],
         "folder {d}/ro is not writable"),
    case("bench-seed-2-70", ["bench", "{d}/ok.yaml", "--seeds", SEED_2_70], "a seed must be from 0 to 2**63 - 1"),
    case("reconstruct-seed-2-70",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--seed", SEED_2_70], "--seed: a seed"),
    case("fit-seed-2-70", ["fit", "{d}/mesh.obj", "-o", "{d}/fit", "--seed", SEED_2_70], "--seed: a seed"),
    case("capture-seed-negative", ["capture", "{d}/mesh.obj", "-o", "{d}/cap", "--seed", "-1"], "--seed: a seed"),
    case("metrics-seed-negative", ["metrics", "{d}/mesh.obj", "{d}/mesh.obj", "--seed", "-5"], "--seed: a seed"),
    case("metrics-samples-1e11-not-an-int", ["metrics", "{d}/mesh.obj", "{d}/mesh.obj", "--samples", "1e11"],
         "argument --samples: invalid int value: '1e11'"),
    case("metrics-samples-huge", ["metrics", "{d}/mesh.obj", "{d}/mesh.obj", "--samples", HUGE],
         "--samples: at most 20,000,000 points"),
    case("reconstruct-samples-huge",
         ["reconstruct", "pointcloud", "{d}/mesh.obj", "-o", "{d}/out.obj", "--samples", HUGE], "TiB of memory"),
    case("demo-points-huge", ["demo", "-o", "{d}/demo", "--points", HUGE], "--points: at most"),
    case("compare-points-huge", ["compare", "{d}/mesh.obj", "-o", "{d}/cmp", "--points", HUGE], "--points: at most"),
    case("bench-set-n-points-huge", ["bench", "{d}/ok.yaml", "--set", f"n_points={HUGE}"], "Sweep.n_points: at most"),
    case("bench-set-n-points-float", ["bench", "{d}/ok.yaml", "--set", "n_points=1e11"],
         "Sweep.n_points: expected an integer"),
    # ---- issue 15 item 5
    case("bench-seeds-negative", ["bench", "{d}/ok.yaml", "--seeds", "-1", "--work", "{d}/w"], "got -1"),
    case("reconstruct-state-existing-folder",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--state", "{d}/emptydir"],
         "--state {d}/emptydir: is a folder"),
    case("capture-views-huge", ["capture", "{d}/mesh.obj", "-o", "{d}/cap", "--views", "100000000"],
         "--views: at most 10,000 views, got 100,000,000 (their images at 256x256 would need"),
    case("capture-resolution-huge", ["capture", "{d}/mesh.obj", "-o", "{d}/cap", "--resolution", "100000"],
         "--resolution: at most 8192"),
    case("capture-images-over-budget", ["capture", "{d}/mesh.obj", "-o", "{d}/cap", "--resolution", "8192"],
         "more than the 16 GiB a capture may hold"),
    case("bench-set-views-huge", ["bench", "{d}/ok.yaml", "--set", "views=100000000"], "Sweep.views: at most"),
    case("reconstruct-out-read-only-folder", ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/ro/out.obj"],
         "-o {d}/ro/out.obj: folder {d}/ro is not writable"),
    case("fit-out-read-only-folder", ["fit", "{d}/mesh.obj", "-o", "{d}/ro/fit"], "not writable"),
    case("capture-out-read-only-folder", ["capture", "{d}/mesh.obj", "-o", "{d}/ro/cap"], "not writable"),
    case("demo-out-read-only-folder", ["demo", "-o", "{d}/ro/demo"], "not writable"),
    case("bench-work-read-only-folder", ["bench", "{d}/ok.yaml", "--work", "{d}/ro"],
         "--work {d}/ro: folder is not writable"),
    case("bench-report-read-only-folder", ["bench", "{d}/ok.yaml", "--work", "{d}/w", "--report", "{d}/ro/rep"],
         "--report {d}/ro/rep: folder {d}/ro is not writable"),
    case("reconstruct-out-existing-folder", ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/adir"],
         "is a folder; give a file name"),
    case("reconstruct-out-unsupported-suffix", ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.xyz"],
         "expected a file ending in .obj, .ply, .off, .stl"),
    case("reconstruct-out-parent-is-a-file",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/afile/out.obj"], "{d}/afile is a file"),
    case("reconstruct-state-is-the-input",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--state", "{d}/pts.npy"],
         "--state {d}/pts.npy: is the input {d}/pts.npy"),
    case("fit-out-folder-of-other-files", ["fit", "{d}/mesh.obj", "-o", "{d}/adir"], "no result.json"),
    case("demo-out-existing-file", ["demo", "-o", "{d}/afile"], "is a file, not a folder"),
    case("compare-out-existing-file", ["compare", "{d}/mesh.obj", "-o", "{d}/afile"], "is a file, not a folder"),
    case("reproduce-tables-out-existing-file", ["reproduce-tables", "-o", "{d}/afile"], "is a file, not a folder"),
    case("bench-db-is-a-folder", ["bench", "{d}/ok.yaml", "--work", "{d}/w", "--db", "{d}/adir"], "is a folder"),
    case("reproduce-tables-report-only-no-store",
         ["reproduce-tables", "--report-only", "--work", "{d}/nowork", "-o", "{d}/rep"], "no results store at"),
    case("bench-set-method-not-in-sweep", ["bench", "{d}/ok.yaml", "--set", "pssr.depth=7"],
         "'pssr' is not among the methods run"),
    case("compare-set-method-not-run", ["compare", "{d}/mesh.obj", "-o", "{d}/cmp", "--methods", "psr", "--set",
                                        "bpa.radius=1"], "'bpa' is not among the methods run"),
    case("capture-distance-nan", ["capture", "{d}/mesh.obj", "-o", "{d}/cap", "--distance", "nan"],
         "--distance must be a positive finite number"),
    case("reconstruct-set-value-not-a-number",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--set", "num_init=abc"], "num_init"),
    case("reconstruct-state-parent-is-a-file",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--state", "{d}/afile/s.pt"],
         "--state {d}/afile/s.pt: {d}/afile is a file"),
    case("reproduce-tables-sweep-and-recipes",
         ["reproduce-tables", "--sweep", "{d}/ok.yaml", "--recipes", "-o", "{d}/rep", "--work", "{d}/w"],
         "--sweep and --recipes both choose the sweeps"),
    case("reproduce-tables-set-method-of-no-sweep",
         ["reproduce-tables", "--sweep", "{d}/ok.yaml", "--set", "pssr.depth=1", "-o", "{d}/rep", "--work", "{d}/w"],
         "'pssr' is not a method of any sweep"),
    case("demo-metric-samples-huge", ["demo", "-o", "{d}/demo", "--metric-samples", HUGE], "--metric-samples: at most"),
    case("bench-timeout-nan", ["bench", "{d}/ok.yaml", "--timeout", "nan", "--work", "{d}/w"],
         "Sweep.timeout_s: expected a positive number, got nan"),
    case("metrics-pred-is-a-folder", ["metrics", "{d}/adir", "{d}/mesh.obj"], "is a folder"),
    case("capture-mesh-is-a-folder", ["capture", "{d}/adir", "-o", "{d}/cap"], "is a folder"),
    case("compare-mesh-is-a-folder", ["compare", "{d}/adir", "-o", "{d}/cmp"], "is a folder, not a mesh file"),
    case("reconstruct-multiview-missing-folder", ["reconstruct", "multiview", "{d}/nosuch", "-o", "{d}/out.obj"],
         "nosuch: no such folder"),
    # ---- issue 57 item 3: no output may be an input (same path, a symbolic or a hard link)
    case("reconstruct-out-is-the-input", ["reconstruct", "pointcloud", "{d}/mesh.obj", "-o", "{d}/mesh.obj"],
         "-o {d}/mesh.obj: is the input {d}/mesh.obj; the output would overwrite it"),
    case("reconstruct-out-is-the-input-by-another-spelling",
         ["reconstruct", "pointcloud", "{d}/mesh.obj", "-o", "{d}/adir/../mesh.obj"], "is the input"),
    case("reconstruct-out-is-a-hard-link-of-the-input",
         ["reconstruct", "pointcloud", "{d}/mesh.obj", "-o", "{d}/hard.obj"], "is the input {d}/mesh.obj"),
    case("reconstruct-state-is-a-link-to-the-input",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--state", "{d}/link.npy"],
         "--state {d}/link.npy: is the input"),
    case("reconstruct-state-is-the-output",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--state", "{d}/out.obj"],
         "is an output too"),
    case("fit-out-holds-the-input", ["fit", "{d}/fitted/mesh.obj", "-o", "{d}/fitted"],
         "-o {d}/fitted: holds the input {d}/fitted/mesh.obj"),
    case("export-store-out-is-the-store", ["export-store", "--db", "{d}/other.sqlite", "-o", "{d}/other.sqlite"],
         "-o {d}/other.sqlite: is the input"),
    # ---- issue 57 item 4: coordinates whose powers overflow float64, refused at load by every command
    case("metrics-gt-1e300", ["metrics", "{d}/mesh.obj", "{d}/big.obj"], "big.obj: coordinates up to 1e+300"),
    case("metrics-pred-1e300", ["metrics", "{d}/big.obj", "{d}/mesh.obj"], "at most 1e+75 are supported"),
    case("fit-1e300", ["fit", "{d}/big.obj", "-o", "{d}/fit"], "coordinates up to 1e+300"),
    case("capture-1e300", ["capture", "{d}/big.obj", "-o", "{d}/cap"], "coordinates up to 1e+300"),
    case("compare-1e300", ["compare", "{d}/big.obj", "-o", "{d}/cmp"], "coordinates up to 1e+300"),
    case("reconstruct-mesh-1e300", ["reconstruct", "pointcloud", "{d}/big.obj", "-o", "{d}/out.obj"],
         "coordinates up to 1e+300"),
    # ---- argparse errors: one line too, no usage block
    case("unknown-command", ["nosuch"], "invalid choice: 'nosuch'"),
    case("reconstruct-missing-out", ["reconstruct", "pointcloud", "{d}/pts.npy"],
         "the following arguments are required: -o/--out"),
    case("bench-jobs-not-an-int", ["bench", "{d}/ok.yaml", "--jobs", "abc"], "argument --jobs: invalid int value"),
    case("bench-inputs-bad-choice", ["bench", "{d}/ok.yaml", "--inputs", "photos"], "invalid choice: 'photos'"),
    case("fit-preset-bad-choice", ["fit", "{d}/mesh.obj", "-o", "{d}/fit", "--preset", "nosuch"], "invalid choice"),
    # ---- already held before issue 15; kept so none regresses
    case("bench-no-sweep", ["bench"], "give a sweep YAML file, or both --methods and --shapes"),
    case("bench-missing-yaml", ["bench", "{d}/nosuch.yaml"], "sweep file {d}/nosuch.yaml not found"),
    case("bench-empty-yaml", ["bench", "{d}/empty.yaml"], "empty.yaml: empty"),
    case("bench-yaml-list", ["bench", "{d}/list.yaml"], "expected a mapping at the top level"),
    case("bench-yaml-binary", ["bench", "{d}/garbage.obj"], "garbage.obj"),
    case("bench-yaml-unknown-key", ["bench", "{d}/unk.yaml"], "unknown keys ['foo']"),
    case("bench-unknown-method", ["bench", "--methods", "nosuch", "--shapes", "torus", "--work", "{d}/w"],
         "unknown method 'nosuch'"),
    case("bench-unknown-shape", ["bench", "--methods", "psr", "--shapes", "nosuch", "--work", "{d}/w"],
         "unknown shape 'nosuch'"),
    case("bench-missing-mesh-file", ["bench", "--methods", "psr", "--shapes", "closed/nosuch.obj", "--data-root",
                                     "{d}/nodir", "--work", "{d}/w"], "no such mesh file"),
    case("bench-jobs-0", ["bench", "{d}/ok.yaml", "--jobs", "0", "--work", "{d}/w"], "RunnerConfig.jobs"),
    case("bench-timeout-negative", ["bench", "{d}/ok.yaml", "--timeout", "-1", "--work", "{d}/w"],
         "Sweep.timeout_s: expected a positive number"),
    case("bench-set-no-equals", ["bench", "{d}/ok.yaml", "--set", "depth"], "expected KEY=VALUE"),
    case("bench-set-unknown-field", ["bench", "{d}/ok.yaml", "--set", "nope=1"], "unknown sweep field 'nope'"),
    case("bench-set-unknown-config-key", ["bench", "{d}/ok.yaml", "--set", "psr.nope=1", "--work", "{d}/w"],
         "psr: unknown config keys ['nope']"),
    case("reproduce-tables-missing-yaml", ["reproduce-tables", "--sweep", "{d}/nosuch.yaml", "-o", "{d}/rep"],
         "not found"),
    case("reproduce-tables-unknown-method",
         ["reproduce-tables", "--methods", "nosuch", "-o", "{d}/rep", "--work", "{d}/w"], "unknown method 'nosuch'"),
    case("fit-missing-mesh", ["fit", "{d}/nosuch.obj", "-o", "{d}/fit"], ("nosuch.obj", "no such file")),
    case("fit-empty-mesh", ["fit", "{d}/empty.obj", "-o", "{d}/fit"], ("empty.obj:", "empty")),
    case("fit-garbage-mesh", ["fit", "{d}/garbage.obj", "-o", "{d}/fit"], "garbage.obj"),
    case("fit-mesh-is-a-folder", ["fit", "{d}/adir", "-o", "{d}/fit"], "is a folder, not a mesh file"),
    case("fit-steps-0", ["fit", "{d}/mesh.obj", "-o", "{d}/fit", "--steps", "0"], "--steps must be at least 1"),
    case("reconstruct-missing-input", ["reconstruct", "pointcloud", "{d}/nosuch.npy", "-o", "{d}/out.obj"],
         "nosuch.npy: no such file"),
    case("reconstruct-empty-input", ["reconstruct", "pointcloud", "{d}/empty.obj", "-o", "{d}/out.obj"],
         ("empty.obj:", "empty")),
    case("reconstruct-unsupported-input", ["reconstruct", "pointcloud", "{d}/ok.yaml", "-o", "{d}/out.obj"],
         "unsupported input format '.yaml'"),
    case("reconstruct-depth-preset-on-points",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--preset", "depth"],
         "'depth' is for multi-view input only"),
    case("reconstruct-unknown-set-key",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--set", "nokey=1"],
         "unknown config keys ['nokey']"),
    case("reconstruct-steps-negative",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--steps", "-1"], "--steps must be >= 0"),
    case("reconstruct-normals-missing",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--normals"], "the input has no normals"),
    case("reconstruct-multiview-not-a-folder",
         ["reconstruct", "multiview", "{d}/pts.npy", "-o", "{d}/out.obj"], "not a folder"),
    case("reconstruct-multiview-not-a-capture",
         ["reconstruct", "multiview", "{d}/emptydir", "-o", "{d}/out.obj"], "not a capture folder"),
    case("capture-missing-mesh", ["capture", "{d}/nosuch.obj", "-o", "{d}/cap"], ("nosuch.obj", "no such file")),
    case("capture-views-0", ["capture", "{d}/mesh.obj", "-o", "{d}/cap", "--views", "0"], "--views must be >= 1"),
    case("capture-out-not-a-capture", ["capture", "{d}/mesh.obj", "-o", "{d}/adir"], "not a capture folder"),
    case("metrics-missing-pred", ["metrics", "{d}/nosuch.obj", "{d}/mesh.obj"], ("nosuch.obj", "no such file")),
    case("metrics-garbage-gt", ["metrics", "{d}/mesh.obj", "{d}/garbage.obj"], "garbage.obj"),
    case("metrics-samples-0", ["metrics", "{d}/mesh.obj", "{d}/mesh.obj", "--samples", "0"], "--samples"),
    case("compare-missing-mesh", ["compare", "{d}/nosuch.obj", "-o", "{d}/cmp"], "not found"),
    case("compare-unsupported-mesh", ["compare", "{d}/notes.txt", "-o", "{d}/cmp"], "unsupported file type"),
    case("compare-unknown-method", ["compare", "{d}/mesh.obj", "-o", "{d}/cmp", "--methods", "nosuch"],
         "unknown method 'nosuch'"),
    case("compare-jobs-0", ["compare", "{d}/mesh.obj", "-o", "{d}/cmp", "--jobs", "0"], "RunnerConfig.jobs"),
    case("demo-unknown-shape", ["demo", "-o", "{d}/demo", "--shape", "nosuch"], "unknown synthetic shape 'nosuch'"),
    case("demo-too-few-points", ["demo", "-o", "{d}/demo", "--points", "5"], "--points: expected at least 10"),
    # ---- issue 58 item 3: the harness's pre-processing stage
    case("bench-preprocess-unknown", ["bench", "{d}/ok.yaml", "--preprocess", "none", "denoise"],
         "unknown pre-processing stage 'denoise'"),
    case("bench-set-preprocess-string", ["bench", "{d}/ok.yaml", "--set", "preprocess=outliers"],
         "Sweep.preprocess: expected a list"),
    case("bench-preprocess-smooth-k-5", ["bench", "{d}/ok.yaml", "--preprocess", "smooth=5"], "k must be an integer"),
    case("compare-preprocess-unknown", ["compare", "{d}/mesh.obj", "-o", "{d}/cmp", "--preprocess", "outlier"],
         "unknown pre-processing stage 'outlier'"),
    case("reconstruct-preprocess-unknown",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--preprocess", "jet"],
         "unknown pre-processing stage 'jet'"),
    case("reconstruct-preprocess-noisy-preset",
         ["reconstruct", "pointcloud", "{d}/pts.npy", "-o", "{d}/out.obj", "--preset", "noisy", "--preprocess",
          "smooth"], "replaces the noisy preset's own smoothing"),
]


@pytest.mark.parametrize("argv,expect", CASES)
def test_bad_input_is_one_line_exit_2(d, capsys, argv, expect):
    argv = [a.replace("{d}", str(d)) for a in argv]
    expect = [e.replace("{d}", str(d)) for e in expect]
    before = _snapshot(d)
    refused(capsys, argv, None, *expect)
    assert _snapshot(d) == before, "the failed command left files behind"


def test_matrix_size():
    assert len(CASES) >= 60
