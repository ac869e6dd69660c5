"""The surface step's stages and settings (`dmesh.surface.STAGES`, `SurfaceConfig`): each stage recorded, every
optional one skippable, overrides by section, the run configs' `surface` field, docs/surface.md in step with the
code, and the package's size limits."""
from __future__ import annotations

import ast
import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from dmesh import solid
from dmesh.surface import STAGES, SurfaceConfig, run
from dmesh.surface.config import SECTIONS, TOP_FIELDS
from common import ball_labels, cloud_diagram

ROOT = Path(__file__).resolve().parents[1]
OPTIONAL = [s.name for s in STAGES if not s.required]

#: Today's settings, written out: a change of a default changes every output, so it must show here.
DEFAULTS = {
    "vote": {"directions": 9, "max_open": 0.25, "min_thickness": 0.5, "sign_neighbours": 3},
    "revote": {"min_faces": 64, "max_open": 0.25, "max_boundary": 0.1},
    "pinches": {"rounds": 20},
    "lids": {"max_hole": 64},
    "fills": {"max_hole": 64, "retries": 3, "tets": True, "tets_sheets": 1e-3, "faired": True},
    "spans": {"ratio": 6.0},
    "reopen": {"ratio": 2.0, "share": 0.5},
    "crumbs": {"max_faces": 4, "max_debris": 1e-3, "floating": 4.0, "beside": 0.05, "floating_max_faces": 64,
               "plane_neighbours": 16},
    "stacked": {"within": 1.0, "max_faces": 64, "neighbours": 16, "over": 0.1, "spacings": 3.0},
    "wind_sheets": {"neighbours": 10, "confident": 0.5, "turn_faces": True},
    "sheet_holes": {"max_edges": 24, "max_share": 0.25, "gap": 8.0, "stray_off": 0.3, "stray_neighbours": 16,
                    "retries": 3},
    "closed_crumbs": {"max_faces": 4},
    "copies": {"separation": 0.05},
    "fair": {"continuity": 1, "density": 4.0, "untangle_rounds": 5},
    "seed": 0, "workers": 1, "spacing_neighbours": 8, "clean": True, "skip": [], "mode": "auto",
}


@pytest.fixture(scope="module")
def holed_ball():
    """A ball's boundary with a cap missing (a lid's hole), a one-face hole (a fill's) and a fin (a sheet face
    on its edge), with the ball's own boundary faces as input samples."""
    pd = cloud_diagram(n=1500, seed=4)
    inside = ball_labels(pd)
    walls = solid.boundary_mask(pd, inside)
    centre = pd.points[pd.faces.astype(np.int64)].mean(1)
    holed = walls & ~(centre[:, 2] > 0.4)
    holed[np.flatnonzero(holed)[0]] = False
    edges = {tuple(e) for e in np.sort(pd.faces[holed][:, [0, 1]], 1).tolist()}
    holed[next(i for i in np.flatnonzero(~walls) if tuple(sorted(pd.faces[i, [0, 1]])) in edges)] = True
    return pd, holed, centre[walls]


def _config(**overrides) -> SurfaceConfig:
    return SurfaceConfig().with_overrides({"lids.max_hole": 8, "fills.max_hole": 8, "revote.min_faces": 8,
                                           **overrides})


def test_every_stage_runs_in_order_and_records_what_it_did(holed_ball):
    pd, walls, samples = holed_ball
    out = run(pd, walls, samples=samples, config=_config())
    stages = out.info["stages"]
    assert list(stages) == [s.name for s in STAGES]
    for record in stages.values():
        assert {"closed", "sheets", "added", "dropped", "seconds"} <= set(record)
    last = stages["fair"]
    assert (last["closed"], last["sheets"]) == (out.closed, len(out.faces) - out.closed)
    assert stages["lids"]["lids"] == out.info["lids"] == 1 and stages["lids"]["added"] == out.info["lid_faces"] > 0
    assert stages["fills"]["holes_filled"] == 1 and stages["fins"]["dropped"] == stages["fins"]["fins_dropped"] >= 1
    assert stages["fair"]["lids_faired"] and stages["fair"]["added"] > 0 and stages["vote"]["vote"] == "parity"
    assert out.info["rim_edges"] == stages["rim"]["rim_edges"]  # the flat keys stay beside the records
    # Orientation only: the labelling and the sheets' winding, nothing cleaned.
    bare = run(pd, walls, config=_config(clean=False))
    assert list(bare.info["stages"]) == [s.name for s in STAGES if not s.cleanup]


