"""Point cloud to mesh (the paper's Exp. 2): expected Chamfer distance, regularisers, two phases.

Letters: G input points, N DMesh points, M scored faces, S samples per step, F output faces.

Procedure (paper appendix 9.2, Algorithm 2; upstream `2_pc_recon.py`):
0. With `outlier_std` > 0 (not upstream; the `fast` and `noisy` presets): input points whose mean distance to their 16
   nearest neighbours is beyond the mean by that many standard deviations are dropped, unless they lie on the
   surface their neighbours form (sparse surface samples, as where a scanner's rays graze;
   `dmesh.recon.init.statistical_inliers`); info["outliers_dropped"] counts them. With `smooth_k` > 0
   (not upstream; the `noisy` preset) every remaining point then moves onto the quadratic jet fitted to its
   `smooth_k` nearest neighbours (`dmesh.recon.init.smooth_points`, CGAL's jet smoothing), which removes most
   of the noise along the normal. With `auto_smooth_k` > 0 instead (the `fast` preset) that smoothing, with
   `auto_smooth_k` neighbours, happens only when the input looks noisy (`dmesh.recon.init.noise_ratio` above
   `NOISY_RATIO`). The seeds and the Chamfer target are the smoothed points. Without either, an input that
   looks noisy gets a warning naming the `noisy` preset. info["noise_ratio"] holds the figure and
   info["smooth_k"] the neighbours used (0: not smoothed).
1. Normalise the input (mean to the origin, max norm 1); keep `num_target` of the points as the Chamfer
   target; initialise from `num_init` seeds (real; of smoothed input at most `smoothed_seeds`, not upstream)
   plus their Voronoi vertices in [-1, 1]^3 (imaginary), plus the 8 corners of [-1.25, 1.25]^3 (imaginary,
   also in the seeds' triangulation; they keep it three-dimensional for flat inputs and the surface away from
   the hull), all weights 1.
2. Phase 1 (`steps_phase1`): every step re-triangulates and scores the WDT faces and the candidates
   (`DMesh.face_probabilities`), samples the probable faces, and minimises expected Chamfer + weight, real
   (ramped) and quality regularisers over positions, weights and reals with `BoundedAdam`.
3. Phase 2 (`steps_phase2`): the WDT is computed once and frozen: its faces get Lambda_wdt = 1 and
   Lambda = dmin of their real values; only the reals move, under expected Chamfer + the growth real
   regulariser. At the steps in `freeze_phase2`, points on the current mesh are frozen at real value 1.
   Once the mesh has not changed for `phase2_patience` steps (not upstream), the phase ends there;
   info["phase2_settled_at"] is that step.
4. The mesh: faces of the final WDT whose three real values exceed `threshold` (`extraction`); with
   `orient`, their closed, outward surface (the surface step, `dmesh.surface`, with the settings `surface`: tets
   inside / outside, small holes filled, fins dropped, open sheets facing the input normals when given); mapped
   back to the input frame.
5. With `redo_fragmented` > 0 and `auto_smooth_k` > 0 (not upstream; the `fast` preset): a run that did not
   smooth its input and whose mesh (its surface before the sheets' clean-up: the surface step's rim stage,
   `_rim`) has more than `redo_fragmented` boundary edges per face and more than `FRAGMENTED_RIM` times the
   square root of its face count (noise that `noise_ratio` missed: the mesh is in shreds; a small intact mesh has
   many boundary edges per face but few per root face) is done again with the input smoothed (`auto_smooth_k`
   neighbours, `smoothed_seeds`); info["fragmented_attempt"] holds the first attempt's figures, and the
   timings' "total" includes it.

The steps run in `dmesh.recon.loop.Loop.run_phase` (backward, update, history, callback, checkpoints);
this module supplies each phase's step function (`_Run.phase1_step`, `_Run.phase2_step`).
A run can be resumed from `state_path` (written atomically every `save_every` steps and at the end of each
phase): same config and same input give the same mesh as an uninterrupted run (the state holds the parameters,
the optimiser, the Chamfer k, the RNG and the phase's candidate faces and neighbour cache).
"""
from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from dmesh.checks import check_coordinates, check_not_a_line
from dmesh.extract import extract  # re-exported: the raw-faces mesh of a DMesh
from dmesh.geometry import gather
from dmesh.losses.chamfer import ExpectedChamfer, sample_faces
from dmesh.losses.regularizers import add_phase1_regularizers, real_regularizer
from dmesh.probability import dmin
from dmesh.recon.budget import reduce_to_budget
from dmesh.recon.config import FRAGMENTED_RIM, POINTCLOUD_PRESETS as PRESETS, PointCloudConfig
from dmesh.recon.guard import BestState, collapsed
from dmesh.recon.init import (NOISY_RATIO, carve_far_faces, noise_ratio, seeds_and_voronoi, separate_thin_walls,
                              smooth_points, statistical_inliers)
