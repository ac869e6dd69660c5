"""Stages that close holes: lids over the closed part's large holes, fills of its small ones, fills of the sheets'
small inner holes where the input sampled across them; and the least-area fill they share.

Letters: V vertices, F faces, G input points, L loop vertices.
"""
from __future__ import annotations

import numpy as np

from dmesh import solid
from dmesh.neighbourhoods import SURFACE_VARIATION, plane_offsets
from dmesh.surface.config import Fills, SheetHoles
from dmesh.surface.crossings import FaceIndex, crossing_triangles
from dmesh.surface.topology import edge_pieces, edge_table, faces_on_edges, half_edges, hole_loops
from dmesh.tolerances import FLOAT64_FLOOR


def lids(state, cfg):
    """A hole of the closed part whose rim has more than `max_hole` edges (a stretch the input did not sample) is
    closed by the inside tets' own boundary across it, which keeps the solid's topology."""
    if len(state.closed):
        faces = solid.oriented_boundary(state.pd, state.inside, np.flatnonzero(state.between & ~state.walls))
        faces = faces[solid.large_lids(state.closed, faces, cfg.max_hole)]
        state.add_closed(faces, lid=True)
        state.info.update(lids=edge_pieces(faces)[0], lid_faces=int(len(faces)))
    return state


def fills(state, cfg):
    """The closed part's holes of at most `max_hole` edges get a least-area triangulation of their loop; a fill
    crossing the surface is redone without its crossing triangles, then, on a closed input, closed by the inside
    tets' boundary where that fits, else (`faired`) filled anyway and marked to be faired like a lid (stage fair
    drops it if it still crosses)."""
    fill, filled, left, crossing = state.closed[:0], 0, 0, 0
    if len(state.closed):
        fill, filled, left, crossing = fill_holes(state.points, state.closed, cfg.max_hole, others=state.sheet,
                                                  retries=cfg.retries)
    state.add_closed(fill, fill=True)
    # Only on a closed input (sheets, but for fins, at most `tets_sheets` of the faces): beside real sheets the
    # tets' boundary across a hole runs through tight spots between them and the solid (docs/surface.md).
    sheets = int((~faces_on_edges(state.sheet, state.closed)).sum()) if len(state.sheet) else 0
    closed_input = sheets <= cfg.tets_sheets * (sheets + len(state.closed))
    tets = tet_fills(state) if crossing and cfg.tets and closed_input else state.closed[:0]
    state.add_closed(tets, fill=True)
    faired = faired_fills(state, cfg.max_hole) if crossing and cfg.faired and closed_input else state.closed[:0]
    state.add_closed(faired, lid=True, fill=True)
    state.info.update(holes_filled=filled, hole_faces=int(len(fill)), holes_left=left, holes_crossing=crossing,
                      tet_fills=edge_pieces(tets)[0] if len(tets) else 0, tet_fill_faces=int(len(tets)),
                      faired_fills=edge_pieces(faired)[0] if len(faired) else 0, faired_fill_faces=int(len(faired)))
    return state


def faired_fills(state, max_hole: int) -> np.ndarray:
    """(K, 3) int64 least-area fills of the closed part's holes of at most `max_hole` edges still open, crossings
    allowed: flat, a fill of a hole in a wall thinner than the sample spacing pokes through the wall's other side
    (the test split's thin_cup); refined and faired (stage fair) it follows the wall, and where it still crosses,
    fair drops it."""
    loops = [loop for loop in hole_loops(state.closed) if len(loop) <= max_hole]
    if not loops:
        return state.closed[:0]
    return fill_holes(state.points, state.closed, max_hole, uncrossed=False, loops=loops)[0]


def tet_fills(state) -> np.ndarray:
    """(K, 3) int64 faces closing holes of the closed part that a fill could not close without crossing the
    surface: for each piece of the inside tets' boundary across a hole (faces of the triangulation, so they cross
    none of its other faces) whose every rim edge is still a hole's edge, its faces, wound outward."""
    faces = solid.oriented_boundary(state.pd, state.inside, np.flatnonzero(state.between & ~state.walls))
    if not len(faces):
        return faces
    edges, _, counts = edge_table(state.closed)
    n = len(state.points)

    def key(e: np.ndarray) -> np.ndarray:
        return e[:, 0] * n + e[:, 1]

    count, piece = edge_pieces(faces)
    he = np.sort(half_edges(faces), axis=1)
    face = np.arange(len(he)) % len(faces)
    keys = key(he)
    on_closed = np.isin(keys, key(edges))
    on_hole = np.isin(keys, key(edges[counts == 1]))
    rim = np.bincount(piece[face[on_closed]], minlength=count)
    fits = np.bincount(piece[face[on_closed & on_hole]], minlength=count)
    return faces[((rim > 0) & (fits == rim))[piece]]


def sheet_holes(state, cfg):
    """A hole inside a sheet (never its rim) of at most `max_edges` edges is filled where the input sampled across
    it and no loop vertex is an outlier the mesh reached."""
    points, info = state.points, state.info
    if state.mode == "open":  # the input's boundary is the shape's: no hole is closed
        info.update(sheet_holes_filled=0, sheet_hole_faces=0)
        return state
    loops = sheet_hole_loops(points, state.sheet, cfg.max_edges, cfg.max_share, avoid=state.closed,
                             stray_off=cfg.stray_off, neighbours=cfg.stray_neighbours)
    if loops and state.samples is not None and cfg.gap > 0:
        # A hole the input did not sample across is one of the shape (a coarse mesh rims it with a few long
        # edges), not one the extraction left in a sampled surface.
        sampled = sampled_loops(points, loops, state.evidence(), cfg.gap)
        info["sheet_holes_unsampled"] = int((~sampled).sum())
        loops = [loop for loop, keep in zip(loops, sampled) if keep]
    fill, filled = state.sheet[:0], 0
    if loops:  # (off the closed part's edges: a sheet fill along one would give it a third face there)
        fill, filled = fill_holes(points, state.sheet, cfg.max_edges, others=state.closed, loops=loops,
                                  off_others=True, retries=cfg.retries)[:2]
    state.add_sheet(fill)
    info.update(sheet_holes_filled=filled, sheet_hole_faces=int(len(fill)))
    return state


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


