"""Distance grids from point clouds, shared by `sdf_mc` and `udf_mc`.

Shape letters: N points, K neighbours per query, M grid nodes in the band, (X, Y, Z) grid nodes per axis.

Only the nodes within a narrow band around the points are evaluated (voxelise the points, dilate by a few
nodes), so a 128^3 grid costs what its band costs, and marching cubes runs only on cubes whose 8 corners are
all in the band (so no surface appears far from the data, e.g. at the medial axis where the sign of a
nearest-sample distance flips).
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

log = logging.getLogger(__name__)


@dataclasses.dataclass
class BandGrid:
    """A regular grid over the points' padded bounding box, and the nodes of the band around the points.

    Attributes:
        origin: (3,) float64 position of node (0, 0, 0).
        voxel: edge length of a grid cell.
        shape: (X, Y, Z) node counts.
        band: (X, Y, Z) bool, True for nodes within `band_nodes` (Chebyshev) of a node holding a point.
        nodes: (M, 3) float64 positions of the band nodes, in the order of `np.nonzero(band)`.
    """

    origin: np.ndarray
    voxel: float
    shape: tuple[int, int, int]
    band: np.ndarray
    nodes: np.ndarray


#: Default cap on grid cells along the longest side: a dense float32 volume of 512^3 is 0.5 GiB, which two runs
#: on a shared 2-core, 23 GiB machine can hold; 1024^3 (8x) cannot (`marching_cubes` builds the dense volume).
MAX_RESOLUTION = 512


def choose_resolution(points: np.ndarray, spacing: float, resolution: int | None, voxel_spacings: float,
                      max_resolution: int = MAX_RESOLUTION) -> tuple[int, bool]:
    """(cells along the longest side of `points`' box, whether the cap bound it).

    `resolution` when given (an explicit grid); else the resolution whose voxel is `voxel_spacings` x
    `spacing` (the mean nearest-neighbour spacing), at most `max_resolution`.
    """
    if resolution is not None:
        return int(resolution), False
    if not voxel_spacings > 0 or not spacing > 0:
        raise ValueError(f"grid: voxel_spacings and the spacing must be positive, got {voxel_spacings}, {spacing}")
    extent = float((points.max(0) - points.min(0)).max())
    want = max(8, int(np.ceil(extent / (voxel_spacings * spacing))))
    return min(want, int(max_resolution)), want > int(max_resolution)


def band_grid(points: np.ndarray, resolution: int, band_nodes: int) -> BandGrid:
    """The band grid for `points` (N, 3) float64 with `resolution` cells along the longest box side."""
    from scipy import ndimage

    if resolution < 8:
        raise ValueError(f"grid resolution must be >= 8, got {resolution}")
    lo, hi = points.min(0), points.max(0)
    voxel = float((hi - lo).max()) / resolution
    if voxel <= 0:
        raise ValueError("points span no volume (all coincide)")
    pad = band_nodes + 2
    origin = lo - pad * voxel
    shape = tuple(int(s) for s in np.ceil((hi - lo) / voxel).astype(int) + 2 * pad + 1)
    idx = np.rint((points - origin) / voxel).astype(np.int64)
    band = np.zeros(shape, dtype=bool)
    band[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    band = ndimage.binary_dilation(band, structure=np.ones((3, 3, 3), bool), iterations=band_nodes)
    nodes = np.stack(np.nonzero(band), axis=1) * voxel + origin
    return BandGrid(origin, voxel, shape, band, nodes)


def imls(query: np.ndarray, points: np.ndarray, normals: np.ndarray, tree, k: int, sigma: float,
         align: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance to the local tangent planes of the k nearest oriented samples, Gaussian-weighted.

    f(x) = sum_i w_i <x - p_i, n_i> / sum_i w_i with w_i = exp(-(|x - p_i|^2 - |x - p_0|^2) / sigma^2) (shifted
    by the nearest neighbour's distance so far nodes do not underflow).

    Args:
        query: (M, 3) float64 positions.
        points, normals: (N, 3) float64 samples and unit normals; `tree` is a scipy cKDTree over `points`.
        k: neighbours per query (clipped to N).
        sigma: Gaussian width, in the points' units.
        align: flip each neighbour's normal to agree with the nearest neighbour's (for unoriented normals).

    Returns:
        f: (M,) float64 signed distance. nearest: (M,) float64 distance to the nearest sample.
        n: (M, 3) float64 the weighted mean normal (not normalised).
    """
    k = min(k, len(points))
    d, i = tree.query(query, k=k, workers=-1)
    if k == 1:
        d, i = d[:, None], i[:, None]
    nb = normals[i]                                   # (M, K, 3)
    if align:
        s = np.sign(np.einsum("mkc,mc->mk", nb, nb[:, 0]))
        s[s == 0] = 1
        nb = nb * s[..., None]
    w = np.exp(-(d * d - d[:, :1] ** 2) / (sigma * sigma))
    plane = np.einsum("mkc,mkc->mk", query[:, None, :] - points[i], nb)
    wsum = w.sum(1)
    f = (w * plane).sum(1) / wsum
    n = (w[..., None] * nb).sum(1) / wsum[:, None]
    return f, d[:, 0], n


def marching_cubes(grid: BandGrid, values: np.ndarray, level: float):
    """Marching cubes of `values` (M,) float64 on the band nodes at `level`; (verts (V, 3), faces (F, 3)).

    Nodes outside the band get +inf-like values and cubes that leave the band are skipped. Faces are wound so
    normals point towards increasing values. Returns empty arrays when the level is never crossed.
    """
    from scipy import ndimage
    from skimage import measure

    far = float(np.abs(values).max() + grid.voxel) if len(values) else 1.0
    vol = np.full(grid.shape, far, dtype=np.float32)
    vol[grid.band] = values
    # A cube is evaluated from its lowest corner; erode so all 8 corners are band nodes.
    mask = ndimage.binary_erosion(grid.band, structure=np.ones((3, 3, 3), bool), border_value=0)
    lo_v, hi_v = float(values.min()) if len(values) else 0.0, far
    if not lo_v < level < hi_v:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    try:
        verts, faces, _, _ = measure.marching_cubes(vol, level=level, spacing=(grid.voxel,) * 3, mask=mask,
                                                    gradient_direction="descent", allow_degenerate=False)
    except (ValueError, RuntimeError) as exc:
        log.info("marching cubes found no surface: %s", exc)
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return verts.astype(np.float64) + grid.origin, faces.astype(np.int64)
