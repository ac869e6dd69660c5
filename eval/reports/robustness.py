"""The robustness report: how each method's accuracy degrades on corrupted inputs, and accuracy at equal size.

Reads the runs of sweeps with input `variants` (`eval.sweep`; their input settings hold a "corruption" dict,
`datasets.corrupt`) and writes into the report folder:

    robustness.md / robustness.csv         one row per input kind, method, class, corruption and level: CD p2s,
                                           CD L1, time, faces, ... (means over the done runs, failures counted)
    robustness_budget.csv                  CD p2s against output faces (clean geometry, every config / density)
    figures/robustness_<kind>.png          CD p2s against level, one panel per class and corruption
    figures/robustness_budget_<kind>.png   matched budget: CD p2s against output face count, one panel per class
    figures/robustness_scan_<shape>.png    renders of the realistic-scan setting: GT, the scan, each method

A run's corruption and level: a variant with one setting (`{noise: 0.005}`) is that corruption at that
level; the clean variant (`{}`) is every corruption at its clean level (noise 0, outliers 0, density = the
sweep's n_points, ...); a variant with several settings is a combined setting, named "realistic_scan" when it
holds a scan, its level being the settings themselves. Corruption rows are shown for the method configs that
ran on some corrupted input; configs run only on clean inputs (the matched-budget sizes) appear in the
budget view. Frame and units as in Table 2: the GT normalised to max vertex norm 1, CD x1e-3 in Markdown, raw
distances in the CSV.

Beside this module (rows, ratios, the Markdown and CSV files): `eval.reports.corruptions` reads a run's corruption
and level, `eval.reports.robustness_figures` draws the figures.
"""
from __future__ import annotations

import html as _html
import logging
import re
from pathlib import Path

from eval.io import write_text
from eval.reports.corruptions import (CLASSES, FACTORS, corruption_of, fmt_level, has_runs,  # noqa: F401
                                      is_robustness, labelled, setting_label, severity)
from eval.reports.robustness_figures import budget_plot, line_plots, scan_renders

log = logging.getLogger(__name__)

CSV_COLUMNS = ["input", "split", "method", "category", "corruption", "level", "n", "failed", "cd_p2s", "cd_l1",
               "time_s",
               "faces", "components", "fscore", "normal_consistency", "setting"]
BUDGET_COLUMNS = ["input", "method", "category", "config", "density", "n", "faces", "cd_p2s", "time_s"]
_METRICS = (("cd_p2s", ("cd_p2s",)), ("cd_l1", ("cd_l1",)), ("time_s", ("time_s",)), ("faces", ("faces", "n_faces")),
            ("components", ("components",)), ("fscore", ("fscore", "f_score")),
            ("normal_consistency", ("normal_consistency", "nc")))


# --------------------------------------------------------------------------------------------------- rows


def _aggregate(g) -> dict:
    from eval.reports.tables import num

    done = g[g["status"] == "done"]
    row = {"n": int(len(done)), "failed": int((g["status"] == "failed").sum())}
    for col, names in _METRICS:
        name = next((n for n in names if n in done.columns), None)
        vals = [num(v) for v in done[name]] if name else []
        vals = [v for v in vals if v is not None]
        row[col] = sum(vals) / len(vals) if vals else None
    per_shape: dict[str, list[float]] = {}
    for shape, value in zip(done["shape"], done["cd_p2s"] if "cd_p2s" in done.columns else []):
        if num(value) is not None:
            per_shape.setdefault(shape, []).append(num(value))
    row["per_shape"] = {k: sum(v) / len(v) for k, v in per_shape.items()}  # for matched comparisons
    return row


def robustness_rows(df) -> list[dict]:
    """One row per input kind, method (+ config), class, corruption and level (raw units; module docstring)."""
    if df is None or not len(df):
        return []
    from eval.reports.tables import split_column

    sub = labelled(df)
    sub["_split"] = split_column(sub)
    rows = []
    for (kind, split), gk in sub.groupby(["input_kind", "_split"], sort=True):
        corrupted = gk[gk["_name"] != "clean"]
        labels = sorted(set(corrupted["_label"]))
        names = [f for f in FACTORS if f in set(corrupted["_name"])]
        names += sorted(set(corrupted["_name"]) - set(FACTORS))
        for label in labels:
            gm = gk[gk["_label"] == label]
            for cat in [c for c in CLASSES if c in set(gm["category"])] + sorted(set(gm["category"]) - set(CLASSES)):
                gc = gm[gm["category"] == cat]
                for name in names:
                    rows += [{**r, "split": split} for r in _factor_rows(gc, kind, label, cat, name)]
    return rows


