"""The sections of a report folder: each function writes one report's files and returns its section of index.html.

Every section function returns (written paths, heading, HTML body), or None for a section left out. Its tables
are rendered to HTML from the same rows and columns as its Markdown file (`eval.reports.render`), so index.html
shows what the Markdown reports say. `eval.reports.write_reports` calls them in order and writes index.html
(`eval.reports.html.write_index`).
"""
from __future__ import annotations

import html as _html
from pathlib import Path

from eval.reports import figures, tables
from eval.reports.render import table_html

#: The input kinds with a Table 2 section.
INPUT_KINDS = ("pointcloud", "multiview")
#: Label of each input kind in headings and captions.
KIND_LABELS = {"pointcloud": "point cloud", "multiview": "multi-view"}
#: The columns of the index's "Failed runs" table.
FAILED_COLUMNS = [("method", "method", None), ("shape", "shape", None), ("seed", "seed", 1), ("error", "error", None)]


def _links(*paths: Path, names: tuple[str, ...] = ("Markdown", "CSV")) -> str:
    return "<p class='links'>" + " ".join(f"<a href='{p.name}'>{n}</a>" for p, n in zip(paths, names)) + "</p>"


def first_setting(df, key):
    """The value of input setting `key` in the first run of `df` that has it, else None."""
    if df is None or not len(df) or "inputs_json" not in df.columns:
        return None
    for v in df["inputs_json"]:
        if isinstance(v, dict) and key in v:
            return v[key]
    return None


def append_markdown(path: Path, text: str) -> None:
    """Appends `text` as a section of the Markdown report `path` (rewritten atomically)."""
    if not text:
        return
    from eval.io import atomic_path

    body = path.read_text()
    with atomic_path(path) as tmp:
        Path(tmp).write_text(body.rstrip("\n") + "\n\n\n" + text)


def table2_section(df, kind: str, out: Path) -> tuple[list[Path], str, str]:
    """Table 2 of input `kind` (`eval.reports.tables.write_table2`), its recipes and DMesh curves appended to
    its Markdown, and on index.html: the table, bar plots, curves, recipes, provenance and failed runs."""
    from eval.reports.curves import curve_figure, curve_runs
    from eval.reports.provenance import PROVENANCE_COLUMNS, PROVENANCE_NOTE, provenance_rows
    from eval.reports.recipes import RECIPE_COLUMNS, recipe_markdown, recipe_rows

    figdir = out / "figures"
    sub = df[df["input_kind"] == kind] if len(df) else df
    n_samples = first_setting(sub, "metric_samples")
    md, csv = tables.write_table2(df, out, kind, n_samples)
    written = [md, csv]
    recipes = recipe_rows(df, kind)
    append_markdown(md, recipe_markdown(recipes))
    rows = tables.table2(df, kind)
    label = KIND_LABELS[kind]
    body = [_links(md, csv, names=("Markdown", "CSV (raw units)")),
            f"<p class='note'>{_html.escape(tables.FRAME_NOTE)} {_html.escape(tables.CD_SHORT_NOTE)} CD values x1e-3; "
            "means over successful runs "
            f"(n) with failures counted; metric samples per side N = {n_samples or 'n/a'}. "
            f"Shaded columns: the paper's published numbers (its own shapes and GPU), for reference.</p>"]
    if not rows:
        body.append(f"<p>No {label} runs in the store yet.</p>")
        return written, f"Table 2: {label} input", "\n".join(body)
    body.append(table_html(rows, tables.table2_columns(rows)))
    bars = figures.bar_plots(rows, figdir / f"bars_{kind}.png", f"Table 2, {label} input: CD and time by class")
    if bars:
        written.append(bars)
        body.append(f"<img src='figures/{bars.name}' alt='bar plots {label}'>")
    curves = curve_figure(curve_runs(df, kind), figdir / f"curves_{kind}.png",
                          f"DMesh runs with gradient steps, {label} input: CD p2s and loss against the step")
    if curves:
        written.append(curves)
        append_markdown(md, "## DMesh curves\n\nCD p2s (the harness monitor, 20K samples per side) and "
                            "loss against the step, one shape per class and configuration:\n\n"
                            f"![curves](figures/{curves.name})\n")
        body.append(f"<img src='figures/{curves.name}' alt='curves {label}'>")
    if recipes:
        body.append("<h3>DMesh recipes</h3>" + table_html(recipes, RECIPE_COLUMNS))
    origin = provenance_rows(df, kind)
    if any(r["earlier_code"] or r["earlier_metrics"] for r in origin):
        body.append("<h3>Provenance</h3>" + f"<p class='note'>{_html.escape(PROVENANCE_NOTE)}</p>"
                    + table_html(origin, PROVENANCE_COLUMNS))
    failures = sub[sub["status"] == "failed"] if len(sub) else sub
    if len(failures):
        frows = [{"method": tables.method_label(r["method"], r["config_label"]), "shape": r["shape"],
                  "seed": int(r["seed"]), "error": tables.text(r["error"])} for _, r in failures.iterrows()]
        body.append("<h3>Failed runs</h3>" + table_html(frows, FAILED_COLUMNS))
    return written, f"Table 2: {label} input", "\n".join(body)


