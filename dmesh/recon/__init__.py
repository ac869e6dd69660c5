"""Reconstruction procedures built on `dmesh.DMesh` (DESIGN.md section 6).

- `config`, `multiview_config`: the settings, presets and recipes of the procedures (torch-free; the multi-view
  ones apart, so that they change no point-cloud run's key);
- `views`: multi-view input checks, normalisation, resampling and image targets;
- `init`: the first points (seeds, Voronoi vertices, poles, carving);
- `optim`: the bounded Adam step;
- `loop`: the one optimisation loop (a step function per phase, history, checkpoints);
- `pointcloud`, `multiview`, `mesh_to_dmesh`: the procedures, each supplying its step functions.

The package imports nothing eagerly, so `dmesh.recon.config` stays cheap; the names below load on first use.
"""

_LAZY = {"ReconstructionResult": "dmesh.recon.loop", "PRESETS": "dmesh.recon.pointcloud",
         "PointCloudConfig": "dmesh.recon.config", "PointCloudResult": "dmesh.recon.pointcloud",
         "reconstruct": "dmesh.recon.pointcloud"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'dmesh.recon' has no attribute {name!r}")


__all__ = sorted(_LAZY)