@pytest.mark.parametrize("name", OPTIONAL)
def test_each_optional_stage_can_be_left_out(holed_ball, name):
    pd, walls, samples = holed_ball
    out = run(pd, walls, samples=samples, config=_config(skip=[name]))
    assert list(out.info["stages"]) == [s.name for s in STAGES if s.name != name]
    assert len(out.faces) > 0


def test_a_required_or_unknown_stage_cannot_be_skipped():
    for name in [s.name for s in STAGES if s.required] + ["no_such_stage"]:
        with pytest.raises(ValueError, match=f"'{name}' cannot be skipped; the stages that may be: revote"):
            SurfaceConfig(skip=[name])
    assert SurfaceConfig(skip="lids").skip == ("lids",)


def test_overrides_by_dotted_key_or_nested_mapping():
    base = SurfaceConfig()
    dotted = base.with_overrides({"lids.max_hole": 100, "skip": ["stacked"], "seed": 3})
    nested = base.with_overrides({"lids": {"max_hole": 100}, "skip": ("stacked",), "seed": 3})
    assert dotted == nested and dotted.lids.max_hole == 100 and dotted.fills.max_hole == 64
    assert dotted.skip == ("stacked",) and dotted.seed == 3 and base.lids.max_hole == 64
    assert SurfaceConfig(**dotted.to_dict()) == dotted
    assert json.loads(json.dumps(SurfaceConfig().to_dict())) == DEFAULTS
    cases = [({"lid.max_hole": 1}, "unknown key 'lid.max_hole'; sections: vote, revote"),
             ({"lids.maxhole": 1}, "SurfaceConfig.lids has no field 'maxhole'; its fields: max_hole"),
             ({"lids.max_hole.x": 1}, "deeper than SECTION.FIELD"), ({"lids": 5}, "'lids' is a section"),
             ({"lids.max_hole": -1}, "SurfaceConfig.lids.max_hole must be >= 0"),
             ({"nope": 1}, "run-wide fields: seed, workers, spacing_neighbours, clean")]
    for overrides, message in cases:
        with pytest.raises(ValueError, match=re.escape(message)) as info:
            base.with_overrides(overrides)
        assert "\n" not in str(info.value)


def test_the_run_configs_hold_the_surface_settings():
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.multiview_config import MultiViewConfig

    cfg = PointCloudConfig.from_preset("fast", {"surface.lids.max_hole": 100, "seed": 5, "workers": 3})
    assert cfg.surface.lids.max_hole == 100 and (cfg.surface.seed, cfg.surface.workers) == (5, 3)
    assert PointCloudConfig.from_preset("fast", {"surface": {"lids": {"max_hole": 100}}}).surface == \
        dataclasses.replace(cfg.surface, seed=0, workers=2)
    assert PointCloudConfig(**dataclasses.asdict(cfg)) == cfg                # a run's config JSON rebuilds it
    assert dataclasses.replace(cfg, seed=7).surface.seed == 7
    assert PointCloudConfig.fast().surface == SurfaceConfig(workers=2)       # today's settings
    views = MultiViewConfig.from_preset("fast", {"surface.fills.max_hole": 10, "seed": 2})
    assert views.surface.fills.max_hole == 10 and views.surface.seed == 2
    assert not views.surface.wind_sheets.turn_faces and views.surface.spans.ratio == 0.0   # from images
    with pytest.raises(ValueError, match="surface.seed: the surface step takes the run's seed"):
        PointCloudConfig.from_preset("fast", {"surface.seed": 1})
    with pytest.raises(ValueError, match="SurfaceConfig.lids has no field 'maxhole'"):
        PointCloudConfig.from_preset("fast", {"surface.lids.maxhole": 1})
    with pytest.raises(ValueError, match=r"unknown config keys \['surfaces'\]"):
        PointCloudConfig.from_preset("fast", {"surfaces": {}})


