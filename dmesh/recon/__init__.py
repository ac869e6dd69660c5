"""Reconstruction procedures built on `dmesh.DMesh` (DESIGN.md section 6)."""
from dmesh.recon.pointcloud import PRESETS, PointCloudConfig, PointCloudResult, reconstruct

__all__ = ["PRESETS", "PointCloudConfig", "PointCloudResult", "reconstruct"]
