# Follows FlexiCubes (Shen, Munkberg, Hasselgren, Chen, Gao, Lindell, Kirk; SIGGRAPH 2023), from its paper
# and the description of nv-tlabs/FlexiCubes (Apache-2.0). Written from scratch here, tables included (they
# are generated below from the cube's connectivity): no code copied.
"""FlexiCubes: a deformable grid of signed distances with learnable dual-vertex weights, fitted to multi-view
diffuse and depth images through the project's renderer (the paper's multi-view baseline in Table 2).

Shape letters: P grid nodes, C cubes, S surface cubes, D dual vertices, Q quads, F faces, V views.

Representation (a `grid`^3 cube grid over the lifted depth pixels' bounding box, padded by `pad`):
- per node: a signed distance s (negative inside) and a deformation, x = x0 + (h / 2) tanh(d), h the cube side;
- per cube: 12 edge weights beta, 8 corner weights alpha (each 1 + 0.99 tanh(raw)) and a split weight
  gamma (0.005 + 0.99 sigmoid(raw)).

Extraction (Dual Marching Cubes with the FlexiCubes weights): a surface cube (mixed signs) has one dual
vertex per group of its sign-changing edges; the groups come from `EDGE_GROUP`, generated below (two
crossing edges share a dual vertex when their inside corners are connected by inside cube edges and their
outside corners by outside edges or face diagonals: on an ambiguous face the inside is separated, the
same rule in every cube, so neighbours agree). On edge e = (i, j) the crossing is u_e = (s_i a_i x_j -
s_j a_j x_i) / (s_i a_i - s_j a_j) and the dual vertex is the beta-weighted mean of its group's crossings.
Each sign-changing grid edge inside the grid joins the dual vertices of its four cubes into a quad, oriented
so that its normal points from the inside node to the outside one. While fitting, a quad is split into
four triangles around its gamma-weighted centroid; the output splits it into two along the diagonal whose
two cubes have the larger gamma product.

Loss: the image loss of `baselines._paper_common` (L1 of diffuse + depth, the DMesh authors' setting for
this baseline, without the GT-SDF loss of the FlexiCubes example) over `views_per_step` random views, plus
the example's regularisers: the sign-change penalty on grid edges (binary cross-entropy of each end's
sigmoid(s) against the other end's sign, weight `lambda_sdf` decaying to a twentieth over the first quarter),
`lambda_dev` x the mean absolute deviation of the distances from each dual vertex to its crossings (L_dev),
and `lambda_weights` x the mean |raw weight|. Adam at `lr` on everything, decayed by 10^(-step / 5000).

Simplified against the original: the signed distances start from a sphere (radius `init_radius` x the
captured object's half extent) instead of the example's random field (whose first meshes have an order of
magnitude more faces to render on a CPU); the resolution of ambiguous cases across faces (the original's
C16 table) and its tetrahedral output are not implemented; images are fitted at `resolution` pixels, a
random `views_per_step` per step, with a soft edge band instead of nvdiffrast's antialiasing.

Default preset (CPU budget, a few minutes per shape on 2 cores; measured by `python -m eval.cli bench
--methods flexicubes --inputs multiview`): grid 48, 600 steps of 4 views at 128 pixels, lr 0.01.
"""
from __future__ import annotations

import dataclasses
import itertools
import logging

import numpy as np

from baselines._paper_common import image_loss, image_targets, sphere_sdf, torch_threads
from baselines.base import Inputs, Method, Stopwatch

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------- tables

#: (8, 3) corner offsets of a cube: corner c sits at (c & 1, (c >> 1) & 1, (c >> 2) & 1).
CORNERS = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], dtype=np.int64)
#: (12, 2) corner pairs of the cube edges: edges 4a .. 4a + 3 run along axis a, from the corner whose bit a is 0.
EDGES = np.array([(c, c | (1 << a)) for a in range(3) for c in range(8) if not (c >> a) & 1], dtype=np.int64)
#: (12,) axis of each cube edge.
EDGE_AXIS = np.repeat(np.arange(3), 4)


