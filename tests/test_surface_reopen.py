"""The `reopen` stage and `SurfaceConfig.mode`: a hole is closed only where the input shows surface across it.

References: a tube with cut ends (its ends are holes of the shape: no sample lies across them) and a sphere (no
hole: every patch is seen), each sampled, reconstructed and compared between the modes; the evidence test on a
sampled plane with a square gap, where which patch is seen is known by construction.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dmesh.surface import SurfaceConfig
from dmesh.surface.evidence import Evidence


def _plane(gap: float, n: int = 60) -> np.ndarray:
    """Samples on a grid of the square [-1, 1]^2 at z = 0, none in the square |x|, |y| < gap."""
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    keep = ~((np.abs(x) < gap) & (np.abs(y) < gap))
    return np.c_[x[keep], y[keep], np.zeros(keep.sum())]


def _patch(half: float, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles covering the square |x|, |y| <= half at height z."""
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_evidence_tells_a_gap_of_the_input_from_a_sampled_stretch():
    spacing = 2 / 59
    evidence = Evidence.of_samples(_plane(gap=0.3), k=8)
    assert np.allclose(np.median(evidence.spacing), spacing * (1 + np.sqrt(2)) / 2, rtol=0.2)
    piece = np.zeros(2, np.int64)
    over_gap = _patch(0.25)
    assert evidence.unseen_pieces(*over_gap, piece, 1, ratio=2.0, share=0.5)[0]
    over_samples = _patch(0.25, z=0.0)
    sampled = Evidence.of_samples(_plane(gap=0.0), k=8)
    assert not sampled.unseen_pieces(*over_samples, piece, 1, ratio=2.0, share=0.5)[0]
    # A patch above the plane is unseen however dense the samples below it.
    assert sampled.unseen_pieces(*_patch(0.25, z=0.5), piece, 1, ratio=2.0, share=0.5)[0]
    # A patch within a disc of `ratio` spacings is below what the sampling can show: not a hole.
    tiny = _patch(1.2 * spacing, z=0.5)
    assert not sampled.unseen_pieces(*tiny, piece, 1, ratio=2.0, share=0.5)[0]


def test_mode_is_checked():
    with pytest.raises(ValueError, match="SurfaceConfig.mode must be one of auto, closed, open"):
        SurfaceConfig(mode="capped")
    assert SurfaceConfig().with_overrides({"mode": "open"}).mode == "open"


def _tube(n: int = 12_000) -> tuple[np.ndarray, np.ndarray]:
    """Samples and normals of a tube of radius 0.1 and length 2 along z with both ends cut open."""
    mesh = trimesh.creation.cylinder(radius=0.1, height=2.0, sections=96)
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[np.abs(mesh.face_normals[:, 2]) < 0.5])
    points, face = trimesh.sample.sample_surface(mesh, n, seed=0)
    return points, mesh.face_normals[face]


def _reconstruct(points, normals, mode):
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct

    return reconstruct(points, normals, PointCloudConfig.from_preset("fast", {"surface.mode": mode}))


def _across_ends(mesh) -> int:
    """Faces whose centroid lies within half the tube's radius of its axis: faces across an end."""
    centre = np.asarray(mesh.triangles_center)
    return int((np.linalg.norm(centre[:, :2], axis=1) < 0.05).sum())


@pytest.fixture(scope="module")
def tube_meshes():
    points, normals = _tube()
    return {mode: _reconstruct(points, normals, mode) for mode in ("auto", "closed", "open")}


def test_a_tube_keeps_its_cut_ends_open_unless_told_it_is_closed(tube_meshes):
    auto, closed, opened = (tube_meshes[m].mesh for m in ("auto", "closed", "open"))
    assert _across_ends(closed) > 50  # closed: the lids cap both ends
    assert _across_ends(auto) == 0 and _across_ends(opened) == 0
    stages = tube_meshes["auto"].info["surface"]["stages"]
    assert stages["reopen"]["holes_reopened"] >= 2 and stages["reopen"]["dropped"] > 0
    assert "holes_reopened" not in tube_meshes["closed"].info["surface"]["stages"]["reopen"]


def test_a_sampled_closed_shape_stays_closed_in_auto():
    from datasets.normalize import normalize
    from datasets.sampling import sample_points
    from datasets.synthetic import generate

    points, normals = sample_points(normalize(generate("sphere"))[0], 8000, 0)
    auto = _reconstruct(points, normals, "auto")
    closed = _reconstruct(points, normals, "closed")
    assert auto.mesh.is_watertight
    assert np.array_equal(auto.mesh.faces, closed.mesh.faces)
    assert np.array_equal(auto.mesh.vertices, closed.mesh.vertices)


