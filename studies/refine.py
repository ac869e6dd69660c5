"""Multi-view `depth` against `refine` (the depth start + image-loss steps), with clean and noisy depth maps.

One shape per class (torus, bowl, plant), normalised to radius 1 and captured in 64 views at 256 pixels;
the noisy captures add Gaussian noise of sigma = 0.5 % of the object radius to every covered depth pixel
(the diffuse images stay clean). Each capture is reconstructed with the `depth` and `refine` presets of
`dmesh.recon.multiview`; the table gives CD p2s against the GT, wall time, which candidate `refine` kept
(-1: its start) and the image loss of the start and of the kept mesh over all views.

Regenerate: `python -m studies refine` (about 20 minutes on 2 cores; `--quick`: torus only, 16 views at
128 pixels).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from eval.bench.common import markdown_table, write_report

SHAPES = ("torus", "bowl", "plant")
#: Depth noise, as a fraction of the object radius (the issue's 0.5 %).
NOISE = 0.005
PRESETS = ("depth", "refine")


def noisy(views, sigma: float, seed: int = 0):
    """A copy of a `MultiView` capture with N(0, sigma) added to every covered depth pixel."""
    rng = np.random.default_rng(seed)
    depth = views.depth + (rng.normal(0.0, sigma, views.depth.shape) * views.mask).astype(views.depth.dtype)
    return dataclasses.replace(views, depth=depth)


def run(shape: str, n_views: int, resolution: int) -> list[dict]:
    from datasets.capture import capture
    from datasets.normalize import normalize
    from datasets.synthetic import generate
    from dmesh.recon.multiview import MultiViewConfig, reconstruct
    from eval.metrics import chamfer_l1_p2s

    gt, _ = normalize(generate(shape))
    clean = capture(gt, n_views, resolution)
    rows = []
    for depth_noise, views in ((0.0, clean), (NOISE, noisy(clean, NOISE))):
        for preset in PRESETS:
            t0 = time.perf_counter()
            res = reconstruct(views, MultiViewConfig.preset(preset))
            wall = time.perf_counter() - t0
            epochs = res.info.get("epochs", [])
            kept = res.info.get("selected_epoch")
            kept_loss = next((e.get("eval_loss") for e in epochs if e["epoch"] == kept), None)
            rows.append({"shape": shape, "depth_noise": depth_noise, "preset": preset,
                         "cd_p2s": chamfer_l1_p2s(res.mesh, gt), "faces": len(res.mesh.faces), "time_s": wall,
                         "kept": "" if kept is None else kept, "start_loss": res.info.get("start_eval_loss", ""),
                         "kept_loss": res.info.get("start_eval_loss") if kept == -1 else (kept_loss or "")})
            print(f"  {shape} noise {depth_noise} {preset}: CD p2s {rows[-1]['cd_p2s'] * 1e3:.3f}e-3, "
                  f"{wall:.0f} s, kept {rows[-1]['kept']}", flush=True)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    rows = []
    for shape in SHAPES[:1] if quick else SHAPES:
        rows += run(shape, 16 if quick else 64, 128 if quick else 256)
    for r in rows:
        r["cd_p2s_e3"] = r.pop("cd_p2s") * 1e3
    cols = ["shape", "depth_noise", "preset", "cd_p2s_e3", "faces", "time_s", "kept", "start_loss", "kept_loss"]
    fmt = {"cd_p2s_e3": ".3f", "time_s": ".0f", "start_loss": ".5f", "kept_loss": ".5f"}
    intro = __doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip() + "\n\nCD p2s in units of 1e-3."
    write_report(out, "refine", "Multi-view depth start against refine", intro,
                 markdown_table(rows, cols, fmt), rows)


if __name__ == "__main__":
    main()
