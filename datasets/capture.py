"""Multi-view capture of a mesh: diffuse, depth and mask images from a ring of cameras (DESIGN.md 8.2).

Shape letters: V views, H x W pixels (H = W = resolution), F faces.

Rendering: OpenGL offscreen through pyrender's platform layer (OSMesa first, EGL if OSMesa cannot be
loaded; set PYOPENGL_PLATFORM to force one; `datasets.gl_raster`). pyrender's own scene renderer is not used
for the images, because it always rasterises with 4x multisampling, which blends values at silhouettes and
at creases; a small shader pipeline rasterises once per pixel centre (no multisampling, no culling, a float32
depth buffer) and writes, per pixel, the camera-space depth and the id of the front-most face. The
images follow from that exactly:

- pixel (i, j), row i from the top, column j from the left, samples the ray through its centre, with
  camera-space direction d_ij = (x_ndc * t, y_ndc * t, -1), t = tan(fov_y / 2) (aspect 1), where
  x_ndc = 2 (j + 0.5) / W - 1 and y_ndc = 1 - 2 (i + 0.5) / H;
- mask[i, j] = some face covers the pixel centre (OpenGL rasterisation rules, both windings; a centre
  exactly on an edge shared by two faces goes to one of them by the top-left rule); geometry nearer than
  the near plane is clipped;
- depth[i, j] = -z_cam of the front-most face at the pixel centre (distance along the view axis, > 0),
  0 where mask is False;
- diffuse[i, j] = |n_f . d_ij / |d_ij||, where n_f = normalize((b - a) x (c - a)) is the flat unit normal
  of that face (corners a, b, c, expressed in camera space) and d_ij as above; 0 where mask is False.
  This is two-sided Lambert with albedo 1, a unit-intensity light at the camera centre (a headlight, no
  falloff) and no ambient term: for the visible point p on the ray, the direction to the eye is
  v = -p/|p| = -d_ij/|d_ij|, so the intensity is |n . v|. Values lie in [0, 1], float32. A zero-area face
  gets diffuse 0. Depth comes from the rasteriser's perspective-correct float32 interpolation, diffuse
  from float64 normals and rays rounded to float32; a CPU renderer sampling pixel centres the same way
  should match to ~1e-5, except on pixels whose centre falls on a silhouette or crease edge.

Cameras (`camera_rig`): views = n_el x n_az with n_el the largest divisor of `views` not above its square
root (64 -> 8 x 8, 4 -> 2 x 2). Elevations are the centres of n_el equal bands over [-80, 80] degrees (for 8:
-70, -50, ..., 70); azimuths are k * 360 / n_az degrees (plus a seeded offset when seed != 0). The world is
Y-up: a camera at elevation e and azimuth a sits at distance * (cos e sin a, sin e, cos e cos a) and looks at
the origin with +Y as its up hint (azimuth 0 is on +Z). Views are ordered elevation-major (all azimuths of
the lowest ring first).

Conventions: `world_to_camera` maps world to OpenGL camera space (the camera looks down -Z, +Y up, +X
right); `projection` is the OpenGL perspective matrix (gluPerspective) with the vertical field of view
`fov_y_degrees` (65 by default: a unit-radius object at distance 2 subtends 60 degrees, so it fits with
about 10% margin; its silhouette spans 0.906 of the half-width), aspect 1, near = 0.05 * distance, far =
50 * distance. Clip coordinates are projection @ world_to_camera @ [x, y, z, 1]. The camera maths (`look_at`,
`perspective`, `pixel_rays`) is `dmesh.camera`'s, shared with the renderers.
"""
from __future__ import annotations

import json
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from datasets.gl_raster import GL_LOCK, GLUnavailableError, Rasterizer, gl_platform, gl_problem  # noqa: F401
from dmesh.camera import FOV_Y_DEGREES, look_at, perspective, pixel_rays  # noqa: F401 - re-exported

log = logging.getLogger(__name__)

__all__ = ["MultiView", "capture", "camera_rig", "look_at", "perspective", "pixel_rays", "FOV_Y_DEGREES",
           "gl_platform", "GLUnavailableError", "CAPTURE_FILES", "foreign_files"]

