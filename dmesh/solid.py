"""Which tets of a DMesh's triangulation lie inside its surface, and the oriented surface that bounds them.

Letters: N points, T tets, F WDT faces, D walk directions, G input points.

The mesh faces ("walls", an (F,) mask over `pd.faces`) cut the weighted Delaunay triangulation into
regions. A tet is labelled inside by a vote over D walks from it to the convex hull:

- parity (no orientation needed): the walk crosses the walls an odd number of times;
- winding (when each wall has a sign from oriented input normals): the signed crossings sum to a non-zero
  number. Where closed parts of the input overlap (two solids sampled as they are, e.g. a stem sunk into a
  bud), parity hollows the overlap and turns the walls inside it inside-out; the winding number keeps the
  union solid. Its absolute value is used, so an input whose normals all point inwards labels the same.

A walk in direction d leaves each tet through the face the ray from the tet's centroid along d leaves by
(the face with the largest outward area vector along d: barycentric coordinates fall at rate
A_k (n_k . d) / 3V), then restarts from the next tet's centroid, so it is a polyline that follows d and
ends on the hull. Each tet's sum over its walk is computed for all tets at once by pointer doubling.
Walks cross a small hole in the walls only where they happen to meet it, so the majority over directions
stays right where a flood fill from the hull would leak inside (the voted parity test of Nooruddin and
Turk, "Simplification and repair of polygonal models using volumetric techniques", IEEE TVCG 2003, carried
out on the tetrahedralisation instead of a voxel grid; the winding variant is the crossing-count form of
the winding number, and labelling the tets of a tetrahedralisation by a winding number is the approach of
Jacobson et al., "Robust inside-outside segmentation using generalized winding numbers", SIGGRAPH 2013).
Written from the papers; no code is taken from either.

Open sheets among the walls mislead the vote: a walk that crosses a closed surface and then a sheet over
it (a mushroom's cap above its stalk) counts two crossings, even, and calls the tet under the sheet outside,
so the part of a solid that a sheet covers from more than half the directions is lost, and filling the hole
that leaves puts a lid across the solid. So the vote is taken twice (`open_sheet_walls`): the walls of
every large open piece (walls joined through edges with exactly two walls, more of them than a hole that
gets filled has edges, whose rim of one-wall edges could span a lid of more than `max_open` of its area)
that the first labelling left (almost) entirely off the inside/outside boundary are set aside as sheets,
and the walks are repeated over the other walls. A closed surface with small holes keeps its say in the
second vote.

Then (`drop_open_regions`, `repair_pinches`):
- regions of inside tets (joined through non-wall faces) whose boundary is mostly not walls are open
  parts seen as volumes (a bowl's cavity closed by a lid of non-wall faces), and regions much thinner than
  the faces around them are pockets between two layers of one sheet: both are relabelled outside;
- pinches, edges or vertices where the inside touches itself (the boundary surface is non-manifold
  there), are removed by flipping the smallest (least volume) group of same-label tets around them.

The boundary between inside and outside tets is then a closed, consistently oriented 2-manifold; each of
its faces is oriented from its inside tet towards its outside tet (outward).
"""
from __future__ import annotations

import logging

import numpy as np

from dmesh.surface.topology import sum_along_walks

log = logging.getLogger(__name__)

#: Most pointer-doubling rounds of a walk (walks of up to 2**32 tets; longer ones, or cycles, abstain).
MAX_DOUBLINGS = 32


def directions(count: int, seed: int = 0) -> np.ndarray:
    """(count, 3) float64 unit vectors spread evenly over the sphere (a Fibonacci lattice, randomly rotated
    by `seed`, so that no direction lines up with the axes of a grid-like input)."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = np.pi * (1.0 + 5.0 ** 0.5) * i
    d = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return d @ q.T


def outward_area_vectors(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T, 4, 3) float64: for each tet, the area-weighted outward normal of the face opposite vertex k."""
    p = points[tets.astype(np.int64)]
    out = np.empty_like(p)
    for k in range(4):
        a, b, c = (p[:, j] for j in range(4) if j != k)
        n = 0.5 * np.cross(b - a, c - a)
        towards_k = np.einsum("ij,ij->i", n, p[:, k] - a) > 0
        out[:, k] = np.where(towards_k[:, None], -n, n)
    return out


