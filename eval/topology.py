"""Topology and statistics of a mesh, and DMesh's RE/FP: the frame-independent figures of `eval.metrics`.

Shape letters: V vertices, F faces, E unique edges. `topology` counts boundary edges and loops, non-manifold edges
and vertices, components, watertightness, winding consistency, Euler characteristic and genus; `mesh_stats` adds
counts, self-intersections (MeshLab's) and triangle quality; `re_fp` is the face recovery and false-positive ratio
of the mesh-to-DMesh experiment; `sheets` splits a face list into pieces of surface and says which are open.
`eval.metrics.compute_metrics` reports all of them beside the distances.
"""
from __future__ import annotations

import logging
import math

import numpy as np

log = logging.getLogger(__name__)


def face_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(F,) float64 triangle areas."""
    t = v[f]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


# ----------------------------------------------------------------------------------------------- RE/FP

def _unique_rows(faces: np.ndarray) -> np.ndarray:
    f = np.sort(np.asarray(faces, dtype=np.int64).reshape(-1, 3), axis=1)
    return np.unique(f, axis=0)


def _row_keys(rows: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(rows).view(np.dtype((np.void, 24))).ravel()


def re_fp(pred_faces: np.ndarray, gt_faces: np.ndarray, n_gt_vertices: int | None = None) -> dict:
    """Face recovery (RE) and false-positive ratio (FP) of DMesh's mesh-to-DMesh experiment.

    Both face lists index one shared vertex array whose first `n_gt_vertices` entries are the GT vertices
    (the prediction may add more vertices after them). Faces are compared as sorted, unique index triples, so
    winding and duplicates (back-to-back pairs) do not matter.

    Args:
        pred_faces: (F, 3) int predicted faces. gt_faces: (F', 3) int GT faces, F' >= 1.
        n_gt_vertices: number of GT vertices; None: max index in gt_faces + 1.

    Returns:
        {"re": recovered / gt_faces, "fp": false / on_gt (0.0 when on_gt is 0), "gt_faces": unique GT
        triples, "on_gt": unique predicted triples whose three vertices are all GT vertices, "recovered":
        those that are GT triples, "false": those that are not}.
    """
    gt = _unique_rows(gt_faces)
    if len(gt) == 0:
        raise ValueError("re_fp: gt_faces is empty")
    if gt.min() < 0:
        raise ValueError("re_fp: negative face index")
    nv = int(gt.max()) + 1 if n_gt_vertices is None else int(n_gt_vertices)
    if gt.max() >= nv:
        raise ValueError(f"re_fp: gt_faces index vertex {int(gt.max())} >= n_gt_vertices {nv}")
    pred = _unique_rows(pred_faces)
    if len(pred) and pred.min() < 0:
        raise ValueError("re_fp: negative face index")
    on_gt = pred[(pred < nv).all(axis=1)]
    hit = np.isin(_row_keys(on_gt), _row_keys(gt))
    recovered = int(hit.sum())
    false = int(len(on_gt) - recovered)
    return {"re": recovered / len(gt), "fp": false / len(on_gt) if len(on_gt) else 0.0, "gt_faces": int(len(gt)),
            "on_gt": int(len(on_gt)), "recovered": recovered, "false": false}


# ------------------------------------------------------------------------------------------ mesh stats

def _edge_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) int64 and how many faces use each (E,) int64."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def _n_components(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the graph on n nodes with edges (a[i], b[i]): (count, (n,) labels)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    adj = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n))
    count, labels = connected_components(adj, directed=False)
    return int(count), labels


def topology(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """Combinatorial figures of a triangle mesh: edges, boundary, manifoldness, winding, Euler characteristic, genus.

    Written here rather than taken from trimesh, which has no per-vertex manifold test, no boundary-loop count
    and no orientability test for an inconsistently wound mesh. Faces that repeat a vertex index have no
    topology and are left out; vertices no face uses are not counted.

    Args:
        vertices: (V, 3) float (only their count matters). faces: (F, 3) int64 indices into vertices.

    Returns:
        {"edges": E unique undirected edges, "boundary_edges": edges used by one face, "boundary_loops":
        connected pieces of the boundary-edge graph (the holes of a 2-manifold), "non_manifold_edges": edges
        used by more than two faces, "non_manifold_vertices": vertices whose faces form more than one fan
        (faces around a vertex joined through the two-face edges at it; a bow-tie vertex, or the ends of a
        non-manifold edge), "components": connected components (faces joined through shared vertices),
        "watertight": F > 0 and every edge is used by exactly two faces, "winding_consistent": every two-face
        edge is run in opposite directions by its two faces, "inconsistent_winding_edges": two-face edges run
        the same way by both, "euler_characteristic": V - E + F, "genus": for an orientable 2-manifold (no
        non-manifold edge or vertex) the sum over components of g with chi = 2 - 2 g - b, i.e.
        (2 C - chi - boundary_loops) / 2; None for a non-manifold or non-orientable mesh}.
    """
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    out = {"edges": 0, "boundary_edges": 0, "boundary_loops": 0, "non_manifold_edges": 0,
           "non_manifold_vertices": 0, "components": 0, "watertight": False, "winding_consistent": True,
           "inconsistent_winding_edges": 0, "euler_characteristic": 0, "genus": None}
    if len(f) == 0:
        return out
    nv = len(np.asarray(vertices).reshape(-1, 3))
    sides = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)   # (3F, 2): side 3i+k runs corner k -> k+1 of face i
    lo, hi = np.minimum(sides[:, 0], sides[:, 1]), np.maximum(sides[:, 0], sides[:, 1])
    nv = max(nv, int(f.max()) + 1)
    keys, edge_of, counts = np.unique(lo * nv + hi, return_inverse=True, return_counts=True)  # 1-D: fast
    edges = np.stack([keys // nv, keys % nv], axis=1)
    edge_of = edge_of.ravel()
    forward = np.bincount(edge_of, weights=(sides[:, 0] < sides[:, 1]), minlength=len(edges))
    two = counts == 2
    bad_winding = two & (forward != 1)
    used = np.unique(f)
    ncomp, _ = _n_components(nv, edges[:, 0], edges[:, 1])
    ncomp -= nv - len(used)                              # unused vertices are singleton components
    bnd = edges[counts == 1]
    _, blab = _n_components(nv, bnd[:, 0], bnd[:, 1])
    loops = int(len(np.unique(blab[np.unique(bnd)]))) if len(bnd) else 0
    nm_vertices = _non_manifold_vertices(f, sides, edge_of, two)
    chi = int(len(used) - len(edges) + len(f))
    out.update({"edges": int(len(edges)), "boundary_edges": int(len(bnd)), "boundary_loops": loops,
                "non_manifold_edges": int((counts > 2).sum()), "non_manifold_vertices": nm_vertices,
                "components": int(ncomp), "watertight": bool(two.all()),
                "winding_consistent": not bool(bad_winding.any()),
                "inconsistent_winding_edges": int(bad_winding.sum()), "euler_characteristic": chi})
    if out["non_manifold_edges"] == 0 and nm_vertices == 0 and _orientable(len(f), edge_of, two, bad_winding):
        g2 = 2 * ncomp - chi - loops
        out["genus"] = g2 // 2 if g2 % 2 == 0 else None
    return out


def _two_face_pairs(edge_of: np.ndarray, two: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two sides (s1, s2), each (M,) int64, of every two-face edge, and that edge's id (M,)."""
    order = np.argsort(edge_of, kind="stable")
    keep = two[edge_of[order]]
    s = order[keep].reshape(-1, 2)                       # sides of one two-face edge sit together once sorted
    return s[:, 0], s[:, 1], edge_of[s[:, 0]]


def _non_manifold_vertices(f: np.ndarray, sides: np.ndarray, edge_of: np.ndarray, two: np.ndarray) -> int:
    """Vertices whose corners (face, vertex) fall into more than one fan; see `topology`.

    Corner 3i+k is vertex f[i, k] in face i; side 3i+k starts at corner 3i+k and ends at corner 3i+(k+1)%3.
    Across a two-face edge the corners of each of its two vertices are joined; a vertex whose corners then
    form more than one group is a non-manifold vertex.
    """
    s1, s2, _ = _two_face_pairs(edge_of, two)
    end1, end2 = 3 * (s1 // 3) + (s1 % 3 + 1) % 3, 3 * (s2 // 3) + (s2 % 3 + 1) % 3   # corners where they end
    ca, cb = [], []
    for v in (sides[s1, 0], sides[s1, 1]):              # each vertex of the edge: its corner in both faces
        ca.append(np.where(sides[s1, 0] == v, s1, end1))
        cb.append(np.where(sides[s2, 0] == v, s2, end2))
    ca, cb = np.concatenate(ca), np.concatenate(cb)
    _, labels = _n_components(3 * len(f), ca, cb)
    vert = f.ravel()                                     # vertex of corner 3i+k
    fans = np.unique(vert * np.int64(3 * len(f)) + labels)  # one entry per (vertex, fan)
    per_vertex = np.bincount(fans // (3 * len(f)))
    return int((per_vertex > 1).sum())


def _orientable(n_faces: int, edge_of: np.ndarray, two: np.ndarray, bad_winding: np.ndarray) -> bool:
    """Whether some choice of reversed faces makes every two-face edge consistently wound.

    Two-colouring of the faces' double cover: node (i, 0) is face i as wound, (i, 1) reversed; a consistent
    edge joins same-state nodes, an inconsistent one opposite states. Orientable iff no face meets itself
    reversed (a Moebius strip does).
    """
    if not bad_winding.any():
        return True
    s1, s2, e = _two_face_pairs(edge_of, two)
    i1, i2 = s1 // 3, s2 // 3
    flip = bad_winding[e].astype(np.int64)
    a = np.concatenate([2 * i1, 2 * i1 + 1])
    b = np.concatenate([2 * i2 + flip, 2 * i2 + 1 - flip])
    _, labels = _n_components(2 * n_faces, a, b)
    return bool((labels[0::2] != labels[1::2]).all())


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Number of faces that cross another face, as MeshLab's self-intersection selection finds them (pymeshlab;
    a neighbour sharing one vertex counts when the edge opposite that vertex passes through it); -1 without
    pymeshlab."""
    if len(faces) == 0:
        return 0
    try:
        import pymeshlab
    except ImportError:
        log.warning("pymeshlab is not installed (project extra [harness]); self-intersections not counted")
        return -1
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64),
                               face_matrix=np.asarray(faces, np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    return int(ms.current_mesh().selected_face_number())


def mesh_stats(mesh, self_intersections: bool = True) -> dict:
    """Counts, topology and triangle-quality figures of a mesh (frame-independent).

    Args:
        mesh: trimesh.Trimesh with vertices (V, 3), faces (F, 3); may be empty.
        self_intersections: count self-intersecting faces (pymeshlab; the slowest figure).

    Returns:
        {"vertices": V, "faces": F, then the `topology` keys (edges, boundary_edges, boundary_loops,
        non_manifold_edges, non_manifold_vertices, components, watertight, winding_consistent,
        inconsistent_winding_edges, euler_characteristic, genus), "self_intersecting_faces": count (-1 if not
        computed), "degenerate_faces": zero-area faces, "aspect_ratio_mean", "aspect_ratio_max": circumradius /
        (2 inradius) (1 for equilateral, inf for degenerate; the mean is over non-degenerate faces),
        "angles_below_10_pct": % of triangle corner angles under 10 degrees (corners of zero-length edges
        excluded)}. Empty meshes give 0 counts and NaN figures.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    out = {"vertices": int(len(v)), "faces": int(len(f)), **topology(v, f), "self_intersecting_faces": 0,
           "degenerate_faces": 0, "aspect_ratio_mean": math.nan, "aspect_ratio_max": math.nan,
           "angles_below_10_pct": math.nan}
    if len(f) == 0:
        return out
    out["self_intersecting_faces"] = self_intersecting_faces(v, f) if self_intersections else -1
    t = v[f]
    la = np.linalg.norm(t[:, 1] - t[:, 2], axis=1)   # opposite corner 0
    lb = np.linalg.norm(t[:, 2] - t[:, 0], axis=1)
    lc = np.linalg.norm(t[:, 0] - t[:, 1], axis=1)
    area = face_areas(v, f)
    scale = np.maximum(np.maximum(la, lb), lc)
    degenerate = area <= 1e-12 * np.maximum(scale * scale, 1e-300)
    out["degenerate_faces"] = int(degenerate.sum())
    with np.errstate(divide="ignore", invalid="ignore"):
        aspect = la * lb * lc * (la + lb + lc) / (16.0 * area * area)
    aspect = np.where(degenerate, np.inf, aspect)
    finite = aspect[~degenerate]
    out["aspect_ratio_mean"] = float(finite.mean()) if len(finite) else math.inf
    out["aspect_ratio_max"] = float(aspect.max())
    angles = []
    for (o1, o2), opp in (((lb, lc), la), ((lc, la), lb), ((la, lb), lc)):
        with np.errstate(divide="ignore", invalid="ignore"):
            cos = (o1 * o1 + o2 * o2 - opp * opp) / (2 * o1 * o2)
        angles.append(np.degrees(np.arccos(np.clip(cos[(o1 > 0) & (o2 > 0)], -1.0, 1.0))))
    a = np.concatenate(angles)
    out["angles_below_10_pct"] = float(100.0 * (a < 10.0).mean()) if len(a) else math.nan
    return out


def sheets(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pieces of surface of a face list: ((F,) component of each face, (C,) bool whether it is open).

    Faces are joined through edges that exactly two faces use, whatever their winding (so a piece wound
    inconsistently stays one piece); a piece is open when one of its edges belongs to it alone.
    """
    F = len(f)
    sides = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    nv = int(f.max()) + 1
    _, edge_of, counts = np.unique(sides[:, 0] * nv + sides[:, 1], return_inverse=True, return_counts=True)
    edge_of = edge_of.ravel()
    face_of = np.repeat(np.arange(F), 3)
    order = np.argsort(edge_of, kind="stable")
    pairs = order[(counts[edge_of] == 2)[order]].reshape(-1, 2)   # the two sides of each two-face edge
    _, comp = _n_components(F, face_of[pairs[:, 0]], face_of[pairs[:, 1]])
    on_boundary = np.bincount(face_of, counts[edge_of] == 1, F) > 0
    is_open = np.bincount(comp, on_boundary, comp.max() + 1) > 0
    return comp, is_open


__all__ = ["face_areas", "mesh_stats", "re_fp", "self_intersecting_faces", "sheets", "topology"]
