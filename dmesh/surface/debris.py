"""Stages that mark spans and drop stray geometry: spans (long closed-part faces to fair), fins, crumbs (stray
pieces, floating pieces, a few faces beside a closed part), the rim count, stacked pieces and closed crumbs.

Letters: V vertices, F faces, G input points.
"""
from __future__ import annotations

import numpy as np

from dmesh.neighbourhoods import SURFACE_VARIATION, plane_offsets
from dmesh.surface.config import Crumbs, Stacked
from dmesh.surface.topology import (half_edges, edge_pieces, edge_table, edges_in,
                                    nonmanifold_edges, rim_edge_count, winding_components)
from dmesh.tolerances import FLOAT64_FLOOR


def spans(state, cfg):
    """A closed-part face whose longest edge is over `ratio` median edge lengths bridges a stretch the input did
    not sample; it is marked to be faired like a lid."""
    if cfg.ratio > 0 and len(state.closed):
        state.span = long_faces(state.points, state.closed, cfg.ratio) & ~state.lid
    state.info["span_faces"] = int(state.span.sum())
    return state


def fins(state, cfg):
    """A sheet face on an edge that two closed-part faces share (a fin standing off the closed surface) is
    dropped; one on the closed part's rim (a hole left open) stays: it continues the surface there."""
    drop = fin_faces(state.sheet, state.closed)
    state.keep_sheet(~drop)
    state.info["fins_dropped"] = int(drop.sum())
    return state


def fin_faces(sheet: np.ndarray, closed: np.ndarray) -> np.ndarray:
    """(S,) bool: faces of `sheet` with an edge that two or more faces of `closed` share.

    Why not every sheet face on a closed-part edge: where the vote left part of an open shape outside (a tube
    near its cut end, whose walks escape through the end), the surface runs on from the closed part's rim as a
    sheet, and dropping its first row would cut the tube into pieces (docs/surface.md, stage 9).
    """
    sheet = np.asarray(sheet, dtype=np.int64)
    if len(sheet) == 0 or len(closed) == 0:
        return np.zeros(len(sheet), bool)
    edges, _, counts = edge_table(np.asarray(closed, dtype=np.int64))
    return edges_in(half_edges(sheet), edges[counts >= 2]).reshape(3, -1).any(0)


def crumbs(state, cfg):
    """Sheet pieces of at most `max_faces` faces are dropped when every piece is one, or when they float apart
    from the larger ones; so is a sheet part of at most `max_debris` of the faces beside a closed part."""
    sheet, closed = state.sheet, state.closed
    drop = crumb_pieces(sheet, cfg.max_faces) | floating_crumbs(
        state.points, sheet, cfg.max_faces, closed, cfg.floating, cfg.beside, cfg.floating_max_faces,
        cfg.plane_neighbours)
    if len(closed) and len(sheet) <= cfg.max_debris * (len(sheet) + len(closed)):
        drop[:] = True  # a few stray faces beside a closed surface: the input sampled a closed one
    state.keep_sheet(~drop)
    state.info["crumbs_dropped"] = int(drop.sum())
    return state


def rim(state, cfg):
    """How ragged the surface came out, before the sheets' clean-up hides it (the point-cloud `fast` preset's test
    for a mesh in shreds, `redo_fragmented`, reads it): rim edges and faces."""
    faces = state.faces()
    state.info.update(rim_edges=rim_edge_count(faces), rim_faces=int(len(faces)))
    return state


def stacked(state, cfg):
    """A sheet piece of at most `max_faces` faces lying over a larger piece or the closed part, within `within`
    local edge lengths of it, is a stray copy left by noise and is dropped; the sheet edges it hung on are kept
    apart (split_fans), as the faces left would join there in a twist where the sheet folds over itself."""
    sheet = state.sheet
    drop = stacked_pieces(state.points, sheet, state.closed, cfg.within, cfg.max_faces,
                          None if state.samples is None else state.evidence(), cfg.neighbours, cfg.over,
                          cfg.spacings)
    hung = nonmanifold_edges(sheet)
    state.hung = hung[edges_in(hung, edge_table(sheet[drop])[0])]
    state.keep_sheet(~drop)
    state.info["stacked_dropped"] = int(drop.sum())
    return state


