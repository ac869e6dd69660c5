# Re-implemented from the paper "Neural Implicit Evolution" (Mehta, Chandraker, Ramamoorthi; ECCV 2022:
# "A Level Set Theory for Neural Implicit Evolution under Explicit Flows"). No code followed (ishit/nie has
# no licence file); a grid replaces the paper's SIREN network to keep it CPU-sized.
"""NIE: a signed-distance grid evolved by the explicit flow of the image loss of its marching-cubes mesh
(the paper's multi-view baseline in Table 2).

Shape letters: G grid nodes per side, N mesh vertices, F mesh faces, V views.

Each epoch (of `epochs`):
1. Marching cubes (scikit-image) of the grid phi (negative inside) at level 0 gives the explicit mesh, its
   vertices v on the zero level of phi's trilinear interpolant and unit normals n = grad phi / |grad phi|.
2. The image loss E of `baselines._paper_common` (L1 of diffuse + depth through the project's renderer, the
   mesh opaque) over `views_per_epoch` random views, and its gradient dE/dv per vertex, divided by the
   vertex's area (a third of its faces' areas) to get the shape gradient per unit area.
3. The explicit flow is gradient descent, v <- v - eps dE/dv; under it the level set moves along n by
   -eps n . dE/dv, so the implicit's new value at v is the target phi(v) + eps n . dE/dv (the paper's
   level-set update). eps is set per epoch so the `speed_quantile` of the non-zero |n . dE/dv| moves
   `step` voxels (decaying linearly to `step` x `step_final` over the epochs), faster vertices clipped
   there: the raw image-loss gradient has no useful scale of its own, and its silhouette terms are orders
   of magnitude larger than its interior ones.
4. Refit: the grid takes the targets by a normalised Gaussian splat of the per-vertex updates (the
   trilinear weights of each vertex on its 8 nodes, smoothed with a Gaussian of `smooth` voxels and
   divided by the smoothed weights), the closed-form least-squares fit of a smooth update field, which
   also extends the velocity to the nodes around the surface. The paper refits its network by gradient
   steps on the same targets with an eikonal term; here every `redistance_every` epochs the grid away from
   the surface is re-initialised to a signed distance instead (`redistance`), and every epoch phi takes a
   small step of mean-curvature flow (`curvature`), the smoothing the paper's network fit provides.

The output is the marching-cubes mesh of the final grid, faces oriented outward. A level set is a closed
surface, so open and mixed shapes come out as thin closed shells or blobs (the paper's Table 2 shows NIE far
behind on them), and its smoothness rounds off detail.

Simplified against the paper: a grid instead of a SIREN, its refit by splatting plus re-initialisation instead
of network training; a sphere start (radius `init_radius` x the captured object's half extent); images at
`resolution` pixels with a random `views_per_epoch` per epoch and a soft edge band for silhouette gradients.

Default preset (CPU budget, a few minutes per shape on 2 cores; measured by `python -m eval.cli bench
--methods nie --inputs multiview`): grid 64, 300 epochs of 8 views at 128 pixels, step 1 voxel.
"""
from __future__ import annotations

import logging

import numpy as np

from baselines._paper_common import image_loss, image_targets, sphere_sdf, torch_threads
from baselines.base import Inputs, Method, Stopwatch, require

log = logging.getLogger(__name__)


class NIE(Method):
    name = "nie"
    input_kind = "multiview"

    def default_config(self) -> dict:
        return {
            "grid": 64,               # grid nodes per side
            "pad": 0.1,               # the grid covers the lifted pixels' bounding cube enlarged by this fraction
            "init_radius": 0.6,       # initial sphere radius, as a fraction of the object's half extent
            "epochs": 300,            # marching cubes + render + refit rounds
            "views_per_epoch": 8,     # random views rendered per epoch
            "resolution": 128,        # optimised image side in pixels (the capture is area-averaged to it)
            "step": 1.0,              # surface motion (voxels) of the speed quantile below in the first epoch
            "step_final": 0.1,        # ... times this in the last epoch (linear decay)
            "speed_quantile": 0.8,    # quantile of the non-zero speeds that moves `step` (faster ones clipped)
            "smooth": 2.0,            # Gaussian width (voxels) of the refit's splat
            "curvature": 0.03,        # per-epoch blend of phi towards its 1-voxel Gaussian blur (curvature flow)
            "redistance_every": 10,   # epochs between re-initialisations of phi away from the surface
            "lambda_depth": 1.0,      # weight of the depth channel's L1 (diffuse 1)
            "edge_width": 1.0,        # the soft renderer's edge band, in optimised pixels
            "threads": 1,             # torch threads
            "render_threads": 2,      # native threads of the renderer
        }

    def prepare(self) -> None:
        require("skimage.measure", package="scikit-image")
        import dmesh.recon.multiview  # noqa: F401  (torch and the native renderer, before the clock starts)

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import trimesh

        _check_config(cfg)
        with sw.stage("targets"):
            targets = image_targets(inputs.views, cfg["resolution"], float(cfg["edge_width"]))
        with torch_threads(int(cfg["threads"])):
            grid, info = evolve(targets, cfg, int(inputs.seed), sw)
        with sw.stage("extract"):
            verts, faces = grid.surface()
        if len(faces) == 0:
            raise RuntimeError("nie: the evolved level set is empty (no zero crossing in the grid)")
        mesh = trimesh.Trimesh(verts, faces, process=False)
        mesh.remove_unreferenced_vertices()
        return mesh, info


