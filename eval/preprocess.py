"""Pre-processing of point-cloud input: a harness stage every point-cloud method gets alike (DESIGN.md 8.5).

Letters: N input points, M points kept, P lifted depth pixels.

A sweep asks for it with `preprocess:` (`eval.sweep.Sweep.preprocess`), the CLI with `--preprocess`; each value
is a *spec*, "none" or stages joined by "+", run in this order:

    outliers[=STD]    statistical outlier removal (`dmesh.recon.init.statistical_inliers`: a point goes when
                      its mean distance to its 16 nearest neighbours is more than STD standard deviations
                      above the mean, unless it lies on the surface its neighbours form; strays that fell
                      near the surface go too). STD default 2, the DMesh `fast` preset's `outlier_std`.
    smooth[=K]        jet smoothing (`dmesh.recon.init.smooth_points`, CGAL's `jet_smooth_point_set`): every
                      point moved onto the quadratic jet fitted to its K nearest neighbours. K default 120,
                      the DMesh `noisy` preset's `smooth_k` (`dmesh.recon.config.NOISY_SMOOTH_K`).
    autosmooth[=K]    the same smoothing, only when the points look noisy (`dmesh.recon.init.noise_ratio` above
                      `NOISY_RATIO`): the DMesh `fast` preset's `auto_smooth_k` rule, as a harness stage.

e.g. "outliers+smooth", "outliers=3+smooth=60". `smooth` and `autosmooth` exclude each other. The canonical
form (`parse_spec`) leaves out parameters at their default; it names the run's input in the run key and in
its row (`psr [+outliers+smooth]`). Normals are kept for the points kept (smoothing moves points, not
normals). Each stage is a plain function (points, normals, config) -> (points, normals, info); `apply` runs
a spec and returns what each stage did (points removed, smoothing neighbours, noise ratio, seconds).

The stages call the library's implementations (the harness may import the library; the library never
imports the harness), so the DMesh rows and every baseline get the same filter, and DMesh's harness config
turns its own copies of them off (`baselines.dmesh_pointcloud.harness_config`).

`lift_depth` turns a multi-view capture into the point cloud the multi-view DMesh `depth` preset fits: every
mask pixel lifted by its depth (`dmesh.recon.views.lifted_points`), a seeded random subset of the preset's
`init_points`, chosen as `dmesh.recon.multiview.depth_init` chooses it; its normals are estimated (PCA of 16
neighbours, `datasets.corrupt.estimate_normals`) and turned toward the camera that saw each pixel, as a
scanner's are. A sweep with `lift_depth: true` runs its point-cloud methods on these (`eval.sweep`).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

#: The stages, in the order a spec runs them.
STAGES = ("outliers", "smooth", "autosmooth")
#: The spec of no pre-processing.
NONE = "none"


@dataclass(frozen=True)
class OutlierConfig:
    """Settings of `remove_outliers`."""

    std_ratio: float = 2.0   # standard deviations above the mean neighbour distance (DMesh `fast`'s outlier_std)
    k: int = 16              # neighbours of the distance test (statistical_inliers' default)
    workers: int = 1         # k-d tree query threads

    def __post_init__(self):
        if not (isinstance(self.std_ratio, (int, float)) and not isinstance(self.std_ratio, bool)
                and 0 < self.std_ratio < float("inf")):
            raise ValueError(f"outliers: the standard-deviation ratio must be a positive number, got {self.std_ratio!r}")
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 1:
            raise ValueError(f"outliers: k must be a positive integer, got {self.k!r}")


@dataclass(frozen=True)
class SmoothConfig:
    """Settings of `smooth`."""

    k: int = 120                 # neighbours of each point's jet (dmesh.recon.config.NOISY_SMOOTH_K)
    only_if_noisy: bool = False  # smooth only when noise_ratio exceeds dmesh.recon.init.NOISY_RATIO (autosmooth)
    workers: int = 1             # > 1: CGAL's TBB threads

    def __post_init__(self):
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 6:
            raise ValueError(f"smooth: k must be an integer of at least 6 (a quadratic jet has 6 coefficients), "
                             f"got {self.k!r}")


def remove_outliers(points: np.ndarray, normals: np.ndarray | None, config: OutlierConfig = OutlierConfig()):
    """Statistical outlier removal (`dmesh.recon.init.statistical_inliers`).

    Args:
        points: (N, 3) float; normals: (N, 3) float or None; config: `OutlierConfig`.
    Returns:
        points (M, 3) float64, normals (M, 3) float64 or None (those of the points kept), and info
        {"outliers_removed": N - M}.
    """
    pts = np.asarray(points, dtype=np.float64)
    keep = _inliers(pts, config)
    nrm = None if normals is None else np.asarray(normals, dtype=np.float64)[keep]
    return pts[keep], nrm, {"outliers_removed": int((~keep).sum())}


def _inliers(points: np.ndarray, config: OutlierConfig) -> np.ndarray:
    """(N,) bool: the points `remove_outliers` keeps."""
    from dmesh.recon.init import statistical_inliers

    return statistical_inliers(points, config.std_ratio, k=config.k, workers=config.workers)


def smooth(points: np.ndarray, normals: np.ndarray | None, config: SmoothConfig = SmoothConfig()):
    """Jet smoothing (`dmesh.recon.init.smooth_points`), with `only_if_noisy` only when the points look noisy.

    Args:
        points: (N, 3) float, N >= 7; normals: (N, 3) float or None (returned as given); config: `SmoothConfig`.
    Returns:
        points (N, 3) float64 (moved, or as given), normals, and info {"smoothed": bool, "smooth_k": neighbours
        used (0: not smoothed)} plus "noise_ratio" with `only_if_noisy`.
    Raises:
        ValueError: fewer than 7 points.
    """
    from dmesh.recon.init import NOISY_RATIO, noise_ratio, smooth_points

    pts = np.asarray(points, dtype=np.float64)
    info: dict = {}
    if config.only_if_noisy:
        info["noise_ratio"] = noise_ratio(pts, workers=config.workers)
        if info["noise_ratio"] <= NOISY_RATIO:
            return pts, normals, {**info, "smoothed": False, "smooth_k": 0}
    if len(pts) < 7:
        raise ValueError(f"smooth: needs at least 7 points, got {len(pts)}")
    k = min(int(config.k), len(pts) - 1)
    return smooth_points(pts, k, workers=config.workers), normals, {**info, "smoothed": True, "smooth_k": k}


# ------------------------------------------------------------------------------------------------- specs

def _stage(token: str, what: str):
    """(name, config) of one stage token "name" or "name=VALUE"; ValueError naming `what` otherwise."""
    name, eq, raw = token.partition("=")
    name = name.strip()
    if name not in STAGES:
        raise ValueError(f"{what}: unknown pre-processing stage {name!r}; stages: {', '.join(STAGES)} (joined by "
                         f"'+', e.g. outliers+smooth), or {NONE}")
    value = None
    if eq:
        try:
            value = float(raw) if name == "outliers" else int(raw)
        except ValueError:
            kind = "a number" if name == "outliers" else "an integer"
            raise ValueError(f"{what}: {name}={raw!r}: expected {kind}") from None
    try:
        if name == "outliers":
            return name, OutlierConfig() if value is None else OutlierConfig(std_ratio=value)
        cfg = SmoothConfig(only_if_noisy=name == "autosmooth")
        return name, cfg if value is None else SmoothConfig(k=value, only_if_noisy=cfg.only_if_noisy)
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from None


def parse_spec(spec, what: str = "preprocess") -> tuple[str, list]:
    """(canonical spec, [(stage name, config), ...] in run order) of a spec (module docstring).

    Raises:
        ValueError: one line naming `what`: not text, an unknown stage, a bad value, a stage given twice, or
            smooth and autosmooth together.
    """
    if not isinstance(spec, str):
        raise ValueError(f"{what}: expected a spec such as {NONE} or outliers+smooth, got {spec!r}")
    text = spec.strip()
    if text in ("", NONE):
        return NONE, []
    stages = dict(_stage(token, what) for token in _tokens(text, what))
    if len(stages) != len(_tokens(text, what)):
        raise ValueError(f"{what}: {spec!r} names a stage twice")
    if "smooth" in stages and "autosmooth" in stages:
        raise ValueError(f"{what}: {spec!r}: smooth and autosmooth exclude each other")
    ordered = [(name, stages[name]) for name in STAGES if name in stages]
    return "+".join(_token(name, cfg) for name, cfg in ordered), ordered


def _tokens(text: str, what: str) -> list[str]:
    tokens = [t.strip() for t in text.split("+")]
    if any(not t for t in tokens):
        raise ValueError(f"{what}: {text!r}: an empty stage (stages are joined by a single '+')")
    return tokens


def _token(name: str, cfg) -> str:
    """The canonical token of a stage: its name, with "=VALUE" when the value is not the default."""
    if name == "outliers":
        return name if cfg.std_ratio == OutlierConfig().std_ratio else f"{name}={cfg.std_ratio:g}"
    return name if cfg.k == SmoothConfig().k else f"{name}={cfg.k}"


def label(spec: str) -> str:
    """The row tag of a canonical spec: "" for none, else "+" and the spec ("+outliers+smooth")."""
    return "" if spec == NONE else f"+{spec}"


def apply(points: np.ndarray, normals: np.ndarray | None, spec: str, workers: int = 1,
          is_outlier: np.ndarray | None = None):
    """Runs the stages of `spec` on a point cloud.

    Args:
        points: (N, 3) float; normals: (N, 3) float or None; spec: a spec (module docstring).
        workers: threads of the stages' neighbour queries.
        is_outlier: optional (N,) bool, the planted outliers of a corrupted input (`datasets.corrupt`): the
            info then says how many of them the stages removed.
    Returns:
        points (M, 3) float64, normals (M, 3) float64 or None, and info: {"spec", "input_points", "points",
        "seconds"} and what each stage reported ("outliers_removed", "smoothed", "smooth_k", "noise_ratio",
        "planted_outliers", "planted_outliers_removed").
    """
    import dataclasses

    canon, stages = parse_spec(spec)
    pts = np.asarray(points, dtype=np.float64)
    nrm = None if normals is None else np.asarray(normals, dtype=np.float64)
    info: dict = {"spec": canon, "input_points": int(len(pts))}
    planted = None
    if is_outlier is not None:
        planted = np.asarray(is_outlier, dtype=bool)
        if planted.shape != (len(pts),):
            raise ValueError(f"is_outlier must have shape ({len(pts)},), got {planted.shape}")
    t0 = time.perf_counter()
    for name, cfg in stages:
        cfg = dataclasses.replace(cfg, workers=int(workers))
        if name == "outliers":
            keep = _inliers(pts, cfg)  # remove_outliers' rule, kept to count the planted outliers it removed
            got = {"outliers_removed": int((~keep).sum())}
            if planted is not None:
                got.update(planted_outliers=int(planted.sum()), planted_outliers_removed=int((planted & ~keep).sum()))
                planted = planted[keep]
            pts, nrm = pts[keep], None if nrm is None else nrm[keep]
        else:
            pts, nrm, got = smooth(pts, nrm, cfg)
        info.update(got)
    info.update(points=int(len(pts)), seconds=round(time.perf_counter() - t0, 4))
    log.info("pre-processing %s: %d -> %d points in %.2f s", canon, info["input_points"], info["points"],
             info["seconds"])
    return pts, nrm, info


# ------------------------------------------------------------------------------------------------- depth

def lift_points_default() -> int:
    """Lifted pixels a point-cloud method gets: the multi-view `depth` preset's `init_points`."""
    from dmesh.recon.multiview_config import MultiViewConfig

    return int(MultiViewConfig.depth().init_points)


