"""Multi-view images to mesh (the paper's Exp. 3): coarse-to-fine epochs, two renderers, two phases.

Letters: V views, H x W pixels (capture), R x R pixels (optimised images), N DMesh points, M scored faces,
F output faces.

Input: anything with the attributes of `datasets.capture.MultiView` (diffuse, depth, mask (V, H, W),
world_to_camera (V, 4, 4), fov_y_degrees, resolution), in the conventions of `dmesh.render`.

Procedure (paper appendix 9.2, Algorithm 2; upstream `3_mv_recon.py`):
1. Normalise: the masked depths are lifted to world points; their bounding-box centre goes to the origin
   and their largest distance from it to 1 (cameras and depths follow: a similarity, so the diffuse images
   are unchanged). Images are area-averaged to `resolution` (any ratio, same field of view). Every point
   stays inside a box [-b, b]^3 with b < the smallest camera's max |coordinate| (at most `box`), so every
   camera lies outside the convex hull of the points, as the tetrahedral renderer needs.
2. Epoch 0 starts from a `grid`^3 grid of real points (cell centres over [-grid_extent, grid_extent]^3, all
   weights 1, all reals 1), or with `init="depth"` (not upstream; the `depth` preset) from DMesh's
   point-cloud fit to `init_points` of the lifted depth pixels (`depth_init`). Epoch e > 0 re-seeds:
   `refine_seeds[e-1]` area-uniform samples of the current mesh (after interior-face removal) become real
   seeds, their Voronoi vertices inside [-domain, domain]^3
   (all, or the `voronoi_per_seed` x seeds with the largest empty spheres) and the 8 corners of the box
   imaginary points (`dmesh.recon.init.seeds_and_voronoi`); the previous points are dropped (upstream:
   only the surface carries over).
3. Phase 1 of each epoch (`steps_phase1`): every step re-triangulates and scores the faces
   (`DMesh.face_probabilities`); faces with Lambda_wdt * max(r) > `alpha_thresh` are drawn by the soft
   renderer (`dmesh.render.soft_render`) with opacity Lambda, over `views_per_step` random views; loss = L1
   of the diffuse images + `lambda_depth` x L1 of the depth channel (`depth_channel`: nearer is larger,
   background 0, like upstream's) over whole images (background included, as upstream; the targets carry
   the soft renderer's silhouette band, `soft_band_targets`, so the fit is unbiased) + the weight,
   real (ramped) and quality regularisers; positions, weights and reals
   move by `BoundedAdam`. Upstream adds 0.1 x the L1 of a hard nvdiffrast render for silhouette gradients;
   our soft renderer has silhouette gradients itself (analytic coverage), so there is no hard term.
4. Phase 2 (`steps_phase2`): the WDT is frozen (Lambda_wdt = 1 on its faces, opacity = dmin of the reals)
   and rendered by the tetrahedral renderer (`dmesh.render.tet_render`, exact depth order); only the reals
   move, under the same image loss + the growth real regulariser. At the steps in `freeze_phase2` the
   points on the current mesh are frozen real (upstream).
5. The mesh: faces of the final WDT whose three reals exceed `threshold`, minus interior faces (`interior`:
   "apex" drops a face when both of its tets have a real apex, upstream's `remove_invisible`; "visible"
   keeps only faces that are the first hit of some pixel ray of some view at the capture's resolution;
   "both" applies both; "sheet" is the point-cloud extraction's one-sheet rule, `dmesh.extract`; "none"
   neither), and with `depth_tolerance` minus the faces whose centroid is not within it of the captured
   depth in any view (`depth_consistent_faces`: interior faces seen through cracks and floaters; not
   upstream), made an oriented, closed surface (`dmesh.extract.surface`; open sheets face the cameras that
   saw them), mapped back to the input frame. The same extraction (visibility at
   the optimised resolution) gives the mesh each re-seed samples; the last epoch's is extracted once, at
   the capture's resolution, unless `select_best` may pick another. With
   `select_best`, each epoch's mesh is rendered opaque from every view and the epoch with the lowest image
   loss is the one extracted (upstream keeps its lowest-render-loss checkpoint, "min_eval_loss").

The steps run in `dmesh.recon.loop.Loop.run_phase` (backward, update, history, callback, checkpoints);
this module supplies each phase's step function (`phase1_step`, `phase2_step` in `reconstruct`).
A run can be resumed from `state_path` (written atomically every `save_every` steps and at each phase end):
the same input and config continue identically, except that the phase's candidate set and neighbour cache
restart empty after a resume.
"""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from dmesh.extract import SurfaceConfig, mesh_faces, surface_of_mesh, towards_cameras
from dmesh.losses.regularizers import add_phase1_regularizers, real_regularizer
from dmesh.probability import dmin
from dmesh.recon.config import (INIT_MODES, INTERIOR_MODES, MULTIVIEW_PRESETS as PRESETS,  # noqa: F401 - re-exported
                                 MULTIVIEW_RECIPES as RECIPES, REFINE_LR, REFINE_STEPS, MultiViewConfig)
