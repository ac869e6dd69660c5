"""Pure combinatorics of triangle lists for the surface step: edge tables, boundary and non-manifold edges and
vertices, edge-connected pieces, hole loops, fan splits, seams, winding components, sums along pointer walks.

Letters: V vertices, F faces, E edges.

Faces are (F, 3) int64 rows of vertex ids. These are written here rather than taken from trimesh or pymeshlab:
the library depends on neither for them (pymeshlab is a harness extra; trimesh's winding fix propagates across
non-manifold edges), and every stage must keep the invariants the surface step relies on (no new vertex, no
edge used by more than two faces, the winding of the closed part untouched).
"""
from __future__ import annotations

import numpy as np


def half_edges(faces: np.ndarray) -> np.ndarray:
    """(3F, 2) directed edges; row i belongs to face i % F."""
    f = np.asarray(faces, dtype=np.int64)
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


def edge_table(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) (sorted rows), the (3F,) edge id of each half-edge (`half_edges`
    order) and the (E,) number of faces on each edge."""
    he = np.sort(half_edges(faces), axis=1)
    if len(he) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    n = int(he.max()) + 1
    keys, inverse, counts = np.unique(he[:, 0] * n + he[:, 1], return_inverse=True, return_counts=True)
    return np.stack([keys // n, keys % n], 1), inverse.reshape(-1), counts


def edges_in(edges: np.ndarray, among: np.ndarray) -> np.ndarray:
    """(E,) bool: which of `edges` ((E, 2) vertex pairs, either order) are in `among` ((K, 2), either order)."""
    a, b = (np.sort(np.asarray(edges, np.int64).reshape(-1, 2), 1),
            np.sort(np.asarray(among, np.int64).reshape(-1, 2), 1))
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool)
    n = int(max(a.max(), b.max())) + 1
    return np.isin(a[:, 0] * n + a[:, 1], b[:, 0] * n + b[:, 1])


def seam_edges(faces: np.ndarray) -> np.ndarray:
    """(K, 2) int64 edges (sorted pairs) shared by exactly two faces that traverse it in the same direction:
    where the winding of `faces` is not consistent."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros((0, 2), np.int64)
    pairs, same = _manifold_pairs(f)
    return np.sort(half_edges(f)[pairs[same, 0]], axis=1)


def _manifold_pairs(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) the two half-edges (`half_edges` rows) of each edge with exactly two faces, and (M,) bool
    whether they run the same way (a seam)."""
    he = half_edges(f)
    _, inverse, counts = edge_table(f)
    order = np.argsort(inverse, kind="stable")
    pairs = order[(counts[inverse] == 2)[order]].reshape(-1, 2)
    return pairs, (he[pairs[:, 0]] == he[pairs[:, 1]]).all(1)


def nonmanifold_edges(faces: np.ndarray) -> np.ndarray:
    """(K, 2) int64 edges shared by more than two faces."""
    edges, _, counts = edge_table(faces)
    return edges[counts > 2]


def crowded_half_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(F, 3) int64 `faces`, the (3F,) edge id of each half-edge (`edge_table`) and the ids of the half-edges on
    edges with more than two faces (half-edge h belongs to face h % F)."""
    f = np.asarray(faces, dtype=np.int64)
    _, inverse, counts = edge_table(f)
    return f, inverse, np.flatnonzero(counts[inverse] > 2)


def boundary_edge_count(faces: np.ndarray) -> int:
    """Number of edges with exactly one face."""
    return int((edge_table(faces)[2] == 1).sum())


def rim_edge_count(faces: np.ndarray) -> int:
    """Boundary edges once every edge with more than two faces is split apart: edges with exactly one face,
    plus one per face on each edge with more than two (`split_at_fans` gives sheets meeting at an edge their own
    copies of it, each a rim there)."""
    counts = edge_table(faces)[2]
    return int((counts == 1).sum() + counts[counts > 2].sum())


def corner_fans(faces: np.ndarray, cut: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fans of corners: (3F,) vertex of each corner (corner j * F + i is vertex j of face i) and (3F,) fan id.

    Two corners at the same vertex are in one fan when their faces are joined, around that vertex, through
    edges with exactly two faces, other than the edges `cut` ((K, 2) vertex pairs). A manifold vertex has
    one fan; a pinched vertex or the end of an edge with more than two faces (or of a cut one) has several.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    corner_vertex = f.T.reshape(-1)  # half-edge c (`half_edges` order) starts at corner c
    start = np.arange(3 * F)
    end = (start + F) % (3 * F)  # the half-edge's end corner: vertex j + 1 of the same face
    edges, inverse, counts = edge_table(f)
    joins = counts == 2
    if cut is not None and len(cut):
        joins &= ~edges_in(edges, cut)
    order = np.argsort(inverse, kind="stable")
    pairs = order[joins[inverse][order]].reshape(-1, 2)  # the two half-edges of each joining edge
    rows, cols = [], []
    for x in (start, end):
        for y in (start, end):
            a, b = x[pairs[:, 0]], y[pairs[:, 1]]
            same = corner_vertex[a] == corner_vertex[b]
            rows.append(a[same])
            cols.append(b[same])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    _, fan = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * F, 3 * F)),
                                  directed=False)
    return corner_vertex, fan.astype(np.int64)