#: The files a capture folder holds: `MultiView.save`'s and `dmesh capture`'s `capture.json` at the top, and
#: the previews `images/{diffuse,depth,mask}_K.png`. Anything else there is someone else's (`foreign_files`).
CAPTURE_FILES = ("views.npz", "cameras.json", "capture.json", "diffuse_grid.png")
_IMAGE_FILE = re.compile(r"(?:diffuse|depth|mask)_[0-9]+\.png")

#: Elevation range (degrees) whose equal bands' centres are the camera rings.
ELEVATION_RANGE = (-80.0, 80.0)
NEAR_FACTOR, FAR_FACTOR = 0.05, 50.0


# ----------------------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------------------

def _grid_shape(views: int) -> tuple[int, int]:
    n_el = max(d for d in range(1, int(np.sqrt(views)) + 1) if views % d == 0)
    return n_el, views // n_el


def camera_rig(views: int = 64, distance: float = 2.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The capture cameras (see the module docstring for the layout).

    Returns:
        world_to_camera: (V, 4, 4) float64.
        angles: (V, 2) float64, (elevation, azimuth) of each view in degrees.
    """
    if views < 1:
        raise ValueError(f"views must be >= 1, got {views}")
    if not np.isfinite(distance) or distance <= 0:
        raise ValueError(f"distance must be positive, got {distance}")
    n_el, n_az = _grid_shape(int(views))
    lo, hi = ELEVATION_RANGE
    elev = lo + (hi - lo) * (np.arange(n_el) + 0.5) / n_el
    offset = 0.0 if seed == 0 else float(np.random.default_rng(seed).uniform(0, 360.0 / n_az))
    azim = offset + 360.0 * np.arange(n_az) / n_az
    e, a = np.meshgrid(elev, azim, indexing="ij")
    angles = np.stack([e.ravel(), a.ravel()], 1)
    er, ar = np.radians(angles[:, 0]), np.radians(angles[:, 1])
    eyes = distance * np.stack([np.cos(er) * np.sin(ar), np.sin(er), np.cos(er) * np.cos(ar)], 1)
    w2c = np.stack([look_at(eye) for eye in eyes])
    return w2c, angles


# ----------------------------------------------------------------------------------------------------------
# Result
# ----------------------------------------------------------------------------------------------------------

@dataclass
class MultiView:
    """Captured views of a mesh (conventions in the module docstring).

    Attributes:
        diffuse: (V, H, W) float32 in [0, 1], |n . v| two-sided Lambert with a headlight; 0 on background.
        depth: (V, H, W) float32, camera-space distance along the view axis (-z_cam); 0 on background.
        mask: (V, H, W) bool, True where the mesh covers the pixel centre.
        world_to_camera: (V, 4, 4) float64, OpenGL camera (looks down -Z).
        projection: (4, 4) float64, OpenGL perspective projection shared by all views.
        fov_y_degrees: vertical field of view.
        resolution: H = W.
    """

    diffuse: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    world_to_camera: np.ndarray
    projection: np.ndarray
    fov_y_degrees: float
    resolution: int

    @property
    def views(self) -> int:
        return int(self.diffuse.shape[0])

    @property
    def camera_to_world(self) -> np.ndarray:
        """(V, 4, 4) float64 camera poses (columns: camera axes and centre in world space)."""
        return np.linalg.inv(self.world_to_camera)

    def save(self, directory: str | os.PathLike) -> Path:
        """Write `views.npz` (all arrays), `cameras.json` and PNG images for people into `directory`.

        PNGs: `images/diffuse_XX.png` (8-bit grey), `images/depth_XX.png` (8-bit, near = bright, scaled per
        view, background black), `images/mask_XX.png` and `diffuse_grid.png` (all diffuse views tiled). Only
        `views.npz` is read back by `load`; the PNGs are lossy previews.
        """
        from PIL import Image

        d = Path(directory)
        (d / "images").mkdir(parents=True, exist_ok=True)
        np.savez_compressed(d / "views.npz", diffuse=self.diffuse, depth=self.depth, mask=self.mask,
                            world_to_camera=self.world_to_camera, projection=self.projection,
                            fov_y_degrees=np.float64(self.fov_y_degrees), resolution=np.int64(self.resolution))
        (d / "cameras.json").write_text(json.dumps(self._cameras_dict(), indent=1) + "\n")
        width = len(str(max(self.views - 1, 1)))
        for k in range(self.views):
            Image.fromarray(_to_u8(self.diffuse[k])).save(d / "images" / f"diffuse_{k:0{width}d}.png")
            Image.fromarray(_depth_preview(self.depth[k], self.mask[k])).save(
                d / "images" / f"depth_{k:0{width}d}.png")
            Image.fromarray(self.mask[k].astype(np.uint8) * 255).save(d / "images" / f"mask_{k:0{width}d}.png")
        Image.fromarray(_to_u8(_tile(self.diffuse))).save(d / "diffuse_grid.png")
        return d

    @classmethod
    def load(cls, directory: str | os.PathLike) -> "MultiView":
        """Read a capture written by `save` (from its `views.npz`).

        Raises ValueError naming the file and the field when the cameras' `fov_y_degrees` or `projection`
        is not one `save` writes: the projection must be finite and agree with the field of view (square
        pixels), since the renderers read one and the baselines the other."""
        path = Path(directory) / "views.npz"
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file (not a capture folder)")
        with np.load(path) as z:
            mv = cls(diffuse=z["diffuse"], depth=z["depth"], mask=z["mask"],
                     world_to_camera=z["world_to_camera"], projection=z["projection"],
                     fov_y_degrees=float(z["fov_y_degrees"]), resolution=int(z["resolution"]))
        problem = mv._camera_problem()
        if problem:
            raise ValueError(f"{path}: {problem}")
        return mv

    def _camera_problem(self) -> str | None:
        """What is wrong with `fov_y_degrees` and `projection` (None: they agree, as `capture` makes them)."""
        fov, proj = self.fov_y_degrees, np.asarray(self.projection)
        if not 0 < fov < 180:  # False for NaN too
            return f"field 'fov_y_degrees' must be in (0, 180) degrees, got {fov}"
        if proj.shape != (4, 4):
            return f"field 'projection' must have shape (4, 4), got {proj.shape}"
        if not np.isfinite(proj).all():
            return "field 'projection' holds NaN or infinite values"
        focal = 1.0 / np.tan(np.radians(fov) / 2.0)
        if not np.allclose(np.diag(proj)[:2], focal, rtol=1e-6, atol=0.0):
            return (f"field 'projection' disagrees with fov_y_degrees {fov:g} (its focal terms "
                    f"{proj[0, 0]:.6g}, {proj[1, 1]:.6g}; expected {focal:.6g} for both)")
        return None

    def _cameras_dict(self) -> dict:
        c2w = self.camera_to_world
        return {
            "convention": "OpenGL: camera looks down -Z, +Y up, +X right; clip = projection @ "
                          "world_to_camera @ [x, y, z, 1]; pixel (i, j) = row i from the top, column j "
                          "from the left, sampled at its centre",
            "depth": "camera-space distance along the view axis (-z_cam), 0 on background",
            "diffuse": "|n_f . d| with n_f the flat unit face normal and d the unit ray through the pixel "
                       "centre (two-sided Lambert, light at the camera centre, albedo 1), 0 on background",
            "fov_y_degrees": self.fov_y_degrees,
            "resolution": self.resolution,
            "projection": self.projection.tolist(),
            "views": [{"index": k, "world_to_camera": self.world_to_camera[k].tolist(),
                       "camera_to_world": c2w[k].tolist(), "eye": c2w[k, :3, 3].tolist()}
                      for k in range(self.views)],
        }


def foreign_files(directory: str | os.PathLike) -> list[str]:
    """The entries of the folder `directory` that no capture writes (paths relative to it, sorted): all but
    the plain files named in `CAPTURE_FILES` and an `images/` folder holding only preview PNGs. A capture
    replaces its folder whole, so a folder with any of these must not be replaced (their owner would lose
    them); [] for an empty folder or an earlier capture."""
    d = Path(directory)
    out = []
    for p in d.iterdir():
        if p.name == "images" and p.is_dir() and not p.is_symlink():
            out += [f"images/{q.name}" for q in p.iterdir()
                    if not (_IMAGE_FILE.fullmatch(q.name) and q.is_file() and not q.is_symlink())]
        elif not (p.name in CAPTURE_FILES and p.is_file() and not p.is_symlink()):
            out.append(p.name + ("/" if p.is_dir() else ""))
    return sorted(out)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def _depth_preview(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = np.zeros(depth.shape, np.uint8)
    if mask.any():
        lo, hi = float(depth[mask].min()), float(depth[mask].max())
        out[mask] = _to_u8(1.0 - 0.8 * (depth[mask] - lo) / max(hi - lo, 1e-12))
    return out


def _tile(images: np.ndarray) -> np.ndarray:
    n, h, w = images.shape
    cols = _grid_shape(n)[1]
    rows = -(-n // cols)
    grid = np.zeros((rows * h, cols * w), images.dtype)
    for k in range(n):
        r, c = divmod(k, cols)
        grid[r * h:(r + 1) * h, c * w:(c + 1) * w] = images[k]
    return grid


# ----------------------------------------------------------------------------------------------------------
# Capture
# ----------------------------------------------------------------------------------------------------------

def _unit_face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def _render_views(v, f, normals, w2c, proj, rays, diffuse, depth, mask, callback) -> None:
    """Fill diffuse, depth and mask (V, H, W) in place, one view at a time."""
    views, resolution = diffuse.shape[:2]
    rast = Rasterizer(v, f, resolution)
    try:
        for k in range(views):
            d, face = rast.render(w2c[k], proj)
            hit = face >= 0
            n_cam = normals[face[hit]] @ w2c[k, :3, :3].T
            diffuse[k][hit] = np.abs(np.einsum("ij,ij->i", n_cam, rays[hit]))
            depth[k] = d
            mask[k] = hit
            if callback is not None:
                callback(k + 1, views)
    finally:
        rast.close()


def capture(mesh: trimesh.Trimesh, views: int = 64, resolution: int = 256, distance: float = 2.0,
            seed: int = 0, *, fov_y_degrees: float = FOV_Y_DEGREES,
            callback: Callable[[int, int], None] | None = None) -> MultiView:
    """Render diffuse, depth and mask images of `mesh` from the camera rig (module docstring).

    The mesh is used as given (normalise it first for the standard frame). Deterministic: the same mesh
    and settings give identical arrays.

    Args:
        mesh: vertices (V, 3), faces (F, 3), F >= 1, finite, F < 2^24.
        views: number of cameras (64: 8 elevations x 8 azimuths).
        resolution: image side H = W in pixels.
        distance: camera distance from the origin.
        seed: 0 for the canonical rig, else a seeded azimuth offset of the whole rig.
        fov_y_degrees: vertical field of view.
        callback: called as callback(done, views) after each view (progress bars live in the CLI).

    Returns:
        A `MultiView` with (views, resolution, resolution) images.

    Raises:
        ValueError: empty or non-finite mesh, bad settings, or a mesh that no camera sees.
        GLUnavailableError: neither OSMesa nor EGL can be started.
    """
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    if len(f) == 0 or len(v) == 0:
        raise ValueError("cannot capture a mesh without faces")
    if not np.isfinite(v).all():
        raise ValueError("cannot capture a mesh with NaN or infinite vertices")
    if len(f) >= 1 << 24:
        raise ValueError(f"too many faces for the capture's float face ids: {len(f)} >= 2^24")
    resolution, views = int(resolution), int(views)
    if resolution < 1 or resolution > 8192:
        raise ValueError(f"resolution must be in [1, 8192], got {resolution}")
    if not 0 < fov_y_degrees < 180:
        raise ValueError(f"fov_y_degrees must be in (0, 180), got {fov_y_degrees}")
    w2c, _ = camera_rig(views, distance, seed)
    proj = perspective(fov_y_degrees, 1.0, NEAR_FACTOR * distance, FAR_FACTOR * distance)
    rays = pixel_rays(resolution, resolution, fov_y_degrees, ndc=True)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    normals = _unit_face_normals(v, f)

    diffuse = np.zeros((views, resolution, resolution), np.float32)
    depth = np.zeros((views, resolution, resolution), np.float32)
    mask = np.zeros((views, resolution, resolution), bool)
    with GL_LOCK:
        _render_views(v, f, normals, w2c, proj, rays, diffuse, depth, mask, callback)
    if not mask.any():
        lo, hi = v.min(0), v.max(0)
        raise ValueError(f"no camera sees the mesh (bounds {np.round(lo, 3).tolist()} to "
                         f"{np.round(hi, 3).tolist()}; cameras at distance {distance} look at the origin)")
    log.debug("captured %d views at %dx%d (%d faces)", views, resolution, resolution, len(f))
    return MultiView(diffuse=diffuse, depth=depth, mask=mask, world_to_camera=w2c, projection=proj,
                     fov_y_degrees=float(fov_y_degrees), resolution=resolution)
