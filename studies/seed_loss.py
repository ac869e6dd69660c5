"""Where the seeds go during phase-1 steps: why gradient steps cost faces (point clouds).

Recipes on the torus (100K samples with normals, seed 0), the state after every few phase-1 steps:

- `fast` start + position steps (40K seeds and their poles; lr = update bound = 1e-4, `tangent_weight` 0.2,
  positions only: the mildest steps tried in README's "Why the steps stall"). A pole lies near the medial
  axis, R from its seed, much farther than the seed spacing h. A tet of three seeds and a pole has a
  circumsphere of radius about R through the seeds, so a neighbouring seed that moves about h^2 / (2R)
  towards the pole enters it and the tet is replaced by tets of four seeds (all real). `tolerance` is that
  estimate, with h the median distance from a seed to its nearest seed and R the median distance to its
  nearest imaginary point. Once the steps exceed it, all-real tets join into slabs (`largest cluster`), the
  one-sheet extraction keeps one side of each slab by one normal per slab, and seeds leave the mesh.
- `paper` preset (10K seeds and all their Voronoi vertices; all parameters, lr 3e-4): the seeds stay real,
  but the weight steps (weights start at 1 and are clamped to [0, 1], as upstream) shrink cells until their
  points drop out of the triangulation (`present`).
- The same recipe at the `fast` preset's density (40K seeds and all their Voronoi vertices), once as
  published and once without weight steps (positions and reals only): does a dense start with the paper's
  imaginary points, nearer their seeds than poles, keep what the steps would otherwise lose?

Columns: `present` points in the weighted Delaunay triangulation, of `points`; `seeds on mesh` real points
that are vertices of a sheet-mode face; faces of the "all" and "sheet" extractions (`dmesh.extract`); the
largest cluster of all-real tets joined through faces; CD p2s x1e-3 of the sheet-mode mesh (the monitor's
20K samples per side; no surface step).
"""
from __future__ import annotations

import numpy as np

from eval.bench.common import markdown_table, write_report

#: (label, preset, overrides, phase-1 steps, steps between rows).
CASES = (
    ("fast start + position steps", "fast",
     {"tangent_weight": 0.2, "lr": 1e-4, "update_bound": 1e-4, "train_phase1": ("points",)}, 10, 2),
    ("paper preset", "paper", {}, 100, 20),
    ("paper preset, 40K seeds", "paper", {"num_init": 40_000}, 40, 10),
    ("paper preset, 40K seeds, no weight steps", "paper", {"num_init": 40_000, "train_phase1": ("points", "reals")},
     40, 10),
)


def _largest_real_cluster(pd, real: np.ndarray) -> int:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    real_tet = real[pd.tets].all(1)
    if not real_tet.any():
        return 0
    ft = pd.face_tets
    both = (ft >= 0).all(1)
    both[both] &= real_tet[ft[both, 0]] & real_tet[ft[both, 1]]
    T = len(pd.tets)
    _, label = connected_components(coo_matrix((np.ones(int(both.sum())), (ft[both, 0], ft[both, 1])),
                                               shape=(T, T)), directed=False)
    return int(np.bincount(label[real_tet]).max())


def _tolerance(points: np.ndarray, real: np.ndarray) -> tuple[float, float, float]:
    """(h, R, h^2 / 2R): median seed spacing, median seed-to-nearest-imaginary distance, the move that breaks
    a seed-seed-seed-pole tet."""
    from scipy.spatial import cKDTree

    seeds, imag = points[real], points[~real]
    h = float(np.median(cKDTree(seeds).query(seeds, k=2)[0][:, 1]))
    r = float(np.median(cKDTree(imag).query(seeds)[0]))
    return h, r, h * h / (2 * r)


def _case(label: str, preset: str, overrides: dict, steps: int, every: int) -> list[dict]:
    from datasets.sampling import sample_points
    from dmesh.extract import mesh_faces, to_trimesh
    from dmesh.model import DMesh
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct
    from eval.bench.quality import _gt
    from eval.metrics import chamfer_l1_p2s
    from eval.runner import MONITOR_SAMPLES

    gt = _gt("torus")
    pts, nrm = sample_points(gt, 100_000, 0)
    rows = []

    def state(params, step):
        dm = DMesh(params["points"], params["weights"], params["reals"])
        pd = dm.power_diagram()
        real = dm.reals.detach().numpy() > 0.5
        present = np.zeros(len(real), bool)
        present[np.unique(pd.tets)] = True
        sheet = mesh_faces(pd, real, "sheet")
        mesh = to_trimesh(pd.points / params["scale"] + params["center"], pd.faces[sheet])
        row = {"recipe": label, "step": step, "points": len(real), "present": int(present.sum()),
               "seeds": int(real.sum()), "seeds_on_mesh": len(np.unique(pd.faces[sheet])),
               "faces_all": int(mesh_faces(pd, real, "all").sum()), "faces_sheet": int(sheet.sum()),
               "largest_cluster": _largest_real_cluster(pd, real),
               "cd_p2s_1e3": 1e3 * float(chamfer_l1_p2s(mesh, gt, n=MONITOR_SAMPLES))}
        if step == 0:
            h, r, tol = _tolerance(np.asarray(pd.points), real)
            row.update(h=h, R=r, tolerance=tol)
        rows.append(row)
        print(f"  {label} step {step}: {row['seeds_on_mesh']} seeds on the mesh, {row['faces_sheet']} faces",
              flush=True)

    def probe(params, record):
        if record["phase"] == 1:
            state(params, int(record["step"]) + 1)

    start = PointCloudConfig.preset(preset, **overrides, steps_phase1=0, steps_phase2=0)
    res = reconstruct(pts, nrm, start)
    state({"points": res.dmesh.points, "weights": res.dmesh.weights, "reals": res.dmesh.reals,
           "center": res.center, "scale": res.scale}, 0)
    cfg = PointCloudConfig.preset(preset, **overrides, steps_phase1=steps, steps_phase2=0)
    reconstruct(pts, nrm, cfg, probe=(every, probe))
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    rows = []
    for label, preset, overrides, steps, every in CASES:
        rows += _case(label, preset, overrides, steps // 5 if quick else steps, max(1, every // 2) if quick else every)
    columns = ["recipe", "step", "points", "present", "seeds", "seeds_on_mesh", "faces_all", "faces_sheet",
               "largest_cluster", "cd_p2s_1e3", "h", "R", "tolerance"]
    rows = [{c: r.get(c, "") for c in columns} for r in rows]
    table = markdown_table(rows, columns, {"cd_p2s_1e3": ".3f", "h": ".4f", "R": ".3f", "tolerance": ".1e"})
    write_report(out, "seed_loss", "Where the seeds go during phase-1 steps", __doc__, table, rows)


if __name__ == "__main__":
    main()
