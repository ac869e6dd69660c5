"""Tests of the CPU renderers (dmesh.render) against the naive reference, finite differences, the
ground-truth capture and each other. Scenes are tiny (<= 64x64 pixels) to keep the file under a minute.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from datasets.capture import camera_rig, look_at
from datasets.capture import gl_problem as _gl_problem
from dmesh import native
from dmesh.reference.render import soft_render_naive, tet_render_naive
from dmesh.render import Camera, soft_render, soft_render_views, tet_render, tet_render_views
from common import assert_close

OUTPUTS = ("diffuse", "depth", "alpha")


def _camera(res: int = 32, eye=(0.3, 0.4, 2.0)) -> Camera:
    return Camera(look_at(eye), height=res, width=res)


def _layered_scene(rng, n_tri: int, spread: float = 0.6):
    """n_tri random triangles at well separated depths (no intersections: no order flips under FD)."""
    v = rng.uniform(-spread, spread, (n_tri, 3, 3))
    v[..., 2] = np.linspace(0.4, -0.4, n_tri)[:, None] + rng.uniform(-0.05, 0.05, (n_tri, 3))
    return v.reshape(-1, 3), np.arange(3 * n_tri).reshape(-1, 3)


def _loss_weights(rng, res: int):
    return [torch.tensor(rng.standard_normal((res, res)), dtype=torch.float32) for _ in OUTPUTS]


def _weighted(out: dict, g) -> torch.Tensor:
    return sum((gi.to(out[k].dtype) * out[k]).sum() for gi, k in zip(g, OUTPUTS))


# --------------------------------------------------------------------------------------------------------
# Soft renderer: native versus the naive reference (values and gradients)
# --------------------------------------------------------------------------------------------------------

def _scene(kind: str, rng):
    if kind == "empty":
        return np.zeros((3, 3)), np.zeros((0, 3), np.int64)
    if kind == "single":
        return _layered_scene(rng, 1)
    if kind == "layers":
        return _layered_scene(rng, 4)
    if kind == "soup":  # intersecting triangles: order per pixel matters, no FD here
        v = rng.uniform(-0.6, 0.6, (18, 3))
        return v, np.arange(18).reshape(-1, 3)
    if kind == "degenerate":  # a zero-area face, a duplicated face and a needle
        v, f = _layered_scene(rng, 2)
        v = np.vstack([v, [[0.0, 0.0, 0.2], [0.3, 0.3, 0.2], [0.6, 0.6, 0.2], [-0.5, 0.1, 0.0],
                           [0.5, 0.11, 0.0], [0.0, 0.1, 0.0]]])
        f = np.vstack([f, [[6, 7, 8], [0, 1, 2], [9, 10, 11]]])
        return v, f
    raise ValueError(kind)


@pytest.mark.parametrize("kind,edge_width,opacity", list(itertools.product(
    ["empty", "single", "layers", "soup", "degenerate"], [1.0, 0.5], ["half", "opaque"])))
def test_soft_matches_reference(kind, edge_width, opacity):
    rng = np.random.default_rng(7)
    v, f = _scene(kind, rng)
    o = np.full(len(f), 1.0) if opacity == "opaque" else rng.uniform(0.2, 0.9, len(f))
    cam = _camera(24)
    g = _loss_weights(rng, 24)
    vt = torch.tensor(v, dtype=torch.float32, requires_grad=True)
    ot = torch.tensor(o, dtype=torch.float32, requires_grad=True)
    out = soft_render(vt, torch.tensor(f), ot, cam, edge_width=edge_width)
    _weighted(out, g).backward()
    # the reference gets the same float32 values, in float64
    vr = vt.detach().double().requires_grad_(True)
    orf = ot.detach().double().requires_grad_(True)
    ref = soft_render_naive(vr, torch.tensor(f), orf, cam, edge_width=edge_width)
    _weighted(ref, g).backward()
    for k in OUTPUTS:
        # the kernel works in double and rounds its images to float32: 1e-5 covers depth ~2 x 2^-24 many times
        assert_close(out[k], ref[k], atol=1e-5, what=f"{kind} {k}")
    if vr.grad is not None:
        # same model, the kernel accumulates in double and returns float32: 1e-4 relative to the largest entry
        # the collinear face's three edges overlap: which edge is nearest is a tie, and either edge's
        # vertex gradient is a valid subgradient, so its corners (rows 6-8) are left out
        keep = np.arange(len(v)) if kind != "degenerate" else np.r_[0:6, 9:len(v)]
        assert_close(vt.grad[keep], vr.grad[keep], atol=1e-5, rtol=1e-4, what=f"{kind} grad verts")
        assert_close(ot.grad, orf.grad, atol=1e-5, rtol=1e-4, what=f"{kind} grad opacity")


def test_min_opacity_culls_faces_and_their_gradients():
    rng = np.random.default_rng(3)
    v, f = _layered_scene(rng, 3)
    o = torch.tensor([0.8, 5e-4, 0.6], requires_grad=True)
    vt = torch.tensor(v, dtype=torch.float32, requires_grad=True)
    out = soft_render(vt, torch.tensor(f), o, _camera(), min_opacity=1e-3)
    _weighted(out, _loss_weights(rng, 32)).backward()
    assert o.grad[1] == 0 and (vt.grad[3:6] == 0).all()
    ref = soft_render(v, f, torch.tensor([0.8, 0.0, 0.6]), _camera())
    for k in OUTPUTS:
        assert torch.equal(out[k].detach(), ref[k])


def test_early_stop_at_t_min():
    # 20 stacked opaque-ish layers: the pixel stops once T < t_min, as the reference does
    rng = np.random.default_rng(5)
    v, f = _layered_scene(rng, 20, spread=0.05)
    v[:, :2] = np.tile(np.array([[-1.0, -1.0], [1.5, -1.0], [-1.0, 1.5]]), (20, 1))
    o = np.full(20, 0.6)
    cam = _camera(8, eye=(0.0, 0.0, 2.0))
    out = soft_render(v, f, o, cam, t_min=1e-3)
    ref = soft_render_naive(torch.tensor(v), torch.tensor(f), torch.tensor(o), cam, t_min=1e-3)
    for k in OUTPUTS:
        assert_close(out[k], ref[k], atol=1e-5, what=k)
    assert float(out["alpha"][4, 4]) < 1.0 - 1e-4  # stopped before reaching the last layers


# --------------------------------------------------------------------------------------------------------
# Soft renderer: gradients against finite differences
# --------------------------------------------------------------------------------------------------------

def _fd_vertex_grads(v, f, o, cam, g, h=1e-3, **kw):
    """Central differences of the weighted loss, evaluated in float64 from the float32 images."""
    fd = np.zeros_like(v)
    for i, j in itertools.product(range(len(v)), range(3)):
        vals = []
        for s in (1, -1):
            vp = v.copy()
            vp[i, j] += s * h
            out = soft_render(torch.tensor(vp, dtype=torch.float32), torch.tensor(f), o, cam, **kw)
            vals.append(float(sum((gi.double() * out[k].double()).sum() for gi, k in zip(g, OUTPUTS))))
        fd[i, j] = (vals[0] - vals[1]) / (2 * h)
    return fd


@pytest.mark.parametrize("which", ["alpha", "all"])
def test_silhouette_gradient_matches_finite_differences(which):
    """One triangle over background: with the loss on alpha only, every position gradient comes from the
    soft edge (coverage), i.e. from moving the silhouette."""
    rng = np.random.default_rng(11)
    v = np.array([[-0.5, -0.4, 0.1], [0.6, -0.3, -0.1], [0.0, 0.5, 0.05]])
    f = np.array([[0, 1, 2]])
    o = torch.tensor([0.7])
    cam = _camera(32)
    g = _loss_weights(rng, 32)
    if which == "alpha":
        g[0].zero_()
        g[1].zero_()
    vt = torch.tensor(v, dtype=torch.float32, requires_grad=True)
    _weighted(soft_render(vt, torch.tensor(f), o, cam), g).backward()
    fd = _fd_vertex_grads(v, f, o, cam, g)
    # h = 1e-3 world = 1/80 pixel: the smoothstep's curvature error is ~1e-6 relative; float32 vertices
    # and images add ~1e-4 relative noise to the differences (measured 3e-4): 2e-3 relative to the max.
    assert np.abs(fd).max() > 1.0
    assert_close(vt.grad, fd, atol=1e-3, rtol=2e-3, what=f"{which} vertex grads vs FD")


def test_layered_gradients_match_finite_differences():
    rng = np.random.default_rng(12)
    v, f = _layered_scene(rng, 3)
    o = np.array([0.6, 0.8, 0.5])
    cam = _camera(32)
    g = _loss_weights(rng, 32)
    vt = torch.tensor(v, dtype=torch.float32, requires_grad=True)
    ot = torch.tensor(o, dtype=torch.float32, requires_grad=True)
    _weighted(soft_render(vt, torch.tensor(f), ot, cam), g).backward()
    fd = _fd_vertex_grads(v, f, ot.detach(), cam, g)
    assert_close(vt.grad, fd, atol=1e-3, rtol=2e-3, what="vertex grads vs FD")
    # opacities: the loss is polynomial in each opacity (degree 1), so differences are exact up to rounding
    fd_o = np.zeros(3)
    for k in range(3):
        vals = []
        for s in (1, -1):
            op = o.copy()
            op[k] += s * 1e-2
            out = soft_render(v, f, torch.tensor(op, dtype=torch.float32), cam)
            vals.append(float(sum((gi.double() * out[n].double()).sum() for gi, n in zip(g, OUTPUTS))))
        fd_o[k] = (vals[0] - vals[1]) / 2e-2
    assert_close(ot.grad, fd_o, atol=1e-3, rtol=1e-3, what="opacity grads vs FD")


def _bitwise_scenes(rng):
    """Two scenes for the thread-count test. "soup": intersecting random triangles over the image. "layers":
    20 parallel semi-transparent triangles covering the whole view, seen head-on, with a diffuse loss weight
    that is odd under the image's vertical flip, so every opacity gradient is a sum of terms that cancel
    in pairs: its value (~1e-16) is pure rounding and shows any change in the order of summation (the old
    per-thread accumulation gave a different value in most 2-thread runs)."""
    res = 64
    centres = rng.uniform(-0.6, 0.6, (600, 1, 3))
    soup = (centres + rng.uniform(-0.15, 0.15, (600, 3, 3))).reshape(-1, 3)
    g_soup = _loss_weights(rng, res)
    tri = np.array([[-20.0, -10.0, 0.0], [20.0, -10.0, 0.0], [0.0, 30.0, 0.0]])
    layers = np.concatenate([tri + [0.0, 0.0, -0.05 * k] for k in range(20)])
    top = rng.standard_normal((res // 2, res))
    odd = torch.tensor(np.vstack([top, -top[::-1]]), dtype=torch.float32)
    zero = torch.zeros(res, res)
    return [("soup", soup, rng.uniform(0.2, 0.9, 600), _camera(res), g_soup),
            ("layers", layers, np.full(20, 0.3), Camera(look_at((0.0, 0.0, 2.0)), height=res, width=res),
             [odd, zero, zero])]


@pytest.mark.parametrize("scene", ["soup", "layers"])
def test_soft_bitwise_identical_across_thread_counts(scene):
    """Forward images and gradients do not depend on the native thread count or schedule (bit for bit):
    each pixel is composited by one thread and the backward adds its row blocks' sums in a fixed order."""
    name, v, o, cam, g = next(s for s in _bitwise_scenes(np.random.default_rng(21)) if s[0] == scene)
    f = torch.arange(len(v)).reshape(-1, 3)

    def run(num_threads):
        vt = torch.tensor(v, dtype=torch.float32, requires_grad=True)
        ot = torch.tensor(o, dtype=torch.float32, requires_grad=True)
        out = soft_render(vt, f, ot, cam, num_threads=num_threads)
        _weighted(out, g).backward()
        return [out[k].detach() for k in OUTPUTS] + [vt.grad, ot.grad]

    one = run(1)
    assert float(one[2].mean()) > 0.25 and one[4].abs().max() > 0  # busy scenes with gradients
    for nt in (2, 2, 3):
        for what, a, b in zip([*OUTPUTS, "grad verts", "grad opacity"], run(nt), one):
            assert torch.equal(a, b), f"{name}: {what} differs between 1 and {nt} threads"


