"""The multi-view input side: validated views, the normalised frame, image resampling and loss targets.

Letters: V views, H x H capture pixels, R x R optimised pixels, P lifted pixels.

Input: anything with the attributes of `datasets.capture.MultiView` (diffuse, depth, mask (V, H, W),
world_to_camera (V, 4, 4), fov_y_degrees, resolution), in the conventions of `dmesh.camera`.

- `check_views`: validated float32 images and float64 cameras (`Views`), or a one-line ValueError.
- `normalisation`: the similarity that takes the lifted depth pixels (`lifted_points`) to radius 1 around
  the origin, with every camera outside [-MIN_BOX, MIN_BOX]^3 (the tetrahedral renderer needs the cameras
  outside the points' convex hull).
- `smooth_from_pool`: points moved onto the quadratic jets of their nearest lifted pixels (the noisy depth
  start's smoothing).
- `downsample`: area average to R pixels (any ratio, same field of view).
- `image_targets`: the loss targets of `dmesh.recon.multiview` at R pixels, the depth channel
  (`depth_channel`) with or without the soft renderer's silhouette band (`soft_band_targets`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from dmesh import camera
from dmesh.tolerances import FLOAT64_FLOOR

#: Every camera must lie outside [-MIN_BOX, MIN_BOX]^3 of the normalised frame (object radius 1).
MIN_BOX = 1.05
#: The point box stays this fraction inside the nearest camera's box (keeps cameras off the hull).
BOX_MARGIN = 0.98
#: Depth range (normalised frame: the object's diameter) mapped to 1 in the depth channel.
DEPTH_SPAN = 2.0


@dataclass
class Views:
    """Validated images (float32) and cameras (float64) of the input, in one frame."""

    diffuse: np.ndarray       # (V, H, W)
    depth: np.ndarray         # (V, H, W), 0 on background
    mask: np.ndarray          # (V, H, W) bool
    world_to_camera: np.ndarray  # (V, 4, 4)
    fov_y_degrees: float


def check_views(views) -> Views:
    """Validated copies of a capture's images and cameras; ValueError (one line) naming the problem."""
    if views is None:
        raise ValueError("no views given (views is None)")
    missing = [a for a in ("diffuse", "depth", "world_to_camera", "fov_y_degrees") if not hasattr(views, a)]
    if missing:
        raise ValueError(f"views lacks {', '.join(missing)} (expected a datasets.capture.MultiView)")
    diffuse = np.asarray(views.diffuse, dtype=np.float32)
    depth = np.asarray(views.depth, dtype=np.float32)
    if diffuse.ndim != 3 or diffuse.shape[0] == 0:
        raise ValueError(f"views.diffuse must have shape (V, H, W) with V >= 1, got {diffuse.shape}")
    if depth.shape != diffuse.shape:
        raise ValueError(f"views.depth must have the diffuse images' shape {diffuse.shape}, got {depth.shape}")
    v, h, w = diffuse.shape
    if h != w:
        raise ValueError(f"views must be square images, got {h} x {w}")
    resolution = getattr(views, "resolution", h)
    if int(resolution) != h:
        raise ValueError(f"views.resolution is {resolution} but the images are {h} x {w}")
    mask = getattr(views, "mask", None)
    mask = depth > 0 if mask is None else np.asarray(mask, dtype=bool)
    if mask.shape != diffuse.shape:
        raise ValueError(f"views.mask must have the diffuse images' shape {diffuse.shape}, got {mask.shape}")
    w2c = np.asarray(views.world_to_camera, dtype=np.float64)
    if w2c.shape != (v, 4, 4):
        raise ValueError(f"views.world_to_camera must have shape ({v}, 4, 4), got {w2c.shape}")
    for name, arr in (("diffuse", diffuse), ("depth", depth), ("world_to_camera", w2c)):
        if not np.isfinite(arr).all():
            raise ValueError(f"views.{name} holds NaN or inf ({int((~np.isfinite(arr)).sum())} values)")
    fov = float(views.fov_y_degrees)
    if not 0.0 < fov < 180.0:
        raise ValueError(f"views.fov_y_degrees must be in (0, 180), got {fov}")
    if (depth[mask] <= 0).any():
        raise ValueError("views.depth must be positive wherever the mask is set")
    if not mask.any():
        raise ValueError("every view is empty (no mask pixel): the object is outside every camera")
    depth = np.where(mask, depth, 0.0).astype(np.float32)
    diffuse = np.where(mask, diffuse, 0.0).astype(np.float32)
    return Views(diffuse, depth, mask, w2c, fov)


