"""The surface step's rules for stray geometry (`dmesh.surface.debris`, `dmesh.surface.finish.keep_flattest`):
crumbs, floating and stacked pieces, closed crumbs, long faces, the flattest pair at a branching edge."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dmesh.surface import debris, finish, holes
from dmesh.surface.evidence import Evidence
from dmesh.surface.topology import edge_table
from common import grid_sheet


def test_crumbs_are_a_sheet_part_made_only_of_small_edge_connected_pieces():
    sheet = trimesh.creation.box().faces  # 12 faces, one piece: a real sheet
    stray = np.array([[20, 21, 22]])  # a lone triangle
    pair = np.array([[30, 31, 32], [31, 32, 33]])  # two triangles sharing an edge
    touching = np.array([[0, 40, 41]])  # shares only a vertex with the box: a piece of its own
    small = np.concatenate([stray, pair, touching])
    assert debris.crumb_pieces(small, 2).all()
    assert not debris.crumb_pieces(small, 1).any()  # the pair is larger than 1 face: a real sheet part
    # Beside a real sheet, small pieces may be parts of it: none is a crumb.
    assert not debris.crumb_pieces(np.concatenate([sheet, small]), 2).any()
    assert debris.crumb_pieces(np.concatenate([sheet, small]), 12).all()
    assert not debris.crumb_pieces(small, 0).any()
    assert debris.crumb_pieces(np.zeros((0, 3), np.int64), 4).shape == (0,)


def test_fins_stand_on_inner_edges_of_the_closed_part_not_on_its_rim():
    """A box with one face out: a sheet face on the hole's rim continues the surface there (a tube running on
    as a sheet past where the vote stopped) and stays; one on an edge two box faces share is a fin."""
    box = np.asarray(trimesh.creation.box().faces, dtype=np.int64)
    closed, rim = box[1:], box[0]
    edges, _, counts = edge_table(closed)
    inner = next(e for e in edges[counts == 2] if not set(e.tolist()) <= set(rim.tolist()))
    on_rim = [rim[0], rim[1], 8]
    fin = [inner[0], inner[1], 9]
    apart = [20, 21, 22]
    assert debris.fin_faces(np.array([on_rim, fin, apart]), closed).tolist() == [False, True, False]
    assert debris.fin_faces(np.array([on_rim, fin]), box).tolist() == [True, True]  # the hole closed: both fins
    assert debris.fin_faces(np.zeros((0, 3), np.int64), closed).shape == (0,)
    assert not debris.fin_faces(np.array([fin]), box[:0]).any()


def test_closed_crumbs_are_tiny_closed_pieces_beside_a_larger_one():
    """One tet's boundary and a two-face pillow beside a sphere go; the sphere alone, a tiny open piece and
    a mesh made only of tiny closed pieces stay."""
    ball = trimesh.creation.icosphere(subdivisions=1)
    n = len(ball.vertices)
    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]) + n
    pillow = np.array([[0, 1, 2], [0, 2, 1]]) + n + 4
    lone = np.array([[0, 1, 2]]) + n + 7
    faces = np.concatenate([ball.faces, tet, pillow, lone])
    crumbs = debris.closed_crumb_pieces(faces, 4)
    assert crumbs.sum() == 6 and crumbs[len(ball.faces):len(ball.faces) + 6].all()
    assert not debris.closed_crumb_pieces(ball.faces, 4).any()
    assert not debris.closed_crumb_pieces(tet, 4).any()           # nothing larger beside it: it is the mesh
    assert not debris.closed_crumb_pieces(faces, 0).any()


def test_keep_flattest_drops_the_fin_across_a_flat_pair():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.0], [0.2, 0.8, -0.3]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4], [2, 0, 5]])    # a flat square split on edge 0-2, two fins
    keep = finish.keep_flattest(v, f)
    assert keep.tolist() == [True, True, False, False]
    assert finish.keep_flattest(v, f[:2]).all()                           # a manifold mesh keeps every face


def test_long_faces_are_long_against_the_median_edge():
    grid = trimesh.creation.box(extents=(1, 1, 1)).subdivide().subdivide()
    v, f = np.asarray(grid.vertices, dtype=np.float64), np.asarray(grid.faces, dtype=np.int64)
    stretched = v.copy()
    stretched[0] = stretched[0] * 9.0  # one corner pulled far out: its faces' edges grow
    at = np.isin(f, [0]).any(1)
    assert debris.long_faces(v, f, 2.0).sum() == 0
    assert np.array_equal(debris.long_faces(stretched, f, 4.0), at)
    assert debris.long_faces(v, f[:0], 4.0).shape == (0,)


def test_stacked_pieces_are_small_pieces_lying_on_a_larger_surface():
    v, f = grid_sheet(12)
    extra = np.array([[3.2, 3.3, 0.1], [4.1, 3.4, -0.1], [3.6, 4.2, 0.05],    # a triangle in the grid's band
                      [3.2, 3.3, 3.0], [4.1, 3.4, 3.0], [3.6, 4.2, 3.0],      # one three edges above it
                      [6.0, 6.0, 0.2]])                                        # apex of a fin on a grid edge
    v = np.concatenate([v, extra])
    n = 144
    near, far = [n, n + 1, n + 2], [n + 3, n + 4, n + 5]
    fin = [5 * 12 + 5, 6 * 12 + 6, n + 6]              # on the diagonal edge of square (5, 5): non-manifold there
    sv, sf = grid_sheet(3, offset=(30.0, 0.0))                # a separate 8-face sheet far away
    v = np.concatenate([v, sv])
    faces = np.concatenate([f, [near, far, fin], sf + len(v) - len(sv)])
    flagged = debris.stacked_pieces(v, faces)
    expect = np.zeros(len(faces), bool)
    expect[len(f)] = expect[len(f) + 2] = True         # the one in the band and the fin (cut off at its edge)
    assert flagged.tolist() == expect.tolist()
    assert not debris.stacked_pieces(v, faces, tol=0).any()
    # A triangle just above another surface given as `others` (e.g. the closed part) lies on it too.
    alone = np.array([near, far])
    assert debris.stacked_pieces(v, alone, others=f).tolist() == [True, False]
    # A triangle in a hole of the grid lies beside its faces, not over them: it covers what they do not.
    centre = 8 * 12 + 8
    holed = f[~(f == centre).any(1)]
    w = np.concatenate([v[:144], [[7.8, 7.8, 0.05], [8.3, 7.9, 0.0], [8.0, 8.3, -0.05]]])
    plug = np.array([[144, 145, 146]])
    assert not debris.stacked_pieces(w, np.concatenate([holed, plug]))[-1]
    # Pieces of one size never absorb each other: two triangles lying on one another both stay.
    w = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.01], [1, 0, 0.01], [0, 1, 0.01]], float)
    assert not debris.stacked_pieces(w, np.array([[0, 1, 2], [3, 4, 5]])).any()


def test_stacked_pieces_keep_a_part_the_input_sampled_a_few_spacings_off():
    """On a coarse mesh (unit edges) a triangle half an edge over a larger surface is within its edge length and
    flagged. With the input's samples (spacing 0.05) the length is at most `Stacked.spacings` (3) of their local
    spacings: the triangle the samples cover on its own, 10 spacings off, stays (an eye in its socket), and one
    in the band of the surface is still a stray copy. The local spacing is measured where each face lies: on a
    grid of samples it is the grid's spacing."""
    v, f = grid_sheet(12)
    band = [[3.2, 3.3, 0.02], [4.1, 3.4, -0.02], [3.6, 4.2, 0.01]]
    eye = [[6.2, 6.3, 0.5], [7.1, 6.4, 0.5], [6.6, 7.2, 0.5]]
    v = np.concatenate([v, band, eye])
    faces = np.concatenate([f, [[144, 145, 146], [147, 148, 149]]])
    assert debris.stacked_pieces(v, faces)[-2:].tolist() == [True, True]
    x, y = np.meshgrid(np.arange(0.0, 11.0, 0.05), np.arange(0.0, 11.0, 0.05), indexing="ij")
    plane = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    bary = np.random.default_rng(0).dirichlet(np.ones(3), 400)
    samples = np.concatenate([plane, bary @ np.array(eye)])
    evidence = Evidence.of_samples(samples, 8)
    assert np.median(evidence.spacing_at(plane[::97])) == pytest.approx(0.05)
    assert debris.stacked_pieces(v, faces, evidence=evidence)[-2:].tolist() == [True, False]


