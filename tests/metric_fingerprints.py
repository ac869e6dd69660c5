"""Fingerprints of the metrics (tests/test_metrics_version.py).

Each run's metrics carry `eval.code_hash.METRICS_VERSION`, not a hash of the metric code's text
(eval/code_hash.py), so the metric code can be refactored without rescoring every stored run; a change to what it
computes must bump METRICS_VERSION, and these fingerprints catch one that does not. Each case scores a fixed
prediction against a fixed GT through `eval.metrics.compute_metrics`, as the harness does, at small sizes, on
every path the harness uses: closed, open, mixed and non-orientable GTs, holes, flipped faces, an empty
prediction, self-intersections, RE/FP and both closest-point backends.

Run `python tests/metric_fingerprints.py` to print the metrics of the code as it is (after bumping
METRICS_VERSION, paste them into `EXPECTED` of tests/test_metrics_version.py).
"""
from __future__ import annotations

import math

import numpy as np

#: Surface samples per mesh in every case (the tables use 100K; the paths are the same).
N_SAMPLES = 2000
#: The metrics computed from closest-point queries (`p2s_backend`).
P2S_FIGURES = ("cd_p2s", "normal_consistency_oriented", "oriented_fraction")


def _gt(name: str):
    """Synthetic shape `name`, turned outward and normalised to radius 1 as `eval.inputs.prepare_gt` does."""
    from datasets import synthetic
    from datasets.meshes import orient_outward
    from datasets.normalize import normalize

    return normalize(orient_outward(synthetic.generate(name), name="fingerprint")[0], radius=1.0)[0]


def _jittered(mesh, scale: float, seed: int, drop: int = 0, flip: int = 0):
    """A copy of `mesh` with its vertices moved by Gaussian noise of `scale`, its first `drop` faces of a fixed
    shuffle removed (holes) and the next `flip` faces reversed."""
    import trimesh

    rng = np.random.default_rng(seed)
    v = np.asarray(mesh.vertices) + rng.normal(0.0, scale, mesh.vertices.shape)
    f = np.asarray(mesh.faces)[rng.permutation(len(mesh.faces))]
    f = f[drop:].copy()
    f[:flip] = f[:flip, ::-1]
    return trimesh.Trimesh(v, f, process=False)


def _values(metrics: dict) -> dict:
    """The metrics as JSON-friendly values (floats, ints, bools, strings; inf and NaN as strings)."""
    out = {}
    for k, v in sorted(metrics.items()):
        if isinstance(v, (bool, np.bool_)):
            out[k] = bool(v)
        elif isinstance(v, (int, np.integer)):
            out[k] = int(v)
        elif isinstance(v, (float, np.floating)):
            out[k] = float(v) if math.isfinite(v) else repr(float(v))
        else:
            out[k] = v
    return out


def matches(found, expected, rtol: float = 1e-9) -> bool:
    """Whether two metric values agree: floats within `rtol` (relative, at least 1e-12 absolute), the rest
    equal."""
    if isinstance(expected, float) and isinstance(found, float):
        return abs(found - expected) <= max(rtol * abs(expected), 1e-12)
    return found == expected and type(found) is type(expected)


def cases() -> dict[str, dict]:
    """{case: {metric: value}} of `compute_metrics` on fixed meshes."""
    import trimesh

    from eval.metrics import compute_metrics

    def score(pred, gt, **kw):
        return _values(compute_metrics(pred, gt, n=N_SAMPLES, seed=1, **kw))

    sphere, disc, plant, mobius = _gt("sphere"), _gt("disc"), _gt("plant"), _gt("mobius")
    out = {
        # Closed GT; holes and reversed faces in the prediction (the topology, orientation and winding figures).
        "closed": score(_jittered(sphere, 0.01, 5, drop=20, flip=15), sphere),
        # The exact closest-point backend: the figures that come from its queries.
        "closed numpy": {k: v for k, v in score(_jittered(sphere, 0.01, 5, drop=20, flip=15), sphere,
                                                p2s_backend="numpy").items() if k.startswith(P2S_FIGURES)},
        "open": score(_jittered(disc, 0.005, 6, drop=5), disc),
        # Every face reversed: an open sheet is right on either side (`oriented_fraction_any_side`).
        "open reversed": score(_jittered(disc, 0.005, 6, flip=len(disc.faces)), disc),
        "mixed": score(_jittered(plant, 0.005, 7, flip=40), plant),
        "non-orientable": score(_jittered(mobius, 0.005, 8), mobius),
        "empty": score(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False), sphere),
    }
    # Two overlapping spheres: self-intersecting faces, two components.
    v = np.asarray(sphere.vertices)
    twin = trimesh.Trimesh(np.vstack([v, v * 0.8 + [0.5, 0.0, 0.0]]),
                           np.vstack([sphere.faces, np.asarray(sphere.faces) + len(v)]), process=False)
    out["self-intersecting"] = score(twin, sphere)
    # Mesh to DMesh: the prediction's first vertices are the GT's; faces missed and faces added (RE/FP).
    extra = np.array([[0, 1, 500], [2, 3, 400]])
    refit = trimesh.Trimesh(v, np.vstack([np.asarray(sphere.faces)[30:], extra]), process=False)
    out["re_fp"] = score(refit, sphere, re_fp_vertices=len(v), self_intersections=False)
    return out


if __name__ == "__main__":
    import pprint

    pprint.pprint(cases(), width=120)
