"""Seeded, parameterised synthetic shapes, by class: closed, open and mixed surfaces.

Every generator takes a seed (for its random parameters) plus keyword parameters and returns a
`trimesh.Trimesh` in its own frame: roughly unit size (normalise with `datasets.normalize` before use) and
Y-up like the capture rig (the generators model Z-up and `datasets.mesh_parts.y_up` rotates their output). The same seed
and parameters always give the identical mesh (same vertex and face arrays).
`SHAPES` maps a name to (class, generator), with class one of "closed", "open", "mixed":

- closed: every connected component is watertight (no boundary edges);
- open: every connected component has boundary edges;
- mixed: disjoint components of both kinds (closed bodies with open attachments). Components never share
  vertices, so merging vertices by position keeps them apart and `datasets.meshes.classify` says "mixed".

The families of `datasets.families` (the test split's shapes smooth at the sampling scale: vessel, thin_cup,
bracket, bracket_hose, tank_pipes; 1.6-2.1M faces each) are in `SHAPES` too. The building blocks (grids,
tubes, booleans, the Y-up turn) are `datasets.mesh_parts`.

Shape letters: V vertices, F faces, U x W a parameter grid of vertices.
The CSG shapes (`genus2`, `csg`) use trimesh booleans with the `manifold3d` engine (harness extra).
"""
from __future__ import annotations

import logging
from typing import Callable

import numpy as np
import trimesh

from datasets.families import FAMILIES
from datasets.mesh_parts import boolean, concat, grid_faces, polar_patch, rotation, tube, y_up

log = logging.getLogger(__name__)

__all__ = ["SHAPES", "generate", "shapes_in_class"]


# ----------------------------------------------------------------------------------------------------------
# Closed shapes
# ----------------------------------------------------------------------------------------------------------

@y_up
def sphere(seed: int = 0, subdivisions: int = 3) -> trimesh.Trimesh:
    """A closed unit icosphere (20 * 4^subdivisions faces), stretched by the seed into an ellipsoid."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    m.apply_scale(1.0 + 0.15 * rng.uniform(-1, 1, 3))
    return m


@y_up
def torus(seed: int = 0, major: float = 0.7, minor: float = 0.25, sections: int = 48) -> trimesh.Trimesh:
    """A closed genus-1 torus (2 * sections * (sections // 2) faces), slightly squashed by the seed."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.torus(major_radius=major, minor_radius=minor, major_sections=sections,
                               minor_sections=sections // 2)
    m.apply_scale([1.0, 1.0, 1.0 + 0.1 * rng.uniform(-1, 1)])
    return m


@y_up
def genus2(seed: int = 0, major: float = 0.6, minor: float = 0.2, sections: int = 48) -> trimesh.Trimesh:
    """A closed genus-2 solid: the union of two overlapping tori (manifold3d boolean, ~4.5K faces)."""
    rng = np.random.default_rng(seed)
    minor = minor * (1.0 + 0.1 * rng.uniform(-1, 1))
    gap = major * (0.9 + 0.08 * rng.uniform(-1, 1))
    parts = []
    for sign in (-1.0, 1.0):
        t = trimesh.creation.torus(major_radius=major, minor_radius=minor, major_sections=sections,
                                   minor_sections=sections // 2)
        t.apply_translation([sign * gap, 0.0, 0.0])
        parts.append(t)
    return boolean("union", parts)


@y_up
def trefoil(seed: int = 0, radius: float = 0.13, samples: int = 160, sides: int = 14) -> trimesh.Trimesh:
    """A closed knotted tube around a trefoil knot (samples * sides * 2 faces), radius varied by the seed."""
    rng = np.random.default_rng(seed)
    t = 2 * np.pi * np.arange(samples) / samples
    curve = np.stack([np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)], 1) / 3.0
    curve[:, 2] *= 1.0 + 0.2 * rng.uniform(-1, 1)
    r = radius * (1.0 + 0.1 * rng.uniform(-1, 1)) * (1.0 + 0.15 * np.sin(3 * t + rng.uniform(0, 2 * np.pi)))
    return tube(curve, r, sides)


@y_up
def csg(seed: int = 0, sections: int = 32) -> trimesh.Trimesh:
    """A closed CSG solid: (box intersect sphere) minus three orthogonal cylinders (manifold3d booleans)."""
    rng = np.random.default_rng(seed)
    half = 0.75 * (1.0 + 0.06 * rng.uniform(-1, 1, 3))
    body = boolean("intersection", [trimesh.creation.box(extents=2 * half),
                                     trimesh.creation.icosphere(subdivisions=3, radius=1.0)])
    r = 0.35 * (1.0 + 0.1 * rng.uniform(-1, 1))
    holes = []
    for axis in np.eye(3):
        c = trimesh.creation.cylinder(radius=r, height=3.0, sections=sections)
        if axis[2] != 1.0:
            c.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], axis))
        holes.append(c)
    return boolean("difference", [body, boolean("union", holes)])