from dmesh.recon.init import seeds_and_voronoi
from dmesh.recon.loop import TRAIN_ALL, Loop, ReconstructionResult, fingerprint, freeze_faces, mesh_mask
from dmesh.recon.optim import BoundedAdam

log = logging.getLogger(__name__)

#: Every camera must lie outside [-MIN_BOX, MIN_BOX]^3 of the normalised frame (object radius 1).
MIN_BOX = 1.05
#: The point box stays this fraction inside the nearest camera's box (keeps cameras off the hull).
BOX_MARGIN = 0.98
#: Depth range (normalised frame: the object's diameter) mapped to 1 in the depth channel.
DEPTH_SPAN = 2.0


@dataclass
class MultiViewResult(ReconstructionResult):
    """Output of `reconstruct` (`dmesh.recon.loop.ReconstructionResult`): mesh in the input (world) frame,
    dmesh in the normalised frame of center / scale; history: one dict per step (epoch, phase, step, loss,
    image, faces, drawn, ...); info: counts (views, resolution, points per epoch, final faces, removed
    interior faces, ...)."""


# ------------------------------------------------------------------------------------------------- input

@dataclass
class _Views:
    """Validated images (float32) and cameras (float64) of the input, in one frame."""

    diffuse: np.ndarray       # (V, H, W)
    depth: np.ndarray         # (V, H, W), 0 on background
    mask: np.ndarray          # (V, H, W) bool
    world_to_camera: np.ndarray  # (V, 4, 4)
    fov_y_degrees: float


def check_views(views) -> _Views:
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
    res = getattr(views, "resolution", h)
    if int(res) != h:
        raise ValueError(f"views.resolution is {res} but the images are {h} x {w}")
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
    return _Views(diffuse, depth, mask, w2c, fov)


def _lifted_points(vw: _Views) -> np.ndarray:
    """(P, 3) float64 world points of every view's mask pixels, lifted by their depths."""
    from dmesh.render import Camera

    h = vw.diffuse.shape[1]
    rays = Camera(np.eye(4), vw.fov_y_degrees, h, h).rays()  # camera-space, z = -1
    c2w = np.linalg.inv(vw.world_to_camera)
    clouds = []
    for k in range(len(c2w)):
        m = vw.mask[k]
        p = rays[m] * vw.depth[k][m][:, None].astype(np.float64)
        clouds.append(p @ c2w[k, :3, :3].T + c2w[k, :3, 3])
    return np.concatenate(clouds)


def _eyes(world_to_camera: np.ndarray) -> np.ndarray:
    """(V, 3) camera centres of a (V, 4, 4) world_to_camera stack: -R^T t."""
    return -np.einsum("vji,vj->vi", world_to_camera[:, :3, :3], world_to_camera[:, :3, 3])


def _look_at_point(world_to_camera: np.ndarray) -> np.ndarray | None:
    """The point nearest (least squares) to every camera's optical axis, or None when the axes are parallel."""
    eyes = _eyes(world_to_camera)
    axis = -world_to_camera[:, 2, :3]  # each camera looks down its -z axis
    proj = np.eye(3)[None] - axis[:, :, None] * axis[:, None, :]
    a, b = proj.sum(0), np.einsum("vij,vj->i", proj, eyes)
    if np.linalg.cond(a) > 1e8:
        return None
    return np.linalg.solve(a, b)


