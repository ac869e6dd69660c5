"""Which faces of a DMesh make its mesh (paper section 4; DESIGN.md section 6).

Letters: N points, T tets, F WDT faces.

A face is on the mesh when it is in the WDT and its three points are real (real value above a threshold).
Modes, from upstream's to ours:

- "all": every such face (upstream's extraction for point clouds).
- "no_interior": also drops faces whose two tets are both all-real, i.e. faces inside a solid block of
  real tets (upstream's `remove_invisible`, used for multi-view).
- "sheet": a connected block of all-real tets ("cluster") is a thickened piece of surface: four surface
  samples that no imaginary point separates. Its interior faces are dropped as in "no_interior", and of its
  boundary, which is two sheets (one facing each side of the surface), only one is kept: the one with the
  larger area, which on a convex patch is the one closer to the surface. A side is told by the apex of the
  tet across each boundary face, against the cluster's normal (its points' direction of least variance).
  Upstream keeps both sheets, so its meshes have many non-manifold edges, and the inner sheet lies farther
  from the surface. Clusters are small (tens of tets at most), so one normal per cluster is enough. The three
  modes on a first DMesh (faces, non-manifold edges, CD, cluster sizes): `python -m studies extraction_modes`.

The output surface (`surface`, `extract(..., orient=True)`): the faces alone carry no orientation and, at a hole
or a fin, no clue whether they bound a solid. Both come from the tets instead (`dmesh.solid`): tets are labelled
inside or outside by walks to the hull, and the mesh faces between an inside and an outside tet form the closed
part, wound outward (open sheets that fooled the walks are set aside and the walks repeated:
`dmesh.solid.open_sheet_walls`); its small holes are filled over their own vertices, larger ones (parts of a
closed surface the input did not sample, e.g. what a scanner did not see) are closed by the inside tets' own
boundary across them, refined and faired (`dmesh.solid.large_lids`, `_fair_lids`); where the walls themselves span
such a stretch (faces of the triangulation between samples on either side of it, far longer than the surface's
median edge: `dmesh.repair.long_faces`), those faces are refined and faired the same way, their corners (samples)
held. Pinches are removed by relabelling tets (`dmesh.repair`). The remaining mesh faces (both sides outside: open
sheets; both inside: membranes inside a solid, e.g. where two sampled solids overlap) are kept where they do not
share an edge with the closed part, wound consistently and facing the input normals when given. Small sheet pieces
lying over a larger piece or the closed part (noise leaves them in the surface's band) are dropped
(`dmesh.repair.stacked_pieces`), and so are those floating apart from every larger piece, off the plane of the
surface nearest them and, beyond a crumb's size, farther from it than their own extent (triangles among stray
points: `dmesh.repair.floating_crumbs`), and a sheet's small inner
holes are filled (`dmesh.repair.sheet_holes`), not its rim, nor a hole beside a vertex off the surface its
neighbours form (an outlier the mesh reached: the fill would be a tent up to it). Where sheets meet at an edge
(three or more faces on it) or at a vertex (or a pinch the relabelling left), each gets its own copy of the
vertices, moved a little into its own faces (`dmesh.repair.split_fans`, `dmesh.repair.separate_copies`): the
surface no longer touches itself there, so a merge of vertices by position (STL, trimesh's default load) does not
join the copies again, and no face is dropped (keeping only the flattest pair of faces at such an edge was tried;
it cost accuracy on coarse meshes: docs/surface.md). Where the input samples a closed surface the result is watertight and
2-manifold; the figures per shape: `python -m eval.bench quality` (reports/bench_quality.md).

Multi-view filters (`filtered_faces`, `extract_filtered`; the interior rules of
`dmesh.recon.multiview_config.INTERIOR_MODES`): "apex" is "no_interior" (a face whose two tets have a real apex is
inside a solid block); "sheet" is "sheet"; "visible" keeps the faces that are the first hit of some pixel
ray of some camera when the mesh is drawn opaque (`visible_faces`, `hard_render`); "both" is "no_interior"
then "visible"; "none" keeps every real face. The depth filter (`depth_consistent_faces`), applied before
the visibility test, keeps the faces whose centroid lies on the captured depth of some view.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from dmesh.camera import focal_length, to_pixels, transform_points

log = logging.getLogger(__name__)

MODES = ("all", "no_interior", "sheet")


def mesh_faces(pd, real: np.ndarray, mode: str = "all") -> np.ndarray:
    """(F,) bool mask of the faces of `pd` (a `dmesh.wdt.PowerDiagram`) on the mesh.

    Args:
        pd: the power diagram (faces, face_tets, tets, points).
        real: (N,) bool, which points are real.
        mode: "all", "no_interior" or "sheet" (module docstring).
    """
    if mode not in MODES:
        raise ValueError(f"unknown extraction mode {mode!r}; choose from {', '.join(MODES)}")
    real = np.asarray(real, dtype=bool)
    on = real[pd.faces].all(1)
    if mode == "all" or not on.any():
        return on
    real_tet = np.r_[real[pd.tets].all(1), False]  # index -1 (hull side) reads False
    n_real = real_tet[pd.face_tets].sum(1)
    if mode == "no_interior":
        return on & (n_real < 2)
    keep = on & (n_real == 0)
    keep[_one_sheet(pd, real_tet[:-1], on & (n_real == 1), on & (n_real == 2))] = True
    return keep


def _one_sheet(pd, real_tet: np.ndarray, boundary: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """Ids of the boundary faces of each all-real-tet cluster on its larger-area side."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from dmesh.solid import face_areas

    T = len(pd.tets)
    a, b = pd.face_tets[interior, 0], pd.face_tets[interior, 1]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(T, T))
    n_comp, label = connected_components(graph, directed=False)

    ids = np.flatnonzero(boundary)
    ft = pd.face_tets[ids].astype(np.int64)
    first_real = real_tet[ft[:, 0]]
    inner = np.where(first_real, ft[:, 0], ft[:, 1])
    outer = np.where(first_real, ft[:, 1], ft[:, 0])
    cluster = label[inner]

    normal = _cluster_normals(pd.points, pd.tets, np.flatnonzero(real_tet), label, n_comp)
    faces = pd.faces[ids].astype(np.int64)
    p = pd.points
    centre = p[faces].mean(1)
    # The apex of the tet across: its vertex sum minus the face's (vertex ids are distinct). A hull face
    # has no tet across; its apex is taken on the negative side (its own first vertex stands in, a valid index).
    apex = pd.tets[np.maximum(outer, 0)].astype(np.int64).sum(1) - faces.sum(1)
    apex = np.where(outer >= 0, apex, faces[:, 0])
    side = np.einsum("ij,ij->i", p[apex] - centre, normal[cluster]) > 0
    side &= outer >= 0
    area = face_areas(p, faces)
    area_pos = np.bincount(cluster, area * side, n_comp)
    area_neg = np.bincount(cluster, area * ~side, n_comp)
    return ids[side == (area_pos >= area_neg)[cluster]]


