"""Simulated range scans of a mesh: the first hits of random rays from a few cameras around it.

Shape letters: N points, C cameras, R rays, F faces.

The protocol follows the scanner simulation of dsr-benchmark (Sulzer et al., TPAMI 2025; described in
`../shared/reference/baselines_and_benchmarks.md`; no code of theirs is used): cameras sit at random on
spheres of radius 2.5 r and 3.5 r around the object, r being half the diagonal of its bounding box, and
every point is the first intersection of a ray from a camera with the surface. So the density varies with
distance and viewing angle, and whatever no camera sees (the inside of a closed body, the far side of a
concavity) gets no points at all.

Here:
- camera k sits on the sphere of radius `radii[k % 2] * r` around the bounding-box centre, in a direction drawn
  uniformly on the unit sphere (seeded); so with an even count half the cameras are on each sphere;
- each camera casts rays in directions drawn uniformly (in solid angle) within the cone that just contains the
  object's bounding sphere, like a pinhole scanner with uniform angular resolution aimed at the object;
- the rays are intersected with the mesh by open3d's `RaycastingScene` (Embree), in batches, until at least N
  rays hit; then N of the hits are kept, chosen uniformly at random (seeded), so every camera keeps its share;
- range noise displaces each hit along its own ray: p = o + (t + e) d with e ~ N(0, noise).

The hits carry the unit normal of the triangle they hit (its winding orientation) and the index of the camera
that saw them; `datasets.corrupt` turns those into the normals a real scan would have (estimated from the
points, oriented toward that camera).
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import trimesh

log = logging.getLogger(__name__)

__all__ = ["Scan", "simulate_scan", "camera_positions", "DEFAULT_RADII", "MAX_CAMERAS"]

#: Camera distances from the bounding-box centre, in units of half the bounding-box diagonal (dsr-benchmark).
DEFAULT_RADII = (2.5, 3.5)
#: The most cameras a scan may have (a sanity bound; real scans of one object use a handful).
MAX_CAMERAS = 1024
#: Ray batches cast before giving up on reaching N hits (each sized from the hit rate of the previous ones).
MAX_BATCHES = 40


@dataclasses.dataclass(frozen=True)
class Scan:
    """The outcome of `simulate_scan`.

    Attributes:
        points: (N, 3) float64 hit points (with range noise when asked).
        face_normals: (N, 3) float64 unit normals of the hit triangles (winding orientation, not flipped).
        camera_index: (N,) int64, the camera (row of `cameras`) whose ray produced each point.
        cameras: (C, 3) float64 camera positions.
        ray_dirs: (N, 3) float64 unit direction of each point's ray (from its camera).
    """

    points: np.ndarray
    face_normals: np.ndarray
    camera_index: np.ndarray
    cameras: np.ndarray
    ray_dirs: np.ndarray


def _bounds(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """(bounding-box centre (3,), half its diagonal r)."""
    lo, hi = np.asarray(mesh.bounds, np.float64)
    return (lo + hi) / 2.0, float(np.linalg.norm(hi - lo) / 2.0)


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) directions uniform on the unit sphere (normalised Gaussian vectors)."""
    v = rng.standard_normal((n, 3))
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.maximum(norm, 1e-300)


def camera_positions(mesh: trimesh.Trimesh, cameras: int, seed: int = 0,
                     radii: tuple[float, ...] = DEFAULT_RADII) -> np.ndarray:
    """(C, 3) float64 camera positions: camera k at `radii[k % len(radii)] * r` from the bounding-box centre
    in a seeded direction uniform on the sphere (r = half the bounding-box diagonal)."""
    centre, r = _bounds(mesh)
    rng = np.random.default_rng([int(seed), 0x5CA4])
    dirs = _unit_vectors(rng, cameras)
    dist = np.array([radii[k % len(radii)] for k in range(cameras)], np.float64) * r
    return centre + dirs * dist[:, None]


