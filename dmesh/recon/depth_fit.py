"""A mesh's vertices moved along their normals to fit captured depth maps (not upstream; the multi-view
`fast` preset's last stage, `MultiViewConfig.depth_fit`).

Letters: N vertices, F faces, S samples per face, V views, H x H pixels.

Why: the image-loss optimisation ends with its surface a little inside the object (each epoch re-seeds from
the previous epoch's flat faces, and its steps do not undo the shrink; docs/preset_choices_multiview.md), so the
extracted mesh's flat faces sit below the surface the depth maps saw. One linear least-squares solve moves
every vertex along its normal so that the faces straddle that surface.

The fit (a Gauss-Newton step of the squared depth residual on the mesh):
1. `samples_per_face` seeded uniform points on every face, each at barycentric weights b over its corners.
2. Every sample projected into every view: where it lands on mask pixels (bilinear depth of the 4 pixels
   around it, all in the mask), the captured depth D differs from its own depth z by less than
   `tolerance`, and the view sees the face at least at `min_cos` (its normal n against the view ray d:
   |n . d| > min_cos, either side, so the winding does not matter), the captured surface point along that
   ray is (D - z) / (d . a) further along d (a: the camera's axis), which is delta = (D - z) (n . d) / (d . a)
   along n. Occluded samples fail the depth test.
3. delta per sample: the mean over its views weighted by (n . d)^2 (grazing views say least).
4. Vertex offsets x (N,) along the vertex normal axes m (`dmesh.sampling.vertex_axes`, sign-free) minimise
   sum_s (sum_i b_si (m_i . n_s) x_i - delta_s)^2 + damp^2 |x|^2 (`scipy.sparse.linalg.lsqr`), each clipped to
   `max_offset`. The factor m_i . n_s carries the sign, so the faces' winding does not matter.
5. With `uncross`: the offsets of the vertices of faces that the fit made cross others shrink until they
   no longer cross (`undo_crossings`), so the fit adds no self-intersection.

Topology and winding are unchanged. Vertices no sample constrains stay where they are (the damping holds
them). Copies of one point (`groups`: the surface step splits a vertex where sheets meet into one copy per
sheet, 5 % of an edge apart, `dmesh.surface.finish.separate_copies`) share one offset along one axis, that of
the mesh with the copies joined: fitted one by one, each moved along its own sheet's normal, up to `max_offset`,
far more than the copies' separation, and the sheets that met there crossed each other
(`python -m studies depth_fit_copies`). Written here because no mesh library offers a least-squares fit
of a mesh to depth maps.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmesh.camera import focal_length, to_pixels, transform_points
from dmesh.sampling import vertex_axes
from dmesh.tolerances import FLOAT64_FLOOR


@dataclass(frozen=True)
class DepthFitConfig:
    """Settings of `fit_to_depth` (lengths in the frame of the mesh and the depth maps)."""

    samples_per_face: int = 12   # seeded points per face whose depth residuals are fitted
    tolerance: float = 0.02      # residuals beyond it are occlusions or other surfaces, not this one
    min_cos: float = 0.2         # views see a face at least this steeply (either side)
    damp: float = 0.05           # Tikhonov damping of the offsets (lsqr's `damp`)
    smooth: float = 0.3          # weight of the offsets' differences along the edges
    max_offset: float = 0.01     # offsets are clipped to this
    uncross: bool = True         # offsets that make faces cross shrink (`undo_crossings`)
    seed: int = 0

    def __post_init__(self):
        if self.samples_per_face < 1:
            raise ValueError(f"DepthFitConfig.samples_per_face must be >= 1, got {self.samples_per_face}")
        for name in ("tolerance", "max_offset"):
            if not getattr(self, name) > 0:
                raise ValueError(f"DepthFitConfig.{name} must be positive, got {getattr(self, name)}")
        if not 0 <= self.min_cos < 1:
            raise ValueError(f"DepthFitConfig.min_cos must be in [0, 1), got {self.min_cos}")
        for name in ("damp", "smooth"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"DepthFitConfig.{name} must be >= 0, got {getattr(self, name)}")


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) unit face normals (`dmesh.geometry.face_normals`) of NumPy arrays."""
    import torch

    from dmesh.geometry import face_normals

    return face_normals(torch.from_numpy(vertices), torch.from_numpy(faces)).numpy()