def _cluster_normals(points: np.ndarray, tets: np.ndarray, real_tets: np.ndarray, label: np.ndarray,
                     n_comp: int) -> np.ndarray:
    """(n_comp, 3) unit direction of least variance of each cluster's tet vertices (zero for no tets)."""
    x = points[tets[real_tets].reshape(-1)]
    lab = np.repeat(label[real_tets], 4)
    count = np.maximum(np.bincount(lab, minlength=n_comp), 1)[:, None]
    mean = np.stack([np.bincount(lab, x[:, i], n_comp) for i in range(3)], 1) / count
    y = x - mean[lab]
    cov = np.empty((n_comp, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(lab, y[:, i] * y[:, j], n_comp)
    _, vectors = np.linalg.eigh(cov)  # ascending eigenvalues: column 0 is the least-variance direction
    return vectors[:, :, 0]


#: `refine`'s density control factor for the lids (`_fair_lids`): CGAL's default, sqrt(2), leaves lids across
#: a large hole with few new vertices there (their scale is the lid's own long edges), so the fair surface
#: stays close to the flat lid; `python -m studies lids` compares factors.
LID_DENSITY = 4.0


@dataclass(frozen=True)
class SurfaceConfig:
    """Settings of `surface` (counts and fractions; no lengths)."""

    directions: int = 9        # walks per tet in the inside/outside vote (dmesh.solid.walk_votes); odd: no ties
    max_open: float = 0.25     # a region of inside tets whose boundary is more than this fraction non-mesh
                               # faces (by area) is an open part, not a solid (dmesh.solid.drop_open_regions);
                               # a piece of walls whose rim spans more than this of its area is a sheet
                               # (dmesh.solid.open_sheet_walls)
    min_thickness: float = 0.5  # ... and one thinner than this many mean edge lengths is a pocket in a sheet
    max_hole: int = 64         # holes of the closed part with at most this many edges are filled; open pieces
                               # of more faces than this can be set aside (dmesh.solid.open_sheet_walls)
    max_crumb: int = 4         # a sheet part made only of pieces this small (edge-connected faces) is dropped,
                               # and so is a closed piece this small beside a larger one, and a sheet piece this
                               # small floating apart from the larger ones (dmesh.repair.floating_crumbs)
    max_debris: float = 1e-3   # ... and so is one of at most this fraction of all the faces beside a closed part
    stacked: float = 1.0       # ... and a sheet piece of a few faces lying within this many edge lengths (at most
                               # 3 input sample spacings each) of a larger piece (dmesh.repair.stacked_pieces); 0
                               # keeps them
    max_sheet_hole: int = 24   # holes inside a sheet with at most this many edges are filled, never its rim
                               # (dmesh.repair.sheet_holes); 0 leaves them open
    hole_gap: float = 8.0      # ... and only where the input sampled across them: the loop's centre within
                               # this many sample spacings of an input point (`surface`'s samples;
                               # dmesh.repair.sampled_loops), else it is a hole of the shape; 0: no test
    repair_rounds: int = 20    # rounds of pinch removal (dmesh.solid.repair_pinches)
    revote: bool = True        # vote again with the open sheets set aside (dmesh.solid.open_sheet_walls)
    clean: bool = True         # fill holes, drop fins and crumbs, split where sheets meet; False: orient only
    lids: bool = True          # ... and close holes of more than max_hole edges with the inside tets' boundary
                               # (dmesh.solid.large_lids), refined and faired (dmesh.native.refine_and_fair)
    spans: float = 6.0         # a closed-part face whose longest edge is over this many median edge lengths spans
                               # a stretch the input did not sample (dmesh.repair.long_faces): it is refined and
                               # faired like a lid, its corners held, and kept flat where its lid piece is
                               # dropped (0: none)
    fairing: int = 1           # the lids' fairing continuity (0 membrane, 1 thin plate, 2 curvature
                               # variation); -1: the lids stay faces of the triangulation, flat
    neighbours: int = 10       # input normals averaged per face to turn sheets (dmesh.repair.orient_sheets)
    turn_faces: bool = True    # a sheet face whose input normals clearly disagree turns on its own (False:
                               # whole sheets only, for vectors that are not normals, e.g. towards cameras)
    seed: int = 0              # rotation of the walk directions
    workers: int = 1           # threads of the k-d tree queries (input normals)

    def __post_init__(self):
        if int(self.directions) < 1:
            raise ValueError(f"SurfaceConfig.directions must be >= 1, got {self.directions}")
        if not 0.0 <= self.max_debris <= 1.0:
            raise ValueError(f"SurfaceConfig.max_debris must be in [0, 1], got {self.max_debris}")
        if not 0.0 <= self.max_open <= 1.0:
            raise ValueError(f"SurfaceConfig.max_open must be in [0, 1], got {self.max_open}")
        if not self.min_thickness >= 0.0:
            raise ValueError(f"SurfaceConfig.min_thickness must be >= 0, got {self.min_thickness}")
        if int(self.neighbours) < 1:
            raise ValueError(f"SurfaceConfig.neighbours must be >= 1, got {self.neighbours}")
        if not self.spans >= 0.0:
            raise ValueError(f"SurfaceConfig.spans must be >= 0, got {self.spans}")
        if not self.stacked >= 0.0:
            raise ValueError(f"SurfaceConfig.stacked must be >= 0, got {self.stacked}")
        if not self.hole_gap >= 0.0:
            raise ValueError(f"SurfaceConfig.hole_gap must be >= 0, got {self.hole_gap}")
        for name in ("max_hole", "max_crumb", "max_sheet_hole", "repair_rounds"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"SurfaceConfig.{name} must be >= 0, got {getattr(self, name)}")
        if int(self.fairing) not in (-1, 0, 1, 2):
            raise ValueError(f"SurfaceConfig.fairing must be -1, 0, 1 or 2, got {self.fairing}")


@dataclass
class Surface:
    """Output of `surface`.

    Attributes:
        faces: (K, 3) int64 oriented faces into `vertices`; the first `closed` rows are the closed part
            (outward), the rest the sheets.
        vertices: (V,) int64 the point of `pd.points` under each vertex (a point where sheets meet has one
            vertex per sheet: `dmesh.repair.split_fans`; `_surface_mesh` moves them apart).
        closed: number of closed-part rows.
        info: counts: inside_tets, regions_dropped, sheets_set_aside (walls left out of the second vote),
            tets_flipped, closed_faces, lids, lid_faces, span_faces, holes_filled, hole_faces, holes_left
            (holes_crossing of them left open because their fill crossed the surface), fins_dropped, crumbs_dropped,
            stacked_dropped, sheet_holes_filled, sheet_hole_faces, sheet_holes_unsampled (left open: the input did
            not sample across them), seams_cut,
            split_vertices, folds_dropped, sheet_faces; vote ("parity" or "winding"); rim_edges and rim_faces:
            `dmesh.repair.rim_edge_count` and the faces of the surface before its sheets' clean-up (stacked
            pieces, sheet holes), after fins and crumbs are dropped.
        lid: (K,) bool, the faces of the lids over large holes of the closed part (`SurfaceConfig.lids`).
        span: (K,) bool, the closed part's faces across a stretch the input did not sample
            (`SurfaceConfig.spans`), faired with the lids.
    """

    faces: np.ndarray
    vertices: np.ndarray
    closed: int
    info: dict = field(default_factory=dict)
    lid: np.ndarray | None = None
    span: np.ndarray | None = None


def surface(pd, walls: np.ndarray, normals=None, config: SurfaceConfig | None = None,
            samples: np.ndarray | None = None) -> Surface:
    """The oriented surface of the mesh faces `walls` of the WDT `pd` (module docstring).

    Args:
        pd: `dmesh.wdt.PowerDiagram`.
        walls: (F,) bool over `pd.faces`, the extracted mesh faces (`mesh_faces`).
        normals: None, or (points (G, 3), normals (G, 3)) float64 oriented input samples in the frame of
            `pd`: they switch the vote from parity to winding and turn each sheet to face them.
        config: `SurfaceConfig` (None: defaults).
        samples: (G, 3) float input points in the frame of `pd` (None: those of `normals`, if any): a hole
            inside a sheet is filled only where they sampled across it (`SurfaceConfig.hole_gap`), and a
            stray copy of a sheet lies within a few of their spacings of the larger surface
            (`dmesh.repair.stacked_pieces`).
    """
    from dmesh import repair, solid

    cfg = config or SurfaceConfig()
    samples = normals[0] if samples is None and normals is not None else samples
    walls = np.asarray(walls, dtype=bool)
    points = pd.points
    if not walls.any():
        return Surface(np.zeros((0, 3), np.int64), np.arange(len(points)), 0, {"closed_faces": 0, "sheet_faces": 0},
                       np.zeros(0, bool), np.zeros(0, bool))
    if normals is not None:
        normals = (np.asarray(normals[0], dtype=np.float64), np.asarray(normals[1], dtype=np.float64))
    sign = None if normals is None else solid.wall_signs(pd, walls, *normals, workers=cfg.workers)
    dirs = solid.directions(cfg.directions, cfg.seed)
    votes = solid.walk_votes(pd, walls, dirs, sign)
    inside, dropped = solid.drop_open_regions(pd, walls, votes > 0.5, cfg.max_open, cfg.min_thickness)
    aside = np.zeros(len(walls), bool)
    if cfg.revote:
        aside = solid.open_sheet_walls(pd, walls, inside, cfg.max_open, cfg.max_hole)
    if aside.any():  # sheets over a solid fooled the walks: vote again without them
        solids = walls & ~aside
        if solids.any():
            votes = solid.walk_votes(pd, solids, dirs, sign)
            inside, dropped = solid.drop_open_regions(pd, solids, votes > 0.5, cfg.max_open, cfg.min_thickness)
        else:  # only sheets: nothing is inside
            inside = np.zeros_like(inside)
    inside, flipped = solid.repair_pinches(pd, inside, cfg.repair_rounds)
    between = solid.boundary_mask(pd, inside)
    closed = solid.oriented_boundary(pd, inside, np.flatnonzero(walls & between))
    info = {"vote": "parity" if sign is None else "winding", "inside_tets": int(inside.sum()),
            "regions_dropped": dropped, "sheets_set_aside": int(aside.sum()), "tets_flipped": flipped,
            "closed_faces": int(len(closed))}
    sheet = pd.faces[walls & ~between].astype(np.int64)
    lid = np.zeros(len(closed), bool)
    if cfg.clean:
        if cfg.lids and len(closed):
            lids = solid.oriented_boundary(pd, inside, np.flatnonzero(between & ~walls))
            lids = lids[solid.large_lids(closed, lids, cfg.max_hole)]
            closed = np.concatenate([closed, lids])
            lid = np.r_[lid, np.ones(len(lids), bool)]
            info.update(lids=repair.edge_pieces(lids)[0], lid_faces=int(len(lids)))
        fill, filled, left, crossing = (repair.fill_holes(points, closed, cfg.max_hole, others=sheet) if len(closed)
                                        else (closed, 0, 0, 0))
        closed = np.concatenate([closed, fill])
        lid = np.r_[lid, np.zeros(len(fill), bool)]
        span = (repair.long_faces(points, closed, cfg.spans) & ~lid if cfg.spans > 0 and len(closed)
                else np.zeros(len(closed), bool))
        info.update(span_faces=int(span.sum()))
        fins = repair.faces_on_edges(sheet, closed)
        sheet = sheet[~fins]
        crumbs = repair.crumbs(sheet, cfg.max_crumb) | repair.floating_crumbs(points, sheet, cfg.max_crumb, closed)
        if len(closed) and len(sheet) <= cfg.max_debris * (len(sheet) + len(closed)):
            crumbs[:] = True  # a few stray faces beside a closed surface: the input sampled a closed one
        sheet = sheet[~crumbs]
        # Before the sheet clean-up below hides it: how ragged the surface came out (the point-cloud `fast`
        # preset's test for a mesh in shreds, `redo_fragmented`, reads it).
        info.update(rim_edges=repair.rim_edge_count(np.concatenate([closed, sheet])),
                    rim_faces=int(len(closed) + len(sheet)))
        stacked = repair.stacked_pieces(points, sheet, closed, cfg.stacked, samples=samples)
        # A piece hanging on an edge of a sheet keeps that edge apart (`split_fans` below); without the piece,
        # the two faces left would join there, and where the sheet folds over itself they would join in a
        # twist (a seam: no winding agrees across it). The winding is found with those edges still apart, and
        # those that come out as seams stay apart, as they were.
        hung = repair.nonmanifold_edges(sheet)
        hung = hung[repair.edges_in(hung, repair.edge_table(sheet[stacked])[0])]
        sheet = sheet[~stacked]
        info.update(holes_filled=filled, hole_faces=int(len(fill)), holes_left=left, holes_crossing=crossing,
                    fins_dropped=int(fins.sum()), crumbs_dropped=int(crumbs.sum()), stacked_dropped=int(stacked.sum()))
        if len(hung):
            apart, source = repair.split_fans(sheet, len(points), hung)
            sheet = source[repair.orient_sheets(points[source], apart, normals, k=cfg.neighbours,
                                                workers=cfg.workers, turn_faces=cfg.turn_faces)]
        else:
            sheet = repair.orient_sheets(points, sheet, normals, k=cfg.neighbours, workers=cfg.workers,
                                         turn_faces=cfg.turn_faces)
    else:
        sheet = repair.orient_sheets(points, sheet, normals, k=cfg.neighbours, workers=cfg.workers,
                                     turn_faces=cfg.turn_faces)
    if cfg.clean:  # after the winding: a hole's loop runs against its faces
        loops = repair.sheet_holes(points, sheet, cfg.max_sheet_hole, avoid=closed)
        if loops and samples is not None and cfg.hole_gap > 0:
            # A hole the input did not sample across is one of the shape (a coarse mesh rims it with a few
            # long edges), not one the extraction left in a sampled surface.
            sampled = repair.sampled_loops(points, loops, samples, cfg.hole_gap)
            info.update(sheet_holes_unsampled=int((~sampled).sum()))
            loops = [loop for loop, keep in zip(loops, sampled) if keep]
        # (off the closed part's edges: a sheet fill along one would give it a third face there)
        fill, filled = (repair.fill_holes(points, sheet, cfg.max_sheet_hole, others=closed, loops=loops,
                                          off_others=True)[:2] if loops else (np.zeros((0, 3), np.int64), 0))
        sheet = np.concatenate([sheet, fill])
        seams = repair.seam_edges(sheet)
        cut = seams[repair.edges_in(seams, hung)]
        info.update(sheet_holes_filled=filled, sheet_hole_faces=int(len(fill)), seams_cut=int(len(cut)))
    faces = np.concatenate([closed, sheet])
    lid = np.r_[lid, np.zeros(len(sheet), bool)]
    span = np.r_[span, np.zeros(len(faces) - len(span), bool)] if cfg.clean else np.zeros(len(faces), bool)
    vertices = np.arange(len(points))
    if cfg.clean:  # sheets meeting at an edge or a vertex get their own copies of its vertices, which
        # `_surface_mesh` moves apart: copies left on one point would make the branch or pinch again in any
        # file of the mesh read back with its vertices merged by position (STL, trimesh's default load).
        faces, vertices = repair.split_fans(faces, len(points), cut)
        keep = repair.drop_crowding(points[vertices], faces)
        folds = int((~keep).sum())
        kept = np.flatnonzero(keep)
        crumbs = repair.closed_crumbs(faces[kept], cfg.max_crumb)
        keep[kept[crumbs]] = False
        faces, lid, span = faces[keep], lid[keep], span[keep]
        closed_count = int(keep[:len(closed)].sum())
        info.update(split_vertices=int(len(vertices) - len(points)), folds_dropped=folds,
                    closed_crumbs_dropped=int(crumbs.sum()))
    else:
        closed_count = len(closed)
    info["sheet_faces"] = int(len(faces) - closed_count)
    log.debug("surface: %s", info)
    return Surface(faces, vertices, closed_count, info, lid, span)


def extract(dm, threshold: float = 0.5, pd=None, mode: str = "all", orient: bool = False, normals=None,
            config: SurfaceConfig | None = None, samples=None):
    """The mesh of a DMesh as a `trimesh.Trimesh` over the used points (float64, the DMesh's frame).

    Args:
        dm: `dmesh.model.DMesh`; threshold: real value above which a point is real.
        pd: its `PowerDiagram` (None: a fresh one).
        mode: which real faces (`mesh_faces`).
        orient: False: those faces as sorted triples; True: the oriented, closed `surface` of them, whose
            `info` goes to `mesh.metadata["surface"]`.
        normals, config, samples: as in `surface` (used with `orient`).
    """
    pd = pd if pd is not None else dm.power_diagram()
    walls = mesh_faces(pd, dm.reals.detach().numpy() > threshold, mode)
    if not orient:
        return to_trimesh(pd.points, pd.faces[walls])
    return _surface_mesh(pd, walls, normals, config, samples)


def surface_of_mesh(mesh, pd, normals=None, config: SurfaceConfig | None = None):
    """`surface` of a mesh whose faces are faces of `pd` and whose vertices are copies of some of
    `pd.points` (e.g. a filtered extraction); returns a new `trimesh.Trimesh` over the used points of `pd`
    (info in `metadata["surface"]`). Raises ValueError when a vertex or face is not in `pd`."""
    from scipy.spatial import cKDTree

    v = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    walls = np.zeros(len(pd.faces), bool)
    if len(faces):
        distance, point = cKDTree(pd.points).query(v)
        far = distance > 1e-9 * (1.0 + np.abs(pd.points).max())  # copies, up to a round trip through a frame
        if far.any():
            raise ValueError(f"surface_of_mesh: {int(far.sum())} mesh vertices are not points of the triangulation")
        ids = pd.face_ids(point[faces])
        if (ids < 0).any():
            raise ValueError(f"surface_of_mesh: {int((ids < 0).sum())} mesh faces are not faces of the "
                             f"triangulation")
        walls[ids] = True
    return _surface_mesh(pd, walls, normals, config)


def _surface_mesh(pd, walls: np.ndarray, normals, config: SurfaceConfig | None, samples=None):
    """`surface` of `walls` as a `trimesh.Trimesh` over the used points of `pd` (info in metadata["surface"])."""
    from dmesh.repair import separate_copies

    cfg = config or SurfaceConfig()
    result = surface(pd, walls, normals, cfg, samples)
    vertices = separate_copies(pd.points[result.vertices], result.faces, result.vertices)
    faces = result.faces
    if result.lid is not None and (result.lid.any() or result.span.any()) and cfg.fairing >= 0:
        vertices, faces = _fair_lids(vertices, faces, result, cfg.fairing)
    mesh = to_trimesh(vertices, faces)
    mesh.metadata["surface"] = result.info
    return mesh


def _fair_lids(vertices: np.ndarray, faces: np.ndarray, result: Surface, continuity: int):
    """The closed part's lids and spans refined and faired (`dmesh.native.refine_and_fair`; a span's corners
    held); their info in `result.info` (lid_vertices_added, lids_faired, lids_dropped: pieces of lids and spans).

    A faired lid can fold where its rim is jagged, or pass through a nearby part of the surface (a leaf over
    the hole). Folds are smoothed away (`dmesh.repair.untangle`). A lid piece with a face still crossing another
    is dropped, and the others are faired again without it: it closes a hole in a tight spot, next to other
    parts of the surface, where the inside/outside labelling is least sure (docs/surface.md: such lids kept flat made
    mixed shapes worse), so its hole stays open as it did before lids; a dropped piece's spans stay, flat. A
    closed part CGAL cannot take as a 2-manifold drops all its lids, with a warning."""
    from dmesh import native, repair

    closed, sheets = faces[:result.closed], faces[result.closed:]
    span = (np.zeros(result.closed, bool) if result.span is None else result.span[:result.closed])
    lid = result.lid[:result.closed] | span
    count, piece = repair.edge_pieces(closed[lid])
    piece_of = np.full(len(closed), -1)
    piece_of[lid] = piece
    dropped = np.zeros(count, bool)
    # A span's vertices are input samples: only the vertices refinement adds move (a lid's own may move too).
    hold = np.ones(len(vertices), bool)
    hold[closed[lid & ~span]] = False
    v, f, solved = vertices, closed, True
    while not dropped.all():
        patch = lid & ~dropped[np.maximum(piece_of, 0)]
        try:
            v, f, refined, solved = native.refine_and_fair(vertices, closed, patch, LID_DENSITY, continuity, hold)
        except ValueError as err:
            log.warning("surface: the lids over %d large holes are dropped (%s)", count, err)
            dropped[:] = True
            break
        v, hit = repair.untangle(v, np.concatenate([f, sheets]), np.r_[refined, np.zeros(len(sheets), bool)],
                                 hold=hold)
        if not hit.any():
            break
        # Refinement keeps each face's index for one of its parts, so a refined piece holding an input face
        # is that face's lid piece.
        ids = np.flatnonzero(refined)
        _, refined_piece = repair.edge_pieces(f[ids])
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
    keep[:len(closed)] = ~(lid & ~span & dropped[np.maximum(piece_of, 0)])  # a span stays, flat
    result.info.update(lid_vertices_added=int(len(v) - len(vertices)), lids_faired=bool(solved and not dropped.all()),
                       lids_dropped=int(dropped.sum()))
    if dropped.any():
        result.info["lid_faces"] = (result.info.get("lid_faces", 0)
                                    - int((lid & ~span & dropped[np.maximum(piece_of, 0)]).sum()))
    return v, np.concatenate([f[keep], sheets])


def towards_cameras(points: np.ndarray, eyes: np.ndarray, limit: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """`surface`'s `normals` from multi-view input: (points, unit vectors from each point towards its eye).

    A captured surface faces the camera that saw it, so the direction to that camera has the sign of the
    surface's outward normal wherever the surface is closed (and of its seen side on an open sheet).

    Args:
        points: (G, 3) float64 captured surface points (lifted depth pixels); eyes: (G, 3) float64 centre of
            the camera that saw each; both in the frame of the triangulation.
        limit: at most this many points are kept, evenly strided (deterministic).
    """
    points = np.asarray(points, dtype=np.float64)
    eyes = np.asarray(eyes, dtype=np.float64)
    if len(points) > limit:
        pick = np.linspace(0, len(points) - 1, limit).astype(np.int64)
        points, eyes = points[pick], eyes[pick]
    d = eyes - points
    return points, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


# ------------------------------------------------------------------------------------------------- multi-view

#: The `mesh_faces` mode behind each multi-view interior rule (the others keep every real face).
_INTERIOR_MODE = {"apex": "no_interior", "both": "no_interior", "sheet": "sheet"}


def depth_consistent_faces(points: np.ndarray, faces: np.ndarray, world_to_camera: np.ndarray, fov_y_degrees: float,
                           depth: np.ndarray, mask: np.ndarray, tolerance: float) -> np.ndarray:
    """(F,) bool: faces whose centroid lies on the captured surface in at least one view.

    A centroid is on the surface in view k when it projects to a mask pixel whose captured depth (-z_cam)
    is within `tolerance` of its own. Interior faces lie behind the captured surface in every view that
    sees their pixel, and floating ones project onto background: both fail. Unlike the "visible" test,
    which trusts the mesh's own renders (an interior face seen through a pixel-wide crack survives it),
    this one checks the input.

    Args:
        points: (N, 3) and faces (F, 3) in the frame of `world_to_camera` (V, 4, 4); depth, mask: (V, H, H)
        captured images in the same frame's units; tolerance: distance along the view axis.
    """
    c = points[faces].mean(1)
    h = depth.shape[1]
    focal = focal_length(fov_y_degrees, h)
    ok = np.zeros(len(faces), bool)
    for k in range(len(world_to_camera)):
        x = transform_points(c, world_to_camera[k])
        z = -x[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = (np.floor(a) for a in to_pixels(x[:, 0], x[:, 1], z, focal, h, h))
        idx = np.flatnonzero((z > 0) & (u >= 0) & (u < h) & (v >= 0) & (v < h))
        iu, iv = u[idx].astype(np.int64), v[idx].astype(np.int64)
        hit = mask[k, iv, iu] & (np.abs(z[idx] - depth[k, iv, iu]) <= tolerance)
        ok[idx[hit]] = True
    return ok


def hard_render(points: np.ndarray, pd, keep: np.ndarray, cameras):
    """Renders the faces of `keep` ((F,) bool over `pd.faces`) opaque, all others transparent, with the
    tetrahedral walk (exact depth order; `dmesh.render.tet_render`).

    A pixel's compositing stops at its first opaque face, so its fragment list holds exactly that face.

    Returns:
        seen: (F,) bool, faces of `keep` that are the first hit of some pixel ray of some camera;
        diffuse, depth, alpha: (V, R, R) float32 images (as `dmesh.render.tet_render`).
    """
    import torch

    from dmesh import native

    opacity = keep.astype(np.float32)
    seen = np.zeros(len(pd.faces), bool)
    threads = max(1, torch.get_num_threads())
    images = []
    for cam in cameras:
        raw = native.tet_render_forward(points, pd.tets, pd.faces, pd.face_tets, opacity, *cam.native_args(),
                                        0.5, 1e-4, threads)
        seen[np.asarray(raw.frag_face, dtype=np.int64)] = True
        images.append((raw.diffuse, raw.depth, raw.alpha))
    diffuse, depth, alpha = (np.stack(x) for x in zip(*images))
    return seen & keep, diffuse, depth, alpha


def visible_faces(points: np.ndarray, pd, keep: np.ndarray, cameras) -> np.ndarray:
    """(F,) bool over `pd.faces`: faces of `keep` ((F,) bool) that are the first hit of some pixel ray of
    some camera (see `hard_render`)."""
    if not keep.any():
        return np.zeros(len(pd.faces), bool)
    return hard_render(points, pd, keep, cameras)[0]


def filtered_faces(dm, threshold: float, pd, interior: str, cameras, render: bool = False, consistent=None):
    """The multi-view extraction's faces (module docstring): (F,) bool over `pd.faces`, the count removed
    from the real faces, and (with `render`, or when the visibility test ran) the hard render's (diffuse,
    depth, alpha) from `cameras`, else None.

    Args:
        dm: `DMesh`; threshold: real value above which a point is real; pd: its `PowerDiagram`; interior: one
            of `dmesh.recon.multiview_config.INTERIOR_MODES`; cameras: the `dmesh.camera.Camera`s of the visibility
            test and the render; consistent: None, or a function (points, faces) -> (F,) bool of faces to
            keep (`depth_consistent_faces`), applied before the visibility test.
    """
    real = dm.reals.detach().numpy() > threshold
    keep = real[pd.faces].all(1)
    before = int(keep.sum())
    if interior in _INTERIOR_MODE:
        keep = mesh_faces(pd, real, _INTERIOR_MODE[interior])
    if consistent is not None and keep.any():
        idx = np.flatnonzero(keep)
        keep[idx] = consistent(dm.points.detach().double().numpy(), pd.faces[idx].astype(np.int64))
    images = None
    if interior in ("visible", "both") or render:
        if cameras is None:
            raise ValueError("the visibility test and the hard render need the cameras")
        seen, *images = hard_render(dm.points.detach().numpy(), pd, keep, cameras)
        if interior in ("visible", "both"):
            keep = seen
    return keep, before - int(keep.sum()), images


def extract_filtered(dm, threshold: float = 0.5, pd=None, interior: str = "apex", cameras=None, consistent=None):
    """The multi-view extraction of a DMesh (`filtered_faces`), as a trimesh over the used points (DMesh frame).

    Args:
        dm: `DMesh`; threshold, interior, cameras, consistent: as in `filtered_faces`; pd: its
            `PowerDiagram` (None: a fresh one).
    Returns:
        (trimesh.Trimesh, number of real faces removed).
    """
    pd = pd if pd is not None else dm.power_diagram()
    keep, removed, _ = filtered_faces(dm, threshold, pd, interior, cameras, consistent=consistent)
    return to_trimesh(dm.points.detach().double().numpy(), pd.faces[keep]), removed


def to_trimesh(points: np.ndarray, faces: np.ndarray):
    """A `trimesh.Trimesh` of `faces` ((F, 3) indices) over the points they use (float64, unprocessed)."""
    import trimesh

    mesh = trimesh.Trimesh(np.array(points, dtype=np.float64), np.asarray(faces, dtype=np.int64).reshape(-1, 3),
                           process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


def orient_faces(mesh) -> None:
    """Consistent winding per connected component (in place), outward for closed components
    (`dmesh.repair.orient_faces`; kept here for the extraction's callers)."""
    from dmesh.repair import orient_faces as _orient

    _orient(mesh)


__all__ = ["MODES", "mesh_faces", "SurfaceConfig", "Surface", "surface", "extract", "surface_of_mesh", "to_trimesh",
           "depth_consistent_faces", "hard_render", "visible_faces", "filtered_faces", "extract_filtered",
           "towards_cameras", "orient_faces"]
