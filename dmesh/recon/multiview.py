"""Multi-view images to mesh (the paper's Exp. 3): coarse-to-fine epochs, two renderers, two phases.

Letters: V views, H x W pixels (capture), R x R pixels (optimised images), N DMesh points, M scored faces,
F output faces.

Input: anything with the attributes of `datasets.capture.MultiView` (diffuse, depth, mask (V, H, W),
world_to_camera (V, 4, 4), fov_y_degrees, resolution), in the conventions of `dmesh.camera`; its checks,
normalisation, resampling and loss targets are `dmesh.recon.views`.

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
   of the diffuse images + `lambda_depth` x L1 of the depth channel (`views.depth_channel`: nearer is larger,
   background 0, like upstream's) over whole images (background included, as upstream; the targets carry
   the soft renderer's silhouette band, `views.soft_band_targets`, so the fit is unbiased) + the weight,
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
   depth in any view (`dmesh.extract.depth_consistent_faces`: interior faces seen through cracks and
   floaters; not upstream), made an oriented, closed surface (the surface step, `dmesh.surface`, with the
   settings `surface`; open sheets face the cameras that saw them), mapped back to the input frame. The same
   extraction (visibility at the optimised resolution) gives the mesh each re-seed samples; the last epoch's is
   extracted once, at the capture's resolution, unless `select_best` may pick another. With
   `select_best`, each epoch's mesh is rendered opaque from every view and the epoch with the lowest image
   loss is the one extracted (upstream keeps its lowest-render-loss checkpoint, "min_eval_loss").
6. With `depth_fit` (not upstream): the mesh's vertices move along their normals by one least-squares fit
   of its faces to the captured depth maps (`dmesh.recon.depth_fit`), which undoes the optimisation's
   inward bias (docs/preset_choices_multiview.md). Topology and winding are unchanged; the copies the surface step
   made of one point move together (`copy_groups`).

The extraction rules are `dmesh.extract.filtered_faces` ("apex" is its "no_interior" mode). The steps run
in `dmesh.recon.loop.Loop.run_phase` (backward, update, history, callback, checkpoints); this module
supplies each phase's step function (`_Run.phase1_step`, `_Run.phase2_step`).
A run can be resumed from `state_path` (written atomically every `save_every` steps and at each phase end):
the same input and config give the same mesh as an uninterrupted run (the state holds the parameters, the
optimiser, the RNG, the epochs so far, the best epoch and the phase's candidate faces and neighbour cache).
"""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from dmesh.extract import depth_consistent_faces, filtered_faces, to_trimesh, towards_cameras
from dmesh.geometry import gather
from dmesh.losses.regularizers import add_phase1_regularizers, real_regularizer
from dmesh.model import DMesh
from dmesh.probability import dmin
from dmesh.recon.multiview_config import MULTIVIEW_PRESETS as PRESETS, MultiViewConfig
from dmesh.recon.depth_fit import DepthFitConfig, fit_to_depth
from dmesh.recon.init import DEPTH_NOISY_RATIO, noise_ratio, seeds_and_voronoi
from dmesh.recon.loop import (TRAIN_ALL, Loop, ReconstructionResult, deterministic, fingerprint, freeze_faces,
                              mesh_mask)
from dmesh.recon.optim import BoundedAdam
from dmesh.recon.views import (BOX_MARGIN, Views, check_views, depth_channel, image_targets, lifted_points,
                               normalisation, smooth_from_pool)
from dmesh.render import Camera, soft_render_views, tet_render_views
from dmesh.sampling import sample_surface
from dmesh.surface import surface_mesh

log = logging.getLogger(__name__)


@dataclass
class MultiViewResult(ReconstructionResult):
    """Output of `reconstruct` (`dmesh.recon.loop.ReconstructionResult`): mesh in the input (world) frame,
    dmesh in the normalised frame of center / scale; history: one dict per step (epoch, phase, step, loss,
    image, faces, drawn, ...); info: counts (views, resolution, points per epoch, final faces, removed
    interior faces, ...)."""


