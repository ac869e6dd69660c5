"""What the surface step's stages pass on (`SurfaceState`) and what the step returns (`Surface`).

Letters: N points of the triangulation, F its faces, T its tets, G input points, K closed-part faces, S sheet
faces, V vertices of the output.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _no_faces() -> np.ndarray:
    return np.zeros((0, 3), np.int64)


def _no_edges() -> np.ndarray:
    return np.zeros((0, 2), np.int64)


@dataclass
class SurfaceState:
    """The surface being made, handed from stage to stage (each changes it in place and returns it).

    Attributes:
        pd: the `dmesh.wdt.PowerDiagram`; walls: (F,) bool over `pd.faces`, the mesh faces given.
        normals: None, or (points (G, 3), normals (G, 3)) float64 oriented input samples in the frame of `pd`.
        samples: None, or (G, 3) float input points in that frame.
        seed, workers, mode, spacing_neighbours: `SurfaceConfig`'s run-wide fields.
        inside: (T,) bool tet labels (the vote, revote and pinches stages); between: (F,) bool, the faces
            between an inside and an outside tet (closed_part); dirs, sign, vote: the vote's walk directions,
            wall signs and settings, which the revote repeats.
        closed: (K, 3) int64 closed-part faces, wound outward; sheet: (S, 3) int64 the other faces. Both index
            `vertices`.
        lid, span: (K,) bool, the closed-part faces of lids (lids stage) and of spans (spans stage), which the
            fair stage refines and fairs; a face that refinement adds counts as lid. fill: (K,) bool, the
            closed-part faces of fills (fills stage).
        vertices: (V,) int64 the point of `pd.points` under each vertex (one per point until split_fans gives a
            point one vertex per fan; -1 for a vertex the fair stage added).
        positions: None (each vertex at its point), or (V, 3) float64 where each vertex lies (copies, fair).
        hung: (H, 2) int64 sheet edges a dropped stacked piece hung on (kept apart by split_fans).
        info: the counts the stages set (`Surface.info`).
        added, dropped: faces the current stage added and dropped (the runner records and resets them).
    """

    pd: object
    walls: np.ndarray
    normals: tuple | None = None
    samples: np.ndarray | None = None
    seed: int = 0
    workers: int = 1
    mode: str = "auto"
    spacing_neighbours: int = 8
    inside: np.ndarray | None = None
    between: np.ndarray | None = None
    dirs: np.ndarray | None = None
    sign: np.ndarray | None = None
    vote: object = None
    closed: np.ndarray = field(default_factory=_no_faces)
    sheet: np.ndarray = field(default_factory=_no_faces)
    lid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    span: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    fill: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    vertices: np.ndarray | None = None
    positions: np.ndarray | None = None
    hung: np.ndarray = field(default_factory=_no_edges)
    info: dict = field(default_factory=dict)
    added: int = 0
    dropped: int = 0
    _evidence: object = None

    def __post_init__(self):
        if self.vertices is None:
            self.vertices = np.arange(len(self.pd.points))

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float64 the triangulation's points."""
        return self.pd.points

    def evidence(self):
        """The `dmesh.surface.evidence.Evidence` of `samples` (local sample spacings), built once per run and
        shared by the stages that measure in sample spacings; None without samples."""
        if self._evidence is None and self.samples is not None:
            from dmesh.surface.evidence import Evidence

            self._evidence = Evidence.of_samples(self.samples, self.spacing_neighbours, self.workers)
        return self._evidence

    def coords(self) -> np.ndarray:
        """(V, 3) float64 where the vertices lie."""
        return self.positions if self.positions is not None else self.points[self.vertices]

    def faces(self) -> np.ndarray:
        """(K + S, 3) int64 the closed part, then the sheets."""
        return np.concatenate([self.closed, self.sheet])

    def set_faces(self, closed: np.ndarray, sheet: np.ndarray) -> None:
        """The closed part and the sheets as they start (closed_part): no lid, no span."""
        self.closed, self.sheet = closed, sheet
        self.lid, self.span, self.fill = (np.zeros(len(closed), bool) for _ in range(3))

    def add_closed(self, faces: np.ndarray, lid: bool = False, fill: bool = False) -> None:
        """`faces` appended to the closed part (as lids, as fills, or as neither lid, fill nor span)."""
        self.closed = np.concatenate([self.closed, faces])
        self.lid = np.r_[self.lid, np.full(len(faces), lid)]
        self.fill = np.r_[self.fill, np.full(len(faces), fill)]
        self.span = np.r_[self.span, np.zeros(len(faces), bool)]
        self.added += len(faces)

    def add_sheet(self, faces: np.ndarray) -> None:
        """`faces` appended to the sheets."""
        self.sheet = np.concatenate([self.sheet, faces])
        self.added += len(faces)

    def keep_sheet(self, keep: np.ndarray) -> None:
        """Only the sheet faces of `keep` ((S,) bool) stay."""
        self.sheet = self.sheet[keep]
        self.dropped += int((~keep).sum())

    def keep_faces(self, keep: np.ndarray) -> None:
        """Only the faces of `keep` ((K + S,) bool over `faces()`) stay."""
        k = keep[:len(self.closed)]
        self.closed, self.lid, self.span, self.fill = self.closed[k], self.lid[k], self.span[k], self.fill[k]
        self.sheet = self.sheet[keep[len(k):]]
        self.dropped += int((~keep).sum())

    def result(self) -> "Surface":
        """The `Surface` of the state."""
        faces = self.faces()
        extra = np.zeros(len(self.sheet), bool)
        return Surface(faces, self.vertices, len(self.closed), self.info, np.r_[self.lid, extra],
                       np.r_[self.span, extra], np.array(self.coords(), dtype=np.float64))


@dataclass
class Surface:
    """Output of `dmesh.surface.run`.

    Attributes:
        faces: (K, 3) int64 oriented faces into `vertices`; the first `closed` rows are the closed part
            (outward), the rest the sheets.
        vertices: (V,) int64 the point of `pd.points` under each vertex (a point where sheets meet has one vertex
            per sheet: split_fans; -1: a vertex the fair stage added).
        closed: number of closed-part rows.
        info: counts, flat (the names docs/surface.md gives each stage: inside_tets, regions_dropped,
            sheets_set_aside, tets_flipped, closed_faces, lids, lid_faces, span_faces, holes_filled, hole_faces,
            holes_left, holes_crossing, tet_fills, tet_fill_faces, faired_fills, faired_fill_faces, fins_dropped,
            crumbs_dropped, rim_edges, rim_faces, stacked_dropped, sheet_holes_filled, sheet_hole_faces, sheet_holes_unsampled, seams_cut, split_vertices, folds_dropped,
            closed_crumbs_dropped, lid_vertices_added, lids_faired, lids_dropped, sheet_faces; vote: "parity" or
            "winding"), and info["stages"]: per stage run, in order, its closed and sheet faces after it, the
            faces it added and dropped, its seconds and the counts it set.
        lid, span: (K,) bool, the faces of lids and spans (`SurfaceState`).
        positions: (V, 3) float64 where each vertex lies (copies moved apart, lids faired); None: at its point.
    """

    faces: np.ndarray
    vertices: np.ndarray
    closed: int
    info: dict = field(default_factory=dict)
    lid: np.ndarray | None = None
    span: np.ndarray | None = None
    positions: np.ndarray | None = None


__all__ = ["SurfaceState", "Surface"]
