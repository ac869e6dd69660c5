"""The benches' wrappers around library calls: they must take every argument the library passes, so a change of
a library signature fails here rather than in a bench that no test runs."""
from __future__ import annotations

import numpy as np

from datasets.normalize import normalize
from datasets.sampling import sample_points
from datasets.synthetic import generate
from dmesh.surface.topology import hole_loops


def test_surface_variants_extract_the_runs_final_dmesh_again():
    """`studies.surface_variants.extractions` (the `debris` and `lids` benches) wraps the point-cloud run's
    extraction for the length of one run: a variant without overrides gives the run's own mesh, in the run's
    frame, and a variant's overrides reach its extraction (here the sheet clean-up left out, so a slightly noisy
    sheet keeps the small holes the clean-up fills)."""
    from datasets.corrupt import add_noise
    from studies.surface_variants import extractions, same_as_run

    gt = normalize(generate("wavy_sheet"))[0]
    pts, nrm = sample_points(gt, 20_000, 0)
    pts = add_noise(pts, 0.005, seed=0)
    res, meshes = extractions(pts, nrm, [("default", {}), ("orient only", {"clean": False})])
    assert set(meshes) == {"default", "orient only"}
    assert same_as_run(meshes["default"][0], res) == "yes"
    assert same_as_run(meshes["orient only"][0], res) == "no"
    holes = {k: len(hole_loops(np.asarray(m.faces))) for k, (m, _) in meshes.items()}
    assert holes["orient only"] > holes["default"], holes
