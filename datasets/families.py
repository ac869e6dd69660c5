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
for the same arguments, models Z-up and returns Y-up (`y_up`), and builds mixed shapes from components that
share no vertices. The CSG steps use manifold3d booleans (`datasets.mesh_parts.boolean`); the meshing at the
sampling scale is `datasets.fine_mesh`. `datasets.synthetic.SHAPES` (the one registry sweeps resolve names in)
holds `FAMILIES` too.

Shape letters: V vertices, F faces, K rings of S points (a swept surface), P profile points.
"""
from __future__ import annotations

import logging

import numpy as np
import trimesh

from datasets.fine_mesh import (GRID_STEP, RING_ALONG, SAMPLES, auto_edge, bezier, capped_tube, cylinder, drop_caps,
                                grid_cells, open_tube, resample, revolve, split_long_edges, tube_step)
from datasets.mesh_parts import boolean, concat, rotation, y_up

log = logging.getLogger(__name__)

__all__ = ["FAMILIES", "vessel", "thin_cup", "bracket", "bracket_hose", "tank_pipes"]


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
        plane = rotation(d, rng.uniform(0, 2 * np.pi))[:3, :3] @ side
        tangent_end = p2 - (0.5 * (p0 + p2) + bow)
        tangent_end /= np.linalg.norm(tangent_end)
        for sign in (-1.0, 1.0):
            angle = sign * np.radians(rng.uniform(25, 40))
            axis = np.cross(tangent_end, plane)
            child = rotation(axis / np.linalg.norm(axis), angle)[:3, :3] @ tangent_end
            todo.append((p2, child, length * rng.uniform(0.7, 0.85), r1 * 2 ** (-1 / 3), level + 1))
    return out


def _tree_clear(branches: list[dict]) -> bool:
    """Whether branches that do not meet at a junction stay apart (by their radii plus a margin)."""
    curves = [bezier(b["p0"], b["p1"], b["p2"], 60) for b in branches]
    for i in range(len(branches)):
        for j in range(i + 1, len(branches)):
            a, b = branches[i], branches[j]
            if np.allclose(a["p2"], b["p0"]) or np.allclose(b["p2"], a["p0"]) or np.allclose(a["p0"], b["p0"]):
                continue
            dist = np.linalg.norm(curves[i][:, None] - curves[j][None], axis=2).min()
            if dist < a["r0"] + b["r0"] + 0.1:
                return False
    return True


@y_up
def vessel(seed: int = 0, levels: int = 3, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Open: a branching tube tree (a vessel or pipe network) with cut ends, every edge below `edge`.

    A trunk bifurcates `levels - 1` times (7 branches, 4 leaf ends at the default 3 levels); each branch is a
    bowed, tapering tube, children thinner by Murray's law (radius / 2^(1/3)) at 25-40 degrees to their
    parent, junctions rounded by a sphere slightly wider than the parent's end. The solids are united (one
    manifold3d boolean), then the flat caps of the root and the leaf ends are removed, so each free end is a
    boundary loop (1 + 2^(levels - 1) loops). The seed draws the bows, angles and lengths (redrawn until
    non-adjacent branches stay apart). `edge` None: the sampling-scale default for `samples` input points
    (`auto_edge`).
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
            dense = bezier(b["p0"], b["p1"], b["p2"])
            curve = resample(dense, tube_step(dense, max(b["r0"], b["r1"]), step))  # as `capped_tube` does
            solids.append(capped_tube(dense, b["r0"], b["r1"], step))
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
        return split_long_edges(drop_caps(boolean("union", solids), ends), step)

    return build(edge or auto_edge(build, samples))


# ----------------------------------------------------------------------------------------------------------
# Closed: a thin-walled shell; a CAD-like part
# ----------------------------------------------------------------------------------------------------------

def _offset_2d(curve: np.ndarray, dist: float) -> np.ndarray:
    """(P, 2) points of a 2D polyline moved by `dist` along its left normals (vertex-averaged)."""
    t = np.gradient(curve, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return curve + dist * np.stack([-t[:, 1], t[:, 0]], 1)


@y_up
def thin_cup(seed: int = 0, wall: float = 0.01, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Closed: a cup whose wall and bottom are `wall` x its radius thick (1 %), with a rounded lip.

    A surface of revolution of one closed profile: the outer bottom, a rounded heel, a slightly flared and
    bulged outer wall up to the rim, a half-circle lip, and the inner wall and bottom offset inward by the wall
    thickness. The seed draws the radius, height, flare and bulge. Every edge is below `edge` (None: the
    sampling-scale default for `samples` input points, `auto_edge`).
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

    return build(edge or auto_edge(build, samples))


def _cup_profile_revolved(radius, height, flare, bulge, heel, thick, z0, edge) -> trimesh.Trimesh:
    """The surface of revolution of `thin_cup` for its drawn parameters."""
    # Outer profile from the bottom centre to the rim (counter-clockwise in (r, z): its left is inside).
    bottom = np.stack([np.linspace(0.0, radius - heel, 200), np.full(200, z0)], 1)
    a = np.linspace(-np.pi / 2, 0.0, 100)
    arc = np.stack([radius - heel + heel * np.cos(a), z0 + heel + heel * np.sin(a)], 1)
    s = np.linspace(0.0, 1.0, 600)
    h = heel + s * (height - heel)
    side = np.stack([radius * (1.0 + flare * s ** 2 + bulge * np.sin(np.pi * s)), z0 + h], 1)
    outer = resample(np.concatenate([bottom, arc[1:], side[1:]]), edge * GRID_STEP / 4)
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
    profile = np.concatenate([resample(profile[: len(outer) + len(lip) + 1], edge * RING_ALONG),
                              resample(profile[len(outer) + len(lip):], edge * RING_ALONG)[1:]])
    return revolve(profile, edge)


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
    body = grid_cells([((x0, y0, z0), (x1, y1, z1)), ((x0, y1, z0), (x1, y0 + depth, z1)),
                        ((x0, y0, z1), (x1, y1, z2))], edge)
    holes = []
    r_base, r_up = params["r_base"], params["r_up"]
    for fx in (0.2, 0.8):  # two bolt holes through the base, in front of the upright
        holes.append(cylinder([x0 + fx * length, y1 + 0.55 * (depth - thick), z0 + thick / 2],
                               [0, 0, 1], r_base, 3 * thick, edge))
    centers = [np.array([x0 + fx * length, y0 + thick / 2, z1 + 0.55 * rise]) for fx in (0.3, 0.7)]
    for c in centers:  # two larger holes through the upright
        holes.append(cylinder(c, [0, 1, 0], r_up, 3 * thick, edge))
    out = split_long_edges(boolean("difference", [body, boolean("union", holes)]), edge)
    return out, {"centers": centers, "radius": r_up}


@y_up
def bracket(seed: int = 0, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Closed: a CAD-like L-bracket with sharp edges and four cylindrical through-holes (genus 4).

    A base plate and an upright plate (boxes meshed as fine grids, united), two bolt holes through the base
    and two larger holes through the upright (manifold3d booleans with finely meshed cylinders). Flat faces
    stay flat and edges stay sharp; the grids make every edge shorter than `edge`, so the flat faces carry no
    large facets either. The seed draws the plate sizes, the thickness and the hole radii. `edge` None: the
    sampling-scale default for `samples` input points (`auto_edge`).
    """
    params = _bracket_params(np.random.default_rng(seed))

    def build(step: float) -> trimesh.Trimesh:
        return _bracket_raw(params, step)[0]

    return build(edge or auto_edge(build, samples))