def _components(nodes: list[int], linked) -> dict[int, int]:
    """Connected components (node -> representative) of `nodes` under the symmetric relation `linked`."""
    parent = {n: n for n in nodes}

    def find(n):
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for a, b in itertools.combinations(nodes, 2):
        if linked(a, b):
            parent[find(a)] = find(b)
    return {n: find(n) for n in nodes}


def _edge_groups() -> tuple[np.ndarray, np.ndarray]:
    """(256, 12) int64 dual-vertex group of each sign-changing edge per sign configuration (-1: no crossing),
    and (256,) the number of groups. Bit c of a configuration is set when corner c is inside."""
    groups = np.full((256, 12), -1, dtype=np.int64)
    count = np.zeros(256, dtype=np.int64)
    for code in range(256):
        inside = [c for c in range(8) if (code >> c) & 1]
        outside = [c for c in range(8) if not (code >> c) & 1]
        comp_in = _components(inside, lambda a, b: bin(a ^ b).count("1") == 1)
        comp_out = _components(outside, lambda a, b: bin(a ^ b).count("1") <= 2)
        ids: dict[tuple[int, int], int] = {}
        for e, (a, b) in enumerate(EDGES):
            if ((code >> a) & 1) == ((code >> b) & 1):
                continue
            i, o = (a, b) if (code >> a) & 1 else (b, a)
            groups[code, e] = ids.setdefault((comp_in[i], comp_out[o]), len(ids))
        count[code] = len(ids)
    return groups, count


EDGE_GROUP, GROUP_COUNT = _edge_groups()


def _quad_slots() -> np.ndarray:
    """(12,) position 0..3 of a cube in the quad around each of its edges, counter-clockwise seen from the
    edge's +axis side: the cube's offsets (db, dc) along the next two axes (b, c) = (a + 1, a + 2) mod 3 of the
    edge inside it are (0, 0), (1, 0), (1, 1), (0, 1) for positions 0, 1, 2, 3."""
    order = {(0, 0): 0, (1, 0): 1, (1, 1): 2, (0, 1): 3}
    out = np.zeros(12, dtype=np.int64)
    for e, (c0, _) in enumerate(EDGES):
        a = EDGE_AXIS[e]
        out[e] = order[(int(CORNERS[c0, (a + 1) % 3]), int(CORNERS[c0, (a + 2) % 3]))]
    return out


QUAD_SLOT = _quad_slots()


# ---------------------------------------------------------------------------------------------- grid

@dataclasses.dataclass
class Grid:
    """Topology and rest positions of an R^3 cube grid.

    Attributes:
        res: R cubes per side; nodes: (P, 3) float64 rest positions, P = (R + 1)^3, node (i, j, k) at index
        (i (R + 1) + j) (R + 1) + k; cube_corners: (C, 8) int64 node indices (CORNERS order), C = R^3;
        edges: (3 R (R + 1)^2, 2) int64 node pairs of all grid edges; voxel: cube side h.
    """

    res: int
    nodes: np.ndarray
    cube_corners: np.ndarray
    edges: np.ndarray
    voxel: float


def make_grid(res: int, center: np.ndarray, half: float) -> Grid:
    """The grid of `res`^3 cubes over the cube [center - half, center + half]^3."""
    n = res + 1
    ijk = np.stack(np.meshgrid(*(np.arange(n),) * 3, indexing="ij"), -1).reshape(-1, 3)
    h = 2.0 * half / res
    nodes = center - half + ijk * h
    cube = np.stack(np.meshgrid(*(np.arange(res),) * 3, indexing="ij"), -1).reshape(-1, 3)
    corner_ijk = cube[:, None, :] + CORNERS[None]
    corners = (corner_ijk[..., 0] * n + corner_ijk[..., 1]) * n + corner_ijk[..., 2]
    idx = np.arange(n ** 3).reshape(n, n, n)
    edges = np.concatenate([np.stack([np.take(idx, range(0, res), a).ravel(),
                                      np.take(idx, range(1, n), a).ravel()], 1) for a in range(3)])
    return Grid(res, nodes, corners, edges, h)


