"""Which faces of a DMesh make its mesh (paper section 4; DESIGN.md section 6).

Letters: N points, T tets, F WDT faces.

A face is on the mesh when it is in the WDT and its three points are real (real value above a threshold).
Modes, from upstream's to ours:

- "all": every such face (upstream's extraction for point clouds).
- "no_interior": also drops faces whose two tets are both all-real, i.e. faces inside a solid block of
  real tets (upstream's `remove_invisible`, used for multi-view).
- "sheet": a connected block of all-real tets ("cluster") is a thickened piece of surface: four surface
  samples that no imaginary point separates. Its interior faces are dropped as in "no_interior", and of its
  boundary, which is two sheets (one facing each side of the surface), only one is kept: the one with the
  larger area, which on a convex patch is the one closer to the surface. A side is told by the apex of the
  tet across each boundary face, against the cluster's normal (its points' direction of least variance).
  Upstream keeps both sheets, so its meshes have many non-manifold edges, and the inner sheet lies farther
  from the surface. Clusters are small (tens of tets at most), so one normal per cluster is enough. The three
  modes on a first DMesh (faces, non-manifold edges, CD, cluster sizes): `python -m studies extraction_modes`.

These are the raw faces: no winding (sorted triples), holes where the input was sparse, fins and stray
triangles where it was noisy, edges shared by three or more faces where sheets meet. `extract` gives them as a
mesh. The oriented, cleaned mesh made from them comes from `dmesh.surface` (`surface_mesh`; `DMesh.extract_mesh`
offers both through its `surface` argument); which to call for which purpose: docs/surface.md.

Multi-view filters (`filtered_faces`; the interior rules of
`dmesh.recon.multiview_config.INTERIOR_MODES`): "apex" is "no_interior" (a face whose two tets have a real apex is
inside a solid block); "sheet" is "sheet"; "visible" keeps the faces that are the first hit of some pixel
ray of some camera when the mesh is drawn opaque (`visible_faces`, `hard_render`); "both" is "no_interior"
then "visible"; "none" keeps every real face. The depth filter (`depth_consistent_faces`), applied before
the visibility test, keeps the faces whose centroid lies on the captured depth of some view.
"""
from __future__ import annotations

import logging

import numpy as np

from dmesh.camera import focal_length, to_pixels, transform_points

log = logging.getLogger(__name__)

MODES = ("all", "no_interior", "sheet")


def mesh_faces(pd, real: np.ndarray, mode: str = "all") -> np.ndarray:
    """(F,) bool mask of the faces of `pd` (a `dmesh.wdt.PowerDiagram`) on the mesh.

    Args:
        pd: the power diagram (faces, face_tets, tets, points).
        real: (N,) bool, which points are real.
        mode: "all", "no_interior" or "sheet" (module docstring).
    """
    if mode not in MODES:
        raise ValueError(f"unknown extraction mode {mode!r}; choose from {', '.join(MODES)}")
    real = np.asarray(real, dtype=bool)
    on = real[pd.faces].all(1)
    if mode == "all" or not on.any():
        return on
    real_tet = np.r_[real[pd.tets].all(1), False]  # index -1 (hull side) reads False
    n_real = real_tet[pd.face_tets].sum(1)
    if mode == "no_interior":
        return on & (n_real < 2)
    keep = on & (n_real == 0)
    keep[_one_sheet(pd, real_tet[:-1], on & (n_real == 1), on & (n_real == 2))] = True
    return keep