def lift_depth(views, n: int, seed: int):
    """The point cloud of a multi-view capture's depth pixels, as the `depth` preset's start takes it.

    Args:
        views: a `datasets.capture.MultiView` (depth, mask (V, H, W), cameras).
        n: pixels kept (a random subset when there are more; all otherwise).
        seed: the subset's seed: `np.random.default_rng(seed).choice`, sorted, as `depth_init` draws it from the
            multi-view procedure's generator of the same seed.
    Returns:
        points (M, 3) float64 in the capture's (GT) frame, normals (M, 3) float64 (PCA, toward each pixel's
        camera), info {"pixels": P, "points": M}.
    Raises:
        ValueError: a capture `dmesh.recon.views.check_views` refuses, or fewer than 10 mask pixels.
    """
    from datasets.corrupt import estimate_normals
    from dmesh.camera import eyes
    from dmesh.recon.views import check_views, lifted_points

    vw = check_views(views)
    pixels = lifted_points(vw)
    if len(pixels) < 10:
        raise ValueError(f"lift_depth: the capture has {len(pixels)} mask pixels; at least 10 are needed")
    view = np.repeat(np.arange(len(vw.mask)), np.asarray(vw.mask).reshape(len(vw.mask), -1).sum(1))
    idx = np.arange(len(pixels))
    if len(pixels) > n:
        idx = np.sort(np.random.default_rng(seed).choice(len(pixels), int(n), replace=False))
    pts = pixels[idx]
    normals = estimate_normals(pts, eyes(np.asarray(vw.world_to_camera, np.float64))[view[idx]])
    return pts, normals, {"pixels": int(len(pixels)), "points": int(len(pts))}


__all__ = ["OutlierConfig", "SmoothConfig", "remove_outliers", "smooth", "parse_spec", "label", "apply",
           "lift_depth", "lift_points_default", "STAGES", "NONE"]