def nonmanifold_vertices(faces: np.ndarray) -> np.ndarray:
    """(K,) int64 vertices whose faces form more than one fan (`corner_fans`): pinched vertices and the
    ends of non-manifold edges."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros(0, np.int64)
    corner_vertex, fan = corner_fans(f)
    key = np.unique(corner_vertex * (3 * len(f)) + fan)  # distinct (vertex, fan) pairs
    vertices, fans = np.unique(key // (3 * len(f)), return_counts=True)
    return vertices[fans > 1]


def split_at_fans(faces: np.ndarray, n_vertices: int | None = None,
               cut: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex split into one copy per fan (`corner_fans`), which makes every vertex manifold and every
    edge with more than two faces (and every edge in `cut`) several edges, without moving or dropping
    anything.

    Args:
        faces: (F, 3) ints; n_vertices: the vertex count (None: the largest index + 1); cut: (K, 2) vertex
            pairs of edges to part even where they have two faces.
    Returns:
        (F, 3) int64 faces over the new vertices and (V',) int64 the original vertex of each new vertex;
        a vertex's first fan (by lowest corner) keeps its id, the others get ids from `n_vertices` on.
    """
    f = np.asarray(faces, dtype=np.int64)
    n = int(f.max()) + 1 if n_vertices is None else int(n_vertices)
    if len(f) == 0:
        return f.copy(), np.arange(n)
    corner_vertex, fan = corner_fans(f, cut)
    pair, first, inverse = np.unique(corner_vertex * (3 * len(f)) + fan, return_index=True, return_inverse=True)
    vertex = pair // (3 * len(f))
    # the pair holding each vertex's lowest corner keeps the vertex id
    order = np.lexsort((first, vertex))
    head = np.r_[True, vertex[order][1:] != vertex[order][:-1]]
    new_id = np.empty(len(pair), np.int64)
    new_id[order[head]] = vertex[order[head]]
    new_id[order[~head]] = n + np.arange(int((~head).sum()))
    source = np.r_[np.arange(n), vertex[order[~head]]]
    return new_id[inverse.reshape(-1)].reshape(3, -1).T.copy(), source


def edge_pieces(faces: np.ndarray, manifold: bool = False) -> tuple[int, np.ndarray]:
    """The edge-connected pieces of `faces` (faces joined through any shared edge; with `manifold`, only
    through edges that exactly two faces share, as the pieces fall apart once `split_at_fans` has cut the
    others): their number and the (F,) piece of each face."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    if F == 0:
        return 0, np.zeros(0, np.int64)
    _, inverse, counts = edge_table(f)
    order = np.argsort(inverse, kind="stable")
    same_edge = inverse[order[1:]] == inverse[order[:-1]]  # consecutive half-edges on one edge join faces
    if manifold:
        same_edge &= counts[inverse[order[1:]]] == 2
    a, b = order[:-1][same_edge] % F, order[1:][same_edge] % F
    count, piece = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(F, F)), directed=False)
    return int(count), piece


def faces_on_edges(faces: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(F,) bool: faces with an edge that is also an edge of `other` (both (., 3) int arrays)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or len(other) == 0:
        return np.zeros(len(f), bool)
    n = int(max(f.max(), np.max(other))) + 1
    mine = np.sort(half_edges(f), axis=1)
    theirs = np.sort(half_edges(other), axis=1)
    hit = np.isin(mine[:, 0] * n + mine[:, 1], theirs[:, 0] * n + theirs[:, 1])
    return hit.reshape(3, -1).any(0)


def hole_loops(faces: np.ndarray) -> list[list[int]]:
    """Simple vertex loops around the holes of consistently wound faces, each in the direction that the
    faces filling it must traverse (opposite to the faces at its edges). A loop through a vertex twice is
    split there into two simple loops."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return []
    he = half_edges(f)
    _, inverse, counts = edge_table(f)
    successors: dict[int, list[int]] = {}
    for a, b in he[counts[inverse] == 1].tolist():
        successors.setdefault(b, []).append(a)  # the hole runs along b -> a
    loops = []
    for start in sorted(successors):
        while successors.get(start):
            path, seen = [start], {start: 0}
            v = successors[start].pop()
            while v != start and successors.get(v):
                if v in seen:  # close the inner loop v ... v and keep v on the path
                    i = seen[v]
                    loops.append(path[i:])
                    for w in path[i + 1:]:
                        del seen[w]
                    path = path[: i + 1]
                else:
                    seen[v] = len(path)
                    path.append(v)
                v = successors[v].pop()
            if v == start:
                loops.append(path)
    return [loop for loop in loops if len(loop) >= 3]


