"""Winding, hole filling and non-manifold clean-up of triangle lists (the last steps of `dmesh.extract`).

Letters: V vertices, F faces, E edges, G input points.

Faces are (F, 3) int64 rows of vertex ids into a (V, 3) float64 array. These are written here rather than
taken from trimesh or pymeshlab: the library depends on neither for them (pymeshlab is a harness extra;
trimesh's `fill_holes` closes only 3- and 4-edge holes and its winding fix propagates across non-manifold
edges), and every step must keep the invariants the extraction relies on (no new vertex, no edge used by
more than two faces, the winding of the closed part untouched).
"""
from __future__ import annotations

import logging

import numpy as np

from dmesh.neighbourhoods import SURFACE_VARIATION, plane_offsets
from dmesh.tolerances import FLOAT64_FLOOR

log = logging.getLogger(__name__)

#: Pointer-doubling rounds of `winding_components` (paths of up to 2^64 faces).
MAX_TREE_DOUBLINGS = 64


def _half_edges(faces: np.ndarray) -> np.ndarray:
    """(3F, 2) directed edges; row i belongs to face i % F."""
    f = np.asarray(faces, dtype=np.int64)
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


def edge_table(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) (sorted rows), the (3F,) edge id of each half-edge (`_half_edges`
    order) and the (E,) number of faces on each edge."""
    he = np.sort(_half_edges(faces), axis=1)
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
    return np.sort(_half_edges(f)[pairs[same, 0]], axis=1)


def _manifold_pairs(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) the two half-edges (`_half_edges` rows) of each edge with exactly two faces, and (M,) bool
    whether they run the same way (a seam)."""
    he = _half_edges(f)
    _, inverse, counts = edge_table(f)
    order = np.argsort(inverse, kind="stable")
    pairs = order[(counts[inverse] == 2)[order]].reshape(-1, 2)
    return pairs, (he[pairs[:, 0]] == he[pairs[:, 1]]).all(1)


def nonmanifold_edges(faces: np.ndarray) -> np.ndarray:
    """(K, 2) int64 edges shared by more than two faces."""
    edges, _, counts = edge_table(faces)
    return edges[counts > 2]


def boundary_edge_count(faces: np.ndarray) -> int:
    """Number of edges with exactly one face."""
    return int((edge_table(faces)[2] == 1).sum())


