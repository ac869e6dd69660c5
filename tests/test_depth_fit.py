"""The fit of a mesh's vertices to captured depth maps (`dmesh.recon.depth_fit`), against the captured object
itself: a coarse mesh inside the sphere moves onto it, the winding does not matter, nothing moves where no view
looks, and settings are checked."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dmesh.recon.depth_fit import DepthFitConfig, depth_residuals, fit_to_depth


@pytest.fixture(scope="module")
def ball():
    """A round unit sphere (a fine icosphere) and its capture: 16 views at 128 pixels."""
    from datasets import capture as cap

    problem = cap.gl_problem()
    if problem is not None:
        pytest.skip(f"no headless OpenGL (OSMesa/EGL): {problem}")
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    return mesh, cap.capture(mesh, views=16, resolution=128)


def _frame(views):
    """The views in the sphere's own frame (the capture's, here normalised already)."""
    from dmesh.recon.views import check_views, normalisation

    vw = check_views(views)
    center, scale, w2c, _ = normalisation(vw)
    return vw, center, scale, w2c


def _distance_to_sphere(mesh: trimesh.Trimesh, sphere: trimesh.Trimesh, n: int = 20_000) -> float:
    """Mean distance of area-uniform samples of `mesh` to the GT sphere's surface."""
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=0)
    _, dist, _ = trimesh.proximity.closest_point(sphere, pts)
    return float(np.mean(dist))


def _fit(mesh, views, **cfg):
    vw, center, scale, w2c = _frame(views)
    v = (np.asarray(mesh.vertices) - center) * scale
    out, info = fit_to_depth(v, mesh.faces, w2c, vw.fov_y_degrees, vw.depth.astype(np.float64) * scale, vw.mask,
                             DepthFitConfig(**cfg))
    return trimesh.Trimesh(out / scale + center, mesh.faces, process=False), info


def test_a_coarse_mesh_inside_the_sphere_moves_onto_it(ball):
    sphere, views = ball
    coarse = trimesh.creation.icosphere(subdivisions=3, radius=0.995)
    before = _distance_to_sphere(coarse, sphere)
    fitted, info = _fit(coarse, views)
    after = _distance_to_sphere(fitted, sphere)
    assert info["fit_samples"] > 0.95 and info["moved"] == len(coarse.vertices)
    assert after < 0.5 * before
    # Outward on average: the inscribed faces and the 0.5 % shrink both put the mesh inside.
    assert np.linalg.norm(fitted.vertices, axis=1).mean() > np.linalg.norm(coarse.vertices, axis=1).mean()
    assert np.array_equal(fitted.faces, coarse.faces)


def test_the_winding_does_not_matter(ball):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.99)
    flipped = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    a, _ = _fit(mesh, ball[1])
    b, _ = _fit(flipped, ball[1])
    moved = np.abs(np.linalg.norm(a.vertices, axis=1) - 0.99)
    assert np.median(moved) > 5e-3
    # The same fit up to its samples (a reversed face draws its points from reversed corners).
    agree = np.abs(a.vertices - b.vertices).max(1) < 1e-3
    assert agree.mean() > 0.95
    assert _distance_to_sphere(a, ball[0]) == pytest.approx(_distance_to_sphere(b, ball[0]), rel=0.1)


def test_nothing_moves_where_no_view_measures(ball):
    far = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    far.vertices += [0.0, 0.0, 50.0]                  # behind the cameras' reach and off every mask
    fitted, info = _fit(far, ball[1])
    assert info == {"fit_samples": 0.0, "median_offset": 0.0, "moved": 0}
    assert np.array_equal(fitted.vertices, far.vertices)


def test_residual_of_a_point_off_the_surface_is_its_normal_offset(ball):
    """A point 0.01 inside the sphere along its outward normal measures about +0.01 (the depth maps' own
    error aside), one 0.01 outside about -0.01; the centre is occluded in every view and measures nothing."""
    sphere, views = ball
    vw, center, scale, w2c = _frame(views)
    d = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
    _, dist, _ = trimesh.proximity.closest_point(sphere, [d * 2.0])
    on = d * (2.0 - dist[0])                                # the GT surface along d
    pts = (np.stack([on - 0.01 * d, on + 0.01 * d, np.zeros(3)]) - center) * scale
    normals = np.stack([d, d, d])
    res = depth_residuals(pts, normals, w2c, vw.fov_y_degrees, vw.depth.astype(np.float64) * scale, vw.mask,
                          DepthFitConfig())
    assert res[0] == pytest.approx(0.01 * scale, abs=2e-3)
    assert res[1] == pytest.approx(-0.01 * scale, abs=2e-3)
    assert np.isnan(res[2])


@pytest.mark.parametrize("bad", [{"samples_per_face": 0}, {"tolerance": 0.0}, {"max_offset": -1.0},
                                 {"min_cos": 1.0}, {"damp": -0.1}, {"smooth": -1.0}])