def test_floating_crumbs_are_small_pieces_far_from_every_larger_one():
    """Beside a real sheet, a crumb within an edge or two of it stays (a thin part that did not join up); one
    several edge lengths from every larger piece and from `others`, off the plane of the surface nearest it, is a
    triangle among stray points; one as far but in that plane is a fragment of the surface (a scanner's sparse
    stretch) and stays."""
    v, f = grid_sheet(12)                                      # unit edges; median edge length 1
    tri = np.array([[0.0, 0.0, 0.0], [0.8, 0.0, 0.0], [0.0, 0.8, 0.0]])
    near = tri + [12.0, 5.0, 0.0]                         # 1 unit past the grid's rim
    far = tri + [5.0, 5.0, 9.0]                           # 9 units above it
    by_others = tri + [30.0, 0.0, 3.0]                    # far from the grid and off its plane, beside `others`
    in_plane = tri + [20.0, 5.0, 0.0]                     # 9 units past the rim, in the grid's plane
    tilted = in_plane + [0.0, 0.0, 2.0]                   # as far, 2 units off that plane
    w = np.concatenate([v, near, far, by_others, in_plane, tilted, by_others[:1] + [0.0, 0.0, 1.0]])
    n = len(v)
    faces = np.concatenate([f, n + np.arange(15).reshape(5, 3)])
    others = np.array([[n + 15, n + 15, n + 15]])
    flag = debris.floating_crumbs(w, faces, 4, others)
    assert not flag[: len(f)].any()
    assert flag[len(f):].tolist() == [False, True, False, False, True]
    assert debris.floating_crumbs(w, faces, 4).tolist()[len(f):] == [False, True, True, False, True]
    # beside -1: no crumb counts as beside, the fragment goes too
    assert debris.floating_crumbs(w, faces, 4, beside=-1.0).tolist()[len(f):] == [False, True, True, True, True]
    assert not debris.floating_crumbs(w, faces, 4, gap=20.0).any()
    assert not debris.floating_crumbs(w, faces[len(f):], 4).any()  # only crumbs: `crumb_pieces` decides