def closed_crumbs(state, cfg):
    """A closed piece of at most `max_faces` faces beside a larger piece (one tet's boundary) is dropped."""
    drop = closed_crumb_pieces(state.faces(), cfg.max_faces)
    state.keep_faces(~drop)
    state.info["closed_crumbs_dropped"] = int(drop.sum())
    return state


def long_faces(vertices: np.ndarray, faces: np.ndarray, ratio: float) -> np.ndarray:
    """(F,) bool: faces whose longest edge is more than `ratio` times the median edge length of `faces` (the
    whole surface's median: a spacing local to each corner misses spans whose rim is sparsely sampled too)."""
    if len(faces) == 0:
        return np.zeros(0, bool)
    corners = vertices[faces]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    return edges.max(1) > ratio * np.median(edges)


def crumb_pieces(faces: np.ndarray, max_faces: int) -> np.ndarray:
    """(F,) bool: the faces of a sheet part made only of crumbs, else none.

    A crumb is an edge-connected piece (faces joined through any shared edge) of at most `max_faces` faces.
    When every piece of the sheet part is a crumb, the input sampled a closed surface and the crumbs are
    stray triangles that open a hole in no surface but make the mesh read as not watertight: all are
    flagged. When some piece is larger, the shape has real sheets and small pieces beside them are often
    parts of those (a thin leaf that did not join up): none is flagged.
    """
    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    if F == 0 or max_faces < 1:
        return np.zeros(F, bool)
    _, comp = edge_pieces(f)
    small = np.bincount(comp)[comp] <= max_faces
    return small if small.all() else np.zeros(F, bool)


def floating_crumbs(vertices: np.ndarray, faces: np.ndarray, max_faces: int, others: np.ndarray | None = None,
                    gap: float = Crumbs.floating, beside: float = Crumbs.beside,
                    max_apart: int = Crumbs.floating_max_faces, neighbours: int = Crumbs.plane_neighbours
                    ) -> np.ndarray:
    """(F,) bool: the faces of the small edge-connected pieces of `faces` that float apart from the surface.

    A crumb (a piece of at most `max_faces` faces) floats apart when none of its vertices lies within `gap`
    median edge lengths of a vertex of a piece of more than `max_faces` faces kept here or of
    `others` ((., 3) int, e.g. the closed part), and it does not lie beside that surface in its plane (its centre
    within `beside` of its distance off the plane of the `neighbours` nearest such vertices, where
    they lie flat: a fragment of a sparsely sampled stretch, as a scanner leaves at grazing angles, not a triangle
    among stray points above it). A larger piece, of up to `max_apart` faces, floats apart on the same
    test against the kept pieces larger than itself, when it also lies farther from them than the diagonal of its
    bounding box. Pieces are decided largest first, so a piece near only dropped ones is dropped too. When every
    piece is a crumb, none (`crumb_pieces` decides those).
    """
    from scipy.spatial import cKDTree

    gap = float(gap)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or max_faces < 1:
        return np.zeros(len(f), bool)
    _, comp = edge_pieces(f)
    size = np.bincount(comp)
    if size.max() <= max_faces:
        return np.zeros(len(f), bool)
    v = np.asarray(vertices, dtype=np.float64)
    he = half_edges(f[size[comp] > max_faces])
    spacing = float(np.median(np.linalg.norm(v[he[:, 1]] - v[he[:, 0]], axis=1)))
    limit = max(max_faces, max_apart)
    base = f[size[comp] > limit]
    if others is not None and len(others):
        base = np.concatenate([base, np.asarray(others, dtype=np.int64).reshape(-1, 3)])
    base_tree = cKDTree(v[np.unique(base)]) if len(base) else None
    by_piece = np.argsort(comp, kind="stable")
    starts = np.concatenate([[0], np.cumsum(size)])
    dropped = np.zeros(len(size), bool)
    kept = []  # vertices of the tested pieces kept so far, which anchor the smaller ones
    # Larger pieces one size at a time (each against the kept larger ones), then all crumbs together.
    mid = np.flatnonzero((size > max_faces) & (size <= limit))
    groups = [mid[size[mid] == s] for s in np.unique(size[mid])[::-1]]
    for pieces in groups + [np.flatnonzero(size <= max_faces)]:
        if not len(pieces):
            continue
        faces_of = [f[by_piece[starts[p]:starts[p + 1]]] for p in pieces]
        dropped[pieces] = _float_apart(v, faces_of, base_tree, np.unique(np.concatenate(kept)) if kept else None,
                                       gap * spacing, size[pieces[0]] > max_faces, beside, neighbours)
        if size[pieces[0]] > max_faces:  # (the crumbs come last: what they keep anchors nothing)
            kept += [piece.ravel() for piece, out in zip(faces_of, dropped[pieces]) if not out]
    return dropped[comp]