def _check_config(cfg: dict) -> None:
    if int(cfg["grid"]) < 8 or int(cfg["epochs"]) < 0 or int(cfg["views_per_epoch"]) < 1:
        raise ValueError(f"nie: need grid >= 8, epochs >= 0, views_per_epoch >= 1; got {cfg['grid']}, "
                         f"{cfg['epochs']}, {cfg['views_per_epoch']}")
    if not 0.0 < float(cfg["init_radius"]) < 1.0 + float(cfg["pad"]):
        raise ValueError(f"nie: init_radius must be in (0, 1 + pad), got {cfg['init_radius']}")
    if not (float(cfg["step"]) > 0 and float(cfg["smooth"]) >= 0 and int(cfg["redistance_every"]) >= 1):
        raise ValueError("nie: need step > 0, smooth >= 0 and redistance_every >= 1")


class LevelSetGrid:
    """phi on a G^3 node grid over [origin, origin + (G - 1) h]^3 (float64, negative inside)."""

    def __init__(self, phi: np.ndarray, origin: np.ndarray, voxel: float):
        self.phi, self.origin, self.voxel = phi, np.asarray(origin, dtype=np.float64), float(voxel)

    @property
    def nodes(self) -> np.ndarray:
        g = self.phi.shape[0]
        ijk = np.stack(np.meshgrid(*(np.arange(g),) * 3, indexing="ij"), -1)
        return self.origin + ijk * self.voxel

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Marching cubes at level 0: (N, 3) float64 vertices, (F, 3) int64 faces, normals outward (towards
        larger phi). Empty arrays when phi has no sign change."""
        from skimage.measure import marching_cubes

        if not (self.phi.min() < 0 < self.phi.max()):
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        v, f, _, _ = marching_cubes(self.phi, 0.0, spacing=(self.voxel,) * 3)
        v = v.astype(np.float64) + self.origin
        f = f.astype(np.int64)
        tri = v[f]
        area_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        _, grad = self.sample(tri.mean(1))
        if (area_normal * grad).sum() < 0:
            f = f[:, ::-1].copy()
        return v, f

    def sample(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear phi (M,) and its gradient (M, 3) at points p (M, 3) (clamped to the grid)."""
        factors, idx = self._factors(p)                                 # (M, 8, 3), (M, 8)
        vals = self.phi.ravel()[idx]
        value = (factors.prod(2) * vals).sum(1)
        grad = np.zeros_like(p)
        sign = np.where((np.arange(8)[:, None] >> np.arange(3)) & 1, 1.0, -1.0)  # (8, 3) d factor / d t
        for a in range(3):
            others = np.delete(factors, a, axis=2).prod(2)             # (M, 8)
            grad[:, a] = (others * sign[:, a] * vals).sum(1) / self.voxel
        return value, grad

    def weights(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear weights (M, 8) and flat node indices (M, 8) of points p (M, 3)."""
        factors, idx = self._factors(p)
        return factors.prod(2), idx

    def _factors(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-axis trilinear factors (M, 8, 3) and flat node indices (M, 8) of points p (M, 3); corner c of a
        cell is at offsets ((c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1)."""
        g = self.phi.shape[0]
        t = (p - self.origin) / self.voxel
        i0 = np.clip(np.floor(t).astype(np.int64), 0, g - 2)
        f = np.clip(t - i0, 0.0, 1.0)
        off = (np.arange(8)[:, None] >> np.arange(3)) & 1               # (8, 3)
        factors = np.where(off[None], f[:, None, :], 1.0 - f[:, None, :])
        i = i0[:, None, :] + off[None]
        return factors, (i[..., 0] * g + i[..., 1]) * g + i[..., 2]


def vertex_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) float64 a third of the summed areas of each vertex's faces."""
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.bincount(faces.ravel(), np.repeat(area / 3.0, 3), minlength=len(verts))


def flow_targets(grid: LevelSetGrid, verts: np.ndarray, faces: np.ndarray, grad_e: np.ndarray,
                 step_voxels: float, quantile: float) -> np.ndarray:
    """(N,) float64 target changes of phi at the mesh vertices: eps n . dE/dv per unit area (module
    docstring, step 3), eps scaled so the `quantile` of the non-zero |speeds| moves `step_voxels` voxels,
    faster ones clipped there."""
    _, grad = grid.sample(verts)
    n = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-12)
    speed = (n * grad_e).sum(1) / np.maximum(vertex_areas(verts, faces), 1e-12)
    moving = np.abs(speed[speed != 0])
    scale = float(np.quantile(moving, quantile)) if len(moving) else 0.0
    if not scale > 0:
        return np.zeros(len(verts))
    return step_voxels * grid.voxel * np.clip(speed / scale, -1.0, 1.0)