def _factor_rows(gc, kind: str, label: str, cat: str, name: str) -> list[dict]:
    """Rows of one corruption for one method and class: its levels, with the clean runs at the clean level."""
    import pandas as pd

    from datasets.corrupt import clean_level

    runs = gc[gc["_name"] == name]
    if not len(runs):
        return []
    clean = gc[gc["_name"] == "clean"]
    # The clean level comes from a clean run's settings: a variant's own settings hold its level for the capture
    # sizes (views, resolution), so the first run's would make whichever variant came first the clean one.
    base = clean if len(clean) else runs
    clean_value = clean_level(name, base["inputs_json"].iloc[0]) if name in FACTORS else None
    if name in FACTORS and len(clean):
        runs = pd.concat([clean.assign(_level=[clean_level(name, s) for s in clean["inputs_json"]]), runs])
    out = []
    for level in sorted(set(runs["_level"]), key=lambda v: severity(name, v, clean_value)):
        if name not in FACTORS:
            setting = level
        else:
            setting = "clean" if level == clean_value else f"{name}={fmt_level(level)}"
        out.append({"input": kind, "method": label, "category": cat, "corruption": name, "level": level,
                    **_aggregate(runs[runs["_level"] == level]), "setting": setting})
    return out


#: Config keys that only set a method's output size (eval/sweeps/robustness_budget.yaml, nie_budget.yaml). A config
#: with any other key (a preset, a smoothing) is another recipe: the budget view shows it as a series of its own
#: instead of joining it to the method's size line.
BUDGET_KNOBS = frozenset({"num_init", "depth", "resolution", "relative_alpha", "grid", "epochs"})


def _budget_method(name: str, clabel: str) -> str:
    keys = {part.split("=", 1)[0] for part in clabel.split(",") if part}
    return name if keys <= BUDGET_KNOBS else f"{name} [{clabel}]"


def budget_rows(df) -> list[dict]:
    """Matched budget: per input kind, method, class, config and density, mean faces and CD p2s of the runs on
    clean geometry (the clean variant, or density alone), in raw units. A config that is not a size knob
    (`BUDGET_KNOBS`) names its own series: `dmesh [preset=noisy]`."""
    from eval.reports.tables import display_name

    if df is None or not len(df):
        return []
    sub = labelled(df)
    sub = sub[sub["_name"].isin(["clean", "density"])]
    rows = []
    for (kind, method, clabel, cat), g in sub.groupby(["input_kind", "method", "config_label", "category"], sort=True):
        dens = g["inputs_json"].map(lambda s: (s.get("corruption") or {}).get("density", s.get("n_points")))
        for d in sorted(set(dens), key=lambda v: -(v or 0)):
            agg = _aggregate(g[dens == d])
            rows.append({"input": kind, "method": _budget_method(display_name(method, kind), clabel or ""),
                         "category": cat,
                         "config": clabel or "default", "density": d, "n": agg["n"], "faces": agg["faces"],
                         "cd_p2s": agg["cd_p2s"], "time_s": agg["time_s"]})
    return rows


#: A DMesh row of the report: the default or a named preset (and, for multi-view, the preset of its point-cloud
#: start), not a study's other overrides: `dmesh [preset=noisy,smooth_k=60]` is a study, and comparing its best
#: level with the others' would pick the winner after the fact.
_DMESH_PRESET = re.compile(r"^dmesh(_mv)? \[[a-z_]+(: [^;\]]*)?(; init_preset=[a-z_]+)?\]$")
#: Columns of the DMesh-against-the-best table (Markdown and HTML).
RATIO_COLUMNS = [("input", "input", None), ("split", "split", None), ("category", "class", None),
                 ("corruption", "corruption", None),
                 ("level", "level", None), ("dmesh", "DMesh", None), ("n", "shapes", None),
                 ("dmesh_cd_p2s", "DMesh CD p2s (x1e-3)", 1e3), ("best", "best other method", None),
                 ("best_cd_p2s", "its CD p2s (x1e-3)", 1e3), ("ratio", "DMesh / best other", 1, ".2f")]


#: The harness pre-processing a row's name carries (`eval.preprocess`): the config-label item after "+".
_PREPROCESS_TAG = re.compile(r"(; |,|\[)(\+[^\],;]+)")


