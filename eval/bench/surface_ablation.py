"""Ablation of the surface step: every stage of `dmesh.surface.STAGES` that may be skipped, left out in turn.

Why: each stage of the surface step must earn its place (issue 59). The variants are generated from the stage
list, so a new stage is in the next ablation without an edit here: `all` (every stage, the default settings),
one `-STAGE` variant per stage `STAGES` does not mark required, and the three modes of `SurfaceConfig.mode`
(`mode=closed`, `mode=open`; `all` is `auto`).

Protocol: point-cloud input as Table 2's (`eval/sweeps/paper.yaml` on the dev split, `test.yaml` on the test
split: 100K samples with normals from the harness's input cache, `--work`), or with `--input scan` the
robustness sweeps' noise-free 6-camera scan of the same shapes (occlusion holes and unseen stretches, where the
hole-closing stages act; rows under split "dev scan"), with `--input noisy_scan` its realistic scan and with
`--input outliers` the cloud with 5 % outliers (where the debris stages act), DMesh's `fast` preset as the harness runs it (no private
filter), reconstructed once per shape and seed; the surface step then runs every variant on the same final
triangulation (`dmesh.surface.replay.run_variants`: the stages before the one a variant leaves out run once for
all variants, each variant's mesh is the step's own for its config, and its seconds are its own stages').
Figures per variant, in the GT frame (mean 0, max vertex norm 1): CD p2s x1e-3 (`eval.metrics.chamfer_l1_p2s`,
`--metric-samples` per side, 20K by default: a comparison of variants, not a table figure), boundary edges,
boundary length (a count depends on the resolution; the length does not), components and watertightness counted
with vertices merged by position (`eval.metrics.mesh_stats`), faces and the step's seconds.

Rows are appended to `OUT/bench_surface_ablation_runs.csv` as each (shape, seed) finishes, so a stopped run resumes
where it stopped; the Markdown report is rewritten from the CSV each time.

Run: `python -m eval.bench surface_ablation --split dev --seeds 0 1 2` (then `--split test`).
"""
from __future__ import annotations

import argparse
import csv
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

COLUMNS = ("split", "class", "shape", "seed", "variant", "cd_p2s", "boundary_edges", "boundary_length",
           "gt_boundary_length", "components", "gt_components", "watertight", "faces", "seconds")


def variants(only: list[str] | None = None) -> list[tuple[str, dict]]:
    """(name, `SurfaceConfig.with_overrides` mapping) of every variant, generated from `dmesh.surface.STAGES`;
    `only`: those named (and `all`, which every ratio needs), a stage's name standing for its `-STAGE` variant."""
    from dmesh.surface import STAGES

    out = [("all", {})]
    out += [(f"-{s.name}", {"skip": [s.name]}) for s in STAGES if not s.required]
    out += [("mode=closed", {"mode": "closed"}), ("mode=open", {"mode": "open"})]
    if only:  # a stage's name stands for its `-STAGE` variant (argparse reads "-lids" as an option)
        only = [f"-{name}" if f"-{name}" in dict(out) else name for name in only]
        unknown = sorted(set(only) - {name for name, _ in out})
        if unknown:
            raise ValueError(f"unknown ablation variant(s) {', '.join(unknown)}")
        out = [(name, o) for name, o in out if name == "all" or name in only]
    return out


def _boundary(vertices: np.ndarray, faces: np.ndarray) -> tuple[int, float]:
    """Boundary edges (one face) and their total length, vertices merged by position."""
    if not len(faces):
        return 0, 0.0
    _, inverse = np.unique(np.round(vertices, 12), axis=0, return_inverse=True)
    f = inverse.reshape(-1)[faces]
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    unique, first, counts = np.unique(edges, axis=0, return_index=True, return_counts=True)
    rim = unique[counts == 1]
    v = np.zeros((inverse.max() + 1, 3))
    v[inverse.reshape(-1)] = vertices
    return int(len(rim)), float(np.linalg.norm(v[rim[:, 0]] - v[rim[:, 1]], axis=1).sum())


def _figures(mesh, gt, n: int, seed: int) -> dict:
    from eval.metrics import chamfer_l1_p2s, mesh_stats

    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    stats = mesh_stats(mesh, self_intersections=False)
    edges, length = _boundary(v, f)
    return {"cd_p2s": chamfer_l1_p2s(mesh, gt, n=n, seed=seed) * 1e3 if len(f) else float("inf"),
            "boundary_edges": edges, "boundary_length": round(length, 6), "components": stats.get("components"),
            "watertight": bool(stats.get("watertight")), "faces": int(len(f))}


#: Input variants: the clean cloud (Table 2's), the noise-free 6-camera scan of the robustness sweeps
#: (`eval/sweeps/robustness.yaml`: occlusion holes and unseen stretches, where lids, spans and fairing act), its
#: realistic scan (range noise, 1 % outliers, estimated normals: where stray pieces and crumbs appear) and the raw
#: cloud with 5 % outliers (DMesh's rows in the robustness tables filter nothing by themselves).
INPUTS = {"clean": {}, "scan": {"corruption": {"scan": 6}},
          "noisy_scan": {"corruption": {"scan": 6, "noise": 0.0025, "outliers": 0.01}},
          "outliers": {"corruption": {"outliers": 0.05}}}


