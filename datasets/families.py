"""Synthetic shape families smooth at the sampling scale, for the test split (issue 58).

The generators of `datasets.synthetic` are coarse polyhedra (658 to 4,536 flat faces): 100K input samples
put tens of samples on every flat facet, and a method that triangulates its samples reproduces a facet
exactly. These families mesh analytic surfaces finely instead: every edge is shorter than `edge` (in the
generator's frame, which is close to the unit-radius frame of `datasets.normalize`), and the defaults keep
the longest edge below the mean nearest-neighbour spacing of 100K area-uniform samples of the normalised
shape (`datasets.splits.edge_to_spacing`), so a sample lands on a facet about as often as a facet exists.
That makes them large: 1.6M to 2.1M faces each at the default 100K samples.

One family per failure class that issue 58 names:

- `vessel` (open): a branching tube tree (a vessel or pipe network) whose root and leaf ends are cut open,
  so each end is a boundary loop;
- `thin_cup` (closed): a cup whose wall (and bottom) is 1 % of its radius thick, with a rounded lip;
- `bracket` (closed): a CAD-like L-bracket with sharp edges and cylindrical through-holes;
- `bracket_hose` (mixed): the bracket with an open hose (a tube with cut ends) threaded through one of its
  holes without touching it;
- `tank_pipes` (mixed): a closed smooth tank with open pipes whose ends stand just off its surface.

Like `datasets.synthetic`, every generator takes a seed for its random parameters, returns the identical mesh
for the same arguments, models Z-up and returns Y-up (`_y_up`), and builds mixed shapes from components that
share no vertices. The CSG steps use manifold3d booleans (`_boolean`). Importing this module adds the
families to `datasets.synthetic.SHAPES` (the one registry sweeps resolve names in); `datasets.synthetic`
imports it at its end, so either import order registers them.

Shape letters: V vertices, F faces, K rings of S points (a swept surface), P profile points.
"""
from __future__ import annotations

import logging

import numpy as np
import trimesh

from datasets import synthetic
from datasets.synthetic import _boolean, _concat, _grid_faces, _rotation, _y_up

log = logging.getLogger(__name__)

__all__ = ["FAMILIES", "vessel", "thin_cup", "bracket", "bracket_hose", "tank_pipes"]

#: Square grids (flat faces) step `edge * _STEP`, so a quad's diagonal stays below `edge`, with a margin.
_STEP = 0.97 / np.sqrt(2.0)
#: Staggered rings (`_ring_angles`): points `edge * _AROUND` apart around a ring and rings `edge * _ALONG`
#: apart, so the triangle sides (the step around, and the hypotenuse over half a step) stay below `edge`,
#: with a margin for a tube's outer side on a bend, where the rings spread.
_AROUND = 0.97
_ALONG = 0.97 * np.sqrt(3.0) / 2 * 0.88


# ----------------------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------------------

def _resample(points: np.ndarray, step: float) -> np.ndarray:
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


def _revolve(profile: np.ndarray, edge: float) -> trimesh.Trimesh:
    """The closed surface of revolution about the z axis of a profile running from the axis to the axis.

    Args:
        profile: (P, 2) float64 (r, z) points, r[0] == r[-1] == 0 and r > 0 between; consecutive points at
            most `edge * _ALONG` apart.
        edge: the longest edge wanted; sets the segments around so the widest ring's steps are short enough.

    Returns:
        A watertight genus-0 mesh, oriented outward.
    """
    r, z = profile[1:-1, 0], profile[1:-1, 1]
    segments = max(8, int(np.ceil(2 * np.pi * r.max() / (edge * _AROUND))))
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
    sides = max(8, int(np.ceil(2 * np.pi * radius.max() / (edge * _AROUND))))
    normal, binormal = _frames(curve)
    phi = _ring_angles(len(curve), sides)[..., None]
    ring = np.cos(phi) * normal[:, None] + np.sin(phi) * binormal[:, None]
    return curve[:, None] + radius[:, None, None] * ring