def preprocess_tag(label: str) -> str:
    """The pre-processing a row ran ("+outliers+smooth"), "" for the raw input."""
    found = _PREPROCESS_TAG.search(label)
    return found.group(2) if found else ""


def _untagged(label: str) -> str:
    """The row's name without its pre-processing tag."""
    tag = preprocess_tag(label)
    return label.replace(f" [{tag}]", "").replace(f"; {tag}", "").replace(f",{tag}", "") if tag else label


def dmesh_ratios(rows: list[dict]) -> list[dict]:
    """Per input kind, class, corruption, level, pre-processing and DMesh preset: DMesh's mean CD p2s against the
    best mean CD p2s among the other methods on the same pre-processed input, both over the same shapes (those
    DMesh has a done run on, among methods with a done run on each of them), and their ratio (the issue's
    goal: within 1.2x of the best; below 1, DMesh is the best). DMesh rows are the default and named presets
    only (`_DMESH_PRESET`)."""
    out, groups = [], {}
    for r in rows:
        if r.get("per_shape"):
            key = (r["input"], r.get("split"), r["category"], r["corruption"], str(r["level"]),
                   preprocess_tag(r["method"]))
            groups.setdefault(key, []).append(r)
    for (kind, split, cat, name, _, _), rs in groups.items():
        dmesh_rows = (r for r in rs if _DMESH_PRESET.match(_untagged(r["method"])))
        for dm in sorted(dmesh_rows, key=lambda r: r["method"]):
            shapes = sorted(dm["per_shape"])
            others = [(sum(r["per_shape"][s] for s in shapes) / len(shapes), r["method"]) for r in rs
                      if not r["method"].startswith("dmesh") and set(shapes) <= set(r["per_shape"])]
            if not others:
                continue
            best_cd, best = min(others)
            mine = sum(dm["per_shape"][s] for s in shapes) / len(shapes)
            out.append({"input": kind, "split": split, "category": cat, "corruption": name, "level": rs[0]["level"],
                        "dmesh": dm["method"], "n": len(shapes), "dmesh_cd_p2s": mine, "best": best,
                        "best_cd_p2s": best_cd, "ratio": mine / best_cd if best_cd > 0 else None})
    return out


def _measured_noise(kind: str, info) -> tuple[float | None, bool | None]:
    """(noise ratio, smoothed) that a DMesh run measured on its input (`dmesh.recon.init.noise_ratio`): the
    point-cloud `fast` preset's info "noise_ratio" / "smooth_k", the multi-view depth start's "init_depth"
    figures (smoothed: from all the pixels, "pool_k" > 0, or by the `noisy` preset, as before the pool);
    None where the run did not record them (runs by code from before the figure)."""
    info = info if isinstance(info, dict) else {}
    if kind == "multiview":
        info = info.get("init_depth") if isinstance(info.get("init_depth"), dict) else {}
        ratio, preset = info.get("noise_ratio"), info.get("preset")
        smoothed = preset == "noisy" or int(info.get("pool_k") or 0) > 0
        return ratio, None if preset is None or ratio is None else smoothed
    ratio, k = info.get("noise_ratio"), info.get("smooth_k")
    return ratio, None if k is None else int(k) > 0


def _made_again(kind: str, info) -> bool | None:
    """Whether a DMesh run's point-cloud fit was made again from the smoothed input after a shredded first
    mesh (`PointCloudConfig.redo_fragmented`; multi-view: the depth start's fit); None where the run cannot
    say (code from before the redo: no "smooth_k" in a point-cloud run's info, no "redone" in a start's)."""
    info = info if isinstance(info, dict) else {}
    if kind == "multiview":
        start = info.get("init_depth")
        return bool(start["redone"]) if isinstance(start, dict) and "redone" in start else None
    if "fragmented_attempt" in info:
        return True
    return False if "smooth_k" in info else None