def walk_votes(pd, walls: np.ndarray, dirs: np.ndarray, face_sign: np.ndarray | None = None) -> np.ndarray:
    """(T,) float64: the fraction of the walks from each tet (one per direction) that vote it inside.

    Args:
        pd: `dmesh.wdt.PowerDiagram`.
        walls: (F,) bool over `pd.faces`, the mesh faces.
        dirs: (D, 3) unit walk directions.
        face_sign: None (parity vote), or (F,) float: +1 / -1 where the wall's outside is the side its
            sorted-vertex normal points to / the other side (winding vote, module docstring).
    Walks that do not reach the hull (cycles) abstain; a tet with no finished walk gets 0.
    """
    T = len(pd.tets)
    if T == 0:
        return np.zeros(0)
    area = outward_area_vectors(pd.points, pd.tets)
    rows = np.arange(T)
    neighbours = pd.neighbors.astype(np.int64)
    tet_faces = pd.tet_faces.astype(np.int64)
    if face_sign is not None:
        p = pd.points
        f = pd.faces.astype(np.int64)
        sorted_normal = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    votes = np.zeros(T)
    finished = np.zeros(T)
    for d in dirs:
        k = np.argmax(area @ d, axis=1)
        face = tet_faces[rows, k]
        if face_sign is None:
            step = walls[face].astype(np.int64)
        else:  # leaving a wall's inside: +1; entering it: -1
            leaving = np.einsum("ij,ij->i", sorted_normal[face], area[rows, k]) > 0
            step = np.where(walls[face], np.where(leaving, 1, -1) * np.sign(face_sign[face]), 0).astype(np.int64)
        total, done = sum_along_walks(np.where(neighbours[rows, k] < 0, T, neighbours[rows, k]), step, MAX_DOUBLINGS)
        inside = (total % 2 == 1) if face_sign is None else (total != 0)
        votes += inside & done
        finished += done
    return votes / np.maximum(finished, 1)


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T,) float64 unsigned tet volumes."""
    p = points[tets.astype(np.int64)]
    return np.abs(np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))) / 6.0


def face_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) float64 triangle areas."""
    f = np.asarray(faces, dtype=np.int64)
    return 0.5 * np.linalg.norm(np.cross(points[f[:, 1]] - points[f[:, 0]], points[f[:, 2]] - points[f[:, 0]]), axis=1)


def _sides(pd, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) bool labels of each face's two tets (a hull face's missing tet is outside)."""
    lab = np.r_[inside, False]  # index -1 reads False
    ft = pd.face_tets.astype(np.int64)
    return lab[ft[:, 0]], lab[ft[:, 1]]


def boundary_mask(pd, inside: np.ndarray) -> np.ndarray:
    """(F,) bool: faces between an inside and an outside tet."""
    a, b = _sides(pd, inside)
    return a != b


def drop_open_regions(pd, walls: np.ndarray, inside: np.ndarray, max_open: float,
                      min_thickness: float = 0.0) -> tuple[np.ndarray, int]:
    """`inside` without the regions that do not bound a solid; returns the new (T,) labels and the number
    of regions dropped.

    A region is a connected set of inside tets joined through non-wall faces. It is dropped when
    - its boundary towards outside tets is more than `max_open` (by area) non-wall faces: a closed surface
      with small holes bounds its region with walls except at the holes, while an open surface (a bowl)
      labelled inside by an indecisive vote closes its region with a lid of non-wall faces; or
    - it is thinner than `min_thickness` times the mean edge length of its boundary faces (thickness: twice
      its volume over its boundary area, that of a slab): a pocket between two layers of one sheet (a thin
      surface sampled from both sides), not a solid the samples could resolve.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    T = len(pd.tets)
    a, b = _sides(pd, inside)
    ft = pd.face_tets.astype(np.int64)
    link = ~walls & a & b
    graph = coo_matrix((np.ones(int(link.sum())), (ft[link, 0], ft[link, 1])), shape=(T, T))
    n, region = connected_components(graph, directed=False)
    ids = np.flatnonzero(a != b)
    if len(ids) == 0:
        return inside, 0
    faces = pd.faces[ids].astype(np.int64)
    area = face_areas(pd.points, faces)
    r = region[np.where(a[ids], ft[ids, 0], ft[ids, 1])]
    wall_area = np.bincount(r, area * walls[ids], n)
    open_area = np.bincount(r, area * ~walls[ids], n)
    drop = open_area > max_open * (wall_area + open_area)
    if min_thickness > 0:
        p = pd.points
        edge = (np.linalg.norm(p[faces[:, 1]] - p[faces[:, 0]], axis=1)
                + np.linalg.norm(p[faces[:, 2]] - p[faces[:, 1]], axis=1)
                + np.linalg.norm(p[faces[:, 0]] - p[faces[:, 2]], axis=1)) / 3.0
        mean_edge = np.bincount(r, edge, n) / np.maximum(np.bincount(r, minlength=n), 1)
        volume = np.bincount(region[inside], tet_volumes(p, pd.tets[inside]), n)
        drop |= 2.0 * volume < min_thickness * mean_edge * (wall_area + open_area)
    dropped = drop & (np.bincount(region[inside], minlength=n) > 0)
    return inside & ~drop[region], int(dropped.sum())


