"""Reports regenerated from the results store (never edited by hand).

`write_reports(db, out, work)` writes into `out`:

    table2_pointcloud.md/.csv, table2_multiview.md/.csv   CD and time by closed / open / mixed (paper's Table 2)
    table1.md/.csv                                        RE / FP of mesh-to-DMesh runs (paper's Table 1)
    ablation_weight.md/.csv, ablation_quality.md/.csv     regulariser ablations (paper's Tables 4 and 5)
    recipes_size.md/.csv, figures/recipes_size.png        the paper preset against the fast start at equal size
    multiview_fast.md/.csv                                the multi-view fast preset's settings study, per run
    figures/bars_<kind>.png                               per-class bar plots of CD and time
    figures/renders_<kind>_<shape>.png                    GT, input and each method's mesh side by side
    checks.md/.csv                                        runs whose final mesh is further from the GT than
                                                          their last monitored one (damage after the steps)
    index.html                                            links and shows all of the above

Modules: `tables` (aggregation, Markdown / CSV), `figures` (renders, plots), `html` (the index page),
`paper_numbers` (the paper's published Tables 1 and 2).
"""
from __future__ import annotations

import html as _html
import logging
from datetime import datetime, timezone
from pathlib import Path

log = logging.getLogger(__name__)

INPUT_KINDS = ("pointcloud", "multiview")


def select_runs(df, keys=None):
    """The runs a report shows: those with `keys` when given (a sweep's runs), else the latest finished run
    (done or failed; else the latest run) of every (method, config, shape, input kind, input settings, seed),
    so results of older code versions that remain in the store are not averaged in, and a rerun still in
    progress (or killed) does not hide a finished one."""
    if df is None or not len(df):
        return df
    if keys is not None:
        return df[df["key"].isin(set(keys))]
    import json

    ident = df.apply(lambda r: json.dumps([r["method"], r["config_label"], r["shape"], r["input_kind"],
                                           r["inputs_json"], int(r["seed"])], sort_keys=True, default=str), axis=1)
    finished = df["status"].isin(["done", "failed"])
    order = df.assign(_ident=ident, _finished=finished).sort_values(["_finished", "started_at"],
                                                                     na_position="first", kind="stable")
    return order.drop_duplicates("_ident", keep="last").drop(columns=["_ident", "_finished"]).sort_index()


