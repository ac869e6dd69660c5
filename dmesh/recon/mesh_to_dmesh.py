"""Mesh to DMesh (the paper's Exp. 1): recover a given mesh's connectivity as a DMesh.

Letters: N points (the G ground-truth vertices first, then inserted points), F GT faces, C candidates.

The GT vertices start as points (weight 1, real 1) and may move at most `max_perturb` per coordinate; they
keep weight 1. Extra points are inserted periodically on unwanted faces (WDT faces on GT vertices that are
not GT faces): k-means centroids of one random point per unwanted face plus up to `max_direct_inserts`
of those points; they start with weight 1 and real 0, and their weights stay in [0, 1]. Only faces whose
three vertices are GT vertices are scored, with the margin loss of paper Appendix 8.1

    L = - sum_{GT, in WDT} min(Delta, m) - sum_{GT, not in WDT} Delta
        + sum_{not GT, in WDT} Delta + sum_{not GT, not in WDT} max(Delta, -m),

so faces already right by more than the margin m stop pulling. RE = recovered GT faces / GT faces and
FP = false faces / WDT faces on GT vertices, on sorted unique triples. The run stops early when
RE > `re_target` and FP < `fp_target`, and keeps the best-RE and best-FP states.

Procedure:
1. Each insertion period (`insert_every` steps) is one phase of `dmesh.recon.loop.Loop.run_phase`: the WDT
   of the current points; points inserted on its unwanted faces (hidden inserted points dropped); a fresh
   `BoundedAdam` over positions and weights at lr `lr` x `decay`^period, bound `update_bound` x the same,
   per-point gradient clip `grad_clip`.
2. Each step (`_Run.step`): re-triangulate, score the faces (the margin loss above), measure RE / FP and
   keep the best states; stop before the update once the targets are met; otherwise backward and the
   bounded update, then the GT vertices are put back within `max_perturb` of their start with weight 1.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
import torch

from dmesh.candidates import CandidateFaces, NeighbourCache, knn_triples
from dmesh.checks import require_positive
from dmesh.deltas import existing_deltas, nonexisting_deltas
from dmesh.recon.loop import Loop, ReconstructionResult, deterministic
from dmesh.recon.optim import BoundedAdam, StepConfig
from dmesh.tolerances import COINCIDENT, FLOAT64_FLOOR
from dmesh.wdt import PowerDiagram, face_keys, triangulate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MeshToDMeshConfig:
    """Settings of the mesh-to-DMesh procedure (frame: mesh normalised to max vertex norm 0.8)."""

    steps: int = 20000            # maximum optimisation steps
    lr: float = 1e-4              # `BoundedAdam` learning rate (positions and weights)
    update_bound: float = 1e-5    # per-step bound on every coordinate and weight change
    max_perturb: float = 1e-2     # GT vertices stay within this of their start, per coordinate
    margin: float = 3e-4          # faces right by more than this stop pulling
    insert_every: int = 5000      # point insertion period in steps (first insertion at step 0)
    max_direct_inserts: int = 1000  # inserted samples kept besides the k-means centroids
    kmeans_fraction: float = 0.1  # k-means clusters per unwanted-face sample
    knn_every: int = 100          # add kNN triples on GT vertices every this many steps
    knn_k: int = 8                # neighbours for kNN triples
    decay: float = 1.0            # lr and update bound are multiplied by this after every insertion period
    grad_clip: float = 0.1        # per-point gradient-norm clip (`BoundedAdam`: a position as a 3-vector, a weight)
    fp_accept: float = 0.005      # the kept state: highest RE among states with FP <= this (else best RE - FP)
    re_target: float = 0.999      # early stop when RE exceeds this ...
    fp_target: float = 0.01       # ... and FP is below this
    ray_length: float = 500.0     # sample distance along hull rays (unit domain)
    seed: int = 0                 # seeds insertion sampling and k-means

    def __post_init__(self):
        require_positive(self, ("steps", "insert_every", "knn_every", "knn_k"))
        if not 0 < self.decay <= 1:
            raise ValueError(f"MeshToDMeshConfig.decay must be in (0, 1], got {self.decay}")
        require_positive(self, ("lr", "update_bound", "max_perturb", "margin", "grad_clip", "ray_length"))


def paper_config(**overrides) -> MeshToDMeshConfig:
    """The published settings (Appendix 10.1): 20K steps, lr 1e-4, insertion every 5000 steps (bunny)."""
    return MeshToDMeshConfig(**overrides)


def fast_config(**overrides) -> MeshToDMeshConfig:
    """A CPU budget: larger steps and more frequent insertion, so small meshes converge in ~1-2K steps."""
    base = dict(steps=3000, lr=1e-3, update_bound=1e-4, insert_every=500, knn_every=50, decay=0.5)
    base.update(overrides)
    return MeshToDMeshConfig(**base)


PRESETS: dict[str, Callable[..., MeshToDMeshConfig]] = {"paper": paper_config, "fast": fast_config}


@dataclass
class Snapshot:
    """A saved point state with its metrics."""

    step: int
    re: float
    fp: float
    points: np.ndarray    # (N, 3) float64
    weights: np.ndarray   # (N,) float64
    faces: np.ndarray     # (K, 3) int64 WDT faces on GT vertices in this state (wound at the end of the run)


@dataclass(kw_only=True)
class MeshToDMeshResult(ReconstructionResult):
    """Outcome of `mesh_to_dmesh` (`dmesh.recon.loop.ReconstructionResult`).

    Attributes:
        mesh: `trimesh.Trimesh` of the final state: all points as vertices (GT vertices first, unreferenced
            inserted points kept, so indices match `points`) and the recovered faces;
        dmesh: the final `DMesh` (float64); center: zeros and scale: 1 (the input's frame);
        points: (N, 3) float64 final positions (GT vertices first); weights: (N,) float64;
        reals: (N,) float64 (1 for GT vertices, 0 for inserted points);
        faces: (K, 3) int64 recovered mesh faces (WDT faces on GT vertices) of the final state;
        re, fp: final recovery and false-positive ratios in [0, 1]; steps: steps run;
        best_re, best_fp: `Snapshot`s of the highest RE and the lowest FP; best: the kept `Snapshot` (what
            the harness reports, like upstream's kept checkpoints): the highest RE among states with
            FP <= `fp_accept`, or, when no state qualifies, the highest RE - FP;
        history: one dict per step (step, steps (the insertion period's end), loss, re, fp, points,
            inserted, seconds);
        timings: seconds per stage ("insert", "wdt", "loss", "backward", "step", "total", "total_cpu");
        info: counts; stopped_early: whether the RE/FP targets were met; config: the config as a dict.
    """

    points: np.ndarray
    weights: np.ndarray
    reals: np.ndarray
    faces: np.ndarray
    re: float
    fp: float
    steps: int
    best_re: Snapshot
    best_fp: Snapshot
    best: Snapshot
    stopped_early: bool = False
    config: dict = field(default_factory=dict)


def recovery_metrics(wdt_gt_keys: np.ndarray, gt_keys: np.ndarray) -> tuple[float, float]:
    """(RE, FP) from sorted unique face keys of the WDT faces on GT vertices and of the GT faces."""
    hit = np.isin(wdt_gt_keys, gt_keys, assume_unique=True).sum()
    re = hit / max(len(gt_keys), 1)
    fp = (len(wdt_gt_keys) - hit) / max(len(wdt_gt_keys), 1)
    return float(re), float(fp)


def _validate(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise ValueError(f"mesh vertices must have shape (G, 3) with G >= 4, got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("mesh vertices must be finite (found NaN or inf)")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"the mesh has no faces (faces shape {f.shape})")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"mesh faces must index vertices in [0, {len(v)})")
    f = np.unique(np.sort(f, axis=1), axis=0)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2])]
    if len(f) == 0:
        raise ValueError("the mesh has only degenerate faces")
    if len(np.unique(v, axis=0)) < len(v):
        raise ValueError("mesh vertices must be distinct (merge duplicate vertices first)")
    return v, f


class _Run:
    """State of one mesh-to-DMesh run (points grow at every insertion)."""

    def __init__(self, vertices: np.ndarray, gt_faces: np.ndarray, cfg: MeshToDMeshConfig):
        self.cfg = cfg
        self.g = len(vertices)
        self.start = torch.from_numpy(vertices.copy())
        self.gt_faces = gt_faces
        self.rng = np.random.default_rng(cfg.seed)
        self.points = torch.tensor(vertices, dtype=torch.float64)
        self.weights = torch.ones(self.g, dtype=torch.float64)
        self.pd: PowerDiagram | None = None  # the insertion's diagram, used by the period's first step
        self._reset_phase()

    @property
    def n(self) -> int:
        return len(self.points)

    def _reset_phase(self):
        self.points = self.points.detach().clone().requires_grad_(True)
        self.weights = self.weights.detach().clone().requires_grad_(True)
        self.reals = (torch.arange(self.n) < self.g).double()  # not trained
        self.cache = NeighbourCache(self.n)
        self.candidates = CandidateFaces(self.n)
        self.candidates.add(self.gt_faces)
        self.gt_keys = np.sort(face_keys(self.gt_faces, self.n))

    def optimizer(self, decay_factor: float) -> BoundedAdam:
        """The `BoundedAdam` of an insertion period: positions and weights, lr and bound times
        `decay_factor` (`decay` ** period)."""
        cfg = self.cfg
        step = StepConfig(lr=cfg.lr * decay_factor, update_bound=cfg.update_bound * decay_factor,
                          grad_clip=cfg.grad_clip)
        return BoundedAdam(self.points, self.weights, self.reals, step, train=("points", "weights"))

    def diagram(self) -> PowerDiagram:
        """The WDT of the current points (the insertion's, when it is fresh)."""
        pd, self.pd = self.pd, None
        if pd is None:
            tri = triangulate(self.points, self.weights)
            pd = PowerDiagram(self.points, self.weights, tri.tets, tri.neighbors)
        return pd

    def insert_points(self) -> int:
        """Drops hidden inserted points and inserts new ones on unwanted faces; returns how many."""
        pd = self.diagram()
        unwanted = self._unwanted(pd)
        keep = np.ones(self.n, bool)
        keep[self.g:] = ~pd.hidden[self.g:]
        p = self.points.detach().numpy()[keep]
        w = self.weights.detach().numpy()[keep]
        new = np.zeros((0, 3))
        if len(unwanted):
            tri = self.points.detach().numpy()[unwanted]                       # (U, 3, 3)
            b = self.rng.dirichlet(np.ones(3), size=len(unwanted))
            samples = np.einsum("uk,ukd->ud", b, tri)
            k = max(1, int(self.cfg.kmeans_fraction * len(samples)))
            centroids = _kmeans(samples, k, self.rng) if len(samples) > k else samples
            direct = samples[self.rng.permutation(len(samples))[: self.cfg.max_direct_inserts]]
            new = np.unique(np.concatenate([centroids, direct]), axis=0)
            new = new[~_coincides(new, p)]
        self.points = torch.tensor(np.concatenate([p, new]), dtype=torch.float64)
        self.weights = torch.tensor(np.concatenate([w, np.ones(len(new))]), dtype=torch.float64)
        self._reset_phase()
        self.pd = self.diagram()
        return len(new)

    def _unwanted(self, pd: PowerDiagram) -> np.ndarray:
        on_gt = pd.faces[(pd.faces < self.g).all(1)].astype(np.int64)
        keys = face_keys(on_gt, self.n)
        return on_gt[~np.isin(keys, self.gt_keys)]

    def step(self, pd: PowerDiagram, knn: bool) -> tuple[torch.Tensor, float, float, np.ndarray]:
        """One loss evaluation on the current diagram; returns (loss, RE, FP, recovered faces)."""
        cfg = self.cfg
        cache = self.cache.update(pd.point_neighbors)
        on_gt = np.flatnonzero((pd.faces < self.g).all(1))
        wdt_keys_all = face_keys(pd.faces[on_gt].astype(np.int64), self.n)
        order = np.argsort(wdt_keys_all)
        wdt_keys = wdt_keys_all[order]
        on_gt = on_gt[order]
        self.candidates.add_sorted_keys(wdt_keys)
        if knn:
            self.candidates.add(knn_triples(self.points.detach().numpy()[: self.g], None, k=cfg.knn_k))
        re, fp = recovery_metrics(wdt_keys, self.gt_keys)

        in_gt = np.isin(wdt_keys, self.gt_keys, assume_unique=True)
        loss = torch.zeros((), dtype=torch.float64)
        # WDT faces on GT vertices: GT ones pulled up to the margin, the others pushed down.
        if len(on_gt):
            d = existing_deltas(self.points, self.weights, pd, cache, cfg.ray_length,
                                face_ids=on_gt).mean(1)
            gt_mask = torch.from_numpy(in_gt)
            loss = loss - d[gt_mask].clamp_max(cfg.margin).sum() + d[~gt_mask].sum()
        # Candidates not in the WDT: GT ones pulled up, the others kept below -margin.
        ck = self.candidates.keys
        pos = np.searchsorted(wdt_keys, ck).clip(max=max(len(wdt_keys) - 1, 0))
        absent = ck if len(wdt_keys) == 0 else ck[wdt_keys[pos] != ck]
        faces = self.candidates.faces_of(absent)
        faces = faces[~pd.hidden[faces].any(1)]
        is_gt = np.isin(face_keys(faces, self.n), self.gt_keys)
        if is_gt.any():
            d = nonexisting_deltas(self.points, self.weights, pd, faces[is_gt], cfg.ray_length)
            loss = loss + d.mean(1).sum()  # Delta = -mean distance: minimising -Delta
        if (~is_gt).any():
            d = nonexisting_deltas(self.points, self.weights, pd, faces[~is_gt], cfg.ray_length,
                                   band=cfg.margin)
            loss = loss + (-d.mean(1)).clamp_min(-cfg.margin).sum()
        return loss, re, fp, pd.faces[on_gt].astype(np.int64)

    def constrain(self, step: int) -> None:
        """After an update: GT vertices within `max_perturb` of their start, with weight 1."""
        bound = self.cfg.max_perturb
        with torch.no_grad():
            gt = self.points[: self.g]
            gt.copy_(torch.maximum(torch.minimum(gt, self.start + bound), self.start - bound))
            self.weights[: self.g] = 1.0


def _better(re: float, fp: float, best: Snapshot | None, fp_accept: float) -> bool:
    """Whether (re, fp) beats the kept state: acceptable FP first, then RE; RE - FP among the rest."""
    if best is None:
        return True
    ok, best_ok = fp <= fp_accept, best.fp <= fp_accept
    if ok != best_ok:
        return ok
    if ok:
        return re > best.re or (re == best.re and fp < best.fp)
    return re - fp > best.re - best.fp


def _coincides(a: np.ndarray, b: np.ndarray, tol: float = COINCIDENT) -> np.ndarray:
    """(len(a),) bool: rows of a within tol of some row of b."""
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool)
    d, _ = cKDTree(b).query(a)
    return d < tol


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = 20) -> np.ndarray:
    """(k, 3) Lloyd k-means centroids started from k random samples (seeded).

    Hand-written because SciPy's kmeans2 assigns by brute force (O(n k) per iteration: 100 s for the
    dragon's 75K samples and 7.5K clusters); here a KD-tree over the centroids assigns in O(n log k).
    """
    from scipy.spatial import cKDTree

    c = x[rng.choice(len(x), k, replace=False)].copy()
    for _ in range(iters):
        _, label = cKDTree(c).query(x)
        count = np.bincount(label, minlength=k)
        sums = np.stack([np.bincount(label, weights=x[:, d], minlength=k) for d in range(3)], axis=1)
        moved = count > 0
        new = c.copy()
        new[moved] = sums[moved] / count[moved, None]
        if np.allclose(new, c):
            break
        c = new
    return c


def _orient(points: np.ndarray, weights: np.ndarray, faces: np.ndarray, gt_vertices: np.ndarray,
            gt_faces: np.ndarray) -> np.ndarray:
    """The (K', 3) output faces: `faces` wound by the surface step (`dmesh.surface.run`, orientation only) on the
    state's WDT, closed parts outward (tets inside / outside), the rest like the input mesh (the normals of its
    faces, at their centroids, stand in for input normals).

    When the input mesh has no non-manifold edge, neither has the output: a false face that shares an edge
    with the closed part (a fin) is dropped, and on an edge that still has more than two faces only the two
    that continue each other best stay (`dmesh.surface.finish.keep_flattest`). An input that is itself
    non-manifold (some scans) keeps every face, so its extra sheets are not cut away."""
    from dmesh.surface import SurfaceConfig, run
    from dmesh.surface.finish import keep_flattest
    from dmesh.surface.topology import faces_on_edges, nonmanifold_edges

    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return faces
    pd = PowerDiagram.from_points(points, weights)
    ids = pd.face_ids(faces)
    walls = np.zeros(len(pd.faces), bool)
    walls[ids[ids >= 0]] = True
    tri = gt_vertices[gt_faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), FLOAT64_FLOOR)
    s = run(pd, walls, (tri.mean(1), normal), None, SurfaceConfig(clean=False))
    wound = np.concatenate([s.faces, faces[ids < 0]])  # (a face not in this WDT, which should not happen, stays)
    if len(nonmanifold_edges(gt_faces)):
        return wound
    closed, rest = wound[:s.closed], wound[s.closed:]
    wound = np.concatenate([closed, rest[~faces_on_edges(rest, closed)]])
    return wound[keep_flattest(points, wound)]


@deterministic
def mesh_to_dmesh(vertices, faces, config: MeshToDMeshConfig | None = None,
                  callback: Callable[[dict], None] | None = None) -> MeshToDMeshResult:
    """Optimises a DMesh whose WDT faces on the given vertices reproduce the given faces.

    Args:
        vertices: (G, 3) float, distinct, already normalised (max vertex norm 0.8 is the convention).
        faces: (F, 3) ints; sorted and made unique here (back-to-back pairs collapse to one face).
        config: `MeshToDMeshConfig` (see `PRESETS`).
        callback: called after every step with its record (step, loss, re, fp, points, inserted, ...).
    Returns:
        `MeshToDMeshResult`. Raises ValueError for a mesh without faces, NaN vertices or duplicates.
    """
    import trimesh

    from dmesh.model import DMesh

    cfg = config or MeshToDMeshConfig()
    v, f = _validate(vertices, faces)
    run = _Run(v, f, cfg)
    loop = Loop(callback)
    kept: dict = {"best_re": None, "best_fp": None, "best": None}
    last = {"re": 0.0, "fp": 0.0, "faces": np.zeros((0, 3), np.int64), "inserted": 0}

    def fit_step(step: int):
        with loop.clock("wdt"):
            pd = run.diagram()
        with loop.clock("loss"):
            loss, re, fp, recovered = run.step(pd, knn=step % cfg.knn_every == 0)
        last.update(re=re, fp=fp, faces=recovered)
        snap = None

        def snapshot():
            return snap or Snapshot(step, re, fp, run.points.detach().numpy().copy(),
                                    run.weights.detach().numpy().copy(), recovered)

        b = kept["best_re"]
        if b is None or re > b.re or (re == b.re and fp < b.fp):
            kept["best_re"] = snap = snapshot()
        b = kept["best_fp"]
        if b is None or fp < b.fp or (fp == b.fp and re > b.re):
            kept["best_fp"] = snap = snapshot()
        if _better(re, fp, kept["best"], cfg.fp_accept):
            kept["best"] = snap = snapshot()
        return loss, {"re": re, "fp": fp, "points": run.n, "inserted": last["inserted"]}

    def converged(figures: dict) -> bool:
        return figures["re"] > cfg.re_target and figures["fp"] < cfg.fp_target

    stopped = False
    for period, begin in enumerate(range(0, cfg.steps, cfg.insert_every)):
        with loop.clock("insert"):
            last["inserted"] = run.insert_points()
        log.debug("step %d: inserted %d points (%d in all)", begin, last["inserted"], run.n)
        end = min(begin + cfg.insert_every, cfg.steps)
        stopped = loop.run_phase(fit_step, run.optimizer(cfg.decay ** period), end, begin,
                                 after_step=run.constrain, stop=converged)
        if stopped:
            break
    reals = run.reals.numpy().copy()
    points, weights = run.points.detach().numpy().copy(), run.weights.detach().numpy().copy()
    # The output faces are wound outward on closed parts and like the input elsewhere (`_orient`).
    wound = np.asarray(faces, dtype=np.int64)  # the input's winding (`_validate` sorts its triples)
    for snap in {id(s): s for s in kept.values() if s is not None}.values():
        snap.faces = _orient(snap.points, snap.weights, snap.faces, v, wound)
    mesh = trimesh.Trimesh(points, _orient(points, weights, last["faces"], v, wound), process=False)
    dm = DMesh(points, weights, reals, dtype=torch.float64)
    info = {"gt_vertices": run.g, "gt_faces": int(len(f)), "points": run.n}
    return MeshToDMeshResult(
        mesh=mesh, dmesh=dm, center=np.zeros(3), scale=1.0, timings=loop.finish(), history=loop.history,
        info=info, points=points, weights=weights, reals=reals, faces=last["faces"], re=last["re"],
        fp=last["fp"], steps=loop.history[-1]["step"] + 1, best_re=kept["best_re"], best_fp=kept["best_fp"],
        best=kept["best"], stopped_early=stopped, config=asdict(cfg))