def _cone_directions(rng: np.random.Generator, axis: np.ndarray, half_angle: float, n: int) -> np.ndarray:
    """(n, 3) unit directions uniform in solid angle within the cone of `half_angle` around unit `axis`."""
    cos_t = rng.uniform(np.cos(half_angle), 1.0, n)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t**2))
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    # An orthonormal frame (u, v, axis): u from the coordinate axis least aligned with `axis`.
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    return (sin_t * np.cos(phi))[:, None] * u + (sin_t * np.sin(phi))[:, None] * v + cos_t[:, None] * axis


def _check(mesh, n, cameras, noise, radii) -> None:
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("simulate_scan: expected a trimesh.Trimesh with faces")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"simulate_scan: n must be a positive integer, got {n!r}")
    if isinstance(cameras, bool) or not isinstance(cameras, (int, np.integer)) or not 1 <= cameras <= MAX_CAMERAS:
        raise ValueError(f"simulate_scan: cameras must be an integer from 1 to {MAX_CAMERAS}, got {cameras!r}")
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"simulate_scan: noise must be a finite number >= 0, got {noise!r}")
    if not radii or min(radii) <= 1.0:
        raise ValueError(f"simulate_scan: camera radii must be > 1 (outside the bounding sphere), got {radii!r}")


def simulate_scan(mesh: trimesh.Trimesh, n: int, cameras: int, seed: int = 0, noise: float = 0.0,
                  radii: tuple[float, ...] = DEFAULT_RADII) -> Scan:
    """N first hits of random rays from `cameras` cameras (see the module docstring).

    Args:
        mesh: the surface, (V, 3) vertices and (F, 3) faces.
        n: number of points to return.
        cameras: number of cameras, 1 to `MAX_CAMERAS`.
        seed: seed of the camera positions, ray directions, the choice of hits and the noise.
        noise: standard deviation of the range noise along each ray, in the mesh's units.
        radii: camera distances in units of half the bounding-box diagonal (each > 1).
    Returns:
        a `Scan` of exactly n points.
    Raises:
        ValueError: bad arguments, or no ray hits the mesh (e.g. a degenerate mesh).
    """
    import open3d as o3d

    _check(mesh, n, cameras, noise, radii)
    centre, r = _bounds(mesh)
    cams = camera_positions(mesh, cameras, seed, radii)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    rng = np.random.default_rng([int(seed), 0x5CA5])
    axes = centre - cams
    dist = np.linalg.norm(axes, axis=1)
    axes /= dist[:, None]
    half = np.arcsin(np.minimum(1.0, r / dist))  # the cone that just holds the bounding sphere
    hits: list[tuple] = []
    total, cast, per_camera = 0, 0, int(np.ceil(n / cameras))
    for _ in range(MAX_BATCHES):
        dirs = np.concatenate([_cone_directions(rng, axes[k], half[k], per_camera) for k in range(cameras)])
        cam_idx = np.repeat(np.arange(cameras), per_camera)
        rays = np.concatenate([cams[cam_idx], dirs], axis=1).astype(np.float32)
        ans = scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        ok = np.isfinite(t)
        hits.append((t[ok], dirs[ok], cam_idx[ok], ans["primitive_normals"].numpy()[ok].astype(np.float64)))
        total, cast = total + int(ok.sum()), cast + len(rays)
        if total >= n:
            break
        rate = total / cast
        if rate == 0:
            raise ValueError("simulate_scan: no ray hit the mesh (is it degenerate?)")
        per_camera = int(np.ceil(1.2 * (n - total) / rate / cameras)) + 1
    else:
        raise ValueError(f"simulate_scan: only {total} of {n} rays hit the mesh after {MAX_BATCHES} batches")
    t, dirs, cam_idx, fn = (np.concatenate(a) for a in zip(*hits))
    keep = np.sort(rng.choice(len(t), size=n, replace=False))
    t, dirs, cam_idx, fn = t[keep], dirs[keep], cam_idx[keep], fn[keep]
    if noise > 0:
        t = t + rng.normal(0.0, noise, size=len(t))
    points = cams[cam_idx] + t[:, None] * dirs
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    log.debug("scan: %d points from %d cameras, %d rays hit", n, cameras, total)
    return Scan(points=points, face_normals=fn, camera_index=cam_idx.astype(np.int64), cameras=cams,
                ray_dirs=dirs)