# --------------------------------------------------------------------------------------------------------
# Soft renderer versus the ground-truth capture
# --------------------------------------------------------------------------------------------------------

def _away_from_silhouettes(mask: np.ndarray, r: int = 2) -> np.ndarray:
    from scipy import ndimage
    return np.stack([ndimage.binary_erosion(m, iterations=r) | ~ndimage.binary_dilation(m, iterations=r)
                     for m in mask])


@pytest.mark.skipif(_gl_problem() is not None, reason="no headless OpenGL (OSMesa/EGL) for the capture")
@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_opaque_mesh_reproduces_capture(shape):
    import trimesh

    from datasets.capture import capture

    if shape == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    else:
        mesh = trimesh.creation.box((1.0, 0.8, 1.2))
        mesh.apply_transform(trimesh.transformations.euler_matrix(0.3, 0.5, 0.1))
    mv = capture(mesh, views=4, resolution=64)
    cams = Camera.from_multiview(mv)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    ones = torch.ones(len(f))

    # Near-hard edges: the model reduces to one sample per pixel centre, like the capture. Only pixel
    # centres within 1e-3 px of an edge may differ (GL's top-left tie rule versus ours): allow 0.2%.
    hard = soft_render_views(v, f, ones, cams, edge_width=1e-3)
    for k in ("diffuse", "depth"):
        err = np.abs(hard[k].numpy() - getattr(mv, k))
        assert (err < 1e-4).mean() > 0.998, f"{k}: {(err >= 1e-4).mean():.4f} of pixels differ"
    assert (np.abs(hard["alpha"].numpy() - mv.mask) > 0.5).mean() < 0.002

    # Default soft edges (1 px band outside each face): away from silhouettes (>= 2 px from the capture's
    # mask boundary) the band only matters where a neighbour's band fragment is composited before the
    # covering face, which the depth-extent sort key makes rare (measured 0.5% of pixels on the sphere,
    # errors up to 0.03 in diffuse, 6e-4 in depth). Tolerances: > 99% of those pixels within 1e-4 and
    # mean abs diff < 1e-3 for both images; float32 GL depth alone differs by ~1e-6.
    soft = soft_render_views(v, f, ones, cams)
    away = _away_from_silhouettes(mv.mask)
    for k in ("diffuse", "depth"):
        err = np.abs(soft[k].numpy() - getattr(mv, k))[away]
        assert (err < 1e-4).mean() > 0.99, f"{k}: {(err >= 1e-4).mean():.4f} of pixels differ"
        assert err.mean() < 1e-3, f"{k}: mean abs diff {err.mean():.3g}"
    # at silhouettes the band adds coverage outside the mask only (never removes it inside)
    assert (soft["alpha"].numpy()[mv.mask] > 0.999).all()


