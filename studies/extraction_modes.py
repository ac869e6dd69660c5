"""Which real faces make the mesh: `dmesh.extract.mesh_faces`'s three modes on a first DMesh.

The first DMesh of a point cloud (`dmesh.recon.init.seeds_and_voronoi`: every sample a real seed, with its two
Voronoi poles as imaginary points, `vertices="poles"`, and the 8 corners of the box) is extracted once in each
mode: "all" (every face of three real points: upstream's point-cloud extraction), "no_interior" (also without
faces between two all-real tets: upstream's multi-view `remove_invisible`) and "sheet" (of each block of all-real
tets, only the larger of its two boundary sheets). No optimisation step is taken, so the figures show what the
modes do to the same faces, not what a run's output is (that adds the surface step, `dmesh.surface`).

Inputs: 40K samples (seed 0) of the torus, genus2, bowl (open) and plant (mixed), in the GT frame (vertex mean
0, max vertex norm 1). Figures: faces, non-manifold edges (more than two faces), boundary edges, CD p2s against
the GT (`eval.metrics.chamfer_l1_p2s`, 100K samples per side), the all-real tets and the largest block of them
(blocks: all-real tets joined across a shared face), and the seconds of `mesh_faces` alone.
"""
from __future__ import annotations

import time

import numpy as np

from eval.bench.common import markdown_table, write_report

SHAPES = ("torus", "genus2", "bowl", "plant")
SAMPLES = 40_000
MODES = ("all", "no_interior", "sheet")


def _blocks(pd, real: np.ndarray) -> tuple[int, int]:
    """(all-real tets, tets in the largest block of them): blocks joined across shared faces, as
    `dmesh.extract._one_sheet` clusters them (its labels are internal to it)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    solid = real[np.asarray(pd.tets)].all(1)
    if not solid.any():
        return 0, 0
    ft = np.asarray(pd.face_tets, np.int64)
    both = (ft[:, 1] >= 0) & solid[ft[:, 0]] & solid[np.maximum(ft[:, 1], 0)]
    T = len(solid)
    _, label = connected_components(sp.coo_matrix((np.ones(both.sum()), (ft[both, 0], ft[both, 1])), shape=(T, T)),
                                    directed=False)
    return int(solid.sum()), int(np.bincount(label[solid]).max())


def _rows(shape: str) -> list[dict]:
    import trimesh

    from datasets.normalize import normalize
    from datasets.sampling import sample_points
    from datasets.synthetic import generate
    from dmesh.extract import mesh_faces
    from dmesh.recon.init import seeds_and_voronoi
    from dmesh.surface.topology import edge_table
    from dmesh.wdt import PowerDiagram
    from eval.metrics import chamfer_l1_p2s

    gt = normalize(generate(shape))[0]
    points, _ = sample_points(gt, SAMPLES, 0)
    positions, reals = seeds_and_voronoi(np.asarray(points, np.float64), len(points), np.random.default_rng(0),
                                         vertices="poles")
    pd = PowerDiagram.from_points(positions, None)
    real = reals > 0.5
    solid, largest = _blocks(pd, real)
    rows = []
    for mode in MODES:
        t0 = time.perf_counter()
        faces = np.asarray(pd.faces)[mesh_faces(pd, real, mode)]
        seconds = time.perf_counter() - t0
        counts = edge_table(faces)[2]
        mesh = trimesh.Trimesh(positions, faces, process=False)
        rows.append({"shape": shape, "mode": mode, "faces": int(len(faces)),
                     "nonmanifold_edges": int((counts > 2).sum()), "boundary_edges": int((counts == 1).sum()),
                     "cd_p2s_1e3": 1e3 * chamfer_l1_p2s(mesh, gt), "real_tets": solid, "largest_block": largest,
                     "seconds": seconds})
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    rows = [r for shape in (SHAPES[:1] if quick else SHAPES) for r in _rows(shape)]
    columns = ["shape", "mode", "faces", "nonmanifold_edges", "boundary_edges", "cd_p2s_1e3", "real_tets",
               "largest_block", "seconds"]
    table = markdown_table(rows, columns, {"cd_p2s_1e3": ".4g", "seconds": ".2f"})
    write_report(out, "extraction_modes", "Extraction modes on a first DMesh", __doc__, table, rows)


if __name__ == "__main__":
    main()