def noise_rows(df) -> list[dict]:
    """Per input kind, corruption and level: the noise ratio DMesh's default presets measured on the inputs
    (point cloud: `fast`, which smooths above `NOISY_RATIO`; multi-view: the `depth` start, which smooths from
    all the pixels above `DEPTH_NOISY_RATIO`), min and max over the runs, how many of them smoothed and how many
    point-cloud fits were made again from the smoothed input after a shredded first mesh (`_made_again`). The
    calibration of both thresholds on the sweeps' own inputs."""
    if df is None or not len(df):
        return []
    sub = labelled(df)
    from eval.reports.labels import method_label

    defaults = (method_label("dmesh", "", "pointcloud"), method_label("dmesh_mv", "preset=depth", "multiview"))
    sub = sub[(sub["status"] == "done") & (sub["_label"].isin(defaults))]
    out = []
    for (kind, name), g in sub.groupby(["input_kind", "_name"], sort=True):
        levels = {str(v): v for v in g["_level"]}
        for key in sorted(levels, key=lambda k: severity(name, levels[k], None)):
            gl = g[g["_level"].map(str) == key]
            seen = [_measured_noise(kind, i) for i in gl["info"]] if "info" in gl.columns else []
            ratios = [r for r, _ in seen if r is not None]
            if not ratios:
                continue
            flags = [s for r, s in seen if r is not None and s is not None]
            again = [a for a in (_made_again(kind, i) for i in gl["info"]) if a is not None]
            out.append({"input": kind, "corruption": name, "level": levels[key], "n": len(ratios),
                        "ratio_min": min(ratios), "ratio_max": max(ratios),
                        "smoothed": f"{sum(flags)} of {len(flags)}" if flags else "",
                        "redone": f"{sum(again)} of {len(again)}" if again else ""})
    return out


# --------------------------------------------------------------------------------------------------- files

NOISE_COLUMNS = [("input", "input", None), ("corruption", "corruption", None), ("level", "level", None),
                 ("n", "runs", 1), ("ratio_min", "noise ratio, min", 1, ".3f"), ("ratio_max", "max", 1, ".3f"),
                 ("smoothed", "smoothed", None), ("redone", "made again", None)]


def _markdown(rows, budget, ratios, figs: list[Path], renders: list[tuple[str, Path]], noise=(),
              provenance=()) -> str:
    from eval.reports.tables import CD_SHORT_NOTE, FRAME_NOTE, markdown, md_text

    cols = [("input", "input", None), ("split", "split", None), ("method", "method", None), ("category", "class", None),
            ("corruption", "corruption", None), ("level", "level", None), ("n", "n", 1), ("failed", "failed", 1),
            ("cd_p2s", "CD p2s (x1e-3)", 1e3), ("cd_l1", "CD L1 (x1e-3)", 1e3), ("time_s", "time (s)", 1),
            ("faces", "faces", 1), ("components", "components", 1)]
    shown = [{**r, "level": fmt_level(r["level"])} for r in rows]
    out = ["# Robustness: corrupted inputs, simulated scans and matched budgets", "",
           f"{FRAME_NOTE} Corruptions and their levels (fractions of the radius for noise and depth noise; "
           "fraction of the points for outliers; points kept for density; densest / sparsest for nonuniform; "
           "cameras for scan) are defined in `datasets/corrupt.py` and `datasets/scan.py`. The clean input is "
           "the first level of every corruption. Means over the done runs (n), failures counted, per split (dev: the "
           "shapes the constants were chosen on; test: never tuned on, `eval/sweeps/test_scan.yaml`; the figures "
           "show dev). "
           f"{CD_SHORT_NOTE} CD x1e-3 here, raw in the CSV; time is the method's wall time in seconds.",
           ""]
    out += [markdown(shown, cols) if rows else "_No runs on corrupted inputs in the store yet._\n"]
    if ratios:
        out += ["", "## DMesh against the best other method (goal: within 1.2x)", "",
                "Each DMesh preset's mean CD p2s over the best mean CD p2s of the other methods, both over the same "
                "shapes (those DMesh ran on); below 1, DMesh is the best. Presets only: the rows of studies with "
                "other overrides are in the table above.",
                "", markdown([{**r, "level": fmt_level(r["level"])} for r in ratios], RATIO_COLUMNS)]
    if noise:
        from dmesh.recon.init import DEPTH_NOISY_RATIO, NOISY_RATIO

        out += ["", "## How noisy DMesh found each input", "",
                "The noise ratio DMesh's library presets measure on their input (`dmesh.recon.init.noise_ratio`: "
                "the median distance of a point to the plane of its 16 nearest neighbours, in neighbour spacings): "
                "point clouds, `fast` (after its outlier filter; it smooths the input as `noisy` does above "
                f"`NOISY_RATIO` = {NOISY_RATIO:g}); multi-view, the `depth` start on the lifted pixels (above "
                f"`DEPTH_NOISY_RATIO` = {DEPTH_NOISY_RATIO:g} it fits each point from its nearest of all the pixels). "
                "The harness's DMesh rows filter nothing, so they record no choice: the runs here were made with "
                "the filters on (earlier code), and calibrate the library's thresholds on these inputs. "
                "`smoothed`: how many of the runs that recorded the choice smoothed. `made again`: how many runs' "
                "point-cloud fits did not smooth at first, came out in shreds (more than `FRAGMENTED_BOUNDARY` "
                "boundary edges per face) and were made again from the smoothed input (noise the ratio missed).",
                "", markdown([{**r, "level": "" if r["level"] is None else fmt_level(r["level"])} for r in noise],
                             NOISE_COLUMNS)]
    if budget:
        out += ["", "## Matched budget: CD p2s against output size (clean geometry)", "",
                markdown(budget, [("input", "input", None), ("method", "method", None),
                                  ("category", "class", None), ("config", "config", None),
                                  ("density", "input points", 1), ("n", "n", 1), ("faces", "faces", 1),
                                  ("cd_p2s", "CD p2s (x1e-3)", 1e3), ("time_s", "time (s)", 1)])]
    if provenance:
        from eval.reports.provenance import provenance_markdown

        out += provenance_markdown(list(provenance))
    if figs or renders:
        out += ["", "## Figures", "", "Line plots: a panel whose methods ran on different shapes (a study on one shape "
                "per class beside a sweep on two) compares them on the shapes all of them ran, named in its title; "
                "the tables above keep every shape.", ""]
        out += [f"- [{p.name}](figures/{p.name})" for p in figs]
        out += [f"- [{p.name}](figures/{p.name}): {md_text(t)}" for t, p in renders]
    out += ["", "_Generated from the results store by `eval.reports.robustness`; do not edit by hand._", ""]
    return "\n".join(out)