def depth_residuals(points: np.ndarray, normals: np.ndarray, world_to_camera: np.ndarray, fov_y_degrees: float,
                    depth: np.ndarray, mask: np.ndarray, cfg: DepthFitConfig) -> np.ndarray:
    """(P,) offsets along `normals` from `points` to the captured surface (procedure steps 2-3 of the module
    docstring); NaN where no view measures one.

    Args:
        points, normals: (P, 3); world_to_camera: (V, 4, 4); depth, mask: (V, H, H) captured depth (-z_cam,
        in the points' units) and coverage.
    """
    h = depth.shape[1]
    focal = focal_length(fov_y_degrees, h)
    cam_to_world = np.linalg.inv(world_to_camera)
    num, den = np.zeros(len(points)), np.zeros(len(points))
    for k in range(len(world_to_camera)):
        x = transform_points(points, world_to_camera[k])
        z = -x[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = to_pixels(x[:, 0], x[:, 1], z, focal, h, h)
            u0, v0 = np.floor(u - 0.5), np.floor(v - 0.5)  # the 4 pixel centres around (u, v)
        idx = np.flatnonzero((z > 0) & (u0 >= 0) & (u0 < h - 1) & (v0 >= 0) & (v0 < h - 1))
        if len(idx) == 0:
            continue
        i0, j0 = v0[idx].astype(np.int64), u0[idx].astype(np.int64)
        a, b = u[idx] - 0.5 - j0, v[idx] - 0.5 - i0
        seen_depth = np.zeros(len(idx))
        covered = np.ones(len(idx), bool)
        for di, dj, w in ((0, 0, (1 - a) * (1 - b)), (0, 1, a * (1 - b)), (1, 0, (1 - a) * b), (1, 1, a * b)):
            seen_depth += w * depth[k, i0 + di, j0 + dj]
            covered &= mask[k, i0 + di, j0 + dj]
        r = seen_depth - z[idx]
        ray = points[idx] - cam_to_world[k, :3, 3]
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), FLOAT64_FLOOR)
        nd = (ray * normals[idx]).sum(1)
        da = ray @ -cam_to_world[k, :3, 2]  # the camera looks down its -Z axis
        good = covered & (np.abs(r) < cfg.tolerance) & (np.abs(nd) > cfg.min_cos) & (da > 0)
        g = idx[good]
        w = nd[good] ** 2
        np.add.at(num, g, w * r[good] * nd[good] / da[good])
        np.add.at(den, g, w)
    out = np.full(len(points), np.nan)
    seen = den > 0
    out[seen] = num[seen] / den[seen]
    return out