def lifted_points(vw: Views) -> np.ndarray:
    """(P, 3) float64 world points of every view's mask pixels, lifted by their depths."""
    return camera.lift_depth(vw.depth, vw.mask, vw.world_to_camera, vw.fov_y_degrees)


#: Queries fitted per batch by `smooth_from_pool` (bounds its memory: chunk x k x 6 float64 values).
POOL_CHUNK = 2000
#: Ridge of `smooth_from_pool`'s least squares, per neighbour (the monomials are at most 1 in size).
POOL_RIDGE = 1e-9


def smooth_from_pool(points: np.ndarray, pool: np.ndarray, k: int, workers: int = 1) -> np.ndarray:
    """(G, 3) float64: every point of `points` moved onto the quadratic jet fitted to its `k` nearest points
    of `pool` (a denser sampling of the same surface, e.g. every lifted pixel when `points` are a subset).

    Per point: the neighbours' centroid and principal plane (smallest-eigenvalue direction as the normal),
    the least-squares height field h = a + b u + c v + d u^2 + e u v + f v^2 over that plane, and the point
    projected onto it along the normal (its own u, v kept). Noise along the normal falls with the number of
    neighbours, and a denser pool gives more of them within the same radius. A quadratic height field over
    that plane is reproduced (up to the tiny ridge, `POOL_RIDGE`).

    Written with SciPy and NumPy: CGAL's `jet_smooth_point_set` (`dmesh.recon.init.smooth_points`) fits
    every point of a set from that same set, so fitting a subset from all the pixels would mean smoothing all
    of them, many times the fits. ValueError for k < 6 or k > len(pool).
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    pool = np.asarray(pool, dtype=np.float64)
    if not 6 <= int(k) <= len(pool):
        raise ValueError(f"smooth_from_pool: k must be in [6, {len(pool)}] for a pool of {len(pool)} points, got {k}")
    tree = cKDTree(pool)
    out = np.empty_like(pts)
    for s in range(0, len(pts), POOL_CHUNK):
        q = pts[s:s + POOL_CHUNK]
        _, idx = tree.query(q, int(k), workers=workers)
        centre = pool[idx].mean(1)
        y = pool[idx] - centre[:, None]
        _, frame = np.linalg.eigh(np.einsum("cki,ckj->cij", y, y))  # columns: normal, then the two tangents
        uvh = np.einsum("cki,cij->ckj", y, frame[:, :, [2, 1, 0]])
        # Tangential coordinates in units of the neighbourhood's radius, and a tiny ridge: a neighbourhood
        # along a line (a thin rod) has no second tangent, which would leave the 6 x 6 system singular.
        radius = np.maximum(np.abs(uvh[..., :2]).max((1, 2)), FLOAT64_FLOOR)[:, None]
        design = _quadratic_terms(uvh[..., 0] / radius, uvh[..., 1] / radius)
        gram = np.einsum("cki,ckj->cij", design, design) + POOL_RIDGE * int(k) * np.eye(6)
        coef = np.linalg.solve(gram, np.einsum("cki,ck->ci", design, uvh[..., 2])[..., None])[..., 0]
        quv = np.einsum("ci,cij->cj", q - centre, frame[:, :, [2, 1]])
        height = (_quadratic_terms(quv[:, 0] / radius[:, 0], quv[:, 1] / radius[:, 0]) * coef).sum(1)
        out[s:s + POOL_CHUNK] = (centre + quv[:, :1] * frame[:, :, 2] + quv[:, 1:] * frame[:, :, 1]
                                 + height[:, None] * frame[:, :, 0])
    return out


def _quadratic_terms(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(..., 6) the monomials 1, u, v, u^2, u v, v^2."""
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], -1)