# ---------------------------------------------------------------------------------------------- extraction

@dataclasses.dataclass
class DualMesh:
    """Output of `extract`: vertices (N, 3) float tensor (dual vertices, then quad centroids when split in
    four), faces (F, 3) int64 tensor, and L_dev (scalar tensor) for the regulariser."""

    verts: object
    faces: object
    dev: object


def extract(grid: Grid, x, s, alpha, beta, gamma, tables: dict, split4: bool) -> DualMesh:
    """The FlexiCubes mesh (module docstring) of node positions x (P, 3), distances s (P,), per-cube
    weights alpha (C, 8), beta (C, 12), gamma (C,) (torch tensors); `tables`: `torch_tables()`."""
    import torch

    corners = tables["cube_corners"]
    code = ((s[corners] < 0).long() << tables["bits"]).sum(1)
    sc = torch.nonzero((code > 0) & (code < 255)).squeeze(1)          # (S,) surface cubes
    if len(sc) == 0:
        return DualMesh(x.new_zeros((0, 3)), torch.zeros((0, 3), dtype=torch.long), x.new_zeros(()))
    cid = corners[sc]                                                   # (S, 8)
    grp = tables["edge_group"][code[sc]]                                # (S, 12)
    cube, edge = torch.nonzero(grp >= 0, as_tuple=True)                 # (E,) crossing entries
    ca, cb = tables["edges"][edge, 0], tables["edges"][edge, 1]
    na, nb = cid[cube, ca], cid[cube, cb]
    sa = s[na] * alpha[sc[cube], ca]
    sb = s[nb] * alpha[sc[cube], cb]
    u = (sa[:, None] * x[nb] - sb[:, None] * x[na]) / (sa - sb)[:, None]  # (E, 3) crossings
    slot = cube * 4 + grp[cube, edge]
    w = beta[sc[cube], edge]
    num = x.new_zeros((len(sc) * 4, 3)).index_add(0, slot, w[:, None] * u)
    den = x.new_zeros(len(sc) * 4).index_add(0, slot, w)
    used = torch.unique(slot)
    remap = torch.full((len(sc) * 4,), -1, dtype=torch.long)
    remap[used] = torch.arange(len(used))
    dual = num[used] / den[used][:, None]                               # (D, 3)
    vid = remap[slot]
    dist = (u - dual[vid]).norm(dim=1)
    cnt = torch.zeros(len(used)).index_add(0, vid, torch.ones(len(vid)))
    mean = x.new_zeros(len(used)).index_add(0, vid, dist) / cnt
    dev = x.new_zeros(len(used)).index_add(0, vid, (dist - mean[vid]).abs()) / cnt

    # Quads: each grid edge's entries from its four cubes (edges on the grid boundary have fewer: dropped).
    key = na * 3 + tables["edge_axis"][edge]
    keys, inv, counts = torch.unique(key, return_inverse=True, return_counts=True)
    quad = torch.full((len(keys), 4), -1, dtype=torch.long)
    quad[inv, tables["quad_slot"][edge]] = vid
    qgamma = x.new_zeros((len(keys), 4))
    qgamma[inv, tables["quad_slot"][edge]] = gamma[sc[cube]]
    start_inside = torch.zeros(len(keys), dtype=torch.bool)
    start_inside[inv] = s[na] < 0
    full = counts == 4
    quad, qgamma, start_inside = quad[full], qgamma[full], start_inside[full]
    quad = torch.where(start_inside[:, None], quad, quad.flip(1))
    qgamma = torch.where(start_inside[:, None], qgamma, qgamma.flip(1))
    return DualMesh(*_triangulate(dual, quad, qgamma, split4), dev.mean())