def _provenance(df) -> list[dict]:
    """`eval.reports.provenance` rows of the robustness runs in `df`, named by input kind and method."""
    from eval.reports.provenance import provenance_rows
    from eval.reports.tables import method_label

    if df is None or not len(df):
        return []
    return provenance_rows(df[is_robustness(df)],
                           label=lambda r: f"{r['input_kind']}: "
                                           f"{method_label(r['method'], r['config_label'], r['input_kind'])}")


def write_robustness(df, out: str | Path, db: str | Path | None = None, work: str | Path | None = None,
                     renders: bool = True) -> tuple[list[Path], str]:
    """Writes the robustness report files (module docstring) from `df` (`Store.dataframe()`, runs selected).

    Returns:
        (written paths, the HTML body of its section of index.html).
    """
    from eval.reports.render import table_html
    from eval.reports.tables import to_csv

    out = Path(out)
    figdir = out / "figures"
    rows, budget = robustness_rows(df), budget_rows(df)
    ratios = dmesh_ratios(rows)
    figs = [p for kind in ("pointcloud", "multiview") for p in
            (line_plots([r for r in rows if r["split"] != "test"], kind, figdir / f"robustness_{kind}.png"),
             budget_plot(budget, kind, figdir / f"robustness_budget_{kind}.png")) if p is not None]
    scans = scan_renders(df, Path(db), Path(work or Path(db).parent), figdir) if renders and db else []
    md, csv, bcsv = out / "robustness.md", out / "robustness.csv", out / "robustness_budget.csv"
    write_text(md, _markdown(rows, budget, ratios, figs, scans, noise_rows(df), _provenance(df)))
    write_text(csv, to_csv([{**r, "level": fmt_level(r["level"])} for r in rows], CSV_COLUMNS))
    write_text(bcsv, to_csv(budget, BUDGET_COLUMNS))
    body = [f"<p class='links'><a href='{md.name}'>Markdown</a> <a href='{csv.name}'>CSV</a> "
            f"<a href='{bcsv.name}'>budget CSV</a></p>"]
    if ratios:
        body.append(table_html([{**r, "level": fmt_level(r["level"])} for r in ratios], RATIO_COLUMNS))
    body += [f"<img src='figures/{p.name}' alt='{_html.escape(p.stem)}'>" for p in figs]
    body += [f"<h3>{_html.escape(t)}</h3><img src='figures/{p.name}' alt='{_html.escape(t)}'>" for t, p in scans]
    return [md, csv, bcsv, *figs, *(p for _, p in scans)], "\n".join(body)