def test_larger_pieces_float_apart_when_farther_than_their_extent():
    """Stray points far off a surface join into pieces of a few long faces: one farther from every larger piece
    than its own extent goes, and the crumb beside it with it (pieces are decided largest first); a piece as
    far but larger than its distance (a fragment of a sparsely seen stretch) stays."""
    v, f = grid_sheet(12)                                      # unit edges, 242 faces
    s, sf = grid_sheet(3)                                      # 8 faces, bounding-box diagonal 2.8
    tri = np.array([[0.0, 0.0, 0.0], [0.8, 0.0, 0.0], [0.0, 0.8, 0.0]])
    parts = [(v, f), (s + [4.0, 4.0, 9.0], sf), (s * 4.0 + [0.0, 0.0, -9.0], sf),
             (tri + [7.0, 4.0, 9.0], np.array([[0, 1, 2]]))]  # 9 above the grid, 1 beside the small piece
    w = np.concatenate([p for p, _ in parts])
    start = np.cumsum([0] + [len(p) for p, _ in parts])
    faces = np.concatenate([q + o for (_, q), o in zip(parts, start)])
    piece = np.repeat(np.arange(4), [len(q) for _, q in parts])
    flag = debris.floating_crumbs(w, faces, 4)
    assert [bool(flag[piece == i].all()) for i in range(4)] == [False, True, False, True]
    assert all(flag[piece == i].all() or not flag[piece == i].any() for i in range(4))
    assert not debris.floating_crumbs(w, faces, 4, max_apart=0).any()  # crumbs only: the small piece anchors it
