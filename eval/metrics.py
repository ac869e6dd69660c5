"""Reconstruction metrics: Chamfer distances, F-score, normal consistency and orientation, RE/FP, mesh topology
and statistics.

Shape letters: N surface samples per mesh, V vertices, F faces, E unique edges.

Frames and units. Every distance metric is computed after mapping **both** meshes by the GT's transform
(`datasets.normalize`: GT vertex mean to the origin, GT max vertex norm 1; DESIGN.md 8.1), so distances are in
units of the GT's radius. The NDC-compatible metrics (`cd_l2_ndc`, `f_score`, `normal_consistency`) then
rescale so the GT's bounding-box diagonal is 1, as NDC and VoroMesh do. Tables multiply `cd_l1` and `cd_p2s`
by 1e3 ("x1e-3").

Sampling. `sample(vertices, faces, n, seed, side)` draws n area-uniform surface points. Each side ("gt",
"pred") draws from its own stream, a child of `seed` (`metric_rng`) that no input draws from: inputs are
sampled from `numpy.random.default_rng(seed)` itself, so a metric sample never repeats an input point's draw
(which would favour methods that keep the input points as vertices; reports/bench_metric_coupling.md). The
two sides differ, so a mesh compared with itself shows the
sampling floor of the sample-based CD (about 5-7e-3 at 1e5 samples on the shared meshes; it shrinks as
1/sqrt(n)), while the point-to-surface CD of a mesh against itself is exactly 0.

Definitions (P: samples of the prediction, G: samples of the GT; d(x, S): Euclidean distance from x to its
nearest point of the sample set S; dist(x, M): exact distance from x to the triangles of mesh M):
- `cd_l1` = mean_{g in G} d(g, P) + mean_{p in P} d(p, G)  (unsquared, summed; DMesh's convention);
- `cd_p2s` = mean_{g in G} dist(g, pred) + mean_{p in P} dist(p, gt)  (no sampling floor; the primary figure);
- `cd_l2_ndc` = mean d(g, P)^2 + mean d(p, G)^2 in the NDC frame (NDC's `cd2`);
- `f_score` = 2 PR / (P + R) with precision P = fraction of p with d(p, G) < 0.003 and recall R = fraction of g
  with d(g, P) < 0.003, in the NDC frame;
- `normal_consistency` = (mean_g |n_g . n_NN(g)| + mean_p |n_p . n_NN(p)|) / 2 with face normals of the samples
  (absolute value: orientation ignored);
- `normal_consistency_oriented` = (mean_g n_g . n_pred(c_g) + mean_p n_p . n_gt(c_p)) / 2, signed, with c_x the
  exact closest point of x on the other mesh (the `cd_p2s` queries); `oriented_fraction` = area-weighted share
  of predicted faces whose normal has a positive dot product with the normal of the GT face closest to the
  face's centroid; `oriented_fraction_any_side` = the same share once each open piece of the prediction (faces
  joined through two-face edges, with a one-face edge somewhere) takes whichever side agrees more. The side of
  an open sheet is a convention that some inputs do not carry: two-sided shading, depth and masks look the
  same from either side, so from multi-view images only the consistency of a sheet's winding and the outward
  side of closed pieces can be asked for. All three compare against the GT oriented outward
  (`datasets.meshes.orient_outward`) and are NaN for a GT that cannot be oriented (`gt_orientable` False).

Topology (`topology`): boundary edges and loops, non-manifold edges and vertices, components, watertightness,
winding consistency, Euler characteristic and genus, for the prediction and (prefixed `gt_`) the GT.
"""
from __future__ import annotations

import logging
import math

import numpy as np

log = logging.getLogger(__name__)

#: F-score distance threshold in the NDC frame (bounding-box diagonal 1).
F_SCORE_THRESHOLD = 0.003


# --------------------------------------------------------------------------------------------- helpers