from dmesh.recon.loop import (Loop, ReconstructionResult, deterministic, fingerprint, freeze_faces, mesh_mask,
                              timed_probabilities)
from dmesh.recon.optim import BoundedAdam
from dmesh.surface.topology import boundary_edge_count
from dmesh.tolerances import DIVISION_FLOOR

log = logging.getLogger(__name__)

#: Fewest distinct input points accepted.
MIN_POINTS = 10
#: Half-size of the box whose corners are added as imaginary points (unit-radius frame).
CORNER_BOX = 1.25
#: With `best_every`: phase 2 starts from the best state scored when the last state scores this much worse
#: (relative; `_Run.keep_best`).
BEST_MARGIN = 0.1


@dataclass
class PointCloudResult(ReconstructionResult):
    """Output of `reconstruct` (`dmesh.recon.loop.ReconstructionResult`): mesh in the input frame, dmesh in the
    unit-radius frame of center / scale; history: one dict per step (phase, step, loss, cd_gt, cd_ours, k,
    faces, ...); info: counts (points, real seeds, final faces, ...)."""


def check_points(points, normals=None) -> tuple[np.ndarray, np.ndarray | None]:
    """Validated float64 copies of (G, 3) points and optional (G, 3) normals; ValueError naming the problem."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if len(pts) == 0:
        raise ValueError("the point cloud is empty")
    bad = ~np.isfinite(pts).all(1)
    if bad.any():
        raise ValueError(f"the point cloud has NaN or inf coordinates ({int(bad.sum())} of {len(pts)} points)")
    distinct = len(np.unique(pts, axis=0))
    if distinct == 1:
        raise ValueError(f"all {len(pts)} points are identical")
    if distinct < MIN_POINTS:
        raise ValueError(f"need at least {MIN_POINTS} distinct points, got {distinct}")
    check_coordinates(pts, "the point cloud")
    check_not_a_line(pts, "the point cloud")
    nrm = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals must have the points' shape {pts.shape}, got {nrm.shape}")
        if not np.isfinite(nrm).all():
            raise ValueError("normals contain NaN or inf")
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        if not (length > 0).all():  # a zero vector has no direction to normalise to
            raise ValueError(f"{int((length <= 0).sum())} of {len(nrm)} normals have zero length (give a direction "
                             f"at every point, or no normals)")
        nrm = nrm / np.maximum(length, DIVISION_FLOOR)
    return pts, nrm


class _Run:
    """One reconstruction's state and its pieces, in the order `reconstruct` calls them: `setup` (seeds,
    normalisation, initial DMesh and Chamfer term), `resume`, the phase step functions (`phase1_step`;
    `freeze_wdt`, then `phase2_step` and `phase2_faces`) and `extract`."""

    def __init__(self, pts_in: np.ndarray, nrm_in: np.ndarray | None, cfg: PointCloudConfig, callback,
                 state_path, probe):
        self.cfg, self.nrm_in = cfg, nrm_in
        self.rng = np.random.default_rng(cfg.seed)
        torch.manual_seed(cfg.seed)
        self.chamfer, self.smoothed = None, False
        if probe is not None:  # the probe also gets the frame, which the input filters may have moved
            every, fn = probe
            probe = (every, lambda params, record: fn({**params, "center": self.center, "scale": self.scale}, record))
        self.loop = Loop(callback, state_path, fingerprint(pts_in, cfg), cfg.save_every,
                         extra_state=lambda: {"k": self.chamfer.k, "rng": self.rng.bit_generator.state,
                                              "probability": self.dm.state,
                                              "best": None if self.best is None else self.best.state()},
                         probe=probe)
        self.best, self.first_faces = None, None  # the phase-1 guard (dmesh.recon.guard)
        self.clock = self.loop.clock
        self.with_normals = cfg.lambda_normal > 0
        self._phase2_mask, self._phase2_same = None, 0  # the last phase-2 mesh, and the steps it has held

    def clean_input(self, pts: np.ndarray, nrm: np.ndarray | None):
        """Procedure step 0 (stage "clean_input"): statistical outliers dropped, the noise measured, the points
        smoothed; returns (points, normals, info figures) and keeps the normals of the points kept."""
        cfg, info = self.cfg, {}
        with self.clock("clean_input"):
            if cfg.outlier_std > 0:
                keep = statistical_inliers(pts, cfg.outlier_std, workers=cfg.workers)
                info["outliers_dropped"] = int((~keep).sum())
                pts, nrm = pts[keep], None if nrm is None else nrm[keep]
            info["noise_ratio"] = noise_ratio(pts, workers=cfg.workers, normals=nrm)
            k = cfg.smooth_k
            if k == 0 and cfg.auto_smooth_k > 0 and info["noise_ratio"] > NOISY_RATIO:
                k = cfg.auto_smooth_k
                log.info("the input looks noisy: its points lie %.3f neighbour spacings off their local planes "
                         "(median; clean samples of smooth surfaces lie under %.2f): smoothing it (%d neighbours)",
                         info["noise_ratio"], NOISY_RATIO, k)
            info["smooth_k"] = int(k)
            self.smoothed = k > 0
            if k > 0:
                pts = smooth_points(pts, min(k, len(pts) - 1), workers=cfg.workers)
            elif info["noise_ratio"] > NOISY_RATIO:
                log.warning("the input looks noisy: its points lie %.3f neighbour spacings off their local planes "
                            "(median; clean samples of smooth surfaces lie under %.2f); the `noisy` preset smooths "
                            "it first (multi-view `depth`: --set init_preset=noisy)", info["noise_ratio"],
                            NOISY_RATIO)
        self.nrm_in = nrm
        return pts, nrm, info

    def setup(self, pts_in: np.ndarray) -> dict:
        """Normalises the input, picks the Chamfer target, builds the initial DMesh and the Chamfer term
        (procedure step 1) and the phase-1 optimiser; returns the run's first info counts."""
        from dmesh.model import DMesh

        cfg, rng, nrm_in = self.cfg, self.rng, self.nrm_in
        self.loop.stage("init")
        with self.clock("init"):
            self.center = pts_in.mean(0)
            radius = float(np.linalg.norm(pts_in - self.center, axis=1).max())
            self.scale = 1.0 / radius
            self.pts = pts = (pts_in - self.center) * self.scale
            tidx = rng.choice(len(pts), cfg.num_target, replace=False) if cfg.num_target < len(pts) else None
            target = pts if tidx is None else pts[tidx]
            target_n = None if nrm_in is None else (nrm_in if tidx is None else nrm_in[tidx])
            seeds = cfg.num_init
            if self.smoothed and cfg.smoothed_seeds > 0:
                seeds = min(seeds, cfg.smoothed_seeds)
            positions, reals = seeds_and_voronoi(pts, seeds, rng, cfg.domain, cfg.max_voronoi, CORNER_BOX,
                                                 vertices=cfg.voronoi)
            thin = {}
            if cfg.thin_walls > 0 and nrm_in is not None:
                positions, reals, thin = separate_thin_walls(positions, reals, pts, nrm_in, cfg.thin_walls,
                                                             workers=cfg.workers)
            carved = 0
            if cfg.carve > 0:
                positions, reals, carved = carve_far_faces(positions, reals, pts, cfg.carve, cfg.extraction,
                                                           workers=cfg.workers)
            self.dm = dm = DMesh(positions, np.ones(len(positions)), reals, cfg.probability_config())
            uses_normals = cfg.lambda_normal > 0 or cfg.tangent_weight < 1.0
            self.chamfer = ExpectedChamfer(target, target_n if uses_normals else None, k_max=cfg.k_max,
                                           mass_tol=cfg.mass_tol, k_first=cfg.k_first, lambda_normal=cfg.lambda_normal,
                                           workers=cfg.workers, impl=cfg.kernels, tangent_weight=cfg.tangent_weight,
                                           coverage=cfg.coverage)
            if cfg.best_every > 0:
                self.best = BestState(target, cfg.seed, cfg.workers)
        self.opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(), cfg.train_phase1)
        return {"input_points": int(len(pts_in)), "target_points": int(len(target)), "points": len(dm),
                "real_seeds": int((reals > 0.5).sum()), "carved": carved, "fingerprint": self.loop.fingerprint,
                **thin}

    def resume(self, info: dict) -> tuple[int, int]:
        """(phase, first step) to run: (1, 0), or the saved position, whose DMesh (with its phase's candidate
        faces and neighbour cache), optimiser, Chamfer k and RNG state replace the fresh ones."""
        from dmesh.model import DMesh

        cfg = self.cfg
        resumed = self.loop.resume()
        if resumed is None:
            return 1, 0
        phase, start = resumed["phase"], resumed["step"]
        if phase == 3:  # finished: straight to extraction
            phase, start = 2, cfg.steps_phase2
        with torch.no_grad():
            self.dm = dm = DMesh(resumed["points"], resumed["weights"], resumed["reals"], cfg.probability_config())
        if "probability" in resumed:  # (states written before it was saved lack it: the phase's caches restart)
            dm.state = resumed["probability"]
        self.opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(),
                               cfg.train_phase1 if phase == 1 else ("reals",))
        if resumed.get("optimizer") is not None:
            self.opt.load_state_dict(resumed["optimizer"])
        self.chamfer.k = int(resumed["k"])
        self.rng.bit_generator.state = resumed["rng"]
        if self.best is not None:
            self.best.restore(resumed.get("best"))
        first = [r["faces"] for r in self.loop.history if r.get("phase") == 1 and "faces" in r]
        self.first_faces = first[0] if first else None
        info["resumed_from"] = {"phase": phase, "step": start, "seconds": self.loop.earlier_seconds}
        log.info("resuming from phase %d step %d", phase, start)
        return phase, start

    def phase1_step(self, step: int):
        """Procedure step 2: re-triangulate and score, sample, expected Chamfer plus the regularisers."""
        cfg, dm, clock = self.cfg, self.dm, self.clock
        probs = timed_probabilities(dm, clock, "phase1_")
        pd = probs.power_diagram
        hard = mesh_mask(dm.reals, pd.faces, cfg.threshold)
        with clock("phase1_sampling"):
            samples = sample_faces(dm.points, probs.faces, probs.prob_wdt, dm.reals, probs.prob, cfg.num_samples,
                                   self.rng, cfg.prob_threshold, with_normals=self.with_normals)
        with clock("phase1_chamfer"):
            loss, fig = self.chamfer(samples)
        with clock("phase1_regularizers"):
            loss = add_phase1_regularizers(loss, dm, probs, pd, cfg, step)
        figures = {"cd_gt": fig["cd_gt"], "cd_ours": fig["cd_ours"], "k": fig["k"], "faces": int(hard.sum()),
                   "candidates": int(len(probs.faces)), "samples": len(samples)}
        if self.first_faces is None:
            self.first_faces = figures["faces"]
        if self.best is not None and step % cfg.best_every == 0:
            with clock("phase1_guard"):
                figures["input_cd"] = self.best.offer(step, dm.points, dm.weights, dm.reals, pd.faces[hard])
        return loss, figures

    def phase1_collapsed(self, figures: dict) -> bool:
        """The `stop` rule of phase 1 (`collapse_share` > 0): its mesh has fewer faces than that share of the
        first step's (dmesh.recon.guard)."""
        return collapsed(figures["faces"], self.first_faces, self.cfg.collapse_share)

    def keep_best(self, info: dict, steps: int, collapsed_at: int | None) -> None:
        """After phase 1 with `best_every` > 0: scores the last state too; phase 2 starts from the best state
        scored when the phase collapsed (`collapsed_at`, its step) or when the last state scores more than
        `BEST_MARGIN` worse (a mesh losing surface; the score's sampling noise is about 0.5 %), else from the last
        (info["best_state"]: the step phase 2 starts from, the best and the last scores)."""
        from dmesh.model import DMesh

        if self.best is None:
            return
        dm = self.dm
        with self.clock("phase1_guard"):
            pd = dm.power_diagram()
            last = self.best.offer(steps, dm.points, dm.weights, dm.reals,
                                   pd.faces[mesh_mask(dm.reals, pd.faces, self.cfg.threshold)])
        kept = self.best.step != steps and (collapsed_at is not None or last > (1.0 + BEST_MARGIN) * self.best.score)
        info["best_state"] = {"step": self.best.step if kept else steps, "best_step": self.best.step,
                              "best_score": self.best.score, "last_score": last, "last_step": steps}
        if kept:
            p = self.best.params
            log.info("phase 1: keeping the state of step %d (input Chamfer %.3g; the last state's %.3g)",
                     self.best.step, self.best.score, last)
            with torch.no_grad():
                self.dm = DMesh(p["points"].clone(), p["weights"].clone(), p["reals"].clone(),
                                self.cfg.probability_config())

    def start_phase2(self) -> None:
        """The phase-2 optimiser (reals only), saved as the state at phase 2 step 0."""
        dm = self.dm
        self.opt = BoundedAdam(dm.points, dm.weights, dm.reals, self.cfg.step_config(), train=("reals",))
        self.loop.save({"phase": 2, "step": 0}, self.opt)

    def freeze_wdt(self) -> None:
        """Procedure step 3's frozen WDT: its faces, scored with Lambda_wdt = 1 from now on."""
        self.loop.stage("phase2")
        with self.clock("phase2_wdt"):
            self.pd = self.dm.power_diagram()
            self.faces = torch.from_numpy(self.pd.faces.astype(np.int64))
            self.ones = torch.ones(len(self.faces), dtype=self.dm.points.dtype)

    def phase2_step(self, step: int):
        """Procedure step 3: freezes at the scheduled steps, samples the frozen faces, expected Chamfer plus the
        growth real regulariser."""
        cfg, dm, clock, pd, faces, ones = self.cfg, self.dm, self.clock, self.pd, self.faces, self.ones
        if step in cfg.freeze_phase2:
            freeze_faces(self.opt, pd.faces[mesh_mask(dm.reals, pd.faces, cfg.threshold)])
        with clock("phase2_sampling"):
            prob = dmin(gather(dm.reals, faces).double(), cfg.alpha_real)
            samples = sample_faces(dm.points, faces, ones, dm.reals, prob, cfg.num_samples, self.rng,
                                   cfg.prob_threshold, with_normals=self.with_normals)
        with clock("phase2_chamfer"):
            loss, fig = self.chamfer(samples)
        with clock("phase2_regularizers"):
            if cfg.lambda_real_end > 0:
                loss = loss + cfg.lambda_real_end * real_regularizer(dm.reals, faces, ones, smooth=False)
        return loss, {"cd_gt": fig["cd_gt"], "cd_ours": fig["cd_ours"], "k": fig["k"],
                      "candidates": int(len(faces)), "samples": len(samples)}

    def phase2_faces(self, step: int) -> dict:
        """The size of the mesh after the update; counts the steps since the mesh last changed
        (`phase2_settled`)."""
        mask = mesh_mask(self.dm.reals, self.pd.faces, self.cfg.threshold)
        same = self._phase2_mask is not None and np.array_equal(mask, self._phase2_mask)
        self._phase2_mask, self._phase2_same = mask, self._phase2_same + 1 if same else 0
        return {"faces": int(mask.sum())}

    def phase2_settled(self, figures: dict) -> bool:
        """The `stop` rule of phase 2 (`phase2_patience` > 0): the mesh has not changed for that many steps, so
        the remaining steps are left out. A resumed phase 2 counts from its resumption."""
        return 0 < self.cfg.phase2_patience <= self._phase2_same

    def extract(self, info: dict) -> PointCloudResult:
        """Procedure step 4: the mesh of the final WDT, mapped back to the input frame."""
        cfg, pd = self.cfg, self.pd
        self.loop.stage("extract")
        with self.clock("extract"):
            # With `orient`: the faces' closed, outward surface (dmesh.surface); input normals, when given, vote
            # inside/outside and turn the open sheets.
            surface = cfg.surface
            if surface is not None and _mostly_thin(info):  # a thin solid, not a pocket in a doubled sheet
                surface = dataclasses.replace(surface, vote=dataclasses.replace(surface.vote, min_thickness=0.0))
            mesh = self.dm.extract_mesh(cfg.threshold, cfg.extraction, surface=surface if cfg.orient else None,
                                        pd=pd, normals=None if self.nrm_in is None else (self.pts, self.nrm_in),
                                        samples=self.pts)
        if "surface" in mesh.metadata:
            info["surface"] = mesh.metadata.pop("surface")
        mesh.vertices = np.asarray(mesh.vertices) / self.scale + self.center
        info.update({"faces": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)),
                     "hidden_points": int(pd.hidden.sum()), "final_k": int(self.chamfer.k)})
        return PointCloudResult(mesh, self.dm, self.center, self.scale, self.loop.finish(), self.loop.history, info)