def _triangulate(dual, quad, qgamma, split4: bool):
    import torch

    if split4:
        centre = (dual[quad] * qgamma[..., None]).sum(1) / qgamma.sum(1, keepdim=True)
        c = torch.arange(len(quad)) + len(dual)
        nxt = quad.roll(-1, dims=1)
        faces = torch.stack([quad, nxt, c[:, None].expand(-1, 4)], -1).reshape(-1, 3)
        return torch.cat([dual, centre]), faces
    diag02 = qgamma[:, 0] * qgamma[:, 2] >= qgamma[:, 1] * qgamma[:, 3]
    a = torch.stack([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]], 1)
    b = torch.stack([quad[:, [1, 2, 3]], quad[:, [1, 3, 0]]], 1)
    return dual, torch.where(diag02[:, None, None], a, b).reshape(-1, 3)


def torch_tables(grid: Grid) -> dict:
    """The lookup tables and the grid's index arrays as torch tensors."""
    import torch

    return {"cube_corners": torch.from_numpy(grid.cube_corners), "bits": torch.arange(8),
            "edge_group": torch.from_numpy(EDGE_GROUP), "edges": torch.from_numpy(EDGES),
            "edge_axis": torch.from_numpy(EDGE_AXIS), "quad_slot": torch.from_numpy(QUAD_SLOT),
            "grid_edges": torch.from_numpy(grid.edges)}


def sign_regularizer(s, grid_edges):
    """Mean binary cross-entropy, over grid edges whose ends differ in sign, of each end's sigmoid(s) against
    the other end's side (the FlexiCubes example's penalty on spurious sign changes)."""
    import torch.nn.functional as F

    pair = s[grid_edges]
    flip = (pair[:, 0] > 0) != (pair[:, 1] > 0)
    if not flip.any():
        return s.new_zeros(())
    a, b = pair[flip, 0], pair[flip, 1]
    return 0.5 * (F.binary_cross_entropy_with_logits(a, (b > 0).float())
                  + F.binary_cross_entropy_with_logits(b, (a > 0).float()))


# ---------------------------------------------------------------------------------------------- method

class FlexiCubes(Method):
    name = "flexicubes"
    input_kind = "multiview"

    def default_config(self) -> dict:
        return {
            "grid": 48,               # cubes per side of the grid
            "pad": 0.1,               # the grid covers the lifted pixels' bounding cube enlarged by this fraction
            "init_radius": 0.6,       # initial sphere radius, as a fraction of the object's half extent
            "steps": 600,             # Adam steps
            "views_per_step": 4,      # random views rendered per step
            "resolution": 128,        # optimised image side in pixels (the capture is area-averaged to it)
            "lr": 0.01,               # Adam learning rate of every parameter (the example's)
            "lambda_depth": 1.0,      # weight of the depth channel's L1 (diffuse 1)
            "lambda_sdf": 0.2,        # sign-change penalty, decaying to a twentieth over the first quarter
            "lambda_dev": 0.5,        # L_dev weight
            "lambda_weights": 0.1,    # weight of the mean |raw weight| (beta, alpha, gamma pre-activation)
            "edge_width": 1.0,        # the soft renderer's edge band, in optimised pixels
            "threads": 1,             # torch threads for the grid arithmetic
            "render_threads": 2,      # native threads of the renderer
        }

    def prepare(self) -> None:
        import dmesh.recon.multiview  # noqa: F401  (torch and the native renderer, before the clock starts)

    def _run(self, inputs: Inputs, cfg: dict, sw: Stopwatch):
        import trimesh

        _check_config(cfg)
        with sw.stage("targets"):
            targets = image_targets(inputs.views, cfg["resolution"], float(cfg["edge_width"]))
        with torch_threads(int(cfg["threads"])):
            verts, faces, info = fit(targets, cfg, int(inputs.seed), sw)
        if len(faces) == 0:
            raise RuntimeError("flexicubes: the fitted signed distances have no zero crossing inside the grid")
        mesh = trimesh.Trimesh(verts, faces, process=False)
        mesh.remove_unreferenced_vertices()
        return mesh, info


