"""Settings of the reconstructions: frozen configs with one comment per field, their presets, and what each
preset does differently from the paper (its recipe). Torch-free, so the command line lists the preset names
without importing the library's kernels; `Presets.from_preset` is the one way from a preset name and overrides to a
config (unknown keys raise ValueError naming the known ones).

- `PointCloudConfig` (`dmesh.recon.pointcloud.reconstruct`): presets `POINTCLOUD_PRESETS`.
- `MultiViewConfig` (`dmesh.recon.multiview.reconstruct`): presets `MULTIVIEW_PRESETS`, in
  `dmesh.recon.multiview_config` (its own module, so a multi-view setting changes no point-cloud run's key).

Both hold the surface step's settings in their field `surface` (a `dmesh.surface.SurfaceConfig`); an override
key `surface.SECTION.FIELD` (or a `surface` mapping of them) sets one of its fields, e.g. `--set
surface.lids.max_hole=100`. The run's seed (and point-cloud workers) are the surface step's too.
"""
from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass, field, fields
from typing import Callable, ClassVar, Mapping

from dmesh.surface.config import SurfaceConfig

#: Implementations of the step's kernels (the expected Chamfer and the Delta recomputation).
KERNELS = ("native", "reference")
#: What phase-1 steps may move.
TRAIN_ALL = ("points", "weights", "reals")
#: The default preset of both reconstructions.
DEFAULT_PRESET = "fast"
POINTCLOUD_PRESETS = ("paper", "fast", "noisy", "compact", "compact_steps", "tiny")
#: Neighbours of the input smoothing of the `noisy` preset, and of `fast`'s when its input looks noisy.
NOISY_SMOOTH_K = 120
#: Real seeds of the `fast` preset: every point of a cloud up to this size (a random subset of a larger one);
#: why: docs/preset_choices.md.
FAST_SEEDS = 100_000
#: Most real seeds of the `fast` and `noisy` presets when they smooth their input; why: docs/preset_choices.md.
SMOOTHED_SEEDS = 20_000
#: Boundary edges per face above which `fast` takes its unsmoothed output for a sign of missed noise ...
FRAGMENTED_BOUNDARY = 0.1
#: Walls up to this many seed spacings thick are separated by mid-surface points in the `fast` presets
#: (`thin_walls`): the reach of a 16-neighbour neighbourhood (docs/preset_choices.md, "Thin walls").
THIN_WALLS = 3.0
#: ... when there are also more than this many times the square root of its face count. Shreds have boundary in
#: proportion to their faces; an intact surface's rim grows with the square root of the face count, so a small
#: intact mesh of a shape with much rim has over 0.1 boundary edges per face. Why: docs/preset_choices.md.
FRAGMENTED_RIM = 20.0
#: The default face budget of the `compact` and `compact_steps` presets.
COMPACT_FACES = 5000
#: The `compact_steps` preset's real seeds per face of the budget: the seeds are chosen so that the optimised mesh
#: has a few more faces than the budget, which the budget stage then removes (quadric edge collapse).
COMPACT_SEEDS_PER_FACE = 1.0
#: Phase-1 steps of the `compact_steps` preset.
COMPACT_STEPS = 200
MULTIVIEW_PRESETS = ("paper", "fast", "depth", "refine", "tiny")


