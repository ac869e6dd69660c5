"""Stages that finish the surface: split_fans (a copy of a vertex per fan of faces, then two faces at most on an
edge), copies (split copies moved apart) and fair (lids and spans refined and faired); and `keep_flattest`, the
pair rule mesh to DMesh uses where sheets meet.

Letters: V vertices, F faces, K closed-part faces.
"""
from __future__ import annotations

import logging

import numpy as np

from dmesh.surface.config import Copies, Fair
from dmesh.surface.crossings import untangle
from dmesh.surface.topology import crowded_half_edges, edge_pieces, edges_in, seam_edges, split_at_fans
from dmesh.tolerances import FLOAT64_FLOOR

log = logging.getLogger(__name__)


def split_fans(state, cfg):
    """Every vertex where sheets meet at an edge or a point gets one copy per fan of faces, so no edge has more
    than two faces; a sheet's seam edges where a stacked piece hung stay apart (`seams_cut`). Copies left on one
    point would make the branch or pinch again in any file read back with its vertices merged by position. On an
    edge that still has more than two faces after the split (a sheet folded onto itself), the two largest stay
    (`folds_dropped`), a guarantee of this stage rather than a stage of its own (docs/surface.md)."""
    seams = seam_edges(state.sheet)
    cut = seams[edges_in(seams, state.hung)]
    n = len(state.closed)
    faces, source = split_at_fans(state.faces(), len(state.vertices), cut)
    state.closed, state.sheet = faces[:n], faces[n:]
    state.vertices = state.vertices[source]
    state.info.update(seams_cut=int(len(cut)), split_vertices=int(len(state.vertices) - len(state.points)))
    keep = drop_crowding(state.coords(), state.faces())
    state.keep_faces(keep)
    state.info["folds_dropped"] = int((~keep).sum())
    return state


def copies(state, cfg):
    """Each copy of a split vertex moves `separation` of the way towards its own faces, so a merge by position
    does not rejoin the copies into a pinch."""
    state.positions = separate_copies(state.coords(), state.faces(), state.vertices, cfg.separation)
    return state


def fair(state, cfg):
    """The lids and spans are refined and faired (Liepa's hole filling; a span's corners, input samples, stay);
    folds over a jagged rim are smoothed, and a lid piece that still crosses a face is dropped, its hole left
    open (a span stays flat)."""
    if not (state.lid.any() or state.span.any()):
        return state
    n = len(state.closed)
    v, f, keep, counts = fair_patches(state.coords(), state.closed, state.sheet, state.lid, state.span,
                                      cfg.continuity, cfg.density, cfg.untangle_rounds)
    new = len(f) - n  # faces refinement added (each refined face keeps its index for one of its parts)
    state.lid = np.r_[state.lid, np.ones(new, bool)][keep]
    state.span = np.r_[state.span, np.zeros(new, bool)][keep]
    state.fill = np.r_[state.fill, np.zeros(new, bool)][keep]
    state.closed = f[keep]
    state.vertices = np.r_[state.vertices, np.full(len(v) - len(state.vertices), -1)]
    state.positions = v
    state.added += new
    state.dropped += int((~keep).sum())
    dropped_lid_faces = counts.pop("lid_faces_dropped")
    state.info.update(counts)
    if counts["lids_dropped"]:
        state.info["lid_faces"] = state.info.get("lid_faces", 0) - dropped_lid_faces
    return state


