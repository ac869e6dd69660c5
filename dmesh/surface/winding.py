"""The sheets' winding: each sheet wound consistently and turned to its input normals (the wind_sheets stage), and
`orient_faces`, the same winding for any mesh.

Letters: V vertices, F faces, G input points.
"""
from __future__ import annotations

import numpy as np

from dmesh.surface.topology import seam_components, split_at_fans, winding_components
from dmesh.tolerances import FLOAT64_FLOOR


def wind_sheets(state, cfg):
    """Each sheet is wound consistently and turned whole to the side its `neighbours` nearest input normals agree
    with; only a sheet that cannot be wound consistently has faces turned one by one (`turn_faces`). The edges a
    dropped stacked piece hung on stay apart while the winding is found."""
    points = state.points
    turn = dict(k=cfg.neighbours, confident=cfg.confident, workers=state.workers, turn_faces=cfg.turn_faces)
    if len(state.hung):
        apart, source = split_at_fans(state.sheet, len(points), state.hung)
        state.sheet = source[orient_sheets(points[source], apart, state.normals, **turn)]
    else:
        state.sheet = orient_sheets(points, state.sheet, state.normals, **turn)
    return state


def orient_sheets(vertices: np.ndarray, faces: np.ndarray, normals=None, k: int = 3, confident: float = 0.5,
                  workers: int = 1, turn_faces: bool = True) -> np.ndarray:
    """(F, 3) int64 faces wound consistently per component, facing the input normals when given.

    Args:
        vertices: (V, 3) float64; faces: (F, 3) ints.
        normals: None, or (points (G, 3), normals (G, 3)) float64 oriented input samples in the same frame.
            A face's agreement is the cosine between its normal and the mean normal of the `k` input points
            nearest its centroid. Each component (`winding_components`) is turned to the side its faces
            agree with (mean agreement by area; below `confident` / 2 either way, as without normals); then,
            in a component that cannot be wound consistently (`seam_components`), each face that agrees or
            disagrees by at least `confident` is turned to agree on its own: where a sheet meets itself at an
            edge (two layers fused by the extraction), a component can be non-orientable and its seam would
            fall anywhere; the input normals put it where the layers meet. An orientable component turns only
            whole, so its winding stays consistent (a fold that faces against its normals stays part of its
            sheet rather than becoming a seam). Faces whose nearest normals cancel (a thin sheet sampled
            from both sides) follow their component. With `turn_faces` False no face turns on its own: for
            vectors that are not normals (directions towards the cameras that saw each point, which on a
            sheet seen from both sides point to either side patch by patch), whole components only.
            Without normals, each component is turned so that its signed volume about the origin is
            positive (outward for a closed component; an open one faces away from the origin, e.g. a cap's
            convex side when the origin is the object's centre).
    """
    f = np.asarray(faces, dtype=np.int64).copy()
    if len(f) == 0:
        return f
    flip, comp, n = winding_components(f)
    f[flip] = f[flip][:, ::-1]
    t = np.asarray(vertices, dtype=np.float64)[f]
    if normals is None or not len(normals[0]):
        turn = np.bincount(comp, np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])), n) < 0
        f[turn[comp]] = f[turn[comp]][:, ::-1]
        return f
    from scipy.spatial import cKDTree

    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    area = np.linalg.norm(cross, axis=1)
    kk = min(k, len(normals[0]))
    _, j = cKDTree(normals[0]).query(t.mean(1), k=kk, workers=workers)
    mean = normals[1][j.reshape(len(f), -1)].sum(1) / kk
    agree = np.einsum("ij,ij->i", cross, mean) / np.maximum(area, FLOAT64_FLOOR)
    vote = np.bincount(comp, agree * area, n) / np.maximum(np.bincount(comp, area, n), FLOAT64_FLOOR)
    volume = np.bincount(comp, np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])), n)
    turn = np.where(np.abs(vote) >= confident / 2, vote < 0, volume < 0)[comp]
    agree[turn] = -agree[turn]
    if turn_faces:
        turn ^= (agree <= -confident) & seam_components(f, comp, n)[comp]
    f[turn] = f[turn][:, ::-1]
    return f


def orient_faces(mesh) -> None:
    """Consistent winding per connected component of a `trimesh.Trimesh` (in place), outward for closed
    components (`orient_sheets` without normals). Non-manifold edges do not propagate the winding."""
    mesh.faces = orient_sheets(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))


__all__ = ["wind_sheets", "orient_sheets", "orient_faces"]
