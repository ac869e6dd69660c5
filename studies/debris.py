"""Stray pieces and small holes of sheets: the point-cloud `fast` preset's surface with and without their clean-up.

Noise in the input (and, less often, a clean sample of a thin part) leaves sheets riddled with small holes and
strewn with pieces of a triangle or two lying in the band of the surface beside them. The extraction
(the surface step, `dmesh.surface`) now drops a piece of at most `stacked.max_faces` (64) faces lying within
`stacked.within` (1) local edge lengths over a larger piece (`dmesh.surface.debris.stacked_pieces`: over one of
its faces, not beside it in a hole), and fills a sheet's holes of at most `sheet_holes.max_edges` (24) edges and
as many of the piece's mean edge lengths, never a piece's longest loop (its rim) nor one whose area is over a
quarter of its piece's (`dmesh.surface.holes.sheet_hole_loops`, filled like the closed part's holes by
`dmesh.surface.holes.fill_holes`), unless a vertex of its loop lies off the surface its neighbouring vertices
form (`sheet_holes.stray_off`: an outlier the mesh reached; `sheet holes beside strays too` fills those as well,
as the first version did). A piece of at most 4 faces floating more than `crumbs.floating` median edge lengths
from every larger piece is dropped unless it lies in the plane of the surface nearest it
(`dmesh.surface.debris.floating_crumbs`, `crumbs.beside`; `floating crumbs kept`: as before the test), and so is
a piece of up to `crumbs.floating_max_faces` faces floating as far and farther than its own extent (`floating
crumbs only`: as before that). The settings are `SurfaceConfig`'s sections (docs/surface.md).

One `fast` run per input (seed 0), on the robustness sweep's inputs (`runs/paper`'s cache: 100K points of each
shape; `noise`: Gaussian noise of that fraction of the radius; `scan`: the 6-camera scan with estimated normals;
`realistic`: the same with range noise 0.0025 and 1 % outliers; `outliers`: that fraction of the points
scattered in the bounding box; `clean`: the exact samples); its final DMesh is
then extracted again with each variant's surface settings (the same call as the run's own extraction: `same`
says whether the default variant reproduces the run's mesh; `stacked beside faces too` drops a piece near a
larger one's plane even where it lies in a hole of it, as the first version did). Figures against the GT (100K samples per side):
CD p2s, faces, boundary edges, components (the GT's beside them), non-manifold edges, edges whose two faces
disagree in winding, self-intersecting faces (pymeshlab); the pieces' faces dropped, the holes filled and the
edges kept apart as seams (`seams_cut`: edges a dropped piece hung on, where the faces left would join in a
twist); `seconds`: the extraction alone.

Regenerate: `python -m studies debris` (17 runs and 170 extractions, about 50 minutes on one core;
`--quick`: the wavy sheet with noise 0.01 only).
"""
from __future__ import annotations

from eval.bench.common import markdown_table, write_report
from studies.surface_variants import REALISTIC, SCAN, cloud, extractions, same_as_run

INPUTS = (("wavy_sheet", "noise 0.01", {"noise": 0.01}), ("wavy_sheet", "clean", {}),
          ("wavy_sheet", "noise 0.0025", {"noise": 0.0025}), ("bowl", "clean", {}), ("bowl", "noise 0.01", {"noise": 0.01}),
          ("plant", "clean", {}), ("plant", "noise 0.0025", {"noise": 0.0025}), ("plant", "noise 0.01", {"noise": 0.01}),
          ("plant", "scan", SCAN), ("flag_box", "clean", {}), ("flag_box", "noise 0.01", {"noise": 0.01}),
          ("flag_box", "scan", SCAN), ("flag_box", "realistic", REALISTIC), ("torus", "clean", {}),
          ("mixed/suzanne.obj", "clean", {}), ("bowl", "outliers 0.1", {"outliers": 0.1}),
          ("wavy_sheet", "outliers 0.1", {"outliers": 0.1}), ("flag_box", "outliers 0.1", {"outliers": 0.1}))
#: (label, overrides of the run's SurfaceConfig)
VARIANTS = (("neither (before)", {"skip": ["stacked", "sheet_holes"]}),
            ("stacked pieces only", {"skip": ["sheet_holes"]}), ("sheet holes only", {"skip": ["stacked"]}),
            ("both (default)", {}), ("stacked within 0.5", {"stacked.within": 0.5}),
            ("stacked beside faces too", {"stacked.over": 1e9}),
            ("sheet holes beside strays too", {"sheet_holes.stray_off": float("inf")}),
            ("floating crumbs kept", {"crumbs.floating": float("inf")}),
            ("floating crumbs only", {"crumbs.floating_max_faces": 0}),
            ("sheet holes up to 12", {"sheet_holes.max_edges": 12}),
            ("sheet holes up to 48", {"sheet_holes.max_edges": 48}))


def _rows(shape: str, kind: str, corruption: dict) -> list[dict]:
    from eval.metrics import chamfer_l1_p2s, mesh_stats
    from eval.runner import load_gt

    points, normals, gt_path, category = cloud(shape, corruption)
    res, meshes = extractions(points, normals, VARIANTS)
    gt = load_gt(gt_path)
    gt_components = mesh_stats(gt)["components"]
    rows = []
    for label, (mesh, seconds) in meshes.items():
        stats = mesh_stats(mesh)
        info = mesh.metadata.get("surface", {})
        rows.append({"shape": shape, "class": category, "input": kind, "variant": label,
                     "cd_p2s": chamfer_l1_p2s(mesh, gt, n=100_000), "faces": stats["faces"],
                     "boundary_edges": stats["boundary_edges"], "components": stats["components"],
                     "gt_components": gt_components, "nonmanifold_edges": stats["non_manifold_edges"],
                     "inconsistent_winding_edges": stats["inconsistent_winding_edges"],
                     "self_intersecting_faces": stats["self_intersecting_faces"],
                     "stacked_dropped": info.get("stacked_dropped", 0),
                     "sheet_holes_filled": info.get("sheet_holes_filled", 0), "seams_cut": info.get("seams_cut", 0),
                     "same": same_as_run(mesh, res) if label == "both (default)" else "", "seconds": seconds})
        print(f"{shape} {kind} {label}: CD p2s {rows[-1]['cd_p2s'] * 1e3:.4f} x1e-3, {stats['components']} "
              f"components, {stats['boundary_edges']} boundary edges, {stats['non_manifold_edges']} NM edges, "
              f"{stats['inconsistent_winding_edges']} seam edges, {stats['self_intersecting_faces']} self-int.", flush=True)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    import torch

    torch.set_num_threads(1)
    rows = [r for case in (INPUTS[:1] if quick else INPUTS) for r in _rows(*case)]
    shown = [{**r, "cd_p2s": r["cd_p2s"] * 1e3} for r in rows]
    cols = ["shape", "class", "input", "variant", "cd_p2s", "faces", "boundary_edges", "components", "gt_components",
            "nonmanifold_edges", "inconsistent_winding_edges", "self_intersecting_faces", "stacked_dropped", "sheet_holes_filled", "seams_cut", "same", "seconds"]
    intro = __doc__.split("\n\nRegenerate")[0] + "\n\nCD p2s in the table is x1e-3 (the CSV holds raw distances)."
    write_report(out, "debris", "Stray pieces and small holes of sheets", intro,
                 markdown_table(shown, cols, {"cd_p2s": ".4f", "seconds": ".1f"}), rows)


if __name__ == "__main__":
    main()