@deterministic
def reconstruct(points, normals=None, config: PointCloudConfig | None = None,
                callback: Callable[[dict], None] | None = None,
                state_path: str | os.PathLike | None = None, probe=None) -> PointCloudResult:
    """Reconstructs a mesh from a point cloud with DMesh.

    Args:
        points: (G, 3) float input points (any frame); normals: (G, 3) float or None (the normal term when
            `config.lambda_normal` > 0; with `config.orient`, the output's inside / outside vote and the side
            its open sheets face).
        config: `PointCloudConfig` (None: the paper preset).
        callback: called after every step with {"phase", "step", "steps", "loss", "cd_gt", "cd_ours", "k",
            "faces" (current mesh faces), "candidates" (scored faces), "samples", "seconds"}; also with
            {"stage": name} when a stage starts ("init", "phase1", "phase2", "extract").
        state_path: file for the resumable state; an existing state of the same input and config is resumed.
        probe: optional (every, fn): fn(params, record) after every `every`-th step of each phase and after
            its last (`Loop`); params holds the current "points", "weights", "reals" tensors and the frame
            ("center", "scale": input = unit frame / scale + center, after the input filters). For curves of
            figures that need the whole state (e.g. the extracted mesh's Chamfer distance).
    Returns:
        `PointCloudResult`.
    Raises:
        ValueError: bad points (empty, too few, NaN, all identical, on one line, coordinates past
            `dmesh.tolerances.MAX_COORDINATE`), zero-length normals, or a bad config.
    """
    cfg = config or PointCloudConfig.paper()
    pts_in, nrm_in = check_points(points, normals)
    if cfg.lambda_normal > 0 and nrm_in is None:
        raise ValueError("lambda_normal > 0 needs normals")
    if cfg.tangent_weight < 1.0 and nrm_in is None:
        raise ValueError("tangent_weight < 1 (the compact preset's 0.2) needs input normals; give normals or set "
                         "tangent_weight=1")
    result = _reconstruct_once(pts_in, nrm_in, cfg, callback, state_path, probe)
    # A mesh of walls thinner than the spacing has the rim of its shreds without noise: no redo when most seeds
    # lie on such walls (`thin_walls`; smoothing would merge the two sides of each wall into one).
    if cfg.redo_fragmented > 0 and cfg.auto_smooth_k > 0 and result.info["smooth_k"] == 0 \
            and not _mostly_thin(result.info):
        boundary, count = _rim(result)
        per_face = boundary / max(count, 1)
        if per_face > cfg.redo_fragmented and boundary > FRAGMENTED_RIM * np.sqrt(count):
            log.warning("the mesh came out in shreds (%.2f boundary edges per face; over %.2f): the input is "
                        "noisier than it measured (%.3f), making it again from the smoothed input (%d neighbours)",
                        per_face, cfg.redo_fragmented, result.info["noise_ratio"], cfg.auto_smooth_k)
            first = {"boundary_edges_per_face": round(float(per_face), 4), "faces": int(count),
                     "seconds": result.timings.get("total")}
            spent = {key: float(result.timings.get(key, 0.0)) for key in ("total", "total_cpu")}
            smoothed = dataclasses.replace(cfg, smooth_k=cfg.auto_smooth_k, auto_smooth_k=0, redo_fragmented=0.0)
            result = _reconstruct_once(pts_in, nrm_in, smoothed, callback, state_path, probe)
            result.info["fragmented_attempt"] = first
            for key, seconds in spent.items():
                result.timings[key] = result.timings.get(key, 0.0) + seconds
    if cfg.faces > 0:
        result.mesh, result.info["budget"] = reduce_to_budget(result.mesh, cfg.faces)
        result.timings["budget"] = result.info["budget"]["seconds"]
        result.timings["budget_cpu"] = result.info["budget"]["cpu_seconds"]
        for key in ("total", "total_cpu"):
            result.timings[key] = result.timings.get(key, 0.0) + result.timings[key.replace("total", "budget")]
        result.info["faces"] = int(len(result.mesh.faces))
    return result


