"""How noisy lifted depth pixels look to the multi-view `depth` start: the calibration of `DEPTH_NOISY_RATIO`.

The start (`dmesh.recon.multiview.depth_start_preset`, `init_preset="auto"`) lifts the depth pixels of every
view into 3D, keeps 100K of them at random and measures their noise ratio (`dmesh.recon.init.noise_ratio`:
the median distance of a point to the plane of its 16 nearest neighbours, in neighbour spacings). Above
`DEPTH_NOISY_RATIO` it first fits each of those points from its nearest of all the lifted pixels
(`dmesh.recon.views.smooth_from_pool`); either way the point-cloud `fast` preset follows.
This table gives that ratio for the harness's own captures (`datasets.capture.capture`, shapes normalised to
radius 1, cameras at distance 2) with the sweeps' depth noise (`datasets.corrupt.add_depth_noise`, Gaussian,
as a fraction of the radius), at the capture sizes the sweeps use. The threshold must sit between the
largest clean figure and the smallest noisy one; the summary below the table says by how much it does.

Regenerate: `python -m studies depth_noise` (`--quick`: the torus and the bowl
at 64 views and 256 pixels only).
"""
from __future__ import annotations

import numpy as np

from eval.bench.common import markdown_table, write_report

#: (views, pixels, shapes, depth-noise levels): the sweeps' captures (robustness_multiview.yaml varies the
#: views and the pixels on its six shapes; Table 2 adds the real meshes) and the tests' small sphere capture.
CASES = (
    (64, 256, ("torus", "genus2", "bowl", "wavy_sheet", "plant", "flag_box"), (0.0, 0.0025, 0.005, 0.01)),
    (64, 256, ("closed/spot.obj", "mixed/suzanne.obj", "open/face.off"), (0.0, 0.0025)),
    (16, 256, ("torus", "bowl", "plant", "flag_box"), (0.0, 0.0025)),
    (8, 256, ("torus", "bowl", "plant", "flag_box"), (0.0, 0.0025)),
    (64, 128, ("torus", "bowl", "plant", "flag_box"), (0.0, 0.0025)),
    (16, 96, ("sphere",), (0.0, 0.0025, 0.005)),
)
QUICK = ((64, 256, ("torus", "bowl"), (0.0, 0.0025)),)
#: Lifted pixels measured per capture, as the start takes them (`MultiViewConfig.init_points`).
POINTS = 100_000


def load_shape(name: str):
    """A shape of the harness, normalised to radius 1: a synthetic name, or a path under the data root."""
    from datasets.normalize import normalize

    if "/" in name:
        from datasets.meshes import load_mesh
        from eval.sweep import default_data_root

        mesh = load_mesh(default_data_root() / name, orient=True)
    else:
        from datasets.synthetic import generate

        mesh = generate(name)
    return normalize(mesh)[0]


def ratios(mesh, views: int, pixels: int, levels, seed: int = 0) -> list[float]:
    """The noise ratio of `POINTS` lifted pixels of `mesh`'s capture at each depth-noise level."""
    from datasets.capture import capture
    from datasets.corrupt import add_depth_noise
    from dmesh.camera import lift_depth
    from dmesh.recon.init import noise_ratio

    clean = capture(mesh, views, pixels)
    out = []
    for level in levels:
        vw = add_depth_noise(clean, level, seed) if level > 0 else clean
        pts = lift_depth(vw.depth, vw.mask, vw.world_to_camera, vw.fov_y_degrees)
        if len(pts) > POINTS:
            pts = pts[np.sort(np.random.default_rng(seed).choice(len(pts), POINTS, replace=False))]
        out.append(noise_ratio(pts, workers=2))
    return out


def summary(rows: list[dict], threshold: float) -> str:
    """Where `threshold` sits between the largest clean ratio and the smallest noisy one."""
    clean = [r["ratio"] for r in rows if r["depth_noise"] == 0]
    noisy = [r["ratio"] for r in rows if r["depth_noise"] > 0]
    hi, lo = max(clean), min(noisy)
    verdict = ("separates them" if hi < threshold < lo else "does NOT separate them")
    return (f"`DEPTH_NOISY_RATIO` = {threshold:g} {verdict}: the largest clean ratio is {hi:.3f} "
            f"({threshold / hi:.1f}x below the threshold), the smallest noisy one {lo:.3f} "
            f"({lo / threshold:.1f}x above).")


def main(out: str = "reports", quick: bool = False) -> None:
    from dmesh.recon.init import DEPTH_NOISY_RATIO

    rows = []
    for views, pixels, shapes, levels in QUICK if quick else CASES:
        for shape in shapes:
            for level, ratio in zip(levels, ratios(load_shape(shape), views, pixels, levels)):
                rows.append({"shape": shape, "views": views, "pixels": pixels, "depth_noise": level,
                             "ratio": ratio, "smoothing": "pool" if ratio > DEPTH_NOISY_RATIO else "none"})
                print(f"  {shape} {views} views {pixels} px noise {level:g}: ratio {ratio:.3f}", flush=True)
    cols = ["shape", "views", "pixels", "depth_noise", "ratio", "smoothing"]
    intro = (__doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip()
             + "\n\n" + summary(rows, DEPTH_NOISY_RATIO)
             + " `smoothing`: whether the start fits its points from all the pixels first.")
    write_report(out, "depth_noise", "Noise ratio of lifted depth pixels (the depth start's preset choice)",
                 intro, markdown_table(rows, cols, {"ratio": ".3f", "depth_noise": "g"}), rows)


if __name__ == "__main__":
    main()
