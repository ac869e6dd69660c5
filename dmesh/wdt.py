"""Weighted Delaunay triangulation (WDT) and its dual, the power diagram.

Letters: N points, T finite tetrahedra, F triangulation faces.

Conventions
- Power distance of x to weighted point (p, w) is |x - p|^2 - w: a larger weight gives a larger cell.
- A point is *hidden* when it owns no power cell; it then appears in no tet.
- Exact duplicate positions are merged before insertion: the first index survives and later copies are
  hidden, whatever their weights (CGAL alone would keep an arbitrary copy).
- Faces are sorted vertex triples. Every face of the WDT is dual to a power-diagram edge: a segment
  between the orthocentres of its two tets, or, for a face on the convex hull, a ray from the orthocentre
  of its one tet along the face's outward unit normal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmesh import native


def regular_triangulation(points, weights, *, parallel: bool | None = None) -> np.ndarray:
    """Tetrahedra of the weighted Delaunay triangulation.

    Args:
        points: (N, 3) float array (NumPy or torch); converted to float64.
        weights: (N,) float array, or None for zeros (plain Delaunay).
        parallel: True for TBB-parallel insertion, False sequential, None automatic (parallel from
            `native.PARALLEL_THRESHOLD` points when TBB is compiled in and torch may use more than one
            thread, `torch.get_num_threads()`, the thread budget every kernel here follows). The tet set
            does not depend on it.

    Returns:
        tets: (T, 4) int32, input indices of each finite tetrahedron (positively oriented).

    Raises:
        ValueError: wrong shapes, NaN/inf, fewer than 4 distinct points, or all points coplanar.
    """
    return triangulate(points, weights, parallel=parallel).tets


@dataclass(frozen=True)
class Triangulation:
    """Result of `triangulate`.

    Attributes:
        tets: (T, 4) int32 input indices of each finite tet.
        neighbors: (T, 4) int32, the tet opposite vertex k of tet t, -1 where that side is the hull.
        duplicate_of: (N,) int32, the surviving index for exact duplicates, -1 otherwise.
        insert_seconds: time of CGAL's range insertion alone (inside the native call).
        total_seconds: time of the whole native call.
        parallel: whether TBB-parallel insertion ran.
    """

    tets: np.ndarray
    neighbors: np.ndarray
    duplicate_of: np.ndarray
    insert_seconds: float
    total_seconds: float
    parallel: bool


def triangulate(points, weights=None, *, parallel: bool | None = None) -> Triangulation:
    """Like `regular_triangulation`, also returning tet adjacency, duplicates and native timings."""
    if parallel is None:
        import torch

        if torch.get_num_threads() <= 1:  # a one-thread budget: TBB would start a thread per core
            parallel = False
    mode = -1 if parallel is None else int(bool(parallel))
    raw = native.regular_triangulation(points, weights, mode)
    s = raw.stats
    return Triangulation(raw.tets, raw.neighbors, raw.duplicate_of, float(s["insert_seconds"]),
                         float(s["total_seconds"]), bool(s["parallel"]))


@dataclass(frozen=True)
class Csr:
    """Compressed rows: row i is `indices[offsets[i]:offsets[i + 1]]` (ascending within a row).

    Attributes:
        offsets: (rows + 1,) int32.
        indices: (offsets[-1],) int32.
    """

    offsets: np.ndarray
    indices: np.ndarray

    def row(self, i: int) -> np.ndarray:
        return self.indices[self.offsets[i]:self.offsets[i + 1]]

    def lengths(self) -> np.ndarray:
        return np.diff(self.offsets)

    def rows(self) -> np.ndarray:
        """(nnz,) int64 row id of every entry of `indices`."""
        return np.repeat(np.arange(len(self.offsets) - 1), self.lengths())


class PowerDiagram:
    """The power diagram dual to a weighted Delaunay triangulation.

    Args:
        points: (N, 3) float array; weights: (N,) float array or None;
        tets: (T, 4) int array of the WDT of (points, weights), e.g. from `regular_triangulation`;
        neighbors: optional (T, 4) int adjacency from `triangulate` (computed from tets when omitted).

    Attributes:
        points: (N, 3) float64; weights: (N,) float64; tets: (T, 4) int32; neighbors: (T, 4) int32.
        orthocentres: (T, 3) float64, power-diagram vertex of each tet (equal power distance to its 4 points).
        faces: (F, 3) int32 sorted vertex triples of every WDT face.
        face_tets: (F, 2) int32, the face's two tets; the second is -1 for a hull face.
        is_hull: (F,) bool, faces on the convex hull (dual edge is a ray).
        ray_dirs: (F, 3) float64 unit outward normal for hull faces (the ray direction), zeros otherwise.
        tet_faces: (T, 4) int32, the face opposite vertex k of tet t.
        point_tets, point_faces, point_neighbors: `Csr` over the N points.
        hidden: (N,) bool, points that own no power cell (in no tet).
    """

    def __init__(self, points, weights, tets, neighbors=None):
        self.points = native.as_points(points)
        self.weights = native.as_weights(weights, len(self.points))
        self.tets = native.as_index(tets, 4, "tets")
        if neighbors is None:
            neighbors = native.tet_neighbors(self.tets)
        self.neighbors = native.as_index(neighbors, 4, "neighbors")
        raw = native.power_diagram(self.points, self.weights, self.tets, self.neighbors)
        self.orthocentres = raw.orthocentres
        self.faces = raw.faces
        self.face_tets = raw.face_tets
        self.ray_dirs = raw.hull_dirs
        self.is_hull = raw.face_tets[:, 1] < 0
        self.tet_faces = raw.tet_faces
        self.point_tets = Csr(*raw.point_tets)
        self.point_faces = Csr(*raw.point_faces)
        self.point_neighbors = Csr(*raw.point_neighbors)
        self.hidden = self.point_tets.lengths() == 0
        self._face_keys = None

    @classmethod
    def from_points(cls, points, weights=None, *, parallel: bool | None = None) -> "PowerDiagram":
        """Triangulates (points, weights) and builds the diagram in one call."""
        tri = triangulate(points, weights, parallel=parallel)
        return cls(points, weights, tri.tets, tri.neighbors)

    @property
    def num_points(self) -> int:
        return len(self.points)

    def dual_edges(self, ray_length: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Both ends of each face's dual edge: (F, 3) start, (F, 3) end (float64).

        For a hull face the end is `start + ray_length * ray_dir`, a point along the ray.
        """
        start = self.orthocentres[self.face_tets[:, 0]]
        end = np.where(self.is_hull[:, None], start + ray_length * self.ray_dirs,
                       self.orthocentres[np.maximum(self.face_tets[:, 1], 0)])
        return start, end

    def face_ids(self, faces) -> np.ndarray:
        """(C,) int64 index into `self.faces` of each row of `faces` ((C, 3) ints, any order), -1 if absent."""
        q = np.sort(np.asarray(faces, dtype=np.int64).reshape(-1, 3), axis=1)
        if self._face_keys is None:
            keys = face_keys(self.faces, self.num_points)
            order = np.argsort(keys)
            self._face_keys = (keys[order], order)
        keys, order = self._face_keys
        k = face_keys(q, self.num_points)
        pos = np.searchsorted(keys, k)
        pos = np.minimum(pos, len(keys) - 1)
        found = (len(keys) > 0) & (keys[pos] == k) if len(keys) else np.zeros(len(k), bool)
        return np.where(found, order[pos], -1)


def face_keys(faces: np.ndarray, n: int) -> np.ndarray:
    """(F,) int64 unique key of each sorted triple (F, 3) over n points (n < 2**21)."""
    if n >= 2**21:
        raise ValueError(f"face_keys supports fewer than 2**21 points, got {n}")
    f = np.asarray(faces, dtype=np.int64)
    return (f[:, 0] * n + f[:, 1]) * n + f[:, 2]