def refit(grid: LevelSetGrid, verts: np.ndarray, delta: np.ndarray, smooth: float) -> None:
    """Adds to phi the smooth update field that takes `delta` (N,) at `verts` (N, 3): a normalised Gaussian
    splat (module docstring, step 4), applied where the smoothed weights exceed 5% of their median at the
    nodes the vertices touch."""
    from scipy.ndimage import gaussian_filter

    w, idx = grid.weights(verts)
    size = grid.phi.size
    num = np.bincount(idx.ravel(), (w * delta[:, None]).ravel(), minlength=size).reshape(grid.phi.shape)
    den = np.bincount(idx.ravel(), w.ravel(), minlength=size).reshape(grid.phi.shape)
    touched = den > 0
    if not touched.any():
        return
    if smooth > 0:
        num, den = gaussian_filter(num, smooth), gaussian_filter(den, smooth)
    keep = den > 0.05 * float(np.median(den[touched]))
    grid.phi[keep] += num[keep] / den[keep]


def smooth_level_set(grid: LevelSetGrid, weight: float) -> None:
    """phi <- (1 - weight) phi + weight G(phi), G a Gaussian blur of one voxel: for a signed distance the blur
    changes phi by about the mean curvature times the variance, so this is a small step of mean-curvature
    flow, the smoothing a level-set evolution needs (the paper gets it from its network's fit)."""
    from scipy.ndimage import gaussian_filter

    grid.phi = (1.0 - weight) * grid.phi + weight * gaussian_filter(grid.phi, 1.0, mode="nearest")


def redistance(grid: LevelSetGrid) -> None:
    """Re-initialises phi to a signed distance away from the surface, keeping the surface itself.

    Nodes of the cells the surface crosses (any node with an opposite sign in its 3 x 3 x 3 neighbourhood)
    keep their values, so the zero level set does not move; every other node takes its sign times the
    distance to the nearest kept node plus that node's |phi| (scipy's Euclidean distance transform: a
    voxel-accurate distance, the classic level-set re-initialisation, in tens of milliseconds for 64^3).
    """
    from scipy.ndimage import distance_transform_edt, maximum_filter, minimum_filter

    inside = grid.phi < 0
    if inside.all() or not inside.any():
        return
    crossing = maximum_filter(inside, size=3) != minimum_filter(inside, size=3)
    dist, idx = distance_transform_edt(~crossing, sampling=grid.voxel, return_indices=True)
    far = ~crossing
    near_value = np.abs(grid.phi[idx[0], idx[1], idx[2]])
    grid.phi[far] = np.where(inside[far], -1.0, 1.0) * (dist[far] + near_value[far])


def evolve(targets, cfg: dict, seed: int, sw: Stopwatch) -> tuple[LevelSetGrid, dict]:
    """Runs the epochs (module docstring) from a sphere; returns the final grid and info."""
    import torch

    rng = np.random.default_rng(seed)
    with sw.stage("init"):
        g = int(cfg["grid"])
        half = targets.half_extent * (1.0 + float(cfg["pad"]))
        grid = LevelSetGrid(np.zeros((g, g, g)), targets.center - half, 2.0 * half / (g - 1))
        grid.phi = sphere_sdf(grid.nodes, targets.center, float(cfg["init_radius"]) * targets.half_extent)
    epochs, batch = int(cfg["epochs"]), min(int(cfg["views_per_epoch"]), targets.views)
    history = []
    for e in range(epochs):
        with sw.stage("marching_cubes"):
            verts, faces = grid.surface()
        if len(faces) == 0:
            raise RuntimeError(f"nie: the level set vanished at epoch {e} (no zero crossing left in the grid)")
        with sw.stage("render"):
            v = torch.tensor(verts, dtype=torch.float32, requires_grad=True)
            ids = rng.choice(targets.views, batch, replace=False)
            loss = image_loss(v, torch.from_numpy(faces), targets, ids, edge_width=float(cfg["edge_width"]),
                              lambda_depth=float(cfg["lambda_depth"]), num_threads=int(cfg["render_threads"]))
            loss.backward()
        with sw.stage("refit"):
            frac = e / max(1, epochs - 1)
            step = float(cfg["step"]) * (1.0 - (1.0 - float(cfg["step_final"])) * frac)
            delta = flow_targets(grid, verts, faces, v.grad.double().numpy(), step, float(cfg["speed_quantile"]))
            refit(grid, verts, delta, float(cfg["smooth"]))
            if float(cfg["curvature"]) > 0:
                smooth_level_set(grid, float(cfg["curvature"]))
            if (e + 1) % int(cfg["redistance_every"]) == 0:
                redistance(grid)
        history.append(float(loss.detach()))
    info = {"grid": g, "voxel": grid.voxel, "epochs": epochs, "views_per_epoch": batch,
            "image_loss_first": history[0] if history else None, "image_loss_last": history[-1] if history else None}
    return grid, info