def rim_edge_count(faces: np.ndarray) -> int:
    """Boundary edges once every edge with more than two faces is split apart: edges with exactly one face,
    plus one per face on each edge with more than two (`split_fans` gives sheets meeting at an edge their own
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
    corner_vertex = f.T.reshape(-1)  # half-edge c (`_half_edges` order) starts at corner c
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


def split_fans(faces: np.ndarray, n_vertices: int | None = None,
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


#: How far `separate_copies` moves each copy of a vertex: this fraction of the way to the mean centroid of its
#: faces (about 3 % of an edge length). Far above float32 rounding and any merge tolerance; far below what a
#: Chamfer distance or a render can see.
COPY_SEPARATION = 0.05


def separate_copies(vertices: np.ndarray, faces: np.ndarray, source: np.ndarray,
                    ratio: float = COPY_SEPARATION) -> np.ndarray:
    """(V, 3) float64 positions in which every vertex that shares its source point with another vertex (the
    copies `split_fans` makes where sheets meet at an edge or a vertex) is moved `ratio` of the way towards the mean
    centroid of its own faces; the other vertices are returned as they are.

    Split copies on one position leave the surface touching itself there, and any merge of vertices by
    position (an STL file, trimesh's default load, a viewer's "merge by distance") joins them into the pinch
    again. Moved into their own faces, the pieces no longer touch (MeshLab's filter that splits non-manifold
    vertices offers the same move as its "vertex displacement ratio").

    Args:
        vertices: (V, 3) float positions of the vertices; faces: (F, 3) int indices into them.
        source: (V,) int, the point each vertex is a copy of (`split_fans`'s second output).
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
    he = _half_edges(f)
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
    flips, _ = sum_along_walks(parent, step, MAX_TREE_DOUBLINGS)
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


# ------------------------------------------------------------------------------------------------ holes

def hole_loops(faces: np.ndarray) -> list[list[int]]:
    """Simple vertex loops around the holes of consistently wound faces, each in the direction that the
    faces filling it must traverse (opposite to the faces at its edges). A loop through a vertex twice is
    split there into two simple loops."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return []
    he = _half_edges(f)
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


def fill_loop(loop: list[int], vertices: np.ndarray, taken: set, banned: set = frozenset()) -> np.ndarray | None:
    """(len(loop) - 2, 3) int64 triangles of least total area spanning the polygon `loop` (dynamic
    programming over its diagonals, as in Barequet and Sharir, "Filling gaps in the boundary of a
    polyhedron", CAGD 1995), wound along the loop; diagonals in `taken` (sorted vertex pairs of existing
    edges) and triangles in `banned` (sorted vertex triples) are not used. None when no such triangulation
    exists."""
    n = len(loop)
    ids = np.asarray(loop, dtype=np.int64)
    p = vertices[ids]
    free = np.ones((n, n), bool)  # free[i, j], i < j: the chord i-j may be used (the loop's edges always)
    i, j = np.triu_indices(n, 2)
    chords = zip(np.minimum(ids[i], ids[j]).tolist(), np.maximum(ids[i], ids[j]).tolist())
    used = np.fromiter((c in taken for c in chords), bool, len(i)) & ~((i == 0) & (j == n - 1))
    free[i[used], j[used]] = False
    at = {u: x for x, u in enumerate(loop)}
    skip = np.array([sorted(at[u] for u in tri) for tri in banned if all(u in at for u in tri)],
                    np.int64).reshape(-1, 3)  # (i, k, j) positions of the banned triangles
    cost = np.full((n, n), np.inf)
    split = np.full((n, n), -1, np.int64)
    cost[np.arange(n - 1), np.arange(1, n)] = 0.0
    for gap in range(2, n):  # every chord i-j of this length at once, over its apexes k
        i = np.arange(n - gap)[:, None]
        j = i + gap
        k = i + np.arange(1, gap)[None, :]
        area = 0.5 * np.linalg.norm(np.cross(p[k] - p[i], p[j] - p[i]), axis=-1)
        mine = skip[skip[:, 2] - skip[:, 0] == gap]
        area[mine[:, 0], mine[:, 1] - mine[:, 0] - 1] = np.inf
        total = cost[i, k] + cost[k, j] + area
        best = np.argmin(total, axis=1)
        value = total[np.arange(len(i)), best]
        ok = free[i[:, 0], j[:, 0]] & np.isfinite(value)
        cost[i[ok, 0], j[ok, 0]] = value[ok]
        split[i[ok, 0], j[ok, 0]] = k[ok, best[ok]]
    if not np.isfinite(cost[0, n - 1]):
        return None
    out, stack = [], [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i >= 2:
            k = int(split[i, j])
            out.append((loop[i], loop[k], loop[j]))
            stack += [(i, k), (k, j)]
    return np.asarray(out, dtype=np.int64)


#: Times a hole whose fill crosses the surface is filled again without the crossing triangles.
FILL_RETRIES = 3


def fill_holes(vertices: np.ndarray, faces: np.ndarray, max_edges: int, uncrossed: bool = True,
               others: np.ndarray | None = None, loops: list[list[int]] | None = None,
               off_others: bool = False) -> tuple[np.ndarray, int, int, int]:
    """Triangles closing the holes of consistently wound `faces` that have at most `max_edges` edges
    (`fill_loop`, no new vertex, no edge used by more than two of them; with `off_others`, no fill edge is
    an edge of `others` either), or the given `loops` (from `hole_loops`, e.g. `sheet_holes`) instead.

    With `uncrossed`, every hole is filled first, then the fills with a triangle crossing `faces` or
    another hole's triangles or `others` (more faces of the mesh, e.g. its sheets; (., 3) int)
    (`crossing_triangles`) are made again without those triangles, up to `FILL_RETRIES` times, and left
    open if they still cross: a fill is not a face of the triangulation, and one through its neighbours
    makes a self-intersecting mesh.

    Returns:
        (K, 3) int64 new faces, the number of holes filled, the number left open, and how many of those
        were left open because their fill crossed the surface.
    """
    f = np.asarray(faces, dtype=np.int64)
    v = np.asarray(vertices, dtype=np.float64)
    others = np.zeros((0, 3), np.int64) if others is None else np.asarray(others, dtype=np.int64)
    if loops is None:
        every = hole_loops(f)
        loops = [loop for loop in every if len(loop) <= max_edges]
    else:
        every = loops
    fills: dict[int, np.ndarray] = {}  # hole -> its accepted triangles
    banned: dict[int, set] = {}  # hole -> triangles of its earlier fills that crossed
    todo, unfillable = list(range(len(loops))), 0
    taken = set(map(tuple, edge_table(np.concatenate([f, others]) if off_others else f)[0].tolist()))
    surface = FaceIndex(v, np.concatenate([f, others])) if uncrossed else None
    for attempt in range(1 + (FILL_RETRIES if uncrossed else 0)):
        kept = [fills[i] for i in sorted(fills)]
        new, owner, chords = [], [], {}
        for i in todo:
            tris = fill_loop(loops[i], v, taken, banned.get(i, frozenset()))
            if tris is None:  # first attempt: no triangulation; later: none without a crossing triangle
                unfillable += attempt == 0
                continue
            new.append(tris)
            owner.append(np.full(len(tris), i))
            chords[i] = set(map(tuple, np.sort(_half_edges(tris), axis=1).tolist())) - taken
            taken |= chords[i]
        if not new:
            break
        tris, owner = np.concatenate(new), np.concatenate(owner)
        hit = (surface.crossing(tris) | crossing_triangles(v, tris, np.concatenate([*kept, tris])) if uncrossed
               else np.zeros(len(tris), bool))
        todo = np.unique(owner[hit]).tolist()
        for i in todo:
            taken -= chords[i]
            banned.setdefault(i, set()).update(map(tuple, np.sort(tris[hit & (owner == i)], axis=1).tolist()))
        fills.update((i, tris[owner == i]) for i in np.setdiff1d(owner, todo).tolist())
        if not todo:
            break
    fill = np.concatenate([fills[i] for i in sorted(fills)]) if fills else np.zeros((0, 3), np.int64)
    crossing = len(loops) - unfillable - len(fills)
    return fill, len(fills), len(every) - len(fills), crossing


#: A sheet hole stays open when a vertex of its loop lies more than this many of its neighbours' mean distances
#: off the plane of its `STRAY_NEIGHBOURS` nearest mesh vertices, where those lie flat
#: (`dmesh.neighbourhoods.SURFACE_VARIATION`): an outlier of the input that the mesh reached; the hole beside
#: it is a gap between faces up to it, and a fill would be one more face of that tent.
STRAY_OFF = 0.3
STRAY_NEIGHBOURS = 16


def sampled_loops(vertices: np.ndarray, loops: list, samples: np.ndarray, gap: float) -> np.ndarray:
    """(len(loops),) bool: which hole loops the input sampled across: the centre of a loop (its vertices'
    mean) lies within `gap` times the samples' spacing (the median distance from a sample to its nearest
    other sample, over at most `SPACING_SAMPLES` of them) of a sample. A loop whose centre is farther from
    every sample surrounds a hole in the input: a hole of the shape, which a coarse mesh rims with a few long
    edges, not a gap the extraction left in a sampled surface."""
    from scipy.spatial import cKDTree

    s = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    if not len(loops) or len(s) < 2:
        return np.ones(len(loops), bool)
    tree = cKDTree(s)
    spacing = sample_spacing(s, tree)
    v = np.asarray(vertices, dtype=np.float64)
    centres = np.array([v[loop].mean(0) for loop in loops])
    return tree.query(centres)[0] <= gap * spacing


def sample_spacing(samples: np.ndarray, tree=None) -> float:
    """The samples' spacing: the median distance from a sample to its nearest other sample, over at most
    `SPACING_SAMPLES` of them (an even subset). `tree`: a cKDTree of `samples`, if one is built already."""
    from scipy.spatial import cKDTree

    s = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    if len(s) < 2:
        return float("inf")
    tree = cKDTree(s) if tree is None else tree
    probe = s[:: max(1, len(s) // SPACING_SAMPLES)]
    return float(np.median(tree.query(probe, k=2)[0][:, 1]))


#: Most samples whose nearest-neighbour distance `sample_spacing` takes the median of (an even subset).
SPACING_SAMPLES = 20_000


def sheet_holes(vertices: np.ndarray, faces: np.ndarray, max_edges: int, max_share: float = 0.25,
                avoid: np.ndarray | None = None, stray_off: float | None = None) -> list[list[int]]:
    """The hole loops (`hole_loops`) inside the sheets `faces` (consistently wound per piece) that a fill may
    close: at most `max_edges` edges and no longer than `max_edges` of its piece's mean edge lengths (a loop
    of long edges runs along triangles spanning a fold, and its fill would too), not the longest loop of
    its piece (its rim: a sheet is open), an area (of the loop's vector area) of at most `max_share` of the
    piece's (a loop that large is part of the rim cut off at a pinch, and its fill would lay a second layer
    on the sheet), no edge of `avoid` ((., 3) int faces, e.g. the closed part, whose edges already have
    their two faces), and no vertex off the surface its neighbours form (`stray_off`; None: `STRAY_OFF`;
    inf: no such test)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or max_edges < 3:
        return []
    v = np.asarray(vertices, dtype=np.float64)
    loops = hole_loops(f)
    if not loops:
        return []
    n, piece = edge_pieces(f)
    he = _half_edges(f)
    _, inverse, counts = edge_table(f)
    rim_half = np.flatnonzero(counts[inverse] == 1)
    face_of = dict(zip(map(tuple, he[rim_half].tolist()), (rim_half % len(f)).tolist()))
    area = np.bincount(piece, 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                                   axis=1), n)
    spacing = (np.bincount(np.tile(piece, 3), np.linalg.norm(v[he[:, 1]] - v[he[:, 0]], axis=1), n)
               / np.maximum(3 * np.bincount(piece, minlength=n), 1))  # mean edge length (inner ones twice)
    blocked = set()
    if avoid is not None and len(avoid):
        blocked = set(map(tuple, edge_table(np.asarray(avoid, dtype=np.int64))[0].tolist()))
    owner, length, share = [], [], []
    for loop in loops:
        p = v[loop]
        q = np.roll(p, -1, axis=0)
        owner.append(piece[face_of[(loop[1], loop[0])]])  # the loop runs against its faces' half-edges
        length.append(float(np.linalg.norm(q - p, axis=1).sum()))
        share.append(0.5 * float(np.linalg.norm(np.cross(p, q).sum(0))) / max(area[owner[-1]], FLOAT64_FLOOR))
    owner, length = np.asarray(owner), np.asarray(length)
    rim = np.full(n, -1)
    order = np.lexsort((length, owner))
    last = np.r_[owner[order][1:] != owner[order][:-1], True]  # the longest loop of each piece
    rim[owner[order][last]] = order[last]
    keep = []
    for i, loop in enumerate(loops):
        edges = zip(loop, loop[1:] + loop[:1])
        if (len(loop) <= max_edges and length[i] <= max_edges * spacing[owner[i]] and rim[owner[i]] != i
                and share[i] <= max_share
                and not any((min(a, b), max(a, b)) in blocked for a, b in edges)):
            keep.append(loop)
    stray_off = STRAY_OFF if stray_off is None else float(stray_off)
    if keep and np.isfinite(stray_off):
        stray = _stray_vertices(v, np.concatenate([f, np.asarray(avoid, np.int64).reshape(-1, 3)]) if avoid is not None
                                else f, np.unique(np.concatenate(keep)), stray_off)
        keep = [loop for loop in keep if not stray.intersection(loop)]
    return keep


