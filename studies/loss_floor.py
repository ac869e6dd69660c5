"""Why the point-cloud gradient steps stall: the sampling floor of the expected Chamfer loss.

The point-cloud loss is a Chamfer distance between N points sampled on the mesh and N target points. Two
independent samplings of the same surface are not at distance 0: each point's nearest neighbour on the other
side lies a fraction of the sample spacing away, tangentially. For each shape (normalised to radius 1) this
bench measures, with N surface samples of the GT itself and N target points on it (independent draws):

- floor: the loss of the GT itself (mean nearest-neighbour distance, both directions, summed), mean over draws;
- signal: the loss of the GT moved outward along its normals by delta (a surface whose CD p2s to the GT is
  about 2 delta) minus the floor: what a step could gain by fixing that error;
- alignment: with the surface moved out by delta, the per-sample descent direction (minus the gradient of the
  loss with respect to the sample position) against the direction that fixes the error (the inward normal):
  the mean cosine over samples and the share of samples whose descent direction points inward at all. 1 and
  100 %: every sample is pulled toward the surface; 0 and 50 %: the gradient is noise.

Two distances: `euclidean` (the loss the paper and this project use) and `plane` (point to the tangent plane
of the matched point: |(s - t) . n_t| from samples to targets, |(t - s) . n_s| from targets to samples), which
has no tangential floor. The loss of a paper-preset run sits at its floor (`reports/table2_pointcloud.md`,
curves), so its steps follow mostly the floor's noise.

Regenerate: `python -m studies loss_floor` (about a minute; `--quick`: the torus only, 2 draws).
"""
from __future__ import annotations

import numpy as np

from eval.bench.common import markdown_table, write_report

SHAPES = ("torus", "bowl", "plant")
COUNTS = (20_000, 100_000)
DELTAS = (0.0, 1e-3, 3e-3)


def _samples(mesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    points, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[face], dtype=np.float64)


def loss_and_gradient(s: np.ndarray, ns: np.ndarray, t: np.ndarray, nt: np.ndarray, mode: str):
    """(loss, (S, 3) gradient of the loss with respect to the samples `s`) of the two-sided mean distance."""
    from scipy.spatial import cKDTree

    grad = np.zeros_like(s)
    _, j = cKDTree(t).query(s, workers=-1)  # samples -> targets
    d = s - t[j]
    if mode == "plane":
        dist = np.abs((d * nt[j]).sum(1))
        grad += np.sign((d * nt[j]).sum(1))[:, None] * nt[j] / len(s)
    else:
        dist = np.linalg.norm(d, axis=1)
        grad += d / np.maximum(dist, 1e-12)[:, None] / len(s)
    loss = dist.mean()
    _, i = cKDTree(s).query(t, workers=-1)  # targets -> samples
    e = s[i] - t
    if mode == "plane":
        dist2 = np.abs((e * ns[i]).sum(1))
        np.add.at(grad, i, np.sign((e * ns[i]).sum(1))[:, None] * ns[i] / len(t))
    else:
        dist2 = np.linalg.norm(e, axis=1)
        np.add.at(grad, i, e / np.maximum(dist2, 1e-12)[:, None] / len(t))
    return loss + dist2.mean(), grad


def run(shape: str, draws: int) -> list[dict]:
    from datasets.normalize import normalize
    from datasets.synthetic import generate

    gt, _ = normalize(generate(shape))
    rows = []
    for n in COUNTS:
        target, target_n = _samples(gt, n, seed=0)
        for mode in ("euclidean", "plane"):
            floor = []
            for delta in DELTAS:
                losses, cosines, inward = [], [], []
                for k in range(draws):
                    s, ns = _samples(gt, n, seed=100 + k)
                    loss, g = loss_and_gradient(s + delta * ns, ns, target, target_n, mode)
                    losses.append(loss)
                    if delta > 0:
                        norm = np.linalg.norm(g, axis=1)
                        hit = norm > 0
                        # a step goes along -g; the offset is fixed along -n: cos(-g, -n) = cos(g, n)
                        cos = (g[hit] * ns[hit]).sum(1) / norm[hit]
                        cosines.append(cos.mean())
                        inward.append((cos > 0).mean())
                if delta == 0:
                    floor = losses
                rows.append({"shape": shape, "n": n, "distance": mode, "delta": delta,
                             "loss": float(np.mean(losses)), "loss_std": float(np.std(losses)),
                             "signal": float(np.mean(losses) - np.mean(floor)) if delta > 0 else "",
                             "cos_inward": float(np.mean(cosines)) if cosines else "",
                             "inward_share": float(np.mean(inward)) if inward else ""})
                print(f"  {shape} N={n} {mode} delta={delta:g}: loss {rows[-1]['loss']:.5f} "
                      f"cos {rows[-1]['cos_inward']}", flush=True)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    rows = []
    for shape in SHAPES[:1] if quick else SHAPES:
        rows += run(shape, 2 if quick else 4)
    cols = ["shape", "n", "distance", "delta", "loss", "loss_std", "signal", "cos_inward", "inward_share"]
    fmt = {"delta": "g", "loss": ".5f", "loss_std": ".1e", "signal": ".5f", "cos_inward": ".3f",
           "inward_share": ".3f"}
    intro = __doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip()
    write_report(out, "loss_floor", "The sampling floor of the point-cloud loss", intro,
                 markdown_table(rows, cols, fmt), rows)


if __name__ == "__main__":
    main()
