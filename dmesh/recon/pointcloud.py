"""Point cloud to mesh (the paper's Exp. 2): expected Chamfer distance, regularisers, two phases.

Letters: G input points, N DMesh points, M scored faces, S samples per step, F output faces.

Procedure (paper appendix 9.2, Algorithm 2; upstream `2_pc_recon.py`):
1. Normalise the input (mean to the origin, max norm 1); keep `num_target` of the points as the Chamfer
   target; initialise from `num_init` seeds (real) plus their Voronoi vertices in [-1, 1]^3 (imaginary),
   plus the 8 corners of [-1.25, 1.25]^3 (imaginary, also in the seeds' triangulation; they keep it
   three-dimensional for flat inputs and the surface away from the hull), all weights 1.
2. Phase 1 (`steps_phase1`): every step re-triangulates and scores the WDT faces and the candidates
   (`DMesh.face_probabilities`), samples the probable faces, and minimises expected Chamfer + weight, real
   (ramped) and quality regularisers over positions, weights and reals with `BoundedAdam`.
3. Phase 2 (`steps_phase2`): the WDT is computed once and frozen: its faces get Lambda_wdt = 1 and
   Lambda = dmin of their real values; only the reals move, under expected Chamfer + the growth real
   regulariser. At the steps in `freeze_phase2`, points on the current mesh are frozen at real value 1.
4. The mesh: faces of the final WDT whose three real values exceed `threshold` (`extraction`); with
   `orient`, their closed, outward surface (`dmesh.extract.surface`: tets inside / outside, small holes
   filled, fins dropped, open sheets facing the input normals when given); mapped back to the input frame.

The steps run in `dmesh.recon.loop.Loop.run_phase` (backward, update, history, callback, checkpoints);
this module supplies each phase's step function (`phase1_step`, `phase2_step` in `reconstruct`).
A run can be resumed from `state_path` (written atomically every `save_every` steps and at the end of each
phase): same config and same input give the same continuation, except that the per-phase candidate set and
neighbour cache restart empty after a resume (they are rebuilt within a few steps).
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from dmesh.extract import SurfaceConfig, extract, orient_faces  # extract, orient_faces: re-exported
from dmesh.losses.chamfer import ExpectedChamfer, sample_faces
from dmesh.losses.regularizers import add_phase1_regularizers, real_regularizer
from dmesh.probability import ProbabilityConfig, dmin
from dmesh.recon.init import carve_far_faces, seeds_and_voronoi
from dmesh.recon.loop import TRAIN_ALL, Loop, ReconstructionResult, fingerprint, freeze_faces, mesh_mask
from dmesh.recon.optim import BoundedAdam, StepConfig

log = logging.getLogger(__name__)

#: Fewest distinct input points accepted.
MIN_POINTS = 10
#: Half-size of the box whose corners are added as imaginary points (unit-radius frame).
CORNER_BOX = 1.25


@dataclass(frozen=True)
class PointCloudConfig:
    """Settings of `reconstruct` (defaults: the paper's, see `paper()`); lengths in the unit-radius frame."""

    num_init: int = 10_000          # input points used as real seeds
    max_voronoi: int | None = None  # keep at most this many Voronoi vertices (None: all inside the domain)
    voronoi_keep: str = "largest"   # which `max_voronoi` to keep: "largest" empty spheres, or "random"
    voronoi: str = "all"            # imaginary points: "all" Voronoi vertices (upstream) or the seeds' "poles"
    carve: float = 0.0              # > 0: imaginary points on first-mesh faces this many seed spacings from
                                    # the input (dmesh.recon.init.carve_far_faces); 0: off (upstream)
    domain: float = 1.0             # Voronoi vertices outside [-domain, domain]^3 are dropped
    num_target: int = 100_000       # input points used as the Chamfer target (random subset)
    num_samples: int = 100_000      # points sampled on the DMesh per step (two strata of half each)
    steps_phase1: int = 1000        # steps optimising positions, weights and reals
    steps_phase2: int = 500         # steps optimising reals on the frozen tessellation
    lr: float = 3e-4                # Adam learning rate (positions, weights; reals: lr / max_real)
    update_bound: float = 3e-4      # per-step bound of each coordinate (reals: update_bound / max_real)
    max_real: float = 3e-3          # upstream's real-value scale (sets the reals' lr and bound)
    grad_clip: float | None = None  # per-point gradient norm clip (None: update_bound / lr)
    k_max: int = 100                # largest (and first) K of the target -> ours term
    mass_tol: float = 1e-4          # residual probability mass that makes K grow
    prob_threshold: float = 1e-3    # faces below this stratum factor are never sampled
    lambda_weight: float = 1e-8     # weight regulariser (power-diagram edge lengths)
    lambda_real_start: float = 1e-3  # real regulariser coefficient at phase-1 step 0
    lambda_real_end: float = 1e-3   # ... after `real_ramp_steps`, and in phase 2
    real_ramp_steps: int = 100      # phase-1 steps of the linear ramp of the real coefficient
    lambda_quality: float = 1e-3    # quality regulariser (aspect ratio x max edge x Lambda)
    lambda_normal: float = 0.0      # normal term of Eq. 13 (needs input normals)
    train_phase1: tuple = ("points", "weights", "reals")  # what phase-1 steps move (upstream: all three)
    freeze_phase1: tuple = ()       # phase-1 steps at which points on the mesh are frozen real
    freeze_phase2: tuple = (0, 250)  # phase-2 steps at which points on the mesh are frozen real
    alpha_wdt: float = 1000.0       # sigmoid sharpness of Lambda_wdt
    alpha_real: float = 100.0       # softmin sharpness of Lambda_real
    knn_interval: int = 10          # kNN candidate triples every this many steps
    knn_k: int = 8                  # neighbours of the kNN candidate triples
    knn_thresholds: tuple = (0.0, 0.2, 0.4, 0.6, 0.8)  # real-value thresholds of the kNN passes
    active_band: float | None = 15.0  # candidates with Delta below -band/alpha get no gradient
    threshold: float = 0.5          # real value above which a point is on the final mesh
    extraction: str = "sheet"       # which real faces make the mesh: "all", "no_interior", "sheet" (dmesh.extract)
    orient: bool = True             # output the faces' oriented, closed surface (dmesh.extract.surface)
    save_every: int = 50            # steps between resumable state saves (with a state path)
    workers: int = 2                # threads of the k-d tree queries
    kernels: str = "native"         # "native" (C++ expected Chamfer and Delta) or "reference" (torch, for checks)
    seed: int = 0                   # seed of every random choice

    def __post_init__(self):
        ints = ("num_init", "num_target", "num_samples", "k_max", "knn_k")
        for name in ints:
            if int(getattr(self, name)) < 1:
                raise ValueError(f"PointCloudConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("steps_phase1", "steps_phase2", "real_ramp_steps", "knn_interval", "save_every"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"PointCloudConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("lr", "update_bound", "max_real", "domain", "alpha_wdt", "alpha_real"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PointCloudConfig.{name} must be positive, got {getattr(self, name)}")
        for name in ("carve", "lambda_weight", "lambda_real_start", "lambda_real_end", "lambda_quality",
                     "lambda_normal", "prob_threshold", "mass_tol"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"PointCloudConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.voronoi_keep not in ("largest", "random"):
            raise ValueError(f"PointCloudConfig.voronoi_keep must be 'largest' or 'random', got {self.voronoi_keep!r}")
        from dmesh.extract import MODES

        if self.extraction not in MODES:
            raise ValueError(f"PointCloudConfig.extraction must be one of {', '.join(MODES)}, got {self.extraction!r}")
        if self.voronoi not in ("all", "poles"):
            raise ValueError(f"PointCloudConfig.voronoi must be 'all' or 'poles', got {self.voronoi!r}")
        if not 0.0 <= self.threshold < 1.0:
            raise ValueError(f"PointCloudConfig.threshold must be in [0, 1), got {self.threshold}")
        if self.kernels not in KERNELS:
            raise ValueError(f"PointCloudConfig.kernels must be one of {', '.join(KERNELS)}, got {self.kernels!r}")
        object.__setattr__(self, "knn_thresholds", tuple(float(t) for t in self.knn_thresholds))
        object.__setattr__(self, "freeze_phase1", tuple(int(s) for s in self.freeze_phase1))
        train = (self.train_phase1,) if isinstance(self.train_phase1, str) else tuple(self.train_phase1)
        if not train or set(train) - set(TRAIN_ALL):
            raise ValueError(f"PointCloudConfig.train_phase1 must name some of {', '.join(TRAIN_ALL)}, got {train}")
        object.__setattr__(self, "train_phase1", train)
        object.__setattr__(self, "freeze_phase2", tuple(int(s) for s in self.freeze_phase2))

    @classmethod
    def paper(cls, **overrides) -> "PointCloudConfig":
        """The published settings (appendix 10.2; upstream exp_2 configs with lr 3e-4)."""
        return cls(**overrides)

    @classmethod
    def fast(cls, **overrides) -> "PointCloudConfig":
        """A CPU budget: well under two minutes per shape on 2 cores.

        40K seeds and their poles (about 90K points; `dmesh.recon.init`) instead of 10K seeds and all
        their Voronoi vertices, with faces far from the input carved (`carve_far_faces`, for holes and open
        borders: wavy_sheet 2.24e-3 -> 0.04e-3); no phase-1 step; 10 phase-2 steps on 50K target points and 50K samples;
        one-sheet extraction (`dmesh.extract`). Chosen by measurement on the torus (2 cores shared with
        another job, 100K input points, cd_p2s x1e-3 / wall s):
        - the previous fast preset (10K seeds, all Voronoi vertices, 4 + 25 steps): 1.49 / 33;
        - its first mesh, before any step: 2.30 (the Voronoi vertices near the surface punch holes);
        - 40K seeds + poles, no step: 0.283 with "all" extraction, 0.199 with "sheet";
        - the same with 10 phase-2 steps: 0.197 / 32 (this preset);
        - with 3 phase-1 steps at lr 1e-5: 0.218 / 76; 20K seeds, 6 phase-1 steps at lr 2e-5: 0.461 / 86
          against 0.403 with none; at the paper's lr 3e-4, 4 phase-1 steps take 0.283 to 1.18.
        Phase-1 steps were too slow for this budget when it was chosen (torch kernels), and their first
        steps are noise: Adam moves every coordinate by about lr, which at this point density scrambles the
        nearly degenerate tets on the surface. So the preset spends its time on density instead; phase 1
        needs the `paper` schedule (its cost and curve: `python -m eval.bench step`)."""
        base = dict(num_init=40_000, voronoi="poles", carve=5.0, max_voronoi=None, num_target=50_000,
                    num_samples=50_000, steps_phase1=0, steps_phase2=10, k_max=16, lambda_weight=0.0,
                    real_ramp_steps=0, freeze_phase2=(0, 5), save_every=10)
        base.update(overrides)
        return cls(**base)

    @classmethod
    def noisy(cls, **overrides) -> "PointCloudConfig":
        """For noisy scans (not upstream): the `fast` start at 10K seeds, then 20 phase-1 steps that move only
        the positions, at the paper's lr 3e-4 with the paper's 100K target points and samples, then the fast
        preset's phase 2. The start puts the mesh
        vertices on noisy samples; the expected Chamfer's steps pull them toward the surface the samples
        spread around. On clean input the same steps only cost accuracy (the start's vertices already lie on
        the surface), so `fast` takes none. Measurements: `python -m eval.bench recipes`."""
        base = dict(num_init=10_000, voronoi="poles", carve=5.0, max_voronoi=None, num_target=100_000,
                    num_samples=100_000, steps_phase1=20, steps_phase2=10, lr=3e-4, update_bound=3e-4,
                    train_phase1=("points",), k_max=16, lambda_weight=0.0, real_ramp_steps=0,
                    freeze_phase2=(0, 5), save_every=10)
        base.update(overrides)
        return cls(**base)

    @classmethod
    def tiny(cls, **overrides) -> "PointCloudConfig":
        """Seconds, for tests and the CLI smoke run: 1000 seeds and their poles (~2.5K points), 2 + 15 steps
        at a tenth of the paper's lr, 4K target points and samples."""
        base = dict(num_init=1000, voronoi="poles", carve=5.0, max_voronoi=None, num_target=4000,
                    num_samples=4000, steps_phase1=2, steps_phase2=15, lr=3e-5, update_bound=3e-5, k_max=12, lambda_weight=0.0,
                    real_ramp_steps=2, freeze_phase2=(0, 8), knn_interval=5, save_every=10)
        base.update(overrides)
        return cls(**base)

    @classmethod
    def preset(cls, name: str, **overrides) -> "PointCloudConfig":
        """`paper`, `fast`, `noisy` or `tiny`."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
        return getattr(cls, name)(**overrides)

    def probability_config(self) -> ProbabilityConfig:
        return ProbabilityConfig(alpha_wdt=self.alpha_wdt, alpha_real=self.alpha_real,
                                 knn_interval=self.knn_interval, knn_k=self.knn_k,
                                 knn_thresholds=self.knn_thresholds, active_band=self.active_band,
                                 impl=self.kernels)

    def step_config(self) -> StepConfig:
        return StepConfig(lr=self.lr, update_bound=self.update_bound, max_real=self.max_real,
                          grad_clip=self.grad_clip)


PRESETS = ("paper", "fast", "noisy", "tiny")
#: Per preset: (whether it takes gradient steps on positions and weights, how it differs from the paper).
#: Reports print these beside every DMesh row.
RECIPES = {
    "paper": (True, "the published recipe: 10K seeds + all their Voronoi vertices, 1000 phase-1 steps (positions, "
                    "weights, reals) + 500 phase-2 steps (reals), lr 3e-4, 100K target points and samples, K <= 100. "
                    "Differs: the 8 corners of [-1.25, 1.25]^3 are added as imaginary points, the mesh is the "
                    "one-sheet extraction (upstream: every face with three real vertices) and is oriented per "
                    "component; CPU kernels."),
    "fast": (False, "an initialisation, no phase-1 step: 40K seeds + their poles (not all Voronoi vertices), faces "
                    "far from the input carved, then 10 phase-2 steps (reals only) on 50K target points and "
                    "samples, K <= 16, one-sheet extraction. Differs: no position or weight optimisation, 4x the "
                    "seeds, 10 of the paper's 1500 steps."),
    "noisy": (True, "not in the paper, for noisy scans: the fast start at 10K seeds, 20 phase-1 steps moving only "
                    "the positions at lr 3e-4 on 100K target points and samples, then the fast preset's 10 phase-2 "
                    "steps. On clean input it is several times worse than `fast`."),
    "tiny": (True, "tests only: 1000 seeds + poles, 2 + 15 steps at lr 3e-5, 4K target points."),
}
#: Implementations of the step's kernels (the expected Chamfer and the Delta recomputation).
KERNELS = ("native", "reference")


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
    nrm = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals must have the points' shape {pts.shape}, got {nrm.shape}")
        if not np.isfinite(nrm).all():
            raise ValueError("normals contain NaN or inf")
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = nrm / np.maximum(length, 1e-12)
    return pts, nrm


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
            its last (`Loop`); params holds the current "points", "weights", "reals" tensors. For curves of
            figures that need the whole state (e.g. the extracted mesh's Chamfer distance).
    Returns:
        `PointCloudResult`.
    Raises:
        ValueError: bad points (empty, too few, NaN, all identical) or config.
    """
    cfg = config or PointCloudConfig.paper()
    pts_in, nrm_in = check_points(points, normals)
    if cfg.lambda_normal > 0 and nrm_in is None:
        raise ValueError("lambda_normal > 0 needs normals")
    from dmesh.representation import DMesh

    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    chamfer = None
    loop = Loop(callback, state_path, fingerprint(pts_in, cfg), cfg.save_every,
                extra_state=lambda: {"k": chamfer.k, "rng": rng.bit_generator.state}, probe=probe)
    clock = loop.clock

    loop.stage("init")
    with clock("init"):
        center = pts_in.mean(0)
        radius = float(np.linalg.norm(pts_in - center, axis=1).max())
        scale = 1.0 / radius
        pts = (pts_in - center) * scale
        tidx = rng.choice(len(pts), cfg.num_target, replace=False) if cfg.num_target < len(pts) else None
        target = pts if tidx is None else pts[tidx]
        target_n = None if nrm_in is None else (nrm_in if tidx is None else nrm_in[tidx])
        positions, reals = seeds_and_voronoi(pts, cfg.num_init, rng, cfg.domain, cfg.max_voronoi, CORNER_BOX,
                                             cfg.voronoi_keep, cfg.voronoi)
        carved = 0
        if cfg.carve > 0:
            positions, reals, carved = carve_far_faces(positions, reals, pts, cfg.carve, cfg.extraction,
                                                       workers=cfg.workers)
        dm = DMesh(positions, np.ones(len(positions)), reals, cfg.probability_config())
        chamfer = ExpectedChamfer(target, target_n if cfg.lambda_normal > 0 else None, k_max=cfg.k_max,
                                  mass_tol=cfg.mass_tol, lambda_normal=cfg.lambda_normal, workers=cfg.workers,
                                  impl=cfg.kernels)
    info = {"input_points": int(len(pts_in)), "target_points": int(len(target)), "points": len(dm),
            "real_seeds": int((reals > 0.5).sum()), "carved": carved, "fingerprint": loop.fingerprint}
    phase, start = 1, 0
    opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(), cfg.train_phase1)
    resumed = loop.resume()
    if resumed is not None:
        phase, start = resumed["phase"], resumed["step"]
        if phase == 3:  # finished: straight to extraction
            phase, start = 2, cfg.steps_phase2
        with torch.no_grad():
            dm = DMesh(resumed["points"], resumed["weights"], resumed["reals"], cfg.probability_config())
        opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(), cfg.train_phase1 if phase == 1 else ("reals",))
        if resumed.get("optimizer") is not None:
            opt.load_state_dict(resumed["optimizer"])
        chamfer.k = int(resumed["k"])
        rng.bit_generator.state = resumed["rng"]
        info["resumed_from"] = {"phase": phase, "step": start}
        log.info("resuming from phase %d step %d", phase, start)
    with_normals = cfg.lambda_normal > 0

    # ----------------------------------------------------------------------------------------- phase 1
    def phase1_step(step: int):
        stage_t: dict = {}
        fp = dm.face_probabilities(timings=stage_t)
        clock.add(stage_t, "phase1_")
        pd = fp.power_diagram
        hard = mesh_mask(dm.reals, pd.faces, cfg.threshold)
        if step in cfg.freeze_phase1:
            freeze_faces(opt, pd.faces[hard])
        with clock("phase1_sampling"):
            samples = sample_faces(dm.points, fp.faces, fp.prob_wdt, dm.reals, fp.prob, cfg.num_samples, rng,
                                   cfg.prob_threshold, with_normals=with_normals)
        with clock("phase1_chamfer"):
            loss, fig = chamfer(samples)
        with clock("phase1_regularizers"):
            loss = add_phase1_regularizers(loss, dm, fp, pd, cfg, step)
        return loss, {"cd_gt": fig["cd_gt"], "cd_ours": fig["cd_ours"], "k": fig["k"], "faces": int(hard.sum()),
                      "candidates": int(len(fp.faces)), "samples": len(samples)}

    if phase == 1:
        loop.stage("phase1")
        loop.run_phase(phase1_step, opt, cfg.steps_phase1, start, {"phase": 1}, "phase1_")
        phase, start = 2, 0
        opt = BoundedAdam(dm.points, dm.weights, dm.reals, cfg.step_config(), train=("reals",))
        loop.save({"phase": 2, "step": 0}, opt)

    # ----------------------------------------------------------------------------------------- phase 2
    loop.stage("phase2")
    with clock("phase2_wdt"):
        pd = dm.power_diagram()
        faces = torch.from_numpy(pd.faces.astype(np.int64))
        ones = torch.ones(len(faces), dtype=dm.points.dtype)

    def phase2_step(step: int):
        if step in cfg.freeze_phase2:
            freeze_faces(opt, pd.faces[mesh_mask(dm.reals, pd.faces, cfg.threshold)])
        with clock("phase2_sampling"):
            prob = dmin(dm.reals[faces].double(), cfg.alpha_real)
            samples = sample_faces(dm.points, faces, ones, dm.reals, prob, cfg.num_samples, rng,
                                   cfg.prob_threshold, with_normals=with_normals)
        with clock("phase2_chamfer"):
            loss, fig = chamfer(samples)
        with clock("phase2_regularizers"):
            if cfg.lambda_real_end > 0:
                loss = loss + cfg.lambda_real_end * real_regularizer(dm.reals, faces, ones, smooth=False)
        return loss, {"cd_gt": fig["cd_gt"], "cd_ours": fig["cd_ours"], "k": fig["k"],
                      "candidates": int(len(faces)), "samples": len(samples)}

    def phase2_faces(step: int) -> dict:  # the mesh after the update
        return {"faces": int(mesh_mask(dm.reals, pd.faces, cfg.threshold).sum())}

    loop.run_phase(phase2_step, opt, cfg.steps_phase2, start, {"phase": 2}, "phase2_", after_step=phase2_faces)
    loop.save({"phase": 3, "step": 0}, opt)

    # ------------------------------------------------------------------------------------- extraction
    loop.stage("extract")
    with clock("extract"):
        # With `orient`: the faces' closed, outward surface (dmesh.extract.surface); input normals, when
        # given, vote inside/outside and turn the open sheets.
        mesh = extract(dm, cfg.threshold, pd, cfg.extraction, orient=cfg.orient,
                       normals=None if nrm_in is None else (pts, nrm_in),
                       config=SurfaceConfig(seed=cfg.seed, workers=cfg.workers))
    if "surface" in mesh.metadata:
        info["surface"] = mesh.metadata.pop("surface")
    mesh.vertices = np.asarray(mesh.vertices) / scale + center
    info.update({"faces": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)),
                 "hidden_points": int(pd.hidden.sum()), "final_k": int(chamfer.k)})
    return PointCloudResult(mesh, dm, center, scale, loop.finish(), loop.history, info)


__all__ = ["PointCloudConfig", "PointCloudResult", "PRESETS", "reconstruct", "check_points", "extract",
           "orient_faces"]