def fit_to_depth(vertices, faces, world_to_camera, fov_y_degrees: float, depth, mask,
                 cfg: DepthFitConfig | None = None, groups=None) -> tuple[np.ndarray, dict]:
    """The mesh's vertices moved along their normals to fit the depth maps (module docstring).

    Args:
        vertices: (N, 3) floats; faces: (F, 3) ints; world_to_camera: (V, 4, 4); fov_y_degrees: the views'
            field of view; depth, mask: (V, H, H) captured depth (-z_cam, in the vertices' units) and coverage.
        cfg: `DepthFitConfig` (None: defaults).
        groups: (N,) ints or None. Vertices with one group id (copies of one point) move by one offset along
            one axis, so they keep their distances; None: every vertex on its own.
    Returns:
        (new (N, 3) float64 vertices, info {"fit_samples": share of samples some view measured,
        "median_offset": median |offset| of the moved vertices, "moved": vertices moved, "held_back":
        vertices held back by `undo_crossings`}).
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.linalg import lsqr

    cfg = cfg or DepthFitConfig()
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return v.copy(), {"fit_samples": 0.0, "median_offset": 0.0, "moved": 0}
    s = int(cfg.samples_per_face)
    rng = np.random.default_rng(cfg.seed)
    uv = rng.random((len(f), s, 2))
    fold = uv.sum(2) > 1.0
    uv[fold] = 1.0 - uv[fold]
    bary = np.concatenate([1.0 - uv.sum(2, keepdims=True), uv], 2)          # (F, S, 3)
    fn = _face_normals(v, f)
    points = np.einsum("fsk,fkd->fsd", bary, v[f]).reshape(-1, 3)
    delta = depth_residuals(points, np.repeat(fn, s, 0), np.asarray(world_to_camera, np.float64),
                            fov_y_degrees, np.asarray(depth, np.float64), np.asarray(mask, bool), cfg)
    measured = np.isfinite(delta)
    if not measured.any():
        return v.copy(), {"fit_samples": 0.0, "median_offset": 0.0, "moved": 0}
    if groups is None:
        g, n = np.arange(len(v)), len(v)
    else:
        g = np.asarray(groups).reshape(-1)
        if len(g) != len(v):
            raise ValueError(f"fit_to_depth: groups has {len(g)} entries for {len(v)} vertices")
        _, g = np.unique(g, return_inverse=True)
        n = int(g.max()) + 1
    fg = g[f]                                                               # the faces over the joined copies
    joined = np.stack([np.bincount(g, v[:, k], n) for k in range(3)], 1) / np.bincount(g, minlength=n)[:, None]
    vn = vertex_axes(joined, fg, smooth=0.0)                                # sign-free vertex normal axes
    along = np.einsum("fkd,fd->fk", vn[fg], fn)                             # (F, 3): m_i . n of each corner
    coef = (bary * along[:, None, :]).reshape(-1, 3)[measured]
    m = int(measured.sum())
    edges = np.unique(np.sort(np.concatenate([fg[:, [0, 1]], fg[:, [1, 2]], fg[:, [2, 0]]]), 1), axis=0)
    rows = np.concatenate([np.repeat(np.arange(m), 3), np.repeat(m + np.arange(len(edges)), 2)])
    cols = np.concatenate([np.repeat(fg, s, 0)[measured].reshape(-1), edges.reshape(-1)])
    vals = np.concatenate([coef.reshape(-1), np.tile([cfg.smooth, -cfg.smooth], len(edges))])
    a = csr_matrix((vals, (rows, cols)), shape=(m + len(edges), n))
    x = lsqr(a, np.concatenate([delta[measured], np.zeros(len(edges))]), damp=cfg.damp)[0]
    x = np.clip(x, -cfg.max_offset, cfg.max_offset)
    held_back = undo_crossings(v, f, x, vn, g) if cfg.uncross else 0
    moved = np.abs(x) > 0
    info = {"fit_samples": float(measured.mean()),
            "median_offset": float(np.median(np.abs(x[moved]))) if moved.any() else 0.0,
            "moved": int(moved[g].sum()), "held_back": held_back}
    return v + (x[:, None] * vn)[g], info


def undo_crossings(vertices: np.ndarray, faces: np.ndarray, x: np.ndarray, axes: np.ndarray,
                   groups: np.ndarray) -> int:
    """Halves, in place, the offsets `x` (one per group, along `axes`) of the vertices of every face that
    crosses another after the fit but not before (`dmesh.surface.crossings.FaceIndex`, pairs as MeshLab counts them),
    round after round until the fit has made no crossing; returns how many vertices were held back.

    Why: a copy group moves rigidly, but the other vertices of the tiny pieces that meet at it do not, so a
    fit of up to `max_offset` can push one piece through its neighbour where the mesh was folded tight.
    Halving keeps as much of the fit as the crossing allows (`python -m studies depth_fit_copies`); an
    offset below 1e-3 of the largest becomes 0. Each round
    shrinks a moved vertex of every new crossing pair (a pair that did not cross with no vertex moved has
    one), so the loop ends, at worst at the unfitted mesh."""
    from dmesh.surface.crossings import FaceIndex

    before = FaceIndex(vertices, faces).crossing(faces)
    held = np.zeros(0, np.int64)
    while True:
        now = vertices + (x[:, None] * axes)[groups]
        bad = FaceIndex(now, faces).crossing(faces) & ~before
        back = np.unique(groups[faces[bad]])
        back = back[x[back] != 0]
        if len(back) == 0:
            return int(np.isin(groups, held).sum())
        x[back] *= 0.5
        x[back[np.abs(x[back]) < 1e-3 * np.abs(x).max(initial=0.0)]] = 0.0
        held = np.union1d(held, back)


__all__ = ["DepthFitConfig", "fit_to_depth", "depth_residuals", "undo_crossings"]
