"""Settings of `dmesh.recon.multiview.reconstruct`: `MultiViewConfig`, its presets (`MULTIVIEW_PRESETS`) and what
each does differently from the paper (`MULTIVIEW_RECIPES`). Torch-free, like `dmesh.recon.config` (the shared parts
and the point-cloud settings), and apart from it so that a multi-view setting changes no point-cloud run's key
(a run's key hashes the sources its method imports, `eval.sweep.method_trees`).
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass, field
from typing import ClassVar

from dmesh.recon.config import KERNELS, MULTIVIEW_PRESETS, POINTCLOUD_PRESETS, Presets, as_tuple
from dmesh.surface.config import SurfaceConfig

INTERIOR_MODES = ("apex", "visible", "both", "sheet", "none")
INIT_MODES = ("grid", "depth")
#: The `refine` preset's phase-1 and phase-2 steps and its learning rate (= per-step bound).
REFINE_STEPS = (10, 5)
REFINE_LR = 1e-5


def multiview_surface() -> SurfaceConfig:
    """The surface step's settings from images: directions towards the cameras are not normals (on a sheet seen
    from both sides they point to either side patch by patch), so sheets turn whole; long faces stay as they are
    (spans are chosen and measured on point clouds only)."""
    return SurfaceConfig().with_overrides({"wind_sheets.turn_faces": False, "spans.ratio": 0.0})


def _tuple(value, n: int, name: str) -> tuple:
    """`value` (int or sequence) as a tuple of n ints (an int is repeated, one per epoch)."""
    if isinstance(value, numbers.Integral):
        return (int(value),) * n
    out = as_tuple(value, int, f"MultiViewConfig.{name}")
    if len(out) != n:
        raise ValueError(f"MultiViewConfig.{name} needs {n} entries (one per epoch), got {len(out)}")
    return out


@dataclass(frozen=True)
class MultiViewConfig(Presets):
    """Settings of `dmesh.recon.multiview.reconstruct` (defaults: the paper's, see `paper()`); lengths in the
    unit-radius frame."""

    PRESETS: ClassVar[tuple] = MULTIVIEW_PRESETS

    init: str = "grid"               # epoch 0 starts from a "grid" (upstream) or the "depth" pixels' DMesh
    init_points: int = 100_000       # "depth": lifted pixels given to the point-cloud reconstruction
    init_preset: str = "auto"        # "depth": its `PointCloudConfig` preset; "auto": "fast", after the pool
                                     # smoothing below when the lifted pixels look noisy
                                     # (dmesh.recon.init.DEPTH_NOISY_RATIO; "noisy" when init_pool_k is 0)
    init_pool_k: int = 500           # "auto" on noisy pixels: each of the init_points is first fitted from its
                                     # init_pool_k nearest of all the lifted pixels (not upstream;
                                     # dmesh.recon.views.smooth_from_pool); 0: off
    init_pooled_preset: str = "fast"  # ... then this point-cloud preset: "fast" (smooths again only points that
                                     # still look noisy or give a shredded mesh) or "noisy" (always smooths
                                     # again, 20K seeds); which when: python -m studies noisy_depth_start
    init_filters: bool = True        # "depth": the start's own input filters (the point-cloud preset's outlier
                                     # removal, noise-triggered smoothing and redo of a shredded mesh, and the
                                     # pooled smoothing above); False: none, the pixels as lifted ("auto" is
                                     # then "fast"; the harness's rows, where filtering is its own stage:
                                     # docs/preprocessing.md)
    grid: int = 20                   # epoch 0: grid^3 real points
    grid_extent: float = 1.25        # ... at the cell centres of [-grid_extent, grid_extent]^3
    refine_seeds: tuple = (1000, 3000, 10_000)  # seeds of epochs 1, 2, ... (one epoch each)
    voronoi_per_seed: float | None = None  # re-seeds keep <= this many Voronoi vertices per seed (None: all)
    reseed_phong: float = 0.0        # re-seeds sample the previous mesh's Phong-curved faces (0: flat, upstream)
    voronoi: str = "all"            # re-seeds' imaginary points: "all" Voronoi vertices or the seeds' "poles"
    domain: float = 1.0              # Voronoi vertices outside [-domain, domain]^3 are dropped
    box: float = 1.25                # points stay in [-b, b]^3, b = min(box, 0.98 x the cameras' box)
    steps_phase1: tuple = (500, 500, 500, 500)  # per epoch: steps with the soft renderer
    steps_phase2: tuple = (500, 500, 500, 500)  # per epoch: steps with the tetrahedral renderer
    lr_first: float = 1e-3           # epoch 0 learning rate (positions, weights; reals: / max_real)
    bound_first: float = 1e-3        # epoch 0 per-step bound of each coordinate
    lr: float = 3e-4                 # later epochs' learning rate
    update_bound: float = 3e-4       # later epochs' per-step bound
    max_real_first: float = 3e-3     # epoch 0: upstream's real-value scale (reals' lr and bound: lr / it)
    max_real: float = 3e-3           # later epochs' real-value scale
    views_per_step: int = 16         # random views rendered per step (upstream batch size)
    resolution: int | None = None    # images are area-averaged to this side (None: the capture's)
    lambda_depth: float = 1.0        # weight of the depth channel's L1 (diffuse 1); see `depth_channel`
    lambda_weight: float = 1e-8      # weight regulariser (power-diagram edge lengths)
    lambda_real_start: float = 1e-2  # real regulariser coefficient at phase-1 step 0 of each epoch
    lambda_real_end: float = 1e-3    # ... after `real_ramp_steps`, and in phase 2
    real_ramp_steps: int = 100       # phase-1 steps of the linear ramp
    lambda_quality: float = 1e-3     # quality regulariser (aspect ratio x max edge x Lambda)
    freeze_phase2: tuple = (0, 250)  # phase-2 steps at which points on the mesh are frozen real
    alpha_thresh: float = 1e-3       # faces with Lambda_wdt x max(r) at or below it are not drawn
    edge_width: float = 1.0          # soft renderer: width of the soft band outside each triangle (pixels)
    band_targets: bool = True        # phase-1 targets get the soft renderer's silhouette band (unbiased fit)
    alpha_wdt: float = 1000.0        # sigmoid sharpness of Lambda_wdt
    alpha_real: float = 100.0        # softmin sharpness of Lambda_real
    knn_interval: int = 10           # kNN candidate triples every this many steps
    knn_k: int = 8                   # neighbours of the kNN candidate triples
    active_band: float | None = 15.0  # candidates with Delta below -band/alpha get no gradient
    threshold: float = 0.5           # real value above which a point is on the final mesh
    interior: str = "apex"           # interior-face removal: one of INTERIOR_MODES
    select_best: bool = False        # return the epoch whose mesh renders closest to all the images (with
                                     # init="depth", the start too: info["selected_epoch"] -1)
    depth_tolerance: float | None = None  # keep only faces within this of the captured depth in some view
    depth_fit: bool = False          # last, the mesh's vertices fitted to the depth maps (not upstream;
                                     # dmesh.recon.depth_fit)
    orient: bool = True              # output the faces' oriented, closed surface (the surface step, dmesh.surface)
    surface: SurfaceConfig = field(default_factory=multiview_surface)  # its settings (seed: the run's)
    save_every: int = 50             # steps between resumable state saves (with a state path)
    kernels: str = "native"          # Delta recomputation: "native" (C++) or "reference" (torch, for checks)
    seed: int = 0                    # seed of every random choice

    def __post_init__(self):
        seeds = as_tuple(self.refine_seeds, int, "MultiViewConfig.refine_seeds")
        object.__setattr__(self, "refine_seeds", seeds)
        n = 1 + len(seeds)
        object.__setattr__(self, "steps_phase1", _tuple(self.steps_phase1, n, "steps_phase1"))
        object.__setattr__(self, "steps_phase2", _tuple(self.steps_phase2, n, "steps_phase2"))
        object.__setattr__(self, "freeze_phase2",
                           as_tuple(self.freeze_phase2, int, f"{type(self).__name__}.freeze_phase2"))
        if int(self.grid) < 2:
            raise ValueError(f"MultiViewConfig.grid must be >= 2, got {self.grid}")
        if any(s < 4 for s in seeds):
            raise ValueError(f"MultiViewConfig.refine_seeds must all be >= 4, got {seeds}")
        if any(s < 0 for s in self.steps_phase1 + self.steps_phase2):
            raise ValueError("MultiViewConfig.steps_phase1 / steps_phase2 must be >= 0")
        for name in ("views_per_step", "knn_k"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"MultiViewConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("real_ramp_steps", "knn_interval", "save_every"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"MultiViewConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("grid_extent", "domain", "box", "lr_first", "bound_first", "lr", "update_bound",
                     "max_real_first", "max_real", "edge_width", "alpha_wdt", "alpha_real"):
            if not getattr(self, name) > 0:
                raise ValueError(f"MultiViewConfig.{name} must be positive, got {getattr(self, name)}")
        for name in ("lambda_depth", "lambda_weight", "lambda_real_start", "lambda_real_end",
                     "lambda_quality", "alpha_thresh"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"MultiViewConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.voronoi_per_seed is not None and not self.voronoi_per_seed >= 0:
            raise ValueError(f"MultiViewConfig.voronoi_per_seed must be >= 0 or None, got {self.voronoi_per_seed}")
        if self.resolution is not None and int(self.resolution) < 4:
            raise ValueError(f"MultiViewConfig.resolution must be >= 4 or None, got {self.resolution}")
        if self.depth_tolerance is not None and not self.depth_tolerance > 0:
            raise ValueError(f"MultiViewConfig.depth_tolerance must be positive or None, got {self.depth_tolerance}")
        if not 0.0 <= self.reseed_phong <= 1.0:
            raise ValueError(f"MultiViewConfig.reseed_phong must be in [0, 1], got {self.reseed_phong}")
        if self.voronoi not in ("all", "poles"):
            raise ValueError(f"MultiViewConfig.voronoi must be 'all' or 'poles', got {self.voronoi!r}")
        if self.init not in INIT_MODES:
            raise ValueError(f"MultiViewConfig.init must be one of {INIT_MODES}, got {self.init!r}")
        if int(self.init_points) < 10:
            raise ValueError(f"MultiViewConfig.init_points must be >= 10, got {self.init_points}")
        if self.init_pooled_preset not in ("fast", "noisy"):
            raise ValueError(f"MultiViewConfig.init_pooled_preset must be 'fast' or 'noisy', got "
                             f"{self.init_pooled_preset!r}")
        if int(self.init_pool_k) != 0 and int(self.init_pool_k) < 6:
            raise ValueError(f"MultiViewConfig.init_pool_k must be 0 (off) or >= 6 (a quadratic jet has 6 "
                             f"coefficients), got {self.init_pool_k}")
        if self.init_preset not in ("auto",) + POINTCLOUD_PRESETS:
            raise ValueError(f"MultiViewConfig.init_preset must be one of {('auto',) + POINTCLOUD_PRESETS}, "
                             f"got {self.init_preset!r}")
        if not self.init_filters and self.init_preset == "noisy":
            raise ValueError("MultiViewConfig.init_preset 'noisy' smooths the lifted pixels, which init_filters "
                             "False leaves as they are; take 'fast' (or 'auto'), or init_filters True")
        if self.interior not in INTERIOR_MODES:
            raise ValueError(f"MultiViewConfig.interior must be one of {INTERIOR_MODES}, got {self.interior!r}")
        if not 0.0 <= self.threshold < 1.0:
            raise ValueError(f"MultiViewConfig.threshold must be in [0, 1), got {self.threshold}")
        if self.kernels not in KERNELS:
            raise ValueError(f"MultiViewConfig.kernels must be one of {', '.join(KERNELS)}, got {self.kernels!r}")
        self.run_surface(multiview_surface)

    @property
    def epochs(self) -> int:
        return 1 + len(self.refine_seeds)

    @classmethod
    def paper(cls, **overrides) -> "MultiViewConfig":
        """The published settings (appendix 10.2; upstream exp_3 thingi/objaverse configs): 4 epochs of
        500 + 500 steps, 16 views per step at the capture's resolution, real regulariser 1e-2 -> 1e-3 over
        100 steps (the paper's "1e-2 closed / 1e-3 open" for the first 100 steps; upstream's plant config),
        diffuse and depth L1 with weight 1 each (upstream's depth is 1 - (ndc_z + 1) / 2 with near 1 and
        far 3: slope 1.5 / z^2 ~ 0.4 per unit at the object centre; our depth channel's slope is 0.5, see
        `depth_channel`). Interior faces: upstream's rule ("apex")."""
        return cls(**overrides)

    @classmethod
    def fast(cls, **overrides) -> "MultiViewConfig":
        """The paper's procedure at a CPU budget: a 14^3 grid at lr 2e-3, re-seeds of 1000 and 3000 samples of
        the previous mesh's Phong-curved faces with all their Voronoi vertices, 150 + 20 steps per epoch of 6
        views optimised at 128 pixels, the "both" interior rule, the depth-consistency filter, `select_best` and
        the final fit of the vertices to the depth maps (`depth_fit`). Why each choice:
        docs/preset_choices_multiview.md; accuracy and time: reports/multiview_fast.md."""
        base = dict(grid=14, refine_seeds=(1000, 3000), steps_phase1=(150, 150, 150), steps_phase2=(20, 20, 20),
                    lr_first=2e-3, bound_first=2e-3, max_real_first=6e-3, views_per_step=6, resolution=128,
                    reseed_phong=0.75,
                    lambda_weight=0.0, real_ramp_steps=10, freeze_phase2=(0,), interior="both", select_best=True,
                    depth_tolerance=0.02, depth_fit=True, save_every=10)
        return cls(**{**base, **overrides})

    @classmethod
    def depth(cls, **overrides) -> "MultiViewConfig":
        """Depth pixels first (not upstream): epoch 0 is DMesh's point-cloud fit to 100K lifted depth pixels
        (`depth_init`, point-cloud `fast` preset; noisy pixels are first smoothed from all the pixels), then the
        multi-view extraction (the point-cloud extraction's one-sheet interior rule, which leaves open parts one
        sheet rather than the overlapping layers of thin tets the apex and visibility rules keep; the
        depth-consistency filter). No image-loss step
        (docs/preset_choices_depth.md)."""
        base = dict(init="depth", refine_seeds=(), steps_phase1=(0,), steps_phase2=(0,), interior="sheet",
                    depth_tolerance=0.02, select_best=False, save_every=10)
        return cls(**{**base, **overrides})

    @classmethod
    def refine(cls, **overrides) -> "MultiViewConfig":
        """The `depth` start followed by image-loss steps (not upstream): phase-1 steps with the soft renderer at
        a small learning rate (the start's points are about 0.01 apart), then phase-2 steps on the reals, and
        `select_best` with the start as a candidate, so the result is never a mesh that renders farther from
        the images than the start. For depth maps with noise, where the diffuse images carry the shape's
        normals. Its measurements: `reports/table2_multiview.md` and `python -m studies refine`."""
        base = dict(init="depth", refine_seeds=(), steps_phase1=(REFINE_STEPS[0],), steps_phase2=(REFINE_STEPS[1],),
                    lr_first=REFINE_LR, bound_first=REFINE_LR, max_real_first=3e-3, views_per_step=6,
                    resolution=None, lambda_weight=0.0, lambda_real_start=1e-3, real_ramp_steps=0,
                    freeze_phase2=(0,), interior="sheet", depth_tolerance=0.02, select_best=True, save_every=10)
        return cls(**{**base, **overrides})

    @classmethod
    def tiny(cls, **overrides) -> "MultiViewConfig":
        """Seconds, for tests: the fast preset's recipe on an 8^3 grid and one re-seed of 300 points (600
        Voronoi vertices), 30 + 10 and 15 + 10 steps at 48 pixels, depth tolerance 0.1 (about two pixels)."""
        base = dict(grid=8, refine_seeds=(300,), voronoi_per_seed=2.0, steps_phase1=(30, 15), steps_phase2=(10, 10),
                    lr_first=2e-3, bound_first=2e-3, max_real_first=6e-3, views_per_step=4, resolution=48,
                    lambda_weight=0.0, real_ramp_steps=4, freeze_phase2=(0,), interior="both", select_best=True,
                    depth_tolerance=0.1, save_every=10)
        return cls(**{**base, **overrides})

    def step_config(self, epoch: int):
        """The `dmesh.recon.optim.StepConfig` of `epoch`."""
        from dmesh.recon.optim import StepConfig

        if epoch == 0:
            return StepConfig(lr=self.lr_first, update_bound=self.bound_first, max_real=self.max_real_first)
        return StepConfig(lr=self.lr, update_bound=self.update_bound, max_real=self.max_real)

    def total_steps(self) -> int:
        return sum(self.steps_phase1) + sum(self.steps_phase2)


#: Per preset: (whether it takes image-loss gradient steps, how it differs from the paper). Reports print
#: these beside every DMesh row.
MULTIVIEW_RECIPES = {
    "paper": (True, "the published recipe: a 20^3 grid, then re-seeds of 1K, 3K and 10K surface samples, 500 "
                    "soft-renderer + 500 tetrahedral-renderer steps per epoch, 16 views per step at the capture's "
                    "resolution, L1 of diffuse + depth. Differs: silhouette gradients come from the soft "
                    "renderer's analytic coverage (upstream: a 0.1 x hard-render term), depth channel slope 0.5, "
                    "16 views per step for every class (the paper: 64 for open shapes; `views_per_step=64` "
                    "gives it at 4x the rendering time)."),
    "fast": (True, "the paper's procedure cut to a CPU budget: a 14^3 grid at lr 2e-3, re-seeds of 1K and 3K "
                   "samples (on the previous mesh's Phong-curved faces, not upstream), 150 + 20 steps per epoch, "
                   "6 views per step at 128 pixels; interior faces removed by apex and visibility, faces off the "
                   "captured depth dropped, the epoch whose mesh renders closest to the images kept, then its "
                   "vertices moved along their normals by a least-squares fit to the depth maps (not upstream)."),
    "depth": (False, "an initialisation, not in the paper: DMesh's point-cloud fit (its `fast` preset) to 100K "
                     "lifted depth pixels, each first fitted from its 500 nearest of all the pixels when they "
                     "look noisy, then the one-sheet interior rule and the depth filter; no image-loss step."),
    "refine": (True, "not in the paper: the `depth` start, then 10 soft-renderer steps at lr 1e-5 and 5 "
                     "tetrahedral-renderer steps (6 views per step), keeping the start when the steps do not "
                     "lower the image loss over all views."),
    "tiny": (True, "tests only: an 8^3 grid and one re-seed of 300 samples at 48 pixels."),
}