# --------------------------------------------------------------------------------------------------------
# Tetrahedral renderer
# --------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tet_scene():
    from dmesh.wdt import PowerDiagram

    rng = np.random.default_rng(1)
    pts = rng.uniform(-1.0, 1.0, (200, 3))
    pd = PowerDiagram.from_points(pts)
    centroid = pts[pd.tets].mean(1)
    inside = np.linalg.norm(centroid, axis=1) < 0.6
    ft = pd.face_tets
    side = lambda t: np.where(t >= 0, inside[np.maximum(t, 0)], False)  # noqa: E731
    boundary = side(ft[:, 0]) != side(ft[:, 1])
    w2c, _ = camera_rig(4, distance=3.0)
    return pts, pd, boundary, Camera.from_views(w2c, resolution=32)


def test_tet_matches_reference(tet_scene):
    pts, pd, _, cams = tet_scene
    rng = np.random.default_rng(2)
    o = rng.uniform(0.0, 0.6, len(pd.faces))
    o[rng.random(len(o)) < 0.3] = 0.0  # many faces crossed without being drawn
    ot = torch.tensor(o, dtype=torch.float32, requires_grad=True)
    g = _loss_weights(rng, 32)
    out = tet_render(pts, pd.tets, pd.faces, pd.face_tets, ot, cams[0])
    _weighted(out, g).backward()
    orf = ot.detach().double().requires_grad_(True)
    ref = tet_render_naive(torch.tensor(pts), pd.faces, orf, cams[0])
    _weighted(ref, g).backward()
    assert float(out["alpha"].detach().sum()) > 50
    for k in OUTPUTS:
        assert_close(out[k], ref[k], atol=1e-5, what=f"tet {k}")
    # stored float32 fragment values and float32 output: 1e-4 relative
    assert_close(ot.grad, orf.grad, atol=1e-5, rtol=1e-4, what="tet grad opacity")