def _check_mesh(mesh, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of a trimesh-like mesh; ValueError for NaN or bad faces."""
    if mesh is None:
        raise ValueError(f"{what} mesh is None")
    v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if not np.isfinite(v).all():
        raise ValueError(f"{what} mesh has NaN or inf vertices")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"{what} mesh has face indices outside its {len(v)} vertices")
    return v, f


def _area(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(F,) float64 triangle areas."""
    t = v[f]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


#: The metric streams' first spawn-key word ("metric" in ASCII), then one word per side: children of the
#: seed that no input stream is (`datasets.sampling` and `datasets.corrupt` draw from `default_rng(seed)` and
#: `default_rng([seed, stage])`, whose spawn keys are empty).
METRIC_STREAM = 0x6D6574726963
SIDES = {"gt": 0, "pred": 1}


def metric_rng(seed: int, side: str) -> np.random.Generator:
    """The Generator of one side's metric samples for `seed`: independent of every input draw of any seed."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(METRIC_STREAM, SIDES[side])))


def sample(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int,
           side: str = "gt") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n area-uniform surface samples from the metric stream of `side` ("gt" or "pred") for `seed`.

    Args:
        vertices: (V, 3) float64; faces: (F, 3) int64 with positive total area.
        n: number of samples; seed: the metric seed; side: whose samples (`metric_rng`).

    Returns:
        points: (n, 3) float64. face: (n,) int64 the face each sample lies on. normals: (n, 3) float64 unit
        face normals (zero for degenerate faces).
    """
    rng = metric_rng(seed, side)
    area = _area(vertices, faces)
    face = rng.choice(len(faces), size=n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1                      # fold the unit square onto the triangle
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    t = vertices[faces[face]]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])
    nrm = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    return pts, face, nrm


def gt_transform(gt) -> tuple[np.ndarray, float]:
    """(center (3,) float64, scale) of the GT frame: x -> (x - center) * scale gives vertex mean 0, max norm 1.

    Uses `datasets.normalize` when importable (the same definition, kept in one place), else computes it.
    """
    v, _ = _check_mesh(gt, "GT")
    if len(v) == 0:
        raise ValueError("GT mesh has no vertices")
    try:
        from datasets.normalize import normalize
    except ImportError:
        c = v.mean(0)
        r = float(np.linalg.norm(v - c, axis=1).max())
        if r == 0:
            raise ValueError("GT mesh vertices all coincide") from None
        return c, 1.0 / r
    _, t = normalize(gt, radius=1.0)
    return np.asarray(t.center, dtype=np.float64), float(t.scale)


def _prepare(pred, gt):
    """Both meshes as (vertices, faces) in the GT frame, and whether the prediction has any area."""
    gv, gf = _check_mesh(gt, "GT")
    pv, pf = _check_mesh(pred, "predicted")
    if len(gf) == 0 or _area(gv, gf).sum() <= 0:
        raise ValueError("GT mesh has no faces with positive area")
    c, s = gt_transform(gt)
    gv, pv = (gv - c) * s, (pv - c) * s
    empty = len(pf) == 0 or not _area(pv, pf).sum() > 0
    return (pv, pf), (gv, gf), empty


# ----------------------------------------------------------------------------------------- distances

def chamfer_l1_samples(pred, gt, n: int = 100_000, seed: int = 0) -> float:
    """Sample-based Chamfer L1: mean d(g, P) + mean d(p, G) with n area-uniform samples each way.

    Args:
        pred, gt: trimesh.Trimesh (vertices (V, 3), faces (F, 3)); both mapped into the GT frame first.
        n: samples per mesh; seed: the metric seed (each side its own stream, `metric_rng`).

    Returns:
        float, in GT-radius units (unsquared distances, summed over both directions); inf for an empty
        prediction. Has a sampling floor > 0 even for identical meshes (see module docstring).
    """
    (pv, pf), (gv, gf), empty = _prepare(pred, gt)
    if empty:
        return math.inf
    from scipy.spatial import cKDTree

    G, _, _ = sample(gv, gf, n, seed, "gt")
    P, _, _ = sample(pv, pf, n, seed, "pred")
    d_gp, _ = cKDTree(P).query(G, workers=-1)
    d_pg, _ = cKDTree(G).query(P, workers=-1)
    return float(d_gp.mean() + d_pg.mean())


def chamfer_l1_p2s(pred, gt, n: int = 100_000, seed: int = 0, backend: str = "auto") -> float:
    """Point-to-surface Chamfer L1: mean dist(g, pred) + mean dist(p, gt), exact distances to the triangles.

    Args:
        pred, gt: trimesh.Trimesh; both mapped into the GT frame first.
        n: samples per mesh; seed: as in `chamfer_l1_samples` (the same sample sets).
        backend: closest-point backend (`eval.closest_point.make_index`): "auto" (open3d if importable),
            "open3d" (Embree, float32: exact up to ~1e-7) or "numpy" (exact float64, ~10x slower).

    Returns:
        float in GT-radius units; 0 for identical meshes (no sampling floor; ~1e-8 with open3d's float32);
        inf for an empty prediction.
    """
    (pv, pf), (gv, gf), empty = _prepare(pred, gt)
    if empty:
        return math.inf
    from eval.closest_point import make_index

    G, _, _ = sample(gv, gf, n, seed, "gt")
    P, _, _ = sample(pv, pf, n, seed, "pred")
    d_g, _, _ = make_index(pv, pf, backend).query(G)
    d_p, _, _ = make_index(gv, gf, backend).query(P)
    return float(d_g.mean() + d_p.mean())