def table1_section(df, out: Path) -> tuple[list[Path], str, str]:
    """Table 1 (`eval.reports.tables.write_table1`): RE / FP of the mesh-to-DMesh runs."""
    md1, csv1 = tables.write_table1(df, out)
    t1 = tables.table1(df)
    body = [_links(md1, csv1)]
    if t1:
        body.append(table_html(t1, tables.TABLE1_COLUMNS))
    else:
        body.append("<p>No mesh-to-DMesh runs in the store yet (the paper's Table 1 is in the Markdown file).</p>")
    return [md1, csv1], "Table 1: mesh to DMesh (RE / FP)", "\n".join(body)


def ablation_section(df_all, out: Path) -> tuple[list[Path], str, str]:
    """The regulariser ablations (`eval.reports.ablation`), one table per knob."""
    from eval.reports import ablation

    files = ablation.write_ablations(df_all, out)
    body = [f"<p class='links'>{' '.join(f'<a href={chr(39)}{p.name}{chr(39)}>{p.name}</a>' for p in files)}</p>"]
    for knob in ablation.KNOBS:
        rows = ablation.ablation_rows(df_all, knob)
        if rows:
            body.append(table_html(ablation.shown_rows(rows), ablation.columns(knob)))
    return files, "Ablations: weight and quality regularisers (paper Tables 4 and 5)", "\n".join(body)


def size_section(df_all, out: Path) -> tuple[list[Path], str, str]:
    """DMesh's gradient steps at equal mesh size (`eval.reports.size`), on clean inputs."""
    from eval.reports.robustness import is_robustness
    from eval.reports.size import write_size

    files = write_size(df_all[~is_robustness(df_all)] if len(df_all) else df_all, out)
    body = [_links(files[0], files[1])]
    body += [f"<img src='figures/{p.name}' alt='CD against faces'>" for p in files[2:]]
    return files, "DMesh's gradient steps at equal mesh size (point clouds)", "\n".join(body)


def compact_section(df_all, out: Path) -> tuple[list[Path], str, str]:
    """Matched budgets (`eval.reports.compact`), on clean inputs."""
    from eval.reports.compact import write_compact
    from eval.reports.robustness import is_robustness

    files = write_compact(df_all[~is_robustness(df_all)] if len(df_all) else df_all, out)
    body = [_links(files[0], files[1])]
    body += [f"<img src='figures/{p.name}' alt='CD against faces at matched budgets'>" for p in files[2:]]
    return files, "Matched budgets: DMesh compact against reconstruct-then-decimate (point clouds)", "\n".join(body)


def mv_settings_section(df_all, out: Path) -> tuple[list[Path], str, str] | None:
    """The multi-view fast preset's settings study (`eval.reports.mv_settings`), when it has runs."""
    from eval.reports.mv_settings import write_mv_settings
    from eval.reports.robustness import is_robustness

    files = write_mv_settings(df_all[~is_robustness(df_all)] if len(df_all) else df_all, out)
    if not files:
        return None
    return files, "The multi-view fast preset's settings, run by run", _links(files[0], files[1])


def robustness_section(df_all, out: Path, db: Path, work: Path, renders: bool) -> tuple[list[Path], str, str] | None:
    """The robustness report (`eval.reports.robustness`), when some run had a corrupted input."""
    from eval.reports.robustness import has_runs, write_robustness

    if not has_runs(df_all):
        return None
    files, body = write_robustness(df_all, out, db, work, renders=renders)
    return files, "Robustness: corrupted inputs, simulated scans, matched budgets", body


def checks_section(df_all, out: Path) -> tuple[list[Path], str, str]:
    """The runs whose final mesh is further from the GT than their last monitored one (`eval.reports.checks`)."""
    from eval.reports.checks import COLUMNS, GAP_RATIO, gap_rows, summary, write_checks

    gaps, ratios = gap_rows(df_all)
    files = write_checks(gaps, ratios, out)
    body = [_links(files[0], files[1]),
            f"<p class='note'>Runs with a monitored curve: {len(ratios)}; final CD p2s over {GAP_RATIO:g}x the last "
            f"monitored one: {len(gaps)}.{_html.escape(summary(ratios))} CD p2s x1e-3.</p>"]
    if gaps:
        body.append(table_html(gaps, COLUMNS))
    return files, "Checks: final mesh against the last monitored mesh", "\n".join(body)


def renders_section(df, db: Path, work: Path, figdir: Path, progress=None) -> tuple[list[Path], str, str] | None:
    """Side-by-side renders of the GT, the input and each method's mesh (`eval.reports.figures.render_figures`)."""
    figs = figures.render_figures(df, db, work, figdir, progress=progress)
    if not figs:
        return None
    body = "\n".join(f"<h3>{_html.escape(cap)}</h3><img src='figures/{p.name}' alt='{_html.escape(cap)}'>"
                     for cap, p in figs)
    return [p for _, p in figs], "Renders: GT, input and each method", body