def as_tuple(value, cast, name: str) -> tuple:
    """A tuple field's value as a tuple of `cast` values: a single number becomes a 1-tuple (so `--set
    freeze_phase2=5` and `freeze_phase2: [5]` mean the same); ValueError naming the field for text or
    anything that is not a number or a sequence of numbers."""
    if isinstance(value, numbers.Number) and not isinstance(value, bool):
        value = (value,)
    if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
        raise ValueError(f"{name} expects a number or a list of numbers like [1, 2], got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, numbers.Number):
            raise ValueError(f"{name} expects a number or a list of numbers like [1, 2], got {value!r}")
        if cast is int and float(v) != int(v):
            raise ValueError(f"{name} expects integers, got {v!r}")
        out.append(cast(v))
    return tuple(out)


class Presets:
    """Mixin of the config classes: `from_preset`, the one way from a preset name and overrides to a config
    (the CLI, the harness methods and the sweeps all use it), `preset` (the class lists its `PRESETS`, each a
    classmethod), and the `ProbabilityConfig` the settings imply."""

    @classmethod
    def from_preset(cls, preset: str | None = None, overrides: Mapping | None = None, *, owner: str = ""):
        """`cls.preset(preset, **overrides)` (default preset `DEFAULT_PRESET`).

        Raises:
            ValueError: an unknown preset, or override keys that are not fields of the class (the message names
                the known ones; `owner` prefixes it, e.g. a harness method's name).
        """
        overrides = dict(overrides or {})
        known = {f.name for f in fields(cls)}
        dotted = {k: overrides.pop(k) for k in list(overrides) if str(k).startswith("surface.")}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"{owner + ': ' if owner else ''}unknown config keys {unknown}; known: {sorted(known)} "
                             f"(and surface.SECTION.FIELD)")
        cfg = cls.preset(str(preset or DEFAULT_PRESET), **overrides)
        if not dotted:
            return cfg
        settings = {k.split(".", 1)[1]: v for k, v in dotted.items()}
        clash = sorted(set(settings) & {"seed", "workers"})
        if clash:
            raise ValueError(f"{owner + ': ' if owner else ''}surface.{clash[0]}: the surface step takes the run's "
                             f"{clash[0]}; set {clash[0]} instead")
        try:
            return dataclasses.replace(cfg, surface=cfg.surface.with_overrides(settings))
        except ValueError as exc:
            raise ValueError(f"{owner + ': ' if owner else ''}{exc}") from None

    @classmethod
    def preset(cls, name: str, **overrides):
        """The config of preset `name` (one of the class's `PRESETS`) with field `overrides`."""
        if name not in cls.PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {', '.join(cls.PRESETS)}")
        return getattr(cls, name)(**overrides)

    def run_surface(self, default: Callable[[], SurfaceConfig], workers: int | None = None) -> None:
        """`__post_init__`'s part for the `surface` field: a mapping of overrides (as `SurfaceConfig.with_overrides`
        takes) applies to `default()`; the run's seed, and `workers` when given, replace the surface step's."""
        surface, name = self.surface, type(self).__name__
        if isinstance(surface, Mapping):
            given = {k: surface[k] for k in ("seed", "workers") if k in surface}
            run = {"seed": self.seed, "workers": workers}
            if any(run[k] is not None and v != run[k] for k, v in given.items()):
                raise ValueError(f"{name}.surface: the surface step takes the run's seed and workers; set those "
                                 f"instead of {sorted(given)}")
            surface = default().with_overrides(surface)
        elif not isinstance(surface, SurfaceConfig):
            raise TypeError(f"{name}.surface must be a SurfaceConfig or a mapping of its settings, got "
                            f"{type(surface).__name__}")
        run = {"seed": int(self.seed)} if workers is None else {"seed": int(self.seed), "workers": int(workers)}
        object.__setattr__(self, "surface", dataclasses.replace(surface, **run))

    def probability_config(self):
        """The `dmesh.probability.ProbabilityConfig` of these settings."""
        from dmesh.probability import ProbabilityConfig

        extra = {"knn_thresholds": self.knn_thresholds} if hasattr(self, "knn_thresholds") else {}
        return ProbabilityConfig(alpha_wdt=self.alpha_wdt, alpha_real=self.alpha_real, knn_interval=self.knn_interval,
                                 knn_k=self.knn_k, active_band=self.active_band, impl=self.kernels, **extra)


# ------------------------------------------------------------------------------------------- point clouds