def _ndc_scale(gv: np.ndarray) -> float:
    """Factor from the GT frame to the NDC frame (GT bounding-box diagonal 1); gv: (V, 3) GT-frame vertices."""
    return 1.0 / float(np.linalg.norm(gv.max(0) - gv.min(0)))


def _sample_metrics(pv, pf, gv, gf, n, seed, threshold):
    """All sample-based figures from one pair of sample sets (see `compute_metrics` for the keys)."""
    from scipy.spatial import cKDTree

    G, _, nG = sample(gv, gf, n, seed, "gt")
    P, _, nP = sample(pv, pf, n, seed, "pred")
    d_gp, i_gp = cKDTree(P).query(G, workers=-1)
    d_pg, i_pg = cKDTree(G).query(P, workers=-1)
    k = _ndc_scale(gv)
    precision = float((d_pg * k < threshold).mean())
    recall = float((d_gp * k < threshold).mean())
    out = {
        "cd_l1": float(d_gp.mean() + d_pg.mean()),
        "cd_l1_gt_to_pred": float(d_gp.mean()),
        "cd_l1_pred_to_gt": float(d_pg.mean()),
        "cd_l2_ndc": float(((d_gp * k) ** 2).mean() + ((d_pg * k) ** 2).mean()),
        "precision": precision,
        "recall": recall,
        "f_score": 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall),
        "normal_consistency": 0.5 * float(np.abs(np.einsum("nc,nc->n", nG, nP[i_gp])).mean()
                                          + np.abs(np.einsum("nc,nc->n", nP, nG[i_pg])).mean()),
    }
    return out, (G, nG), (P, nP)


def cd_l2_ndc(pred, gt, n: int = 100_000, seed: int = 0) -> float:
    """NDC's `cd2`: mean d(g, P)^2 + mean d(p, G)^2 in the NDC frame (GT bbox diagonal 1); inf if pred is empty.

    Args: as `chamfer_l1_samples` (same samples). Returns: float, squared NDC units.
    """
    (pv, pf), (gv, gf), empty = _prepare(pred, gt)
    return math.inf if empty else _sample_metrics(pv, pf, gv, gf, n, seed, F_SCORE_THRESHOLD)[0]["cd_l2_ndc"]


def f_score(pred, gt, threshold: float = F_SCORE_THRESHOLD, n: int = 100_000, seed: int = 0) -> float:
    """F-score at `threshold` (NDC frame, unsquared sample NN distances); in [0, 1], 0 if pred is empty.

    Args: pred, gt: trimesh.Trimesh; threshold: distance in NDC units (bbox diagonal 1); n, seed: as above.
    """
    (pv, pf), (gv, gf), empty = _prepare(pred, gt)
    return 0.0 if empty else _sample_metrics(pv, pf, gv, gf, n, seed, threshold)[0]["f_score"]


def normal_consistency(pred, gt, n: int = 100_000, seed: int = 0) -> float:
    """Mean |n . n_NN| of sample face normals, both ways, averaged; in [0, 1], NaN if pred is empty."""
    (pv, pf), (gv, gf), empty = _prepare(pred, gt)
    return math.nan if empty else _sample_metrics(pv, pf, gv, gf, n, seed, F_SCORE_THRESHOLD)[0][
        "normal_consistency"]


# ----------------------------------------------------------------------------------------------- RE/FP

def _unique_rows(faces: np.ndarray) -> np.ndarray:
    f = np.sort(np.asarray(faces, dtype=np.int64).reshape(-1, 3), axis=1)
    return np.unique(f, axis=0)