def normalisation(vw: Views) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Centre, scale (object radius 1), normalised world_to_camera (V, 4, 4) and camera centres (V, 3).

    The frame maps x -> (x - centre) * scale. The centre is the lifted pixels' bounding-box centre; when
    that leaves a camera inside [-MIN_BOX, MIN_BOX]^3 / BOX_MARGIN (a lopsided object: the box centre moves
    towards a camera), the cameras' common look-at point is tried instead (the capture rig's: the object's
    vertex mean).
    Raises:
        ValueError: degenerate lifted points, or a camera too close to the object with either centre.
    """
    pts = lifted_points(vw)
    candidates = [0.5 * (pts.min(0) + pts.max(0))]
    look = camera.look_at_point(vw.world_to_camera)
    if look is not None:
        candidates.append(look)
    nearest = []
    for center in candidates:
        radius = float(np.linalg.norm(pts - center, axis=1).max())
        if not radius > 1e-9:
            raise ValueError(f"the lifted depth pixels span no volume (radius {radius:.3g}): a degenerate capture")
        scale = 1.0 / radius
        # World -> normalised: x' = (x - center) * scale; camera space scales by the same factor.
        w2c = vw.world_to_camera.copy()
        w2c[:, :3, 3] = scale * (w2c[:, :3, 3] + np.einsum("vij,j->vi", w2c[:, :3, :3], center))
        eyes = camera.eyes(w2c)
        cam_box = float(np.abs(eyes).max(1).min())
        if BOX_MARGIN * cam_box >= MIN_BOX:
            return center, scale, w2c, eyes
        nearest.append(cam_box)
    raise ValueError(f"a camera is too close to the object: every camera must lie outside the box "
                     f"[-{MIN_BOX}, {MIN_BOX}]^3 around it (object radius 1), the nearest is at {max(nearest):.3f}")


def _area_matrix(src: int, dst: int) -> np.ndarray:
    """(dst, src) float64 area-averaging weights: row j covers source pixels [j s/d, (j + 1) s/d)."""
    edges = np.arange(dst + 1) * (src / dst)
    lo, hi = edges[:-1, None], edges[1:, None]
    k = np.arange(src)[None, :]
    overlap = np.clip(np.minimum(hi, k + 1) - np.maximum(lo, k), 0.0, None)
    return overlap / overlap.sum(1, keepdims=True)


def downsample(images: np.ndarray, size: int) -> np.ndarray:
    """Area average of (V, H, H) images to (V, size, size) float32 (any ratio; the identity at size H).

    The result's pixel (i, j) is the mean over its footprint [i H/size, (i + 1) H/size) x [...] of the
    source, so a camera of the same field of view at `size` pixels samples the same scene.
    """
    h = images.shape[1]
    if size == h:
        return images.astype(np.float32, copy=True)
    a = _area_matrix(h, size)
    return (a @ images.astype(np.float64) @ a.T).astype(np.float32)


def soft_band_targets(channels: list[np.ndarray], mask: np.ndarray, size: int, edge_width: float) -> list[np.ndarray]:
    """Targets for the soft renderer: each capture channel with the renderer's silhouette band added, then
    area-averaged to (V, size, size) float32.

    The soft renderer draws every triangle fully inside and with a coverage band of `edge_width` pixels
    (smoothstep of the distance) outside, so a rendered silhouette lies about edge_width / 2 pixels outside
    the true one; the capture's is exact (one sample at each pixel centre). Fitting the one to the other
    would shrink the surface by that much (about half a pixel). So the targets get the same band: a
    background pixel at distance d (optimised pixels) from the object's edge takes the value of its nearest
    object pixel times smoothstep(1 - d / edge_width), computed at the capture's resolution (distance
    transform) before the area average. Inner depth edges (self-occlusion) keep the plain targets.

    Args:
        channels: (V, H, H) arrays, 0 on the background; mask: (V, H, H) bool; size: optimised side;
        edge_width: the soft renderer's band width in optimised pixels.
    """
    from scipy.ndimage import distance_transform_edt

    h = mask.shape[1]
    step = size / h  # one capture pixel in optimised pixels
    out = [np.array(c, dtype=np.float64) for c in channels]
    for k in range(len(mask)):
        if not mask[k].any() or mask[k].all():
            continue
        dist, (ii, jj) = distance_transform_edt(~mask[k], sampling=step, return_indices=True)
        # Pixel centres are one capture pixel apart; the edge lies about half a pixel before the object's.
        d = np.clip(dist - 0.5 * step, 0.0, None) / edge_width
        band = ~mask[k] & (d < 1.0)
        s = 1.0 - d[band]
        a = s * s * (3.0 - 2.0 * s)
        for c in out:
            c[k][band] = a * c[k][ii[band], jj[band]]
    return [downsample(c, size) for c in out]


def depth_channel(depth: torch.Tensor, alpha: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """The depth the loss compares: (far - z) / DEPTH_SPAN per fragment, composited, 0 on background.

    Like upstream's 1 - (ndc_z + 1) / 2, it falls with distance and is 0 on the background (as far away as
    `far`, beyond every point of the box): peeling a wrongly opaque layer off a background pixel then lowers
    the loss monotonically. Raw distances would not (background 0 but deeper layers larger), and carving the
    initial grid stalls. Composited values are sum a T z = `depth` and sum a T = `alpha`, so the channel is
    (far alpha - depth) / DEPTH_SPAN, linear in the renderer's outputs.

    Args:
        depth, alpha: (B, R, R) renderer outputs; far: (B,) per view.
    """
    return (far[:, None, None] * alpha - depth) / DEPTH_SPAN


@dataclass
class ImageTargets:
    """The loss targets of the multi-view reconstruction at the optimised resolution.

    Attributes:
        exact: (diffuse, depth channel) (V, R, R) float32 tensors, one sample per pixel centre (the
            tetrahedral renderer's and the hard render's targets).
        soft: the same with the soft renderer's silhouette band (phase 1; `soft_band_targets`), or `exact`.
        far: (V,) float32 tensor, each view's far distance of the depth channel.
    """

    exact: tuple
    soft: tuple
    far: torch.Tensor


def image_targets(vw: Views, scale: float, eyes: np.ndarray, box: float, size: int, edge_width: float,
                  band: bool) -> ImageTargets:
    """`ImageTargets` of the views in the normalised frame (`normalisation`'s scale and camera centres) at
    `size` pixels; every point lies in [-box, box]^3, so far = |eye| + sqrt(3) box is behind all of them;
    band: whether the soft targets carry the silhouette band."""
    # Depth channel: (far - z) / DEPTH_SPAN where covered, 0 on background (see `depth_channel`).
    far = np.linalg.norm(eyes, axis=1) + math.sqrt(3.0) * box
    channel = (far[:, None, None] * vw.mask - vw.depth.astype(np.float64) * scale) / DEPTH_SPAN
    exact = (torch.from_numpy(downsample(vw.diffuse, size)), torch.from_numpy(downsample(channel, size)))
    soft = exact
    if band:
        soft = tuple(torch.from_numpy(x) for x in soft_band_targets([vw.diffuse, channel], vw.mask, size, edge_width))
    return ImageTargets(exact, soft, torch.from_numpy(far.astype(np.float32)))


__all__ = ["MIN_BOX", "BOX_MARGIN", "DEPTH_SPAN", "Views", "check_views", "lifted_points", "normalisation",
           "downsample", "soft_band_targets", "depth_channel", "ImageTargets", "image_targets"]
