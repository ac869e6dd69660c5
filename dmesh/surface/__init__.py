"""The surface step: from the mesh faces of a DMesh's triangulation to a mesh that is closed and outward-facing
where the shape is closed, one consistently wound sheet per open part, and 2-manifold even once its vertices are
merged by position. Why each stage is there, and how to check the output: docs/surface.md.

The stages, in the order they run (`STAGES`; each has its section of `SurfaceConfig`, where it has settings):

1. vote: the tets are labelled inside or outside by walks to the hull (signed by the input normals when given),
   and regions that are open parts or pockets are set outside.
2. revote: large open pieces the vote left off the inside/outside boundary are set aside and the vote repeated.
3. pinches: tets are flipped until the inside/outside boundary is 2-manifold.
4. closed_part: the mesh faces between an inside and an outside tet, wound outward; the others are sheets.
5. lids: large holes of the closed part are closed by the inside tets' boundary across them.
6. fills: small holes of the closed part get a least-area fill that crosses nothing.
7. spans: closed-part faces far longer than the median edge are marked to be faired like lids.
8. reopen: lids, fills and spans over holes the input shows (no sample across them) are taken out again, so
   the shape's own boundary stays open (`SurfaceConfig.mode`: "auto"; "open" takes out all, "closed" none).
9. fins: sheet faces on an edge that two closed-part faces share are dropped (not those on its rim).
10. crumbs: stray sheet pieces (all tiny, floating apart, or a few faces beside a closed part) are dropped.
11. rim: the rim edges of the surface so far are counted (the point-cloud `fast` preset's shred test).
12. stacked: small sheet pieces lying on a larger surface (stray copies) are dropped.
13. wind_sheets: each sheet is wound consistently and turned to its input normals.
14. sheet_holes: small inner holes of the sheets are filled where the input sampled across them.
15. split_fans: each vertex where sheets meet gets one copy per fan of faces; on an edge that still has more
    than two faces, the two largest stay.
16. closed_crumbs: tiny closed pieces beside a larger one are dropped.
17. copies: the copies of a split vertex move apart into their own faces.
18. fair: the lids and spans are refined and faired; a lid piece that then crosses a face is dropped.

With `SurfaceConfig.clean` False only the orientation runs (stages 1-4 and 13); `SurfaceConfig.skip` leaves out
stages that are not required.

Entry points: `run` (a `Surface`: faces, vertices and counts) and `surface_mesh` (the same as a trimesh) of the mesh
faces of a `dmesh.wdt.PowerDiagram`; `surface_of_wdt_mesh` for a mesh whose faces are faces of the
triangulation; `orient_faces` winds any mesh. Which to call for which purpose: docs/surface.md.

Letters: N points, F triangulation faces, G input points, K output faces, V output vertices.
"""
from __future__ import annotations

import time
from typing import Callable, NamedTuple

import numpy as np

from dmesh.surface import debris, evidence, finish, holes, label, winding
from dmesh.surface.config import REQUIRED, SECTIONS, STAGE_NAMES, SurfaceConfig
from dmesh.surface.state import Surface, SurfaceState
from dmesh.surface.winding import orient_faces, orient_sheets


class Stage(NamedTuple):
    """One stage: its name, its function (state, its section of the config or None) -> state, the name of its
    `SurfaceConfig` section (None: no settings), whether it may not be skipped, and whether it is clean-up
    (left out with `SurfaceConfig.clean` False)."""

    name: str
    fn: Callable
    section: str | None
    required: bool
    cleanup: bool


def _stage(fn: Callable, cleanup: bool = True) -> Stage:
    """The stage of `fn`: a stage is named after its function, and its section (if any) after the stage; it is
    required when `dmesh.surface.config.REQUIRED` names it."""
    name = fn.__name__
    return Stage(name, fn, name if name in SECTIONS else None, name in REQUIRED, cleanup)


STAGES = (
    _stage(label.vote, cleanup=False),
    _stage(label.revote, cleanup=False),
    _stage(label.pinches, cleanup=False),
    _stage(label.closed_part, cleanup=False),
    _stage(holes.lids),
    _stage(holes.fills),
    _stage(debris.spans),
    _stage(evidence.reopen),
    _stage(debris.fins),
    _stage(debris.crumbs),
    _stage(debris.rim),
    _stage(debris.stacked),
    _stage(winding.wind_sheets, cleanup=False),
    _stage(holes.sheet_holes),
    _stage(finish.split_fans),
    _stage(debris.closed_crumbs),
    _stage(finish.copies),
    _stage(finish.fair),
)
if tuple(s.name for s in STAGES) != STAGE_NAMES:  # the config validates `skip` by the names alone
    raise ImportError("dmesh.surface.STAGES and dmesh.surface.config.STAGE_NAMES list different stages")