def test_without_samples_auto_closes_as_closed_does():
    """Multi-view input has no samples to judge a hole by: auto keeps the lids, as closed does."""
    from common import ball_labels, cloud_diagram
    from dmesh import solid
    from dmesh.surface import run

    pd = cloud_diagram(n=1500, seed=4)
    walls = solid.boundary_mask(pd, ball_labels(pd))
    centre = pd.points[pd.faces.astype(np.int64)].mean(1)
    holed = walls & ~(centre[:, 2] > 0.4)
    config = SurfaceConfig().with_overrides({"lids.max_hole": 8, "revote.min_faces": 8})
    auto = run(pd, holed, config=config)
    closed = run(pd, holed, config=config.with_overrides({"mode": "closed"}))
    assert auto.info["lids"] == 1 and np.array_equal(auto.faces, closed.faces)
    # With samples all over the ball, the lid is seen and stays; with samples only on the ball's lower half, the
    # cap is many spacings from any sample, a hole the input shows: it stays open.
    seen = run(pd, holed, samples=centre[walls], config=config)
    assert seen.info["holes_reopened"] == 0 and np.array_equal(seen.faces, closed.faces)
    unseen = run(pd, holed, samples=centre[walls & (centre[:, 2] < 0.0)], config=config)
    assert unseen.info["holes_reopened"] == 1 and unseen.closed == closed.info["closed_faces"] < closed.closed


def test_tet_fills_close_exactly_the_holes_left_open():
    """A hole that a least-area fill cannot close without crossing the surface is closed by the inside tets'
    boundary across it: here every hole of a ball with faces taken out, whose closed part plus the tet fills
    must be a closed 2-manifold again (each edge on exactly two faces)."""
    from common import ball_labels, cloud_diagram
    from dmesh import solid
    from dmesh.surface import STAGES
    from dmesh.surface.holes import tet_fills
    from dmesh.surface.state import SurfaceState
    from dmesh.surface.topology import edge_table

    pd = cloud_diagram(n=1500, seed=4)
    walls = solid.boundary_mask(pd, ball_labels(pd))
    holed = walls.copy()
    holed[np.flatnonzero(walls)[[0, 40, 80]]] = False
    state = SurfaceState(pd, holed, mode="closed")
    config = SurfaceConfig()
    for stage in STAGES[:4]:  # the labelling and the closed part
        state = stage.fn(state, getattr(config, stage.section) if stage.section else None)
    assert (edge_table(state.closed)[2] == 1).sum() >= 9  # three holes
    faces = tet_fills(state)
    counts = edge_table(np.concatenate([state.closed, faces]))[2]
    assert len(faces) >= 3 and (counts == 2).all()


@pytest.mark.parametrize("faired", [True, False])
def test_fills_that_still_cross_are_faired_like_lids(monkeypatch, faired):
    """Holes whose least-area fill crosses the surface and that no tet fill closes (here: every fill made to
    cross, tet fills off) get their fill anyway, marked as lids so that stage fair refines, fairs and, if it
    still crosses, drops it (`fills.faired`); without it they stay open."""
    from common import ball_labels, cloud_diagram
    from dmesh import solid
    from dmesh.surface import STAGES, holes
    from dmesh.surface.state import SurfaceState
    from dmesh.surface.topology import edge_table

    real = holes.fill_holes

    def crossing_all(vertices, faces, max_edges, uncrossed=True, **kw):
        if not uncrossed:
            return real(vertices, faces, max_edges, uncrossed=False, **kw)
        n = len(holes.hole_loops(np.asarray(faces)))
        return np.zeros((0, 3), np.int64), 0, n, n

    monkeypatch.setattr(holes, "fill_holes", crossing_all)
    pd = cloud_diagram(n=1500, seed=4)
    walls = solid.boundary_mask(pd, ball_labels(pd))
    holed = walls.copy()
    holed[np.flatnonzero(walls)[[0, 40, 80]]] = False
    state = SurfaceState(pd, holed, mode="closed")
    config = SurfaceConfig().with_overrides({"fills.tets": False, "fills.faired": faired})
    for stage in STAGES[:4]:
        state = stage.fn(state, getattr(config, stage.section) if stage.section else None)
    before = len(state.closed)
    state = holes.fills(state, config.fills)
    added = len(state.closed) - before
    assert state.info["holes_crossing"] >= 3
    if faired:
        assert state.info["faired_fills"] >= 3 and added == state.info["faired_fill_faces"] > 0
        assert state.lid[before:].all() and state.fill[before:].all() and not state.lid[:before].any()
        assert (edge_table(state.closed)[2] == 2).all()  # closed again
    else:
        assert added == 0 and (edge_table(state.closed)[2] == 1).sum() >= 9