# ------------------------------------------------------------------------------------------------- starts

#: The depth start's own input filters (`MultiViewConfig.init_filters` False turns them off): point-cloud config
#: fields at their off values (outlier removal, jet smoothing, noise-triggered smoothing, redo of a shredded mesh).
UNFILTERED = {"outlier_std": 0.0, "smooth_k": 0, "auto_smooth_k": 0, "redo_fragmented": 0.0}


def depth_init(vw: Views, center: np.ndarray, scale: float, box: float, cfg: MultiViewConfig,
               rng: np.random.Generator, info: dict):
    """Epoch 0's DMesh from the depth pixels (`init="depth"`; not upstream): `cfg.init_points` of the lifted mask
    pixels (a random subset, normalised frame) go through DMesh's point-cloud fit (preset `cfg.init_preset`),
    far closer to the captured surface than the grid start refined through the images (`MultiViewConfig.depth`),
    and its DMesh is mapped into this frame (positions by the similarity, weights by its squared scale: the same
    power diagram), every point clipped into the box.

    "auto" takes the point-cloud `fast` preset. When the subset looks noisy (`depth_start_preset`), each of its
    points is first moved onto the jet fitted to its `cfg.init_pool_k` nearest of all the lifted pixels
    (`smooth_from_pool`; the overlapping views sample the surface far more densely than the subset), then goes
    to `cfg.init_pooled_preset`. With `cfg.init_filters` False the pixels go as lifted: no pooled smoothing,
    "auto" is `fast`, and the preset's own filters are off (`UNFILTERED`)."""
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct as reconstruct_points

    pixels = (lifted_points(vw) - center) * scale
    pts = pixels
    if len(pts) > cfg.init_points:
        pts = pts[np.sort(rng.choice(len(pts), int(cfg.init_points), replace=False))]
    if cfg.init_filters:
        preset, ratio = depth_start_preset(pts, cfg.init_preset)
    else:
        preset, ratio = ("fast" if cfg.init_preset == "auto" else cfg.init_preset), None
    pooled = cfg.init_filters and cfg.init_preset == "auto" and preset == "noisy" and cfg.init_pool_k > 0
    if pooled:
        k = min(int(cfg.init_pool_k), len(pixels))
        log.info("depth start: the %d points fitted from their %d nearest of %d lifted pixels", len(pts), k,
                 len(pixels))
        pts, preset = smooth_from_pool(pts, pixels, k), cfg.init_pooled_preset
    # Its mesh is not used, but it is oriented: the preset's check for a shredded mesh (`redo_fragmented`) then
    # counts the boundary edges of the oriented surface, as on point clouds (the raw extraction of a shredded
    # sheet counts fewer).
    pc_cfg = PointCloudConfig.preset(preset, seed=cfg.seed, orient=True, **({} if cfg.init_filters else UNFILTERED))
    fit = reconstruct_points(pts, None, pc_cfg)
    dm = fit.dmesh
    back = 1.0 / fit.scale
    points = np.clip(dm.points.detach().double().numpy() * back + fit.center, -box, box)
    info["init_depth"] = {"lifted_points": int(len(pts)), "points": len(dm), "faces": int(len(fit.mesh.faces)),
                          "seconds": fit.timings.get("total"), "preset": preset, "filters": bool(cfg.init_filters),
                          "noise_ratio": ratio,
                          "pool_k": k if pooled else 0, "pixels": int(len(pixels)),
                          "redone": "fragmented_attempt" in fit.info}
    return DMesh(points, dm.weights.detach().double().numpy() * back**2, dm.reals.detach().double().numpy(),
                 cfg.probability_config())