# ------------------------------------------------------------------------------------------------ winding

def winding_components(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Consistent winding over manifold edges: (F,) bool faces to flip, (F,) component ids, count.

    Faces are joined through edges shared by exactly two faces; a spanning forest of that graph (breadth
    first from one face per component) fixes each face's flip relative to its tree parent: the two must
    traverse their shared edge in opposite directions. The flips are summed along the tree paths by pointer
    doubling. A non-orientable component (a Mobius strip) keeps one seam.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    if F == 0:
        return np.zeros(0, bool), np.zeros(0, np.int64), 0
    he = half_edges(f)
    _, inverse, counts = edge_table(f)
    manifold = counts[inverse] == 2
    order = np.argsort(inverse, kind="stable")
    pairs = order[manifold[order]].reshape(-1, 2)
    fa, fb = pairs[:, 0] % F, pairs[:, 1] % F
    same = (he[pairs[:, 0]] == he[pairs[:, 1]]).all(1)  # same direction: one of the two must flip
    # one tree edge per face pair (a pair sharing two edges is folded; its first edge decides)
    _, first = np.unique(np.stack([np.minimum(fa, fb), np.maximum(fa, fb)], 1), axis=0, return_index=True)
    first = first[fa[first] != fb[first]]
    fa, fb, same = fa[first], fb[first], same[first]
    graph = coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(F, F)).tocsr()
    n, comp = connected_components(graph, directed=False)
    roots = np.unique(comp, return_index=True)[1]
    forest = coo_matrix((np.ones(len(fa) + n), (np.r_[fa, np.full(n, F)], np.r_[fb, roots])),
                        shape=(F + 1, F + 1))
    _, parent = breadth_first_order(forest, F, directed=False, return_predecessors=True)
    parent = parent[:F].astype(np.int64)
    parent[parent < 0] = F
    # the same-direction flag of each face's tree edge (pairs are unique, keyed by their sorted ids)
    pair_key = np.minimum(fa, fb) * F + np.maximum(fa, fb)
    by_key = np.argsort(pair_key)
    child = np.flatnonzero(parent < F)
    tree_key = np.minimum(parent[child], child) * F + np.maximum(parent[child], child)
    step = np.zeros(F, np.int64)
    step[child] = same[by_key[np.searchsorted(pair_key[by_key], tree_key)]]
    flips, _ = sum_along_walks(parent, step, max(1, F.bit_length()))  # a tree path has at most F faces
    return (flips % 2).astype(bool), comp.astype(np.int64), int(n)


def seam_components(faces: np.ndarray, comp: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: which of the `n` components (`comp`, per face) have a seam, an edge shared by exactly two of
    their faces that both traverse in the same direction. After `winding_components`' flips only a
    non-orientable component (a Mobius strip, or a sheet fused to itself) keeps one."""
    f = np.asarray(faces, dtype=np.int64)
    out = np.zeros(n, bool)
    if len(f) == 0:
        return out
    pairs, same = _manifold_pairs(f)
    out[np.asarray(comp)[pairs[same, 0] % len(f)]] = True
    return out


def sum_along_walks(nxt: np.ndarray, step: np.ndarray, max_doublings: int) -> tuple[np.ndarray, np.ndarray]:
    """Sum of `step` ((T,) ints or floats) along each node's path of `nxt` pointers to the sink (index
    len(nxt)), by pointer doubling, at most `max_doublings` rounds. Returns the (T,) sums and (T,) bool whether
    the path reached the sink."""
    T = len(nxt)
    nxt = np.r_[nxt, T]
    total = np.r_[step, 0]
    for _ in range(max_doublings):
        if (nxt == T).all():
            break
        total = total + total[nxt]
        nxt = nxt[nxt]
    return total[:-1], nxt[:-1] == T


__all__ = ["half_edges", "edge_table", "edges_in", "seam_edges", "nonmanifold_edges", "crowded_half_edges",
           "boundary_edge_count", "rim_edge_count", "corner_fans", "nonmanifold_vertices", "split_at_fans",
           "edge_pieces", "faces_on_edges", "hole_loops", "winding_components", "seam_components", "sum_along_walks"]