def write_reports(db: str | Path, out: str | Path, work: str | Path | None = None, title: str = "DMesh harness report",
                  renders: bool = True, progress=None, keys=None) -> list[Path]:
    """Regenerates every report file under `out` from the store `db`; returns the written paths.

    Args:
        db: SQLite results store.
        out: report folder (created).
        work: the sweep's work folder (input cache, used for GT / input renders); default: the store's folder.
        title: heading of index.html.
        renders: False skips the pyrender figures (tables and bar plots only).
        keys: report only these run keys (e.g. a sweep's); None: the latest run of each configuration.
    Raises:
        FileNotFoundError: `db` does not exist.
    """
    from eval.reports import figures, tables
    from eval.reports.html import table_html, write_index
    from eval.reports.curves import curve_figure, curve_runs
    from eval.reports.recipes import recipe_markdown, recipe_rows
    from eval.store import Store

    db = Path(db)
    if not db.is_file():
        raise FileNotFoundError(f"results store {db} not found")
    out = Path(out)
    work = Path(work) if work else db.parent
    with Store(db) as store:
        df_all = select_runs(store.dataframe(), keys)
    from eval.reports.ablation import KNOBS, ablation_rows, is_ablation, write_ablations
    from eval.reports.robustness import has_runs, is_robustness, write_robustness
    from eval.reports.mv_settings import is_mv_settings_study, write_mv_settings
    from eval.reports.size import is_size_study, write_size

    # Table 2 compares methods at their sweep settings; the regulariser ablations, the DMesh size study, the
    # multi-view settings study and the runs on corrupted inputs (robustness sweeps) get their own tables.
    df = (df_all[~is_ablation(df_all) & ~is_size_study(df_all) & ~is_mv_settings_study(df_all)
                 & ~is_robustness(df_all)] if len(df_all) else df_all)
    counts = df["status"].value_counts().to_dict() if len(df) else {}
    written: list[Path] = []
    sections: list[tuple[str, str]] = []
    figdir = out / "figures"
    for kind in INPUT_KINDS:
        sub = df[df["input_kind"] == kind] if len(df) else df
        n_samples = _first_setting(sub, "metric_samples")
        md, csv = tables.write_table2(df, out, kind, n_samples)
        written += [md, csv]
        recipes = recipe_rows(df, kind)
        _append_markdown(md, recipe_markdown(recipes))
        rows = tables.table2(df, kind)
        label = {"pointcloud": "point cloud", "multiview": "multi-view"}[kind]
        body = [f"<p class='links'><a href='{md.name}'>Markdown</a> <a href='{csv.name}'>CSV (raw units)</a></p>",
                f"<p class='note'>{_html.escape(tables.FRAME_NOTE)} CD values x1e-3; means over successful runs "
                f"(n) with failures counted; metric samples per side N = {n_samples or 'n/a'}. "
                f"Shaded columns: the paper's published numbers (its own shapes and GPU), for reference.</p>"]
        if rows:
            cols = [("method", "method", None), ("category", "class", None), ("split", "split", None),
                    ("n", "n", 1), ("failed", "failed", 1), ("cd_p2s", "CD p2s (x1e-3)", 1e3),
                    ("cd_p2s_sd", "sd", 1e3), ("cd_l1", "CD L1 (x1e-3)", 1e3), ("time_s", "time (s)", 1)]
            if any(r.get("cpu_s") is not None for r in rows):
                cols.append(("cpu_s", "CPU (s)", 1))
            if any("fscore" in r for r in rows):
                cols.append(("fscore", "F-score", 1))
            if any("normal_consistency" in r for r in rows):
                cols.append(("normal_consistency", "NC", 1))
            cols += [("paper_cd_l1", "paper CD (x1e-3)", 1e3, ".2f"), ("paper_time_s", "paper time (s)", 1, ".2f")]
            body.append(table_html(rows, cols, paper_cols=("paper_cd_l1", "paper_time_s")))
            bars = figures.bar_plots(rows, figdir / f"bars_{kind}.png", f"Table 2, {label} input: CD and time by class")
            if bars:
                written.append(bars)
                body.append(f"<img src='figures/{bars.name}' alt='bar plots {label}'>")
            curves = curve_figure(curve_runs(df, kind), figdir / f"curves_{kind}.png",
                                  f"DMesh runs with gradient steps, {label} input: CD p2s and loss against the step")
            if curves:
                written.append(curves)
                _append_markdown(md, "## DMesh curves\n\nCD p2s (the harness monitor, 20K samples per side) and "
                                     "loss against the step, one shape per class and configuration:\n\n"
                                     f"![curves](figures/{curves.name})\n")
                body.append(f"<img src='figures/{curves.name}' alt='curves {label}'>")
            if recipes:
                body.append("<h3>DMesh recipes</h3>" + table_html(
                    recipes, [("method", "row", None), ("kind", "made by", None), ("recipe", "recipe", None)]))
            from eval.reports.provenance import PROVENANCE_NOTE, provenance_rows

            origin = provenance_rows(df, kind)
            if any(r["earlier_code"] or r["earlier_metrics"] for r in origin):
                body.append("<h3>Provenance</h3>" + f"<p class='note'>{_html.escape(PROVENANCE_NOTE)}</p>" + table_html(
                    origin, [("method", "method", None), ("runs", "runs", 1), ("earlier_code", "earlier code", 1),
                             ("earlier_metrics", "earlier metrics", 1)]))
            failures = sub[sub["status"] == "failed"] if len(sub) else sub
            if len(failures):
                frows = [{"method": tables.method_label(r["method"], r["config_label"]), "shape": r["shape"],
                          "seed": int(r["seed"]), "error": tables.text(r["error"])} for _, r in failures.iterrows()]
                fcols = [("method", "method", None), ("shape", "shape", None), ("seed", "seed", 1),
                         ("error", "error", None)]
                body.append("<h3>Failed runs</h3>" + table_html(frows, fcols))
        else:
            body.append(f"<p>No {label} runs in the store yet.</p>")
        sections.append((f"Table 2: {label} input", "\n".join(body)))

    md1, csv1 = tables.write_table1(df, out)
    written += [md1, csv1]
    t1 = tables.table1(df)
    body = [f"<p class='links'><a href='{md1.name}'>Markdown</a> <a href='{csv1.name}'>CSV</a></p>"]
    if t1:
        body.append(table_html(t1, [("shape", "shape", None), ("method", "method", None), ("RE", "RE (%)", 100, ".2f"),
                                    ("FP", "FP (%)", 100, ".2f"), ("steps", "steps", 1), ("time_s", "time (s)", 1),
                                    ("paper_RE", "paper RE (%)", 100, ".2f"), ("paper_FP", "paper FP (%)", 100, ".2f")],
                                paper_cols=("paper_RE", "paper_FP")))
    else:
        body.append("<p>No mesh-to-DMesh runs in the store yet (the paper's Table 1 is in the Markdown file).</p>")
    sections.append(("Table 1: mesh to DMesh (RE / FP)", "\n".join(body)))

    ablation_files = write_ablations(df_all, out)
    written += ablation_files
    body = [f"<p class='links'>{' '.join(f'<a href={chr(39)}{p.name}{chr(39)}>{p.name}</a>' for p in ablation_files)}"
            "</p>"]
    for knob in KNOBS:
        rows = ablation_rows(df_all, knob)
        if rows:
            body.append(table_html([{**r, "value": f"{r['value']:g}"} for r in rows],
                                   [("value", KNOBS[knob][0], None), ("n", "n", 1), ("cd_p2s", "CD p2s (x1e-3)", 1e3),
                                    ("faces", "faces", 1), ("aspect_ratio", "aspect ratio", 1),
                                    ("time_s", "time (s)", 1), ("paper_cd", "paper CD", 1, ".2f"),
                                    ("paper_faces", "paper faces", 1)],
                                   paper_cols=("paper_cd", "paper_faces")))
    sections.append(("Ablations: weight and quality regularisers (paper Tables 4 and 5)", "\n".join(body)))
    size_files = write_size(df_all[~is_robustness(df_all)] if len(df_all) else df_all, out)
    written += size_files
    body = [f"<p class='links'><a href='{size_files[0].name}'>Markdown</a> <a href='{size_files[1].name}'>CSV</a></p>"]
    body += [f"<img src='figures/{p.name}' alt='CD against faces'>" for p in size_files[2:]]
    sections.append(("DMesh's gradient steps at equal mesh size (point clouds)", "\n".join(body)))
    mv_files = write_mv_settings(df_all[~is_robustness(df_all)] if len(df_all) else df_all, out)
    if mv_files:
        written += mv_files
        sections.append(("The multi-view fast preset's settings, run by run",
                         f"<p class='links'><a href='{mv_files[0].name}'>Markdown</a> "
                         f"<a href='{mv_files[1].name}'>CSV</a></p>"))
    if has_runs(df_all):
        files, body = write_robustness(df_all, out, db, work, renders=renders)
        written += files
        sections.append(("Robustness: corrupted inputs, simulated scans, matched budgets", body))

    from eval.reports.checks import GAP_RATIO, gap_rows, summary, write_checks

    gaps, ratios = gap_rows(df_all)
    check_files = write_checks(gaps, ratios, out)
    written += check_files
    body = [f"<p class='links'><a href='{check_files[0].name}'>Markdown</a> "
            f"<a href='{check_files[1].name}'>CSV</a></p>",
            f"<p class='note'>Runs with a monitored curve: {len(ratios)}; final CD p2s over {GAP_RATIO:g}x the last "
            f"monitored one: {len(gaps)}.{_html.escape(summary(ratios))}</p>"]
    if gaps:
        body.append(table_html(gaps, [("method", "method", None), ("shape", "shape", None),
                                      ("input_kind", "input", None), ("monitor_cd_p2s", "monitor CD p2s (x1e-3)", 1e3),
                                      ("cd_p2s", "final CD p2s (x1e-3)", 1e3), ("ratio", "ratio", 1, ".2f"),
                                      ("earlier_code", "earlier code", None)]))
    sections.append(("Checks: final mesh against the last monitored mesh", "\n".join(body)))

    if renders and len(df):
        figs = render_figures(df, db, work, figdir, progress=progress)
        written += [p for _, p in figs]
        if figs:
            body = "\n".join(f"<h3>{_html.escape(cap)}</h3><img src='figures/{p.name}' alt='{_html.escape(cap)}'>"
                             for cap, p in figs)
            sections.append(("Renders: GT, input and each method", body))

    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    meta = (f"Generated {stamp} from <code>{_html.escape(str(db))}</code>: "
            + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) + " runs.")
    written.append(write_index(out, sections, title, meta))
    return written