def separate_copies(vertices: np.ndarray, faces: np.ndarray, source: np.ndarray,
                    ratio: float = Copies.separation) -> np.ndarray:
    """(V, 3) float64 positions in which every vertex that shares its source point with another vertex (the
    copies `split_at_fans` makes where sheets meet at an edge or a vertex) is moved `ratio` of the way towards the mean
    centroid of its own faces; the other vertices are returned as they are.

    Split copies on one position leave the surface touching itself there, and any merge of vertices by
    position (an STL file, trimesh's default load, a viewer's "merge by distance") joins them into the pinch
    again. Moved into their own faces, the pieces no longer touch (MeshLab's filter that splits non-manifold
    vertices offers the same move as its "vertex displacement ratio").

    Args:
        vertices: (V, 3) float positions of the vertices; faces: (F, 3) int indices into them.
        source: (V,) int, the point each vertex is a copy of (`split_at_fans`'s second output).
        ratio: fraction of the way to the centroid, in [0, 1).
    """
    if not 0.0 <= ratio < 1.0:
        raise ValueError(f"ratio must be in [0, 1), got {ratio}")
    v = np.array(vertices, dtype=np.float64, copy=True).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    src = np.asarray(source, dtype=np.int64).reshape(-1)
    if len(src) != len(v):
        raise ValueError(f"source has {len(src)} entries for {len(v)} vertices")
    if len(f) == 0 or ratio == 0.0:
        return v
    shared = np.bincount(src)[src] > 1
    corners = f.reshape(-1)
    degree = np.bincount(corners, minlength=len(v))
    move = shared & (degree > 0)
    if not move.any():
        return v
    centroid = np.repeat(v[f].mean(1), 3, axis=0)  # the centroid of each corner's face
    total = np.stack([np.bincount(corners, centroid[:, k], len(v)) for k in range(3)], 1)
    target = total[move] / degree[move, None]
    v[move] += ratio * (target - v[move])
    return v


def fair_patches(vertices: np.ndarray, closed: np.ndarray, sheets: np.ndarray, lid: np.ndarray, span: np.ndarray,
                 continuity: int = Fair.continuity, density: float = Fair.density,
                 rounds: int = Fair.untangle_rounds) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The closed part's lids and spans refined and faired (`dmesh.native.refine_and_fair`; a span's corners held).

    A faired lid can fold where its rim is jagged, or pass through a nearby part of the surface (a leaf over
    the hole). Folds are smoothed away (`dmesh.surface.crossings.untangle`). A lid piece with a face still
    crossing another is dropped, and the others are faired again without it: it closes a hole in a tight spot,
    next to other parts of the surface, where the inside/outside labelling is least sure (docs/surface.md: such
    lids kept flat made mixed shapes worse), so its hole stays open as it did before lids; a dropped piece's
    spans stay, flat. A closed part CGAL cannot take as a 2-manifold drops all its lids, with a warning.

    Args:
        vertices: (V, 3) float; closed: (K, 3) int closed-part faces; sheets: (S, 3) int the other faces;
        lid, span: (K,) bool, the closed-part faces of lids and of spans.
    Returns:
        (V', 3) float64 vertices (the first V as given, but moved where free), (K', 3) int64 the closed part
        refined (each input face keeps its index for one of its parts), (K',) bool the faces to keep (False:
        a dropped lid piece's), and the counts: lid_vertices_added, lids_faired, lids_dropped (pieces of
        lids and spans), lid_faces_dropped.
    """
    from dmesh import native

    patch_faces, own = lid | span, lid & ~span
    count, piece = edge_pieces(closed[patch_faces])
    piece_of = np.full(len(closed), -1)
    piece_of[patch_faces] = piece
    dropped = np.zeros(count, bool)
    # A span's vertices are input samples: only the vertices refinement adds move (a lid's own may move too).
    hold = np.ones(len(vertices), bool)
    hold[closed[own]] = False
    v, f, solved = vertices, closed, True
    while not dropped.all():
        patch = patch_faces & ~dropped[np.maximum(piece_of, 0)]
        try:
            v, f, refined, solved = native.refine_and_fair(vertices, closed, patch, density, continuity, hold)
        except ValueError as err:
            log.warning("surface: the lids over %d large holes are dropped (%s)", count, err)
            dropped[:] = True
            break
        v, hit = untangle(v, np.concatenate([f, sheets]), np.r_[refined, np.zeros(len(sheets), bool)], rounds,
                          hold=hold)
        if not hit.any():
            break
        # Refinement keeps each face's index for one of its parts, so a refined piece holding an input face
        # is that face's lid piece.
        ids = np.flatnonzero(refined)
        _, refined_piece = edge_pieces(f[ids])
        known = ids < len(closed)
        owner = np.full(refined_piece.max() + 1, -1)
        owner[refined_piece[known]] = piece_of[ids[known]]
        bad = owner[np.unique(refined_piece[hit])]
        if (bad < 0).any():
            dropped[:] = True
        dropped[bad[bad >= 0]] = True
    if dropped.all():
        v, f, solved = vertices, closed, True
    if not solved:
        log.warning("surface: the fairing of the lids over %d large holes was not solved; they stay refined, "
                    "unfaired", count)
    # The dropped pieces' faces were left out of the last patch, so they are still the input's, at their indices.
    keep = np.ones(len(f), bool)
    keep[:len(closed)] = ~(own & dropped[np.maximum(piece_of, 0)])  # a span stays, flat
    return v, f, keep, {"lid_vertices_added": int(len(v) - len(vertices)),
                        "lids_faired": bool(solved and not dropped.all()), "lids_dropped": int(dropped.sum()),
                        "lid_faces_dropped": int((~keep).sum())}


def drop_crowding(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) bool faces to keep: on each edge with more than two faces, the two largest.

    Meant for what `split_at_fans` leaves: an edge whose faces are joined around both its ends, a sheet folded
    onto itself; each face dropped leaves a hole of one face.
    """
    f, inverse, he = crowded_half_edges(faces)
    F = len(f)
    keep = np.ones(F, bool)
    if len(he) == 0:
        return keep
    area = 0.5 * np.linalg.norm(np.cross(vertices[f[:, 1]] - vertices[f[:, 0]], vertices[f[:, 2]] - vertices[f[:, 0]]),
                                axis=1)
    edge, face = inverse[he], he % F
    order = np.lexsort((face, -area[face], edge))
    edge, face = edge[order], face[order]
    first = np.r_[True, edge[1:] != edge[:-1]]
    rank = np.arange(len(edge)) - np.maximum.accumulate(np.where(first, np.arange(len(edge)), 0))
    keep[face[rank >= 2]] = False
    return keep


