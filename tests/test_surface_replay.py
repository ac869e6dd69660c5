"""`dmesh.surface.replay.run_variants` gives each config exactly what `dmesh.surface.run` gives it alone."""
from __future__ import annotations

import numpy as np
import pytest

from dmesh.surface import STAGES, run
from dmesh.surface.replay import run_variants


@pytest.fixture(scope="module")
def plant_step():
    """The triangulation, mesh faces and input of a small `fast` reconstruction of the mixed plant (sheets, a
    closed part, holes: most stages act on it)."""
    from datasets import synthetic
    from datasets.sampling import sample_points
    from dmesh.extract import mesh_faces
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct

    points, normals = sample_points(synthetic.generate("plant"), 6000, seed=0)
    cfg = PointCloudConfig.fast(seed=0, outlier_std=0.0, auto_smooth_k=0, redo_fragmented=0.0)
    result = reconstruct(points, normals, cfg)
    pd = result.dmesh.power_diagram()
    walls = mesh_faces(pd, result.dmesh.reals.detach().numpy() > cfg.threshold, cfg.extraction)
    unit = (np.asarray(points, np.float64) - result.center) * result.scale
    return pd, walls, (unit, np.asarray(normals, np.float64)), cfg.surface


def _same(a, b) -> None:
    assert np.array_equal(a.faces, b.faces) and np.array_equal(a.vertices, b.vertices) and a.closed == b.closed
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.lid, b.lid) and np.array_equal(a.span, b.span)
    counts = {k: v for k, v in a.info.items() if k != "stages"}
    assert counts == {k: v for k, v in b.info.items() if k != "stages"}
    assert list(a.info["stages"]) == list(b.info["stages"])
    for name, record in a.info["stages"].items():
        assert {k: v for k, v in record.items() if k != "seconds"} == \
            {k: v for k, v in b.info["stages"][name].items() if k != "seconds"}, name


def test_every_variant_is_what_the_step_gives_it_alone(plant_step):
    pd, walls, normals, base = plant_step
    configs = {"all": base, "mode=open": base.with_overrides({"mode": "open"}),
               "lids.max_hole=8": base.with_overrides({"lids.max_hole": 8}),
               "-fins-fair": base.with_overrides({"skip": ["fins", "fair"]}),
               "orientation only": base.with_overrides({"clean": False})}
    configs.update({f"-{s.name}": base.with_overrides({"skip": [s.name]}) for s in STAGES if not s.required})
    together = run_variants(pd, walls, normals, normals[0], configs)
    assert list(together) == list(configs)
    for name, cfg in configs.items():
        _same(together[name], run(pd, walls, normals, normals[0], cfg))
    # The variants differ where their stages act (the check above is not comparing one mesh with itself).
    assert len({len(together[name].faces) for name in configs}) > 3