def test_tet_opacity_gradient_matches_finite_differences(tet_scene):
    pts, pd, _, cams = tet_scene
    rng = np.random.default_rng(4)
    o = rng.uniform(0.05, 0.5, len(pd.faces))
    g = _loss_weights(rng, 32)
    ot = torch.tensor(o, dtype=torch.float32, requires_grad=True)
    _weighted(tet_render(pts, pd.tets, pd.faces, pd.face_tets, ot, cams[1]), g).backward()
    picks = np.argsort(-np.abs(ot.grad.numpy()))[:6]
    for k in picks:
        vals = []
        for s in (1, -1):
            op = o.copy()
            op[k] += s * 1e-2
            out = tet_render(pts, pd.tets, pd.faces, pd.face_tets, torch.tensor(op, dtype=torch.float32), cams[1])
            vals.append(float(sum((gi.double() * out[n].double()).sum() for gi, n in zip(g, OUTPUTS))))
        fd = (vals[0] - vals[1]) / 2e-2
        # linear in each opacity: central differences are exact up to float32 image rounding
        assert abs(float(ot.grad[k]) - fd) <= 1e-3 + 1e-3 * abs(fd), (k, float(ot.grad[k]), fd)


def test_soft_and_tet_agree_on_opaque_region(tet_scene):
    """The boundary of a union of tets drawn opaque: the walk and the rasteriser see the same surface."""
    pts, pd, boundary, cams = tet_scene
    o = torch.tensor(boundary, dtype=torch.float32)
    tet = tet_render_views(pts, pd.tets, pd.faces, pd.face_tets, o, cams)
    hard = soft_render_views(pts, pd.faces, o, cams, edge_width=1e-3)
    soft = soft_render_views(pts, pd.faces, o, cams)
    assert float(tet["alpha"].sum()) > 100
    mask = tet["alpha"].numpy() > 0.5
    away = _away_from_silhouettes(mask)
    for k in OUTPUTS:
        # near-hard edges: identical up to float32 rounding except rays through an edge (<= 0.5%)
        err = np.abs(tet[k].numpy() - hard[k].numpy())
        assert (err < 1e-4).mean() > 0.995, f"{k}: {(err >= 1e-4).mean():.4f} differ"
        # default soft edges, away from silhouettes: the faces here are large (few px inner-edge blends)
        err = np.abs(tet[k].numpy() - soft[k].numpy())[away]
        assert (err < 1e-4).mean() > 0.97, f"soft {k}: {(err >= 1e-4).mean():.4f} differ"