def fill_holes(vertices: np.ndarray, faces: np.ndarray, max_edges: int, uncrossed: bool = True,
               others: np.ndarray | None = None, loops: list[list[int]] | None = None,
               off_others: bool = False, retries: int = Fills.retries) -> tuple[np.ndarray, int, int, int]:
    """Triangles closing the holes of consistently wound `faces` that have at most `max_edges` edges
    (`fill_loop`, no new vertex, no edge used by more than two of them; with `off_others`, no fill edge is
    an edge of `others` either), or the given `loops` (from `hole_loops`, e.g. `sheet_holes`) instead.

    With `uncrossed`, every hole is filled first, then the fills with a triangle crossing `faces` or
    another hole's triangles or `others` (more faces of the mesh, e.g. its sheets; (., 3) int)
    (`crossing_triangles`) are made again without those triangles, up to `retries` times, and left
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
    for attempt in range(1 + (retries if uncrossed else 0)):
        kept = [fills[i] for i in sorted(fills)]
        new, owner, chords = [], [], {}
        for i in todo:
            tris = fill_loop(loops[i], v, taken, banned.get(i, frozenset()))
            if tris is None:  # first attempt: no triangulation; later: none without a crossing triangle
                unfillable += attempt == 0
                continue
            new.append(tris)
            owner.append(np.full(len(tris), i))
            chords[i] = set(map(tuple, np.sort(half_edges(tris), axis=1).tolist())) - taken
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


def sampled_loops(vertices: np.ndarray, loops: list, evidence, gap: float) -> np.ndarray:
    """(len(loops),) bool: which hole loops the input sampled across: the centre of a loop (its vertices'
    mean) lies within `gap` local sample spacings (`evidence`: `dmesh.surface.evidence.Evidence` of the
    samples; the spacing at the nearest sample, `spacing_at`) of a sample. A loop whose centre is farther from
    every sample surrounds a hole in the input: a hole of the shape, which a coarse mesh rims with a few long
    edges, not a gap the extraction left in a sampled surface."""
    if not len(loops) or len(evidence.spacing) < 2:
        return np.ones(len(loops), bool)
    v = np.asarray(vertices, dtype=np.float64)
    centres = np.array([v[loop].mean(0) for loop in loops])
    distance = evidence.tree.query(centres, workers=evidence.workers)[0]
    return distance <= gap * evidence.spacing_at(centres)


def sheet_hole_loops(vertices: np.ndarray, faces: np.ndarray, max_edges: int,
                     max_share: float = SheetHoles.max_share, avoid: np.ndarray | None = None,
                     stray_off: float = SheetHoles.stray_off,
                     neighbours: int = SheetHoles.stray_neighbours) -> list[list[int]]:
    """The hole loops (`hole_loops`) inside the sheets `faces` (consistently wound per piece) that a fill may
    close: at most `max_edges` edges and no longer than `max_edges` of its piece's mean edge lengths (a loop
    of long edges runs along triangles spanning a fold, and its fill would too), not the longest loop of
    its piece (its rim: a sheet is open), an area (of the loop's vector area) of at most `max_share` of the
    piece's (a loop that large is part of the rim cut off at a pinch, and its fill would lay a second layer
    on the sheet), no edge of `avoid` ((., 3) int faces, e.g. the closed part, whose edges already have
    their two faces), and no vertex off the surface its neighbours form (more than `stray_off` of its mean
    distance to its `neighbours` nearest mesh vertices off their plane; inf: no such test)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or max_edges < 3:
        return []
    v = np.asarray(vertices, dtype=np.float64)
    loops = hole_loops(f)
    if not loops:
        return []
    n, piece = edge_pieces(f)
    he = half_edges(f)
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
    stray_off = float(stray_off)
    if keep and np.isfinite(stray_off):
        stray = _stray_vertices(v, np.concatenate([f, np.asarray(avoid, np.int64).reshape(-1, 3)]) if avoid is not None
                                else f, np.unique(np.concatenate(keep)), stray_off, neighbours)
        keep = [loop for loop in keep if not stray.intersection(loop)]
    return keep


def _stray_vertices(vertices: np.ndarray, faces: np.ndarray, at: np.ndarray, off_ratio: float,
                    neighbours: int) -> set:
    """The vertices of `at` more than `off_ratio` of their neighbours' mean distance off the plane of their
    `neighbours` nearest vertices of `faces`, where those form a piece of surface."""
    from scipy.spatial import cKDTree

    used = np.unique(faces)
    k = min(neighbours + 1, len(used))
    if k < 4:
        return set()
    dist, idx = cKDTree(vertices[used]).query(vertices[at], k)
    nb = used[idx]
    others = np.argsort(nb == at[:, None], axis=1, kind="stable")[:, : k - 1]  # the vertex itself left out
    nb, dist = np.take_along_axis(nb, others, 1), np.take_along_axis(dist, others, 1)
    variation, off = plane_offsets(vertices, at, nb)
    return set(at[(variation < SURFACE_VARIATION) & (off > off_ratio * dist.mean(1))].tolist())


__all__ = ["lids", "fills", "faired_fills", "sheet_holes", "fill_loop", "fill_holes", "sampled_loops",
           "sheet_hole_loops"]
