"""The face budget of a reconstruction (`faces` > 0, the `compact` preset; not upstream): a mesh with more faces
than the budget is reduced to it by quadric edge collapse.

Why this way: the seeds set a DMesh mesh's size only roughly (about one to one and a half faces per seed after
the steps, depending on the shape), so the `compact` preset seeds a little above the budget and removes the
rest here. The reduction is MeshLab's quadric edge collapse (Garland and Heckbert 1997; pymeshlab
`meshing_decimation_quadric_edge_collapse`) at the settings the harness's reconstruct-then-decimate rows use
(`baselines/decimate.py`: MeshLab's defaults), so a DMesh mesh and a decimated classical mesh are reduced the
same way. A library for it: pymeshlab is the field's implementation, and the project depends on it already.
"""
from __future__ import annotations

import logging
import time

import numpy as np

log = logging.getLogger(__name__)

#: A mesh this far below its budget is reported (the seeds gave too few faces).
SHORT = 0.9


def reduce_to_budget(mesh, faces: int):
    """(mesh, info): `mesh` (trimesh.Trimesh) reduced to about `faces` faces when it has more, else unchanged;
    info {"faces_before", "faces", "seconds", "cpu_seconds", "short"} ("short": True when the mesh has under
    0.9 x the budget).
    """
    import trimesh

    before, t0, c0 = int(len(mesh.faces)), time.perf_counter(), time.process_time()
    if before > int(faces):
        try:
            import pymeshlab
        except ImportError as exc:
            raise RuntimeError("the face budget needs pymeshlab (pip install pymeshlab)") from exc
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(mesh.vertices, dtype=np.float64),
                                   face_matrix=np.asarray(mesh.faces, dtype=np.int32)))
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=int(faces), qualitythr=0.3, preserveboundary=False, boundaryweight=1.0,
            optimalplacement=True, preservetopology=False, preservenormal=False, planarquadric=False,
            autoclean=True)
        out = ms.current_mesh()
        mesh = trimesh.Trimesh(np.asarray(out.vertex_matrix(), dtype=np.float64),
                               np.asarray(out.face_matrix(), dtype=np.int64), process=False)
    info = {"faces_before": before, "faces": int(len(mesh.faces)), "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0,
            "short": bool(len(mesh.faces) < SHORT * int(faces))}
    if info["short"]:
        log.warning("the mesh has %d faces, under %.0f %% of its budget of %d: more seeds (num_init) would give "
                    "more", info["faces"], 100 * SHORT, faces)
    return mesh, info


__all__ = ["SHORT", "reduce_to_budget"]