# ----------------------------------------------------------------------------------------------------------
# Open shapes
# ----------------------------------------------------------------------------------------------------------

@y_up
def disc(seed: int = 0, rings: int = 16, segments: int = 64) -> trimesh.Trimesh:
    """An open planar disc (z = 0) with a wobbly elliptic rim; segments * (2 rings - 1) faces."""
    rng = np.random.default_rng(seed)
    phi = 2 * np.pi * np.arange(segments) / segments
    k = int(rng.integers(3, 7))
    rim = 1.0 + 0.08 * np.sin(k * phi + rng.uniform(0, 2 * np.pi))
    aspect = 1.0 - 0.2 * rng.uniform(0, 1)
    s = (np.arange(1, rings + 1) / rings)[:, None]
    pts = np.stack([s * rim * np.cos(phi), s * rim * aspect * np.sin(phi), np.zeros((rings, segments))], -1)
    return polar_patch(pts, np.zeros(3))


@y_up
def bowl(seed: int = 0, rings: int = 20, segments: int = 64) -> trimesh.Trimesh:
    """An open bowl: a unit spherical cap around the -z pole, opening angle set by the seed (70-100 deg)."""
    rng = np.random.default_rng(seed)
    theta_max = np.radians(rng.uniform(70, 100))
    theta = (np.arange(1, rings + 1) / rings)[:, None] * theta_max
    phi = 2 * np.pi * np.arange(segments)[None] / segments
    squash = 1.0 + 0.15 * rng.uniform(-1, 1)
    pts = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi) * np.ones_like(phi),
                    -np.cos(theta) * squash * np.ones_like(phi)], -1)
    return polar_patch(pts, np.array([0.0, 0.0, -squash]))


@y_up
def open_cylinder(seed: int = 0, rows: int = 24, segments: int = 64) -> trimesh.Trimesh:
    """An open tube without caps (two boundary loops), with a seeded radius ripple along its height."""
    rng = np.random.default_rng(seed)
    h = np.linspace(-0.8, 0.8, rows)[:, None]
    phi = 2 * np.pi * np.arange(segments)[None] / segments
    r = 0.5 * (1.0 + 0.15 * np.sin(np.pi * h * rng.uniform(1, 3) + rng.uniform(0, 2 * np.pi)))
    pts = np.stack([r * np.cos(phi), r * np.sin(phi), h * np.ones_like(phi)], -1)
    return trimesh.Trimesh(pts.reshape(-1, 3), grid_faces(rows, segments, wrap_w=True), process=False)