def open_sheet_walls(pd, walls: np.ndarray, inside: np.ndarray, max_open: float, min_faces: int,
                     max_boundary: float = 0.1) -> np.ndarray:
    """(F,) bool: the walls of the open pieces that `inside` leaves mostly off its boundary (module docstring).

    A piece is a set of walls joined through edges that exactly two walls share; its rim is its edges with
    a single wall (an edge with three or more walls, where pieces meet, is not rim). A piece is open when
    the disk its rim could span, L^2 / 4 pi for rim length L (an upper bound on the area of its holes), is
    more than `max_open` of its area: a sheet's rim spans a lid of about its own size, the few small holes
    of a closed surface span almost nothing. An open piece of more than `min_faces` faces with at most
    `max_boundary` of its area between an inside and an outside tet is a sheet the labelling did not treat
    as part of a solid. Other pieces stay: a small one covers little of any walk's view (and may plug a
    hole for the walks that pass there), and a piece partly on the boundary is partly a solid's surface.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from dmesh.surface.topology import edge_table

    out = np.zeros(len(walls), bool)
    ids = np.flatnonzero(walls)
    if len(ids) == 0:
        return out
    f = pd.faces[ids].astype(np.int64)
    F = len(f)
    _, edge_of, counts = edge_table(f)
    order = np.argsort(edge_of, kind="stable")
    pairs = order[(counts[edge_of] == 2)[order]].reshape(-1, 2) % F  # the two walls of each two-wall edge
    n, piece = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(F, F)),
                                    directed=False)
    p = pd.points
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # edge_table's half-edge order
    rim = (counts[edge_of] == 1) * np.linalg.norm(p[half[:, 1]] - p[half[:, 0]], axis=1)
    rim_length = np.bincount(piece[np.arange(3 * F) % F], rim, n)
    area = face_areas(p, f)
    piece_area = np.bincount(piece, area, n)
    is_open = rim_length ** 2 / (4.0 * np.pi) > max_open * piece_area
    on_boundary = np.bincount(piece, area * boundary_mask(pd, inside)[ids], n)
    big = np.bincount(piece, minlength=n) > min_faces
    sheet = is_open & big & (on_boundary <= max_boundary * piece_area)
    out[ids[sheet[piece]]] = True
    return out


def _groups(pd, tets: np.ndarray, inside: np.ndarray, shared: tuple) -> list[np.ndarray]:
    """Same-label groups among `tets` (the star of a vertex or the ring of an edge), joined through the
    faces that contain all of `shared`; all hull-side gaps count as one outside tet (id -1)."""
    pos = {int(t): i for i, t in enumerate(tets)}
    parent = list(range(len(tets) + 1))  # the last node stands for the outside beyond the hull

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    hull = len(tets)
    for i, t in enumerate(tets.tolist()):
        for k in range(4):
            if int(pd.tets[t, k]) in shared:
                continue
            nb = int(pd.neighbors[t, k])
            j = hull if nb < 0 else pos.get(nb)
            if j is None:
                continue
            same = (not inside[t]) if nb < 0 else bool(inside[t]) == bool(inside[nb])
            if same:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(tets) + 1):
        groups.setdefault(find(i), []).append(i)
    ids = np.r_[tets, -1]
    return [ids[np.asarray(g)] for g in groups.values() if g != [hull]]


def repair_pinches(pd, inside: np.ndarray, rounds: int = 20) -> tuple[np.ndarray, int]:
    """Flips tets until the inside/outside boundary has no non-manifold edge or vertex (or `rounds` pass).

    Around an edge (or vertex) of a manifold boundary the tets form exactly one inside and one outside group;
    at a pinch there are more. The group of least volume is flipped, which merges its two neighbouring
    groups; groups reaching the hull, or holding a tet flipped before (so that two pinches cannot undo each
    other's repair), are not flipped; when every group is, the whole star (ring) becomes inside, which takes
    the vertex (edge) off the boundary. Returns the new (T,) labels and the number of tet flips.
    """
    from dmesh.surface.topology import nonmanifold_edges, nonmanifold_vertices

    inside = inside.copy()
    volume = tet_volumes(pd.points, pd.tets)
    touched = np.zeros(len(inside), bool)
    flipped = 0
    for _ in range(rounds):
        faces = pd.faces[boundary_mask(pd, inside)].astype(np.int64)
        bad_edges, bad_vertices = nonmanifold_edges(faces), nonmanifold_vertices(faces)
        if len(bad_edges) == 0 and len(bad_vertices) == 0:
            break
        stars = [np.intersect1d(pd.point_tets.row(u), pd.point_tets.row(v)) for u, v in bad_edges.tolist()]
        shared = [tuple(e) for e in bad_edges.tolist()]
        stars += [pd.point_tets.row(v) for v in bad_vertices.tolist()]
        shared += [(v,) for v in bad_vertices.tolist()]
        changed = False
        for star, key in zip(stars, shared):
            groups = _groups(pd, star.astype(np.int64), inside, key)
            if len(groups) <= 2:
                continue  # already repaired by an earlier flip of this round
            cost = [np.inf if (g < 0).any() or touched[g].any() else volume[g].sum() for g in groups]
            if np.isfinite(min(cost)):
                g = groups[int(np.argmin(cost))]
            else:
                g = star[~inside[star]].astype(np.int64)
            inside[g] = ~inside[g]
            touched[g] = True
            flipped += len(g)
            changed = changed or len(g) > 0
        if not changed:
            break
    return inside, flipped


def large_lids(closed: np.ndarray, lids: np.ndarray, min_rim: int) -> np.ndarray:
    """(L,) bool: the `lids` faces of pieces whose rim has more than `min_rim` edges.

    `closed` (the walls between inside and outside tets) and `lids` (the other faces between them) make the
    whole boundary of the inside tets, a closed 2-manifold once pinches are repaired. A piece of lids (joined
    through edges with two lid faces) covers one hole of the walls, or several that the inside tets join, and
    its rim is its edges shared with a wall. A small hole is better closed over its own rim (`dmesh.surface.
    holes.fill_holes`); a hole too large for that is where the input did not sample a closed surface (the part a
    scanner did not see), and the inside tets' boundary across it keeps the solid's topology there (an
    unseen band around a torus stays a band, where a fill of each rim would cap it twice).
    """
    from dmesh.surface.topology import edge_pieces, edge_table

    L = len(lids)
    if L == 0:
        return np.zeros(0, bool)
    count, piece = edge_pieces(lids)
    every = np.concatenate([lids, closed]).astype(np.int64)
    _, inverse, _ = edge_table(every)
    face = np.arange(len(inverse)) % len(every)  # the face of each half-edge (`edge_table`'s order)
    walled = np.zeros(int(inverse.max()) + 1, bool)
    walled[inverse[face >= L]] = True
    rim = (face < L) & walled[inverse]  # a lid's half-edge on an edge it shares with a wall
    rim_edges = np.bincount(piece[face[rim]], minlength=count)
    return rim_edges[piece] > min_rim


def oriented_boundary(pd, inside: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(K, 3) int64: the faces `ids` (each between an inside and an outside tet) wound so that their normal
    (right-hand rule) points from the inside tet to the outside one."""
    ids = np.asarray(ids, dtype=np.int64)
    a, _ = _sides(pd, inside)
    ft = pd.face_tets.astype(np.int64)
    faces = pd.faces[ids].astype(np.int64)
    inner = np.where(a[ids], ft[ids, 0], ft[ids, 1])
    apex = pd.tets[inner].astype(np.int64).sum(1) - faces.sum(1)  # the inside tet's vertex off the face
    p = pd.points
    normal = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    towards_apex = np.einsum("ij,ij->i", normal, p[apex] - p[faces[:, 0]]) > 0
    faces[towards_apex] = faces[towards_apex][:, ::-1]
    return faces


def wall_signs(pd, walls: np.ndarray, points: np.ndarray, normals: np.ndarray, k: int = 3,
               workers: int = 1) -> np.ndarray:
    """(F,) float64: for each wall, the sign of its sorted-vertex normal against the sum of the `k` input
    normals nearest each of its three vertices (0 for non-walls and ties); `walk_votes`' `face_sign`.

    The normals are taken at the vertices, not at the centroid: on a wall thinner than the sample spacing the
    far side's samples can lie nearer a large face's centroid than its own corners do, and their normals point
    the other way (docs/preset_choices.md, "Thin walls").

    Args:
        points, normals: (G, 3) float64 oriented input samples in the frame of `pd`.
    """
    from scipy.spatial import cKDTree

    out = np.zeros(len(pd.faces))
    ids = np.flatnonzero(walls)
    if len(ids) == 0 or len(points) == 0:
        return out
    f = pd.faces[ids].astype(np.int64)
    p = pd.points
    normal = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    k = min(k, len(points))
    _, j = cKDTree(points).query(p[f].reshape(-1, 3), k=k, workers=workers)
    j = j.reshape(len(ids), -1)
    out[ids] = np.sign(np.einsum("ij,ij->i", normal, normals[j].sum(1)))
    return out


__all__ = ["directions", "walk_votes", "drop_open_regions", "open_sheet_walls", "repair_pinches",
           "boundary_mask", "oriented_boundary", "wall_signs", "tet_volumes", "face_areas"]