def test_tet_rejects_camera_inside_hull(tet_scene):
    pts, pd, boundary, _ = tet_scene
    cam = Camera(look_at((0.0, 0.0, 0.2)), height=8, width=8)
    with pytest.raises(ValueError, match="inside the convex hull"):
        tet_render(pts, pd.tets, pd.faces, pd.face_tets, np.full(len(pd.faces), 0.5), cam)


# --------------------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------------------

def test_bad_inputs_raise():
    v, f = np.zeros((3, 3)), np.array([[0, 1, 2]])
    cam = _camera(8)
    with pytest.raises(ValueError, match="opacity must lie in"):
        soft_render(v, f, [1.5], cam)
    with pytest.raises(ValueError, match="faces must index"):
        soft_render(v, [[0, 1, 3]], [0.5], cam)
    with pytest.raises(ValueError, match="verts must have shape"):
        soft_render(np.zeros((3, 2)), f, [0.5], cam)
    with pytest.raises(ValueError, match="edge_width"):
        soft_render(v, f, [0.5], cam, edge_width=0.0)
    with pytest.raises(TypeError, match="Camera"):
        soft_render(v, f, [0.5], np.eye(4))
    with pytest.raises(ValueError, match="fov_y_degrees"):
        Camera(np.eye(4), fov_y_degrees=180.0)
    # the native layer checks again (it is callable directly) and refuses silent dtype conversions
    w2c = np.eye(4)
    args = (w2c, 1.0, 8, 8, 0.01, 1.0, 1e-3, 1e-4, 1)
    with pytest.raises(ValueError, match="faces holds"):
        native._native.soft_render_forward(v.astype(np.float32), np.array([[0, 1, 7]], np.int32),
                                           np.array([0.5], np.float32), *args)
    with pytest.raises(TypeError):
        native._native.soft_render_forward(v, f.astype(np.int32), np.array([0.5], np.float32), *args)


def test_views_helper_stacks():
    rng = np.random.default_rng(0)
    v, f = _layered_scene(rng, 2)
    w2c, _ = camera_rig(4)
    cams = Camera.from_views(w2c, resolution=16)
    out = soft_render_views(v, f, np.full(2, 0.5), cams)
    assert all(out[k].shape == (4, 16, 16) and out[k].dtype == torch.float32 for k in OUTPUTS)
    single = soft_render(v, f, np.full(2, 0.5), cams[2])
    assert torch.equal(out["diffuse"][2], single["diffuse"])
