"""Naive per-pixel references of the renderers in `dmesh.render` (torch, float64, autograd).

Letters: N vertices, F faces, H x W pixels, P = H W pixels.

`soft_render_naive` evaluates the soft renderer's model (native/src/soft_render.h) for every pixel and
every face, sorts each pixel's fragments by (sort key, face id) and composites them; no tiles, no priority
queue. Written in differentiable torch, so its autograd gradients are an independent check of the native
backward. `tet_render_naive` intersects every pixel ray with every face and composites the crossings in
depth order, which is what the tetrahedral walk computes without the walk. Both cost O(P F): small
scenes only.
"""
from __future__ import annotations

import torch

from dmesh.camera import Camera, to_pixels, transform_points


def _camera_space(verts: torch.Tensor, camera: Camera) -> torch.Tensor:
    return transform_points(verts.to(torch.float64), torch.as_tensor(camera.world_to_camera, dtype=torch.float64))


def _rays(camera: Camera) -> torch.Tensor:
    return torch.as_tensor(camera.rays(), dtype=torch.float64).reshape(-1, 3)


def _images(out: dict, camera: Camera) -> dict:
    """The per-chunk pixel values of `out` as (H, W) images."""
    shape = (camera.height, camera.width)
    return {k: torch.cat(v).reshape(shape) for k, v in out.items()}


def _append(out: dict, values) -> None:
    for key, value in zip(("diffuse", "depth", "alpha"), values):
        out[key].append(value)


def _composite(key, a, c, z, t_min: float):
    """Per pixel (rows), sort fragments by (key, face id) and composite front to back.

    key, a, c, z: (P, F); face ids are the column order, so a stable sort by key breaks ties by id.
    """
    order = torch.sort(key.detach(), dim=1, stable=True).indices
    a, c, z = (torch.gather(x, 1, order) for x in (a, c, z))
    one_minus = 1.0 - a
    trans = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), one_minus[:, :-1]], 1), 1)
    include = (trans.detach() >= t_min).to(a.dtype)  # a fragment is composited iff T before it >= t_min
    w = a * trans * include
    return (w * c).sum(1), (w * z).sum(1), w.sum(1)


def soft_render_naive(verts, faces, opacity, camera: Camera, *, edge_width: float = 1.0,
                      min_opacity: float = 1e-3, t_min: float = 1e-4, chunk: int = 4096) -> dict:
    """The soft renderer's model, evaluated naively (see `dmesh.render.soft_render`).

    Args:
        verts: (N, 3) float tensor, world space (float64 inside; gradients flow through autograd).
        faces: (F, 3) integer tensor.
        opacity: (F,) float tensor in [0, 1].
        camera, edge_width, min_opacity, t_min: as in `soft_render`.
        chunk: pixels per batch (memory is O(chunk F)).

    Returns:
        dict of "diffuse", "depth", "alpha": (H, W) float64 tensors.
    """
    faces = torch.as_tensor(faces, dtype=torch.long)
    opacity = torch.as_tensor(opacity).to(torch.float64)
    P = _camera_space(torch.as_tensor(verts), camera)
    tri = P[faces]                                           # (F, 3, 3)
    vdepth = -tri[..., 2]                                    # (F, 3)
    drawn = (opacity > min_opacity) & (vdepth >= camera.near).all(1)
    safe = torch.where(drawn[:, None], vdepth, torch.ones_like(vdepth))
    # (F, 3, 2) pixel coordinates of the corners
    q = torch.stack(to_pixels(tri[..., 0], tri[..., 1], safe, camera.focal, camera.width, camera.height), -1)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = torch.cross(e1, e2, dim=1)                                                    # (F, 3)
    degenerate = n.norm(dim=1) <= 1e-12 * e1.norm(dim=1) * e2.norm(dim=1)             # no normal: c 0, z zmax
    n = torch.where(degenerate[:, None], torch.zeros_like(n), n)
    nlen = n.norm(dim=1)
    num = (n * tri[:, 0]).sum(1)
    zmin, zmax = vdepth.min(1).values, vdepth.max(1).values
    e = torch.roll(q, -1, dims=1) - q                                                 # edges a -> b
    area2 = e[:, 0, 0] * e[:, 1, 1] - e[:, 0, 1] * e[:, 1, 0]
    sgn = torch.where(area2 >= 0, 1.0, -1.0).to(torch.float64)
    elen = e.norm(dim=2)                                                              # (F, 3)

    rays = _rays(camera)
    jj = torch.arange(camera.width, dtype=torch.float64) + 0.5
    ii = torch.arange(camera.height, dtype=torch.float64) + 0.5
    pix = torch.stack(torch.meshgrid(ii, jj, indexing="ij")[::-1], -1).reshape(-1, 2)  # (P, 2) = (u, v)
    out = {k: [] for k in ("diffuse", "depth", "alpha")}
    w = float(edge_width)
    for s in range(0, len(pix), chunk):
        p = pix[s:s + chunk][:, None, None, :]                                        # (p, 1, 1, 2)
        d = rays[s:s + chunk]                                                         # (p, 3)
        rel = p - q[None]                                                             # (p, F, 3, 2)
        cross = e[None, ..., 0] * rel[..., 1] - e[None, ..., 1] * rel[..., 0]         # (p, F, 3)
        sd = sgn[None, :, None] * cross / torch.where(elen > 0, elen, torch.ones_like(elen))[None]
        sd = torch.where(elen[None] > 0, sd, torch.full_like(sd, float("inf")))
        inside = (sd >= 0).all(2) & (area2 != 0)[None]
        l2 = (e * e).sum(2)[None]
        t = ((rel * e[None]).sum(3) / torch.where(l2 > 0, l2, torch.ones_like(l2))).clamp(0.0, 1.0)
        r = rel - t[..., None] * e[None]
        d2 = (r * r).sum(3).min(2).values
        dist = torch.sqrt(d2.clamp_min(1e-30))
        sv = (1.0 - dist / w).clamp(0.0, 1.0)
        cov = torch.where(inside, torch.ones_like(sv), sv * sv * (3.0 - 2.0 * sv))
        cov = torch.where(drawn[None] & ((sd > -w).all(2) | inside), cov, torch.zeros_like(cov))
        a = opacity[None] * cov
        den = d @ n.T                                                                  # (p, F)
        zr = num[None] / torch.where(den != 0, den, torch.ones_like(den))
        zr = torch.where((den != 0) & torch.isfinite(zr), zr, zmax[None].expand_as(zr))
        z = torch.where(zr < zmin[None], zmin[None].expand_as(zr), torch.where(zr > zmax[None], zmax[None], zr))
        dlen = d.norm(dim=1, keepdim=True)
        c = torch.where(nlen[None] > 0, den.abs() / (torch.where(nlen > 0, nlen, torch.ones_like(nlen))[None] * dlen),
                        torch.zeros_like(den))
        key = torch.where(cov < 1.0, z + (zmax - zmin)[None], z)  # band fragments sort one depth extent back
        z_sort = torch.where(a > 0, key, torch.full_like(z, float("inf")))
        _append(out, _composite(z_sort, a, c, z, t_min))
    return _images(out, camera)