def depth_start_preset(points: np.ndarray, requested: str) -> tuple[str, float | None]:
    """(point-cloud preset, noise ratio or None) of the depth start: `requested` itself, except "auto", which
    takes `noisy` (outliers dropped, then jet smoothing; `depth_init` smooths from all the pixels instead) when
    the lifted pixels `points` lie more than `DEPTH_NOISY_RATIO` neighbour spacings off their local planes
    (`dmesh.recon.init.noise_ratio`), else `fast`. Depth noise lifts every pixel off the surface along its ray;
    the smoothing takes most of it out, while on clean pixels it only rounds edges, hence the measurement
    rather than one fixed preset."""
    if requested != "auto":
        return requested, None
    ratio = noise_ratio(points)
    preset = "noisy" if ratio > DEPTH_NOISY_RATIO else "fast"
    log.info("depth start: the lifted pixels lie %.3f neighbour spacings off their local planes (median; noisy "
             "above %.2f): point-cloud preset %r", ratio, DEPTH_NOISY_RATIO, preset)
    return preset, ratio


def _grid_points(n: int, extent: float, box: float) -> np.ndarray:
    c = (np.arange(n) + 0.5) / n * (2.0 * extent) - extent
    g = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    return np.clip(g, -box, box)


def _depth_filter(vw: Views, world_to_camera: np.ndarray, scale: float, tolerance: float | None):
    """The extraction's `consistent` test (`dmesh.extract.depth_consistent_faces`) in the normalised frame,
    or None without a tolerance."""
    if tolerance is None:
        return None
    depth = vw.depth.astype(np.float64) * scale

    def consistent(pts, faces):
        return depth_consistent_faces(pts, faces, world_to_camera, vw.fov_y_degrees, depth, vw.mask, tolerance)
    return consistent


def _outputs(images) -> dict[str, torch.Tensor]:
    """A hard render's (diffuse, depth, alpha) arrays as a renderer's output dict."""
    return dict(zip(("diffuse", "depth", "alpha"), (torch.from_numpy(x) for x in images)))


def _candidate(epoch: int, eval_loss: float, dm) -> dict:
    """`select_best`'s record of a DMesh: its epoch, image loss and a copy of its parameters."""
    return {"epoch": epoch, "eval_loss": eval_loss, "points": dm.points.detach().clone(),
            "weights": dm.weights.detach().clone(), "reals": dm.reals.detach().clone()}


# ------------------------------------------------------------------------------------------------- procedure

