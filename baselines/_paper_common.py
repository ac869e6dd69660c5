"""Helpers shared by the paper's optimisation baselines (`voromesh`, `flexicubes`, `nie`).

Shape letters: V views, H x H capture pixels, R x R optimised pixels, N mesh vertices, F mesh faces.

The multi-view baselines fit an opaque triangle mesh to the capture's diffuse and depth images with the
project's own renderer, `dmesh.render.soft_render`, every face at opacity 1. For an opaque mesh that is a hard
rasteriser (the front-most face of each pixel, its depth and flat two-sided Lambert shading) except within
`edge_width` pixels of a triangle edge, where a smoothstep coverage band gives the silhouette gradients an
edge term would give (nvdiffrast's antialiasing in the originals). The loss is DMesh's multi-view image
loss (`dmesh.recon.multiview`): L1 of the diffuse images plus `lambda_depth` x L1 of the depth channel
(far - z) / 2 (0 on the background, so peeling a wrong layer off the background lowers the loss), over
whole images, against targets that carry the renderer's own silhouette band (`soft_band_targets`, so the
fit is unbiased), area-averaged to R pixels.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math

import numpy as np

log = logging.getLogger(__name__)


@contextlib.contextmanager
def torch_threads(n: int):
    """Run a block with `n` torch threads (restored afterwards). Small torch ops on a busy 2-core machine are
    many times slower with 2 OpenMP threads (spin-waits) than with 1."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(old)


@dataclasses.dataclass
class ImageTargets:
    """A capture prepared for fitting (module docstring).

    Attributes:
        cameras: V `dmesh.render.Camera`s at R x R pixels.
        diffuse: (V, R, R) float32 tensor, targets of the diffuse channel.
        depth: (V, R, R) float32 tensor, targets of the depth channel (far - z) / 2, 0 on the background.
        far: (V,) float32 tensor, per-view far distance of the depth channel.
        center: (3,) float64 centre of the lifted depth pixels' bounding box (world frame).
        half_extent: half the longest side of that bounding box.
    """

    cameras: list
    diffuse: object
    depth: object
    far: object
    center: np.ndarray
    half_extent: float

    @property
    def views(self) -> int:
        return len(self.cameras)


def image_targets(views, resolution: int | None, edge_width: float) -> ImageTargets:
    """Validated targets and cameras of a capture (`datasets.capture.MultiView` or alike).

    Args:
        views: the capture; resolution: optimised image side R (None or >= H: the capture's); edge_width:
            the soft renderer's band width in optimised pixels.
    Raises:
        ValueError: no views, or a capture `dmesh.recon.views.check_views` rejects (one line).
    """
    import torch

    from dmesh.camera import Camera, lift_depth
    from dmesh.recon.views import DEPTH_SPAN, check_views, soft_band_targets

    if views is None:
        raise ValueError("this method needs a multi-view capture (inputs.views is None)")
    vw = check_views(views)
    h = vw.diffuse.shape[1]
    res = h if resolution is None else min(int(resolution), h)
    if res < 8:
        raise ValueError(f"the optimised image resolution must be at least 8 pixels, got {res}")
    pts = lift_depth(vw.depth, vw.mask, vw.world_to_camera, vw.fov_y_degrees)
    lo, hi = pts.min(0), pts.max(0)
    center, half = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())
    if not half > 1e-9:
        raise ValueError("the lifted depth pixels span no volume: a degenerate capture")
    c2w = np.linalg.inv(vw.world_to_camera)
    eyes = c2w[:, :3, 3]
    far = np.linalg.norm(eyes - center, axis=1) + math.sqrt(3.0) * half
    channel = (far[:, None, None] * vw.mask - vw.depth.astype(np.float64)) / DEPTH_SPAN
    diffuse, depth = soft_band_targets([vw.diffuse, channel], vw.mask, res, edge_width)
    return ImageTargets(cameras=Camera.from_views(vw.world_to_camera, vw.fov_y_degrees, res),
                        diffuse=torch.from_numpy(diffuse), depth=torch.from_numpy(depth),
                        far=torch.from_numpy(far.astype(np.float32)), center=center, half_extent=half)


def image_loss(verts, faces, targets: ImageTargets, ids, *, edge_width: float = 1.0, lambda_depth: float = 1.0,
               num_threads: int | None = None):
    """Mean over the views `ids` of L1(diffuse) + lambda_depth x L1(depth channel) of the opaque mesh.

    Args:
        verts: (N, 3) float tensor (differentiable); faces: (F, 3) int64 tensor; targets: `image_targets`;
        ids: view indices; edge_width, num_threads: `dmesh.render.soft_render`'s.
    Returns:
        a scalar tensor.
    """
    import torch

    from dmesh.recon.views import depth_channel
    from dmesh.render import soft_render

    opacity = torch.ones(len(faces), dtype=torch.float32)
    total = verts.new_zeros(())
    for i in ids:
        i = int(i)
        out = soft_render(verts, faces, opacity, targets.cameras[i], edge_width=edge_width, num_threads=num_threads)
        loss = (out["diffuse"] - targets.diffuse[i]).abs().mean()
        if lambda_depth > 0:
            z = depth_channel(out["depth"][None], out["alpha"][None], targets.far[i:i + 1])[0]
            loss = loss + lambda_depth * (z - targets.depth[i]).abs().mean()
        total = total + loss
    return total / max(1, len(ids))


def sphere_sdf(nodes: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """(...) float64 signed distance (negative inside) of nodes (..., 3) to the sphere (center, radius)."""
    return np.linalg.norm(nodes - center, axis=-1) - radius