def _tube_step(curve: np.ndarray, radius: float, edge: float) -> float:
    """The ring spacing along `curve` (P, 3) for a tube of `radius`: `edge * _ALONG`, shortened by the most
    the rings spread on the outer side of a bend (a factor 1 + radius x the curve's largest curvature)."""
    d = np.diff(curve, axis=0)
    ds = np.linalg.norm(d, axis=1)
    t = d / ds[:, None]
    kappa = np.linalg.norm(np.diff(t, axis=0), axis=1) / (0.5 * (ds[1:] + ds[:-1]))
    return edge * _ALONG / (1.0 + radius * float(kappa.max(initial=0.0)))


def _bezier(p0, p1, p2, n: int = 400) -> np.ndarray:
    """(n, 3) float64 points of the quadratic Bezier curve with control points p0, p1, p2."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 2 * np.asarray(p0) + 2 * t * (1 - t) * np.asarray(p1) + t * t * np.asarray(p2)


def _open_tube(curve: np.ndarray, radius: float, edge: float) -> trimesh.Trimesh:
    """An open tube of `radius` (both ends cut: two boundary loops) around a dense open polyline `curve` (P, 3)."""
    c = _resample(curve, _tube_step(curve, radius, edge))
    return _ringed(_sweep_rings(c, np.full(len(c), float(radius)), edge))


def _capped_tube(curve: np.ndarray, r0: float, r1: float, edge: float) -> trimesh.Trimesh:
    """A closed solid: a tube tapering from radius r0 to r1 along `curve` (P, 3), closed by flat end caps
    (concentric staggered rings in the end planes, so the caps are meshed as finely as the wall)."""
    c = _resample(curve, _tube_step(curve, max(r0, r1), edge))
    n0 = int(np.ceil(r0 / (edge * _ALONG)))
    n1 = int(np.ceil(r1 / (edge * _ALONG)))
    # Sweep the cap rings as rings of the same tube at the end points, radii shrinking toward the centre.
    radius = np.concatenate([r0 * np.arange(1, n0) / n0, np.linspace(r0, r1, len(c)), r1 * np.arange(n1 - 1, 0, -1) / n1])
    centre = np.concatenate([np.repeat(c[:1], n0 - 1, 0), c, np.repeat(c[-1:], n1 - 1, 0)])
    normal, binormal = _frames(c)
    normal = np.concatenate([np.repeat(normal[:1], n0 - 1, 0), normal, np.repeat(normal[-1:], n1 - 1, 0)])
    binormal = np.concatenate([np.repeat(binormal[:1], n0 - 1, 0), binormal, np.repeat(binormal[-1:], n1 - 1, 0)])
    sides = max(8, int(np.ceil(2 * np.pi * max(r0, r1) / (edge * _AROUND))))
    phi = _ring_angles(len(radius), sides)[..., None]
    rings = centre[:, None] + radius[:, None, None] * (np.cos(phi) * normal[:, None] + np.sin(phi) * binormal[:, None])
    return _ringed(rings, c[0], c[-1])


def _grid_cells(cells: list[tuple[tuple, tuple]], edge: float) -> trimesh.Trimesh:
    """A watertight solid made of axis-aligned boxes that meet face to face, every face a fine square grid.

    Each cell (lo (3,), hi (3,)) is meshed as a box whose faces are grids of step at most `edge * _STEP`,
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
        nu = int(np.ceil((hi[u] - lo[u]) / (edge * _STEP))) + 1
        nw = int(np.ceil((hi[w] - lo[w]) / (edge * _STEP))) + 1
        gu, gw = np.meshgrid(np.linspace(lo[u], hi[u], nu), np.linspace(lo[w], hi[w], nw), indexing="ij")
        p = np.empty((nu, nw, 3))
        p[..., u], p[..., w], p[..., ax] = gu, gw, lo[ax] if side < 0 else hi[ax]
        f = _grid_faces(nu, nw)
        # (u, w, ax) is a right-handed cycle for ax = 0 and 2, left-handed for ax = 1: face outward.
        if (side > 0) != (ax != 1):
            f = f[:, ::-1]
        parts.append(trimesh.Trimesh(p.reshape(-1, 3), f, process=False))
    solid = _concat(parts)
    solid.merge_vertices()  # equal linspaces give bit-identical points on shared lines
    return trimesh.Trimesh(solid.vertices, solid.faces, process=False)


