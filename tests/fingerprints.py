"""Fingerprints of the inputs the harness generates (tests/test_input_version.py).

A stored run depends on its input's data, and the harness caches inputs by shape, settings and
`eval.code_hash.INPUT_VERSION`, not by the code that made them (eval/code_hash.py). So a change to what datasets/
generates must bump INPUT_VERSION; these fingerprints catch one that does not. Each case generates a small input
along the harness's own path (the same functions, smaller sizes) and reduces every array to a fingerprint: its
shape, its sum and its sum against fixed pseudo-random weights (any change to any value moves the latter).

Run `python tests/fingerprints.py` to print the fingerprints of the code as it is (after bumping INPUT_VERSION,
paste them into `EXPECTED` of tests/test_input_version.py).
"""
from __future__ import annotations

import inspect
from pathlib import Path

import numpy as np

SHARED_MESH = Path(__file__).resolve().parents[2] / "shared" / "meshes" / "closed" / "spot.obj"


def fingerprint(array) -> list:
    """[shape, sum of magnitudes, sum, weighted sum] of `array` (float64 arithmetic; bools and ints as numbers).
    Compare the sums within a tolerance of the magnitude (`matches`): a sum near 0 is rounding alone."""
    a = np.asarray(array, dtype=np.float64).reshape(-1)
    weights = np.random.default_rng(12345).uniform(-1.0, 1.0, len(a))
    return [list(np.shape(array)), float(np.abs(a).sum()), float(a.sum()), float(a @ weights)]


def matches(found: list, expected: list, rtol: float = 1e-10) -> bool:
    """Whether two fingerprints agree: the same shape, every sum within `rtol` of the sum of magnitudes."""
    if found[0] != expected[0]:
        return False
    scale = rtol * max(abs(expected[1]), 1e-300)
    return all(abs(a - b) <= scale for a, b in zip(found[1:], expected[1:]))


def _mesh(mesh) -> dict:
    return {"vertices": fingerprint(mesh.vertices), "faces": fingerprint(mesh.faces)}


def _gt(mesh):
    """The GT as `eval.inputs.prepare_gt` makes it: turned outward, normalised to radius 1."""
    from datasets.meshes import orient_outward
    from datasets.normalize import normalize

    return normalize(orient_outward(mesh, name="fingerprint")[0], radius=1.0)[0]


def cases() -> dict[str, dict]:
    """{case: {array name: fingerprint}} of every input generation the harness uses, at small sizes."""
    from datasets import synthetic
    from datasets.capture import capture, gl_problem
    from datasets.corrupt import add_depth_noise, corrupt_cloud
    from datasets.sampling import sample_points

    out: dict[str, dict] = {}
    for name, (_, make) in synthetic.SHAPES.items():
        # The families of datasets/families.py are meshed finer than the sampling scale of `samples` points
        # (about 2M faces for the 100K of the tables): here at the scale of 2000, the same code at 1/50 the cost.
        coarse = {"samples": 2000} if "samples" in inspect.signature(make).parameters else {}
        out[f"shape {name}"] = _mesh(synthetic.generate(name, seed=1, **coarse))
    gt = _gt(synthetic.generate("flag_box"))
    out["gt flag_box"] = _mesh(gt)
    points, normals = sample_points(gt, 3000, seed=2)
    out["samples"] = {"points": fingerprint(points), "normals": fingerprint(normals)}
    for label, corruption in {"noise": {"noise": 0.005}, "outliers": {"outliers": 0.05}, "density": {"density": 1000},
                              "nonuniform": {"nonuniform": 8}, "estimated": {"normals": "estimated"},
                              "scan": {"scan": 6, "noise": 0.0025, "outliers": 0.01}}.items():
        arrays = corrupt_cloud(gt, points, normals, corruption, seed=3)
        out[f"corrupt {label}"] = {k: fingerprint(v) for k, v in sorted(arrays.items())}
    if gl_problem() is None:
        views = capture(gt, views=4, resolution=32)
        out["capture"] = {k: fingerprint(getattr(views, k)) for k in ("diffuse", "depth", "mask", "world_to_camera",
                                                                      "projection")}
        out["depth noise"] = {"depth": fingerprint(add_depth_noise(views, 0.005, seed=4).depth)}
    if SHARED_MESH.is_file():
        from datasets.meshes import classify, load_mesh

        mesh = load_mesh(str(SHARED_MESH))
        out["shared spot"] = {**_mesh(_gt(mesh)), "class": classify(mesh)}
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(cases(), indent=None).replace('}, "', '},\n "'))
