"""Multi-view inputs (`dmesh.recon.views`): checks, resampling, soft-band targets, normalisation. The
captures (`sphere`, `sphere_views` from conftest.py) need headless OpenGL (OSMesa or EGL)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from datasets import capture as cap
from datasets.normalize import normalize
from dmesh.camera import eyes as camera_eyes
from dmesh.recon.views import check_views, depth_channel, downsample, soft_band_targets
from common import fake_views

_NO_GL = cap.gl_problem()
needs_gl = pytest.mark.skipif(_NO_GL is not None, reason=f"no headless OpenGL (OSMesa/EGL): {_NO_GL}")


def test_check_views_masks_the_background():
    views = fake_views()
    views.diffuse[:, 0, 0] = 0.7                   # lit background pixel: not part of the object
    vw = check_views(views)
    assert vw.diffuse[:, 0, 0].max() == 0 and vw.depth.dtype == np.float32


def test_downsample_is_an_area_average(rng):
    img = rng.random((3, 12, 12)).astype(np.float32)
    half = downsample(img, 6)
    want = img.reshape(3, 6, 2, 6, 2).mean(axis=(2, 4))
    assert np.allclose(half, want, atol=1e-6)
    odd = downsample(img, 5)                       # non-integer ratio: each pixel averages its footprint
    assert odd.shape == (3, 5, 5) and np.allclose(odd.mean(axis=(1, 2)), img.mean(axis=(1, 2)), atol=1e-6)
    assert np.array_equal(downsample(img, 12), img)


@needs_gl
def test_band_targets_make_the_soft_fit_unbiased(sphere, sphere_views):
    """The GT sphere, drawn opaque by the soft renderer at 48 pixels, fits the plain targets best when shrunk
    (its band puts the silhouette about half a pixel outside) but the band targets best at its true size."""
    from dmesh.render import Camera, soft_render_views

    res, width = 48, 1.0
    vw = check_views(sphere_views)
    far = np.linalg.norm(camera_eyes(vw.world_to_camera), axis=1) + 2.0
    channel = far[:, None, None] * vw.mask - vw.depth.astype(np.float64)
    plain = [torch.from_numpy(downsample(x, res)) for x in (vw.diffuse, channel)]
    band = [torch.from_numpy(x) for x in soft_band_targets([vw.diffuse, channel], vw.mask, res, width)]
    assert torch.equal(band[0][plain[0] > 0.999], plain[0][plain[0] > 0.999])  # object pixels unchanged
    cams = Camera.from_views(vw.world_to_camera, vw.fov_y_degrees, res)
    faces = torch.from_numpy(np.asarray(sphere.faces, np.int64))
    pixel = 2.0 * 2.0 * np.tan(np.radians(vw.fov_y_degrees) / 2) / res  # one pixel at the sphere's distance
    offsets = np.array([-1.0, -0.5, 0.0, 0.5]) * pixel
    losses = {"plain": [], "band": []}
    for off in offsets:
        verts = torch.from_numpy(np.asarray(sphere.vertices) * (1.0 + off)).float()
        out = soft_render_views(verts, faces, torch.ones(len(faces)), cams, edge_width=width, min_opacity=0.0)
        z = depth_channel(out["depth"], out["alpha"], torch.from_numpy(far).float()) * 2.0
        for name, (td, tz) in (("plain", plain), ("band", band)):
            losses[name].append(float((out["diffuse"] - td).abs().mean() + (z - tz).abs().mean()))
    assert offsets[int(np.argmin(losses["plain"]))] < 0, losses
    assert offsets[int(np.argmin(losses["band"]))] == 0.0, losses


@needs_gl
def test_lopsided_object_falls_back_to_the_look_at_centre():
    """The shared face mask is lopsided: its lifted box centre moves towards a camera of the rig, which then
    sits inside the object's box; the cameras' look-at point (the vertex mean) keeps every camera out."""
    from common import shared_mesh

    from dmesh.recon.views import BOX_MARGIN, MIN_BOX, lifted_points, normalisation

    from datasets.meshes import load_mesh

    gt, _ = normalize(load_mesh(shared_mesh("open/face.off")), radius=1.0)
    vw = check_views(cap.capture(gt, views=64, resolution=64))
    pts = lifted_points(vw)
    box_centre = 0.5 * (pts.min(0) + pts.max(0))
    radius = np.linalg.norm(pts - box_centre, axis=1).max()
    eyes = camera_eyes(vw.world_to_camera)
    assert BOX_MARGIN * np.abs((eyes - box_centre) / radius).max(1).min() < MIN_BOX  # the box centre fails
    center, scale, _, eyes_n = normalisation(vw)
    cam_box = np.abs(eyes_n).max(1).min()
    assert np.allclose(center, 0.0, atol=1e-6) and BOX_MARGIN * cam_box >= MIN_BOX
