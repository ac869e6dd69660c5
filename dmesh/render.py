"""CPU differentiable renderers of semi-transparent triangles (DESIGN.md section 7).

Letters: N vertices, F faces, T tets, V views, H x W pixels.

Cameras, rays and pixels follow `dmesh.camera` (the conventions of the ground-truth capture,
`datasets/capture.py`): an OpenGL `Camera` looking down -Z, each pixel sampling the ray through its centre.
Outputs per pixel: diffuse = |n_f . d| (flat unit face normal, unit ray: two-sided Lambert with a
headlight, albedo 1), depth = -z_cam of the surface, alpha = coverage; background 0 in all three.

- `soft_render` (phase 1): every face with opacity > `min_opacity` is a triangle of alpha
  opacity * coverage, where the coverage is 1 inside the projected triangle and falls smoothly
  (smoothstep) to 0 at `edge_width` pixels outside it. Fragments are composited front to back in
  per-pixel depth order (C += c a T, T *= 1 - a, stop when T < t_min), exact per pixel rather than one
  depth per face: the key is the depth of the face's plane at the pixel (clamped to the face's depth
  range), pushed back by the face's depth extent for soft-band fragments so that the face covering a
  pixel centre precedes its neighbours' bands. Depth is composited the same way
  and NOT normalised by alpha (sum of a T z; for an opaque surface it is the surface depth, at a soft
  silhouette it fades to 0 like the capture's background). Gradients reach vertex positions (through
  coverage, i.e. silhouettes, the depth of the hit and the face normal) and face opacities.
  Because the soft band lies outside the triangles, an opaque closed mesh renders without cracks along
  its inner edges and matches a hard rasteriser except within `edge_width` pixels of an edge: inner
  edges blend two neighbouring faces, silhouettes grow by edge_width / 2 pixel on average.
- `tet_render` (phase 2): each ray walks a fixed tetrahedralisation from its first hull face and
  composites every face it crosses with alpha = opacity, in exact order; gradients reach opacities only.

The native kernels are in `native/src/soft_render.h` and `native/src/tet_render.h`; the naive reference
(the same model, per pixel in torch) is `dmesh.reference.render`. Both renderers work on one view per
call with `num_threads` native threads; the soft renderer keeps its largest work arrays (about 350 bytes
per face for the forward, 500 for the backward) per calling thread between calls, to avoid page faults.
"""
from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from dmesh import native
from dmesh.camera import FOV_Y_DEGREES, Camera  # noqa: F401 - re-exported (the renderers' camera)

log = logging.getLogger(__name__)

__all__ = ["Camera", "soft_render", "soft_render_views", "tet_render", "tet_render_views", "FOV_Y_DEGREES"]

def _threads(num_threads: int | None) -> int:
    return int(num_threads) if num_threads else max(1, torch.get_num_threads())


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy()


def _check_common(verts: torch.Tensor, faces: torch.Tensor, opacity: torch.Tensor, camera: Camera, fn: str):
    # The value checks run in NumPy: torch's elementwise reductions cost tens of ms here on 2e5 faces.
    if not isinstance(camera, Camera):
        raise TypeError(f"{fn}: camera must be a dmesh.render.Camera, got {type(camera).__name__}")
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"{fn}: verts must have shape (N, 3), got {tuple(verts.shape)}")
    if not verts.dtype.is_floating_point:
        raise TypeError(f"{fn}: verts must be a float tensor, got {verts.dtype}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{fn}: faces must have shape (F, 3), got {tuple(faces.shape)}")
    if faces.dtype.is_floating_point or faces.dtype == torch.bool:
        raise TypeError(f"{fn}: faces must be an integer tensor, got {faces.dtype}")
    if opacity.shape != (faces.shape[0],):
        raise ValueError(f"{fn}: opacity must have shape ({faces.shape[0]},), got {tuple(opacity.shape)}")
    f, o = _np(faces), _np(opacity)
    if f.size and (int(f.min()) < 0 or int(f.max()) >= len(verts)):
        raise ValueError(f"{fn}: faces must index verts in [0, {len(verts)}), got values in "
                         f"[{int(f.min())}, {int(f.max())}]")
    if o.size and not (o.min() >= 0 and o.max() <= 1):
        raise ValueError(f"{fn}: opacity must lie in [0, 1] (got min {float(o.min()):.4g}, "
                         f"max {float(o.max()):.4g})")
    if not np.isfinite(_np(verts)).all():
        raise ValueError(f"{fn}: verts must be finite")


