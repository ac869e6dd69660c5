"""The paper's other Table 2 baselines: VoroMesh (point cloud), FlexiCubes and NIE (multi-view).

Small shapes and short runs (each test well under 30 s). Accuracy bounds are point-to-surface Chamfer L1 in
GT-radius units, each justified next to it (grid spacing, or a fraction of the starting shape's error);
multi-view tests need headless OpenGL for the capture (skipped without it).
"""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
import trimesh

from baselines.base import Inputs
from baselines.flexicubes import EDGE_GROUP, EDGES, GROUP_COUNT, extract, make_grid, torch_tables
from baselines.nie import LevelSetGrid, redistance
from baselines.registry import METHODS, get_method
from datasets import capture as cap
from datasets import synthetic
from datasets.normalize import normalize
from eval.metrics import chamfer_l1_p2s

N_METRIC = 10_000
_NO_GL = cap.gl_problem()
needs_igl = pytest.mark.skipif(importlib.util.find_spec("igl") is None, reason="libigl not installed")


@pytest.fixture(scope="module")
def torus():
    gt, _ = normalize(synthetic.generate("torus", seed=0), radius=1.0)
    return gt


#: A small VoroMesh run: 10K points, a 32^3 generator lattice, 100 epochs.
VM_SMALL = {"grid": 32, "epochs": 100}


def _cloud(mesh, n=10_000, normals=True):
    pts, fi = trimesh.sample.sample_surface(mesh, n, seed=0)
    return Inputs(points=pts.astype(np.float32),
                  normals=mesh.face_normals[fi].astype(np.float32) if normals else None, seed=0)


def test_registered():
    assert get_method("voromesh").input_kind == "pointcloud"
    assert get_method("flexicubes").input_kind == "multiview"
    assert get_method("nie").input_kind == "multiview"
    assert {"voromesh", "flexicubes", "nie"} <= set(METHODS)


# --------------------------------------------------------------------------------------------- VoroMesh

@pytest.fixture(scope="module")
def voromesh_torus(torus):
    if importlib.util.find_spec("igl") is None:
        pytest.skip("libigl not installed")
    return get_method("voromesh").reconstruct(_cloud(torus), VM_SMALL)


def test_voromesh_closed_torus(torus, voromesh_torus):
    res = voromesh_torus
    mesh = res.mesh.copy()
    mesh.merge_vertices()
    # Faces between inside and outside Voronoi cells of a closed, well-labelled surface form a closed surface.
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(torus.volume, rel=0.1)
    # Grid spacing 2.1 / 31 = 0.068: the flat Voronoi faces pass through the points and stay within a small
    # fraction of a cell of the surface (measured 0.11 spacing; bound 0.2).
    assert chamfer_l1_p2s(res.mesh, torus, n=N_METRIC) < 0.2 * 2.1 / 31
    assert res.info["generators"] > 1000 and res.info["inside_cells"] > 0


def test_voromesh_open_surface_fails_as_in_the_paper(torus, voromesh_torus):
    bowl, _ = normalize(synthetic.generate("bowl", seed=0), radius=1.0)
    method = get_method("voromesh")
    closed = chamfer_l1_p2s(voromesh_torus.mesh, torus, n=N_METRIC)
    try:
        open_cd = chamfer_l1_p2s(method.reconstruct(_cloud(bowl), VM_SMALL).mesh, bowl, n=N_METRIC)
    except RuntimeError as exc:  # a clear failure is also acceptable: no inside/outside interface at all
        assert "voromesh:" in str(exc)
        return
    # The winding number of an open sheet is about 0.5 on both sides: the labelling, and the mesh, go wrong.
    assert open_cd > 5 * closed


@needs_igl
def test_voromesh_bad_input(torus):
    method = get_method("voromesh")
    with pytest.raises(ValueError, match="normals"):
        method.reconstruct(_cloud(torus, normals=False))
    with pytest.raises(ValueError, match="at least"):
        method.reconstruct(Inputs(points=np.zeros((0, 3), np.float32), normals=np.zeros((0, 3), np.float32)))
    with pytest.raises(ValueError, match="point cloud"):
        method.reconstruct(Inputs())
    with pytest.raises(ValueError, match="unknown config keys"):
        method.reconstruct(_cloud(torus), {"grdi": 32})
    far = _cloud(torus)
    far.points = far.points * 3.0
    with pytest.raises(ValueError, match="normalised frame"):
        method.reconstruct(far)


