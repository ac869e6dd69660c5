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

import io
import logging
import os
from pathlib import Path

import numpy as np
import trimesh

from datasets.mesh_files import check_off, check_ply, obj_with_absolute_indices
from dmesh.checks import check_coordinates

log = logging.getLogger(__name__)

__all__ = ["FORMATS", "MERGE_TOLERANCE", "ORIENTATIONS", "load_mesh", "merge_vertices", "check_ply", "check_off",
           "unique_faces", "classify", "components", "boundary_edges", "orient_outward"]

#: File suffixes load_mesh reads (trimesh's loaders).
FORMATS = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def load_mesh(path: str | os.PathLike, orient: bool = False) -> trimesh.Trimesh:
    """Load a triangle mesh from OBJ, PLY, OFF, STL or GLB, with vertices merged by position.

    Scenes (GLB/GLTF, multi-object OBJ) are flattened with their transforms and concatenated. PLY and OFF
    files are first checked against their headers (`check_ply`, `check_off`). Vertices at the same position
    are merged (OBJ files split them along UV seams; STL stores each triangle's corners), unreferenced
    vertices dropped and faces that repeat a vertex index (collapsed by the merge) removed; no other repair
    is done. "The same position" means within `MERGE_TOLERANCE` of the bounding box's largest side (see
    `merge_vertices`), so the merge neither overflows nor collapses vertices at any coordinate scale.

    Args:
        path: a mesh file.
        orient: pass the mesh through `orient_outward` (for a ground truth or an input to sample: an
            inside-out closed mesh is flipped, with a warning naming the file); its status goes into
            `mesh.metadata["orientation"]`. A mesh of no area is refused then. Never set it for a
            prediction under test.

    Returns:
        A `trimesh.Trimesh` with vertices (V, 3) float64 and faces (F, 3) int64, F >= 1.

    Raises:
        FileNotFoundError: no such file.
        ValueError: one line naming the file and the problem: unsupported suffix, unreadable file, element
            counts that disagree with the header, no faces, non-finite (NaN/inf) vertices, coordinates past
            `dmesh.tolerances.MAX_COORDINATE`, or face indices out of range. OBJ relative (negative) face
            indices count back from the last vertex read, as the format says.
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
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: no faces (empty file)")
    try:
        if suffix == ".ply":
            check_ply(path)
        elif suffix == ".off":
            check_off(path)
    except ValueError as exc:  # same form as trimesh's failures below
        detail = str(exc).removeprefix(f"{path}: ")
        raise ValueError(f"{path}: cannot read mesh ({detail})") from None
    try:
        relative = obj_with_absolute_indices(path) if suffix == ".obj" else None
        if relative is not None:
            loaded = trimesh.load(io.BytesIO(relative), file_type="obj", process=False)
        else:
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
    check_coordinates(v, str(path))

    v, f = merge_vertices(v, f)
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    if not ok.all():
        log.info("%s: dropped %d faces that repeat a vertex after merging", path, int((~ok).sum()))
        if not ok.any():
            raise ValueError(f"{path}: no faces left (every face repeats a vertex)")
        f = f[ok]
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    if not used.all():  # drop unreferenced vertices, keeping the order of the rest
        remap = np.cumsum(used) - 1
        v, f = v[used], remap[f]
    out = trimesh.Trimesh(v, f, process=False)
    log.debug("%s: %d vertices, %d faces", path, len(out.vertices), len(out.faces))
    if orient:
        if not out.area > 0:  # before the winding is judged: a surface of no area has no winding to report
            raise ValueError(f"{path}: no face has a positive area (every face is degenerate); a ground truth or "
                             f"an input to sample needs a surface")
        out, _ = orient_outward(out, name=str(path))
    return out


#: Vertices closer than this fraction of the bounding box's largest side count as one position
#: (trimesh's `tol.merge` 1e-8, made relative so that it means the same at every coordinate scale).
MERGE_TOLERANCE = 1e-8


def merge_vertices(vertices, faces, tolerance: float = MERGE_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices that round to the same position on a grid of `tolerance` × the bounding box's largest
    side, among the vertices the faces use (the others are dropped).

    Coordinates are measured from the box's minimum corner in units of its largest side, so the grid keys
    stay within [0, 1 / tolerance] whatever the scale or position: no integer overflow at 1e12 (trimesh's
    absolute 1e-8 grid overflows int64 past ~9e10), no collapse of a mesh 1e-12 across, no lost precision
    for a mesh translated far from the origin. Like trimesh's, the grid can keep two vertices apart that
    straddle a cell boundary; exact duplicates always merge.

    Args:
        vertices: (V, 3) float, finite.
        faces: (F, 3) integer indices into vertices.
        tolerance: grid cell size relative to the box's largest side, in (0, 1).

    Returns:
        vertices: (V', 3) float64, the first occurrence of each position, in input order.
        faces: (F, 3) int64, indices into the merged vertices.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not 0 < tolerance < 1:
        raise ValueError(f"tolerance must be in (0, 1), got {tolerance}")
    if not np.isfinite(v).all():
        raise ValueError("vertices must be finite to merge them")
    used = np.unique(f.ravel())  # ascending, so merged vertices keep the input order (as trimesh's)
    if len(used) == 0:
        return np.zeros((0, 3)), f
    p = v[used]
    lo = p.min(axis=0)
    with np.errstate(over="ignore", invalid="ignore"):
        d = p - lo  # in [0, extent]: measured from the box's corner, so a far translation costs no precision
        if not np.isfinite(d).all():  # a box wider than the largest float (coordinates near +-1e308)
            d = p * 0.5 - lo * 0.5
    extent = float(d.max())
    if extent > 0:
        keys = np.round(d / extent / tolerance).astype(np.int64)  # in [0, 1 / tolerance]: cannot overflow
    else:
        keys = np.zeros(p.shape, np.int64)  # one point
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    # Number the merged vertices in input order, keeping each group's first member's position.
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(first), np.int64)
    rank[order] = np.arange(len(first))
    new_index = np.full(len(v), -1, np.int64)
    new_index[used] = rank[inverse]
    return v[used[first[order]]], new_index[f]


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
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    sides = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2)
    n = int(f.max()) + 1 if len(f) else 1
    # One int64 key per edge (lo * n + hi sorts like the (lo, hi) rows): a 1-D unique, ~5x faster than rows.
    keys, inverse, counts = np.unique(sides.min(axis=1) * n + sides.max(axis=1), return_inverse=True,
                                      return_counts=True)
    return np.stack([keys // n, keys % n], axis=1), inverse.reshape(-1, 3), counts


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


# ------------------------------------------------------------------------------------------ orientation

#: What `orient_outward` finds, in `mesh.metadata["orientation"]` and its second return value.
ORIENTATIONS = ("outward", "flipped", "open", "inconsistent", "non_orientable")
#: Closed parts whose total signed volume is within this fraction of L^3 (L: the bounding box's largest side)
#: count as flat (back-to-back face pairs, a doubled sheet): no inside, so nothing to flip.
FLAT_VOLUME = 1e-9


def _signed_volumes(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n,) float64 signed volume of each face group `labels` (F,): sum of det(v0, v1, v2) / 6 over its faces.

    Translation-invariant for a closed, consistently wound group; measured from the vertex mean to limit
    round-off. Written here because trimesh computes one volume per mesh, not per face group.
    """
    t = vertices[faces] - vertices.mean(axis=0)
    det = np.einsum("fi,fi->f", t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0
    return np.bincount(labels, weights=det, minlength=n)


def orient_outward(mesh: trimesh.Trimesh, name: str = "mesh", quiet: bool = False) -> tuple[trimesh.Trimesh, str]:
    """Turn an inside-out closed mesh outward, and say how the mesh is oriented.

    Orientation metrics and the normals of every sampled input follow the GT's face winding, so an
    inside-out GT file (negative signed volume) would make an outward prediction look inverted. The
    components are those of `components` (faces joined through manifold edges).

    Args:
        mesh: vertices (V, 3), faces (F, 3), F >= 1.
        name: how log lines name the mesh (its file).
        quiet: log at DEBUG instead of WARNING / INFO (for a mesh whose loader already reported it).

    Returns:
        (mesh, status). status is one of `ORIENTATIONS`:
        "outward": consistently wound, every component closed, and the closed components' total signed
            volume is >= 0; the input mesh is returned unchanged.
        "flipped": consistently wound and the closed components' total signed volume was negative: their
            faces were reversed (a new mesh; open components keep their winding). The total, not each
            component's sign, decides, so the inner shell of a hollow solid (a negative component inside a
            larger positive one) stays as it is; a lone inverted part among outward ones is not fixed and
            is logged.
        "open": consistently wound, with at least one open component (no inside, so its winding is kept);
            closed components, if any, were already outward.
        "inconsistent": two faces run a shared manifold edge the same way, but some choice of reversed
            faces would fix it (orientable); returned unchanged: the harness does not choose faces to
            reverse in a GT, and orientation metrics against it are skipped.
        "non_orientable": no consistent winding exists (a Moebius strip, a Klein bottle); unchanged.
        The returned mesh carries the status in `metadata["orientation"]`.
    """
    faces = np.asarray(mesh.faces, np.int64)
    if len(faces) == 0:
        raise ValueError(f"{name}: cannot orient a mesh without faces")
    warn, info = (log.debug, log.debug) if quiet else (log.warning, log.info)
    if not mesh.is_winding_consistent:
        trial = mesh.copy()
        trimesh.repair.fix_winding(trial)  # BFS over face adjacency; fails only without a consistent winding
        status = "inconsistent" if trial.is_winding_consistent else "non_orientable"
        if status == "inconsistent":
            warn("%s: face winding is inconsistent (fixable by reversing faces, which the harness does not "
                 "do to a GT); orientation metrics against it are skipped", name)
        else:
            warn("%s: the surface is non-orientable (no consistent face winding exists); orientation "
                 "metrics against it are skipped", name)
        return _tagged(mesh, status), status
    labels, closed = components(mesh)
    v = np.asarray(mesh.vertices, np.float64)
    vol = _signed_volumes(v, faces, labels, len(closed))
    flat = FLAT_VOLUME * float(np.ptp(v[np.unique(faces)], axis=0).max()) ** 3
    total = float(vol[closed].sum())
    out, status = mesh, ("outward" if closed.all() else "open")
    if closed.any() and total < -flat:
        flip = closed[labels]
        f = faces.copy()
        f[flip] = f[flip][:, ::-1]
        out = trimesh.Trimesh(v, f, process=False)
        vol = -vol if closed.all() else np.where(closed, -vol, vol)
        status = "flipped"
        warn("%s: closed and inside-out (signed volume %.4g): %d faces of %d closed component(s) "
             "flipped outward", name, total, int(flip.sum()), int(closed.sum()))
    inverted = int((closed & (vol < -flat)).sum())
    if inverted:
        info("%s: %d closed component(s) keep a negative signed volume (cavities, or inverted parts "
             "among outward ones; left as they are)", name, inverted)
    return _tagged(out, status), status


def _tagged(mesh: trimesh.Trimesh, status: str) -> trimesh.Trimesh:
    """A new mesh object (same arrays) with `status` in its metadata; the caller's mesh stays untouched."""
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False,
                           metadata={**mesh.metadata, "orientation": status})
