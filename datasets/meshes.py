"""Real meshes from disk: loading, unique face triples, and closed / open / mixed classification.

Shape letters: V vertices, F faces, E edges, C connected components.

Classification works on connected components, where two faces are connected when a path of manifold
edges (edges used by exactly two faces) joins them, as in trimesh's `split`. A component is *closed* when
none of its edges is used by only one of its own faces, else *open*. A mesh is "closed" when every
component is closed, "open" when every component is open, and "mixed" otherwise.

How the shared test meshes (`../shared/meshes/`) come out (checked in tests/test_datasets.py): every mesh
in closed/ and open/ agrees with its folder, and so do mixed/ogre.obj (39 closed / 5 open components) and
mixed/suzanne.obj (1 / 3). mixed/beetle.obj is classified "open": its main shell (1966 of 2053 faces) is
open, and its 32 other components (1 to 32 faces each) hang on it by non-manifold edges and each has an
edge used by only one of its own faces. The shared README counts 24 of them closed because it calls a
component closed when none of its edges is a boundary edge of the *whole* mesh, which makes a lone triangle
on three non-manifold edges "closed"; a lone triangle is an open surface, so the mesh is left "open" here
rather than forced into its folder's class. Of the Stanford files, bun_zipper is open, the dragons closed,
and the res2/res3/res4 decimations mixed (their back-to-back face pairs are 2-face closed components).
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import trimesh

log = logging.getLogger(__name__)

__all__ = ["FORMATS", "load_mesh", "unique_faces", "classify", "components", "boundary_edges"]

#: File suffixes load_mesh reads (trimesh's loaders).
FORMATS = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Load a triangle mesh from OBJ, PLY, OFF, STL or GLB, with vertices merged by position.

    Scenes (GLB/GLTF, multi-object OBJ) are flattened with their transforms and concatenated. Vertices at
    the same position are merged (OBJ files split them along UV seams), unreferenced vertices dropped and
    faces that repeat a vertex index (collapsed by the merge) removed; no other repair is done.

    Args:
        path: a mesh file.

    Returns:
        A `trimesh.Trimesh` with vertices (V, 3) float64 and faces (F, 3) int64, F >= 1.

    Raises:
        FileNotFoundError: no such file.
        ValueError: one line naming the file and the problem: unsupported suffix, unreadable file, no
            faces, non-finite (NaN/inf) vertices, or face indices out of range.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, not a mesh file")
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"{path}: unsupported mesh format {suffix or '(none)'!r}; "
                         f"use one of {', '.join(FORMATS)}")
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files; report them as one line
        raise ValueError(f"{path}: cannot read mesh ({type(exc).__name__}: {_one_line(exc)})") from None

    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
    else:
        geoms = [loaded] if isinstance(loaded, trimesh.Trimesh) else []
    geoms = [g for g in geoms if len(g.faces) > 0]
    if not geoms:
        raise ValueError(f"{path}: no faces (not a triangle mesh, or empty)")

    verts, faces, offset = [], [], 0
    for g in geoms:
        v = np.asarray(g.vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(g.faces, dtype=np.int64).reshape(-1, 3)
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    if not np.isfinite(v).all():
        bad = int((~np.isfinite(v).all(axis=1)).sum())
        raise ValueError(f"{path}: {bad} vertices have NaN or infinite coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{path}: face indices out of range [0, {len(v)})")

    mesh = trimesh.Trimesh(v, f, process=False)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    faces = np.asarray(mesh.faces)
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    if not ok.all():
        log.info("%s: dropped %d faces that repeat a vertex after merging", path, int((~ok).sum()))
        if not ok.any():
            raise ValueError(f"{path}: no faces left (every face repeats a vertex)")
        mesh.update_faces(ok)
    mesh.remove_unreferenced_vertices()
    out = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
                          process=False)
    log.debug("%s: %d vertices, %d faces", path, len(out.vertices), len(out.faces))
    return out


def unique_faces(faces) -> np.ndarray:
    """Face triples with each row sorted, duplicates removed (back-to-back pairs collapse to one).

    Args:
        faces: (F, 3) integer array of vertex indices.

    Returns:
        (F', 3) int64, rows sorted ascending and unique, in lexicographic order.
    """
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {f.shape}")
    if not (np.issubdtype(f.dtype, np.integer) or f.size == 0):
        raise TypeError(f"faces must be integers, got {f.dtype}")
    return np.unique(np.sort(f.astype(np.int64), axis=1), axis=0).reshape(-1, 3)


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) int64, the edge id of each face side (F, 3) and faces per edge (E,)."""
    f = np.asarray(faces, np.int64)
    sides = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2), axis=1)
    edges, inverse, counts = np.unique(sides, axis=0, return_inverse=True, return_counts=True)
    return edges, inverse.reshape(-1, 3), counts


def boundary_edges(mesh: trimesh.Trimesh) -> np.ndarray:
    """Boundary edges: (B, 2) int64 vertex pairs (sorted) used by exactly one face."""
    edges, _, counts = _edges(mesh.faces)
    return edges[counts == 1]


def components(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of faces joined through manifold edges, and whether each is closed.

    Two faces are in the same component when a path of edges shared by exactly two faces joins them (as in
    trimesh's `split`); a non-manifold edge (3 or more faces) joins nothing. A component is closed when
    none of its edges is used by only one of its own faces.

    Returns:
        labels: (F,) int64, the component of each face, numbered 0..C-1.
        closed: (C,) bool, True where the component has no boundary edge.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(mesh.faces, np.int64)
    nf = len(faces)
    if nf == 0:
        return np.zeros(0, np.int64), np.zeros(0, bool)
    _, side_edge, counts = _edges(faces)
    side_edge = side_edge.ravel()
    side_face = np.repeat(np.arange(nf), 3)
    order = np.argsort(side_edge, kind="stable")
    e_sorted, f_sorted = side_edge[order], side_face[order]
    # Entries of a two-face edge sit next to each other once sorted by edge id.
    first = np.flatnonzero((counts[e_sorted] == 2)[:-1] & (e_sorted[:-1] == e_sorted[1:]))
    a, b = f_sorted[first], f_sorted[first + 1]
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(nf, nf))
    ncomp, labels = connected_components(graph, directed=False)
    # Faces per (component, edge): a count of 1 is a boundary edge of that component.
    key = labels[side_face].astype(np.int64) * (int(side_edge.max()) + 1) + side_edge
    uniq, per = np.unique(key, return_counts=True)
    is_open = np.zeros(ncomp, bool)
    is_open[(uniq[per == 1] // (int(side_edge.max()) + 1))] = True
    return labels.astype(np.int64), ~is_open


def classify(mesh: trimesh.Trimesh) -> str:
    """"closed", "open" or "mixed" from the boundary edges of each connected component (see the module).

    Vertices should already be merged by position (`load_mesh` does this); a mesh with split seams would
    look open.
    """
    if len(mesh.faces) == 0:
        raise ValueError("cannot classify a mesh without faces")
    _, closed = components(mesh)
    if closed.all():
        return "closed"
    if not closed.any():
        return "open"
    return "mixed"
