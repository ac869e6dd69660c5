"""Output quality of DMesh meshes before and after the tet-based surface step (`dmesh.surface`).

Cases (issue [quality]), one DMesh run each, whose final state is extracted twice (multi-view: two runs of
the same seed, one without the orientation step):
- "before": the extracted faces as they were output until now, wound per connected component
  (`dmesh.surface.orient_faces`; mesh to DMesh: the WDT's sorted triples, not wound at all);
- "after": the library's output now (`DMesh.extract_mesh(..., surface=...)`, the multi-view run's own surface
  step, mesh_to_dmesh's `_orient`).

Inputs: point cloud, `fast` preset, 100K samples with their normals, on torus, genus2, spot, bowl, plant,
flag_box and suzanne (seed 0), and spot with seeds 1-4; multi-view, `depth` preset on the harness capture
(64 views, 256 pixels) of torus, bowl and plant; mesh to DMesh, the 60-vertex torus of tests/test_mesh_to_dmesh.py.

Figures: `oriented`, the area fraction of faces whose normal agrees with the GT normal at the GT point
closest to the face centroid (closed GTs turned outward first, `datasets.meshes.orient_outward`); `any_side`,
the same with each open piece on whichever side agrees more (`eval.metrics.oriented_fractions`: the side of a
sheet seen in two-sided images is a convention, its consistency is not); watertight (every edge has two
faces); boundary edges; non-manifold edges (more than two faces) and vertices (more than one fan of faces);
edges whose two faces run them the same way (inconsistent winding), all four counted with the vertices
merged by position, as a file of the mesh reads back (a pinch split into copies on one point is still a
pinch); CD p2s (`eval.metrics.chamfer_l1_p2s`,
x1e-3, GT frame: vertex mean 0, max vertex norm 1); `surface_s`, the seconds of the surface step.
"""
from __future__ import annotations

import time

import numpy as np

from eval.bench.common import markdown_table, write_report

POINTCLOUD = ("torus", "genus2", "spot", "bowl", "plant", "flag_box", "suzanne")
REPEATS = ("spot", (1, 2, 3, 4))
MULTIVIEW = ("torus", "bowl", "plant")
FILES = {"spot": "closed/spot.obj", "suzanne": "mixed/suzanne.obj"}
SAMPLES = 100_000


def _gt(name: str):
    from datasets.meshes import load_mesh, orient_outward
    from datasets.normalize import normalize
    from datasets.synthetic import generate
    from eval.sweep import default_data_root

    mesh = load_mesh(default_data_root() / FILES[name]) if name in FILES else generate(name)
    return orient_outward(normalize(mesh)[0], name, quiet=True)[0]


def figures(mesh, gt) -> dict:
    from datasets.meshes import merge_vertices
    from dmesh.surface.topology import edge_table, nonmanifold_vertices
    from eval.metrics import chamfer_l1_p2s, oriented_fractions, topology

    # Topology as a file of the mesh reads back: vertices on one position merged (as `compute_metrics`).
    v, f = merge_vertices(mesh.vertices, mesh.faces) if len(mesh.faces) else (mesh.vertices, np.zeros((0, 3), int))
    counts = edge_table(f)[2]
    orient = oriented_fractions(mesh, gt)
    return {"faces": int(len(f)), "oriented": orient["oriented_fraction"],
            "any_side": orient["oriented_fraction_any_side"],
            "watertight": bool(len(f) and (counts == 2).all()), "boundary_edges": int((counts == 1).sum()),
            "nonmanifold_edges": int((counts > 2).sum()),
            "nonmanifold_vertices": int(len(nonmanifold_vertices(f))),
            "inconsistent_winding_edges": int(topology(v, f)["inconsistent_winding_edges"]),
            "cd_p2s_1e3": 1e3 * chamfer_l1_p2s(mesh, gt)}


def _pointcloud(name: str, seed: int) -> list[dict]:
    from datasets.sampling import sample_points
    from dmesh.recon.pointcloud import PointCloudConfig, reconstruct
    from dmesh.surface import orient_faces

    gt = _gt(name)
    pts, nrm = sample_points(gt, SAMPLES, seed)
    cfg = PointCloudConfig.fast(seed=seed, orient=False)
    res = reconstruct(pts, nrm, cfg)
    before = res.mesh.copy()
    orient_faces(before)
    t0 = time.perf_counter()
    after = res.dmesh.extract_mesh(cfg.threshold, cfg.extraction, surface=cfg.surface,
                                   normals=((np.asarray(pts, np.float64) - res.center) * res.scale,
                                            np.asarray(nrm, np.float64)))
    seconds = time.perf_counter() - t0
    after.vertices = np.asarray(after.vertices) / res.scale + res.center
    case = {"input": "pointcloud", "shape": name, "seed": seed}
    return [case | {"variant": "before"} | figures(before, gt),
            case | {"variant": "after"} | figures(after, gt) | {"surface_s": seconds}]


def _multiview(name: str) -> list[dict]:
    from datasets import capture
    from dmesh.recon import multiview as mv
    from dmesh.surface import orient_faces

    gt = _gt(name)
    views = capture.capture(gt, views=64, resolution=256)
    before = mv.reconstruct(views, mv.MultiViewConfig.depth(orient=False)).mesh.copy()
    orient_faces(before)
    after = mv.reconstruct(views, mv.MultiViewConfig.depth())  # the same run, as the library outputs it
    case = {"input": "multiview", "shape": name, "seed": 0}
    return [case | {"variant": "before"} | figures(before, gt),
            case | {"variant": "after"} | figures(after.mesh, gt) | {"surface_s": after.timings.get("orient")}]


def _mesh_to_dmesh() -> list[dict]:
    import trimesh

    from dmesh.recon.mesh_to_dmesh import fast_config, mesh_to_dmesh

    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.45, major_sections=10, minor_sections=6)
    v = torus.vertices - torus.vertices.mean(0)
    v = v / np.linalg.norm(v, axis=1).max() * 0.8
    gt = trimesh.Trimesh(v, torus.faces, process=False)
    r = mesh_to_dmesh(v, torus.faces, fast_config(steps=800, insert_every=200, decay=1.0))
    before = trimesh.Trimesh(r.best.points, np.sort(r.best.faces, axis=1), process=False)
    after = trimesh.Trimesh(r.best.points, r.best.faces, process=False)
    case = {"input": "mesh", "shape": "torus_60v", "seed": 0}
    return [case | {"variant": "before"} | figures(before, gt), case | {"variant": "after"} | figures(after, gt)]


def main(out: str = "reports", quick: bool = False) -> None:
    shapes = POINTCLOUD[:1] if quick else POINTCLOUD
    rows = []
    for name in shapes:
        rows += _pointcloud(name, 0)
    if not quick:
        for seed in REPEATS[1]:
            rows += _pointcloud(REPEATS[0], seed)
    for name in MULTIVIEW[:1] if quick else MULTIVIEW:
        rows += _multiview(name)
    rows += _mesh_to_dmesh()
    columns = ["input", "shape", "seed", "variant", "faces", "oriented", "any_side", "watertight", "boundary_edges",
               "nonmanifold_edges", "nonmanifold_vertices", "inconsistent_winding_edges", "cd_p2s_1e3", "surface_s"]
    rows = [{c: r.get(c, "") for c in columns} for r in rows]
    table = markdown_table(rows, columns,
                           {"oriented": ".4f", "any_side": ".4f", "cd_p2s_1e3": ".4g", "surface_s": ".1f"})
    write_report(out, "bench_quality", "Output quality: orientation, watertightness, manifoldness", __doc__, table,
                 rows)


if __name__ == "__main__":
    main()