def _check_settings(min_opacity: float, t_min: float, fn: str):
    if not 0.0 <= min_opacity < 1.0:
        raise ValueError(f"{fn}: min_opacity must be in [0, 1), got {min_opacity}")
    if not 0.0 < t_min < 1.0:
        raise ValueError(f"{fn}: t_min must be in (0, 1), got {t_min}")


def _as_tensor(x, dtype=None) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x), dtype=dtype)


def _images(raw) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A native forward's (diffuse, depth, alpha) images as tensors."""
    return torch.from_numpy(raw.diffuse), torch.from_numpy(raw.depth), torch.from_numpy(raw.alpha)


def _output_grads(shape: tuple[int, int], grads) -> list[torch.Tensor]:
    """The gradients of (diffuse, depth, alpha) as float32 images, zeros for an unused output."""
    zero = torch.zeros(shape, dtype=torch.float32)
    return [zero if x is None else x.float() for x in grads]


class _SoftRasterize(torch.autograd.Function):
    """Soft tile rasteriser: (verts, opacity) -> (diffuse, depth, alpha); native forward/backward pair."""

    @staticmethod
    def forward(ctx, verts, opacity, faces, camera, settings):
        # settings = (edge_width, min_opacity, t_min, num_threads)
        raw = native.soft_render_forward(verts, faces, opacity, *camera.native_args(), *settings)
        ctx.camera, ctx.settings, ctx.stats = camera, settings, raw.stats
        ctx.save_for_backward(verts, opacity, faces, torch.from_numpy(raw.frag_face),
                              torch.from_numpy(raw.pix_range))
        return _images(raw)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_diffuse, g_depth, g_alpha):
        verts, opacity, faces, frag_face, pix_range = ctx.saved_tensors
        g = _output_grads((ctx.camera.height, ctx.camera.width), (g_diffuse, g_depth, g_alpha))
        gv, go = native.soft_render_backward(verts, faces, opacity, *ctx.camera.native_args(), *ctx.settings,
                                             frag_face, pix_range, *g)
        grad_verts = torch.from_numpy(gv).to(verts.dtype) if ctx.needs_input_grad[0] else None
        grad_opacity = torch.from_numpy(go).to(opacity.dtype) if ctx.needs_input_grad[1] else None
        # one gradient per forward input: verts, opacity, faces, camera, settings
        return grad_verts, grad_opacity, None, None, None


def soft_render(verts, faces, opacity, camera: Camera, *, edge_width: float = 1.0, min_opacity: float = 1e-3,
                t_min: float = 1e-4, num_threads: int | None = None) -> dict[str, torch.Tensor]:
    """Renders semi-transparent triangles with soft edges (module docstring), differentiably.

    Args:
        verts: (N, 3) float tensor (or array), world space; computed in float32 by the kernel, gradients
            come back in verts' dtype.
        faces: (F, 3) integer tensor, indices into verts (any winding: shading is two-sided).
        opacity: (F,) float tensor in [0, 1], each face's opacity (the face probability Lambda).
        camera: the view.
        edge_width: width in pixels of the soft band outside each projected triangle, > 0.
        min_opacity: faces with opacity <= this are neither drawn nor differentiated.
        t_min: a pixel stops compositing once its transmittance falls below this.
        num_threads: native threads (default torch.get_num_threads()).

    Returns:
        dict with "diffuse", "depth", "alpha": (H, W) float32 tensors, differentiable with respect to
        verts and opacity. Depth is -z_cam composited as sum a T z (not divided by alpha).

    Example:
        >>> import torch; from dmesh.render import Camera, soft_render
        >>> from dmesh.camera import look_at
        >>> cam = Camera(look_at((0.0, 0.0, 2.0)), height=32, width=32)
        >>> v = torch.tensor([[-.5, -.5, 0.], [.5, -.5, 0.], [0., .5, 0.]], requires_grad=True)
        >>> out = soft_render(v, torch.tensor([[0, 1, 2]]), torch.tensor([0.8]), cam)
        >>> out["alpha"].sum().backward()
    """
    verts, faces, opacity = _as_tensor(verts), _as_tensor(faces), _as_tensor(opacity)
    _check_common(verts, faces, opacity, camera, "soft_render")
    _check_settings(min_opacity, t_min, "soft_render")
    if not edge_width > 0.0:
        raise ValueError(f"soft_render: edge_width must be positive, got {edge_width}")
    settings = (float(edge_width), float(min_opacity), float(t_min), _threads(num_threads))
    d, z, a = _SoftRasterize.apply(verts, opacity, faces.detach(), camera, settings)
    return {"diffuse": d, "depth": z, "alpha": a}