# --------------------------------------------------------------------------------------------- FlexiCubes

def test_flexicubes_tables():
    assert GROUP_COUNT[0] == GROUP_COUNT[255] == 0
    for code in range(256):
        inside = [(code >> c) & 1 for c in range(8)]
        crossing = np.array([inside[a] != inside[b] for a, b in EDGES])
        assert ((EDGE_GROUP[code] >= 0) == crossing).all()
        assert sorted(set(EDGE_GROUP[code][crossing])) == list(range(GROUP_COUNT[code]))
    # One inside corner: one dual vertex on its three edges.
    assert GROUP_COUNT[1] == 1 and (EDGE_GROUP[1] >= 0).sum() == 3
    # Corners 0 and 3 (a face diagonal) inside: the inside is separated on the ambiguous face, two dual
    # vertices; the complement (that face's other diagonal outside) then joins its outside corners: one.
    assert GROUP_COUNT[0b00001001] == 2
    assert GROUP_COUNT[0b11110110] == 1
    # Opposite corners of the cube: two separate patches either way.
    assert GROUP_COUNT[0b10000001] == 2 and GROUP_COUNT[0b01111110] == 2


@pytest.mark.parametrize("split4", [True, False])
def test_flexicubes_extraction_of_analytic_fields(split4):
    grid = make_grid(32, np.zeros(3), 1.1)
    tables = torch_tables(grid)
    x = torch.from_numpy(grid.nodes)
    c = len(grid.cube_corners)
    ones = (torch.ones(c, 8, dtype=torch.float64), torch.ones(c, 12, dtype=torch.float64),
            torch.ones(c, dtype=torch.float64))
    p = grid.nodes
    cases = [(np.linalg.norm(p, axis=1) - 0.7, 4 / 3 * np.pi * 0.7 ** 3, 2),
             (np.hypot(np.hypot(p[:, 0], p[:, 2]) - 0.6, p[:, 1]) - 0.25, 2 * np.pi ** 2 * 0.6 * 0.25 ** 2, 0)]
    for sdf, volume, euler in cases:
        out = extract(grid, x, torch.from_numpy(sdf), *ones, tables, split4)
        mesh = trimesh.Trimesh(out.verts.numpy(), out.faces.numpy(), process=False)
        mesh.merge_vertices()
        assert mesh.is_watertight and mesh.euler_number == euler
        # Outward faces, and the volume of a 0.069-voxel grid's dual surface within 4% of the analytic one.
        assert mesh.volume == pytest.approx(volume, rel=0.04)


def test_flexicubes_gradients_match_finite_differences():
    # Directional derivatives of the four-way split mesh's vertices along random directions of (sdf, alpha,
    # beta, gamma), autograd against central differences in float64 (a full gradcheck takes minutes here).
    grid = make_grid(4, np.zeros(3), 1.0)
    tables = torch_tables(grid)
    rng = np.random.default_rng(0)
    c = len(grid.cube_corners)
    base = [torch.from_numpy(np.linalg.norm(grid.nodes, axis=1) - 0.55),
            torch.from_numpy(rng.uniform(0.5, 1.5, (c, 8))), torch.from_numpy(rng.uniform(0.5, 1.5, (c, 12))),
            torch.from_numpy(rng.uniform(0.1, 0.9, c))]
    x = torch.from_numpy(grid.nodes)

    def verts(args):
        return extract(grid, x, *args, tables, split4=True).verts

    params = [t.clone().requires_grad_(True) for t in base]
    out = verts(params)
    w = torch.from_numpy(rng.normal(size=tuple(out.shape)))
    grads = torch.autograd.grad((out * w).sum(), params)
    h = 1e-6
    for _ in range(4):
        d = [torch.from_numpy(rng.normal(size=tuple(t.shape))) * (0.01 if i == 0 else 0.1) for i, t in enumerate(base)]
        plus = verts([t + h * di for t, di in zip(base, d)])
        minus = verts([t - h * di for t, di in zip(base, d)])
        assert plus.shape == out.shape  # no sign flips: the same mesh on both sides
        fd = float(((plus - minus) * w).sum() / (2 * h))
        ad = float(sum((g * di).sum() for g, di in zip(grads, d)))
        assert fd == pytest.approx(ad, rel=1e-5, abs=1e-8)


