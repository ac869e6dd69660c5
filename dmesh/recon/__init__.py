"""Reconstruction procedures built on `dmesh.DMesh` (DESIGN.md section 6); their shared optimisation loop
is `dmesh.recon.loop`."""
from dmesh.recon.loop import ReconstructionResult
from dmesh.recon.pointcloud import PRESETS, PointCloudConfig, PointCloudResult, reconstruct

__all__ = ["PRESETS", "PointCloudConfig", "PointCloudResult", "ReconstructionResult", "reconstruct"]