def _stack_views(outs: list[dict]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([o[k] for o in outs]) for k in ("diffuse", "depth", "alpha")}


def soft_render_views(verts, faces, opacity, cameras: Sequence[Camera], **kwargs) -> dict[str, torch.Tensor]:
    """`soft_render` over several views: dict of (V, H, W) float32 tensors (all cameras the same size)."""
    if not cameras:
        raise ValueError("soft_render_views: no cameras")
    return _stack_views([soft_render(verts, faces, opacity, c, **kwargs) for c in cameras])


class _TetRasterize(torch.autograd.Function):
    """Tetrahedral walk renderer: opacity -> (diffuse, depth, alpha); gradients to opacity only."""

    @staticmethod
    def forward(ctx, opacity, verts, tets, faces, face_tets, camera, settings):
        # settings = (min_opacity, t_min, num_threads)
        raw = native.tet_render_forward(verts, tets, faces, face_tets, opacity, *camera.native_args(), *settings)
        ctx.shape, ctx.num_threads, ctx.stats = (camera.height, camera.width), settings[2], raw.stats
        ctx.save_for_backward(opacity, torch.from_numpy(raw.frag_face), torch.from_numpy(raw.frag_diffuse),
                              torch.from_numpy(raw.frag_depth), torch.from_numpy(raw.pix_range))
        return _images(raw)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_diffuse, g_depth, g_alpha):
        opacity, frag_face, frag_diffuse, frag_depth, pix_range = ctx.saved_tensors
        g = _output_grads(ctx.shape, (g_diffuse, g_depth, g_alpha))
        go = native.tet_render_backward(opacity, frag_face, frag_diffuse, frag_depth, pix_range, *g,
                                        ctx.num_threads)
        # one gradient per forward input: opacity, verts, tets, faces, face_tets, camera, settings
        return torch.from_numpy(go).to(opacity.dtype), None, None, None, None, None, None


def tet_render(verts, tets, faces, face_tets, opacity, camera: Camera, *, min_opacity: float = 1e-3,
               t_min: float = 1e-4, num_threads: int | None = None) -> dict[str, torch.Tensor]:
    """Renders the faces of a fixed tetrahedralisation by walking each pixel ray through it (module docstring).

    Args:
        verts: (N, 3) float tensor or array, world space (no gradient).
        tets: (T, 4) integer, indices into verts.
        faces: (F, 3) integer, every face of the tets once (e.g. `dmesh.wdt.PowerDiagram.faces`).
        face_tets: (F, 2) integer, the two tets of each face, -1 second for a convex-hull face
            (`PowerDiagram.face_tets`).
        opacity: (F,) float tensor in [0, 1]; faces with opacity <= min_opacity are crossed but not drawn.
        camera: the view; it must lie outside the convex hull of the tets (ValueError otherwise).
        min_opacity, t_min, num_threads: as in `soft_render`.

    Returns:
        dict with "diffuse", "depth", "alpha": (H, W) float32 tensors, differentiable with respect to
        opacity only. Depth is composited as sum a T z (not divided by alpha).
    """
    verts, tets, faces = _as_tensor(verts), _as_tensor(tets), _as_tensor(faces)
    face_tets, opacity = _as_tensor(face_tets), _as_tensor(opacity)
    _check_common(verts, faces, opacity, camera, "tet_render")
    _check_settings(min_opacity, t_min, "tet_render")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tet_render: tets must have shape (T, 4), got {tuple(tets.shape)}")
    if face_tets.shape != (faces.shape[0], 2):
        raise ValueError(f"tet_render: face_tets must have shape ({faces.shape[0]}, 2), got "
                         f"{tuple(face_tets.shape)}")
    settings = (float(min_opacity), float(t_min), _threads(num_threads))
    d, z, a = _TetRasterize.apply(opacity, verts.detach(), tets.detach(), faces.detach(), face_tets.detach(),
                                  camera, settings)
    return {"diffuse": d, "depth": z, "alpha": a}


def tet_render_views(verts, tets, faces, face_tets, opacity, cameras: Sequence[Camera],
                     **kwargs) -> dict[str, torch.Tensor]:
    """`tet_render` over several views: dict of (V, H, W) float32 tensors."""
    if not cameras:
        raise ValueError("tet_render_views: no cameras")
    return _stack_views([tet_render(verts, tets, faces, face_tets, opacity, c, **kwargs) for c in cameras])
