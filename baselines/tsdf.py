"""TSDF depth fusion (Curless and Levoy 1996) of a multi-view capture, then marching cubes, through open3d.

Shape letters: V views, H x W pixels, F output faces.

Camera conventions. The capture stores OpenGL cameras: `world_to_camera` (V, 4, 4) maps world points to a
camera frame with x right, y up and the camera looking down -z; `projection` is the OpenGL projection. open3d
wants OpenCV extrinsics (x right, y down, looking down +z), so each extrinsic is diag(1, -1, -1, 1) @
world_to_camera. Depth images hold the positive distance along the view axis (-z_gl = +z_cv), 0 for
background, with row 0 at the top of the image. Pinhole intrinsics from the vertical field of view and the
resolution: fy = (H / 2) / tan(fov_y / 2), fx = fy * (P00 / P11) (= fy for square pixels), and the principal
point at the image centre in pixel-index coordinates, cx = W / 2 - 0.5, cy = H / 2 - 0.5 (OpenGL pixel centres
sit at half-integers of window coordinates).

Grid (issue 58, docs/protocol.md): the voxel is one depth pixel's footprint at the median depth of the
capture (`voxel_pixels` 1; depth / fy), the multi-view analogue of "a voxel no larger than the sample
spacing", capped at 384 voxels a side (`max_resolution`). For the 64-view 256 px captures at distance 2 it
is 0.0074-0.0085 (296 and 259 voxels on the dev torus and bowl; 192 before): 24 s and 0.8-1.2 GiB on one
thread, CD p2s torus 1.20 -> 0.87e-3, bowl 11.8 -> 8.3e-3 (20K metric samples). An explicit `resolution`
overrides it.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from baselines.base import Inputs, Method, Stopwatch, require

log = logging.getLogger(__name__)

#: OpenGL camera frame -> OpenCV camera frame (flip y and z).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def intrinsics(fov_y_degrees: float, width: int, height: int, projection: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) float64 OpenCV pinhole matrix for an OpenGL camera of vertical FOV `fov_y_degrees` and W x H pixels.

    `projection` (4, 4) OpenGL, when given, supplies the aspect (P00 / P11) for non-square pixels.
    """
    if not 0 < fov_y_degrees < 180:
        raise ValueError(f"fov_y_degrees must be in (0, 180), got {fov_y_degrees}")
    fy = 0.5 * height / math.tan(math.radians(fov_y_degrees) / 2)
    fx = fy if projection is None else fy * float(projection[0, 0]) / float(projection[1, 1])
    return np.array([[fx, 0.0, width / 2 - 0.5], [0.0, fy, height / 2 - 0.5], [0.0, 0.0, 1.0]])


def opencv_extrinsics(world_to_camera_gl: np.ndarray) -> np.ndarray:
    """(V, 4, 4) float64 OpenCV world-to-camera matrices from OpenGL ones (V, 4, 4)."""
    return GL_TO_CV @ np.asarray(world_to_camera_gl, dtype=np.float64)


def check_views(views) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated (depth (V, H, W) float32 with background 0, world_to_camera (V, 4, 4), K (3, 3)) of a capture."""
    if views is None:
        raise ValueError("this method needs a multi-view capture (inputs.views is None)")
    depth = np.asarray(views.depth, dtype=np.float32)
    if depth.ndim != 3 or depth.shape[0] == 0:
        raise ValueError(f"views.depth must have shape (V, H, W) with V >= 1, got {depth.shape}")
    w2c = np.asarray(views.world_to_camera, dtype=np.float64)
    if w2c.shape != (depth.shape[0], 4, 4):
        raise ValueError(f"views.world_to_camera must have shape ({depth.shape[0]}, 4, 4), got {w2c.shape}")
    if not (np.isfinite(depth).all() and np.isfinite(w2c).all()):
        raise ValueError("views hold NaN or inf depths or cameras")
    mask = getattr(views, "mask", None)
    if mask is not None:
        depth = np.where(np.asarray(mask, dtype=bool), depth, 0.0).astype(np.float32)
    if not (depth > 0).any():
        raise ValueError("every depth map is empty (the object is outside every camera)")
    proj = getattr(views, "projection", None)
    K = intrinsics(float(views.fov_y_degrees), depth.shape[2], depth.shape[1],
                   None if proj is None else np.asarray(proj, dtype=np.float64))
    return depth, w2c, K


class TSDFFusion(Method):
    name = "tsdf"
    input_kind = "multiview"

    def default_config(self) -> dict:
        return {
            "resolution": None,   # voxels along each side of the fusion cube; None: from the pixel footprint
            "voxel_pixels": 1.0,  # automatic voxel = this x the pixel footprint at the median depth (protocol:
                                  # a voxel no larger than the sample spacing, here one depth pixel)
            "max_resolution": 384,  # cap on the automatic resolution (memory of the uniform volume)
            "bound": 1.1,         # the cube is [-bound, bound]^3 (the object fits in the unit ball)
            "trunc_voxels": 4.0,  # truncation distance, in voxels
            "depth_trunc": 6.0,   # ignore depths beyond this distance
        }

    def prepare(self) -> None:
        require("open3d")

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import trimesh

        o3d = require("open3d")
        depth, w2c, K = check_views(inputs.views)
        V, H, W = depth.shape
        bound = float(cfg["bound"])
        footprint = float(np.median(depth[depth > 0])) / float(K[1, 1])   # one pixel's width at the median depth
        if cfg["resolution"] is not None:
            res = int(cfg["resolution"])
        else:
            if not float(cfg["voxel_pixels"]) > 0:
                raise ValueError(f"tsdf: voxel_pixels must be positive, got {cfg['voxel_pixels']}")
            res = min(int(np.ceil(2 * bound / (float(cfg["voxel_pixels"]) * footprint))), int(cfg["max_resolution"]))
        if res < 8 or bound <= 0:
            raise ValueError(f"tsdf: need resolution >= 8 and bound > 0, got {res}, {bound}")
        voxel = 2 * bound / res
        with sw.stage("integrate"):
            # UniformTSDFVolume: open3d 0.20's ScalableTSDFVolume returned no surface from these float depth
            # maps (measured), the uniform one does.
            vol = o3d.pipelines.integration.UniformTSDFVolume(
                length=2 * bound, resolution=res, sdf_trunc=float(cfg["trunc_voxels"]) * voxel,
                color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor,
                origin=np.full((3, 1), -bound))
            intr = o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
            ext = opencv_extrinsics(w2c)
            gray = o3d.geometry.Image(np.zeros((H, W, 3), dtype=np.uint8))
            for v in range(V):
                rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
                    gray, o3d.geometry.Image(np.ascontiguousarray(depth[v])), depth_scale=1.0,
                    depth_trunc=float(cfg["depth_trunc"]), convert_rgb_to_intensity=False)
                vol.integrate(rgbd, intr, np.ascontiguousarray(ext[v]))
        with sw.stage("marching_cubes"):
            tm = vol.extract_triangle_mesh()
            mesh = trimesh.Trimesh(np.asarray(tm.vertices), np.asarray(tm.triangles, dtype=np.int64),
                                   process=False)
            if len(mesh.faces):
                mesh.merge_vertices()
                mesh.remove_unreferenced_vertices()
        return mesh, {"views": V, "image_size": (H, W), "voxel": voxel, "resolution": res,
                      "pixel_footprint": footprint, "fx": K[0, 0], "fy": K[1, 1]}
