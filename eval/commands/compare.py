"""`dmesh compare MESH`: reconstruct the user's mesh with several methods and compare them.

The mesh is loaded and normalised (vertex mean 0, max vertex norm 1); a 100K-point cloud with normals (and
a 64-view capture when a multi-view method is asked) is taken from it; each method runs as one run of a
one-shape sweep (cached under DIR/.work, so rerunning with more methods only runs the new ones). Prints a
table and writes DIR/report.md, DIR/results.csv and DIR/renders_<input>.png.

The mesh is the ground truth: an inside-out closed mesh is flipped outward before anything is sampled or
rendered from it (`datasets.meshes.orient_outward`), and the report says so. Beside CD, faces and time the
report lists each output's mesh quality (orientation against the GT, watertightness, non-manifold edges and
vertices, components and genus against the GT's, self-intersections).
"""
from __future__ import annotations

from pathlib import Path

NAME = "compare"
HELP = "run several methods on your mesh's point cloud / views and write a small comparison report"


def add_arguments(p) -> None:
    p.add_argument("mesh", help="mesh file (OBJ, PLY, OFF, STL, GLB)")
    p.add_argument("--methods", nargs="+", metavar="METHOD",
                   help="registered method names (default: every registered point-cloud baseline)")
    p.add_argument("-o", "--out", default="compare", help="report folder (default: compare)")
    p.add_argument("--points", type=int, default=100_000, help="point-cloud samples (default: 100000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=1, help="concurrent runs (default: 1)")
    p.add_argument("--timeout", type=float, default=1800.0, help="per-run limit in seconds (default: 1800)")
    p.add_argument("--set", action="append", default=[], metavar="METHOD.KEY=VALUE", dest="sets",
                   help="override a method's config, e.g. psr.depth=7; repeatable")
    p.add_argument("--preprocess", nargs="+", metavar="SPEC", default=["none"],
                   help="pre-processing of every point-cloud method's input, one row per method and spec: none, or "
                        "stages joined by '+' (outliers[=STD], smooth[=K], autosmooth[=K]), e.g. --preprocess none "
                        "outliers+smooth (default: none; docs/preprocessing.md)")


def run(args) -> int:
    from baselines import registry

    from eval.cli import check_output_dir
    from eval.commands.bench import check_work
    from eval.reports import tables
    from eval.reports.figures import render_figures
    from eval.runner import RunnerConfig, run_sweep
    from eval.store import Store
    from eval.shapes import MESH_SUFFIXES
    from eval.sweep import Sweep, get_method
    from eval.values import check_points, check_seed

    mesh_path = Path(args.mesh)
    if mesh_path.is_dir():
        raise ValueError(f"mesh {mesh_path}: is a folder, not a mesh file")
    if not mesh_path.is_file():
        raise FileNotFoundError(f"mesh {mesh_path} not found")
    if not mesh_path.name.lower().endswith(MESH_SUFFIXES):
        raise ValueError(f"mesh {mesh_path}: unsupported file type; expected one of {', '.join(MESH_SUFFIXES)}")
    check_points("--points", args.points)
    check_seed("--seed", args.seed)
    from eval.preprocess import parse_spec

    for spec in args.preprocess:
        parse_spec(spec, "--preprocess")
    out = check_output_dir(args.out, "-o")
    work = out / ".work"
    check_work(work, work / "results.sqlite")
    if args.methods:
        methods = [get_method(m) for m in args.methods]
    else:
        methods = [m for n, m in sorted(registry.METHODS.items())
                   if m.input_kind == "pointcloud" and not n.startswith("dmesh")]
    # Reading the mesh first: an unreadable or empty file fails here, before DIR is created.
    from datasets.meshes import load_mesh

    try:
        mesh = load_mesh(mesh_path)
    except (ValueError, OSError) as exc:
        raise ValueError(f"mesh {mesh_path} cannot be read: {' '.join(str(exc).split())}") from None
    if len(mesh.faces) == 0:
        raise ValueError(f"mesh {mesh_path} has no faces")
    from datasets.meshes import orient_outward

    mesh, _ = orient_outward(mesh, name=str(mesh_path), quiet=True)  # the sweep's prepare_gt logs it
    kinds = tuple(k for k in ("pointcloud", "multiview") if any(m.input_kind == k for m in methods))
    sweep = Sweep(name=f"compare {mesh_path.name}", methods=tuple(m.name for m in methods),
                  shapes=(str(mesh_path.resolve()),), inputs=kinds, seeds=(args.seed,), n_points=args.points,
                  timeout_s=args.timeout, preprocess=tuple(args.preprocess)).with_overrides(args.sets)
    runner = RunnerConfig(work=str(work), jobs=args.jobs)
    summary = run_sweep(sweep, runner)
    keys = set(summary.keys)
    with Store(runner.db_path) as store:
        df = store.dataframe()
    df = df[df["key"].isin(keys)]
    rows = []
    for _, d in df.sort_values(["input_kind", "method", "config_label"]).iterrows():
        rows.append({"method": tables.method_label(d["method"], d["config_label"], d["input_kind"]),
                     "input": d["input_kind"],
                     "status": d["status"], "cd_p2s": tables.num(d.get("cd_p2s")),
                     "cd_l1": tables.num(d.get("cd_l1")), "faces": tables.num(d.get("faces")),
                     "time_s": tables.num(d.get("time_s")), "peak_memory_mb": tables.num(d.get("peak_memory_mb")),
                     "error": d.get("error") or "", **(tables.quality_row(d) if d["status"] == "done" else {})})
    cols = [("method", "method", None), ("input", "input", None), ("status", "status", None),
            ("cd_p2s", "CD p2s (x1e-3)", 1e3), ("cd_l1", "CD L1 (x1e-3)", 1e3), ("faces", "faces", 1),
            ("time_s", "time (s)", 1), ("peak_memory_mb", "peak MiB", 1), ("error", "error", None)]
    quality_cols = [("method", "method", None), ("input", "input", None)] + tables.QUALITY_RUN_COLUMNS
    csv_cols = [c for c, _, _ in cols] + ["nc_oriented", "oriented_fraction", "oriented_fraction_any_side",
                                          "watertight", "boundary_edges", "non_manifold_edges",
                                          "non_manifold_vertices", "components",
                                          "gt_components", "genus", "gt_genus", "self_intersecting_faces"]
    figs = render_figures(df, runner.db_path, work, out)
    category = df["category"].iloc[0] if len(df) else "unknown"
    md = [f"# Comparison on {mesh_path.name} ({category})", "",
          f"{tables.FRAME_NOTE} Point cloud: {args.points} area-uniform samples with normals, seed {args.seed}"
          + ("." if sweep.preprocess == ("none",) else f"; pre-processing (every point-cloud method alike, the "
             f"row's +tag): {', '.join(sweep.preprocess)}."),
          "", _gt_line(mesh), "", tables.CD_NOTE, "", tables.markdown(rows, cols), "",
          "## Mesh quality", "", tables.QUALITY_NOTE, "",
          tables.markdown([r for r in rows if r["status"] == "done"], quality_cols), ""]
    md += [f"![{cap}]({p.name})\n" for cap, p in figs]
    md += ["_Generated by `dmesh compare` from the results store in `.work/`._", ""]
    from eval.io import write_text

    write_text(out / "report.md", "\n".join(md))
    write_text(out / "results.csv", tables.to_csv(rows, csv_cols))
    print(_gt_line(mesh).replace("*", ""))
    w = max(8, max((len(r["method"]) for r in rows), default=8))
    print(f"{'method':<{w}}  {'input':<10} {'status':<6} {'CD p2s':>9} {'CD L1':>9} {'faces':>8} {'time s':>8} "
          f"{'orient %':>8} {'watertight':>10} {'NM edges':>8}")
    for r in rows:
        def c(v, s=1.0):
            return tables.fmt(v * s) if v is not None else "-"
        print(f"{r['method']:<{w}}  {r['input']:<10} {r['status']:<6} {c(r['cd_p2s'], 1e3):>9} {c(r['cd_l1'], 1e3):>9} "
              f"{c(r['faces']):>8} {c(r['time_s']):>8} {c(r.get('oriented_fraction'), 100):>8} "
              f"{r.get('watertight_text') or '-':>10} {c(r.get('non_manifold_edges')):>8}"
              + (f"  {r['error']}" if r["error"] else ""))
    print(f"CD x1e-3 in the normalised frame (max |v| = 1). Wrote {out / 'report.md'}")
    return 0


def _gt_line(mesh) -> str:
    """One sentence on the GT's orientation and topology for the report (mesh: the loaded, oriented GT)."""
    from eval.metrics import topology

    status = mesh.metadata.get("orientation", "")
    say = {"outward": "closed and facing outward", "open": "orientable, with open parts (kept as wound)",
           "flipped": "closed and inside-out in the file: flipped outward before sampling and rendering",
           "inconsistent": "inconsistently wound: cannot be oriented, so the oriented figures are blank",
           "non_orientable": "non-orientable: only the unsigned normal consistency applies, the oriented "
                             "figures are blank"}.get(status, status)
    t = topology(mesh.vertices, mesh.faces)
    genus = "-" if t["genus"] is None else t["genus"]
    return (f"*GT orientation:* {say}. *GT topology:* {'watertight' if t['watertight'] else 'not watertight'}, "
            f"{t['components']} component(s), genus {genus}, {t['boundary_edges']} boundary edges, "
            f"{t['non_manifold_edges']} non-manifold edges.")
