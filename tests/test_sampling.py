"""Surface sampling (`dmesh.sampling`): flat and Phong-curved samples, sign-free vertex axes."""
from __future__ import annotations

import numpy as np
import trimesh

from dmesh.sampling import sample_surface, vertex_axes


def _radius_error(points: np.ndarray) -> float:
    return float(np.abs(np.linalg.norm(points, axis=1) - 1.0).mean())


def test_phong_samples_of_a_coarse_sphere_lie_closer_to_the_sphere():
    mesh = trimesh.creation.icosphere(subdivisions=1)  # 80 faces: flat samples lie well inside
    flat = sample_surface(mesh, 5000, np.random.default_rng(0))
    curved = sample_surface(mesh, 5000, np.random.default_rng(0), phong=0.75)
    assert _radius_error(flat) > 0.02
    assert _radius_error(curved) < 0.5 * _radius_error(flat)


def test_phong_samples_ignore_the_faces_winding():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    faces = mesh.faces.copy()
    faces[::2] = faces[::2, ::-1]  # every other face wound the other way
    flipped = trimesh.Trimesh(mesh.vertices, faces, process=False)
    axes, axes_flipped = vertex_axes(mesh.vertices, mesh.faces), vertex_axes(flipped.vertices, flipped.faces)
    np.testing.assert_allclose(np.abs((axes * axes_flipped).sum(1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.abs((axes * mesh.vertices).sum(1)), 1.0, atol=1e-9)  # the sphere's normals
    curved = sample_surface(flipped, 5000, np.random.default_rng(0), phong=0.75)
    assert _radius_error(curved) < 0.5 * _radius_error(sample_surface(flipped, 5000, np.random.default_rng(0)))


def test_phong_zero_is_the_flat_sampler_and_creases_stay_flat():
    box = trimesh.creation.box()
    a = sample_surface(box, 3000, np.random.default_rng(1))
    b = sample_surface(box, 3000, np.random.default_rng(1), phong=0.75)
    np.testing.assert_array_equal(a, sample_surface(box, 3000, np.random.default_rng(1), phong=0.0))
    # a cube's corners have no tangent plane: its curved samples stay on its faces
    np.testing.assert_allclose(a, b, atol=1e-12)
    assert not vertex_axes(box.vertices, box.faces).any()