@pytest.fixture(scope="module")
def sphere_capture():
    if _NO_GL is not None:
        pytest.skip(f"no headless OpenGL (OSMesa/EGL): {_NO_GL}")
    gt, _ = normalize(synthetic.generate("sphere", seed=0), radius=1.0)
    return gt, cap.capture(gt, views=16, resolution=64)


def _start_error(gt):
    """CD of the methods' starting sphere (radius 0.6 of the object's half extent) against the GT: 0.60."""
    return chamfer_l1_p2s(trimesh.creation.icosphere(3, radius=0.6), gt, n=N_METRIC)


def test_flexicubes_fits_a_sphere(sphere_capture):
    gt, views = sphere_capture
    res = get_method("flexicubes").reconstruct(Inputs(views=views), {"grid": 16, "steps": 80, "resolution": 64})
    cd = chamfer_l1_p2s(res.mesh, gt, n=N_METRIC)
    # The start (radius 0.6 against 1) is 0.60 off; the fit must close 95% of that, to a fifth of a voxel
    # (0.15): measured 0.017, bound 0.030.
    assert cd < 0.05 * _start_error(gt)
    assert res.info["image_loss_last"] < res.info["image_loss_first"]


def test_multiview_bad_input(sphere_capture):
    gt, views = sphere_capture
    for name in ("flexicubes", "nie"):
        method = get_method(name)
        with pytest.raises(ValueError, match="multi-view capture"):
            method.reconstruct(Inputs(points=np.zeros((20, 3), np.float32)))
        empty = cap.MultiView(diffuse=np.zeros_like(views.diffuse), depth=np.zeros_like(views.depth),
                              mask=np.zeros_like(views.mask), world_to_camera=views.world_to_camera,
                              projection=views.projection, fov_y_degrees=views.fov_y_degrees,
                              resolution=views.resolution)
        with pytest.raises(ValueError, match="empty"):
            method.reconstruct(Inputs(views=empty))
        with pytest.raises(ValueError, match="unknown config keys"):
            method.reconstruct(Inputs(views=views), {"stpes": 3})


# --------------------------------------------------------------------------------------------- NIE

def test_nie_level_set_grid():
    grid = LevelSetGrid(np.zeros((24, 24, 24)), np.full(3, -1.1), 2.2 / 23)
    rng = np.random.default_rng(0)
    grid.phi = rng.normal(size=grid.phi.shape)
    p = rng.uniform(-1.0, 1.0, (40, 3))
    _, grad = grid.sample(p)
    h = 1e-6
    fd = np.stack([(grid.sample(p + h * e)[0] - grid.sample(p - h * e)[0]) / (2 * h) for e in np.eye(3)], 1)
    assert np.abs(fd - grad).max() < 1e-6
    # A sphere's distance field: outward faces, the analytic volume, vertices on the zero level.
    grid.phi = np.linalg.norm(grid.nodes, axis=-1) - 0.7
    verts, faces = grid.surface()
    mesh = trimesh.Trimesh(verts, faces, process=False)
    assert mesh.is_watertight and mesh.volume == pytest.approx(4 / 3 * np.pi * 0.7 ** 3, rel=0.03)
    assert np.abs(grid.sample(verts)[0]).max() < 1e-6  # scikit-image returns float32 vertices
    # Re-initialisation of a distorted far field: the surface stays, the far field becomes a distance again.
    exact = grid.phi.copy()
    far = np.abs(exact) > 3 * grid.voxel
    grid.phi[far] *= 3.0
    redistance(grid)
    v2, _ = grid.surface()
    assert np.allclose(np.sort(np.linalg.norm(v2, axis=1)), np.sort(np.linalg.norm(verts, axis=1)), atol=1e-6)
    assert np.abs(grid.phi[far] - exact[far]).max() < 0.5 * grid.voxel


def test_nie_fits_a_sphere(sphere_capture):
    gt, views = sphere_capture
    res = get_method("nie").reconstruct(Inputs(views=views), {"grid": 24, "epochs": 40, "resolution": 64})
    mesh = res.mesh.copy()
    mesh.merge_vertices()
    assert mesh.is_watertight  # a level set's marching-cubes mesh inside the grid is closed
    # The start is 0.60 off; the evolved level set must close 90% of that, to two thirds of a voxel (0.1):
    # measured 0.015, bound 0.060 (the evolution is noisy: a 32^3 grid over 60 epochs measured 0.078).
    assert chamfer_l1_p2s(res.mesh, gt, n=N_METRIC) < 0.1 * _start_error(gt)