def _stray_vertices(vertices: np.ndarray, faces: np.ndarray, at: np.ndarray, off_ratio: float) -> set:
    """The vertices of `at` more than `off_ratio` of their neighbours' mean distance off the plane of their
    `STRAY_NEIGHBOURS` nearest vertices of `faces`, where those form a piece of surface."""
    from scipy.spatial import cKDTree

    used = np.unique(faces)
    k = min(STRAY_NEIGHBOURS + 1, len(used))
    if k < 4:
        return set()
    dist, idx = cKDTree(vertices[used]).query(vertices[at], k)
    nb = used[idx]
    others = np.argsort(nb == at[:, None], axis=1, kind="stable")[:, : k - 1]  # the vertex itself left out
    nb, dist = np.take_along_axis(nb, others, 1), np.take_along_axis(dist, others, 1)
    variation, off = plane_offsets(vertices, at, nb)
    return set(at[(variation < SURFACE_VARIATION) & (off > off_ratio * dist.mean(1))].tolist())


# ------------------------------------------------------------------------------------------------ crossings
# Written here: pymeshlab's self-intersection filter is a harness extra, and CGAL's (through the native
# module) tests every pair of the mesh where only the few fill triangles against their neighbours are needed.

def segments_through_triangles(p0: np.ndarray, p1: np.ndarray, a: np.ndarray, b: np.ndarray,
                               c: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """(P,) bool: segment p0[i] p1[i] passes through the interior of triangle a[i] b[i] c[i], all (P, 3)
    float64 (Moller and Trumbore, "Fast, minimum storage ray-triangle intersection", JGT 1997). A segment
    that only touches the triangle, or lies in its plane, does not."""
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("pc,pc->p", e1, h)
    ok = np.abs(det) > FLOAT64_FLOOR
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p0 - a
    u = np.einsum("pc,pc->p", s, h) * inv
    q = np.cross(s, e1)
    w = np.einsum("pc,pc->p", d, q) * inv
    t = np.einsum("pc,pc->p", e2, q) * inv
    return ok & (u > eps) & (w > eps) & (u + w < 1 - eps) & (t > eps) & (t < 1 - eps)


def triangles_cross(vertices: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(P,) bool over pairs of triangles s[i], t[i] ((P, 3) vertex ids): an edge of one passes through the
    other. Pairs sharing one vertex test only the edges opposite it (as VCG's self-intersection filter
    does); pairs sharing an edge or more never cross."""
    same = s[:, :, None] == t[:, None, :]
    n = same.any(2).sum(1)
    out = np.zeros(len(s), bool)
    for x, y, x_shared in ((s, t, same.any(2)), (t, s, same.any(1))):
        a, b, c = (vertices[y[:, k]] for k in range(3))
        for i in range(3):  # the edge of x opposite its corner i
            use = (n == 0) | ((n == 1) & x_shared[:, i])
            if use.any():
                j, k = (i + 1) % 3, (i + 2) % 3
                hit = segments_through_triangles(vertices[x[use, j]], vertices[x[use, k]], a[use], b[use], c[use])
                out[np.flatnonzero(use)[hit]] = True
    return out


class FaceIndex:
    """Bounding spheres (centroid, farthest corner) of faces and a tree of their centroids, to find the faces
    that a few triangles cross (`crossing`) without rebuilding it for each batch."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        from scipy.spatial import cKDTree

        self.vertices, self.faces = vertices, np.asarray(faces, dtype=np.int64)
        self.centres, self.radii = _spheres(vertices, self.faces)
        # One tree per power-of-two band of radii: a search reaches only as far as the band's largest face.
        band = np.floor(np.log2(np.maximum(self.radii, FLOAT64_FLOOR))).astype(np.int64)
        self.bands = []
        for b in np.unique(band):
            members = np.flatnonzero(band == b)
            self.bands.append((members, cKDTree(self.centres[members]), self.radii[members].max()))

    def crossing(self, tris: np.ndarray) -> np.ndarray:
        """(T,) bool: triangles `tris` ((T, 3) vertex ids) crossing one of the faces (`triangles_cross`;
        the faces may contain them). Candidate pairs are those whose bounding spheres overlap."""
        tris = np.asarray(tris, dtype=np.int64)
        hit = np.zeros(len(tris), bool)
        if len(tris) == 0 or len(self.faces) == 0:
            return hit
        centres, radii = _spheres(self.vertices, tris)
        for members, tree, reach in self.bands:
            near = tree.query_ball_point(centres, radii + reach)
            ti = np.repeat(np.arange(len(tris)), [len(x) for x in near])
            if len(ti) == 0:
                continue
            fi = members[np.concatenate([np.asarray(x, np.int64) for x in near])]
            close = np.linalg.norm(centres[ti] - self.centres[fi], axis=1) <= radii[ti] + self.radii[fi]
            ti, fi = ti[close], fi[close]
            hit[ti[triangles_cross(self.vertices, tris[ti], self.faces[fi])]] = True
        return hit


#: Rounds of `untangle`: each smooths the patch around the faces still crossing, then tests them again.
UNTANGLE_ROUNDS = 5


def untangle(vertices: np.ndarray, faces: np.ndarray, patch: np.ndarray, rounds: int = UNTANGLE_ROUNDS,
             hold: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Smooths away the folds of a patch: where a patch face crosses another face (`FaceIndex`), the patch's
    free vertices (those on patch faces only) within two rings of it move to the mean of their neighbours (five
    uniform Laplacian sweeps), and the test runs again, up to `rounds` times.

    Written here: the folds are a few faces of a faired patch (`dmesh.native.refine_and_fair` over a jagged
    rim), and the smoothing must stay inside the patch, which the libraries' whole-mesh smoothers do not.

    Args:
        vertices: (V, 3) float; faces: (F, 3) int; patch: (F,) bool.
        hold: None, or (H,) bool over the first H vertices: those that are never free.
    Returns:
        (V, 3) float64 vertices (only free patch vertices moved) and (P,) bool over `faces[patch]`: the patch
        faces that still cross a face.
    """
    from scipy.sparse import coo_matrix

    v = np.array(vertices, dtype=np.float64, copy=True)
    f = np.asarray(faces, dtype=np.int64)
    patch = np.asarray(patch, dtype=bool)
    tris = f[patch]
    hit = FaceIndex(v, f).crossing(tris)
    if not hit.any():
        return v, hit
    free = np.zeros(len(v), bool)
    free[tris.reshape(-1)] = True
    free[f[~patch].reshape(-1)] = False
    if hold is not None:
        free[:len(hold)] &= ~np.asarray(hold, dtype=bool)
    e = _half_edges(tris)
    ring = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(v), len(v))).tocsr()
    ring = ((ring + ring.T) > 0).astype(np.float64)
    degree = np.maximum(np.asarray(ring.sum(1)).reshape(-1), 1.0)
    for _ in range(rounds):
        region = np.zeros(len(v), bool)
        region[tris[hit].reshape(-1)] = True
        for _ in range(2):
            region |= (ring @ region.astype(np.float64)) > 0
        region &= free
        if not region.any():
            break
        rows = ring[region]
        for _ in range(5):
            v[region] = (rows @ v) / degree[region, None]
        hit = FaceIndex(v, f).crossing(tris)
        if not hit.any():
            break
    return v, hit


def _spheres(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3) centroids and (F,) distances to the farthest corner of the triangles `faces`."""
    corners = vertices[faces]
    centres = corners.mean(1)
    return centres, np.linalg.norm(corners - centres[:, None], axis=2).max(1)


def crossing_triangles(vertices: np.ndarray, tris: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T,) bool: triangles `tris` crossing a triangle of `faces` (`FaceIndex.crossing`)."""
    return FaceIndex(vertices, faces).crossing(tris)


# ------------------------------------------------------------------------------------------------ fins

def faces_on_edges(faces: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(F,) bool: faces with an edge that is also an edge of `other` (both (., 3) int arrays)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or len(other) == 0:
        return np.zeros(len(f), bool)
    n = int(max(f.max(), np.max(other))) + 1
    mine = np.sort(_half_edges(f), axis=1)
    theirs = np.sort(_half_edges(other), axis=1)
    hit = np.isin(mine[:, 0] * n + mine[:, 1], theirs[:, 0] * n + theirs[:, 1])
    return hit.reshape(3, -1).any(0)


def edge_pieces(faces: np.ndarray, manifold: bool = False) -> tuple[int, np.ndarray]:
    """The edge-connected pieces of `faces` (faces joined through any shared edge; with `manifold`, only
    through edges that exactly two faces share, as the pieces fall apart once `split_fans` has cut the
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


def long_faces(vertices: np.ndarray, faces: np.ndarray, ratio: float) -> np.ndarray:
    """(F,) bool: faces whose longest edge is more than `ratio` times the median edge length of `faces` (the
    whole surface's median: a spacing local to each corner misses spans whose rim is sparsely sampled too)."""
    if len(faces) == 0:
        return np.zeros(0, bool)
    corners = vertices[faces]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    return edges.max(1) > ratio * np.median(edges)


def crumbs(faces: np.ndarray, max_faces: int) -> np.ndarray:
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


#: A crumb beside real sheets is dropped when all its vertices lie farther than this many of the sheets' median
#: edge lengths from every vertex of a larger piece (`floating_crumbs`): a triangle among stray points, where a
#: part of a thin sheet that did not join up lies within an edge or two of it.
FLOATING = 4.0
#: ... unless it lies in the plane of the surface beside it, off that plane by at most this share of its distance
#: from it: a fragment of the same surface lies in that plane, a triangle among stray points above the surface
#: lies off it by about its whole distance.
FLOATING_BESIDE = 0.05
#: Pieces larger than a crumb, up to this many faces, float apart when they also lie farther from every larger
#: piece than their own extent: stray points far off the surface join into pieces of a few long-edged faces,
#: while the fragments a scanner leaves of a sparsely seen stretch lie among each other, closer than their size.
FLOATING_MAX_FACES = 64


def floating_crumbs(vertices: np.ndarray, faces: np.ndarray, max_faces: int, others: np.ndarray | None = None,
                    gap: float | None = None) -> np.ndarray:
    """(F,) bool: the faces of the small edge-connected pieces of `faces` that float apart from the surface.

    A crumb (a piece of at most `max_faces` faces) floats apart when none of its vertices lies within `gap`
    median edge lengths (None: `FLOATING`) of a vertex of a piece of more than `max_faces` faces kept here or of
    `others` ((., 3) int, e.g. the closed part), and it does not lie beside that surface in its plane (its centre
    within `FLOATING_BESIDE` of its distance off the plane of the `STRAY_NEIGHBOURS` nearest such vertices, where
    they lie flat: a fragment of a sparsely sampled stretch, as a scanner leaves at grazing angles, not a triangle
    among stray points above it). A larger piece, of up to `FLOATING_MAX_FACES` faces, floats apart on the same
    test against the kept pieces larger than itself, when it also lies farther from them than the diagonal of its
    bounding box. Pieces are decided largest first, so a piece near only dropped ones is dropped too. When every
    piece is a crumb, none (`crumbs` decides those).
    """
    from scipy.spatial import cKDTree

    gap = FLOATING if gap is None else float(gap)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or max_faces < 1:
        return np.zeros(len(f), bool)
    _, comp = edge_pieces(f)
    size = np.bincount(comp)
    if size.max() <= max_faces:
        return np.zeros(len(f), bool)
    v = np.asarray(vertices, dtype=np.float64)
    he = _half_edges(f[size[comp] > max_faces])
    spacing = float(np.median(np.linalg.norm(v[he[:, 1]] - v[he[:, 0]], axis=1)))
    limit = max(max_faces, FLOATING_MAX_FACES)
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
                                       gap * spacing, size[pieces[0]] > max_faces)
        if size[pieces[0]] > max_faces:  # (the crumbs come last: what they keep anchors nothing)
            kept += [piece.ravel() for piece, out in zip(faces_of, dropped[pieces]) if not out]
    return dropped[comp]


def _float_apart(v: np.ndarray, pieces: list, base_tree, extra: np.ndarray | None, gap: float,
                 beyond_extent: bool) -> np.ndarray:
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
    if far.any() and sum(t.n for t in trees) >= STRAY_NEIGHBOURS:
        anchors = np.concatenate([t.data for t in trees])  # (only the plane test needs them)
        at = np.flatnonzero(far)
        centre = np.array([v[pieces[i]].mean(1).mean(0) for i in at])
        # The nearest anchors of each centre over both trees: each tree's own nearest, merged.
        found = [t.query(centre, k=min(STRAY_NEIGHBOURS, t.n)) for t in trees]
        distance = np.concatenate([d.reshape(len(at), -1) for d, _ in found], axis=1)
        offset = np.cumsum([0] + [t.n for t in trees[:-1]])
        index = np.concatenate([i.reshape(len(at), -1) + o for (_, i), o in zip(found, offset)], axis=1)
        order = np.argsort(distance, axis=1, kind="stable")[:, :STRAY_NEIGHBOURS]
        distance, neighbours = np.take_along_axis(distance, order, 1), np.take_along_axis(index, order, 1)
        points = np.concatenate([anchors, centre])
        variation, off = plane_offsets(points, np.arange(len(anchors), len(points)), neighbours)
        far[at] = ~((variation < SURFACE_VARIATION) & (off <= FLOATING_BESIDE * distance[:, 0]))
    return far


#: Largest piece (faces) that `stacked_pieces` tests: stray copies are a few faces each; a larger piece near
#: another is more likely a real part of the shape lying close to it.
STACKED_MAX_FACES = 64
#: Nearest faces (by centroid) `stacked_pieces` measures each face against.
STACKED_NEIGHBOURS = 16
#: A face lies on another only over it: its centroid's closest point on the other face is at most this many
#: local edge lengths aside from the foot of the perpendicular (a piece in a hole of a larger one lies beside
#: its faces, and covers what they do not).
STACKED_OVER = 0.1
#: A stray copy lies in the band the input's samples spread over: with samples given, `stacked_pieces`'s length
#: is at most this many sample spacings. On a dense mesh an edge is shorter than that and the cap changes
#: nothing; a coarse mesh's edges are many spacings long, and a part of the shape lying within one of them of
#: another (an eye in its socket) is no copy: the input sampled it on its own.
STACKED_SPACINGS = 3.0


def stacked_pieces(vertices: np.ndarray, faces: np.ndarray, others: np.ndarray | None = None,
                   tol: float = 1.0, max_faces: int = STACKED_MAX_FACES, samples: np.ndarray | None = None
                   ) -> np.ndarray:
    """(F,) bool: the faces of small pieces of `faces` that lie on a larger surface: stray copies of it.

    Pieces are joined through edges of two faces (`edge_pieces` with `manifold`: a piece hanging on a
    non-manifold edge is cut off there by `split_fans`). A piece of at most `max_faces` faces is flagged when the
    centroid of each of its faces lies over a face of a strictly larger piece or of `others` (more faces of
    the mesh, e.g. its closed part; (., 3) int), within `tol` local edge lengths of its plane (the length:
    the median longest edge of the face's `STACKED_NEIGHBOURS` nearest faces; "over": its closest point on
    that face at most `STACKED_OVER` of them aside from the foot of the perpendicular). Noise in the input
    leaves such pieces: a triangle or two floating in the band of the surface over it. They cover nothing
    the larger surface does not, yet each adds a component and three boundary edges, and in a render they
    flicker through the surface. A piece that covers a part of the shape nothing else covers lies farther
    off (a leaf that did not join up) or beside the larger piece's faces (in a hole of it), and stays.
    `samples`: None, or (G, 3) input points in the frame of `vertices`: with them the length is at most
    `STACKED_SPACINGS` of their spacings (`sample_spacing`), so on a coarse mesh a piece the input sampled
    on its own, a few spacings off a larger one, stays. `tol` <= 0 flags nothing.
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
    k = min(STACKED_NEIGHBOURS, len(every))
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
    over = aside <= STACKED_OVER * scale[np.repeat(np.arange(len(query)), k)[larger]]
    gap[np.flatnonzero(larger)[over]] = np.abs(along[over])
    if samples is not None:
        scale = np.minimum(scale, STACKED_SPACINGS * sample_spacing(samples))
    ratio = gap.reshape(len(query), k).min(1) / np.maximum(scale, FLOAT64_FLOOR)
    worst = np.zeros(n)
    np.maximum.at(worst, piece[query], ratio)
    on_surface = (worst <= tol) & (size <= max_faces)
    return on_surface[piece]


def closed_crumbs(faces: np.ndarray, max_faces: int) -> np.ndarray:
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


def drop_crowding(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) bool faces to keep: on each edge with more than two faces, the two largest.

    Meant for what `split_fans` leaves: an edge whose faces are joined around both its ends, a sheet folded
    onto itself; each face dropped leaves a hole of one face.
    """
    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    keep = np.ones(F, bool)
    if F == 0:
        return keep
    _, inverse, counts = edge_table(f)
    he = np.flatnonzero(counts[inverse] > 2)
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
    f = np.asarray(faces, dtype=np.int64)
    F = len(f)
    keep = np.ones(F, bool)
    if F == 0:
        return keep
    _, inverse, counts = edge_table(f)
    he = np.flatnonzero(counts[inverse] > 2)
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


__all__ = ["edge_table", "nonmanifold_edges", "corner_fans", "nonmanifold_vertices", "split_fans", "separate_copies",
           "boundary_edge_count", "winding_components", "orient_sheets", "orient_faces", "hole_loops", "fill_loop",
           "fill_holes", "keep_flattest", "faces_on_edges", "drop_crowding"]