def _normalisation(vw: _Views) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Centre, scale (object radius 1), normalised world_to_camera (V, 4, 4) and camera centres (V, 3).

    The centre is the lifted pixels' bounding-box centre; when that leaves a camera inside [-MIN_BOX,
    MIN_BOX]^3 / BOX_MARGIN (a lopsided object: the box centre moves towards a camera), the cameras'
    common look-at point is tried instead (the capture rig's: the object's vertex mean).
    Raises:
        ValueError: degenerate lifted points, or a camera too close to the object with either centre.
    """
    pts = _lifted_points(vw)
    centres = [0.5 * (pts.min(0) + pts.max(0))]
    look = _look_at_point(vw.world_to_camera)
    if look is not None:
        centres.append(look)
    nearest = []
    for center in centres:
        radius = float(np.linalg.norm(pts - center, axis=1).max())
        if not radius > 1e-9:
            raise ValueError(f"the lifted depth pixels span no volume (radius {radius:.3g}): a degenerate capture")
        scale = 1.0 / radius
        # World -> normalised: x' = (x - center) * scale; camera space scales by the same factor.
        w2c = vw.world_to_camera.copy()
        w2c[:, :3, 3] = scale * (w2c[:, :3, 3] + np.einsum("vij,j->vi", w2c[:, :3, :3], center))
        eyes = _eyes(w2c)
        cam_box = float(np.abs(eyes).max(1).min())
        if BOX_MARGIN * cam_box >= MIN_BOX:
            return center, scale, w2c, eyes
        nearest.append(cam_box)
    raise ValueError(f"a camera is too close to the object: every camera must lie outside the box "
                     f"[-{MIN_BOX}, {MIN_BOX}]^3 around it (object radius 1), the nearest is at {max(nearest):.3f}")


def depth_init(vw: _Views, center: np.ndarray, scale: float, box: float, cfg: MultiViewConfig,
               rng: np.random.Generator, info: dict):
    """Epoch 0's DMesh from the depth pixels (`init="depth"`; not upstream): `cfg.init_points` of the lifted
    mask pixels (a random subset, normalised frame) go through the point-cloud reconstruction
    (`dmesh.recon.pointcloud.reconstruct`, preset `cfg.init_preset`), and its DMesh is mapped into this
    frame (positions by the similarity, weights by its squared scale, so the power diagram is the same) with
    every point clipped into the box. The depth images are half of the multi-view input; lifted, they are
    a point cloud on the captured surface, and DMesh's point-cloud fit is far closer to it than the grid
    start refined through the images (see `MultiViewConfig.depth`)."""
    from dmesh.recon.pointcloud import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct as reconstruct_points
    from dmesh.model import DMesh

    pts = (_lifted_points(vw) - center) * scale
    if len(pts) > cfg.init_points:
        pts = pts[np.sort(rng.choice(len(pts), int(cfg.init_points), replace=False))]
    pc_cfg = PointCloudConfig.preset(cfg.init_preset, seed=cfg.seed, orient=False)  # its mesh is not used
    res = reconstruct_points(pts, None, pc_cfg)
    dm = res.dmesh
    back = 1.0 / res.scale
    points = np.clip(dm.points.detach().double().numpy() * back + res.center, -box, box)
    info["init_depth"] = {"lifted_points": int(len(pts)), "points": len(dm), "faces": int(len(res.mesh.faces)),
                          "seconds": res.timings.get("total")}
    return DMesh(points, dm.weights.detach().double().numpy() * back**2, dm.reals.detach().double().numpy(),
                 cfg.probability_config())


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


# ------------------------------------------------------------------------------------------------- helpers

def soft_band_targets(channels: list[np.ndarray], mask: np.ndarray, size: int, edge_width: float) -> list[np.ndarray]:
    """Targets for the soft renderer: each capture channel with the renderer's silhouette band added, then
    area-averaged to (V, size, size) float32.

    The soft renderer draws every triangle fully inside and with a coverage band of `edge_width` pixels
    (smoothstep of the distance) outside, so a rendered silhouette lies about edge_width / 2 pixels outside
    the true one; the capture's is exact (one sample at each pixel centre). Fitting the one to the other
    would shrink the surface by that much: measured on the torus at 128 pixels, the image loss of the GT
    mesh offset along its normals is lowest at -0.01 (half a pixel) with the plain targets. So the targets
    get the same band: a background pixel at distance d (optimised pixels) from the object's edge takes
    the value of its nearest object pixel times smoothstep(1 - d / edge_width), computed at the capture's
    resolution (distance transform) before the area average. Inner depth edges (self-occlusion) keep the
    plain targets.

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