def _one_sheet(pd, real_tet: np.ndarray, boundary: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """Ids of the boundary faces of each all-real-tet cluster on its larger-area side."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from dmesh.solid import face_areas

    T = len(pd.tets)
    a, b = pd.face_tets[interior, 0], pd.face_tets[interior, 1]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(T, T))
    n_comp, label = connected_components(graph, directed=False)

    ids = np.flatnonzero(boundary)
    ft = pd.face_tets[ids].astype(np.int64)
    first_real = real_tet[ft[:, 0]]
    inner = np.where(first_real, ft[:, 0], ft[:, 1])
    outer = np.where(first_real, ft[:, 1], ft[:, 0])
    cluster = label[inner]

    normal = _cluster_normals(pd.points, pd.tets, np.flatnonzero(real_tet), label, n_comp)
    faces = pd.faces[ids].astype(np.int64)
    p = pd.points
    centre = p[faces].mean(1)
    # The apex of the tet across: its vertex sum minus the face's (vertex ids are distinct). A hull face
    # has no tet across; its apex is taken on the negative side (its own first vertex stands in, a valid index).
    apex = pd.tets[np.maximum(outer, 0)].astype(np.int64).sum(1) - faces.sum(1)
    apex = np.where(outer >= 0, apex, faces[:, 0])
    side = np.einsum("ij,ij->i", p[apex] - centre, normal[cluster]) > 0
    side &= outer >= 0
    area = face_areas(p, faces)
    area_pos = np.bincount(cluster, area * side, n_comp)
    area_neg = np.bincount(cluster, area * ~side, n_comp)
    return ids[side == (area_pos >= area_neg)[cluster]]


def _cluster_normals(points: np.ndarray, tets: np.ndarray, real_tets: np.ndarray, label: np.ndarray,
                     n_comp: int) -> np.ndarray:
    """(n_comp, 3) unit direction of least variance of each cluster's tet vertices (zero for no tets)."""
    x = points[tets[real_tets].reshape(-1)]
    lab = np.repeat(label[real_tets], 4)
    count = np.maximum(np.bincount(lab, minlength=n_comp), 1)[:, None]
    mean = np.stack([np.bincount(lab, x[:, i], n_comp) for i in range(3)], 1) / count
    y = x - mean[lab]
    cov = np.empty((n_comp, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(lab, y[:, i] * y[:, j], n_comp)
    _, vectors = np.linalg.eigh(cov)  # ascending eigenvalues: column 0 is the least-variance direction
    return vectors[:, :, 0]


def towards_cameras(points: np.ndarray, eyes: np.ndarray, limit: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """`dmesh.surface.run`'s `normals` from multi-view input: (points, unit vectors from each point towards its eye).

    A captured surface faces the camera that saw it, so the direction to that camera has the sign of the
    surface's outward normal wherever the surface is closed (and of its seen side on an open sheet).

    Args:
        points: (G, 3) float64 captured surface points (lifted depth pixels); eyes: (G, 3) float64 centre of
            the camera that saw each; both in the frame of the triangulation.
        limit: at most this many points are kept, evenly strided (deterministic).
    """
    points = np.asarray(points, dtype=np.float64)
    eyes = np.asarray(eyes, dtype=np.float64)
    if len(points) > limit:
        pick = np.linspace(0, len(points) - 1, limit).astype(np.int64)
        points, eyes = points[pick], eyes[pick]
    d = eyes - points
    return points, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


# ------------------------------------------------------------------------------------------------- multi-view

#: The `mesh_faces` mode behind each multi-view interior rule (the others keep every real face).
_INTERIOR_MODE = {"apex": "no_interior", "both": "no_interior", "sheet": "sheet"}


def depth_consistent_faces(points: np.ndarray, faces: np.ndarray, world_to_camera: np.ndarray, fov_y_degrees: float,
                           depth: np.ndarray, mask: np.ndarray, tolerance: float) -> np.ndarray:
    """(F,) bool: faces whose centroid lies on the captured surface in at least one view.

    A centroid is on the surface in view k when it projects to a mask pixel whose captured depth (-z_cam)
    is within `tolerance` of its own. Interior faces lie behind the captured surface in every view that
    sees their pixel, and floating ones project onto background: both fail. Unlike the "visible" test,
    which trusts the mesh's own renders (an interior face seen through a pixel-wide crack survives it),
    this one checks the input.

    Args:
        points: (N, 3) and faces (F, 3) in the frame of `world_to_camera` (V, 4, 4); depth, mask: (V, H, H)
        captured images in the same frame's units; tolerance: distance along the view axis.
    """
    c = points[faces].mean(1)
    h = depth.shape[1]
    focal = focal_length(fov_y_degrees, h)
    ok = np.zeros(len(faces), bool)
    for k in range(len(world_to_camera)):
        x = transform_points(c, world_to_camera[k])
        z = -x[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = (np.floor(a) for a in to_pixels(x[:, 0], x[:, 1], z, focal, h, h))
        idx = np.flatnonzero((z > 0) & (u >= 0) & (u < h) & (v >= 0) & (v < h))
        iu, iv = u[idx].astype(np.int64), v[idx].astype(np.int64)
        hit = mask[k, iv, iu] & (np.abs(z[idx] - depth[k, iv, iu]) <= tolerance)
        ok[idx[hit]] = True
    return ok


def hard_render(points: np.ndarray, pd, keep: np.ndarray, cameras):
    """Renders the faces of `keep` ((F,) bool over `pd.faces`) opaque, all others transparent, with the
    tetrahedral walk (exact depth order; `dmesh.render.tet_render`).

    A pixel's compositing stops at its first opaque face, so its fragment list holds exactly that face.

    Returns:
        seen: (F,) bool, faces of `keep` that are the first hit of some pixel ray of some camera;
        diffuse, depth, alpha: (V, R, R) float32 images (as `dmesh.render.tet_render`).
    """
    import torch

    from dmesh import native

    opacity = keep.astype(np.float32)
    seen = np.zeros(len(pd.faces), bool)
    threads = max(1, torch.get_num_threads())
    images = []
    for cam in cameras:
        raw = native.tet_render_forward(points, pd.tets, pd.faces, pd.face_tets, opacity, *cam.native_args(),
                                        0.5, 1e-4, threads)
        seen[np.asarray(raw.frag_face, dtype=np.int64)] = True
        images.append((raw.diffuse, raw.depth, raw.alpha))
    diffuse, depth, alpha = (np.stack(x) for x in zip(*images))
    return seen & keep, diffuse, depth, alpha


def visible_faces(points: np.ndarray, pd, keep: np.ndarray, cameras) -> np.ndarray:
    """(F,) bool over `pd.faces`: faces of `keep` ((F,) bool) that are the first hit of some pixel ray of
    some camera (see `hard_render`)."""
    if not keep.any():
        return np.zeros(len(pd.faces), bool)
    return hard_render(points, pd, keep, cameras)[0]


def filtered_faces(dm, threshold: float, pd, interior: str, cameras, render: bool = False, consistent=None):
    """The multi-view extraction's faces (module docstring): (F,) bool over `pd.faces`, the count removed
    from the real faces, and (with `render`, or when the visibility test ran) the hard render's (diffuse,
    depth, alpha) from `cameras`, else None.

    Args:
        dm: `DMesh`; threshold: real value above which a point is real; pd: its `PowerDiagram`; interior: one
            of `dmesh.recon.multiview_config.INTERIOR_MODES`; cameras: the `dmesh.camera.Camera`s of the visibility
            test and the render; consistent: None, or a function (points, faces) -> (F,) bool of faces to
            keep (`depth_consistent_faces`), applied before the visibility test.
    """
    real = dm.reals.detach().numpy() > threshold
    keep = real[pd.faces].all(1)
    before = int(keep.sum())
    if interior in _INTERIOR_MODE:
        keep = mesh_faces(pd, real, _INTERIOR_MODE[interior])
    if consistent is not None and keep.any():
        idx = np.flatnonzero(keep)
        keep[idx] = consistent(dm.points.detach().double().numpy(), pd.faces[idx].astype(np.int64))
    images = None
    if interior in ("visible", "both") or render:
        if cameras is None:
            raise ValueError("the visibility test and the hard render need the cameras")
        seen, *images = hard_render(dm.points.detach().numpy(), pd, keep, cameras)
        if interior in ("visible", "both"):
            keep = seen
    return keep, before - int(keep.sum()), images


def extract(dm, threshold: float = 0.5, pd=None, mode: str = "all"):
    """The raw-faces mesh of a DMesh: its `mesh_faces` as sorted triples, a `trimesh.Trimesh` over the points they
    use (float64, the DMesh's frame; `to_trimesh`).

    Args:
        dm: `dmesh.model.DMesh`; threshold: real value above which a point is real; pd: its `PowerDiagram`
            (None: a fresh one); mode: which real faces (`mesh_faces`).
    """
    pd = pd if pd is not None else dm.power_diagram()
    return to_trimesh(pd.points, pd.faces[mesh_faces(pd, dm.reals.detach().numpy() > threshold, mode)])


def to_trimesh(points: np.ndarray, faces: np.ndarray):
    """A `trimesh.Trimesh` of `faces` ((F, 3) indices) over the points they use (float64, unprocessed)."""
    import trimesh

    mesh = trimesh.Trimesh(np.array(points, dtype=np.float64), np.asarray(faces, dtype=np.int64).reshape(-1, 3),
                           process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


__all__ = ["MODES", "mesh_faces", "extract", "to_trimesh", "depth_consistent_faces", "hard_render", "visible_faces",
           "filtered_faces", "towards_cameras"]