def _float_apart(v: np.ndarray, pieces: list, base_tree, extra: np.ndarray | None, gap: float,
                 beyond_extent: bool, beside: float, neighbours: int) -> np.ndarray:
    """(len(pieces),) bool: `floating_crumbs`' test of each piece ((n, 3) faces) against the anchors: the
    points of `base_tree` and the vertices `extra` (indices)."""
    from scipy.spatial import cKDTree

    trees = [t for t in (base_tree, cKDTree(v[extra]) if extra is not None and len(extra) else None)
             if t is not None]
    if not trees:
        return np.zeros(len(pieces), bool)
    corners = [np.unique(p) for p in pieces]
    flat = v[np.concatenate(corners)]
    near = np.min([t.query(flat)[0] for t in trees], axis=0)
    near = np.minimum.reduceat(near, np.cumsum([0] + [len(c) for c in corners[:-1]]))
    far = near > gap
    if beyond_extent:
        far &= near > np.array([np.linalg.norm(v[c].max(0) - v[c].min(0)) for c in corners])
    if far.any() and sum(t.n for t in trees) >= neighbours:
        anchors = np.concatenate([t.data for t in trees])  # (only the plane test needs them)
        at = np.flatnonzero(far)
        centre = np.array([v[pieces[i]].mean(1).mean(0) for i in at])
        # The nearest anchors of each centre over both trees: each tree's own nearest, merged.
        found = [t.query(centre, k=min(neighbours, t.n)) for t in trees]
        distance = np.concatenate([d.reshape(len(at), -1) for d, _ in found], axis=1)
        offset = np.cumsum([0] + [t.n for t in trees[:-1]])
        index = np.concatenate([i.reshape(len(at), -1) + o for (_, i), o in zip(found, offset)], axis=1)
        order = np.argsort(distance, axis=1, kind="stable")[:, :neighbours]
        distance, nearest = np.take_along_axis(distance, order, 1), np.take_along_axis(index, order, 1)
        points = np.concatenate([anchors, centre])
        variation, off = plane_offsets(points, np.arange(len(anchors), len(points)), nearest)
        far[at] = ~((variation < SURFACE_VARIATION) & (off <= beside * distance[:, 0]))
    return far