def tet_render_naive(verts, faces, opacity, camera: Camera, *, min_opacity: float = 1e-3,
                     t_min: float = 1e-4, chunk: int = 4096) -> dict:
    """Every face a pixel ray crosses, composited in depth order with alpha = opacity (hard, no coverage).

    For the faces of a tetrahedralisation, seen from outside its convex hull, this is what
    `dmesh.render.tet_render` computes by walking. Args as in `soft_render_naive` (faces (F, 3), opacity
    (F,)); returns (H, W) float64 "diffuse", "depth", "alpha", differentiable with respect to opacity.
    """
    faces = torch.as_tensor(faces, dtype=torch.long)
    opacity = torch.as_tensor(opacity).to(torch.float64)
    P = _camera_space(torch.as_tensor(verts), camera).detach()
    tri = P[faces]
    a0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = torch.cross(e1, e2, dim=1)
    nlen = n.norm(dim=1)
    rays = _rays(camera)
    out = {k: [] for k in ("diffuse", "depth", "alpha")}
    for s in range(0, len(rays), chunk):
        d = rays[s:s + chunk]                                     # (p, 3)
        pv = torch.cross(d[:, None].expand(-1, len(faces), -1), e2[None].expand(len(d), -1, -1), dim=2)
        det = (e1[None] * pv).sum(2)
        ok = det != 0
        inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
        tv = -a0[None]
        bu = (tv * pv).sum(2) * inv
        qv = torch.cross(tv.expand(len(d), -1, -1), e1[None].expand(len(d), -1, -1), dim=2)
        bv = (d[:, None] * qv).sum(2) * inv
        depth = (e2[None] * qv).sum(2) * inv
        hit = ok & (bu >= -1e-12) & (bv >= -1e-12) & (bu + bv <= 1 + 1e-12) & (depth > 0)
        a = torch.where(hit & (opacity[None] > min_opacity), opacity[None].expand_as(depth), torch.zeros_like(depth))
        c = (d @ n.T).abs() / (torch.where(nlen > 0, nlen, torch.ones_like(nlen))[None] * d.norm(dim=1, keepdim=True))
        z_sort = torch.where(a > 0, depth, torch.full_like(depth, float("inf")))
        _append(out, _composite(z_sort, a, c, depth, t_min))
    return _images(out, camera)