def _check_config(cfg: dict) -> None:
    if int(cfg["grid"]) < 4 or int(cfg["steps"]) < 0 or int(cfg["views_per_step"]) < 1:
        raise ValueError(f"flexicubes: need grid >= 4, steps >= 0, views_per_step >= 1; got {cfg['grid']}, "
                         f"{cfg['steps']}, {cfg['views_per_step']}")
    if not 0.0 < float(cfg["init_radius"]) < 1.0 + float(cfg["pad"]):
        raise ValueError(f"flexicubes: init_radius must be in (0, 1 + pad), got {cfg['init_radius']}")


def fit(targets, cfg: dict, seed: int, sw: Stopwatch):
    """Optimise the grid against `targets` (`image_targets`); returns (verts (N, 3) float64, faces (F, 3)
    int64, info) of the final two-triangle extraction."""
    import torch

    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    with sw.stage("init"):
        half = targets.half_extent * (1.0 + float(cfg["pad"]))
        grid = make_grid(int(cfg["grid"]), targets.center, half)
        tables = torch_tables(grid)
        x0 = torch.from_numpy(grid.nodes.astype(np.float32))
        s0 = sphere_sdf(grid.nodes, targets.center, float(cfg["init_radius"]) * targets.half_extent)
        sdf = torch.tensor(s0, dtype=torch.float32, requires_grad=True)
        deform = torch.zeros((len(x0), 3), requires_grad=True)
        weight = torch.zeros((len(grid.cube_corners), 21), requires_grad=True)
        opt = torch.optim.Adam([sdf, deform, weight], lr=float(cfg["lr"]))
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 10.0 ** (-k / 5000.0))
    steps, batch = int(cfg["steps"]), min(int(cfg["views_per_step"]), targets.views)

    def params():
        x = x0 + (0.5 * grid.voxel * (1.0 - 1e-3)) * torch.tanh(deform)
        beta = 1.0 + 0.99 * torch.tanh(weight[:, :12])
        alpha = 1.0 + 0.99 * torch.tanh(weight[:, 12:20])
        gamma = 0.005 + 0.99 * torch.sigmoid(weight[:, 20])
        return x, alpha, beta, gamma

    history = []
    for step in range(steps):
        with sw.stage("extract"):
            x, alpha, beta, gamma = params()
            mesh = extract(grid, x, sdf, alpha, beta, gamma, tables, split4=True)
        if len(mesh.faces) == 0:
            raise RuntimeError(f"flexicubes: the surface vanished at step {step} (no sign change left in the grid)")
        with sw.stage("render"):
            ids = rng.choice(targets.views, batch, replace=False)
            img = image_loss(mesh.verts, mesh.faces, targets, ids, edge_width=float(cfg["edge_width"]),
                             lambda_depth=float(cfg["lambda_depth"]), num_threads=int(cfg["render_threads"]))
        with sw.stage("backward"):
            t = step / max(1, steps)
            w_sdf = float(cfg["lambda_sdf"]) * (1.0 - (1.0 - 1.0 / 20.0) * min(1.0, 4.0 * t))
            reg = (w_sdf * sign_regularizer(sdf, tables["grid_edges"]) + float(cfg["lambda_dev"]) * mesh.dev
                   + float(cfg["lambda_weights"]) * weight.abs().mean())
            loss = img + reg
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        history.append(float(img.detach()))
    with sw.stage("extract"), torch.no_grad():
        x, alpha, beta, gamma = params()
        mesh = extract(grid, x, sdf, alpha, beta, gamma, tables, split4=False)
    info = {"grid": grid.res, "voxel": grid.voxel, "steps": steps, "views_per_step": batch,
            "image_loss_first": history[0] if history else None, "image_loss_last": history[-1] if history else None}
    return mesh.verts.double().numpy(), mesh.faces.numpy(), info


__all__ = ["FlexiCubes", "EDGE_GROUP", "GROUP_COUNT", "extract", "make_grid"]