def keep_flattest(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) bool faces to keep: on each edge with more than two faces, the two that continue each other best.

    Each face at the edge is represented by the direction from the edge to its third vertex, perpendicular to
    the edge; the pair whose directions are most opposite (a dihedral angle nearest 180 degrees: the two
    sides of one smooth surface) stays, the other faces there go. A false face spanning across a surface makes
    a sharp fold with every true one, so it is the one dropped. One pass over the edges.
    """
    f, inverse, he = crowded_half_edges(faces)
    F = len(f)
    keep = np.ones(F, bool)
    if len(he) == 0:
        return keep
    v = np.asarray(vertices, dtype=np.float64)
    edge, face, corner = inverse[he], he % F, he // F  # half-edge k of a face runs corner k -> k + 1
    a, b, c = f[face, corner], f[face, (corner + 1) % 3], f[face, (corner + 2) % 3]
    e = v[b] - v[a]
    e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), FLOAT64_FLOOR)
    u = v[c] - v[a]
    u -= np.einsum("ij,ij->i", u, e)[:, None] * e
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), FLOAT64_FLOOR)
    order = np.argsort(edge, kind="stable")
    edge, face, u = edge[order], face[order], u[order]
    starts = np.flatnonzero(np.r_[True, edge[1:] != edge[:-1]])
    for s0, s1 in zip(starts, np.r_[starts[1:], len(edge)]):
        cos = u[s0:s1] @ u[s0:s1].T
        np.fill_diagonal(cos, np.inf)
        i, j = np.unravel_index(np.argmin(cos), cos.shape)
        drop = np.setdiff1d(np.arange(s1 - s0), [i, j])
        keep[face[s0 + drop]] = False
    return keep


__all__ = ["split_fans", "copies", "fair", "separate_copies", "fair_patches", "drop_crowding",
           "keep_flattest"]