def run(pd, walls: np.ndarray, normals=None, samples: np.ndarray | None = None,
        config: SurfaceConfig | None = None) -> Surface:
    """The surface of the mesh faces `walls` of the triangulation `pd`: every stage of `STAGES` in order (module
    docstring), but those `config` leaves out.

    Args:
        pd: `dmesh.wdt.PowerDiagram`.
        walls: (F,) bool over `pd.faces`, the mesh faces (`dmesh.extract.mesh_faces`).
        normals: None, or (points (G, 3), normals (G, 3)) float oriented input samples in the frame of `pd`: they
            switch the vote from parity to winding and turn each sheet to face them.
        samples: (G, 3) float input points in the frame of `pd` (None: those of `normals`, if any): a sheet's hole
            is filled only where they sampled across it, and a stray copy of a sheet lies within a few of their
            spacings of the larger surface.
        config: `SurfaceConfig` (None: defaults).
    Returns:
        `Surface`; its info["stages"] holds, per stage run, its closed and sheet faces after it, the faces it
        added and dropped, its seconds and the counts it set.
    """
    cfg = config or SurfaceConfig()
    samples = normals[0] if samples is None and normals is not None else samples
    walls = np.asarray(walls, dtype=bool)
    points = pd.points
    if not walls.any():
        return Surface(np.zeros((0, 3), np.int64), np.arange(len(points)), 0,
                       {"closed_faces": 0, "sheet_faces": 0, "stages": {}}, np.zeros(0, bool), np.zeros(0, bool),
                       np.array(points, dtype=np.float64))
    if normals is not None:
        normals = (np.asarray(normals[0], dtype=np.float64), np.asarray(normals[1], dtype=np.float64))
    state = SurfaceState(pd, walls, normals, samples, cfg.seed, cfg.workers, cfg.mode, cfg.spacing_neighbours)
    records = {}
    for stage in STAGES:
        if stage.name not in cfg.skip and (cfg.clean or not stage.cleanup):
            state, records[stage.name] = _run_stage(stage, state, cfg)
    state.info["sheet_faces"] = int(len(state.sheet))
    state.info["stages"] = records
    return state.result()


def _run_stage(stage: Stage, state: SurfaceState, cfg: SurfaceConfig) -> tuple[SurfaceState, dict]:
    """`stage` run on `state`, and its record: faces after it, faces added and dropped, seconds, the counts it set."""
    before = dict(state.info)
    state.added = state.dropped = 0
    start = time.perf_counter()
    state = stage.fn(state, getattr(cfg, stage.section) if stage.section else None)
    seconds = time.perf_counter() - start
    counts = {k: v for k, v in state.info.items() if k not in before or before[k] != v}
    return state, {"closed": int(len(state.closed)), "sheets": int(len(state.sheet)), "added": int(state.added),
                   "dropped": int(state.dropped), "seconds": round(seconds, 6), **counts}


def surface_mesh(pd, walls: np.ndarray, normals=None, samples: np.ndarray | None = None,
                 config: SurfaceConfig | None = None):
    """`run` as a `trimesh.Trimesh` over the vertices its faces use (float64, the frame of `pd`), its info in
    `mesh.metadata["surface"]`."""
    from dmesh.extract import to_trimesh

    result = run(pd, walls, normals, samples, config)
    mesh = to_trimesh(result.positions, result.faces)
    mesh.metadata["surface"] = result.info
    return mesh


def surface_of_wdt_mesh(mesh, pd, normals=None, config: SurfaceConfig | None = None):
    """`surface_mesh` of a mesh whose faces are faces of `pd` and whose vertices are copies of some of `pd.points`
    (a mesh extracted from it and saved, say); ValueError when a vertex or face is not in `pd`."""
    from scipy.spatial import cKDTree

    v = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    walls = np.zeros(len(pd.faces), bool)
    if len(faces):
        distance, point = cKDTree(pd.points).query(v)
        far = distance > 1e-9 * (1.0 + np.abs(pd.points).max())  # copies, up to a round trip through a frame
        if far.any():
            raise ValueError(f"surface_of_wdt_mesh: {int(far.sum())} mesh vertices are not points of the "
                             f"triangulation")
        ids = pd.face_ids(point[faces])
        if (ids < 0).any():
            raise ValueError(f"surface_of_wdt_mesh: {int((ids < 0).sum())} mesh faces are not faces of the "
                             f"triangulation")
        walls[ids] = True
    return surface_mesh(pd, walls, normals, None, config)


__all__ = ["STAGES", "Stage", "SurfaceConfig", "Surface", "SurfaceState", "run", "surface_mesh",
           "surface_of_wdt_mesh", "orient_faces", "orient_sheets"]
