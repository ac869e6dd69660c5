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

Topology (`eval.topology.topology`, re-exported here with `mesh_stats`, `re_fp` and `self_intersecting_faces`):
boundary edges and loops, non-manifold edges and vertices, components, watertightness, winding consistency, Euler
characteristic and genus, for the prediction and (prefixed `gt_`) the GT.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from eval.topology import face_areas, mesh_stats, re_fp, self_intersecting_faces, sheets, topology  # noqa: F401

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
    area = face_areas(vertices, faces)
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
    if len(gf) == 0 or face_areas(gv, gf).sum() <= 0:
        raise ValueError("GT mesh has no faces with positive area")
    c, s = gt_transform(gt)
    gv, pv = (gv - c) * s, (pv - c) * s
    empty = len(pf) == 0 or not face_areas(pv, pf).sum() > 0
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
    area = face_areas(pv, pf)
    agree = np.einsum("fc,fc->f", _face_normals(pv, pf), ngf[face_c]) > 0
    comp, is_open = sheets(pf)
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
    if not len(pf) or not face_areas(pv, pf).sum() > 0:
        return {"oriented_fraction": math.nan, "oriented_fraction_any_side": math.nan}
    return _oriented_fractions(pv, pf, _face_normals(gv, gf), make_index(gv, gf, p2s_backend))


#: `gt.metadata` key of the GT's own figures (`gt_figures`), when the caller knows them (every run of a shape
#: scores against the same GT file: `eval.execute.with_gt_figures` computes them once).
GT_FIGURES_KEY = "gt_figures"


def gt_figures(gt) -> tuple[object, dict]:
    """The GT oriented outward (`datasets.meshes.orient_outward`) and its `gt_*` keys (see `compute_metrics`).
    A `gt.metadata[GT_FIGURES_KEY]` dict is taken as they are (the GT must then be outward already)."""
    return _gt_figures(gt)


def _gt_figures(gt) -> tuple[object, dict]:
    """`gt_figures`."""
    import trimesh

    from datasets.meshes import orient_outward

    if not isinstance(gt, trimesh.Trimesh):
        gt = trimesh.Trimesh(*_check_mesh(gt, "GT"), process=False)
    known = gt.metadata.get(GT_FIGURES_KEY)
    if isinstance(known, dict):  # computed for this very GT (`eval.execute.with_gt_figures`), which is outward
        return gt, dict(known)
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
