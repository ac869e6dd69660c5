"""Mesh-quality metrics: signed normal consistency and oriented fraction against exact references (a mesh
against itself, its inverted copy, a copy with a known set of faces reversed), topology figures of meshes
whose genus, components, boundary and non-manifold elements are known by construction, and the tables and
CLI that show them."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from eval.metrics import compute_metrics, mesh_stats, topology


def _inverted(m: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(m.vertices, m.faces[:, ::-1], process=False)


def _open_cylinder(sections: int = 16) -> trimesh.Trimesh:
    """A tube without caps: 2 sections-edge boundary loops, Euler characteristic 0."""
    c = trimesh.creation.cylinder(radius=1.0, height=2.0, sections=sections)
    side = np.abs(c.face_normals[:, 2]) < 0.5
    return trimesh.Trimesh(c.vertices, c.faces[side], process=False)


def _with_fins(m: trimesh.Trimesh, k: int) -> tuple[trimesh.Trimesh, int]:
    """m plus one fin triangle on each of k distinct edges (each such edge gets a third face); returns the
    mesh and the number of distinct edge endpoints (the vertices where a second fan of faces starts)."""
    edges = m.edges_unique[:: max(1, len(m.edges_unique) // k)][:k]
    v = [m.vertices]
    f = [m.faces]
    n = len(m.vertices)
    for i, (a, b) in enumerate(edges):
        tip = m.vertices[[a, b]].mean(axis=0) * 1.5 + [0.0, 0.0, 0.3]
        v.append(tip[None])
        f.append([[a, b, n + i]])
    return trimesh.Trimesh(np.vstack(v), np.vstack(f), process=False), len(np.unique(edges))


# ------------------------------------------------------------------------------------------ orientation

@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(3)


def test_inverted_copy_fails_the_oriented_metrics(sphere):
    m = compute_metrics(_inverted(sphere), sphere, n=20_000, self_intersections=False)
    assert m["normal_consistency"] > 0.99                       # orientation-blind: the inversion is invisible
    assert m["normal_consistency_oriented"] == pytest.approx(-1.0, abs=1e-6)
    assert m["oriented_fraction"] == pytest.approx(0.0, abs=1e-9)
    same = compute_metrics(sphere, sphere, n=20_000, self_intersections=False)
    assert same["normal_consistency_oriented"] == pytest.approx(1.0, abs=1e-6)
    assert same["oriented_fraction"] == pytest.approx(1.0, abs=1e-9)
    assert same["gt_orientation"] == "outward" and same["gt_orientable"] is True


def test_oriented_fraction_is_the_area_of_the_faces_that_agree(sphere):
    # Reverse the faces above z = 0.3: each face's closest GT point is on that same face (its centroid lies
    # on it), so the expected fraction is exactly the area share of the unreversed faces.
    up = sphere.triangles_center[:, 2] > 0.3
    f = sphere.faces.copy()
    f[up] = f[up][:, ::-1]
    pred = trimesh.Trimesh(sphere.vertices, f, process=False)
    m = compute_metrics(pred, sphere, n=40_000, self_intersections=False)
    share = sphere.area_faces[~up].sum() / sphere.area
    assert m["oriented_fraction"] == pytest.approx(share, abs=1e-9)
    # Signed NC: samples on reversed faces give -1, others +1 (expected 2 share - 1); 4e4 samples per side
    # leave a standard error of about 0.005, 0.03 is 6 of them.
    assert m["normal_consistency_oriented"] == pytest.approx(2 * share - 1, abs=0.03)
    assert m["inconsistent_winding_edges"] > 0 and m["winding_consistent"] is False
    assert m["genus"] == 0                                        # still an orientable sphere, wound badly


def test_any_side_frees_the_side_of_open_pieces_only(sphere):
    # GT: a closed sphere and, beside it, an open tube. The tube's side is a convention (the any-side figure
    # lets each open piece take its better side); the sphere's is not (it must face outward).
    tube = _open_cylinder(32)
    tube = trimesh.Trimesh(tube.vertices + [4.0, 0.0, 0.0], tube.faces, process=False)
    gt = trimesh.util.concatenate([sphere, tube])
    a_sphere, a_tube = sphere.area, tube.area
    both = a_sphere + a_tube

    def pred(sphere_faces, tube_faces):
        return trimesh.Trimesh(gt.vertices, np.vstack([sphere_faces, tube_faces + len(sphere.vertices)]),
                               process=False)

    m = compute_metrics(pred(sphere.faces, tube.faces[:, ::-1]), gt, n=5000, self_intersections=False)
    assert m["oriented_fraction"] == pytest.approx(a_sphere / both, abs=1e-9)
    assert m["oriented_fraction_any_side"] == pytest.approx(1.0, abs=1e-9)
    m = compute_metrics(pred(sphere.faces[:, ::-1], tube.faces), gt, n=5000, self_intersections=False)
    assert m["oriented_fraction"] == pytest.approx(a_tube / both, abs=1e-9)
    assert m["oriented_fraction_any_side"] == pytest.approx(a_tube / both, abs=1e-9)
    # Half of the tube reversed: one piece (the two halves share two-face edges), wound inconsistently, so
    # no choice of side puts more than its larger half right.
    up = tube.triangles_center[:, 2] > 0.3
    tf = tube.faces.copy()
    tf[up] = tf[up][:, ::-1]
    m = compute_metrics(pred(sphere.faces, tf), gt, n=5000, self_intersections=False)
    larger = max(tube.area_faces[up].sum(), tube.area_faces[~up].sum())
    assert m["oriented_fraction_any_side"] == pytest.approx((a_sphere + larger) / both, abs=1e-9)
    assert m["oriented_fraction_any_side"] < 0.99


def test_inside_out_gt_is_flipped_inside_compute_metrics(sphere):
    m = compute_metrics(sphere, _inverted(sphere), n=5000, self_intersections=False)
    assert m["gt_orientation"] == "flipped" and m["gt_orientable"] is True
    assert m["oriented_fraction"] == pytest.approx(1.0) and m["normal_consistency_oriented"] == pytest.approx(1.0)


def test_non_orientable_gt_gets_no_oriented_figures():
    from datasets.synthetic import generate

    mobius = generate("mobius", seed=0)
    m = compute_metrics(mobius, mobius, n=5000, self_intersections=False)
    assert m["gt_orientation"] == "non_orientable" and m["gt_orientable"] is False
    assert math.isnan(m["normal_consistency_oriented"]) and math.isnan(m["oriented_fraction"])
    assert m["normal_consistency"] > 0.99                          # the unsigned one still applies
    assert m["genus"] is None and m["gt_genus"] is None and m["boundary_loops"] == 1


def test_empty_prediction_has_nan_oriented_figures(sphere):
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
    m = compute_metrics(empty, sphere, n=500)
    assert math.isnan(m["normal_consistency_oriented"]) and math.isnan(m["oriented_fraction"])
    assert m["faces"] == 0 and m["genus"] is None and m["gt_genus"] == 0


# ---------------------------------------------------------------------------------------------- topology

def test_topology_of_known_surfaces():
    torus = topology(*(lambda t: (t.vertices, t.faces))(trimesh.creation.torus(1.0, 0.3)))
    assert (torus["genus"], torus["euler_characteristic"], torus["components"]) == (1, 0, 1)
    assert torus["watertight"] and torus["boundary_edges"] == 0 and torus["non_manifold_edges"] == 0

    a = trimesh.creation.icosphere(2)
    b = a.copy()
    b.apply_translation([3.0, 0.0, 0.0])
    two = trimesh.util.concatenate([a, b])
    t = topology(two.vertices, two.faces)
    assert (t["components"], t["euler_characteristic"], t["genus"], t["watertight"]) == (2, 4, 0, True)

    tube = _open_cylinder(sections=16)
    t = topology(tube.vertices, tube.faces)
    assert (t["boundary_loops"], t["boundary_edges"], t["euler_characteristic"], t["genus"]) == (2, 32, 0, 0)
    assert t["watertight"] is False and t["components"] == 1

    # A torus with one face removed: one boundary loop of 3 edges, chi = -1, still genus 1.
    tor = trimesh.creation.torus(1.0, 0.3)
    t = topology(tor.vertices, tor.faces[1:])
    assert (t["boundary_loops"], t["boundary_edges"], t["euler_characteristic"], t["genus"]) == (1, 3, -1, 1)


@pytest.mark.parametrize("k", [1, 3, 7])
def test_fins_give_exactly_the_non_manifold_edges_built(k):
    mesh, ends = _with_fins(trimesh.creation.icosphere(2), k)
    t = topology(mesh.vertices, mesh.faces)
    assert t["non_manifold_edges"] == k
    assert t["non_manifold_vertices"] == ends        # each fin starts a second fan at both ends of its edge
    assert t["boundary_edges"] == 2 * k and t["genus"] is None and t["watertight"] is False


def test_bow_tie_vertex_and_reversed_face():
    bow = topology([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], [[0, 1, 2], [0, 3, 4]])
    assert (bow["non_manifold_vertices"], bow["non_manifold_edges"], bow["components"]) == (1, 0, 1)
    assert bow["genus"] is None and bow["boundary_loops"] == 1
    box = trimesh.creation.box()
    f = box.faces.copy()
    f[0] = f[0, ::-1]
    t = topology(box.vertices, f)
    assert t["inconsistent_winding_edges"] == 3 and t["winding_consistent"] is False and t["genus"] == 0
    empty = topology(np.zeros((0, 3)), np.zeros((0, 3), int))
    assert empty["edges"] == 0 and empty["genus"] is None and empty["watertight"] is False


def test_compute_metrics_counts_a_pinch_split_into_copies_on_one_point(sphere):
    """Two spheres touching at one point, written with that point twice: a file of it reads back pinched,
    so the metrics (as `load_mesh` and `dmesh metrics`) merge vertices by position before counting."""
    a = trimesh.Trimesh(sphere.vertices, sphere.faces, process=False)
    top = int(np.argmax(a.vertices[:, 2]))
    b = trimesh.Trimesh(a.vertices * [1, 1, -1] + [0, 0, 2 * a.vertices[top, 2]], a.faces[:, ::-1], process=False)
    pair = trimesh.Trimesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + len(a.vertices)]),
                           process=False)
    as_written = topology(pair.vertices, pair.faces)
    assert (as_written["non_manifold_vertices"], as_written["components"]) == (0, 2)
    m = compute_metrics(pair, sphere, n=2000, self_intersections=False)
    assert (m["non_manifold_vertices"], m["components"], m["vertices"]) == (1, 1, 2 * len(a.vertices) - 1)
    assert m["watertight"] and m["non_manifold_edges"] == 0 and m["genus"] is None


def test_topology_agrees_with_trimesh():
    """Euler characteristic, watertightness and winding consistency against trimesh's own, on meshes with
    boundaries, several components, unused vertices and a reversed face."""
    tube = _open_cylinder(12)
    unused = trimesh.Trimesh(np.vstack([tube.vertices, [[5.0, 5.0, 5.0]]]), tube.faces, process=False)
    ico = trimesh.creation.icosphere(1)
    f = ico.faces.copy()
    f[3] = f[3, ::-1]
    cases = [trimesh.creation.box(), trimesh.creation.torus(1.0, 0.4), tube, unused, ico,
             trimesh.util.concatenate([ico, trimesh.creation.torus(3.0, 0.5)]),
             trimesh.Trimesh(ico.vertices, f, process=False)]
    for m in cases:
        t = topology(m.vertices, m.faces)
        ref = trimesh.Trimesh(m.vertices, m.faces, process=False)
        ref.remove_unreferenced_vertices()
        assert t["euler_characteristic"] == ref.euler_number
        assert t["watertight"] == ref.is_watertight and t["winding_consistent"] == ref.is_winding_consistent
        assert t["components"] == len(ref.split(only_watertight=False))


def test_mesh_stats_and_compute_metrics_carry_the_topology_keys():
    torus = trimesh.creation.torus(1.0, 0.3)
    s = mesh_stats(torus, self_intersections=False)
    assert (s["genus"], s["euler_characteristic"], s["boundary_loops"], s["non_manifold_vertices"]) == (1, 0, 0, 0)
    m = compute_metrics(_open_cylinder(), torus, n=2000, self_intersections=False)
    assert (m["gt_genus"], m["gt_components"], m["gt_watertight"], m["gt_boundary_edges"]) == (1, 1, True, 0)
    assert (m["genus"], m["boundary_loops"], m["watertight"]) == (0, 2, False)
    assert m["gt_euler_characteristic"] == 0 and m["gt_non_manifold_edges"] == 0


# ------------------------------------------------------------------------------------------ CLI, tables

def test_cli_metrics_json_has_the_quality_keys(tmp_path, capsys, sphere):
    from eval.cli import main

    gt, pred = tmp_path / "gt_inside_out.ply", tmp_path / "pred.ply"
    _inverted(sphere).export(gt)
    sphere.export(pred)
    assert main(["metrics", str(pred), str(gt), "--samples", "2000", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["gt_orientation"] == "flipped" and data["gt_orientable"] is True
    assert data["oriented_fraction"] == pytest.approx(1.0) and data["normal_consistency_oriented"] > 0.999
    for key in ("watertight", "boundary_edges", "boundary_loops", "non_manifold_edges", "non_manifold_vertices",
                "components", "euler_characteristic", "genus", "gt_genus", "gt_euler_characteristic",
                "self_intersecting_faces", "inconsistent_winding_edges"):
        assert key in data, key


def test_quality_columns_in_table2(tmp_path):
    from eval.reports import tables
    from eval.store import Store

    def row(key, shape, metrics):
        return {"key": key, "method": "psr", "config_label": "", "shape": shape, "category": "closed",
                "input_kind": "pointcloud", "config_json": {}, "inputs_json": {"metric_samples": 100},
                "seed": 0, "status": "done", "gt_hash": "0" * 64, "code_version": "test",
                "metrics_json": {"cd_p2s": 1e-3, "cd_l1": 2e-3, **metrics}, "timings_json": {"total": 1.0}}

    good = {"normal_consistency_oriented": 0.98, "oriented_fraction": 1.0, "oriented_fraction_any_side": 1.0,
            "watertight": True,
            "non_manifold_edges": 0, "non_manifold_vertices": 0, "boundary_edges": 0, "components": 1,
            "gt_components": 1, "genus": 1, "gt_genus": 1, "self_intersecting_faces": 0, "winding_consistent": True}
    # consistently wound but facing the other way in part (an open sheet whose side was not observable)
    bad = {**good, "normal_consistency_oriented": 0.2, "oriented_fraction": 0.6, "oriented_fraction_any_side": 0.9,
           "watertight": False,
           "non_manifold_edges": 4, "non_manifold_vertices": 6, "boundary_edges": 10, "genus": None,
           "self_intersecting_faces": -1}
    with Store(tmp_path / "s.sqlite") as s:
        s.upsert(row("a", "torus", good))
        s.upsert(row("b", "torus@1", bad))
        df = s.dataframe()
    (r,) = tables.table2(df, "pointcloud")
    assert r["normal_consistency_oriented"] == pytest.approx(0.59)
    assert (r["oriented_fraction"], r["oriented_fraction_min"]) == (pytest.approx(0.8), 0.6)
    assert (r["oriented_fraction_any_side"], r["oriented_fraction_any_side_min"]) == (pytest.approx(0.95), 0.9)
    assert (r["watertight_share"], r["no_nm_edges_share"], r["topology_match_share"]) == (0.5, 0.5, 0.5)
    assert r["winding_share"] == 1.0
    assert (r["non_manifold_edges"], r["boundary_edges"], r["self_intersecting_faces"]) == (2.0, 5.0, 0.0)
    md, _ = tables.write_table2(df, tmp_path / "rep", "pointcloud")
    text = md.read_text()
    assert ("## Mesh quality by class" in text
            and "| psr | closed | dev | 2 | 0.590 | 80.0 | 60.0 | 95.0 | 90.0 | 100 | 50 | 50 |" in text)
    assert "## Runs: mesh quality" in text and "| 1 (GT 1) | - (GT 1) |" in text