def test_cli_sets_a_surface_field(tmp_path, capsys):
    from datasets.normalize import normalize
    from datasets.sampling import sample_points
    from datasets.synthetic import generate
    from eval.cli import main

    pts, nrm = sample_points(normalize(generate("sphere"))[0], 3000, 0)
    np.save(tmp_path / "pts.npy", np.c_[pts, nrm])
    out = tmp_path / "mesh.obj"
    args = ["-q", "reconstruct", "pointcloud", str(tmp_path / "pts.npy"), "-o", str(out), "--preset", "tiny",
            "--steps", "0", "--set", "num_init=300", "--set", "surface.fills.max_hole=100",
            "--set", "surface.skip=[stacked]"]
    assert main(args) == 0, capsys.readouterr().err
    report = json.loads((tmp_path / "mesh.timings.json").read_text())
    assert report["config"]["surface"]["fills"]["max_hole"] == 100
    assert "stacked" not in report["info"]["surface"]["stages"] and "fills" in report["info"]["surface"]["stages"]
    assert main(args[:-4] + ["--set", "surface.fills.maxhole=1"]) == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "no field 'maxhole'" in err


def _surface_doc() -> str:
    return (ROOT / "docs" / "surface.md").read_text()


def test_docs_list_the_stages_in_order_and_every_setting():
    text = _surface_doc()
    listed = re.findall(r"^\d+\. \*\*(\w+)\*\*", text, re.M)
    assert listed == [s.name for s in STAGES]
    import dmesh.surface as package

    assert re.findall(r"^\d+\. (\w+):", package.__doc__, re.M) == [s.name for s in STAGES]
    for section, cls in SECTIONS.items():
        for f in dataclasses.fields(cls):
            assert f"`{section}.{f.name}`" in text, f"docs/surface.md does not name {section}.{f.name}"
    for name in TOP_FIELDS:
        assert f"`{name}`" in text, name
    assert {s.section for s in STAGES} - {None} == set(SECTIONS)


def test_no_test_study_or_bench_patches_a_surface_setting():
    """The surface step's settings are `SurfaceConfig` fields: nothing sets a module constant of it instead."""
    patch = re.compile(r"setattr\([^,]*(?:surface|repair|extract|debris|holes|finish|topology|crossings|winding"
                       r"|label)[^,]*,\s*[\"'][A-Z][A-Z0-9_]+[\"']|set_constant\(\s*[\"']dmesh\.")
    hits = [f"{p.relative_to(ROOT)}:{text[:m.start()].count(chr(10)) + 1}"
            for folder in ("tests", "studies", "eval") for p in (ROOT / folder).rglob("*.py")
            if p.name != Path(__file__).name for text in [p.read_text()] for m in patch.finditer(text)]
    assert not hits, hits
    assert patch.search('monkeypatch.setattr(debris, "FLOATING", 1)')  # (the pattern finds what it should)


def test_the_package_stays_in_small_modules_and_functions():
    long = {}
    for path in (ROOT / "dmesh" / "surface").glob("*.py"):
        text = path.read_text()
        if len(text.splitlines()) > 400:
            long[path.name] = len(text.splitlines())
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 80:
                long[f"{path.name}::{node.name}"] = node.end_lineno - node.lineno + 1
    assert not long, long
    assert not (ROOT / "dmesh" / "repair.py").exists()