# ----------------------------------------------------------------------------------------------------------
# Mixed: closed bodies with open tubes, as disjoint components
# ----------------------------------------------------------------------------------------------------------

@y_up
def bracket_hose(seed: int = 0, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Mixed: the closed `bracket` (same seed) with an open hose (a tube with cut ends, 60 % of the hole's
    radius) threaded through one of its upright holes, curving down in front and up behind; the hose never
    touches the bracket. `edge` None: the sampling-scale default for `samples` input points
    (`auto_edge`)."""
    rng = np.random.default_rng(seed)
    params = _bracket_params(rng)
    which = int(rng.integers(2))

    def build(step: float) -> trimesh.Trimesh:
        part, info = _bracket_raw(params, step)
        c, r = info["centers"][which], info["radius"]
        front, back = c + np.array([0.0, 0.45, -0.1]), c + np.array([0.0, -0.5, 0.25])
        curve = np.concatenate([bezier(front, c + [0.0, 0.2, 0.0], c, 200)[:-1],
                                bezier(c, c - [0.0, 0.2, 0.0], back, 200)])
        return concat([part, open_tube(curve, 0.6 * r, step)])

    return build(edge or auto_edge(build, samples))


@y_up
def tank_pipes(seed: int = 0, pipes: int = 2, samples: int = SAMPLES, edge: float | None = None) -> trimesh.Trimesh:
    """Mixed: a closed smooth tank (a surface of revolution with rounded ends) and `pipes` open pipes (tubes
    with cut ends) leaving its side, their inner ends 2 % of the tank's radius off its surface, bending up.
    The seed draws the tank's proportions and each pipe's height, direction and bend. `edge` None: the
    sampling-scale default for `samples` input points (`auto_edge`)."""
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
        curves.append((bezier(start, start + reach * out, end), r_pipe))

    def build(step: float) -> trimesh.Trimesh:
        tank = revolve(resample(profile, step * RING_ALONG), step)
        return concat([tank] + [open_tube(curve, r, step) for curve, r in curves])

    return build(edge or auto_edge(build, samples))


#: name -> (class, generator) of the families (in `datasets.synthetic.SHAPES`, the registry sweeps resolve names in).
FAMILIES = {
    "thin_cup": ("closed", thin_cup),
    "bracket": ("closed", bracket),
    "vessel": ("open", vessel),
    "bracket_hose": ("mixed", bracket_hose),
    "tank_pipes": ("mixed", tank_pipes),
}