def _row_keys(rows: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(rows).view(np.dtype((np.void, 24))).ravel()


def re_fp(pred_faces: np.ndarray, gt_faces: np.ndarray, n_gt_vertices: int | None = None) -> dict:
    """Face recovery (RE) and false-positive ratio (FP) of DMesh's mesh-to-DMesh experiment.

    Both face lists index one shared vertex array whose first `n_gt_vertices` entries are the GT vertices
    (the prediction may add more vertices after them). Faces are compared as sorted, unique index triples, so
    winding and duplicates (back-to-back pairs) do not matter.

    Args:
        pred_faces: (F, 3) int predicted faces. gt_faces: (F', 3) int GT faces, F' >= 1.
        n_gt_vertices: number of GT vertices; None: max index in gt_faces + 1.

    Returns:
        {"re": recovered / gt_faces, "fp": false / on_gt (0.0 when on_gt is 0), "gt_faces": unique GT
        triples, "on_gt": unique predicted triples whose three vertices are all GT vertices, "recovered":
        those that are GT triples, "false": those that are not}.
    """
    gt = _unique_rows(gt_faces)
    if len(gt) == 0:
        raise ValueError("re_fp: gt_faces is empty")
    if gt.min() < 0:
        raise ValueError("re_fp: negative face index")
    nv = int(gt.max()) + 1 if n_gt_vertices is None else int(n_gt_vertices)
    if gt.max() >= nv:
        raise ValueError(f"re_fp: gt_faces index vertex {int(gt.max())} >= n_gt_vertices {nv}")
    pred = _unique_rows(pred_faces)
    if len(pred) and pred.min() < 0:
        raise ValueError("re_fp: negative face index")
    on_gt = pred[(pred < nv).all(axis=1)]
    hit = np.isin(_row_keys(on_gt), _row_keys(gt))
    recovered = int(hit.sum())
    false = int(len(on_gt) - recovered)
    return {"re": recovered / len(gt), "fp": false / len(on_gt) if len(on_gt) else 0.0, "gt_faces": int(len(gt)),
            "on_gt": int(len(on_gt)), "recovered": recovered, "false": false}


# ------------------------------------------------------------------------------------------ mesh stats

def _edge_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) int64 and how many faces use each (E,) int64."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def _n_components(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the graph on n nodes with edges (a[i], b[i]): (count, (n,) labels)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    adj = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n))
    count, labels = connected_components(adj, directed=False)
    return int(count), labels


