"""Reports regenerated from the results store (never edited by hand).

`write_reports(db, out, work)` writes into `out`:

    table2_pointcloud.md/.csv, table2_multiview.md/.csv   CD and time by closed / open / mixed (paper's Table 2)
    table1.md/.csv                                        RE / FP of mesh-to-DMesh runs (paper's Table 1)
    ablation_weight.md/.csv, ablation_quality.md/.csv     regulariser ablations (paper's Tables 4 and 5)
    recipes_size.md/.csv, figures/recipes_size.png        the paper preset against the fast start at equal size
    compact.md/.csv, figures/compact.png                  matched budgets: DMesh compact against reconstruct +
                                                          decimate, with the GT-decimation floor
    multiview_fast.md/.csv                                the multi-view fast preset's settings study, per run
    figures/bars_<kind>.png                               per-class bar plots of CD and time
    figures/renders_<kind>_<shape>.png                    GT, input and each method's mesh side by side
    checks.md/.csv                                        runs whose final mesh is further from the GT than
                                                          their last monitored one (damage after the steps)
    index.html                                            links and shows all of the above

Modules: `tables` (aggregation, Markdown / CSV), `render` (the one table renderer, Markdown and HTML),
`sections` (each report's files and its section of the index), `figures` (renders, plots), `html` (the index
page), `paper_numbers` (the paper's published Tables 1 and 2).
"""
from __future__ import annotations

import html as _html
import logging
from pathlib import Path

log = logging.getLogger(__name__)


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
                  renders: bool = True, progress=None, keys=None, source: str | None = None) -> list[Path]:
    """Regenerates every report file under `out` from the store `db`; returns the written paths.

    Args:
        db: SQLite results store.
        out: report folder (created).
        work: the sweep's work folder (input cache, used for GT / input renders); default: the store's folder.
        title: heading of index.html.
        renders: False skips the pyrender figures (tables and bar plots only).
        keys: report only these run keys (e.g. a sweep's); None: the latest run of each configuration.
        source: what index.html names as the runs' source (default: `db`'s path).
    Raises:
        FileNotFoundError: `db` does not exist.
    """
    from eval.reports import sections
    from eval.reports.ablation import is_ablation
    from eval.reports.compact import is_compact
    from eval.reports.html import write_index
    from eval.reports.mv_settings import is_mv_settings_study
    from eval.reports.robustness import is_robustness
    from eval.reports.size import is_size_study
    from eval.store import Store

    db = Path(db)
    if not db.is_file():
        raise FileNotFoundError(f"results store {db} not found")
    out = Path(out)
    work = Path(work) if work else db.parent
    with Store(db) as store:
        df_all = select_runs(store.dataframe(), keys)
    # Table 2 compares methods at their sweep settings; the regulariser ablations, the DMesh size study, the
    # multi-view settings study, the matched budgets and the runs on corrupted inputs (robustness sweeps) get
    # their own tables.
    df = (df_all[~is_ablation(df_all) & ~is_size_study(df_all) & ~is_mv_settings_study(df_all)
                 & ~is_compact(df_all) & ~is_robustness(df_all)] if len(df_all) else df_all)
    counts = df["status"].value_counts().to_dict() if len(df) else {}
    done = [sections.table2_section(df, kind, out) for kind in sections.INPUT_KINDS]
    done += [sections.table1_section(df, out), sections.ablation_section(df_all, out),
             sections.size_section(df_all, out), sections.compact_section(df_all, out),
             sections.mv_settings_section(df_all, out),
             sections.robustness_section(df_all, out, db, work, renders), sections.checks_section(df_all, out)]
    if renders and len(df):
        done.append(sections.renders_section(df, db, work, out / "figures", progress=progress))
    written = [p for section in done if section for p in section[0]]
    # The time of the newest run, not of this pass: the same runs give the same page (a report-only pass on a
    # fresh clone reproduces the committed one).
    finished = df_all["finished_at"].dropna() if "finished_at" in df_all else []
    stamp = (str(max(finished))[:16].replace("T", " ") + " UTC") if len(finished) else "no runs"
    meta = (f"Runs up to {stamp}, from <code>{_html.escape(source or str(db))}</code>: "
            + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) + " runs.")
    written.append(write_index(out, [s[1:] for s in done if s], title, meta))
    return written
