"""datasets: synthetic shapes, mesh loading and classification, normalisation, point sampling."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datasets import families, meshes, normalize, sampling, synthetic
from datasets.mesh_parts import concat
from common import SHARED_MESHES, shared_mesh

ALL_SHAPES = list(synthetic.SHAPES)
#: The coarse generators; the smooth families of datasets/families.py (2M faces) are checked in test_splits.py.
COARSE_SHAPES = [name for name in ALL_SHAPES if name not in families.FAMILIES]


# ------------------------------------------------------------------------------------------------ synthetic

@pytest.mark.parametrize("name", COARSE_SHAPES)
def test_synthetic_shape_generates_deterministically_with_its_class(name):
    cls = synthetic.SHAPES[name][0]
    a = synthetic.generate(name, seed=3)
    b = synthetic.generate(name, seed=3)
    c = synthetic.generate(name, seed=4)
    assert isinstance(a, trimesh.Trimesh)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert not (a.vertices.shape == c.vertices.shape and np.allclose(a.vertices, c.vertices)), \
        "the seed should change the shape"
    assert 100 <= len(a.faces) <= 10_000, "keep synthetic meshes modest"
    assert np.isfinite(a.vertices).all()
    assert meshes.classify(a) == cls
    _, closed = meshes.components(a)
    if cls == "closed":
        assert a.is_watertight
    elif cls == "open":
        assert len(meshes.boundary_edges(a)) > 0 and not closed.any()
    else:
        assert closed.any() and (~closed).any()
    # Merging by position (what load_mesh does) must not change the class: parts never share vertices.
    merged = trimesh.Trimesh(a.vertices, a.faces, process=False)
    merged.merge_vertices()
    assert meshes.classify(merged) == cls


def test_synthetic_topology_of_named_shapes():
    assert synthetic.generate("torus").euler_number == 0
    assert synthetic.generate("genus2").euler_number == -2
    assert synthetic.generate("trefoil").euler_number == 0
    assert synthetic.generate("mobius").euler_number == 0
    assert len(meshes.components(synthetic.generate("plant"))[1]) >= 3


def test_shapes_in_class_and_unknown_names():
    for cls in ("closed", "open", "mixed"):
        names = synthetic.shapes_in_class(cls)
        assert len(names) >= 5 and all(synthetic.SHAPES[n][0] == cls for n in names)
    assert sorted(sum((synthetic.shapes_in_class(c) for c in ("closed", "open", "mixed")), [])) == sorted(ALL_SHAPES)
    with pytest.raises(ValueError, match="unknown synthetic shape"):
        synthetic.generate("teacup")
    with pytest.raises(ValueError, match="unknown shape class"):
        synthetic.shapes_in_class("solid")


def test_synthetic_parameters_are_used():
    assert len(synthetic.generate("sphere", subdivisions=2).faces) == 320
    assert len(synthetic.generate("wavy_sheet", holes=0, n=10).faces) == 2 * 9 * 9


# ------------------------------------------------------------------------------------------------ classify

def _quad_sheet(offset=0.0):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float) + offset
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def test_classify_small_cases():
    tet = trimesh.creation.box()
    assert meshes.classify(tet) == "closed"
    assert meshes.classify(_quad_sheet()) == "open"
    both = concat([tet, _quad_sheet(5.0)])
    assert meshes.classify(both) == "mixed"
    # A fin glued to a closed box along a non-manifold edge: the box stays closed, the fin is open.
    box = trimesh.creation.box()
    edge = box.edges_unique[0]
    fin_v = np.vstack([box.vertices, box.vertices[edge].mean(0) + [3.0, 3.0, 3.0]])
    fin = trimesh.Trimesh(fin_v, np.vstack([box.faces, [edge[0], edge[1], len(box.vertices)]]), process=False)
    labels, closed = meshes.components(fin)
    assert len(closed) == 2 and closed.sum() == 1
    assert meshes.classify(fin) == "mixed"
    with pytest.raises(ValueError):
        meshes.classify(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int), process=False))


def test_unique_faces_collapses_back_to_back_pairs():
    f = np.array([[2, 1, 0], [0, 1, 2], [3, 1, 2], [2, 3, 1]], np.int32)
    u = meshes.unique_faces(f)
    assert u.dtype == np.int64
    assert u.tolist() == [[0, 1, 2], [1, 2, 3]]
    assert meshes.unique_faces(np.zeros((0, 3), int)).shape == (0, 3)
    with pytest.raises(ValueError):
        meshes.unique_faces(np.zeros((4, 2), int))


# ------------------------------------------------------------------------------------------------ load_mesh

#: Expected class of each shared mesh; beetle.obj disagrees with its folder (see datasets/meshes.py).
SHARED = {
    "closed/spot.obj": "closed", "closed/fandisk.obj": "closed", "closed/rocker_arm.obj": "closed",
    "closed/bunny_closed.obj": "closed",
    "open/face.off": "open", "open/terrain.ply": "open", "open/planar_mesh.ply": "open",
    "open/teapot.obj": "open", "open/beetle_alt.obj": "open",
    "mixed/ogre.obj": "mixed", "mixed/suzanne.obj": "mixed", "mixed/beetle.obj": "open",
}


@pytest.mark.parametrize("rel", list(SHARED))
def test_load_and_classify_shared_meshes(rel):
    m = meshes.load_mesh(shared_mesh(rel))
    assert m.vertices.dtype == np.float64 and m.faces.dtype == np.int64
    assert len(m.faces) > 0 and np.isfinite(m.vertices).all()
    assert meshes.classify(m) == SHARED[rel]


def test_load_merges_uv_seams():
    m = meshes.load_mesh(shared_mesh("closed/spot.obj"))
    assert len(m.vertices) == 2930 and len(m.faces) == 5856 and m.is_watertight


@pytest.mark.parametrize("fmt", ["obj", "ply", "off", "stl", "glb"])
def test_load_formats_round_trip(tmp_path, fmt):
    src = synthetic.generate("torus", sections=16)
    path = tmp_path / f"torus.{fmt}"
    src.export(path)
    m = meshes.load_mesh(path)
    assert len(m.faces) == len(src.faces) and len(m.vertices) == len(src.vertices)
    assert meshes.classify(m) == "closed"


def test_load_glb_scene_concatenates(tmp_path):
    a = trimesh.creation.box()
    b = _quad_sheet()
    scene = trimesh.Scene()
    scene.add_geometry(a, node_name="box")
    scene.add_geometry(b, node_name="sheet", transform=trimesh.transformations.translation_matrix([5, 0, 0]))
    path = tmp_path / "scene.glb"
    scene.export(path)
    m = meshes.load_mesh(path)
    assert len(m.faces) == len(a.faces) + len(b.faces)
    assert m.vertices[:, 0].max() == pytest.approx(6.0)
    assert meshes.classify(m) == "mixed"


def _one_line_error(path, match):
    with pytest.raises(ValueError, match=match) as info:
        meshes.load_mesh(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_load_bad_files(tmp_path):
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 999\n\x00\x01\x02")
    _one_line_error(garbage, "cannot read mesh|no faces")
    points = tmp_path / "points.obj"
    points.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    _one_line_error(points, "no faces")
    empty = tmp_path / "empty.off"
    empty.write_text("")
    _one_line_error(empty, "cannot read mesh|no faces")
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    _one_line_error(nan, "NaN")
    odd = tmp_path / "mesh.xyz"
    odd.write_text("0 0 0\n")
    _one_line_error(odd, "unsupported mesh format")
    with pytest.raises(FileNotFoundError):
        meshes.load_mesh(tmp_path / "missing.obj")


def test_shared_meshes_folder_is_beside_the_checkout():
    if not SHARED_MESHES.exists():
        pytest.skip("no shared meshes beside the checkout")
    assert (SHARED_MESHES / "closed").is_dir()


# ------------------------------------------------------------------------------------------------ normalize

@pytest.mark.parametrize("radius", [1.0, 0.8])
def test_normalize_invariants(radius):
    src = synthetic.generate("flag_box", seed=2)
    src.apply_scale(7.0)
    src.apply_translation([3.0, -2.0, 10.0])
    out, t = normalize.normalize(src, radius=radius)
    assert np.allclose(out.vertices.mean(0), 0.0, atol=1e-12)
    assert np.linalg.norm(out.vertices, axis=1).max() == pytest.approx(radius, rel=1e-12)
    assert np.allclose(t.apply(src.vertices), out.vertices)
    assert np.allclose(t.inverse(out.vertices), src.vertices)
    assert np.array_equal(out.faces, src.faces)
    assert t.apply(np.zeros(3, np.float32)).dtype == np.float32
    assert normalize.Transform.from_dict(t.to_dict()) == t
    assert np.allclose(t.apply_mesh(src).vertices, out.vertices)
    # The input is not modified.
    assert src.vertices[:, 2].max() > 5


def test_normalize_bad_input():
    with pytest.raises(ValueError, match="coincide"):
        normalize.normalize(trimesh.Trimesh(np.ones((3, 3)), [[0, 1, 2]], process=False))
    with pytest.raises(ValueError, match="radius"):
        normalize.normalize(trimesh.creation.box(), radius=0.0)
    with pytest.raises(ValueError):
        normalize.Transform(center=np.zeros(2), scale=1.0)
    with pytest.raises(ValueError):
        normalize.Transform(center=np.zeros(3), scale=-1.0)


# ------------------------------------------------------------------------------------------------ sampling

def test_sampling_is_deterministic_and_on_the_surface():
    mesh = synthetic.generate("sphere", subdivisions=2)
    p1, n1 = sampling.sample_points(mesh, n=2000, seed=5)
    p2, n2 = sampling.sample_points(mesh, n=2000, seed=5)
    p3, _ = sampling.sample_points(mesh, n=2000, seed=6)
    assert p1.shape == (2000, 3) and n1.shape == (2000, 3)
    assert p1.dtype == np.float32 and n1.dtype == np.float32
    assert np.array_equal(p1, p2) and np.array_equal(n1, n2)
    assert not np.array_equal(p1, p3)
    closest, dist, tri = trimesh.proximity.closest_point(mesh, p1.astype(np.float64))
    assert dist.max() < 1e-5  # float32 rounding of coordinates of size ~1
    assert np.allclose(np.linalg.norm(n1, axis=1), 1.0, atol=1e-6)
    # Each normal is the normal of a face containing its point (the nearest face, up to ties on edges).
    agree = np.einsum("ij,ij->i", n1, mesh.face_normals[tri]) > 0.999
    assert agree.mean() > 0.99


def test_sampling_is_area_uniform():
    # Two disjoint triangles with areas 1 : 3.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [5, 0, 0], [8, 0, 0], [5, 2, 0]], float)
    mesh = trimesh.Trimesh(v, [[0, 1, 2], [3, 4, 5]], process=False)
    p, n = sampling.sample_points(mesh, n=40_000, seed=0)
    frac = (p[:, 0] >= 5).mean()
    assert frac == pytest.approx(0.75, abs=0.01)  # binomial sd ~0.002
    assert np.allclose(n, [0, 0, 1])
    left = p[p[:, 0] < 5]
    assert (left[:, 0] >= 0).all() and (left[:, 1] >= -1e-7).all() and (2 * left[:, 0] + left[:, 1] <= 2 + 1e-6).all()


def test_sampling_bad_input():
    with pytest.raises(ValueError, match="area"):
        sampling.sample_points(trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False), n=10)
    with pytest.raises(ValueError):
        sampling.sample_points(trimesh.creation.box(), n=-1)
    p, n = sampling.sample_points(trimesh.creation.box(), n=0)
    assert p.shape == (0, 3)
