"""Pinhole cameras: pixel rays, projection to pixels, eye positions, look-at, depth lifting.

Letters: V views, H x W pixels, P points.

Conventions (those of the capture, `datasets.capture`, and of the renderers, `dmesh.render`): an OpenGL
camera, `world_to_camera` (4, 4) float64 looking down -Z with +Y up and +X right; vertical field of view
`fov_y_degrees`, square pixels, focal length f = H / (2 tan(fov_y / 2)) in pixels. Pixel (i, j), row i from
the top and column j from the left, covers [j, j + 1) x [i, i + 1) in pixel coordinates (u, v) and samples
the ray through its centre, camera-space direction ((j + 0.5 - W / 2) / f, -(i + 0.5 - H / 2) / f, -1); a
camera-space point (x, y, z) at depth -z > 0 lands at u = W / 2 + f x / (-z), v = H / 2 - f y / (-z).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Default vertical field of view (degrees): fits a unit-radius object at distance 2 with ~10% margin.
FOV_Y_DEGREES = 65.0


def focal_length(fov_y_degrees: float, height: int) -> float:
    """Focal length in pixels of an image `height` pixels high: H / (2 tan(fov_y / 2))."""
    return 0.5 * height / math.tan(math.radians(fov_y_degrees) / 2.0)


def pixel_rays(height: int, width: int, fov_y_degrees: float, *, ndc: bool = False) -> np.ndarray:
    """(H, W, 3) float64 camera-space directions through the pixel centres, z = -1 (not unit length).

    Two roundings of the same rays: ndc=False divides pixel offsets by the focal length (the renderers');
    ndc=True scales normalised device coordinates, x_ndc = 2 (j + 0.5) / W - 1, by tan(fov_y / 2) (the
    capture's; its images were made with these).
    """
    d = np.empty((height, width, 3))
    if ndc:
        t = np.tan(np.radians(fov_y_degrees) / 2.0)
        x = (2.0 * ((np.arange(width) + 0.5) / width) - 1.0) * t * (width / height)
        y = (1.0 - 2.0 * ((np.arange(height) + 0.5) / height)) * t
    else:
        f = focal_length(fov_y_degrees, height)
        x = (np.arange(width) + 0.5 - 0.5 * width) / f
        y = -(np.arange(height) + 0.5 - 0.5 * height) / f
    d[..., 0] = x[None, :]
    d[..., 1] = y[:, None]
    d[..., 2] = -1.0
    return d


def transform_points(points, matrix):
    """(..., 3) points mapped by the affine part of a (4, 4) `matrix` (NumPy arrays or torch tensors)."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def to_pixels(x, y, depth, focal: float, width: int, height: int):
    """Pixel coordinates (u, v) of camera-space points (x, y, -depth) (arrays or tensors; module docstring)."""
    return 0.5 * width + focal * x / depth, 0.5 * height - focal * y / depth


def eyes(world_to_camera: np.ndarray) -> np.ndarray:
    """(V, 3) camera centres of a (V, 4, 4) world_to_camera stack: -R^T t."""
    return -np.einsum("vji,vj->vi", world_to_camera[:, :3, :3], world_to_camera[:, :3, 3])


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-camera (4, 4) float64 for an OpenGL camera at `eye` looking at `target` (camera -Z)."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    z = eye - target
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: the view direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = x, y, z
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def look_at_point(world_to_camera: np.ndarray) -> np.ndarray | None:
    """The point nearest (least squares) to every camera's optical axis, or None when the axes are parallel."""
    centres = eyes(world_to_camera)
    axis = -world_to_camera[:, 2, :3]  # each camera looks down its -z axis
    proj = np.eye(3)[None] - axis[:, :, None] * axis[:, None, :]
    a, b = proj.sum(0), np.einsum("vij,vj->i", proj, centres)
    if np.linalg.cond(a) > 1e8:
        return None
    return np.linalg.solve(a, b)


def perspective(fov_y_degrees: float, aspect: float, near: float, far: float) -> np.ndarray:
    """The OpenGL perspective projection (4, 4) float64 (gluPerspective; camera looks down -Z)."""
    f = 1.0 / np.tan(np.radians(fov_y_degrees) / 2.0)
    p = np.zeros((4, 4))
    p[0, 0] = f / aspect
    p[1, 1] = f
    p[2, 2] = (far + near) / (near - far)
    p[2, 3] = 2.0 * far * near / (near - far)
    p[3, 2] = -1.0
    return p


def lift_depth(depth: np.ndarray, mask: np.ndarray, world_to_camera: np.ndarray, fov_y_degrees: float) -> np.ndarray:
    """(P, 3) float64 world points of every mask pixel of (V, H, W) `depth` (-z_cam), lifted along its ray."""
    rays = pixel_rays(depth.shape[1], depth.shape[2], fov_y_degrees)
    camera_to_world = np.linalg.inv(world_to_camera)
    clouds = []
    for k in range(len(camera_to_world)):
        m = mask[k]
        p = rays[m] * depth[k][m][:, None].astype(np.float64)
        clouds.append(transform_points(p, camera_to_world[k]))
    return np.concatenate(clouds)


@dataclass(frozen=True, eq=False)
class Camera:
    """One pinhole camera in the module's conventions.

    Attributes:
        world_to_camera: (4, 4) float64, OpenGL world-to-camera transform (camera looks down -Z).
        fov_y_degrees: vertical field of view in (0, 180).
        height: H >= 1 pixels.
        width: W >= 1 pixels (square pixels: the horizontal half-angle follows from W / H).
        near: faces with a corner nearer than this (camera-space depth) are not drawn, > 0.
    """

    world_to_camera: np.ndarray
    fov_y_degrees: float = FOV_Y_DEGREES
    height: int = 256
    width: int = 256
    near: float = 1e-2

    def __post_init__(self):
        m = np.ascontiguousarray(self.world_to_camera, dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise ValueError(f"Camera.world_to_camera must be a finite (4, 4) matrix, got shape {m.shape}")
        object.__setattr__(self, "world_to_camera", m)
        if not 0.0 < float(self.fov_y_degrees) < 180.0:
            raise ValueError(f"Camera.fov_y_degrees must be in (0, 180), got {self.fov_y_degrees}")
        for name in ("height", "width"):
            v = getattr(self, name)
            if int(v) != v or not 1 <= int(v) <= 16384:
                raise ValueError(f"Camera.{name} must be an integer in [1, 16384], got {v}")
            object.__setattr__(self, name, int(v))
        if not float(self.near) > 0.0:
            raise ValueError(f"Camera.near must be positive, got {self.near}")

    @property
    def fov_y(self) -> float:
        """Vertical field of view in radians."""
        return math.radians(self.fov_y_degrees)

    @property
    def focal(self) -> float:
        """Focal length in pixels (`focal_length`)."""
        return focal_length(self.fov_y_degrees, self.height)

    @classmethod
    def from_views(cls, world_to_camera, fov_y_degrees: float = FOV_Y_DEGREES, resolution: int = 256,
                   near: float = 1e-2) -> list["Camera"]:
        """One camera per view of a (V, 4, 4) float64 `world_to_camera` stack, square images."""
        w2c = np.asarray(world_to_camera, dtype=np.float64)
        if w2c.ndim != 3 or w2c.shape[1:] != (4, 4):
            raise ValueError(f"world_to_camera must have shape (V, 4, 4), got {w2c.shape}")
        return [cls(m, fov_y_degrees, resolution, resolution, near) for m in w2c]

    @classmethod
    def from_multiview(cls, views, near: float = 1e-2) -> list["Camera"]:
        """The cameras of a `datasets.capture.MultiView` (or anything with its three attributes)."""
        return cls.from_views(views.world_to_camera, views.fov_y_degrees, views.resolution, near)

    def rays(self) -> np.ndarray:
        """(H, W, 3) float64 camera-space directions through the pixel centres, z = -1 (`pixel_rays`)."""
        return pixel_rays(self.height, self.width, self.fov_y_degrees)

    def native_args(self) -> tuple:
        """(world_to_camera, fov_y radians, height, width, near): the camera arguments of the native kernels."""
        return (self.world_to_camera, self.fov_y, self.height, self.width, self.near)


__all__ = ["FOV_Y_DEGREES", "Camera", "focal_length", "pixel_rays", "transform_points", "to_pixels", "eyes",
           "look_at", "look_at_point", "perspective", "lift_depth"]