#: Share of the seeds on thin walls (`thin_wall_points`) above which a shredded first mesh is not redone smoothed
#: and the surface step's vote keeps regions thinner than `vote.min_thickness` (the walls are a solid's).
THIN_WALL_SHARE = 0.5


def _mostly_thin(info: dict) -> bool:
    """Whether most seeds of a run lie on walls thinner than the spacing (`separate_thin_walls`' count)."""
    return info.get("thin_wall_points", 0) > THIN_WALL_SHARE * info.get("real_seeds", 0)


def _rim(result: PointCloudResult) -> tuple[int, int]:
    """(boundary edges, faces) by which `redo_fragmented` judges a mesh: the oriented surface's before the
    clean-up of its sheets (info["surface"]'s rim_edges, rim_faces), whose hole fills and dropped pieces
    would hide the shreds (docs/preset_choices.md); without `orient`, the extracted faces' boundary edges."""
    surface = result.info.get("surface", {})
    if "rim_edges" in surface:
        return int(surface["rim_edges"]), int(surface["rim_faces"])
    faces = np.asarray(result.mesh.faces)
    return boundary_edge_count(faces), len(faces)


def _reconstruct_once(pts_in, nrm_in, cfg, callback, state_path, probe) -> PointCloudResult:
    """One pass of the procedure's steps 0-4 on checked input."""
    run = _Run(pts_in, nrm_in, cfg, callback, state_path, probe)  # its clock and resume key: the raw input
    pts_in, _, cleaning = run.clean_input(pts_in, nrm_in)
    info = run.setup(pts_in)
    info.update(cleaning)
    phase, start = run.resume(info)
    if phase == 1:
        run.loop.stage("phase1")
        if run.loop.run_phase(run.phase1_step, run.opt, cfg.steps_phase1, start, {"phase": 1}, "phase1_",
                              stop=run.phase1_collapsed if cfg.collapse_share > 0 else None):
            info["phase1_collapsed_at"] = int(run.loop.history[-1]["step"])
            log.warning("phase 1 stopped at step %d: its mesh fell to %d faces, under %.2f of its first %d",
                        info["phase1_collapsed_at"], run.loop.history[-1]["faces"], cfg.collapse_share,
                        run.first_faces)
        if cfg.steps_phase1 > 0:  # the state now: the collapsed step's (no update), else the last step's
            run.keep_best(info, info.get("phase1_collapsed_at", cfg.steps_phase1), info.get("phase1_collapsed_at"))
        start = 0
        run.start_phase2()
    run.freeze_wdt()
    if run.loop.run_phase(run.phase2_step, run.opt, cfg.steps_phase2, start, {"phase": 2}, "phase2_",
                          after_step=run.phase2_faces, stop=run.phase2_settled):
        info["phase2_settled_at"] = int(run.loop.history[-1]["step"])
    run.loop.save({"phase": 3, "step": 0}, run.opt)
    return run.extract(info)


__all__ = ["PointCloudConfig", "PointCloudResult", "PRESETS", "reconstruct", "check_points", "extract"]