@y_up
def wavy_sheet(seed: int = 0, n: int = 48, holes: int = 3) -> trimesh.Trimesh:
    """An open wavy cloth sheet over [-1, 1]^2 with `holes` round holes (about 2 n^2 faces)."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n), indexing="ij")
    kx, ky = rng.uniform(1.5, 3.0, 2)
    z = 0.15 * np.sin(kx * x + rng.uniform(0, 2 * np.pi)) * np.cos(ky * y + rng.uniform(0, 2 * np.pi))
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    faces = grid_faces(n, n)
    centers: list[np.ndarray] = []
    radii: list[float] = []
    while len(centers) < holes:  # well-separated holes strictly inside the sheet, so it stays connected
        c, r = rng.uniform(-0.55, 0.55, 2), rng.uniform(0.12, 0.2)
        if all(np.linalg.norm(c - c2) > r + r2 + 0.15 for c2, r2 in zip(centers, radii)):
            centers.append(c)
            radii.append(r)
    mid = verts[faces].mean(1)[:, :2]
    keep = np.ones(len(faces), bool)
    for c, r in zip(centers, radii):
        keep &= np.linalg.norm(mid - c, axis=1) > r
    m = trimesh.Trimesh(verts, faces[keep], process=False)
    m.remove_unreferenced_vertices()
    return m


@y_up
def mobius(seed: int = 0, segments: int = 120, across: int = 8) -> trimesh.Trimesh:
    """An open, non-orientable Mobius strip (one boundary loop), width set by the seed."""
    rng = np.random.default_rng(seed)
    width = 0.35 * (1.0 + 0.2 * rng.uniform(-1, 1))
    u = (2 * np.pi * np.arange(segments) / segments)[:, None]
    s = np.linspace(-width, width, across)[None]
    r = 1.0 + s * np.cos(u / 2)
    pts = np.stack([r * np.cos(u), r * np.sin(u), s * np.sin(u / 2)], -1)
    pts[..., 2] *= 1.0 + 0.3 * rng.uniform(-1, 1)
    return trimesh.Trimesh(pts.reshape(-1, 3), grid_faces(segments, across, wrap_u=True, flip_u=True),
                           process=False)


@y_up
def leaf(seed: int = 0, rings: int = 14, segments: int = 64) -> trimesh.Trimesh:
    """An open curved leaf with pointed tips along x in [-1, 1] (a lens-mapped disc, bent and folded)."""
    rng = np.random.default_rng(seed)
    phi = 2 * np.pi * np.arange(segments) / segments
    s = (np.arange(1, rings + 1) / rings)[:, None]
    x, y = s * np.cos(phi), s * np.sin(phi)
    width = 0.35 * (1.0 + 0.2 * rng.uniform(-1, 1))
    asym = 0.3 * rng.uniform(-1, 1)  # moves the widest point along the midrib (egg shape)
    xs = x + asym * (1 - x * x) * 0.5
    yy = width * y * np.sqrt(np.clip(1 - x * x, 0, None))  # half-width width * (1 - x^2): pointed tips
    bend, fold = rng.uniform(0.1, 0.3), rng.uniform(0.5, 1.5)
    zz = bend * xs * xs + fold * yy * yy
    pts = np.stack([xs, yy, zz], -1)
    return polar_patch(pts, np.array([asym * 0.5, 0.0, bend * 0.25 * asym * asym]))


# ----------------------------------------------------------------------------------------------------------
# Mixed shapes (closed bodies + open attachments, as disjoint components)
# ----------------------------------------------------------------------------------------------------------

@y_up
def plant(seed: int = 0, leaves: int = 4) -> trimesh.Trimesh:
    """Mixed: a closed stem and a closed bud (closed) with `leaves` open leaves around the stem."""
    rng = np.random.default_rng(seed)
    stem_r, height = 0.05, 1.6
    stem = trimesh.creation.cylinder(radius=stem_r, height=height, sections=16)
    bud = trimesh.creation.icosphere(subdivisions=2, radius=0.15)
    bud.apply_translation([0, 0, height / 2 + 0.12])
    parts = [stem, bud]
    for k in range(leaves):
        lf = leaf.__wrapped__(seed=int(rng.integers(1 << 31)), rings=8, segments=32)
        lf.apply_scale(0.3)
        lf.apply_translation([0.3 + stem_r + 0.02, 0, 0])  # base tip just off the stem surface
        lf.apply_transform(rotation([0, 1, 0], -np.radians(rng.uniform(20, 45))))  # tilt upwards
        lf.apply_transform(rotation([0, 0, 1], k * 2.39996 + rng.uniform(-0.3, 0.3)))  # golden angle
        lf.apply_translation([0, 0, -0.5 + 0.9 * (k + 0.5) / leaves])
        parts.append(lf)
    return concat(parts)


@y_up
def mushroom(seed: int = 0) -> trimesh.Trimesh:
    """Mixed: a closed stalk (capsule) under an open cap (a spherical cap shell, no underside)."""
    rng = np.random.default_rng(seed)
    stalk_r = 0.15 * (1.0 + 0.2 * rng.uniform(-1, 1))
    stalk = trimesh.creation.capsule(height=0.8, radius=stalk_r, count=[16, 16])
    cap = bowl.__wrapped__(seed=int(rng.integers(1 << 31)), rings=14, segments=48)
    cap.apply_transform(rotation([1, 0, 0], np.pi))  # opening downwards
    cap.apply_scale(0.6 * (1.0 + 0.15 * rng.uniform(-1, 1)))
    top = cap.vertices[:, 2].max()
    cap.apply_translation([0, 0, 0.4 + stalk_r + 0.15 - top])
    return concat([stalk, cap])


@y_up
def flag_box(seed: int = 0) -> trimesh.Trimesh:
    """Mixed: a closed box with a closed flagpole on top and an open, wavy flag on the pole."""
    rng = np.random.default_rng(seed)
    size = 0.8 * (1.0 + 0.1 * rng.uniform(-1, 1, 3))
    box = trimesh.creation.box(extents=size)
    pole_h, pole_r = 1.0, 0.03
    pole = trimesh.creation.cylinder(radius=pole_r, height=pole_h, sections=12)
    pole.apply_translation([0, 0, size[2] / 2 + pole_h / 2 - 0.02])  # sunk slightly into the box
    nu, nw = 24, 14
    u, w = np.meshgrid(np.linspace(0, 0.7, nu), np.linspace(0, 0.4, nw), indexing="ij")
    amp, k = rng.uniform(0.03, 0.08), rng.uniform(6, 12)
    flag_pts = np.stack([u + pole_r + 0.01, amp * np.sin(k * u) * u / 0.7, w], -1).reshape(-1, 3)
    flag = trimesh.Trimesh(flag_pts, grid_faces(nu, nw), process=False)
    flag.apply_translation([0, 0, size[2] / 2 + pole_h - 0.45])
    return concat([box, pole, flag])


@y_up
def lamp(seed: int = 0) -> trimesh.Trimesh:
    """Mixed: a closed base, pole and bulb under an open lampshade (a truncated cone without caps)."""
    rng = np.random.default_rng(seed)
    base = trimesh.creation.cylinder(radius=0.4, height=0.1, sections=32)
    base.apply_translation([0, 0, -0.75])
    pole = trimesh.creation.cylinder(radius=0.03, height=1.0, sections=12)
    pole.apply_translation([0, 0, -0.2])
    bulb = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    bulb.apply_translation([0, 0, 0.4])
    rows, segs = 10, 48
    h = np.linspace(0, 1, rows)[:, None]
    phi = 2 * np.pi * np.arange(segs)[None] / segs
    r_bot, r_top = 0.45 * (1 + 0.1 * rng.uniform(-1, 1)), 0.25 * (1 + 0.1 * rng.uniform(-1, 1))
    r = r_bot + (r_top - r_bot) * h
    pts = np.stack([r * np.cos(phi), r * np.sin(phi), (0.2 + 0.45 * h) * np.ones_like(phi)], -1)
    shade = trimesh.Trimesh(pts.reshape(-1, 3), grid_faces(rows, segs, wrap_w=True), process=False)
    return concat([base, pole, bulb, shade])


@y_up
def tablecloth(seed: int = 0, n: int = 40) -> trimesh.Trimesh:
    """Mixed: a closed table (top + 4 legs, boxes) under an open cloth draped over its top."""
    rng = np.random.default_rng(seed)
    half, top_z, thick = 0.6, 0.2, 0.06
    top = trimesh.creation.box(extents=[2 * half, 2 * half, thick])
    top.apply_translation([0, 0, top_z - thick / 2])
    parts = [top]
    for sx in (-1, 1):
        for sy in (-1, 1):
            legs = trimesh.creation.box(extents=[0.08, 0.08, 0.8])
            legs.apply_translation([sx * (half - 0.08), sy * (half - 0.08), top_z - thick - 0.4 + 0.01])
            parts.append(legs)
    ext = half * (1.3 + 0.1 * rng.uniform(-1, 1))
    x, y = np.meshgrid(np.linspace(-ext, ext, n), np.linspace(-ext, ext, n), indexing="ij")
    over = np.maximum(np.maximum(np.abs(x), np.abs(y)) - half, 0.0)
    ripple = 0.03 * np.sin(rng.uniform(8, 14) * np.arctan2(y, x)) * (over > 0)
    z = top_z + 0.01 - 1.5 * over + ripple * over / max(ext - half, 1e-9)
    cloth = trimesh.Trimesh(np.stack([x, y, z], -1).reshape(-1, 3), grid_faces(n, n), process=False)
    return concat(parts + [cloth])


#: name -> (class, generator); class is one of "closed", "open", "mixed".
SHAPES: dict[str, tuple[str, Callable[..., trimesh.Trimesh]]] = {
    "sphere": ("closed", sphere),
    "torus": ("closed", torus),
    "genus2": ("closed", genus2),
    "trefoil": ("closed", trefoil),
    "csg": ("closed", csg),
    "disc": ("open", disc),
    "bowl": ("open", bowl),
    "open_cylinder": ("open", open_cylinder),
    "wavy_sheet": ("open", wavy_sheet),
    "mobius": ("open", mobius),
    "leaf": ("open", leaf),
    "plant": ("mixed", plant),
    "mushroom": ("mixed", mushroom),
    "flag_box": ("mixed", flag_box),
    "lamp": ("mixed", lamp),
    "tablecloth": ("mixed", tablecloth),
}

CLASSES = ("closed", "open", "mixed")


def shapes_in_class(cls: str) -> list[str]:
    """Names of the synthetic shapes of class `cls` ("closed", "open" or "mixed"), in `SHAPES` order."""
    if cls not in CLASSES:
        raise ValueError(f"unknown shape class {cls!r}; choose from {', '.join(CLASSES)}")
    return [name for name, (c, _) in SHAPES.items() if c == cls]


def generate(name: str, seed: int = 0, **params) -> trimesh.Trimesh:
    """The synthetic shape `name` (see `SHAPES`) for `seed`; raises ValueError for an unknown name.

    Returns:
        A new `trimesh.Trimesh` (vertices (V, 3) float64, faces (F, 3) int64), identical for equal
        arguments.
    """
    if name not in SHAPES:
        raise ValueError(f"unknown synthetic shape {name!r}; choose from {', '.join(SHAPES)}")
    return SHAPES[name][1](seed=seed, **params)


# The smooth families of the test split (datasets/families.py), in the same registry.
SHAPES.update(FAMILIES)
