"""Lids over large holes and spans across unseen stretches: the point-cloud `fast` preset's surface with and
without them, and their settings.

A scanner leaves parts of a closed surface unsampled (the inside of a torus's hole, a concave corner). The
surface step (`dmesh.surface`) labels the triangulation's tets inside or outside and keeps the mesh faces
between the two; a hole in them of more than `lids.max_hole` (64) edges used to stay open. Now the inside tets'
own boundary closes it (the lids stage: `dmesh.solid.large_lids`), refined and faired by CGAL (the fair stage:
`dmesh.native.refine_and_fair`, density control factor `fair.density`, thin-plate continuity `fair.continuity` 1).
Where the tets' labelling closed such a stretch with faces of the triangulation that are walls (the mesh's own
faces, between samples on either side of the stretch), there was no hole to lid, and those long flat faces cut
the chord across it. Closed-part faces whose longest edge is over `spans.ratio` (6) times the median edge length
are now refined and faired with the lids, their corners held (`dmesh.surface.debris.long_faces`; `no spans`: as
before; `spans 4` / `spans 8`: other thresholds).

One `fast` run per input (seed 0), on the robustness sweep's inputs (`runs/paper`'s cache: 100K points of each
shape, `scan`: the 6-camera scan with estimated normals; `realistic`: the same with range noise 0.0025 and 1 %
outliers; `clean`: the exact samples); its final DMesh is then extracted again with each variant's surface
settings (the same call as the run's own extraction: `same` says whether the default variant reproduces the
run's mesh). Figures against the GT (100K samples per side): CD p2s, faces, boundary edges, components,
self-intersecting faces (pymeshlab); the lids' pieces, faces, the span faces, the vertices the refinement added
and the pieces dropped because their faired form crossed the surface (`flat lids` keeps every lid and span as
faces of the triangulation instead); `seconds`: the extraction alone.

Regenerate: `python -m studies lids` (14 runs and 140 extractions, about 40 minutes on one core; `--quick`:
the torus scan only).
"""
from __future__ import annotations

from eval.bench.common import markdown_table, write_report
from studies.surface_variants import REALISTIC, SCAN, cloud, extractions, same_as_run

INPUTS = (("torus", "scan", SCAN), ("genus2", "scan", SCAN), ("plant", "scan", SCAN), ("flag_box", "scan", SCAN),
          ("torus", "realistic", REALISTIC), ("genus2", "realistic", REALISTIC), ("plant", "realistic", REALISTIC),
          ("flag_box", "realistic", REALISTIC), ("torus", "clean", {}), ("plant", "clean", {}),
          # mixed shapes whose lid crossed the surface when faired (dropped now; flat lids is how it was kept)
          ("flag_box", "outliers 0.05", {"outliers": 0.05}), ("flag_box", "estimated normals", {"normals": "estimated"}),
          ("plant", "nonuniform 8", {"nonuniform": 8.0}),
          # long faces of a sampled stretch, not a span: the sparse end of a non-uniform cloud
          ("torus", "nonuniform 8", {"nonuniform": 8.0}))
#: (label, overrides of the run's SurfaceConfig)
VARIANTS = (("no lids", {"skip": ["lids"]}), ("flat lids", {"skip": ["fair"]}),
            ("faired, density sqrt(2)", {"fair.density": 2.0 ** 0.5}), ("faired (default)", {}),
            ("faired, density 8", {"fair.density": 8.0}), ("membrane (fairing 0)", {"fair.continuity": 0}),
            ("curvature (fairing 2)", {"fair.continuity": 2}), ("no spans", {"spans.ratio": 0.0}),
            ("spans 4", {"spans.ratio": 4.0}), ("spans 8", {"spans.ratio": 8.0}))


def _rows(shape: str, kind: str, corruption: dict) -> list[dict]:
    from eval.metrics import chamfer_l1_p2s, mesh_stats
    from eval.runner import load_gt

    points, normals, gt_path, category = cloud(shape, corruption)
    res, meshes = extractions(points, normals, VARIANTS)
    gt = load_gt(gt_path)
    rows = []
    for label, (mesh, seconds) in meshes.items():
        stats = mesh_stats(mesh)
        info = mesh.metadata.get("surface", {})
        same = same_as_run(mesh, res) if label == "faired (default)" else ""
        rows.append({"shape": shape, "class": category, "input": kind, "variant": label,
                     "cd_p2s": chamfer_l1_p2s(mesh, gt, n=100_000), "faces": stats["faces"],
                     "boundary_edges": stats["boundary_edges"], "components": stats["components"],
                     "self_intersecting_faces": stats["self_intersecting_faces"], "lids": info.get("lids", 0),
                     "lid_faces": info.get("lid_faces", 0), "span_faces": info.get("span_faces", 0),
                     "lid_vertices_added": info.get("lid_vertices_added", 0),
                     "lids_dropped": info.get("lids_dropped", 0),
                     "smooth_k": res.info.get("smooth_k"), "same": same, "seconds": seconds})
        print(f"{shape} {kind} {label}: CD p2s {rows[-1]['cd_p2s'] * 1e3:.3f} x1e-3, {stats['components']} "
              f"components, {stats['boundary_edges']} boundary edges", flush=True)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    import torch

    torch.set_num_threads(1)
    rows = [r for case in (INPUTS[:1] if quick else INPUTS) for r in _rows(*case)]
    shown = [{**r, "cd_p2s": r["cd_p2s"] * 1e3} for r in rows]
    cols = ["shape", "class", "input", "variant", "cd_p2s", "faces", "boundary_edges", "components",
            "self_intersecting_faces", "lids", "lid_faces", "span_faces", "lid_vertices_added", "lids_dropped", "smooth_k", "same",
            "seconds"]
    intro = __doc__.split("\n\nRegenerate")[0] + "\n\nCD p2s in the table is x1e-3 (the CSV holds raw distances)."
    write_report(out, "lids", "Lids over large holes, spans across unseen stretches", intro,
                 markdown_table(shown, cols, {"cd_p2s": ".3f", "seconds": ".1f"}), rows)


if __name__ == "__main__":
    main()
