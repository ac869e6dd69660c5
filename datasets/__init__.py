"""Datasets for the harness: synthetic shapes, real meshes, normalisation, point samples, multi-view capture.

Submodules (imported on first use, so `import datasets` stays cheap):

- `datasets.synthetic`: seeded generators by class (closed / open / mixed), `SHAPES`, `generate`;
- `datasets.meshes`: `load_mesh`, `unique_faces`, `classify`, `orient_outward`;
- `datasets.normalize`: `Transform`, `normalize` (vertex mean, max vertex norm);
- `datasets.sampling`: `sample_points` (area-uniform samples with face normals);
- `datasets.capture`: `capture`, `MultiView` (diffuse + depth + mask images with their cameras).
"""
from __future__ import annotations

import importlib

_SUBMODULES = ("synthetic", "meshes", "normalize", "sampling", "capture")


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