def _first_setting(df, key):
    if df is None or not len(df) or "inputs_json" not in df.columns:
        return None
    for v in df["inputs_json"]:
        if isinstance(v, dict) and key in v:
            return v[key]
    return None


def render_figures(df, db: Path, work: Path, figdir: Path, progress=None) -> list[tuple[str, Path]]:
    """One side-by-side figure per (input kind, shape): GT, input, then each method's mesh with its CD."""
    from eval.reports import figures, tables
    from eval.runner import input_path, resolve_mesh_path, shape_dir
    from eval.shapes import ShapeRef

    if progress is None:
        from eval.progress import progress
    cache = work / "renders"
    out = []
    groups = list(df.groupby(["input_kind", "category", "shape"], sort=True))
    order = {"pointcloud": 0, "multiview": 1}
    groups.sort(key=lambda g: (order.get(g[0][0], 9), ("closed", "open", "mixed").index(g[0][1])
                               if g[0][1] in ("closed", "open", "mixed") else 9, g[0][2]))
    for (kind, category, shape), g in progress(groups, desc="renders", unit="figure", leave=False):
        try:
            first = g.sort_values("seed").iloc[0]
            settings = first["inputs_json"] if isinstance(first["inputs_json"], dict) else {}
            ref = ShapeRef(id=shape, kind="file", source="", gt_hash=first["gt_hash"] or "")
            radius = float(settings.get("radius", 1.0))
            gt = shape_dir(work, ref, radius) / "gt.ply"
            missing = not gt.is_file()  # GT or a done run's mesh absent (e.g. a clone with the store export only)
            panels = []
            panels.append(("ground truth", figures.cached_render(gt, cache) if gt.is_file()
                           else figures._placeholder("GT missing")))
            if kind == "pointcloud" and "n_points" in settings:
                p = input_path(work, ref, kind, settings, int(first["seed"]))
                if p.is_file():
                    panels.append((f"input: {settings['n_points']} points", figures.cached_render(p, cache, "points")))
            elif kind == "multiview" and "views" in settings:
                p = input_path(work, ref, kind, settings, int(first["seed"]))
                thumb = figures.multiview_thumbnail(p) if p.exists() else None
                if thumb is not None:
                    panels.append((f"input: {settings['views']} views (one shown)", thumb))
            seed0 = g[g["seed"] == first["seed"]]
            for _, r in seed0.sort_values(["method", "config_label"]).iterrows():
                label = tables.method_label(r["method"], r["config_label"], kind)
                mp = resolve_mesh_path(r.to_dict(), db)
                if r["status"] == "done" and mp is not None and mp.is_file():
                    cd = r.get("cd_p2s")
                    cap = f"{label}\nCD p2s {tables.fmt(float(cd) * 1e3)}e-3" if cd is not None and cd == cd else label
                    panels.append((cap, figures.cached_render(mp, cache)))
                else:
                    missing = missing or r["status"] == "done"
                    err = (tables.text(r.get("error")) or r["status"])[:34]
                    panels.append((f"{label}\n{r['status']}: {err}", figures._placeholder(r["status"])))
            name = f"renders_{kind}_{_safe(shape)}.png"
            title = f"{shape} ({category}), {kind} input, seed {int(first['seed'])}"
            if missing and (figdir / name).is_file():  # keep the figure drawn from the meshes, not placeholders
                out.append((title, figdir / name))
                continue
            out.append((title, figures.side_by_side(panels, figdir / name, title, cache=cache)))
        except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not lose the tables
            log.warning("renders for %s / %s skipped: %s", kind, shape, exc)
    return out


def _append_markdown(path: Path, text: str) -> None:
    """Appends `text` as a section of the Markdown report `path` (rewritten atomically)."""
    if not text:
        return
    from eval.io import atomic_path

    body = path.read_text()
    with atomic_path(path) as tmp:
        Path(tmp).write_text(body.rstrip("\n") + "\n\n\n" + text)


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_@." else "_" for c in name)
