"""Shared by the surface-step benches (`lids`, `debris`): one point-cloud `fast` run per robustness input, its
final DMesh extracted again with each variant's surface settings.

`dmesh.recon.pointcloud.reconstruct` makes the surface of its final DMesh once, inside the run; these benches
wrap that call (`dmesh.surface.surface_mesh`) for the length of one run, so each variant sees exactly the
faces, normals and samples the run's own surface step saw, with the run's surface settings plus the variant's
overrides (`SurfaceConfig.with_overrides`: "stacked.within", "skip", ...).
"""
from __future__ import annotations

import time

import numpy as np

WORK = "runs/paper"  # the input cache of the robustness sweep
SCAN = {"normals": "estimated", "scan": 6}
REALISTIC = {"noise": 0.0025, "normals": "estimated", "outliers": 0.01, "scan": 6}


def cloud(shape: str, corruption: dict):
    """(points, normals, GT path, class) of the robustness sweep's input of `shape` with `corruption`."""
    from eval.runner import prepare_gt, prepare_input
    from eval.sweep import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), WORK, 1.0)
    settings = {"n_points": 100_000, "radius": 1.0, "corruption": dict(corruption)}
    with np.load(prepare_input(ref, gt_path, "pointcloud", settings, 0, WORK)) as z:
        return z["points"], z["normals"], gt_path, ref.category


def extractions(points, normals, variants):
    """The `fast` run (seed 0) and {label: (mesh in the run's frame, seconds)} of each variant.

    `variants`: (label, overrides of the run's `SurfaceConfig`) pairs."""
    import dmesh.recon.pointcloud as pc
    import dmesh.surface as surface
    from dmesh.recon.config import PointCloudConfig

    meshes = {}
    real_surface_mesh = surface.surface_mesh

    def every_variant(pd, walls, normals=None, samples=None, config=None):
        for label, overrides in variants:
            t0 = time.perf_counter()
            mesh = real_surface_mesh(pd, walls, normals, samples, config.with_overrides(overrides))
            meshes[label] = (mesh, time.perf_counter() - t0)
        return real_surface_mesh(pd, walls, normals, samples, config)

    surface.surface_mesh = every_variant  # (`DMesh.extract_mesh` looks it up at each call)
    try:
        res = pc.reconstruct(points, normals, PointCloudConfig.fast(seed=0))
    finally:
        surface.surface_mesh = real_surface_mesh
    for mesh, _ in meshes.values():
        mesh.vertices = np.asarray(mesh.vertices) / res.scale + res.center  # the run's own frame change
    return res, meshes


def same_as_run(mesh, res) -> str:
    """"yes" when `mesh` is the run's own output mesh, else "no"."""
    same = (np.array_equal(mesh.faces, res.mesh.faces)
            and np.allclose(mesh.vertices, res.mesh.vertices, rtol=0, atol=1e-12))
    return "yes" if same else "no"