def topology(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """Combinatorial figures of a triangle mesh: edges, boundary, manifoldness, winding, Euler characteristic, genus.

    Written here rather than taken from trimesh, which has no per-vertex manifold test, no boundary-loop count
    and no orientability test for an inconsistently wound mesh. Faces that repeat a vertex index have no
    topology and are left out; vertices no face uses are not counted.

    Args:
        vertices: (V, 3) float (only their count matters). faces: (F, 3) int64 indices into vertices.

    Returns:
        {"edges": E unique undirected edges, "boundary_edges": edges used by one face, "boundary_loops":
        connected pieces of the boundary-edge graph (the holes of a 2-manifold), "non_manifold_edges": edges
        used by more than two faces, "non_manifold_vertices": vertices whose faces form more than one fan
        (faces around a vertex joined through the two-face edges at it; a bow-tie vertex, or the ends of a
        non-manifold edge), "components": connected components (faces joined through shared vertices),
        "watertight": F > 0 and every edge is used by exactly two faces, "winding_consistent": every two-face
        edge is run in opposite directions by its two faces, "inconsistent_winding_edges": two-face edges run
        the same way by both, "euler_characteristic": V - E + F, "genus": for an orientable 2-manifold (no
        non-manifold edge or vertex) the sum over components of g with chi = 2 - 2 g - b, i.e.
        (2 C - chi - boundary_loops) / 2; None for a non-manifold or non-orientable mesh}.
    """
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    out = {"edges": 0, "boundary_edges": 0, "boundary_loops": 0, "non_manifold_edges": 0,
           "non_manifold_vertices": 0, "components": 0, "watertight": False, "winding_consistent": True,
           "inconsistent_winding_edges": 0, "euler_characteristic": 0, "genus": None}
    if len(f) == 0:
        return out
    nv = len(np.asarray(vertices).reshape(-1, 3))
    sides = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)   # (3F, 2): side 3i+k runs corner k -> k+1 of face i
    lo, hi = np.minimum(sides[:, 0], sides[:, 1]), np.maximum(sides[:, 0], sides[:, 1])
    nv = max(nv, int(f.max()) + 1)
    keys, edge_of, counts = np.unique(lo * nv + hi, return_inverse=True, return_counts=True)  # 1-D: fast
    edges = np.stack([keys // nv, keys % nv], axis=1)
    edge_of = edge_of.ravel()
    forward = np.bincount(edge_of, weights=(sides[:, 0] < sides[:, 1]), minlength=len(edges))
    two = counts == 2
    bad_winding = two & (forward != 1)
    used = np.unique(f)
    ncomp, _ = _n_components(nv, edges[:, 0], edges[:, 1])
    ncomp -= nv - len(used)                              # unused vertices are singleton components
    bnd = edges[counts == 1]
    _, blab = _n_components(nv, bnd[:, 0], bnd[:, 1])
    loops = int(len(np.unique(blab[np.unique(bnd)]))) if len(bnd) else 0
    nm_vertices = _non_manifold_vertices(f, sides, edge_of, two)
    chi = int(len(used) - len(edges) + len(f))
    out.update({"edges": int(len(edges)), "boundary_edges": int(len(bnd)), "boundary_loops": loops,
                "non_manifold_edges": int((counts > 2).sum()), "non_manifold_vertices": nm_vertices,
                "components": int(ncomp), "watertight": bool(two.all()),
                "winding_consistent": not bool(bad_winding.any()),
                "inconsistent_winding_edges": int(bad_winding.sum()), "euler_characteristic": chi})
    if out["non_manifold_edges"] == 0 and nm_vertices == 0 and _orientable(len(f), edge_of, two, bad_winding):
        g2 = 2 * ncomp - chi - loops
        out["genus"] = g2 // 2 if g2 % 2 == 0 else None
    return out


def _two_face_pairs(edge_of: np.ndarray, two: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two sides (s1, s2), each (M,) int64, of every two-face edge, and that edge's id (M,)."""
    order = np.argsort(edge_of, kind="stable")
    keep = two[edge_of[order]]
    s = order[keep].reshape(-1, 2)                       # sides of one two-face edge sit together once sorted
    return s[:, 0], s[:, 1], edge_of[s[:, 0]]


def _non_manifold_vertices(f: np.ndarray, sides: np.ndarray, edge_of: np.ndarray, two: np.ndarray) -> int:
    """Vertices whose corners (face, vertex) fall into more than one fan; see `topology`.

    Corner 3i+k is vertex f[i, k] in face i; side 3i+k starts at corner 3i+k and ends at corner 3i+(k+1)%3.
    Across a two-face edge the corners of each of its two vertices are joined; a vertex whose corners then
    form more than one group is a non-manifold vertex.
    """
    s1, s2, _ = _two_face_pairs(edge_of, two)
    end1, end2 = 3 * (s1 // 3) + (s1 % 3 + 1) % 3, 3 * (s2 // 3) + (s2 % 3 + 1) % 3   # corners where they end
    ca, cb = [], []
    for v in (sides[s1, 0], sides[s1, 1]):              # each vertex of the edge: its corner in both faces
        ca.append(np.where(sides[s1, 0] == v, s1, end1))
        cb.append(np.where(sides[s2, 0] == v, s2, end2))
    ca, cb = np.concatenate(ca), np.concatenate(cb)
    _, labels = _n_components(3 * len(f), ca, cb)
    vert = f.ravel()                                     # vertex of corner 3i+k
    fans = np.unique(vert * np.int64(3 * len(f)) + labels)  # one entry per (vertex, fan)
    per_vertex = np.bincount(fans // (3 * len(f)))
    return int((per_vertex > 1).sum())


def _orientable(n_faces: int, edge_of: np.ndarray, two: np.ndarray, bad_winding: np.ndarray) -> bool:
    """Whether some choice of reversed faces makes every two-face edge consistently wound.

    Two-colouring of the faces' double cover: node (i, 0) is face i as wound, (i, 1) reversed; a consistent
    edge joins same-state nodes, an inconsistent one opposite states. Orientable iff no face meets itself
    reversed (a Moebius strip does).
    """
    if not bad_winding.any():
        return True
    s1, s2, e = _two_face_pairs(edge_of, two)
    i1, i2 = s1 // 3, s2 // 3
    flip = bad_winding[e].astype(np.int64)
    a = np.concatenate([2 * i1, 2 * i1 + 1])
    b = np.concatenate([2 * i2 + flip, 2 * i2 + 1 - flip])
    _, labels = _n_components(2 * n_faces, a, b)
    return bool((labels[0::2] != labels[1::2]).all())


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Number of faces that cross another face, as MeshLab's self-intersection selection finds them (pymeshlab;
    a neighbour sharing one vertex counts when the edge opposite that vertex passes through it); -1 without
    pymeshlab."""
    if len(faces) == 0:
        return 0
    try:
        import pymeshlab
    except ImportError:
        log.warning("pymeshlab is not installed (project extra [harness]); self-intersections not counted")
        return -1
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64),
                               face_matrix=np.asarray(faces, np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    return int(ms.current_mesh().selected_face_number())


def mesh_stats(mesh, self_intersections: bool = True) -> dict:
    """Counts, topology and triangle-quality figures of a mesh (frame-independent).

    Args:
        mesh: trimesh.Trimesh with vertices (V, 3), faces (F, 3); may be empty.
        self_intersections: count self-intersecting faces (pymeshlab; the slowest figure).

    Returns:
        {"vertices": V, "faces": F, then the `topology` keys (edges, boundary_edges, boundary_loops,
        non_manifold_edges, non_manifold_vertices, components, watertight, winding_consistent,
        inconsistent_winding_edges, euler_characteristic, genus), "self_intersecting_faces": count (-1 if not
        computed), "degenerate_faces": zero-area faces, "aspect_ratio_mean", "aspect_ratio_max": circumradius /
        (2 inradius) (1 for equilateral, inf for degenerate; the mean is over non-degenerate faces),
        "angles_below_10_pct": % of triangle corner angles under 10 degrees (corners of zero-length edges
        excluded)}. Empty meshes give 0 counts and NaN figures.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    out = {"vertices": int(len(v)), "faces": int(len(f)), **topology(v, f), "self_intersecting_faces": 0,
           "degenerate_faces": 0, "aspect_ratio_mean": math.nan, "aspect_ratio_max": math.nan,
           "angles_below_10_pct": math.nan}
    if len(f) == 0:
        return out
    out["self_intersecting_faces"] = self_intersecting_faces(v, f) if self_intersections else -1
    t = v[f]
    la = np.linalg.norm(t[:, 1] - t[:, 2], axis=1)   # opposite corner 0
    lb = np.linalg.norm(t[:, 2] - t[:, 0], axis=1)
    lc = np.linalg.norm(t[:, 0] - t[:, 1], axis=1)
    area = _area(v, f)
    scale = np.maximum(np.maximum(la, lb), lc)
    degenerate = area <= 1e-12 * np.maximum(scale * scale, 1e-300)
    out["degenerate_faces"] = int(degenerate.sum())
    with np.errstate(divide="ignore", invalid="ignore"):
        aspect = la * lb * lc * (la + lb + lc) / (16.0 * area * area)
    aspect = np.where(degenerate, np.inf, aspect)
    finite = aspect[~degenerate]
    out["aspect_ratio_mean"] = float(finite.mean()) if len(finite) else math.inf
    out["aspect_ratio_max"] = float(aspect.max())
    angles = []
    for (o1, o2), opp in (((lb, lc), la), ((lc, la), lb), ((la, lb), lc)):
        with np.errstate(divide="ignore", invalid="ignore"):
            cos = (o1 * o1 + o2 * o2 - opp * opp) / (2 * o1 * o2)
        angles.append(np.degrees(np.arccos(np.clip(cos[(o1 > 0) & (o2 > 0)], -1.0, 1.0))))
    a = np.concatenate(angles)
    out["angles_below_10_pct"] = float(100.0 * (a < 10.0).mean()) if len(a) else math.nan
    return out


# ------------------------------------------------------------------------------------------------ all

def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(F, 3) float64 unit face normals by the right-hand rule of the winding (zero for degenerate faces)."""
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _orientation_metrics(pv, pf, gv, gf, samples_g, samples_p, face_g, face_p, gt_index) -> dict:
    """Signed normal agreement with the GT: `normal_consistency_oriented`, `oriented_fraction` and
    `oriented_fraction_any_side` (module docstring).

    Args: the prediction (pv, pf) and GT (gv, gf) in the GT frame; samples_g / samples_p: (N, 3) sample
        normals of each; face_g: (N,) the prediction face nearest each GT sample, face_p: (N,) the GT face
        nearest each prediction sample (the cd_p2s queries); gt_index: closest-point index of the GT.
    """
    npf, ngf = _face_normals(pv, pf), _face_normals(gv, gf)
    nc = 0.5 * float(np.einsum("nc,nc->n", samples_g, npf[face_g]).mean()
                     + np.einsum("nc,nc->n", samples_p, ngf[face_p]).mean())
    return {"normal_consistency_oriented": nc, **_oriented_fractions(pv, pf, ngf, gt_index)}


def _oriented_fractions(pv, pf, ngf, gt_index) -> dict:
    """`oriented_fraction` and `oriented_fraction_any_side` of the prediction (pv, pf) against GT face normals
    `ngf` and the GT's closest-point index (module docstring)."""
    _, face_c, _ = gt_index.query(pv[pf].mean(axis=1))           # GT face nearest each prediction centroid
    area = _area(pv, pf)
    agree = np.einsum("fc,fc->f", _face_normals(pv, pf), ngf[face_c]) > 0
    comp, is_open = _sheets(pf)
    n = len(is_open)
    right, total = np.bincount(comp, area * agree, n), np.bincount(comp, area, n)
    any_side = np.where(is_open, np.maximum(right, total - right), right)
    return {"oriented_fraction": float(area[agree].sum() / area.sum()),
            "oriented_fraction_any_side": float(any_side.sum() / total.sum())}


def oriented_fractions(pred, gt, p2s_backend: str = "auto") -> dict:
    """{"oriented_fraction", "oriented_fraction_any_side"} of `pred` against `gt` (trimesh meshes in one frame;
    the GT taken as it is wound, so turn an inside-out GT outward first), without the rest of
    `compute_metrics`. NaN for an empty prediction."""
    from eval.closest_point import make_index

    pv, pf = _check_mesh(pred, "prediction")
    gv, gf = _check_mesh(gt, "GT")
    if not len(pf) or not _area(pv, pf).sum() > 0:
        return {"oriented_fraction": math.nan, "oriented_fraction_any_side": math.nan}
    return _oriented_fractions(pv, pf, _face_normals(gv, gf), make_index(gv, gf, p2s_backend))


def _sheets(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pieces of surface of a face list: ((F,) component of each face, (C,) bool whether it is open).

    Faces are joined through edges that exactly two faces use, whatever their winding (so a piece wound
    inconsistently stays one piece); a piece is open when one of its edges belongs to it alone.
    """
    F = len(f)
    sides = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    nv = int(f.max()) + 1
    _, edge_of, counts = np.unique(sides[:, 0] * nv + sides[:, 1], return_inverse=True, return_counts=True)
    edge_of = edge_of.ravel()
    face_of = np.repeat(np.arange(F), 3)
    order = np.argsort(edge_of, kind="stable")
    pairs = order[(counts[edge_of] == 2)[order]].reshape(-1, 2)   # the two sides of each two-face edge
    _, comp = _n_components(F, face_of[pairs[:, 0]], face_of[pairs[:, 1]])
    on_boundary = np.bincount(face_of, counts[edge_of] == 1, F) > 0
    is_open = np.bincount(comp, on_boundary, comp.max() + 1) > 0
    return comp, is_open


def _gt_figures(gt) -> tuple[object, dict]:
    """The GT oriented outward (`datasets.meshes.orient_outward`) and its `gt_*` keys (see `compute_metrics`)."""
    import trimesh

    from datasets.meshes import orient_outward

    if not isinstance(gt, trimesh.Trimesh):
        gt = trimesh.Trimesh(*_check_mesh(gt, "GT"), process=False)
    loaded = gt.metadata.get("orientation") if isinstance(getattr(gt, "metadata", None), dict) else None
    gt, found = orient_outward(gt, name="GT", quiet=loaded is not None)  # its loader reported it already
    # A GT flipped when it was loaded reads "outward" now; report what the loader found.
    status = "flipped" if loaded == "flipped" and found == "outward" else found
    topo = topology(gt.vertices, gt.faces)
    figures = {"gt_orientation": status, "gt_orientable": status in ("outward", "flipped", "open")}
    figures.update({f"gt_{k}": topo[k] for k in ("watertight", "boundary_edges", "non_manifold_edges",
                                                   "components", "euler_characteristic", "genus")})
    return gt, figures


def compute_metrics(pred, gt, n: int = 100_000, seed: int = 0, self_intersections: bool = True,
                    re_fp_vertices: int | None = None, p2s_backend: str = "auto") -> dict:
    """Every metric of a prediction against its GT, as one flat dict (both meshes in the GT frame).

    The GT is first passed through `datasets.meshes.orient_outward`: an inside-out closed GT is flipped, so
    the oriented figures always compare against an outward GT (the harness's loaders flip it earlier, before
    any input is sampled or rendered from it).

    Args:
        pred: trimesh.Trimesh prediction (may be empty: flagged, not an error). gt: trimesh.Trimesh with
            positive area. Both must have finite vertices (ValueError otherwise). A `gt.metadata["orientation"]`
            of "flipped" (set by `load_mesh(..., orient=True)`) is reported as the GT's orientation.
        n: area-uniform samples per mesh (each side from its own stream of `seed`, `metric_rng`).
        self_intersections: count self-intersecting faces of the prediction (pymeshlab).
        re_fp_vertices: when the prediction's first K vertices are the GT's vertices in order (mesh to
            DMesh), K; adds the `re_fp` keys ("re", "fp", ...). None: no RE/FP.
        p2s_backend: closest-point backend for `cd_p2s` (see `chamfer_l1_p2s`).

    Returns:
        {"empty": no prediction face has area (then distances are inf, f_score/precision/recall 0 and the
        normal figures NaN), "n_samples", "seed",
        "cd_l1", "cd_l1_gt_to_pred", "cd_l1_pred_to_gt": sample Chamfer L1 and its two halves (GT-radius units),
        "cd_p2s", "cd_p2s_gt_to_pred", "cd_p2s_pred_to_gt": point-to-surface Chamfer L1 and halves (GT-radius
        units), "cd_l2_ndc" (squared NDC units), "f_score", "precision", "recall" (at 0.003 NDC),
        "normal_consistency": unsigned, at nearest samples (module docstring),
        "normal_consistency_oriented": signed, (mean_g n_g . n_pred(closest point of g) + mean_p n_p .
        n_gt(closest point of p)) / 2 with face normals at the exact closest points of the cd_p2s queries, in
        [-1, 1]: 1 for a mesh against itself, -1 for its inverted copy (so it is not bounded by the unsigned
        figure, whose pairs are nearest samples),
        "oriented_fraction": area-weighted fraction of the prediction's faces whose normal points the same way
        (positive dot product) as the GT face closest to the face's centroid, in [0, 1];
        "oriented_fraction_any_side": the same with each open piece of the prediction on its better side
        (closed pieces must face outward; module docstring), in [0.5, 1] per open piece;
        the oriented figures are NaN when the GT is not orientable (see gt_orientation),
        "gt_orientation": the GT's `orient_outward` status ("outward", "flipped", "open", "inconsistent",
        "non_orientable"), "gt_orientable": False for the last two,
        "gt_watertight", "gt_boundary_edges", "gt_non_manifold_edges", "gt_components",
        "gt_euler_characteristic", "gt_genus": the GT's `topology` figures, to set beside the prediction's;
        then the `mesh_stats` keys of the prediction with its vertices merged by position
        (`datasets.meshes.merge_vertices`, as `load_mesh` reads a file; vertices, faces, edges, boundary_edges,
        boundary_loops, non_manifold_edges, non_manifold_vertices, components, watertight, winding_consistent,
        inconsistent_winding_edges, euler_characteristic, genus, self_intersecting_faces, degenerate_faces,
        aspect_ratio_mean, aspect_ratio_max, angles_below_10_pct)}.
    """
    (pv, pf), (gv, _), empty = _prepare(pred, gt)
    gt, gt_figures = _gt_figures(gt)                  # same vertices; faces reversed if it was inside-out
    gf = np.asarray(gt.faces, dtype=np.int64)
    out: dict = {"empty": bool(empty), "n_samples": int(n), "seed": int(seed)}
    if empty:
        log.warning("empty prediction: distances reported as inf")
        out.update({"cd_l1": math.inf, "cd_l1_gt_to_pred": math.inf, "cd_l1_pred_to_gt": math.inf,
                    "cd_p2s": math.inf, "cd_p2s_gt_to_pred": math.inf, "cd_p2s_pred_to_gt": math.inf,
                    "cd_l2_ndc": math.inf, "f_score": 0.0, "precision": 0.0, "recall": 0.0,
                    "normal_consistency": math.nan, "normal_consistency_oriented": math.nan,
                    "oriented_fraction": math.nan, "oriented_fraction_any_side": math.nan})
    else:
        from eval.closest_point import make_index

        figures, (G, nG), (P, nP) = _sample_metrics(pv, pf, gv, gf, n, seed, F_SCORE_THRESHOLD)
        gt_index = make_index(gv, gf, p2s_backend)
        d_g, face_g, _ = make_index(pv, pf, p2s_backend).query(G)
        d_p, face_p, _ = gt_index.query(P)
        out.update({"cd_l1": figures.pop("cd_l1"), "cd_l1_gt_to_pred": figures.pop("cd_l1_gt_to_pred"),
                    "cd_l1_pred_to_gt": figures.pop("cd_l1_pred_to_gt"),
                    "cd_p2s": float(d_g.mean() + d_p.mean()), "cd_p2s_gt_to_pred": float(d_g.mean()),
                    "cd_p2s_pred_to_gt": float(d_p.mean())})
        out.update(figures)
        if gt_figures["gt_orientable"]:
            out.update(_orientation_metrics(pv, pf, gv, gf, nG, nP, face_g, face_p, gt_index))
        else:
            log.info("GT is %s: oriented normal figures are NaN (only the unsigned one applies)",
                     gt_figures["gt_orientation"].replace("_", "-"))
            out.update({"normal_consistency_oriented": math.nan, "oriented_fraction": math.nan,
                        "oriented_fraction_any_side": math.nan})
    out.update(gt_figures)
    import trimesh

    from datasets.meshes import merge_vertices

    # Topology as a file of this mesh reads once loaded (`load_mesh`, trimesh's default, an STL): copies of a
    # vertex on one position are one vertex, so splitting a pinch or a branch without moving it hides nothing.
    mv, mf = merge_vertices(pv, pf) if len(pf) else (pv, pf)
    out.update(mesh_stats(trimesh.Trimesh(mv, mf, process=False), self_intersections=self_intersections))
    if re_fp_vertices is not None:
        out.update(re_fp(pf, gf, n_gt_vertices=int(re_fp_vertices)))
    return out