class _Run:
    """One reconstruction (module docstring): the input in its normalised frame, the DMesh and its optimiser,
    the phase step functions `Loop.run_phase` calls, and each epoch's extraction."""

    def __init__(self, views, cfg: MultiViewConfig, callback, state_path):
        self.cfg = cfg
        self.vw = vw = check_views(views)
        self.rng = np.random.default_rng(cfg.seed)
        torch.manual_seed(cfg.seed)
        key = fingerprint(np.concatenate([vw.diffuse.ravel(), vw.depth.ravel(),
                                          vw.world_to_camera.ravel().astype(np.float32)]), cfg)
        self.loop = Loop(callback, state_path, key, cfg.save_every,
                         extra_state=lambda: {"rng": self.rng.bit_generator.state, "epochs": self.info["epochs"],
                                              "best": self.best, "probability": self.dm.state})
        self.clock = self.loop.clock
        self.best = None   # the epoch whose mesh renders closest to the images ("select_best")
        self.final = None  # the last epoch's (mesh, faces kept, removed) when it is the output
        self.pd = None     # the current triangulation
        self.loop.stage("init")
        with self.clock("init"):
            self._frame()
        self.batch = min(cfg.views_per_step, len(self.cameras))
        self.info: dict = {"views": len(self.cameras), "capture_resolution": vw.diffuse.shape[1],
                           "resolution": self.size, "views_per_step": self.batch, "box": self.box,
                           "fingerprint": key, "epochs": []}

    def _frame(self) -> None:
        """The normalised frame, the box of the points, the targets and the cameras."""
        cfg, vw = self.cfg, self.vw
        self.center, self.scale, w2c, self.eyes = normalisation(vw)
        self.w2c = w2c
        cam_box = float(np.abs(self.eyes).max(1).min())
        self.box = min(cfg.box, BOX_MARGIN * cam_box)
        h = vw.diffuse.shape[1]
        self.size = h if cfg.resolution is None else min(int(cfg.resolution), h)
        self.targets = image_targets(vw, self.scale, self.eyes, self.box, self.size, cfg.edge_width,
                                     cfg.band_targets)
        self.cameras = Camera.from_views(w2c, vw.fov_y_degrees, self.size)
        # The final extraction's visibility test runs at the capture's resolution.
        self.full = Camera.from_views(w2c, vw.fov_y_degrees, h) if cfg.interior in ("visible", "both") else None
        self.consistent = _depth_filter(vw, w2c, self.scale, cfg.depth_tolerance)

    def image_loss(self, out: dict, ids: torch.Tensor, targets: tuple | None = None) -> torch.Tensor:
        """L1 of the diffuse images + lambda_depth x L1 of the depth channel, views `ids` (default targets:
        the exact ones)."""
        target_d, target_z = self.targets.exact if targets is None else targets
        loss = (out["diffuse"] - target_d[ids]).abs().mean()
        if self.cfg.lambda_depth > 0:
            z = depth_channel(out["depth"], out["alpha"], self.targets.far[ids])
            loss = loss + self.cfg.lambda_depth * (z - target_z[ids]).abs().mean()
        return loss

    def eval_loss(self, images) -> float:
        """The image loss of a hard render (`dmesh.extract.hard_render`) over every view."""
        with torch.no_grad():
            return float(self.image_loss(_outputs(images), torch.arange(len(self.cameras))))

    def init_points(self, epoch: int, mesh) -> DMesh:
        """Epoch `epoch`'s starting DMesh: the grid or the depth start, or the re-seed from `mesh`."""
        cfg, box = self.cfg, self.box
        if epoch == 0 and cfg.init == "depth":
            self.loop.stage("init_depth")
            with self.clock("init_depth"):
                return depth_init(self.vw, self.center, self.scale, box, cfg, self.rng, self.info)
        if epoch == 0 or mesh is None:
            return DMesh(_grid_points(cfg.grid, cfg.grid_extent, box), None, None, cfg.probability_config())
        n = cfg.refine_seeds[epoch - 1]
        keep = None if cfg.voronoi_per_seed is None else int(math.ceil(cfg.voronoi_per_seed * n))
        samples = sample_surface(mesh, n, self.rng, cfg.reseed_phong)
        pos, reals = seeds_and_voronoi(samples, n, self.rng, min(cfg.domain, box), keep, box, vertices=cfg.voronoi)
        return DMesh(np.clip(pos, -box, box), np.ones(len(pos)), reals, cfg.probability_config())

    def start(self) -> tuple[int, int, int]:
        """The DMesh and optimiser to start from, fresh or resumed; returns (epoch, phase, step)."""
        cfg = self.cfg
        resumed = self.loop.resume()
        if resumed is None:
            self.dm = self.init_points(0, None)
            self.opt = BoundedAdam(self.dm.points, self.dm.weights, self.dm.reals, cfg.step_config(0))
            if cfg.select_best and cfg.init == "depth":
                # The depth start is a candidate too (epoch -1): image-loss steps never leave a worse mesh.
                with self.clock("extract"):
                    pd = self.dm.power_diagram()
                    images = filtered_faces(self.dm, cfg.threshold, pd, cfg.interior, self.cameras, True,
                                            self.consistent)[2]
                    self.best = _candidate(-1, self.eval_loss(images), self.dm)
                self.info["start_eval_loss"] = self.best["eval_loss"]
            return 0, 1, 0
        epoch, phase, start = resumed["epoch"], resumed["phase"], resumed["step"]
        self.dm = DMesh(resumed["points"], resumed["weights"], resumed["reals"], cfg.probability_config())
        if "probability" in resumed:  # (states written before it was saved lack it: the phase's caches restart)
            self.dm.state = resumed["probability"]
        self.opt = BoundedAdam(self.dm.points, self.dm.weights, self.dm.reals, cfg.step_config(epoch),
                               TRAIN_ALL if phase == 1 else ("reals",))
        if resumed.get("optimizer") is not None:
            self.opt.load_state_dict(resumed["optimizer"])
        self.rng.bit_generator.state = resumed["rng"]
        self.info["epochs"], self.best = list(resumed["epochs"]), resumed["best"]
        self.info["resumed_from"] = {"epoch": epoch, "phase": phase, "step": start,
                                     "seconds": self.loop.earlier_seconds}
        log.info("resuming from epoch %d phase %d step %d", epoch, phase, start)
        return epoch, phase, start

    def pick_views(self) -> np.ndarray:
        n_views = len(self.cameras)
        if self.batch < n_views:
            return np.sort(self.rng.choice(n_views, self.batch, replace=False))
        return np.arange(n_views)

    def current_mesh(self) -> np.ndarray:
        """(F,) bool over the current triangulation's faces: the current mesh."""
        return mesh_mask(self.dm.reals, self.pd.faces, self.cfg.threshold)

    # ------------------------------------------------------------------- phase 1: soft renderer, all move
    def phase1_step(self, step: int):
        cfg, dm, clock = self.cfg, self.dm, self.clock
        stage_t: dict = {}
        probs = dm.face_probabilities(timings=stage_t)
        clock.add(stage_t, "phase1_")
        self.pd = probs.power_diagram
        ids = self.pick_views()
        with clock("phase1_render"):
            with torch.no_grad():
                rmax = dm.reals[probs.faces].max(1).values
                drawn = torch.nonzero(probs.prob_wdt.detach() * rmax > cfg.alpha_thresh).squeeze(1)
            out = soft_render_views(dm.points, probs.faces[drawn], probs.prob[drawn].float(),
                                    [self.cameras[i] for i in ids], edge_width=cfg.edge_width, min_opacity=0.0)
            loss_img = self.image_loss(out, torch.from_numpy(ids), self.targets.soft)
        with clock("phase1_regularizers"):
            loss = add_phase1_regularizers(loss_img, dm, probs, self.pd, cfg, step)
        return loss, {"image": float(loss_img.detach()), "drawn": int(len(drawn)),
                      "candidates": int(len(probs.faces)), "points": len(dm)}

    def phase1_after(self, step: int) -> dict:  # points stay in the box; the mesh after the update
        with torch.no_grad():
            self.dm.points.clamp_(-self.box, self.box)
        return {"faces": int(self.current_mesh().sum())}

    # ------------------------------------------------------ phase 2: tetrahedral renderer, frozen WDT, reals
    def phase2_step(self, step: int):
        cfg, dm, pd = self.cfg, self.dm, self.pd
        faces, ones, verts = self.wdt
        if step in cfg.freeze_phase2:
            freeze_faces(self.opt, pd.faces[self.current_mesh()])
        ids = self.pick_views()
        with self.clock("phase2_render"):
            opacity = dmin(gather(dm.reals, faces).double(), cfg.alpha_real).float()
            out = tet_render_views(verts, pd.tets, pd.faces, pd.face_tets, opacity, [self.cameras[i] for i in ids])
            loss_img = self.image_loss(out, torch.from_numpy(ids))
        with self.clock("phase2_regularizers"):
            loss = loss_img
            if cfg.lambda_real_end > 0:
                loss = loss + cfg.lambda_real_end * real_regularizer(dm.reals, faces, ones, smooth=False)
        return loss, {"image": float(loss_img.detach()), "drawn": int(len(faces)), "candidates": int(len(faces)),
                      "points": len(dm)}

    def phase2_after(self, step: int) -> dict:  # the mesh after the update
        return {"faces": int(self.current_mesh().sum())}

    def run_epoch(self, epoch: int, phase: int, start: int):
        """Phases 1 (unless resumed in phase 2) and 2 of one epoch from step `start`; returns its mesh."""
        cfg, loop = self.cfg, self.loop
        tag = f"epoch{epoch}_"
        if phase == 1:
            loop.stage(tag + "phase1")
            loop.run_phase(self.phase1_step, self.opt, cfg.steps_phase1[epoch], start, {"epoch": epoch, "phase": 1},
                           "phase1_", after_step=self.phase1_after)
            start = 0
            self.opt = BoundedAdam(self.dm.points, self.dm.weights, self.dm.reals, cfg.step_config(epoch),
                                   train=("reals",))
            loop.save({"epoch": epoch, "phase": 2, "step": 0}, self.opt)
        loop.stage(tag + "phase2")
        with self.clock("phase2_wdt"):
            self.pd = self.dm.power_diagram()
            faces = torch.from_numpy(self.pd.faces.astype(np.int64))
            self.wdt = (faces, torch.ones(len(faces), dtype=torch.float64), self.dm.points.detach())
        loop.run_phase(self.phase2_step, self.opt, cfg.steps_phase2[epoch], start, {"epoch": epoch, "phase": 2},
                       "phase2_", after_step=self.phase2_after)
        return self.end_epoch(epoch)

    def end_epoch(self, epoch: int):
        """The epoch's mesh, its record and (`select_best`) its image loss; returns the mesh."""
        cfg, dm, pd = self.cfg, self.dm, self.pd
        with self.clock("extract"):
            # Between epochs the visibility test and the hard render run at the optimised resolution; the
            # last epoch's mesh is the output unless `select_best` may pick another, so it is extracted once,
            # as the output is (full resolution).
            last = epoch == cfg.epochs - 1 and not cfg.select_best
            keep, removed, images = filtered_faces(dm, cfg.threshold, pd, cfg.interior,
                                                   self.full if last else self.cameras, cfg.select_best,
                                                   self.consistent)
            mesh = to_trimesh(dm.points.detach().double().numpy(), pd.faces[keep])
            self.final = (mesh, keep, removed) if last else None
            record = {"epoch": epoch, "points": len(dm), "faces": int(len(mesh.faces)), "interior_removed": removed}
            if images is not None and not last:  # (the last epoch's images are at the capture's resolution)
                record["eval_loss"] = self.eval_loss(images)
                if cfg.select_best and (self.best is None or record["eval_loss"] < self.best["eval_loss"]):
                    self.best = _candidate(epoch, record["eval_loss"], dm)
        self.info["epochs"].append(record)
        self.loop.stage(f"epoch{epoch}_end", **record, vertices=np.asarray(mesh.vertices) / self.scale + self.center,
                        triangles=np.asarray(mesh.faces))
        return mesh

    def reseed(self, epoch: int, mesh) -> None:
        """Epoch `epoch`'s DMesh and optimiser from the previous epoch's mesh."""
        with self.clock("init"):
            if len(mesh.faces) == 0:
                log.warning("epoch %d ended with an empty mesh; epoch %d restarts from the grid", epoch - 1, epoch)
            self.dm = self.init_points(epoch, mesh if len(mesh.faces) else None)
            self.opt = BoundedAdam(self.dm.points, self.dm.weights, self.dm.reals, self.cfg.step_config(epoch))
            self.pd = None

    def output(self) -> MultiViewResult:
        """The selected epoch's mesh, oriented (`orient`) and mapped back to the input frame."""
        cfg, vw, info, best = self.cfg, self.vw, self.info, self.best
        self.loop.stage("extract")
        with self.clock("extract"):
            if best is not None and best["epoch"] != cfg.epochs - 1:
                self.dm = DMesh(best["points"], best["weights"], best["reals"], cfg.probability_config())
                self.pd = None
            if best is not None:
                info["selected_epoch"] = best["epoch"]
            if self.final is not None:
                mesh, keep, removed = self.final
            else:
                self.pd = self.pd if self.pd is not None else self.dm.power_diagram()
                keep, removed, _ = filtered_faces(self.dm, cfg.threshold, self.pd, cfg.interior, self.full,
                                                  consistent=self.consistent)
                mesh = to_trimesh(self.dm.points.detach().double().numpy(), self.pd.faces[keep])
        groups = None  # the points of the triangulation the vertices are copies of (None: each its own)
        if cfg.orient:  # the faces' closed, outward surface (dmesh.surface); sheets face their cameras
            with self.clock("orient"):
                points = np.asarray(mesh.vertices, dtype=np.float64)
                seen = np.repeat(np.arange(len(vw.mask)), vw.mask.reshape(len(vw.mask), -1).sum(1))
                towards = towards_cameras((lifted_points(vw) - self.center) * self.scale, self.eyes[seen])
                # (directions towards the cameras are not normals: `multiview_config.multiview_surface`)
                mesh = surface_mesh(self.pd, keep, towards, None, cfg.surface)
                info["surface"] = mesh.metadata.pop("surface")
                if len(points) and cfg.depth_fit:
                    groups = copy_groups(mesh.vertices, points)
        if cfg.depth_fit and len(mesh.faces):  # vertices onto the captured depth (dmesh.recon.depth_fit)
            with self.clock("depth_fit"):
                verts, info["depth_fit"] = fit_to_depth(mesh.vertices, mesh.faces, self.w2c, vw.fov_y_degrees,
                                                        vw.depth.astype(np.float64) * self.scale, vw.mask,
                                                        DepthFitConfig(seed=cfg.seed), groups=groups)
                mesh.vertices = verts
        mesh.vertices = np.asarray(mesh.vertices) / self.scale + self.center
        info.update({"faces": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)), "points": len(self.dm),
                     "interior_removed": removed, "hidden_points": int(self.pd.hidden.sum())})
        return MultiViewResult(mesh, self.dm, self.center, self.scale, self.loop.finish(), self.loop.history, info)