def _cylinder(center, axis, radius: float, length: float, edge: float) -> trimesh.Trimesh:
    """A closed cylinder (fan caps) of `radius` and `length` centred at `center` along unit `axis`; the wall
    is fine (rings every `edge * _ALONG`), the caps coarse (they are cut away when the cylinder drills a hole)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    c = np.asarray(center, float)
    line = c + np.linspace(-length / 2, length / 2, 2)[:, None] * axis
    dense = _resample(line, edge * _ALONG)
    rings = _sweep_rings(dense, np.full(len(dense), radius), edge)
    return _ringed(rings, dense[0], dense[-1])


def _drop_caps(mesh: trimesh.Trimesh, ends: list[tuple[np.ndarray, np.ndarray, float]],
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


def _auto_edge(build, samples: int) -> float:
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


def _split_long_edges(mesh: trimesh.Trimesh, edge: float) -> trimesh.Trimesh:
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
                raise RuntimeError("_split_long_edges: two split edges on one face")
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


# ----------------------------------------------------------------------------------------------------------
# Open: branching tubes with cut ends
# ----------------------------------------------------------------------------------------------------------

def _branch_tree(rng: np.random.Generator, levels: int) -> list[dict]:
    """Branches of a bifurcating tree growing up from (0, 0, -0.9): each a dict with the Bezier control
    points p0, p1, p2 and the radii r0, r1; children start where their parent ends."""
    out: list[dict] = []
    todo = [(np.array([0.0, 0.0, -0.9]), np.array([0.0, 0.0, 1.0]), 0.7, 0.11, 0)]
    while todo:
        p0, d, length, r0, level = todo.pop(0)
        side = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        p2 = p0 + length * d
        bow = side * length * rng.uniform(-0.12, 0.12)
        r1 = r0 * 0.9  # taper along the branch
        out.append(dict(p0=p0, p1=0.5 * (p0 + p2) + bow, p2=p2, r0=r0, r1=r1, level=level))
        if level + 1 >= levels:
            continue
        # Two children in a plane turned about the parent's axis, each at 25-40 degrees to it.
        plane = _rotation(d, rng.uniform(0, 2 * np.pi))[:3, :3] @ side
        tangent_end = p2 - (0.5 * (p0 + p2) + bow)
        tangent_end /= np.linalg.norm(tangent_end)
        for sign in (-1.0, 1.0):
            angle = sign * np.radians(rng.uniform(25, 40))
            axis = np.cross(tangent_end, plane)
            child = _rotation(axis / np.linalg.norm(axis), angle)[:3, :3] @ tangent_end
            todo.append((p2, child, length * rng.uniform(0.7, 0.85), r1 * 2 ** (-1 / 3), level + 1))
    return out


def _tree_clear(branches: list[dict]) -> bool:
    """Whether branches that do not meet at a junction stay apart (by their radii plus a margin)."""
    curves = [_bezier(b["p0"], b["p1"], b["p2"], 60) for b in branches]
    for i in range(len(branches)):
        for j in range(i + 1, len(branches)):
            a, b = branches[i], branches[j]
            if np.allclose(a["p2"], b["p0"]) or np.allclose(b["p2"], a["p0"]) or np.allclose(a["p0"], b["p0"]):
                continue
            dist = np.linalg.norm(curves[i][:, None] - curves[j][None], axis=2).min()
            if dist < a["r0"] + b["r0"] + 0.1:
                return False
    return True


@_y_up
def vessel(seed: int = 0, levels: int = 3, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Open: a branching tube tree (a vessel or pipe network) with cut ends, every edge below `edge`.

    A trunk bifurcates `levels - 1` times (7 branches, 4 leaf ends at the default 3 levels); each branch is a
    bowed, tapering tube, children thinner by Murray's law (radius / 2^(1/3)) at 25-40 degrees to their
    parent, junctions rounded by a sphere slightly wider than the parent's end. The solids are united (one
    manifold3d boolean), then the flat caps of the root and the leaf ends are removed, so each free end is a
    boundary loop (1 + 2^(levels - 1) loops). The seed draws the bows, angles and lengths (redrawn until
    non-adjacent branches stay apart). `edge` None: the sampling-scale default for `samples` input points
    (`_auto_edge`).
    """
    rng = np.random.default_rng(seed)
    for _ in range(100):
        branches = _branch_tree(rng, levels)
        if _tree_clear(branches):
            break
    else:  # pragma: no cover - the margins make a clash rare
        raise ValueError(f"vessel: no clear tree found for seed {seed}")

    def build(step: float) -> trimesh.Trimesh:
        solids, ends = [], []
        for b in branches:
            dense = _bezier(b["p0"], b["p1"], b["p2"])
            curve = _resample(dense, _tube_step(dense, max(b["r0"], b["r1"]), step))  # as `_capped_tube` does
            solids.append(_capped_tube(dense, b["r0"], b["r1"], step))
            t0, t1 = curve[0] - curve[1], curve[-1] - curve[-2]
            if b["level"] == 0:
                ends.append((curve[0], t0 / np.linalg.norm(t0), b["r0"]))
            if b["level"] == levels - 1:
                ends.append((curve[-1], t1 / np.linalg.norm(t1), b["r1"]))
            else:  # a junction: a sphere a little wider than the parent's end holds its cap and the children's
                r = 1.05 * b["r1"]
                sub = int(np.ceil(np.log2(1.2 * r / (step * 0.9))))  # icosphere edges ~ 1.1 r / 2^sub
                ball = trimesh.creation.icosphere(subdivisions=sub, radius=r)
                ball.apply_translation(curve[-1])
                solids.append(ball)
        return _split_long_edges(_drop_caps(_boolean("union", solids), ends), step)

    return build(edge or _auto_edge(build, samples))


