"""Meshing at the sampling scale, for the smooth families of `datasets.families`: every edge shorter than `edge`.

Square grids step `edge * GRID_STEP`; swept surfaces (tubes, surfaces of revolution) are staggered rings
`edge * RING_AROUND` apart around and `edge * RING_ALONG` apart along; `auto_edge` picks the default `edge` of a
generator from the sample spacing of `SAMPLES` input points, and `split_long_edges` splits what a boolean left
longer. Why the families are meshed this finely: `datasets.families`.

Shape letters: V vertices, F faces, K rings of S points (a swept surface), P profile points.
"""
from __future__ import annotations

import numpy as np
import trimesh

from datasets.mesh_parts import concat, grid_faces

__all__ = ["GRID_STEP", "RING_AROUND", "RING_ALONG", "SAMPLES", "EDGE_FRACTION", "resample", "revolve", "tube_step",
           "bezier", "open_tube", "capped_tube", "grid_cells", "cylinder", "drop_caps", "auto_edge",
           "split_long_edges"]

#: Square grids (flat faces) step `edge * GRID_STEP`, so a quad's diagonal stays below `edge`, with a margin.
GRID_STEP = 0.97 / np.sqrt(2.0)
#: Staggered rings (`_ring_angles`): points `edge * RING_AROUND` apart around a ring and rings `edge * RING_ALONG`
#: apart, so the triangle sides (the step around, and the hypotenuse over half a step) stay below `edge`,
#: with a margin for a tube's outer side on a bend, where the rings spread.
RING_AROUND = 0.97
RING_ALONG = 0.97 * np.sqrt(3.0) / 2 * 0.88


# ----------------------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------------------

def resample(points: np.ndarray, step: float) -> np.ndarray:
    """A polyline resampled at equal arc length, every segment at most `step` long.

    Args:
        points: (P, D) float64, a densely sampled open polyline.
        step: the longest segment allowed.

    Returns:
        (Q, D) float64 with the same end points, Q = ceil(length / step) + 1.
    """
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    q = int(np.ceil(s[-1] / step)) + 1
    t = np.linspace(0.0, s[-1], q)
    return np.stack([np.interp(t, s, points[:, d]) for d in range(points.shape[1])], 1)


def _ringed(rings: np.ndarray, start: np.ndarray | None = None, end: np.ndarray | None = None) -> trimesh.Trimesh:
    """A swept surface through K closed rings, optionally closed by a pole vertex fanned to each end ring.

    Rings are meant to be staggered (ring k turned by half a step against ring k - 1, see `_ring_angles`), so
    each quad is split along its short diagonal, from (k, j + 1) to (k + 1, j): near-equilateral triangles,
    1.7x fewer than a square grid for the same longest edge.

    Args:
        rings: (K, S, 3) float64, K rings of S points each, in sweep order.
        start, end: (3,) float64 pole vertices fanned to the first / last ring, or None (that end stays
            open: a boundary loop).

    Returns:
        A mesh of 2 S (K - 1) faces plus S per pole, consistently oriented; with both poles it is watertight
        and oriented outward (positive volume).
    """
    k, s = rings.shape[:2]
    i, j = np.meshgrid(np.arange(k - 1), np.arange(s), indexing="ij")
    i, j = i.ravel(), j.ravel()
    a, b = i * s + j, (i + 1) * s + j
    c, d = (i + 1) * s + (j + 1) % s, i * s + (j + 1) % s
    verts = [rings.reshape(-1, 3)]
    faces = [np.stack([a, b, d], 1), np.stack([b, c, d], 1)]
    jj = np.arange(s)
    nxt = (jj + 1) % s
    n = k * s
    if start is not None:
        verts.append(np.asarray(start, float)[None])
        faces.append(np.stack([np.full(s, n), jj, nxt], 1))
        n += 1
    if end is not None:
        verts.append(np.asarray(end, float)[None])
        last = (k - 1) * s
        faces.append(np.stack([np.full(s, n), last + nxt, last + jj], 1))
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces).astype(np.int64), process=False)
    if start is not None and end is not None and mesh.volume < 0:
        mesh.invert()
    return mesh


def _ring_angles(rings: int, sides: int) -> np.ndarray:
    """(K, S) float64 angles of staggered rings: ring k is turned by k half-steps (2 pi / S / 2)."""
    return 2 * np.pi * (np.arange(sides)[None] + 0.5 * np.arange(rings)[:, None]) / sides


