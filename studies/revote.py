"""The second inside/outside vote of the surface step (`dmesh.solid.open_sheet_walls`): one vote against two.

An open sheet over a solid (a mushroom's cap over its stalk) fools the walks of the first vote: a walk that
crosses the solid's surface and then the sheet counts two crossings and calls the tet outside. The second
vote sets such sheets aside. Each case is one point-cloud run of DMesh (`fast` preset, 100K samples with
their normals, seed 0; once with `num_init` 2500, a coarse mesh like the `paper` preset's, and once with the
preset's 40K seeds) whose final state is extracted twice: "one vote" (the surface step with its revote stage
skipped, `surface.skip=[revote]`) and "two votes" (the default). Shapes: the mixed class (plant, mushroom, flag_box,
suzanne), where sheets and solids meet, and one closed and one open shape as controls.

Figures as in `eval.bench.quality` (`oriented`, `any_side`, watertight, boundary and non-manifold edges, CD p2s
x1e-3 in the GT frame), plus `components`, `set_aside` (walls left out of the second vote) and `hole_faces`
(faces that filling holes added: a lid across a solid cut by the first vote is one).
"""
from __future__ import annotations

import numpy as np

from eval.bench.common import markdown_table, write_report
from eval.bench.quality import SAMPLES, _gt, figures

SHAPES = ("plant", "mushroom", "flag_box", "suzanne", "torus", "bowl")
NUM_INIT = (2500, 40_000)


def _case(name: str, num_init: int) -> list[dict]:
    from datasets.sampling import sample_points
    from dmesh.recon.pointcloud import PointCloudConfig, reconstruct
    from eval.metrics import topology

    gt = _gt(name)
    pts, nrm = sample_points(gt, SAMPLES, 0)
    cfg = PointCloudConfig.fast(num_init=num_init, orient=False)
    res = reconstruct(pts, nrm, cfg)
    normals = ((np.asarray(pts, np.float64) - res.center) * res.scale, np.asarray(nrm, np.float64))
    rows = []
    for variant, revote in (("one vote", False), ("two votes", True)):
        surface = cfg.surface.with_overrides({"skip": [] if revote else ["revote"]})
        mesh = res.dmesh.extract_mesh(cfg.threshold, cfg.extraction, surface=surface, normals=normals)
        info = mesh.metadata.pop("surface")
        mesh.vertices = np.asarray(mesh.vertices) / res.scale + res.center
        rows.append({"shape": name, "num_init": num_init, "variant": variant} | figures(mesh, gt)
                    | {"components": int(topology(mesh.vertices, mesh.faces)["components"]),
                       "set_aside": info.get("sheets_set_aside", 0), "hole_faces": info.get("hole_faces", 0)})
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    rows = []
    for name in SHAPES[1:2] if quick else SHAPES:
        for num_init in NUM_INIT[:1] if quick else NUM_INIT:
            rows += _case(name, num_init)
    columns = ["shape", "num_init", "variant", "faces", "oriented", "any_side", "watertight", "boundary_edges",
               "nonmanifold_edges", "components", "set_aside", "hole_faces", "cd_p2s_1e3"]
    rows = [{c: r.get(c, "") for c in columns} for r in rows]
    table = markdown_table(rows, columns, {"oriented": ".4f", "any_side": ".4f", "cd_p2s_1e3": ".4g"})
    write_report(out, "revote", "The surface step's second vote: sheets over solids", __doc__, table, rows)


if __name__ == "__main__":
    main()