def _state(shape: str, seed: int, work: Path, n_points: int, variant: dict | None = None):
    """The GT, the input and the final triangulation of DMesh `fast` (as the harness runs it) for one shape."""
    from baselines.dmesh_pointcloud import harness_config
    from dmesh.extract import mesh_faces
    from dmesh.recon.config import PointCloudConfig
    from dmesh.recon.pointcloud import reconstruct
    from eval.inputs import load_gt, prepare_gt, prepare_input
    from eval.shapes import resolve_shape

    ref, gt_path = prepare_gt(resolve_shape(shape), work)
    path = prepare_input(ref, gt_path, "pointcloud", {"radius": 1.0, "n_points": n_points, **(variant or {})}, seed,
                         work)
    data = np.load(path)
    points, normals = data["points"], data["normals"]
    cfg = harness_config(PointCloudConfig.fast(seed=seed))
    result = reconstruct(points, normals, cfg)
    pd = result.dmesh.power_diagram()
    walls = mesh_faces(pd, result.dmesh.reals.detach().numpy() > cfg.threshold, cfg.extraction)
    unit = (np.asarray(points, np.float64) - result.center) * result.scale
    return load_gt(gt_path), pd, walls, (unit, np.asarray(normals, np.float64)), result, cfg


def _run_shape(split: str, cls: str, shape: str, seed: int, work: Path, n: int, points: int,
               variant: dict | None = None, only: list[str] | None = None) -> list[dict]:
    import trimesh

    from dmesh.extract import to_trimesh
    from dmesh.surface.replay import run_variants

    gt, pd, walls, (unit, normals), result, cfg = _state(shape, seed, work, points, variant)
    gt_edges, gt_length = _boundary(np.asarray(gt.vertices), np.asarray(gt.faces))
    gt_components = int(len(trimesh.graph.connected_components(gt.face_adjacency, nodes=np.arange(len(gt.faces)))))
    # Every variant at once: the stages before the one a variant leaves out run once for all (each result is the
    # step's own for its config); a variant's seconds are its stages' own, shared ones included.
    configs = {name: cfg.surface.with_overrides(overrides) for name, overrides in variants(only)}
    surfaces = run_variants(pd, walls, (unit, normals), unit, configs)
    rows = []
    for name, surface in surfaces.items():
        seconds = sum(r["seconds"] for r in surface.info.get("stages", {}).values())
        mesh = to_trimesh(surface.positions, surface.faces)
        mesh.vertices = np.asarray(mesh.vertices) / result.scale + result.center
        rows.append({"split": split, "class": cls, "shape": shape, "seed": seed, "variant": name,
                     **_figures(mesh, gt, n, seed), "gt_boundary_length": round(gt_length, 6),
                     "gt_components": gt_components, "seconds": round(seconds, 2)})
        log.info("%s seed %d %s: CD p2s %.4f", shape, seed, name, rows[-1]["cd_p2s"])
    return rows


def _read(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def _write_csv(path: Path, rows: list[dict]) -> None:
    from eval.io import write_text
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS)
    writer.writeheader()
    writer.writerows({k: r.get(k, "") for k in COLUMNS} for r in rows)
    write_text(path, buf.getvalue())


def summary(rows: list[dict]) -> list[dict]:
    """Per split, class and variant: means over shape-seed runs, and each against `all` on the same runs."""
    from collections import defaultdict

    by = defaultdict(list)
    for r in rows:
        by[(r["split"], r["class"], r["variant"])].append(r)
    base = {(r["split"], r["shape"], r["seed"]): r for r in rows if r["variant"] == "all"}
    order = {name: i for i, (name, _) in enumerate(variants())}
    classes = {"closed": 0, "open": 1, "mixed": 2}
    out = []
    for (split, cls, variant), group in sorted(by.items(), key=lambda item: (
            item[0][0], classes.get(item[0][1], 3), order.get(item[0][2], len(order)))):
        cd = [float(r["cd_p2s"]) for r in group]
        ratio = [float(r["cd_p2s"]) / max(float(base[(split, r["shape"], r["seed"])]["cd_p2s"]), 1e-12)
                 for r in group if (split, r["shape"], r["seed"]) in base]
        length = [float(r["boundary_length"]) / max(float(r["gt_boundary_length"]), 1e-12)
                  for r in group if float(r["gt_boundary_length"]) > 0]
        out.append({"split": split, "class": cls, "variant": variant, "n": len(group),
                    "cd_p2s": float(np.mean(cd)), "cd_vs_all": float(np.mean(ratio)) if ratio else float("nan"),
                    "worst_vs_all": float(np.max(ratio)) if ratio else float("nan"),
                    "boundary_edges": float(np.mean([float(r["boundary_edges"]) for r in group])),
                    "rim_vs_gt": float(np.mean(length)) if length else float("nan"),
                    "components": float(np.mean([float(r["components"]) for r in group])),
                    "watertight": sum(str(r["watertight"]) == "True" for r in group),
                    "seconds": float(np.mean([float(r["seconds"]) for r in group]))})
    return out