def stacked_pieces(vertices: np.ndarray, faces: np.ndarray, others: np.ndarray | None = None,
                   tol: float = Stacked.within, max_faces: int = Stacked.max_faces, evidence=None,
                   neighbours: int = Stacked.neighbours, over: float = Stacked.over,
                   spacings: float = Stacked.spacings) -> np.ndarray:
    """(F,) bool: the faces of small pieces of `faces` that lie on a larger surface: stray copies of it.

    Pieces are joined through edges of two faces (`edge_pieces` with `manifold`: a piece hanging on a
    non-manifold edge is cut off there by `split_at_fans`). A piece of at most `max_faces` faces is flagged when the
    centroid of each of its faces lies over a face of a strictly larger piece or of `others` (more faces of
    the mesh, e.g. its closed part; (., 3) int), within `tol` local edge lengths of its plane (the length:
    the median longest edge of the face's `neighbours` nearest faces; "over": its closest point on
    that face at most `over` of them aside from the foot of the perpendicular). Noise in the input
    leaves such pieces: a triangle or two floating in the band of the surface over it. They cover nothing
    the larger surface does not, yet each adds a component and three boundary edges, and in a render they
    flicker through the surface. A piece that covers a part of the shape nothing else covers lies farther
    off (a leaf that did not join up) or beside the larger piece's faces (in a hole of it), and stays.
    `evidence`: None, or the `dmesh.surface.evidence.Evidence` of the input points in the frame of `vertices`:
    with it the length is at most `spacings` local sample spacings at the face (`Evidence.spacing_at`), so on a
    coarse mesh a piece the input sampled on its own, a few spacings off a larger one, stays. `tol` <= 0 flags nothing.
    """
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    flagged = np.zeros(F, bool)
    if F == 0 or tol <= 0:
        return flagged
    v = np.asarray(vertices, dtype=np.float64)
    o = np.zeros((0, 3), np.int64) if others is None else np.asarray(others, dtype=np.int64)
    n, piece = edge_pieces(f, manifold=True)
    size = np.bincount(piece, minlength=n)
    query = np.flatnonzero(size[piece] <= max_faces)
    if len(query) == 0 or size.min() == size.max() and len(o) == 0:
        return flagged
    every = np.concatenate([f, o])
    owner_size = np.r_[size[piece], np.full(len(o), np.inf)]
    corners = v[every]
    centres = corners.mean(1)
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(1)
    k = min(neighbours, len(every))
    _, near = cKDTree(centres).query(centres[query], k)
    near = np.asarray(near, np.int64).reshape(len(query), k)
    scale = np.median(longest[near], axis=1)
    qi, fi = np.repeat(query, k), near.ravel()
    larger = owner_size[fi] > size[piece[qi]]  # pieces of one size never absorb each other
    gap = np.full(len(qi), np.inf)
    tri, q = corners[fi[larger]], centres[qi[larger]]
    offset = q - closest_point(tri, q)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), FLOAT64_FLOOR)
    along = np.einsum("ij,ij->i", offset, normal)
    aside = np.linalg.norm(offset - along[:, None] * normal, axis=1)  # 0 when q lies over the face
    on = aside <= over * scale[np.repeat(np.arange(len(query)), k)[larger]]
    gap[np.flatnonzero(larger)[on]] = np.abs(along[on])
    if evidence is not None:
        scale = np.minimum(scale, spacings * evidence.spacing_at(centres[query]))
    ratio = gap.reshape(len(query), k).min(1) / np.maximum(scale, FLOAT64_FLOOR)
    worst = np.zeros(n)
    np.maximum.at(worst, piece[query], ratio)
    on_surface = (worst <= tol) & (size <= max_faces)
    return on_surface[piece]


def closed_crumb_pieces(faces: np.ndarray, max_faces: int) -> np.ndarray:
    """(F,) bool: the faces of closed pieces of at most `max_faces` faces beside a larger piece.

    Pieces are joined through edges that exactly two faces share (`winding_components`); a piece is closed
    when each of its edges has two faces. The smallest real closed surface, a tetrahedron, has 4 faces; a
    closed piece that small beside the mesh's real surface (one tet's boundary, or two faces on the same
    three vertices) is debris of the extraction: it adds a component and, being flat or tiny, faces both
    ways at once.
    """
    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    if F == 0 or max_faces < 1:
        return np.zeros(F, bool)
    _, comp, n = winding_components(f)
    _, inverse, counts = edge_table(f)
    on_boundary = np.zeros(F, bool)
    np.logical_or.at(on_boundary, np.arange(3 * F) % F, counts[inverse] != 2)
    size = np.bincount(comp, minlength=n)
    is_open = np.bincount(comp, on_boundary, n) > 0
    if size.max() <= max_faces:
        return np.zeros(F, bool)
    return ((size <= max_faces) & ~is_open)[comp]


__all__ = ["spans", "fins", "crumbs", "rim", "stacked", "closed_crumbs", "long_faces", "crumb_pieces",
           "floating_crumbs", "stacked_pieces", "closed_crumb_pieces"]