# ----------------------------------------------------------------------------------------------------------
# Closed: a thin-walled shell; a CAD-like part
# ----------------------------------------------------------------------------------------------------------

def _offset_2d(curve: np.ndarray, dist: float) -> np.ndarray:
    """(P, 2) points of a 2D polyline moved by `dist` along its left normals (vertex-averaged)."""
    t = np.gradient(curve, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return curve + dist * np.stack([-t[:, 1], t[:, 0]], 1)


@_y_up
def thin_cup(seed: int = 0, wall: float = 0.01, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Closed: a cup whose wall and bottom are `wall` x its radius thick (1 %), with a rounded lip.

    A surface of revolution of one closed profile: the outer bottom, a rounded heel, a slightly flared and
    bulged outer wall up to the rim, a half-circle lip, and the inner wall and bottom offset inward by the wall
    thickness. The seed draws the radius, height, flare and bulge. Every edge is below `edge` (None: the
    sampling-scale default for `samples` input points, `_auto_edge`).
    """
    rng = np.random.default_rng(seed)
    radius = 0.5 * (1.0 + 0.1 * rng.uniform(-1, 1))
    height = 1.3 * (1.0 + 0.1 * rng.uniform(-1, 1))
    flare, bulge = rng.uniform(0.0, 0.2), rng.uniform(-0.05, 0.08)
    heel = 0.12 * radius
    thick = wall * radius
    z0 = -height / 2

    def build(step: float) -> trimesh.Trimesh:
        return _cup_profile_revolved(radius, height, flare, bulge, heel, thick, z0, step)

    return build(edge or _auto_edge(build, samples))


def _cup_profile_revolved(radius, height, flare, bulge, heel, thick, z0, edge) -> trimesh.Trimesh:
    """The surface of revolution of `thin_cup` for its drawn parameters."""
    # Outer profile from the bottom centre to the rim (counter-clockwise in (r, z): its left is inside).
    bottom = np.stack([np.linspace(0.0, radius - heel, 200), np.full(200, z0)], 1)
    a = np.linspace(-np.pi / 2, 0.0, 100)
    arc = np.stack([radius - heel + heel * np.cos(a), z0 + heel + heel * np.sin(a)], 1)
    s = np.linspace(0.0, 1.0, 600)
    h = heel + s * (height - heel)
    side = np.stack([radius * (1.0 + flare * s ** 2 + bulge * np.sin(np.pi * s)), z0 + h], 1)
    outer = _resample(np.concatenate([bottom, arc[1:], side[1:]]), edge * _STEP / 4)
    inner = _offset_2d(outer, thick)
    top_o, top_i = outer[-1], inner[-1]
    mid = 0.5 * (top_o + top_i)
    n = (top_o - top_i) / np.linalg.norm(top_o - top_i)
    up = np.array([-n[1], n[0]])
    up = up if up[1] > 0 else -up
    th = np.linspace(0.0, np.pi, 64)[1:-1]
    lip = mid + (thick / 2) * (np.cos(th)[:, None] * n + np.sin(th)[:, None] * up)
    inner[0, 0] = 0.0  # the offset of the bottom centre stays on the axis
    profile = np.concatenate([outer, lip, inner[::-1]])
    profile = np.concatenate([_resample(profile[: len(outer) + len(lip) + 1], edge * _ALONG),
                              _resample(profile[len(outer) + len(lip):], edge * _ALONG)[1:]])
    return _revolve(profile, edge)


def _bracket_params(rng: np.random.Generator) -> dict:
    """The drawn sizes of `bracket`: plate length, depth, thickness, upright rise and the hole radii."""
    return dict(length=1.5 * (1.0 + 0.08 * rng.uniform(-1, 1)), depth=0.8 * (1.0 + 0.08 * rng.uniform(-1, 1)),
                thick=0.12 * (1.0 + 0.15 * rng.uniform(-1, 1)), rise=0.75 * (1.0 + 0.1 * rng.uniform(-1, 1)),
                r_base=rng.uniform(0.06, 0.09), r_up=rng.uniform(0.12, 0.16))


def _bracket_raw(params: dict, edge: float) -> tuple[trimesh.Trimesh, dict]:
    """The Z-up L-bracket of `bracket` for `params` (`_bracket_params`), and the centres and radius of its
    upright's holes."""
    length, depth, thick, rise = params["length"], params["depth"], params["thick"], params["rise"]
    x0, y0, z0 = -length / 2, -depth / 2, -0.35
    x1, y1, z1, z2 = x0 + length, y0 + thick, z0 + thick, z0 + thick + rise
    # The L section (in y, z) as three cells: the corner, the rest of the base, the rest of the upright.
    body = _grid_cells([((x0, y0, z0), (x1, y1, z1)), ((x0, y1, z0), (x1, y0 + depth, z1)),
                        ((x0, y0, z1), (x1, y1, z2))], edge)
    holes = []
    r_base, r_up = params["r_base"], params["r_up"]
    for fx in (0.2, 0.8):  # two bolt holes through the base, in front of the upright
        holes.append(_cylinder([x0 + fx * length, y1 + 0.55 * (depth - thick), z0 + thick / 2],
                               [0, 0, 1], r_base, 3 * thick, edge))
    centers = [np.array([x0 + fx * length, y0 + thick / 2, z1 + 0.55 * rise]) for fx in (0.3, 0.7)]
    for c in centers:  # two larger holes through the upright
        holes.append(_cylinder(c, [0, 1, 0], r_up, 3 * thick, edge))
    out = _split_long_edges(_boolean("difference", [body, _boolean("union", holes)]), edge)
    return out, {"centers": centers, "radius": r_up}


@_y_up
def bracket(seed: int = 0, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Closed: a CAD-like L-bracket with sharp edges and four cylindrical through-holes (genus 4).

    A base plate and an upright plate (boxes meshed as fine grids, united), two bolt holes through the base
    and two larger holes through the upright (manifold3d booleans with finely meshed cylinders). Flat faces
    stay flat and edges stay sharp; the grids make every edge shorter than `edge`, so the flat faces carry no
    large facets either. The seed draws the plate sizes, the thickness and the hole radii. `edge` None: the
    sampling-scale default for `samples` input points (`_auto_edge`).
    """
    params = _bracket_params(np.random.default_rng(seed))

    def build(step: float) -> trimesh.Trimesh:
        return _bracket_raw(params, step)[0]

    return build(edge or _auto_edge(build, samples))


# ----------------------------------------------------------------------------------------------------------
# Mixed: closed bodies with open tubes, as disjoint components
# ----------------------------------------------------------------------------------------------------------

@_y_up
def bracket_hose(seed: int = 0, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Mixed: the closed `bracket` (same seed) with an open hose (a tube with cut ends, 60 % of the hole's
    radius) threaded through one of its upright holes, curving down in front and up behind; the hose never
    touches the bracket. `edge` None: the sampling-scale default for `samples` input points
    (`_auto_edge`)."""
    rng = np.random.default_rng(seed)
    params = _bracket_params(rng)
    which = int(rng.integers(2))

    def build(step: float) -> trimesh.Trimesh:
        part, info = _bracket_raw(params, step)
        c, r = info["centers"][which], info["radius"]
        front, back = c + np.array([0.0, 0.45, -0.1]), c + np.array([0.0, -0.5, 0.25])
        curve = np.concatenate([_bezier(front, c + [0.0, 0.2, 0.0], c, 200)[:-1],
                                _bezier(c, c - [0.0, 0.2, 0.0], back, 200)])
        return _concat([part, _open_tube(curve, 0.6 * r, step)])

    return build(edge or _auto_edge(build, samples))


@_y_up
def tank_pipes(seed: int = 0, pipes: int = 2, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Mixed: a closed smooth tank (a surface of revolution with rounded ends) and `pipes` open pipes (tubes
    with cut ends) leaving its side, their inner ends 2 % of the tank's radius off its surface, bending up.
    The seed draws the tank's proportions and each pipe's height, direction and bend. `edge` None: the
    sampling-scale default for `samples` input points (`_auto_edge`)."""
    rng = np.random.default_rng(seed)
    radius = 0.45 * (1.0 + 0.1 * rng.uniform(-1, 1))
    half = 0.35 * (1.0 + 0.15 * rng.uniform(-1, 1))
    waist = rng.uniform(0.0, 0.1)
    t = np.linspace(-np.pi / 2, np.pi / 2, 2000)
    # A stadium profile (straight side between two quarter-ellipse ends), pinched by `waist` at mid height.
    zs = np.where(t < 0, -half + 0.8 * radius * np.sin(t), half + 0.8 * radius * np.sin(t))
    rs = radius * np.cos(t)
    rs = rs * (1.0 - waist * np.exp(-(zs / half) ** 2))
    profile = np.concatenate([[[0.0, zs[0]]], np.stack([rs, zs], 1)[1:-1], [[0.0, zs[-1]]]])
    curves = []
    for k in range(pipes):
        phi = 2 * np.pi * k / pipes + rng.uniform(-0.4, 0.4)
        z = rng.uniform(-0.5, 0.5) * half
        out = np.array([np.cos(phi), np.sin(phi), 0.0])
        r_pipe = rng.uniform(0.06, 0.09)
        zz = np.linspace(z - r_pipe, z + r_pipe, 50)  # the widest the tank gets beside the pipe's end ring
        r_here = radius * (1.0 - waist * np.exp(-(zz / half) ** 2)).max()
        start = np.array([0.0, 0.0, z]) + (r_here + 0.02 * radius) * out
        reach = rng.uniform(0.3, 0.45)
        end = start + reach * out + np.array([0.0, 0.0, rng.uniform(0.3, 0.5)])
        curves.append((_bezier(start, start + reach * out, end), r_pipe))

    def build(step: float) -> trimesh.Trimesh:
        tank = _revolve(_resample(profile, step * _ALONG), step)
        return _concat([tank] + [_open_tube(curve, r, step) for curve, r in curves])

    return build(edge or _auto_edge(build, samples))


#: name -> (class, generator) of the families, added to `datasets.synthetic.SHAPES` on import.
FAMILIES = {
    "thin_cup": ("closed", thin_cup),
    "bracket": ("closed", bracket),
    "vessel": ("open", vessel),
    "bracket_hose": ("mixed", bracket_hose),
    "tank_pipes": ("mixed", tank_pipes),
}
synthetic.SHAPES.update(FAMILIES)
