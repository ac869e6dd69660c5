"""Shared by the surface-step benches (`lids`, `debris`): one point-cloud `fast` run per robustness input, its
final DMesh extracted again with each variant's surface settings.

`dmesh.recon.pointcloud.reconstruct` extracts its final DMesh once, inside the run; these benches wrap that
call (`pointcloud.extract`) for the length of one run, so each variant sees exactly the DMesh, threshold and
normals the run's own extraction saw.
"""
from __future__ import annotations

import contextlib
import dataclasses
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


def set_constant(module: str, name: str):
    """A `context` for `extractions`: value -> a context manager that sets `module.name` to the value for its
    length (None: leaves the default)."""
    import importlib

    @contextlib.contextmanager
    def setting(value):
        mod = importlib.import_module(module)
        before = getattr(mod, name)
        setattr(mod, name, before if value is None else value)
        try:
            yield
        finally:
            setattr(mod, name, before)

    return setting


def extractions(points, normals, variants, context=None):
    """The `fast` run (seed 0) and {label: (mesh in the run's frame, seconds)} of each variant.

    `variants`: (label, SurfaceConfig overrides, extra) triples; `context(extra)`, when given, is a context
    manager the variant's extraction runs in (e.g. a module constant set for it)."""
    import dmesh.recon.pointcloud as pc
    from dmesh.recon.config import PointCloudConfig

    meshes = {}
    real_extract = pc.extract

    def extract_all(dm, threshold, pd, mode, orient, normals, config, samples=None):
        for label, overrides, extra in variants:
            with context(extra) if context else contextlib.nullcontext():
                t0 = time.perf_counter()
                mesh = real_extract(dm, threshold, pd, mode, orient=orient, normals=normals,
                                    config=dataclasses.replace(config, **overrides), samples=samples)
                seconds = time.perf_counter() - t0
            meshes[label] = (mesh, seconds)
        return real_extract(dm, threshold, pd, mode, orient=orient, normals=normals, config=config,
                            samples=samples)

    pc.extract = extract_all
    try:
        res = pc.reconstruct(points, normals, PointCloudConfig.fast(seed=0))
    finally:
        pc.extract = real_extract
    for mesh, _ in meshes.values():
        mesh.vertices = np.asarray(mesh.vertices) / res.scale + res.center  # the run's own frame change
    return res, meshes


def same_as_run(mesh, res) -> str:
    """"yes" when `mesh` is the run's own output mesh, else "no"."""
    same = (np.array_equal(mesh.faces, res.mesh.faces)
            and np.allclose(mesh.vertices, res.mesh.vertices, rtol=0, atol=1e-12))
    return "yes" if same else "no"