def revolve(profile: np.ndarray, edge: float) -> trimesh.Trimesh:
    """The closed surface of revolution about the z axis of a profile running from the axis to the axis.

    Args:
        profile: (P, 2) float64 (r, z) points, r[0] == r[-1] == 0 and r > 0 between; consecutive points at
            most `edge * RING_ALONG` apart.
        edge: the longest edge wanted; sets the segments around so the widest ring's steps are short enough.

    Returns:
        A watertight genus-0 mesh, oriented outward.
    """
    r, z = profile[1:-1, 0], profile[1:-1, 1]
    segments = max(8, int(np.ceil(2 * np.pi * r.max() / (edge * RING_AROUND))))
    phi = _ring_angles(len(r), segments)
    rings = np.stack([r[:, None] * np.cos(phi), r[:, None] * np.sin(phi),
                      np.broadcast_to(z[:, None], (len(r), segments))], -1)
    return _ringed(rings, np.array([0.0, 0.0, profile[0, 1]]), np.array([0.0, 0.0, profile[-1, 1]]))


def _frames(curve: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parallel-transport frames along an open polyline: (normal, binormal), each (U, 3) float64 unit."""
    tangent = np.gradient(curve, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    seed = np.array([0.0, 0.0, 1.0]) if abs(tangent[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    normal = np.empty_like(curve)
    normal[0] = np.cross(tangent[0], np.cross(seed, tangent[0]))
    normal[0] /= np.linalg.norm(normal[0])
    for k in range(1, len(curve)):
        nk = normal[k - 1] - np.dot(normal[k - 1], tangent[k]) * tangent[k]
        normal[k] = nk / np.linalg.norm(nk)
    return normal, np.cross(tangent, normal)


def _sweep_rings(curve: np.ndarray, radius: np.ndarray, edge: float) -> np.ndarray:
    """(U, S, 3) staggered circular cross-sections of `radius` (U,) around `curve` (U, 3), S set by the widest."""
    sides = max(8, int(np.ceil(2 * np.pi * radius.max() / (edge * RING_AROUND))))
    normal, binormal = _frames(curve)
    phi = _ring_angles(len(curve), sides)[..., None]
    ring = np.cos(phi) * normal[:, None] + np.sin(phi) * binormal[:, None]
    return curve[:, None] + radius[:, None, None] * ring


def tube_step(curve: np.ndarray, radius: float, edge: float) -> float:
    """The ring spacing along `curve` (P, 3) for a tube of `radius`: `edge * RING_ALONG`, shortened by the most
    the rings spread on the outer side of a bend (a factor 1 + radius x the curve's largest curvature)."""
    d = np.diff(curve, axis=0)
    ds = np.linalg.norm(d, axis=1)
    t = d / ds[:, None]
    kappa = np.linalg.norm(np.diff(t, axis=0), axis=1) / (0.5 * (ds[1:] + ds[:-1]))
    return edge * RING_ALONG / (1.0 + radius * float(kappa.max(initial=0.0)))


def bezier(p0, p1, p2, n: int = 400) -> np.ndarray:
    """(n, 3) float64 points of the quadratic Bezier curve with control points p0, p1, p2."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 2 * np.asarray(p0) + 2 * t * (1 - t) * np.asarray(p1) + t * t * np.asarray(p2)


def open_tube(curve: np.ndarray, radius: float, edge: float) -> trimesh.Trimesh:
    """An open tube of `radius` (both ends cut: two boundary loops) around a dense open polyline `curve` (P, 3)."""
    c = resample(curve, tube_step(curve, radius, edge))
    return _ringed(_sweep_rings(c, np.full(len(c), float(radius)), edge))


def capped_tube(curve: np.ndarray, r0: float, r1: float, edge: float) -> trimesh.Trimesh:
    """A closed solid: a tube tapering from radius r0 to r1 along `curve` (P, 3), closed by flat end caps
    (concentric staggered rings in the end planes, so the caps are meshed as finely as the wall)."""
    c = resample(curve, tube_step(curve, max(r0, r1), edge))
    n0 = int(np.ceil(r0 / (edge * RING_ALONG)))
    n1 = int(np.ceil(r1 / (edge * RING_ALONG)))
    # Sweep the cap rings as rings of the same tube at the end points, radii shrinking toward the centre.
    radius = np.concatenate([r0 * np.arange(1, n0) / n0, np.linspace(r0, r1, len(c)),
                             r1 * np.arange(n1 - 1, 0, -1) / n1])
    centre = np.concatenate([np.repeat(c[:1], n0 - 1, 0), c, np.repeat(c[-1:], n1 - 1, 0)])
    normal, binormal = _frames(c)
    normal = np.concatenate([np.repeat(normal[:1], n0 - 1, 0), normal, np.repeat(normal[-1:], n1 - 1, 0)])
    binormal = np.concatenate([np.repeat(binormal[:1], n0 - 1, 0), binormal, np.repeat(binormal[-1:], n1 - 1, 0)])
    sides = max(8, int(np.ceil(2 * np.pi * max(r0, r1) / (edge * RING_AROUND))))
    phi = _ring_angles(len(radius), sides)[..., None]
    rings = centre[:, None] + radius[:, None, None] * (np.cos(phi) * normal[:, None] + np.sin(phi) * binormal[:, None])
    return _ringed(rings, c[0], c[-1])


def grid_cells(cells: list[tuple[tuple, tuple]], edge: float) -> trimesh.Trimesh:
    """A watertight solid made of axis-aligned boxes that meet face to face, every face a fine square grid.

    Each cell (lo (3,), hi (3,)) is meshed as a box whose faces are grids of step at most `edge * GRID_STEP`,
    except the faces two cells share (inside the solid); an edge line two outer faces share gets identical
    points in both (the step count depends only on the side length), so merging vertices joins them. No
    boolean is used: manifold3d would collapse the collinear cut points of a straight intersection line
    across a fine grid into long sliver fans.

    Args:
        cells: boxes on a common lattice (two cells share a whole face or nothing).
        edge: the longest edge wanted.

    Returns:
        A watertight mesh, oriented outward.
    """
    rects = []  # (axis, side, lo, hi) of every cell face
    for lo, hi in cells:
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        rects += [(ax, side, lo, hi) for ax in range(3) for side in (-1, 1)]

    def plane(r):  # a cell face without its side: two cells sharing it give the same tuple
        ax, side, lo, hi = r
        flat = lo.copy(), hi.copy()
        flat[0][ax] = flat[1][ax] = lo[ax] if side < 0 else hi[ax]
        return ax, tuple(flat[0]), tuple(flat[1])

    count: dict = {}
    for r in rects:
        count[plane(r)] = count.get(plane(r), 0) + 1
    parts = []
    for ax, side, lo, hi in rects:
        if count[plane((ax, side, lo, hi))] > 1:  # inside the solid
            continue
        u, w = [a for a in range(3) if a != ax]
        nu = int(np.ceil((hi[u] - lo[u]) / (edge * GRID_STEP))) + 1
        nw = int(np.ceil((hi[w] - lo[w]) / (edge * GRID_STEP))) + 1
        gu, gw = np.meshgrid(np.linspace(lo[u], hi[u], nu), np.linspace(lo[w], hi[w], nw), indexing="ij")
        p = np.empty((nu, nw, 3))
        p[..., u], p[..., w], p[..., ax] = gu, gw, lo[ax] if side < 0 else hi[ax]
        f = grid_faces(nu, nw)
        # (u, w, ax) is a right-handed cycle for ax = 0 and 2, left-handed for ax = 1: face outward.
        if (side > 0) != (ax != 1):
            f = f[:, ::-1]
        parts.append(trimesh.Trimesh(p.reshape(-1, 3), f, process=False))
    solid = concat(parts)
    solid.merge_vertices()  # equal linspaces give bit-identical points on shared lines
    return trimesh.Trimesh(solid.vertices, solid.faces, process=False)


def cylinder(center, axis, radius: float, length: float, edge: float) -> trimesh.Trimesh:
    """A closed cylinder (fan caps) of `radius` and `length` centred at `center` along unit `axis`; the wall
    is fine (rings every `edge * RING_ALONG`), the caps coarse (they are cut away when the cylinder drills a hole)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    c = np.asarray(center, float)
    line = c + np.linspace(-length / 2, length / 2, 2)[:, None] * axis
    dense = resample(line, edge * RING_ALONG)
    rings = _sweep_rings(dense, np.full(len(dense), radius), edge)
    return _ringed(rings, dense[0], dense[-1])


def drop_caps(mesh: trimesh.Trimesh, ends: list[tuple[np.ndarray, np.ndarray, float]],
               tol: float = 1e-6) -> trimesh.Trimesh:
    """The mesh without the faces lying on flat end caps: each end is (center (3,), unit outward axis (3,),
    radius); a face goes when all its corners lie in the end's plane within `tol` and within the radius."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    drop = np.zeros(len(f), bool)
    for center, axis, radius in ends:
        d = v - center
        on = (np.abs(d @ axis) < tol) & (np.linalg.norm(d, axis=1) < radius * (1 + 1e-3))
        drop |= on[f].all(1)
    out = trimesh.Trimesh(v, f[~drop], process=False)
    out.remove_unreferenced_vertices()
    return out


#: Input samples the default resolution is set for (the harness's point clouds, DESIGN.md 8.1).
SAMPLES = 100_000
#: The default longest edge as a fraction of the mean nearest-neighbour spacing of `samples` area-uniform
#: samples of the normalised shape (`datasets.splits.edge_to_spacing`): below 1 with a margin.
EDGE_FRACTION = 0.9
#: The longest edge of the coarse first build that measures a shape's scale and sample spacing.
_COARSE = 0.04


def auto_edge(build, samples: int) -> float:
    """The default `edge` of a generator, in its own frame: `EDGE_FRACTION` x the spacing that
    `datasets.splits.edge_to_spacing` measures (`samples` points, seed 0) on a coarse build
    (`build(_COARSE)`), taken back from the normalised frame to the generator's."""
    from datasets.normalize import normalize
    from datasets.splits import edge_to_spacing

    if samples < 2:
        raise ValueError(f"samples: expected at least 2 points, got {samples}")
    coarse = build(_COARSE)
    _, transform = normalize(coarse)
    _, _, spacing = edge_to_spacing(coarse, samples)
    return EDGE_FRACTION * spacing / transform.scale


def split_long_edges(mesh: trimesh.Trimesh, edge: float) -> trimesh.Trimesh:
    """The mesh with every edge longer than `edge` bisected (conforming: both faces of a split edge are split
    in two), repeated until none is left. Mends the few slivers a boolean leaves along its cut curves.

    An edge is long in both faces that hold it, so each pass works on the faces with a long edge only: each
    of them picks its longest edge, and an edge is split when every face holding it picked it.
    """
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    for _ in range(64):
        tri = v[f]
        length = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2)  # (F, 3): edges 01, 12, 20
        long_ = length > edge
        rows = np.flatnonzero(long_.any(1))
        if len(rows) == 0:
            break
        sub, sub_len = f[rows], length[rows]
        ends = np.stack([sub, sub[:, [1, 2, 0]]], 2)  # (R, 3, 2)
        key = np.sort(ends, axis=2)
        key = key[..., 0] * len(v) + key[..., 1]  # (R, 3) int64 edge keys
        ids, inverse = np.unique(key, return_inverse=True)
        inverse = inverse.reshape(key.shape)
        which = sub_len.argmax(1)
        pick = inverse[np.arange(len(rows)), which]
        votes = np.bincount(pick, minlength=len(ids))
        holders = np.bincount(inverse[long_[rows]], minlength=len(ids))
        split = (votes == holders) & (votes > 0)
        if not split.any():  # every long edge is some face's second choice: split the longest one
            split[pick[np.argmax(sub_len.max(1))]] = True
        hit = split[inverse] & (np.arange(3)[None] == which[:, None])  # at most the picked edge of a face
        if not (split[inverse].sum(1) == hit.sum(1)).all():  # a face holds a split edge it did not pick
            hit = split[inverse]
            if (hit.sum(1) > 1).any():
                raise RuntimeError("split_long_edges: two split edges on one face")
        a_ = np.flatnonzero(split)
        mid = np.full(len(ids), -1)
        mid[a_] = len(v) + np.arange(len(a_))
        va, vb = ids[a_] // len(v), ids[a_] % len(v)
        v = np.concatenate([v, 0.5 * (v[va] + v[vb])])
        new = []
        for k in range(3):  # faces whose split edge is edge k (corners k, k+1)
            r = hit[:, k]
            a, b, c = sub[r, k], sub[r, (k + 1) % 3], sub[r, (k + 2) % 3]
            m = mid[inverse[r, k]]
            new += [np.stack([a, m, c], 1), np.stack([m, b, c], 1)]
        changed = np.zeros(len(f), bool)
        changed[rows[hit.any(1)]] = True
        f = np.concatenate([f[~changed]] + new)
    return trimesh.Trimesh(v, f, process=False)