def test_bad_settings_are_named(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        DepthFitConfig(**bad)


def _split_at_equator(mesh):
    """The sphere as two pieces that meet along its equator: every vertex shared by a face above and one below
    gets a second copy for the faces below, and the copies move a little into their own faces, as the surface
    step splits a point where sheets meet (`dmesh.surface.finish.separate_copies`). Returns (vertices, faces,
    source)."""
    from dmesh.surface.finish import separate_copies

    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    below = v[f].mean(1)[:, 2] < 0
    shared = np.intersect1d(f[below].ravel(), f[~below].ravel())
    copy = np.full(len(v), -1)
    copy[shared] = len(v) + np.arange(len(shared))
    faces = f.copy()
    faces[below] = np.where(copy[f[below]] >= 0, copy[f[below]], f[below])
    source = np.concatenate([np.arange(len(v)), shared])
    return separate_copies(v[source], faces, source), faces, source


def test_copies_of_one_point_move_together(ball):
    """With `groups`, the copies of a point take one offset along one axis, so the pieces keep their distance
    and move as the unsplit mesh does; each copy on its own moves along its own piece's normal, and the two
    pieces part."""
    sphere, views = ball
    whole = trimesh.creation.icosphere(subdivisions=3, radius=0.99)
    v, f, source = _split_at_equator(whole)
    copies = np.flatnonzero(np.bincount(source)[source] > 1)
    assert len(copies) > 20
    vw, center, scale, w2c = _frame(views)

    def fit(vertices, faces, groups=None):
        out, _ = fit_to_depth((vertices - center) * scale, faces, w2c, vw.fov_y_degrees,
                              vw.depth.astype(np.float64) * scale, vw.mask, DepthFitConfig(), groups=groups)
        return out / scale + center - vertices     # the displacements

    together = fit(v, f, groups=source)
    apart = fit(v, f)
    unsplit = fit(np.asarray(whole.vertices), np.asarray(whole.faces))

    def spread(d):  # the largest difference between the displacements of copies of one point
        return max(np.abs(d[source == s] - d[source == s][0]).max() for s in np.unique(source[copies]))

    assert spread(together) < 1e-12
    assert spread(apart) > 1e-3
    assert np.abs(together - unsplit[source]).max() < 1e-4       # each copy on its own: 8e-4
    assert np.median(np.linalg.norm(unsplit, axis=1)) > 1e-3     # the fit does move the sphere's vertices


def test_copy_groups_finds_each_copys_point():
    from dmesh.recon.multiview import copy_groups

    v, f, source = _split_at_equator(trimesh.creation.icosphere(subdivisions=2))
    assert np.array_equal(copy_groups(v, trimesh.creation.icosphere(subdivisions=2).vertices), source)


def test_groups_must_match_the_vertices(ball):
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.99)
    vw, center, scale, w2c = _frame(ball[1])
    with pytest.raises(ValueError, match="groups has 3 entries"):
        fit_to_depth(np.asarray(mesh.vertices), mesh.faces, w2c, vw.fov_y_degrees, vw.depth.astype(np.float64),
                     vw.mask, groups=[0, 1, 2])


def test_offsets_that_make_faces_cross_go_back():
    """A floor (two triangles at z = 0), a wall standing 0.005 above it, and a triangle far away, each pushed
    down by the fit: the wall's foot through the floor. Its offsets and the floor's shrink until no face
    crosses another (half of them do: the foot then stays 0.004 above the floor), the far triangle keeps its
    own; with the wall lifted instead nothing is held back."""
    from dmesh.recon.depth_fit import undo_crossings
    from dmesh.surface.crossings import FaceIndex

    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],            # the floor
                  [-0.3, 0, 0.005], [0.3, 0, 0.005], [0, 0, 1],              # the wall
                  [5, 5, 0], [6, 5, 0], [5, 6, 0]], dtype=np.float64)          # far away
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9]])
    axes = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    groups = np.arange(len(v))
    x = np.array([-0.002] * 4 + [-0.01, -0.01, 0.0] + [-0.004] * 3)
    assert FaceIndex(v + x[:, None] * axes, f).crossing(f).sum() == 3   # the wall and both floor faces
    held_back = undo_crossings(v, f, x, axes, groups)
    assert held_back == 6 and np.allclose(x[:6], [-0.001] * 4 + [-0.005] * 2) and np.all(x[7:] == -0.004)
    assert not FaceIndex(v + x[:, None] * axes, f).crossing(f).any()
    harmless = np.array([-0.002] * 4 + [0.01, 0.01, 0.0] + [-0.004] * 3)   # the wall lifted instead
    kept = harmless.copy()
    assert undo_crossings(v, f, kept, axes, groups) == 0 and np.array_equal(kept, harmless)


def test_crossings_the_mesh_had_before_the_fit_stay_its_own():
    """A wall through the floor before the fit: the fit's offsets elsewhere are kept (it made no crossing)."""
    from dmesh.recon.depth_fit import undo_crossings

    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],
                  [-0.3, 0, -0.2], [0.3, 0, -0.2], [0, 0, 1]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    x = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.003])
    assert undo_crossings(v, f, x, np.tile([0.0, 0.0, 1.0], (len(v), 1)), np.arange(len(v))) == 0
    assert x[6] == 0.003
