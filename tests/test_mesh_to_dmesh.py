"""Mesh to DMesh (Exp. 1): small meshes are recovered exactly and wound outward; bad input is refused in
one line."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from dmesh.recon.mesh_to_dmesh import _orient, fast_config, mesh_to_dmesh, recovery_metrics
from dmesh.wdt import face_keys
from common import check_closed, cycle


def _normalise(v):
    v = np.asarray(v, dtype=np.float64)
    v = v - v.mean(0)
    return v / np.linalg.norm(v, axis=1).max() * 0.8


def small_torus():
    """60 vertices, 120 faces, closed and not convex (its Delaunay hull is not the mesh)."""
    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.45, major_sections=10, minor_sections=6)
    return _normalise(t.vertices), np.asarray(t.faces)


def small_sheet():
    """64 vertices, 98 faces, an open wavy sheet."""
    g = np.linspace(-1, 1, 8)
    x, y = np.meshgrid(g, g)
    z = 0.3 * np.sin(2 * x) * np.cos(2 * y)
    idx = np.arange(64).reshape(8, 8)
    f = np.concatenate([np.c_[idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel()],
                        np.c_[idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()]])
    return _normalise(np.c_[x.ravel(), y.ravel(), z.ravel()]), f


@pytest.mark.parametrize("make", [small_torus, small_sheet], ids=["closed-torus", "open-sheet"])
def test_small_meshes_are_recovered_exactly(make):
    v, f = make()
    # No lr decay: these meshes need ~370 steps at full step size (measured: torus 367, sheet 121), and the
    # fast preset's decay of 0.5 per period, tuned for the bunny's final FP, slows them past the budget.
    r = mesh_to_dmesh(v, f, fast_config(steps=800, insert_every=200, decay=1.0))
    assert r.stopped_early, f"RE {r.re:.3f} FP {r.fp:.3f} after {r.steps} steps"
    assert r.re == 1.0 and r.fp == 0.0
    # The recovered faces are exactly the GT faces, checked independently of the metric function.
    got = {tuple(x) for x in np.sort(r.faces, axis=1).tolist()}
    assert got == {tuple(x) for x in np.sort(f, axis=1).tolist()}
    # GT vertices stayed within the perturbation bound; their weights stayed 1.
    assert np.abs(r.points[: len(v)] - v).max() <= fast_config().max_perturb + 1e-12
    assert np.all(r.weights[: len(v)] == 1.0)


def test_recovery_metrics():
    n = 10
    gt = np.sort(face_keys(np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 5]]), n))
    wdt = np.sort(face_keys(np.array([[0, 1, 2], [1, 2, 3], [0, 1, 9]]), n))
    re, fp = recovery_metrics(wdt, gt)
    assert re == pytest.approx(0.5) and fp == pytest.approx(1 / 3)


@pytest.mark.parametrize("vertices, faces, message", [
    (np.random.default_rng(0).random((10, 3)), np.zeros((0, 3), int), "no faces"),
    (np.r_[np.random.default_rng(0).random((9, 3)), [[np.nan, 0, 0]]], np.array([[0, 1, 2]]), "finite"),
    (np.random.default_rng(0).random((10, 3)), np.array([[0, 1, 20]]), "index vertices"),
])
def test_bad_meshes_raise(vertices, faces, message):
    with pytest.raises(ValueError, match=message):
        mesh_to_dmesh(vertices, faces, fast_config(steps=1))


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "eval.cli", "-q", *args], capture_output=True, text=True)


def test_fit_cli_writes_state_mesh_and_json(tmp_path):
    v, f = small_torus()
    path = tmp_path / "torus.ply"
    trimesh.Trimesh(v, f, process=False).export(path)
    r = _cli("fit", str(path), "-o", str(tmp_path / "out"), "--steps", "5")
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "out" / "result.json").read_text())
    assert summary["steps"] == 5 and 0 <= summary["RE"] <= 100 and 0 <= summary["FP"] <= 100
    assert (tmp_path / "out" / "dmesh.npz").exists() and (tmp_path / "out" / "mesh.ply").exists()


def test_fit_cli_bad_inputs_are_one_line_errors(tmp_path):
    empty = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((20, 3))).export(empty)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    for path in (empty, nan, tmp_path / "missing.obj"):
        r = _cli("fit", str(path), "-o", str(tmp_path / "out"))
        assert r.returncode == 2, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_stanford_bunny_res4_reaches_the_paper_figures():
    """The paper's Exp. 1 bunny (453 vertices, 948 faces): RE >= 99.7 %, FP <= 0.5 % (paper: 99.78 / 0.00).

    Measured with the fast preset: RE 99.89 %, FP 0.44 % at step 950 (about 400 s on a loaded 2-core box)."""
    from common import shared_mesh
    from datasets.meshes import load_mesh
    from datasets.normalize import normalize

    mesh, _ = normalize(load_mesh(shared_mesh("stanford/bun_zipper_res4_948.ply")), radius=0.8)
    r = mesh_to_dmesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), fast_config(steps=1500))
    assert r.best.re >= 0.997 and r.best.fp <= 0.005, (r.best.re, r.best.fp, r.best.step)


def test_kept_state_prefers_acceptable_fp_then_re():
    from dmesh.recon.mesh_to_dmesh import Snapshot, _better

    def snap(re, fp):
        return Snapshot(0, re, fp, np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3), np.int64))

    assert _better(0.99, 0.004, snap(0.999, 0.006), 0.005)      # acceptable FP beats higher RE
    assert not _better(0.999, 0.006, snap(0.99, 0.004), 0.005)
    assert _better(0.998, 0.004, snap(0.995, 0.0), 0.005)       # among acceptable: higher RE
    assert _better(0.99, 0.02, snap(0.98, 0.02), 0.005)          # neither acceptable: RE - FP
    assert _better(0.5, 0.5, None, 0.005)


def test_mesh_to_dmesh_output_is_wound_outward_even_for_an_inside_out_input():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    v = sphere.vertices * 0.8
    sorted_faces = np.sort(sphere.faces, axis=1)  # what the WDT gives
    for given in (sphere.faces, sphere.faces[:, ::-1]):  # outward and inside-out input windings
        out = _orient(v, np.ones(len(v)), sorted_faces, v, given)
        mesh = check_closed(out, v)
        assert mesh.volume > 0
    # An open cap keeps the input's winding, whichever it is.
    cap = sphere.faces[sphere.triangles_center[:, 2] > 0.3]
    for given in (cap, cap[:, ::-1]):
        out = _orient(v, np.ones(len(v)), np.sort(given, axis=1), v, given)
        assert {cycle(f) for f in out.tolist()} == {cycle(f) for f in given.tolist()}


def test_false_faces_go_when_the_input_is_manifold_and_stay_when_it_is_not():
    from dmesh.wdt import PowerDiagram

    sphere = trimesh.creation.icosphere(subdivisions=1)
    v = sphere.vertices * 0.8
    true = {tuple(x) for x in np.sort(sphere.faces, axis=1).tolist()}
    pd = PowerDiagram.from_points(v, np.ones(len(v)))
    wdt = np.sort(pd.faces.astype(np.int64), axis=1)
    edges = {tuple(sorted(e)) for e in sphere.edges.tolist()}
    # WDT faces through the inside that share an edge with the sphere: each makes that edge non-manifold
    false = [x for x in wdt.tolist() if tuple(x) not in true
             and {(x[0], x[1]), (x[0], x[2]), (x[1], x[2])} & edges]
    faces = np.concatenate([np.sort(sphere.faces, axis=1), np.array(false[:1])])
    out = _orient(v, np.ones(len(v)), faces, v, sphere.faces)      # manifold input: a closed, outward sphere
    assert {tuple(x) for x in np.sort(out, axis=1).tolist()} == true
    assert check_closed(out, v).volume > 0
    nonmanifold_input = np.concatenate([sphere.faces, np.array(false[:1])])
    out = _orient(v, np.ones(len(v)), faces, v, nonmanifold_input)
    assert len(out) == len(faces)                                   # such an input's extra faces stay
