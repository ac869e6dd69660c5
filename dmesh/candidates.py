"""Per-phase, only-growing sets: candidate faces and the neighbour cache.

Letters: N points, F faces, C candidate faces. Both structures belong to one optimisation phase over a
fixed number of points; start a new one when a phase starts or points are added.
"""
from __future__ import annotations

import numpy as np

from dmesh import native
from dmesh.wdt import Csr, face_keys


class NeighbourCache:
    """Every triangulation edge seen in the phase, in both directions, as per-point sorted lists.

    The bisector planes of a point's reduced power cell are taken from its cached neighbours, so planes of
    former neighbours stay available after the triangulation changes.

    Attributes:
        csr: `Csr` over N points (row i: ascending ids of every point ever adjacent to i).
    """

    def __init__(self, num_points: int):
        self.num_points = int(num_points)
        self.csr = Csr(np.zeros(self.num_points + 1, np.int32), np.zeros(0, np.int32))

    def update(self, point_neighbors: Csr) -> Csr:
        """Adds the current neighbour lists (a `PowerDiagram.point_neighbors`); returns the cache."""
        if len(point_neighbors.offsets) != self.num_points + 1:
            raise ValueError(f"neighbour lists cover {len(point_neighbors.offsets) - 1} points, "
                             f"the cache {self.num_points}")
        self.csr = Csr(*native.merge_csr(self.csr.offsets, self.csr.indices, point_neighbors.offsets,
                                         point_neighbors.indices))
        return self.csr


class CandidateFaces:
    """Sorted unique face triples, only growing during a phase.

    Attributes:
        keys: (C,) int64 sorted `wdt.face_keys` of the candidates.
    """

    def __init__(self, num_points: int):
        self.num_points = int(num_points)
        self.keys = np.zeros(0, np.int64)

    def add(self, faces: np.ndarray) -> None:
        """Adds faces (F, 3) ints (any vertex order; duplicates and degenerate triples are dropped)."""
        f = sort_triples(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2])]
        if len(f) == 0:
            return
        if f.min() < 0 or f.max() >= self.num_points:
            raise ValueError(f"candidate faces must index points in [0, {self.num_points})")
        self.add_sorted_keys(np.unique(face_keys(f, self.num_points)))

    def add_sorted_keys(self, keys: np.ndarray) -> None:
        """Adds faces given as sorted unique `face_keys` (the fast path for a WDT's faces)."""
        if len(self.keys) == 0:
            self.keys = keys.astype(np.int64, copy=True)
            return
        # One linear merge of the two sorted runs (native).
        self.keys = native.union_sorted_keys(self.keys, keys)

    def off_wdt(self, wdt_keys: np.ndarray, hidden: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((C', 3) int64 triples, (C',) int64 keys) of the candidates that are not WDT faces (`wdt_keys`,
        sorted) and have no `hidden` point ((N,) bool), in key order: the faces a pass scores beside the WDT's."""
        if len(hidden) != self.num_points:  # the keys decode with n = len(hidden)
            raise ValueError(f"hidden covers {len(hidden)} points, the candidates {self.num_points}")
        return native.off_wdt_candidates(self.keys, wdt_keys, hidden)

    @property
    def faces(self) -> np.ndarray:
        """(C, 3) int64 sorted triples."""
        return self.faces_of(self.keys)

    def faces_of(self, keys: np.ndarray) -> np.ndarray:
        """(K, 3) int64 triples of the given keys."""
        n = self.num_points
        return np.stack([keys // (n * n), (keys // n) % n, keys % n], axis=1)

    def __len__(self) -> int:
        return len(self.keys)


def sort_triples(f: np.ndarray) -> np.ndarray:
    """(M, 3) rows sorted ascending; min/max arithmetic, several times faster than np.sort(axis=1)."""
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    lo = np.minimum(np.minimum(a, b), c)
    hi = np.maximum(np.maximum(a, b), c)
    return np.stack([lo, a + b + c - lo - hi, hi], axis=1)


def knn_triples(points: np.ndarray, reals: np.ndarray | None, candidates: np.ndarray | None = None,
                k: int = 8, thresholds=(0.0, 0.2, 0.4, 0.6, 0.8)) -> np.ndarray:
    """Faces joining each point to every pair of its k nearest neighbours.

    For each threshold, only points with real value above it (and in `candidates`, e.g. points owning a
    power cell) take part, and neighbours are searched among those points.

    Args:
        points: (N, 3) float; reals: (N,) float in [0, 1] or None (all points, one pass);
        candidates: (N,) bool mask of eligible points or None.
    Returns:
        (M, 3) int64 sorted triples (with repeats; `CandidateFaces.add` makes them unique).
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    eligible = np.ones(len(points), bool) if candidates is None else np.asarray(candidates, bool)
    passes = [eligible] if reals is None else [eligible & (np.asarray(reals) > t) for t in thresholds]
    out = []
    seen = []  # passes with the same point set give the same triples (e.g. binary real values)
    pairs = np.array([(a, b) for a in range(k) for b in range(a + 1, k)], dtype=np.int64)
    for mask in passes:
        ids = np.flatnonzero(mask)
        if len(ids) < 3 or any(np.array_equal(ids, other) for other in seen):
            continue
        seen.append(ids)
        kk = min(k, len(ids) - 1)
        _, nn = cKDTree(points[ids]).query(points[ids], kk + 1)
        nn = ids[nn[:, 1:]]                                                  # drop self
        pp = pairs[(pairs < kk).all(1)]
        tri = np.concatenate([np.repeat(ids, len(pp))[:, None],
                              nn[:, pp].reshape(-1, 2)], axis=1)
        out.append(tri)
    if not out:
        return np.zeros((0, 3), np.int64)
    return sort_triples(np.concatenate(out).astype(np.int64))