def _grid_points(n: int, extent: float, box: float) -> np.ndarray:
    c = (np.arange(n) + 0.5) / n * (2.0 * extent) - extent
    g = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    return np.clip(g, -box, box)


def sample_surface(mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 area-uniform random points on a triangle mesh (one uniform barycentric point per draw)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        return tri.reshape(-1, 3)[:n].copy()
    pick = rng.choice(len(f), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    fold = u + w > 1.0
    u[fold], w[fold] = 1.0 - u[fold], 1.0 - w[fold]
    t = tri[pick]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])


def interior_faces(pd, real: np.ndarray) -> np.ndarray:
    """(F,) bool over `pd.faces`: both adjacent tets have a real apex (upstream's `remove_invisible`).

    Args:
        pd: `PowerDiagram`; real: (N,) bool, points on the mesh. Hull faces (one tet) are never interior.
    """
    ft = pd.face_tets.astype(np.int64)
    out = ft[:, 1] >= 0
    inner = np.flatnonzero(out)
    fsum = pd.faces[inner].astype(np.int64).sum(1)
    for side in (0, 1):
        # The apex is the tet vertex not in the face: the sum of the tet's vertices minus the face's.
        apex = pd.tets[ft[inner, side]].astype(np.int64).sum(1) - fsum
        out[inner] &= real[apex]
    return out