def write_report(rows: list[dict], out: Path) -> None:
    from eval.bench.common import markdown_table, write_report as write

    table = markdown_table(summary(rows), ["split", "class", "variant", "n", "cd_p2s", "cd_vs_all", "worst_vs_all",
                                           "boundary_edges", "rim_vs_gt", "components", "watertight", "seconds"],
                           {"cd_p2s": ".4f", "cd_vs_all": ".3f", "worst_vs_all": ".2f", "boundary_edges": ".0f",
                            "rim_vs_gt": ".2f", "components": ".1f", "seconds": ".1f"})
    intro = ("\n\n".join(__doc__.split("\n\n")[:3]) + "\n\n"
             "Columns: `cd_p2s` the class mean (x1e-3); `cd_vs_all` the mean over runs of the variant's CD p2s over "
            "the `all` variant's on the same run, `worst_vs_all` the largest; `rim_vs_gt` boundary length over the "
            "GT's (shapes with a boundary); `watertight` counts runs. A stage pays where leaving it out makes "
            "`cd_vs_all` > 1, the rim further from the GT's, or fewer runs watertight. A stage that no variant shows "
            "paying on the dev split, clean, scanned or with outliers, goes (issue 59): `folds` went this way (into "
            "`split_fans`), so its rows are of the code before. Every other stage pays on some dev input (the "
            "verdict per stage: docs/surface.md), but for two: `reopen` acts only on shapes with cut ends, which "
            "the dev split lacks (on the test split it pays most of all), and `revote` only on the coarse meshes "
            "of the gradient presets (`python -m studies revote`), which this ablation of `fast` does not run.")
    write(out, "bench_surface_ablation", "Surface step ablation", intro, table, summary(rows))


def main(out: str = "reports", quick: bool = False) -> int:
    """`python -m eval.bench surface_ablation`: both splits at 3 seeds (resumable); `--quick`: the torus at 20K
    input samples, seed 0, into `out` (a smoke run of every variant)."""
    if quick:
        return cli(["--split", "dev", "--shapes", "torus", "--points", "20000", "--out", str(out),
                    "--work", str(Path(out) / "work")])
    code = cli(["--split", "dev", "--seeds", "0", "1", "2", "--out", str(out)])
    return code or cli(["--split", "test", "--seeds", "0", "1", "2", "--out", str(out)])


def cli(argv=None) -> int:
    """`python -m eval.bench.surface_ablation [--split S] [--seeds ...] [--shapes ...]`: part of the ablation."""
    from datasets import splits

    p = argparse.ArgumentParser(prog="python -m eval.bench.surface_ablation", description=__doc__.split("\n")[0])
    p.add_argument("--split", choices=sorted(splits.SPLITS), default="dev")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--shapes", nargs="+", help="a subset of the split's shapes")
    p.add_argument("--work", default="runs/paper", help="the harness work folder whose input cache to use")
    p.add_argument("--metric-samples", type=int, default=20_000)
    p.add_argument("--points", type=int, default=100_000, help="input samples (Table 2: 100K)")
    p.add_argument("--input", choices=sorted(INPUTS), default="clean",
                   help="clean: Table 2's cloud; scan: the robustness sweeps' noise-free 6-camera scan (rows under "
                        "split 'SPLIT scan'); noisy_scan: its realistic scan; outliers: the clean cloud with 5 %% "
                        "outliers")
    p.add_argument("--variants", nargs="+", help="only these variants (and all): stage names for their -STAGE variants, e.g. crumbs mode=open")
    p.add_argument("--out", default="reports")
    args = p.parse_args(argv)
    label = args.split if args.input == "clean" else f"{args.split} {args.input}"
    try:
        variants(args.variants)
    except ValueError as exc:
        p.error(str(exc))
    out, work = Path(args.out), Path(args.work)
    path = out / "bench_surface_ablation_runs.csv"
    rows = _read(path)
    done = {(r["split"], r["shape"], str(r["seed"])) for r in rows}
    for shape in args.shapes or splits.shapes(args.split):
        cls = splits.SPLITS[args.split].get(shape) or splits.shape_class(shape)
        for seed in args.seeds:
            if (label, shape, str(seed)) in done:
                continue
            try:
                new = _run_shape(label, cls, shape, seed, work, args.metric_samples, args.points, INPUTS[args.input],
                                 args.variants)
            except Exception as exc:  # a failed shape is reported and the ablation goes on
                log.error("%s seed %d failed: %s", shape, seed, exc)
                continue
            rows += new
            _write_csv(path, rows)
            write_report(rows, out)
    if rows:
        write_report(rows, out)
    return 0


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    sys.exit(cli())
