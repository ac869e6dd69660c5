"""The gradients of one point-cloud phase-1 step: each loss term's share, and autograd against finite differences.

For a small torus input (20K points) and the initial DMesh of two recipes (the `fast` preset's 2K seeds
+ poles, the `paper` preset's 1K seeds + all Voronoi vertices), at a fixed triangulation, candidate set and
sample draw, the step's loss is split into its terms (expected Chamfer, weight, real and quality
regularisers, each times its coefficient). For each term and each parameter group (positions, weights,
reals):

- share: the norm of the term's gradient over the sum of the terms' norms in that group;
- autograd: the directional derivative g . u along a random unit direction u;
- fd: the central difference (L(x + h u) - L(x - h u)) / 2h of the same term;
- rel_err: |autograd - fd| / max(|fd|, tiny).

The detached quantities of the method (the softmin weights of Lambda_real, the normaliser of the quality
and real regularisers; as upstream) are recomputed at x +- h u, so their derivative is in `fd` and not in
`autograd`: a rel_err well above the FD noise (see the h column pair) measures that surrogate gradient.

Regenerate: `python -m eval.bench gradients` (about a minute); writes reports/bench_gradients.{md,csv}.
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import torch

from eval.bench.common import markdown_table, write_report

TERMS = ("chamfer", "weight", "real", "quality")
GROUPS = ("points", "weights", "reals")
#: Central-difference steps along the unit direction (two, to show the FD's own noise). The parameters are
#: float32, so a step below ~1e-5 drowns in their rounding; the last one gives rel_err.
STEPS = (1e-3, 1e-4)


def _input(n: int):
    from datasets.normalize import normalize
    from datasets.sampling import sample_points
    from datasets.synthetic import generate

    gt, _ = normalize(generate("torus"))
    return sample_points(gt, n, 0)


def _initial_dmesh(pts, cfg):
    """The DMesh `reconstruct` starts from with `cfg` (no step), with a fresh probability state."""
    from dmesh.recon.pointcloud import reconstruct
    from dmesh.model import DMesh

    result = reconstruct(pts, None, dataclasses.replace(cfg, steps_phase1=0, steps_phase2=0))
    d = result.dmesh
    return DMesh(d.points.detach().numpy(), d.weights.detach().numpy(), d.reals.detach().numpy(),
                 cfg.probability_config())


class StepTerms:
    """The loss terms of a phase-1 step as a function of the DMesh parameters, with the triangulation's
    candidate set, the Chamfer K and the drawn (face, barycentric) pairs fixed at their values for the initial
    parameters."""

    def __init__(self, dm, target, cfg, seed: int = 0):
        from dmesh.losses.chamfer import ExpectedChamfer, sample_faces

        self.dm, self.cfg, self.seed = dm, cfg, seed
        self.chamfer = ExpectedChamfer(target, None, k_max=cfg.k_max, mass_tol=cfg.mass_tol, impl=cfg.kernels)
        fp = dm.face_probabilities()               # fills the candidate set once
        self.state = copy.deepcopy(dm.state)
        # One draw, kept as (face, barycentric) pairs: the draw's discrete choices are constants of the step,
        # as they are in its gradient (a fresh draw at x +- h u would flip a few samples and jump the loss).
        with torch.no_grad():
            drawn = sample_faces(dm.points, fp.faces, fp.prob_wdt, dm.reals, fp.prob, cfg.num_samples,
                                 np.random.default_rng(seed), cfg.prob_threshold)
            tri = dm.points.double()[fp.faces[drawn.face]]
            edges = torch.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], dim=2)   # (S, 3, 2)
            self.uv = torch.linalg.lstsq(edges, (drawn.points - tri[:, 0]).unsqueeze(2)).solution.squeeze(2)
        self.tri = fp.faces[drawn.face].clone()
        self.keys = self._keys(self.tri)
        self.missing = 0

    def _keys(self, faces: torch.Tensor) -> np.ndarray:
        """One int64 per face (its sorted vertex triple), to find the drawn faces after the scored list changes."""
        n = len(self.dm)
        f = np.sort(faces.numpy(), axis=1).astype(np.int64)
        return (f[:, 0] * n + f[:, 1]) * n + f[:, 2]

    def __call__(self) -> dict[str, torch.Tensor]:
        from dmesh.losses.chamfer import SurfaceSamples
        from dmesh.losses.regularizers import quality_regularizer, real_regularizer, weight_regularizer

        dm, cfg = self.dm, self.cfg
        dm.state = copy.deepcopy(self.state)
        fp = dm.face_probabilities()
        # The drawn faces by vertex triple: a tiny step can flip near-degenerate tets and reorder the scored
        # faces; a drawn face that is no longer scored keeps its samples with probability 0 (counted).
        keys = self._keys(fp.faces)
        order = np.argsort(keys)
        pos = np.searchsorted(keys, self.keys, sorter=order).clip(max=len(keys) - 1)
        idx = order[pos]
        found = keys[idx] == self.keys
        self.missing = max(self.missing, int((~found).sum()))
        face = torch.from_numpy(np.where(found, idx, 0))
        tri = self.tri
        p = dm.points.double()
        a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
        points = a + self.uv[:, :1] * (b - a) + self.uv[:, 1:] * (c - a)
        prob = fp.prob.double()[face] * torch.from_numpy(found.astype(np.float64))
        chamfer, _ = self.chamfer(SurfaceSamples(points, face, prob), adapt=False)
        return {"chamfer": chamfer,
                "weight": cfg.lambda_weight * weight_regularizer(dm.points, dm.weights, fp.power_diagram,
                                                                   diagram=fp.diagram),
                "real": cfg.lambda_real_start * real_regularizer(dm.reals, fp.faces, fp.prob_wdt),
                "quality": cfg.lambda_quality * quality_regularizer(dm.points, fp.faces, fp.prob, min_prob=1e-4)}


def check(case: str, cfg, pts, seed: int = 0) -> list[dict]:
    """Rows (case, term, group, share, autograd, fd at each h, rel_err) for one initial DMesh."""
    dm = _initial_dmesh(pts, cfg)
    terms = StepTerms(dm, pts, cfg, seed)
    params = {"points": dm.points, "weights": dm.weights, "reals": dm.reals}
    grads = {}
    for name in TERMS:
        for p in params.values():
            p.grad = None
        value = terms()[name]
        if value.requires_grad:
            value.backward()
        grads[name] = {g: (params[g].grad.clone() if params[g].grad is not None else torch.zeros_like(params[g]))
                       for g in GROUPS}
    gen = torch.Generator().manual_seed(seed)
    rows = []
    for g in GROUPS:
        u = torch.randn(params[g].shape, generator=gen, dtype=params[g].dtype)
        u /= u.norm()
        fd = {name: [] for name in TERMS}
        terms.missing = 0
        for h in STEPS:
            vals = []
            origin = params[g].detach().clone()  # float32: x + hu - hu is not x again
            for sign in (1.0, -1.0):
                with torch.no_grad():
                    params[g].copy_(origin + sign * h * u)
                    vals.append({k: float(v) for k, v in terms().items()})
                    params[g].copy_(origin)
            for name in TERMS:
                fd[name].append((vals[0][name] - vals[1][name]) / (2 * h))
        norms = {name: float(grads[name][g].norm()) for name in TERMS}
        total = sum(norms.values()) or 1.0
        for name in TERMS:
            ad = float((grads[name][g] * u).sum())
            ref = fd[name][-1]
            rows.append({"case": case, "points": len(dm), "term": name, "group": g, "share": norms[name] / total,
                         "grad_norm": norms[name], "autograd": ad, "lost_faces": terms.missing,
                         **{f"fd_h{h:g}": v for h, v in zip(STEPS, fd[name])},
                         "rel_err": abs(ad - ref) / max(abs(ref), 1e-30) if (ad or ref) else 0.0})
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    from dmesh.recon.pointcloud import PointCloudConfig

    pts, _ = _input(5_000 if quick else 20_000)
    n = 2_000 if quick else 20_000
    cases = {"fast init": PointCloudConfig.fast(num_init=500 if quick else 2000, num_target=n, num_samples=n),
             "paper init": PointCloudConfig.paper(num_init=250 if quick else 1000, num_target=n, num_samples=n,
                                                  lambda_real_start=1e-3)}
    rows = []
    for case, cfg in cases.items():
        print(f"{case} ...", flush=True)
        rows += check(case, cfg, pts)
    cols = (["case", "points", "term", "group", "lost_faces", "share", "grad_norm", "autograd"]
            + [f"fd_h{h:g}" for h in STEPS] + ["rel_err"])
    fmt = {c: ".3g" for c in cols[5:]}
    intro = (__doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip()
             + "\n\nCoefficients: each case's preset (fast: no weight regulariser, real 1e-3, quality 1e-3; paper: "
               "weight 1e-8, real 1e-3, quality 1e-3).")
    write_report(out, "bench_gradients", "Gradients of one point-cloud phase-1 step", intro,
                 markdown_table(rows, cols, fmt), rows)


if __name__ == "__main__":
    main()
