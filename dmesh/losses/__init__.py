"""Losses and regularisers of the reconstruction procedures (DESIGN.md section 5)."""
from dmesh.losses.chamfer import ExpectedChamfer, SurfaceSamples, chamfer_l1, expected_min_distance, sample_faces
from dmesh.losses.regularizers import quality_regularizer, ramp, real_regularizer, weight_regularizer

__all__ = ["ExpectedChamfer", "SurfaceSamples", "chamfer_l1", "expected_min_distance", "sample_faces",
           "quality_regularizer", "ramp", "real_regularizer", "weight_regularizer"]