def copy_groups(vertices, points) -> np.ndarray:
    """(V,) int: for each vertex of the surface step's mesh, the index of the extracted point it is a copy of.

    The surface step gives a point where sheets meet one copy per sheet, each moved a few percent of an edge
    into its own faces (`dmesh.surface.finish.separate_copies`); every other vertex is one of `points` itself. So the
    nearest of `points` is the vertex's source. `fit_to_depth` moves a group's copies together."""
    from scipy.spatial import cKDTree

    return cKDTree(np.asarray(points, dtype=np.float64)).query(np.asarray(vertices, dtype=np.float64))[1]


@deterministic
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
    for bit at a given thread count: the triangulation's order is canonical, the native kernels (renderers,
    Delta) reduce in a fixed order and torch runs its deterministic algorithms (`loop.deterministic`).
    """
    cfg = config or MultiViewConfig.paper()
    if not isinstance(cfg, MultiViewConfig):
        raise TypeError(f"config must be a MultiViewConfig, got {type(cfg).__name__}")
    run = _Run(views, cfg, callback, state_path)
    epoch, phase, start = run.start()
    while epoch < cfg.epochs:
        mesh = run.run_epoch(epoch, phase, start)
        epoch, phase, start = epoch + 1, 1, 0
        if epoch < cfg.epochs:
            run.reseed(epoch, mesh)
        run.loop.save({"epoch": epoch, "phase": 1, "step": 0}, run.opt)
    return run.output()


__all__ = ["MultiViewConfig", "MultiViewResult", "PRESETS", "reconstruct"]