def depth_consistent_faces(points: np.ndarray, faces: np.ndarray, world_to_camera: np.ndarray, fov_y_degrees: float,
                           depth: np.ndarray, mask: np.ndarray, tolerance: float) -> np.ndarray:
    """(F,) bool: faces whose centroid lies on the captured surface in at least one view.

    A centroid is on the surface in view k when it projects to a mask pixel whose captured depth (-z_cam)
    is within `tolerance` of its own. Interior faces lie behind the captured surface in every view that
    sees their pixel, and floating ones project onto background: both fail. Unlike the "visible" test,
    which trusts the mesh's own renders (an interior face seen through one pixel-wide crack survives it),
    this one checks the input; on the torus, 85-100% of the predicted area farther than 0.03 from the GT
    lay inside the object with "both".

    Args:
        points: (N, 3) and faces (F, 3) in the frame of `world_to_camera` (V, 4, 4); depth, mask: (V, H, H)
        captured images in the same frame's units; tolerance: distance along the view axis.
    """
    c = points[faces].mean(1)
    h = depth.shape[1]
    focal = 0.5 * h / math.tan(math.radians(fov_y_degrees) / 2.0)
    ok = np.zeros(len(faces), bool)
    for k in range(len(world_to_camera)):
        x = c @ world_to_camera[k, :3, :3].T + world_to_camera[k, :3, 3]
        z = -x[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.floor(focal * x[:, 0] / z + 0.5 * h)
            v = np.floor(-focal * x[:, 1] / z + 0.5 * h)
        idx = np.flatnonzero((z > 0) & (u >= 0) & (u < h) & (v >= 0) & (v < h))
        iu, iv = u[idx].astype(np.int64), v[idx].astype(np.int64)
        hit = mask[k, iv, iu] & (np.abs(z[idx] - depth[k, iv, iu]) <= tolerance)
        ok[idx[hit]] = True
    return ok


def hard_render(points: np.ndarray, pd, keep: np.ndarray, cameras):
    """Renders the faces of `keep` ((F,) bool over `pd.faces`) opaque, all others transparent, with the
    tetrahedral walk (exact depth order).

    A pixel's compositing stops at its first opaque face, so its fragment list holds exactly that face.

    Returns:
        seen: (F,) bool, faces of `keep` that are the first hit of some pixel ray of some camera;
        diffuse, depth, alpha: (V, R, R) float32 images (as `dmesh.render.tet_render`).
    """
    from dmesh import native

    opacity = keep.astype(np.float32)
    seen = np.zeros(len(pd.faces), bool)
    threads = max(1, torch.get_num_threads())
    images = []
    for cam in cameras:
        raw = native.tet_render_forward(points, pd.tets, pd.faces, pd.face_tets, opacity, cam.world_to_camera,
                                        cam.fov_y, cam.height, cam.width, cam.near, 0.5, 1e-4, threads)
        seen[np.asarray(raw.frag_face, dtype=np.int64)] = True
        images.append((raw.diffuse, raw.depth, raw.alpha))
    diffuse, depth, alpha = (np.stack(x) for x in zip(*images))
    return seen & keep, diffuse, depth, alpha


def visible_faces(points: np.ndarray, pd, keep: np.ndarray, cameras) -> np.ndarray:
    """(F,) bool over `pd.faces`: faces of `keep` ((F,) bool) that are the first hit of some pixel ray of
    some camera (see `hard_render`)."""
    if not keep.any():
        return np.zeros(len(pd.faces), bool)
    return hard_render(points, pd, keep, cameras)[0]


def _mesh_faces(dm, threshold: float, pd, interior: str, cameras, render: bool = False, consistent=None):
    """(F,) bool over `pd.faces` of the extracted mesh, the count removed as interior, and (with `render`,
    or when the visibility test ran) the hard render's (diffuse, depth, alpha) from `cameras`, else None.
    `consistent`: None, or a function (points, faces) -> (F,) bool of faces to keep (`depth_consistent_faces`),
    applied before the visibility test."""
    real = dm.reals.detach().numpy() > threshold
    keep = mesh_mask(dm.reals, pd.faces, threshold)
    before = int(keep.sum())
    if interior in ("apex", "both"):
        keep &= ~interior_faces(pd, real)
    elif interior == "sheet":
        keep = mesh_faces(pd, real, "sheet")
    if consistent is not None and keep.any():
        idx = np.flatnonzero(keep)
        keep[idx] = consistent(dm.points.detach().double().numpy(), pd.faces[idx].astype(np.int64))
    images = None
    if interior in ("visible", "both") or render:
        if cameras is None:
            raise ValueError("the visibility test and the hard render need the cameras")
        seen, *images = hard_render(dm.points.detach().numpy(), pd, keep, cameras)
        if interior in ("visible", "both"):
            keep = seen
    return keep, before - int(keep.sum()), images


def _start_candidate(dm, cfg: MultiViewConfig, cameras, consistent, loss_fn) -> dict:
    """`select_best`'s record of the starting DMesh (epoch -1): its mesh rendered opaque from every view
    (at the optimised resolution) and scored by `loss_fn`, with a copy of its parameters."""
    pd = dm.power_diagram()
    _, _, images = _mesh_faces(dm, cfg.threshold, pd, cfg.interior, cameras, True, consistent)
    with torch.no_grad():
        loss = float(loss_fn(dict(zip(("diffuse", "depth", "alpha"), (torch.from_numpy(x) for x in images)))))
    return {"epoch": -1, "eval_loss": loss, "points": dm.points.detach().clone(),
            "weights": dm.weights.detach().clone(), "reals": dm.reals.detach().clone()}


def extract(dm, threshold: float = 0.5, pd=None, interior: str = "apex", cameras=None, consistent=None):
    """The mesh of a DMesh after interior-face removal, as a trimesh over the used points (DMesh frame).

    Args:
        dm: `DMesh`; threshold: real value above which a point is on the mesh; pd: its `PowerDiagram` (None:
            a fresh one); interior: one of `INTERIOR_MODES` (module docstring); cameras: the
            `dmesh.render.Camera`s of the "visible" test; consistent: see `_mesh_faces`.
    Returns:
        (trimesh.Trimesh, number of faces removed as interior).
    """
    pd = pd if pd is not None else dm.power_diagram()
    keep, removed, _ = _mesh_faces(dm, threshold, pd, interior, cameras, consistent=consistent)
    return _as_trimesh(dm, pd, keep), removed


def _as_trimesh(dm, pd, keep: np.ndarray):
    import trimesh

    mesh = trimesh.Trimesh(dm.points.detach().double().numpy(), pd.faces[keep].astype(np.int64), process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


# ------------------------------------------------------------------------------------------------- procedure

def reconstruct(views, config: MultiViewConfig | None = None, callback: Callable[[dict], None] | None = None,
                state_path: str | os.PathLike | None = None) -> MultiViewResult:
    """Reconstructs a mesh from multi-view diffuse and depth images with DMesh.

    Args:
        views: a `datasets.capture.MultiView` (or anything with its attributes), any world frame.
        config: `MultiViewConfig` (None: the paper preset).
        callback: called after every step with {"epoch", "phase", "step", "steps", "loss", "image", "faces"
            (current mesh faces), "drawn" (faces rendered), "candidates", "seconds"}; and with
            {"stage": name} when a stage starts ("init", "init_depth" (`init="depth"`), "epoch<e>_phase1",
            "epoch<e>_phase2", "extract").
        state_path: file for the resumable state; an existing state of the same input and config is resumed.
    Returns:
        `MultiViewResult`.
    Raises:
        ValueError: bad views (none, mismatched shapes, NaN, empty masks, cameras too close) or config.

    Every random choice (views per step, surface samples, seeds) comes from `config.seed`. Runs repeat bit
    for bit on any thread count: the triangulation's order is canonical and the native kernels (renderers,
    Delta) reduce in a fixed order.
    """
    from dmesh.render import Camera, soft_render_views, tet_render_views
    from dmesh.model import DMesh

    cfg = config or MultiViewConfig.paper()
    if not isinstance(cfg, MultiViewConfig):
        raise TypeError(f"config must be a MultiViewConfig, got {type(cfg).__name__}")
    vw = check_views(views)
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    run_key = fingerprint(np.concatenate([vw.diffuse.ravel(), vw.depth.ravel(),
                                          vw.world_to_camera.ravel().astype(np.float32)]), cfg)
    loop = Loop(callback, state_path, run_key, cfg.save_every,
                extra_state=lambda: {"rng": rng.bit_generator.state, "epochs": info["epochs"], "best": best})
    clock = loop.clock

    loop.stage("init")
    with clock("init"):
        center, scale, w2c, eyes = _normalisation(vw)
        cam_box = float(np.abs(eyes).max(1).min())
        box = min(cfg.box, BOX_MARGIN * cam_box)
        h = vw.diffuse.shape[1]
        res = h if cfg.resolution is None else min(int(cfg.resolution), h)
        # Depth channel: (far - z) / 2 where covered, 0 on background (see `depth_channel`).
        far = np.linalg.norm(eyes, axis=1) + math.sqrt(3.0) * box
        lifted = (far[:, None, None] * vw.mask - vw.depth.astype(np.float64) * scale) / DEPTH_SPAN
        # Exact targets for the tetrahedral renderer and the hard render (one sample per pixel centre) ...
        exact = (torch.from_numpy(downsample(vw.diffuse, res)), torch.from_numpy(downsample(lifted, res)))
        # ... and targets with the soft renderer's silhouette band for phase 1 (see `soft_band_targets`).
        soft = exact
        if cfg.band_targets:
            soft = tuple(torch.from_numpy(x) for x in
                         soft_band_targets([vw.diffuse, lifted], vw.mask, res, cfg.edge_width))
        far = torch.from_numpy(far.astype(np.float32))
        cameras = Camera.from_views(w2c, vw.fov_y_degrees, res)
        # The final extraction's visibility test runs at the capture's resolution.
        full = Camera.from_views(w2c, vw.fov_y_degrees, h) if cfg.interior in ("visible", "both") else None
        consistent = None
        if cfg.depth_tolerance is not None:
            depth_n = vw.depth.astype(np.float64) * scale

            def consistent(pts, faces):
                return depth_consistent_faces(pts, faces, w2c, vw.fov_y_degrees, depth_n, vw.mask, cfg.depth_tolerance)
    n_views = len(cameras)
    batch = min(cfg.views_per_step, n_views)
    info: dict = {"views": n_views, "capture_resolution": h, "resolution": res, "views_per_step": batch,
                  "box": box, "fingerprint": run_key, "epochs": []}

    def image_loss(out, ids, targets=exact) -> torch.Tensor:
        target_d, target_z = targets
        loss = (out["diffuse"] - target_d[ids]).abs().mean()
        if cfg.lambda_depth > 0:
            z = depth_channel(out["depth"], out["alpha"], far[ids])
            loss = loss + cfg.lambda_depth * (z - target_z[ids]).abs().mean()
        return loss

    def init_points(epoch: int, mesh) -> DMesh:
        if epoch == 0 and cfg.init == "depth":
            loop.stage("init_depth")
            with clock("init_depth"):
                return depth_init(vw, center, scale, box, cfg, rng, info)
        if epoch == 0 or mesh is None:
            pts = _grid_points(cfg.grid, cfg.grid_extent, box)
            return DMesh(pts, None, None, cfg.probability_config())
        n = cfg.refine_seeds[epoch - 1]
        keep = None if cfg.voronoi_per_seed is None else int(math.ceil(cfg.voronoi_per_seed * n))
        samples = sample_surface(mesh, n, rng)
        pos, reals = seeds_and_voronoi(samples, n, rng, min(cfg.domain, box), keep, box, vertices=cfg.voronoi)
        return DMesh(np.clip(pos, -box, box), np.ones(len(pos)), reals, cfg.probability_config())

    epoch, phase, start = 0, 1, 0
    best = None  # the epoch whose mesh renders closest to the images ("select_best")
    resumed = loop.resume()
    if resumed is None:
        dm = init_points(0, None)
        opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(0))
        if cfg.select_best and cfg.init == "depth":
            # The depth start is a candidate too (epoch -1): image-loss steps never leave a worse mesh.
            with clock("extract"):
                best = _start_candidate(dm, cfg, cameras, consistent, lambda out: image_loss(out, torch.arange(n_views)))
            info["start_eval_loss"] = best["eval_loss"]
    else:
        epoch, phase, start = resumed["epoch"], resumed["phase"], resumed["step"]
        dm = DMesh(resumed["points"], resumed["weights"], resumed["reals"], cfg.probability_config())
        opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(epoch),
                          TRAIN_ALL if phase == 1 else ("reals",))
        if resumed.get("optimizer") is not None:
            opt.load_state_dict(resumed["optimizer"])
        rng.bit_generator.state = resumed["rng"]
        info["epochs"], best = list(resumed["epochs"]), resumed["best"]
        info["resumed_from"] = {"epoch": epoch, "phase": phase, "step": start}
        log.info("resuming from epoch %d phase %d step %d", epoch, phase, start)

    def pick_views() -> np.ndarray:
        return np.sort(rng.choice(n_views, batch, replace=False)) if batch < n_views else np.arange(n_views)

    pd, final = None, None

    # ------------------------------------------------------------------- phase 1: soft renderer, all move
    def phase1_step(step: int):
        nonlocal pd
        stage_t: dict = {}
        fp = dm.face_probabilities(timings=stage_t)
        clock.add(stage_t, "phase1_")
        pd = fp.power_diagram
        ids = pick_views()
        with clock("phase1_render"):
            with torch.no_grad():
                rmax = dm.reals[fp.faces].max(1).values
                drawn = torch.nonzero(fp.prob_wdt.detach() * rmax > cfg.alpha_thresh).squeeze(1)
            out = soft_render_views(dm.points, fp.faces[drawn], fp.prob[drawn].float(),
                                    [cameras[i] for i in ids], edge_width=cfg.edge_width, min_opacity=0.0)
            loss_img = image_loss(out, torch.from_numpy(ids), soft)
        with clock("phase1_regularizers"):
            loss = add_phase1_regularizers(loss_img, dm, fp, pd, cfg, step)
        return loss, {"image": float(loss_img.detach()), "drawn": int(len(drawn)),
                      "candidates": int(len(fp.faces)), "points": len(dm)}

    def phase1_after(step: int) -> dict:  # points stay in the box; the mesh after the update
        with torch.no_grad():
            dm.points.clamp_(-box, box)
        return {"faces": int(mesh_mask(dm.reals, pd.faces, cfg.threshold).sum())}

    # ------------------------------------------------------ phase 2: tetrahedral renderer, frozen WDT, reals
    def phase2_step(step: int):
        if step in cfg.freeze_phase2:
            freeze_faces(opt, pd.faces[mesh_mask(dm.reals, pd.faces, cfg.threshold)])
        ids = pick_views()
        with clock("phase2_render"):
            opacity = dmin(dm.reals[faces].double(), cfg.alpha_real).float()
            out = tet_render_views(verts, pd.tets, pd.faces, pd.face_tets, opacity, [cameras[i] for i in ids])
            loss_img = image_loss(out, torch.from_numpy(ids))
        with clock("phase2_regularizers"):
            loss = loss_img
            if cfg.lambda_real_end > 0:
                loss = loss + cfg.lambda_real_end * real_regularizer(dm.reals, faces, ones, smooth=False)
        return loss, {"image": float(loss_img.detach()), "drawn": int(len(faces)), "candidates": int(len(faces)),
                      "points": len(dm)}

    def phase2_after(step: int) -> dict:  # the mesh after the update
        return {"faces": int(mesh_mask(dm.reals, pd.faces, cfg.threshold).sum())}

    while epoch < cfg.epochs:
        tag = f"epoch{epoch}_"
        if phase == 1:
            loop.stage(tag + "phase1")
            loop.run_phase(phase1_step, opt, cfg.steps_phase1[epoch], start, {"epoch": epoch, "phase": 1},
                           "phase1_", after_step=phase1_after)
            phase, start = 2, 0
            opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(epoch), train=("reals",))
            loop.save({"epoch": epoch, "phase": 2, "step": 0}, opt)

        loop.stage(tag + "phase2")
        with clock("phase2_wdt"):
            pd = dm.power_diagram()
            faces = torch.from_numpy(pd.faces.astype(np.int64))
            ones = torch.ones(len(faces), dtype=torch.float64)
            verts = dm.points.detach()
        loop.run_phase(phase2_step, opt, cfg.steps_phase2[epoch], start, {"epoch": epoch, "phase": 2},
                       "phase2_", after_step=phase2_after)

        # ------------------------------------------------------------------------------ end of the epoch
        with clock("extract"):
            # Between epochs the visibility test and the hard render run at the optimised resolution; the
            # last epoch's mesh is the output unless `select_best` may pick another, so it is extracted once,
            # as the output is (full resolution).
            last = epoch == cfg.epochs - 1 and not cfg.select_best
            keep, removed, images = _mesh_faces(dm, cfg.threshold, pd, cfg.interior, full if last else cameras,
                                                cfg.select_best, consistent)
            mesh = _as_trimesh(dm, pd, keep)
            final = (mesh, removed) if last else None
            record = {"epoch": epoch, "points": len(dm), "faces": int(len(mesh.faces)), "interior_removed": removed}
            if images is not None and not last:  # (the last epoch's images are at the capture's resolution)
                with torch.no_grad():
                    out = dict(zip(("diffuse", "depth", "alpha"), (torch.from_numpy(x) for x in images)))
                    record["eval_loss"] = float(image_loss(out, torch.arange(n_views)))
                if cfg.select_best and (best is None or record["eval_loss"] < best["eval_loss"]):
                    best = {"epoch": epoch, "eval_loss": record["eval_loss"], "points": dm.points.detach().clone(),
                            "weights": dm.weights.detach().clone(), "reals": dm.reals.detach().clone()}
        info["epochs"].append(record)
        loop.stage(tag + "end", **record, vertices=np.asarray(mesh.vertices) / scale + center,
                   triangles=np.asarray(mesh.faces))
        epoch, phase, start = epoch + 1, 1, 0
        if epoch < cfg.epochs:
            with clock("init"):
                if len(mesh.faces) == 0:
                    log.warning("epoch %d ended with an empty mesh; epoch %d restarts from the grid", epoch - 1,
                                epoch)
                dm = init_points(epoch, mesh if len(mesh.faces) else None)
                opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(epoch))
                pd = None
        loop.save({"epoch": epoch, "phase": 1, "step": 0}, opt)

    # ----------------------------------------------------------------------------------------- extraction
    loop.stage("extract")
    with clock("extract"):
        if best is not None and best["epoch"] != cfg.epochs - 1:
            dm = DMesh(best["points"], best["weights"], best["reals"], cfg.probability_config())
            pd = None
        if best is not None:
            info["selected_epoch"] = best["epoch"]
        if final is not None:
            mesh, removed = final
        else:
            pd = pd if pd is not None else dm.power_diagram()
            mesh, removed = extract(dm, cfg.threshold, pd, cfg.interior, full, consistent)
    if cfg.orient:  # the faces' closed, outward surface (dmesh.extract.surface); sheets face their cameras
        with clock("orient"):
            seen = np.repeat(np.arange(len(vw.mask)), vw.mask.reshape(len(vw.mask), -1).sum(1))
            towards = towards_cameras((_lifted_points(vw) - center) * scale, eyes[seen])
            mesh = surface_of_mesh(mesh, pd, towards, SurfaceConfig(seed=cfg.seed))
            info["surface"] = mesh.metadata.pop("surface")
    mesh.vertices = np.asarray(mesh.vertices) / scale + center
    info.update({"faces": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)), "points": len(dm),
                 "interior_removed": removed, "hidden_points": int(pd.hidden.sum())})
    return MultiViewResult(mesh, dm, center, scale, loop.finish(), loop.history, info)


__all__ = ["MultiViewConfig", "MultiViewResult", "PRESETS", "reconstruct", "check_views", "downsample",
           "extract", "interior_faces", "visible_faces", "sample_surface"]
