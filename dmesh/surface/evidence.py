"""Where the input shows surface: the question every hole-closing stage asks before it closes a hole.

A hole of the extracted surface is either one the extraction left in a sampled surface (a gap between faces
where input points lie across it) or one of the shape itself (the cut end of a tube, the rim of a sheet, a gap
a scanner did not see). Only the input can tell them apart, so the stages that close holes (lids, fills,
spans) keep a patch only where input samples lie across it, in `SurfaceConfig.mode` "auto".

Lengths here are local: each sample's spacing is the mean distance to its `k` nearest neighbours
(`SurfaceConfig.spacing_neighbours`), so a scan twice as dense in one place as in another is judged alike in
both. The other stages that measure in sample spacings (`stacked`, `sheet_holes`) take the same local spacing
at the place tested (`spacing_at`), scaled by one factor so that its median over the samples is the samples'
median nearest-neighbour distance: on uniform samples it is the global spacing those stages were set in. A
point of a patch is *seen* when its nearest sample lies within `ratio` of that sample's spacings. A patch is
*unseen*, a hole the input shows, when more than `share` of its area is not seen and it is larger than a disc
of `ratio` spacings (a smaller hole is below what the sampling can show either way, and closing it keeps a
closed shape closed).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Evidence:
    """The input samples as a k-d tree with each sample's local spacing (`of_samples`)."""

    tree: object
    spacing: np.ndarray  # (G,) float64, each sample's mean distance to its k nearest neighbours
    workers: int = 1
    unit: float = 1.0    # median nearest-neighbour distance / median spacing (`spacing_at`'s scale)

    @classmethod
    def of_samples(cls, samples: np.ndarray, k: int, workers: int = 1) -> "Evidence":
        """The evidence of (G, 3) samples with spacings over `k` neighbours (at most G - 1)."""
        from scipy.spatial import cKDTree

        samples = np.asarray(samples, dtype=np.float64)
        tree = cKDTree(samples)
        k = max(1, min(int(k), len(samples) - 1))
        distance, _ = tree.query(samples, k + 1, workers=workers)
        spacing = distance[:, 1:].mean(1)
        unit = float(np.median(distance[:, 1]) / max(float(np.median(spacing)), 1e-300))
        return cls(tree, spacing, workers, unit)

    def spacing_at(self, points: np.ndarray) -> np.ndarray:
        """(P,) the local sample spacing at each point: its nearest sample's spacing x `unit`, in units of the
        samples' median nearest-neighbour distance."""
        _, nearest = self.tree.query(np.asarray(points, dtype=np.float64).reshape(-1, 3), workers=self.workers)
        return self.spacing[nearest] * self.unit

    def ratio(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P,) distance of each point to its nearest sample in that sample's spacings, and (P,) that
        spacing."""
        distance, nearest = self.tree.query(np.asarray(points, dtype=np.float64), workers=self.workers)
        spacing = self.spacing[nearest]
        return distance / np.maximum(spacing, 1e-300), spacing

    def unseen_pieces(self, vertices: np.ndarray, faces: np.ndarray, piece: np.ndarray, count: int,
                      ratio: float, share: float) -> np.ndarray:
        """(count,) bool: which pieces of `faces` (labels `piece`) the input shows to be holes: more than
        `share` of their area unseen (centroids over `ratio` spacings from every sample) and their area over
        that of a disc of `ratio` mean spacings."""
        if not len(faces):
            return np.zeros(count, bool)
        tri = vertices[faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        r, spacing = self.ratio(tri.mean(1))
        total = np.bincount(piece, area, count)
        unseen = np.bincount(piece, area * (r > ratio), count)
        mean_sq = np.bincount(piece, area * spacing ** 2, count) / np.maximum(total, 1e-300)
        return (unseen > share * total) & (total > np.pi * ratio ** 2 * mean_sq)


def reopen(state, cfg):
    """The pieces of lids, fills and spans that the input shows to be holes of the shape (`Evidence`) are taken
    out again, so those holes stay open: in mode "auto" with input samples; in mode "open", every piece; in
    mode "closed", none."""
    from dmesh.surface.topology import edge_pieces

    patch = state.lid | state.fill | state.span
    if state.mode == "closed" or not patch.any() or (state.mode == "auto" and state.samples is None):
        return state
    ids = np.flatnonzero(patch)
    count, piece = edge_pieces(state.closed[ids])
    if state.mode == "open":
        out = np.ones(count, bool)
    else:
        out = state.evidence().unseen_pieces(state.coords(), state.closed[ids], piece, count, cfg.ratio, cfg.share)
    keep = np.ones(len(state.closed) + len(state.sheet), bool)
    keep[ids[out[piece]]] = False
    state.info.update(holes_reopened=int(out.sum()), reopened_faces=int((~keep).sum()))
    state.keep_faces(keep)
    return state