@dataclass(frozen=True)
class PointCloudConfig(Presets):
    """Settings of `dmesh.recon.pointcloud.reconstruct` (defaults: the paper's, see `paper()`); lengths in the
    unit-radius frame."""

    PRESETS: ClassVar[tuple] = POINTCLOUD_PRESETS

    outlier_std: float = 0.0        # > 0: input points whose mean distance to their 16 nearest neighbours exceeds
                                    # the mean by this many standard deviations are dropped first, unless they lie
                                    # on the surface of their neighbours (not upstream;
                                    # dmesh.recon.init.statistical_inliers); 0: off
    smooth_k: int = 0               # > 0: then every input point is moved onto the quadratic jet fitted to its
                                    # smooth_k nearest neighbours (not upstream; dmesh.recon.init.smooth_points,
                                    # CGAL's jet smoothing): denoising for noisy scans; 0: off
    auto_smooth_k: int = 0          # > 0 and smooth_k 0: smooth with this many neighbours only when the input
                                    # looks noisy (noise_ratio above dmesh.recon.init.NOISY_RATIO); 0: off
    num_init: int = 10_000          # input points used as real seeds
    smoothed_seeds: int = 0         # > 0: at most this many seeds when the input was smoothed (not upstream):
                                    # smoothed points still lie about a seed spacing off the surface at dense
                                    # seeding, and the mesh falls apart; 0: num_init always
    redo_fragmented: float = 0.0    # > 0 with auto_smooth_k: an unsmoothed run whose mesh has more boundary edges
                                    # than this many per face (and than FRAGMENTED_RIM x sqrt(faces)) is run
                                    # again smoothed (not upstream: noise that noise_ratio missed shreds the
                                    # mesh); 0: off
    max_voronoi: int | None = None  # keep at most this many Voronoi vertices (None: all inside the domain)
    voronoi: str = "all"            # imaginary points: "all" Voronoi vertices (upstream) or the seeds' "poles"
    thin_walls: float = 0.0         # > 0 with input normals: walls up to this many seed spacings thick get
                                    # imaginary points on their mid-surface instead of poles (not upstream;
                                    # dmesh.recon.init.separate_thin_walls); 0: off
    carve: float = 0.0              # > 0: imaginary points on first-mesh faces this many seed spacings from
                                    # the input (dmesh.recon.init.carve_far_faces); 0: off (upstream)
    domain: float = 1.0             # Voronoi vertices outside [-domain, domain]^3 are dropped
    num_target: int = 100_000       # input points used as the Chamfer target (random subset)
    num_samples: int = 100_000      # points sampled on the DMesh per step (two strata of half each)
    steps_phase1: int = 1000        # steps optimising positions, weights and reals
    steps_phase2: int = 500         # steps optimising reals on the frozen tessellation
    phase2_patience: int = 50       # > 0: phase 2 ends once the mesh (faces whose three reals exceed `threshold`)
                                    # has not changed for this many steps (not upstream); 0: all steps_phase2
    lr: float = 3e-4                # Adam learning rate (positions, weights; reals: lr / max_real)
    update_bound: float = 3e-4      # per-step bound of each coordinate (reals: update_bound / max_real)
    max_real: float = 3e-3          # upstream's real-value scale (sets the reals' lr and bound)
    grad_clip: float | None = None  # per-point gradient norm clip (None: update_bound / lr)
    k_max: int = 100                # largest (and first) K of the target -> ours term
    mass_tol: float = 1e-4          # residual probability mass that makes K grow
    k_first: int = 16               # samples every target row takes first; only rows keeping more than
                                    # `mass_tol` beyond them are searched to K (not upstream); 0: all rows to K
    prob_threshold: float = 1e-3    # faces below this stratum factor are never sampled
    lambda_weight: float = 1e-8     # weight regulariser (power-diagram edge lengths)
    lambda_real_start: float = 1e-3  # real regulariser coefficient at phase-1 step 0
    lambda_real_end: float = 1e-3   # ... after `real_ramp_steps`, and in phase 2
    real_ramp_steps: int = 100      # phase-1 steps of the linear ramp of the real coefficient
    lambda_quality: float = 1e-3    # quality regulariser (aspect ratio x max edge x Lambda)
    lambda_normal: float = 0.0      # normal term of Eq. 13 (needs input normals)
    tangent_weight: float = 1.0     # Chamfer offsets' tangential part scaled by this (needs normals; 1: upstream)
    train_phase1: tuple = ("points", "weights", "reals")  # what phase-1 steps move (upstream: all three)
    freeze_phase2: tuple = (0, 250)  # phase-2 steps at which points on the mesh are frozen real
    alpha_wdt: float = 1000.0       # sigmoid sharpness of Lambda_wdt
    alpha_real: float = 100.0       # softmin sharpness of Lambda_real
    knn_interval: int = 10          # kNN candidate triples every this many steps
    knn_k: int = 8                  # neighbours of the kNN candidate triples
    knn_thresholds: tuple = (0.0, 0.2, 0.4, 0.6, 0.8)  # real-value thresholds of the kNN passes
    active_band: float | None = 15.0  # candidates with Delta below -band/alpha get no gradient
    coverage: bool = False          # True: a target row's probability mass beyond its K nearest samples is charged at
                                    # the farthest one's distance (not upstream: the paper's loss drops it, so it
                                    # falls as the surface fades; dmesh.reference.chamfer.miss_term)
    collapse_share: float = 0.0     # > 0: phase 1 stops once its mesh has fewer faces than this share of the mesh
                                    # at its first step (not upstream); 0: off
    best_every: int = 0             # > 0: every this many phase-1 steps (and after the last) the current mesh is
                                    # scored against the input, without the GT (`input_chamfer`), and phase 2
                                    # starts from the best state scored (not upstream); 0: the last state
    faces: int = 0                  # > 0: a face budget (not upstream): a mesh with more faces is reduced to this
                                    # many by quadric edge collapse (dmesh.recon.budget); 0: none
    threshold: float = 0.5          # real value above which a point is on the final mesh
    extraction: str = "sheet"       # which real faces make the mesh: "all", "no_interior", "sheet" (dmesh.extract)
    orient: bool = True             # output the faces' oriented, closed surface (the surface step, dmesh.surface)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)  # its settings (seed, workers: the run's)
    save_every: int = 50            # steps between resumable state saves (with a state path)
    workers: int = 2                # threads of the k-d tree queries (at most torch.get_num_threads())
    kernels: str = "native"         # "native" (C++ expected Chamfer and Delta) or "reference" (torch, for checks)
    seed: int = 0                   # seed of every random choice

    def __post_init__(self):
        if int(self.smoothed_seeds) < 0:
            raise ValueError(f"PointCloudConfig.smoothed_seeds must be >= 0 (0: off), got {self.smoothed_seeds}")
        ints = ("num_init", "num_target", "num_samples", "k_max", "knn_k")
        for name in ints:
            if int(getattr(self, name)) < 1:
                raise ValueError(f"PointCloudConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("smooth_k", "auto_smooth_k"):
            if int(getattr(self, name)) != 0 and not 6 <= int(getattr(self, name)) <= 1000:
                raise ValueError(f"PointCloudConfig.{name} must be 0 (off) or in [6, 1000] (a quadratic jet has 6 "
                                 f"coefficients), got {getattr(self, name)}")
        for name in ("steps_phase1", "steps_phase2", "phase2_patience", "real_ramp_steps", "knn_interval",
                     "save_every", "k_first", "best_every", "faces"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"PointCloudConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("lr", "update_bound", "max_real", "domain", "alpha_wdt", "alpha_real"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PointCloudConfig.{name} must be positive, got {getattr(self, name)}")
        if not 0.0 <= self.collapse_share < 1.0:
            raise ValueError(f"PointCloudConfig.collapse_share must be in [0, 1) (0: off), got {self.collapse_share}")
        if 0 < int(self.faces) < 4:
            raise ValueError(f"PointCloudConfig.faces must be 0 (no budget) or at least 4, got {self.faces}")
        for name in ("outlier_std", "redo_fragmented", "carve", "thin_walls", "lambda_weight", "lambda_real_start",
                     "lambda_real_end", "lambda_quality", "lambda_normal", "prob_threshold", "mass_tol"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"PointCloudConfig.{name} must be >= 0, got {getattr(self, name)}")
        from dmesh.extract import MODES

        if self.extraction not in MODES:
            raise ValueError(f"PointCloudConfig.extraction must be one of {', '.join(MODES)}, got {self.extraction!r}")
        if self.voronoi not in ("all", "poles"):
            raise ValueError(f"PointCloudConfig.voronoi must be 'all' or 'poles', got {self.voronoi!r}")
        if not 0.0 <= self.threshold < 1.0:
            raise ValueError(f"PointCloudConfig.threshold must be in [0, 1), got {self.threshold}")
        if self.kernels not in KERNELS:
            raise ValueError(f"PointCloudConfig.kernels must be one of {', '.join(KERNELS)}, got {self.kernels!r}")
        object.__setattr__(self, "knn_thresholds",
                           as_tuple(self.knn_thresholds, float, "PointCloudConfig.knn_thresholds"))
        train = (self.train_phase1,) if isinstance(self.train_phase1, str) else tuple(self.train_phase1)
        if not train or set(train) - set(TRAIN_ALL):
            raise ValueError(f"PointCloudConfig.train_phase1 must name some of {', '.join(TRAIN_ALL)}, got {train}")
        object.__setattr__(self, "train_phase1", train)
        object.__setattr__(self, "freeze_phase2",
                           as_tuple(self.freeze_phase2, int, f"{type(self).__name__}.freeze_phase2"))
        self.run_surface(SurfaceConfig, self.workers)

    @classmethod
    def paper(cls, **overrides) -> "PointCloudConfig":
        """The published settings (appendix 10.2; upstream exp_2 configs with lr 3e-4)."""
        return cls(**overrides)

    @classmethod
    def fast(cls, **overrides) -> "PointCloudConfig":
        """A CPU budget, about a minute per shape on 2 cores: stray input points dropped (`outlier_std` 2, a
        statistical test that keeps sparse stretches of surface), up to 100K seeds (every input point of a
        Table 2 cloud) and their poles (`dmesh.recon.init`) instead of 10K seeds and all their Voronoi
        vertices, faces far from the input
        carved (`carve_far_faces`, for holes and open borders), no gradient step (at this density the
        steps cost accuracy), one-sheet extraction (`dmesh.extract`). An input that looks noisy
        (`noise_ratio` above `NOISY_RATIO`) is smoothed first as `noisy` smooths it (`auto_smooth_k`), and then
        gives at most 20K seeds (`smoothed_seeds`); clean input is not smoothed. An unsmoothed run whose mesh
        comes out in shreds (more than `FRAGMENTED_BOUNDARY` boundary edges per face and `FRAGMENTED_RIM` times
        the square root of its face count, noise that `noise_ratio` missed) is run again smoothed
        (`redo_fragmented`). Why each choice: docs/preset_choices.md; why no
        phase-1 step: `python -m studies recipes`."""
        base = dict(outlier_std=2.0, auto_smooth_k=NOISY_SMOOTH_K, num_init=FAST_SEEDS, voronoi="poles",
                    smoothed_seeds=SMOOTHED_SEEDS, redo_fragmented=FRAGMENTED_BOUNDARY,
                    carve=5.0, max_voronoi=None, thin_walls=THIN_WALLS,
                    num_target=50_000, num_samples=50_000, steps_phase1=0, steps_phase2=0, k_max=16,
                    lambda_weight=0.0, real_ramp_steps=0, freeze_phase2=(0, 5), save_every=10)
        return cls(**{**base, **overrides})

    @classmethod
    def noisy(cls, **overrides) -> "PointCloudConfig":
        """For noisy scans (not upstream): the `fast` preset with its input always smoothed. After `fast`'s
        outlier filter every point moves onto the quadratic jet fitted to its 120 nearest neighbours
        (`smooth_k`, CGAL's jet smoothing), which takes most of the noise off the surface normal. On clean
        input the smoothing rounds curved parts and costs accuracy, so `fast` smooths only input that looks
        noisy; this preset is for noise that `fast`'s measurement misses. Like `fast` on smoothed input, at
        most 20K seeds (`smoothed_seeds`). Measurements: `reports/robustness.md`
        (the robustness sweep); the choice of k: docs/preset_choices.md."""
        return cls.fast(**{**dict(smooth_k=NOISY_SMOOTH_K, auto_smooth_k=0), **overrides})

    @classmethod
    def compact(cls, **overrides) -> "PointCloudConfig":
        """A mesh of `faces` faces (default 5000), for users who need a light mesh (not upstream): the `fast`
        preset (no gradient step), then the budget stage reduces its mesh to `faces` by quadric edge collapse
        (`dmesh.recon.budget`), as the classical reconstruct-then-decimate rows do. Chosen on the dev split over
        `compact_steps`: why and the figures, docs/presets.md, "compact" (reports/compact.md)."""
        faces = int(overrides.pop("faces", COMPACT_FACES))
        if faces < 4:
            raise ValueError(f"PointCloudConfig.faces must be at least 4 for the compact preset, got {faces}")
        return cls.fast(**{"faces": faces, **overrides})

    @classmethod
    def compact_steps(cls, **overrides) -> "PointCloudConfig":
        """A mesh of `faces` faces (default 5000) made by gradient steps (not upstream): the `fast` preset's start
        at `COMPACT_SEEDS_PER_FACE` real seeds per face of the budget, then `COMPACT_STEPS` phase-1 steps on the
        loss with the tangential part of the Chamfer offsets scaled by 0.2 (`tangent_weight`, a lower sampling
        floor) and the mass beyond each target row's candidates charged (`coverage`), the best state kept by its
        Chamfer distance to the input (`best_every` 10), the phase stopped if its mesh falls below a quarter of
        its first faces (`collapse_share`); then the surface step, and the budget stage reduces the mesh to
        `faces` by quadric edge collapse. `compact` was chosen over it on the dev split; it stays for that
        comparison (docs/presets.md, reports/compact.md)."""
        faces = int(overrides.get("faces", COMPACT_FACES))
        if faces < 4:
            raise ValueError(f"PointCloudConfig.faces must be at least 4 for the compact_steps preset, got {faces}")
        base = dict(faces=faces, num_init=max(int(round(faces * COMPACT_SEEDS_PER_FACE)), 10),
                    steps_phase1=COMPACT_STEPS, tangent_weight=0.2, coverage=True, best_every=10,
                    collapse_share=0.25)
        return cls.fast(**{**base, **overrides})

    @classmethod
    def tiny(cls, **overrides) -> "PointCloudConfig":
        """Seconds, for tests and the CLI smoke run: 1000 seeds and their poles (~2.5K points), 2 + 15 steps
        at a tenth of the paper's lr, 4K target points and samples."""
        base = dict(num_init=1000, voronoi="poles", carve=5.0, max_voronoi=None, num_target=4000,
                    num_samples=4000, steps_phase1=2, steps_phase2=15, lr=3e-5, update_bound=3e-5, k_max=12,
                    lambda_weight=0.0, real_ramp_steps=2, freeze_phase2=(0, 8), knn_interval=5, save_every=10)
        return cls(**{**base, **overrides})

    def step_config(self):
        """The `dmesh.recon.optim.StepConfig` of these settings."""
        from dmesh.recon.optim import StepConfig

        return StepConfig(lr=self.lr, update_bound=self.update_bound, max_real=self.max_real,
                          grad_clip=self.grad_clip)


#: Per preset: (whether it takes gradient steps on positions and weights, how it differs from the paper).
#: Reports print these beside every DMesh row.
POINTCLOUD_RECIPES = {
    "paper": (True, "the published recipe: 10K seeds + all their Voronoi vertices, 1000 phase-1 steps (positions, "
                    "weights, reals) + 500 phase-2 steps (reals), lr 3e-4, 100K target points and samples, K <= 100. "
                    "Differs: the 8 corners of [-1.25, 1.25]^3 are added as imaginary points, a target row of the "
                    "expected Chamfer term stops at its 16 nearest samples when at most 1e-4 of probability lies "
                    "beyond them (upstream, and `k_first=0`: every row takes the global K), the mesh is the "
                    "one-sheet extraction (upstream: every face with three real vertices) and is oriented per "
                    "component; phase 2 ends once the mesh has not changed for 50 steps (upstream: all 500); "
                    "CPU kernels."),
    "fast": (False, "an initialisation, no phase-1 step: stray input points dropped and, when the input looks "
                    "noisy, the rest smoothed as `noisy` does (both not upstream), up to 100K seeds (every point of a "
                    "100K-point cloud; 20K when smoothed) + their poles (not all Voronoi vertices), faces far from "
                    "the input carved, no gradient step, one-sheet extraction; a mesh that comes out in shreds "
                    "(unseen noise) is made again from the smoothed input. Differs: no optimisation (none of the "
                    "paper's 1500 steps), 10x the seeds (2x when smoothed)."),
    "noisy": (False, "not in the paper, for noisy scans: the `fast` preset (no phase-1 step) with its input "
                     "always smoothed after the outlier filter (every point moved onto the quadratic jet of its 120 "
                     "nearest neighbours, CGAL's jet smoothing) and at most 20K seeds, where `fast` smooths only "
                     "input that looks noisy. "
                     "On clean input it is several times worse than `fast`."),
    "compact": (False, "not in the paper, a mesh of N faces (`faces`, default 5000): the `fast` preset (no gradient "
                       "step) reduced to N faces by quadric edge collapse, as the reconstruct-then-decimate "
                       "baselines. Chosen on the dev split over `compact_steps` (3-4x more accurate at 5K faces). "
                       "Differs: no optimisation, 10x the seeds, a budget."),
    "compact_steps": (True, "not in the paper, a mesh of N faces (`faces`, default 5000): the `fast` start at N seeds "
                      "(and their poles), 200 phase-1 steps (positions, weights, reals) on the expected Chamfer "
                      "with the tangential part of the offsets scaled by 0.2 and the probability mass beyond each "
                      "target row's candidates charged (the paper drops it), the state of the best Chamfer "
                      "distance to the input kept, then the surface step and quadric edge collapse down to N "
                      "faces. Differs: N seeds (paper 10K) + poles, 200 steps (paper 1000 + 500), a budget."),
    "tiny": (True, "tests only: 1000 seeds + poles, 2 + 15 steps at lr 3e-5, 4K target points."),
}
