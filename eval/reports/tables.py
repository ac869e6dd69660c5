"""Tables from the results store: the paper's Table 2 (CD and time by class), Table 1 (RE / FP), and beside
each a mesh-quality table (orientation against the GT, watertightness, manifoldness, topology).

All tables are computed from `Store.dataframe()` (one row per run) and written as Markdown + CSV. CSV files
keep raw units (Chamfer distances as plain distances in the normalised GT frame; times in seconds; RE / FP in
percent, like the paper); Markdown shows Chamfer distances x1e-3 and RE / FP in percent, and says so. Each
table's columns are defined once (`table2_columns`, `TABLE1_COLUMNS`) and rendered to Markdown here and to HTML
on index.html by the same renderer (`eval.reports.render`, whose helpers stay importable from here).

Frame: every GT is normalised to vertex mean 0 and max vertex norm 1 (the DMesh frame), inputs and
predictions live in that frame, and metrics are computed there.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

from eval.io import write_text
from eval.reports import paper_numbers
from eval.reports.labels import DISPLAY_NAMES, display_name, method_label, preset_of  # noqa: F401 - re-exported
from eval.reports.render import cell, fmt, markdown, md_text, num, text, to_csv  # noqa: F401 - re-exported
from eval.shapes import CATEGORIES

log = logging.getLogger(__name__)

FRAME_NOTE = ("Frame: each GT is normalised to vertex mean 0 and max vertex norm 1; inputs and predictions "
              "live in that frame and metrics are computed there.")
CD_NOTE = ("`cd_p2s`: point-to-surface Chamfer L1 (mean distance from samples of each mesh to the other "
           "mesh's triangles, summed over both directions; no sampling floor; the primary figure). "
           "`cd_l1`: the paper's convention, sample-to-sample Chamfer L1 (mean nearest-sample distance, summed "
           "over both directions) with N samples per side (N in the table notes); it has a sampling floor of "
           "a few 1e-3. Both: unsquared distances, the two directions' means summed (no factor 1/2), in the "
           "frame above; metric samples drawn from streams of their own (metric seed 0), never an input's draw. "
           "Markdown shows both x1e-3; the CSV holds raw distances.")
#: The Chamfer convention in one sentence, for the reports that have no `CD_NOTE` (conventions differ by orders of
#: magnitude between codebases, so every table states its own).
CD_SHORT_NOTE = ("Chamfer distances are L1: unsquared, the two directions' means summed (no factor 1/2), from the "
                 "sweep's metric samples per side (100K in the bundled sweeps); CD p2s measures each sample's "
                 "distance to the other mesh's triangles, CD L1 to the other mesh's nearest sample.")
#: Extra per-class means shown when the metrics provide them: (column, candidate metric names).
OPTIONAL_METRICS = (("fscore", ("fscore", "f_score", "f1", "fscore_0.003")),
                    ("normal_consistency", ("normal_consistency", "nc")),
                    ("normal_consistency_oriented", ("normal_consistency_oriented",)))
QUALITY_NOTE = ("Mesh quality (`eval.metrics.compute_metrics`): *oriented NC* is the signed normal consistency "
                "(1: every normal agrees with the GT's at the closest point, -1: inside out; the unsigned NC "
                "ignores orientation); *oriented* is the area-weighted share of faces whose normal points the "
                "GT's way at the GT point closest to the face centre; both are blank for a GT that cannot be "
                "oriented (a Moebius strip). Inside-out closed GTs are flipped outward before use. "
                "*sheets either side*: the same share once each open piece of the mesh takes whichever side "
                "agrees more (closed pieces must still face outward): an open sheet seen in two-sided shaded "
                "images, depth and masks has no side to pick, so for multi-view rows *oriented* says which "
                "side was chosen and this says whether each sheet is wound consistently and the closed parts "
                "face out. *consistent winding*: share of runs in which every edge with two faces is wound "
                "oppositely by them. "
                "*watertight*: every edge has exactly two faces; *NM*: non-manifold edges (more than two "
                "faces) and vertices (more than one fan of faces); *topology = GT*: same number of connected "
                "components and same genus as the GT; *self-int.*: faces crossing another face.")


SPLIT_NOTE = ("Splits: *dev* is the shapes every constant and preset of the project was chosen on (Table 2's "
              "12); *test* is shapes no constant was tuned on, run and never tuned (`datasets.splits`); *other* "
              "is shapes in neither. n counts shape-seed runs; *sd* is the sample standard deviation of CD p2s "
              "over them.")


def _metric(df, names):
    for n in names:
        if n in df.columns:
            return df[n]
    return None


def table2(df, input_kind: str) -> list[dict]:
    """Per (method + config, class) aggregates of the runs of `input_kind`, in raw units.

    Args:
        df: `Store.dataframe()` (columns method, config_label, category, input_kind, status, cd_p2s, cd_l1,
            time_s, ...).
        input_kind: "pointcloud" or "multiview".
    Returns:
        rows per method, class and split (`split_column`): method, category, split, n (done runs), failed,
        cd_p2s, cd_l1, time_s (means over done runs; None if none), cd_p2s_sd (their spread), optional fscore /
        normal_consistency / normal_consistency_oriented means, the `quality_summary` keys, paper_cd_l1 and
        paper_time_s (None when the paper has no row for the method).
        Ordered by method, then closed / open / mixed. Runs still running (or pending) make no row: a method
        and class appear once a run of them has finished (done or failed).
    """
    if df is None or len(df) == 0:
        return []
    sub = df[(df["input_kind"] == input_kind) & df["status"].isin(["done", "failed"])]
    sub = sub.assign(split=split_column(sub))
    rows = []
    for (method, clabel), g in sub.groupby(["method", "config_label"], sort=True):
        # The paper's DMesh figures stand only beside the preset that runs the paper's procedure.
        paper = (paper_numbers.table2_row(method, input_kind)
                 if preset_of(method, clabel) in (None, "paper") else None)
        for cat in [c for c in CATEGORIES if c in set(g["category"])] + sorted(set(g["category"]) - set(CATEGORIES)):
            gc = g[g["category"] == cat]
            for split in [s for s in SPLITS if s in set(gc["split"])]:
                gs = gc[gc["split"] == split]
                done = gs[gs["status"] == "done"]
                row = {"method": method_label(method, clabel, input_kind), "category": cat, "split": split,
                       "n": int(len(done)), "failed": int((gs["status"] == "failed").sum()),
                       "cd_p2s": _mean(done, "cd_p2s"), "cd_p2s_sd": _sd(done, "cd_p2s"),
                       "cd_l1": _mean(done, "cd_l1"), "time_s": _mean(done, "time_s"), "cpu_s": _mean(done, "cpu_s")}
                for col, names in OPTIONAL_METRICS:
                    s = _metric(done, names)
                    if s is not None:
                        row[col] = _mean_series(s)
                row.update(quality_summary(done))
                row["paper_cd_l1"] = paper.get(cat) if paper else None
                row["paper_time_s"] = paper.get("time_s") if paper else None
                rows.append(row)
    return rows


#: The splits a table shows, in order: dev (constants chosen there), test (run, never tuned), and "other" for
#: shapes in neither (a user's own).
SPLITS = ("dev", "test", "other")


def split_column(df):
    """Each run's split (`datasets.splits.split_of` of its shape; "other" when in neither)."""
    from datasets.splits import split_of

    return df["shape"].map(lambda shape: split_of(str(shape)) or "other") if len(df) else df["shape"]


def side_by_side(rows: list[dict]) -> list[dict]:
    """`table2` rows as one row per method and class with each split's n, mean CD p2s and its spread."""
    out: dict[tuple, dict] = {}
    for r in rows:
        row = out.setdefault((r["method"], r["category"]), {"method": r["method"], "category": r["category"]})
        row.update({f"{r['split']}_n": r["n"], f"{r['split']}_cd_p2s": r["cd_p2s"],
                    f"{r['split']}_cd_p2s_sd": r["cd_p2s_sd"]})
    return list(out.values())


def _mean(df, col):
    if col not in df.columns or len(df) == 0:
        return None
    return _mean_series(df[col])


def _sd(df, col):
    """Sample standard deviation of `col` over the rows (None below two values): the spread over shape-seed
    runs that a mean is given with."""
    if col not in df.columns:
        return None
    s = df[col].dropna().astype(float)
    return float(s.std(ddof=1)) if len(s) > 1 else None


def _mean_series(s):
    s = s.dropna().astype(float)
    return float(s.mean()) if len(s) else None


def _share(flags) -> float | None:
    """Fraction of True among the known (non-missing) flags; None when none is known."""
    known = [bool(x) for x in flags if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return sum(known) / len(known) if known else None


def quality_summary(done) -> dict:
    """Mesh-quality aggregates of some done runs (DataFrame rows with `compute_metrics` columns); None where
    the runs do not carry the figure (rows stored before it existed).

    Returns:
        {"oriented_fraction": mean, "oriented_fraction_min": min (the issue's target is on every run),
        "oriented_fraction_any_side", "oriented_fraction_any_side_min": the same with open pieces free to take
        either side (`eval.metrics`; what multi-view input can decide),
        "watertight_share": fraction of runs that are watertight, "winding_share": fraction whose winding is
        consistent (`topology`'s `winding_consistent`), "no_nm_edges_share": fraction with no
        non-manifold edge, "non_manifold_edges", "non_manifold_vertices", "boundary_edges": means,
        "topology_match_share": fraction whose component count and genus equal the GT's,
        "self_intersecting_faces": mean over the runs where it was counted}.
    """
    def col(name):
        return done[name] if name in done.columns else None

    def mean(name, keep=lambda s: s):
        s = col(name)
        return _mean_series(keep(s.dropna().astype(float))) if s is not None else None

    out = {}
    for name in ("oriented_fraction", "oriented_fraction_any_side"):
        s = col(name)
        s = s.dropna().astype(float) if s is not None else None
        out[name] = _mean_series(s) if s is not None else None
        out[f"{name}_min"] = float(s.min()) if s is not None and len(s) else None
    out.update({
           "watertight_share": _share(col("watertight")) if col("watertight") is not None else None,
           "winding_share": _share(col("winding_consistent")) if col("winding_consistent") is not None else None,
           "no_nm_edges_share": None, "non_manifold_edges": mean("non_manifold_edges"),
           "non_manifold_vertices": mean("non_manifold_vertices"), "boundary_edges": mean("boundary_edges"),
           "topology_match_share": None,
           "self_intersecting_faces": mean("self_intersecting_faces", lambda s: s[s >= 0])})
    nm = col("non_manifold_edges")
    if nm is not None:
        out["no_nm_edges_share"] = _share([None if v != v else v == 0 for v in nm.astype(float)])
    if all(c in done.columns for c in ("components", "gt_components", "genus", "gt_genus")):
        out["topology_match_share"] = _share([_topology_match(r) for _, r in done.iterrows()])
    return out


def _topology_match(r) -> bool | None:
    """Whether a run's component count and genus equal its GT's; None when the GT's are unknown."""
    gc, gg = num(r.get("gt_components")), num(r.get("gt_genus"))
    if gc is None:
        return None
    c, g = num(r.get("components")), num(r.get("genus"))
    return c == gc and g is not None and g == gg


def quality_row(r) -> dict:
    """Mesh-quality figures of one run (a store row): raw values for CSV, and "a (GT b)" text cells.

    Returns:
        {"nc_oriented", "oriented_fraction", "watertight" (True / False / None), "boundary_edges",
        "non_manifold_edges", "non_manifold_vertices", "components", "gt_components", "genus", "gt_genus",
        "self_intersecting_faces" (None when not counted), "components_vs_gt", "genus_vs_gt" (text cells:
        "3 (GT 1)"; genus "-" when undefined: non-manifold or non-orientable), "watertight_text"}.
    """
    w = r.get("watertight")
    w = None if w is None or (isinstance(w, float) and math.isnan(w)) else bool(w)
    si = num(r.get("self_intersecting_faces"))
    out = {"nc_oriented": num(r.get("normal_consistency_oriented")),
           "oriented_fraction": num(r.get("oriented_fraction")),
           "oriented_fraction_any_side": num(r.get("oriented_fraction_any_side")), "watertight": w,
           "watertight_text": "" if w is None else ("yes" if w else "no"),
           "boundary_edges": num(r.get("boundary_edges")), "non_manifold_edges": num(r.get("non_manifold_edges")),
           "non_manifold_vertices": num(r.get("non_manifold_vertices")),
           "self_intersecting_faces": si if si is not None and si >= 0 else None}
    for k in ("components", "genus"):
        mine, gt = num(r.get(k)), num(r.get(f"gt_{k}"))
        out[k], out[f"gt_{k}"] = mine, gt
        cell_ = "" if mine is None and gt is None else ("-" if mine is None else str(int(mine)))
        if gt is not None or (k == "genus" and num(r.get("gt_components")) is not None):
            cell_ += f" (GT {'-' if gt is None else int(gt)})"
        out[f"{k}_vs_gt"] = cell_
    return out


#: Columns of a per-run mesh-quality table (`quality_row` keys), for `markdown`.
QUALITY_RUN_COLUMNS = [("nc_oriented", "oriented NC", 1), ("oriented_fraction", "oriented (%)", 100, ".1f"),
                       ("oriented_fraction_any_side", "oriented, sheets either side (%)", 100, ".1f"),
                       ("watertight_text", "watertight", None), ("boundary_edges", "boundary edges", 1),
                       ("non_manifold_edges", "NM edges", 1), ("non_manifold_vertices", "NM vertices", 1),
                       ("components_vs_gt", "components", None), ("genus_vs_gt", "genus", None),
                       ("self_intersecting_faces", "self-int. faces", 1)]
#: Columns of a per-class mesh-quality table (`quality_summary` keys).
QUALITY_SUMMARY_COLUMNS = [("normal_consistency_oriented", "oriented NC", 1),
                           ("oriented_fraction", "oriented (%)", 100, ".1f"),
                           ("oriented_fraction_min", "oriented min (%)", 100, ".1f"),
                           ("oriented_fraction_any_side", "sheets either side (%)", 100, ".1f"),
                           ("oriented_fraction_any_side_min", "sheets either side, min (%)", 100, ".1f"),
                           ("winding_share", "consistent winding (%)", 100, ".0f"),
                           ("watertight_share", "watertight (%)", 100, ".0f"),
                           ("no_nm_edges_share", "no NM edges (%)", 100, ".0f"),
                           ("non_manifold_edges", "NM edges", 1), ("non_manifold_vertices", "NM vertices", 1),
                           ("boundary_edges", "boundary edges", 1),
                           ("topology_match_share", "topology = GT (%)", 100, ".0f"),
                           ("self_intersecting_faces", "self-int. faces", 1)]


def per_shape(df, input_kind: str) -> list[dict]:
    """One row per run of `input_kind` (method, shape, class, seed, status (done, failed, or unfinished for a
    run stored as running), cd_p2s, cd_l1, time_s, faces, error, and for done runs the `quality_row` keys)."""
    if df is None or len(df) == 0:
        return []
    sub = df[df["input_kind"] == input_kind].sort_values(["category", "shape", "method", "config_label", "seed"])
    out = []
    for _, r in sub.iterrows():
        out.append({"method": method_label(r["method"], r["config_label"], input_kind),
                    "shape": r["shape"],
                    "category": r["category"], "seed": int(r["seed"]),
                    # A report is a snapshot: a run stored as running had not finished when it was written.
                    "status": "unfinished" if r["status"] == "running" else r["status"],
                    "cd_p2s": num(r.get("cd_p2s")), "cd_l1": num(r.get("cd_l1")), "time_s": num(r.get("time_s")),
                    "cpu_s": num(r.get("cpu_s")), "faces": num(r.get("faces", r.get("n_faces"))),
                    "error": text(r.get("error")),
                    **(quality_row(r) if r["status"] == "done" else {})})
    return out


TABLE2_CSV_COLUMNS = ["method", "category", "split", "n", "failed", "cd_p2s", "cd_p2s_sd", "cd_l1", "time_s",
                      "fscore", "normal_consistency", "paper_cd_l1", "paper_time_s", "normal_consistency_oriented",
                      "oriented_fraction", "oriented_fraction_min", "oriented_fraction_any_side",
                      "oriented_fraction_any_side_min", "watertight_share", "no_nm_edges_share",
                      "non_manifold_edges", "non_manifold_vertices", "boundary_edges", "topology_match_share",
                      "self_intersecting_faces", "cpu_s"]


def table2_columns(rows: list[dict]) -> list[tuple]:
    """The columns of Table 2 (`table2` rows), in its Markdown report and on index.html alike: the optional
    figures (CPU time, F-score, NC, oriented NC) only when some row has them."""
    cols = [("method", "method", None), ("category", "class", None), ("split", "split", None), ("n", "n", 1),
            ("failed", "failed", 1), ("cd_p2s", "CD p2s (x1e-3)", 1e3), ("cd_p2s_sd", "sd", 1e3),
            ("cd_l1", "CD L1 (x1e-3)", 1e3), ("time_s", "time (s)", 1)]
    if any(r.get("cpu_s") is not None for r in rows):
        cols.append(("cpu_s", "CPU (s)", 1))
    if any("fscore" in r for r in rows):
        cols.append(("fscore", "F-score", 1))
    if any("normal_consistency" in r for r in rows):
        cols.append(("normal_consistency", "NC", 1))
    if any(r.get("normal_consistency_oriented") is not None for r in rows):
        cols.append(("normal_consistency_oriented", "oriented NC", 1))
    return cols + [("paper_cd_l1", "paper CD (x1e-3)", 1e3, ".2f"), ("paper_time_s", "paper time (s)", 1, ".2f")]


def table2_markdown(rows: list[dict], input_kind: str, details: list[dict], n_samples: int | None,
                    title: str | None = None, provenance: list[dict] | None = None) -> str:
    label = {"pointcloud": "point cloud", "multiview": "multi-view"}.get(input_kind, input_kind)
    cols = table2_columns(rows)
    out = [f"# {md_text(title) if title else f'Table 2 ({label} input): Chamfer distance and time by class'}", "",
           f"Input: {label}. {FRAME_NOTE} Means over the successful runs of each class (n), with the number of "
           f"failed runs beside them; a failed run has no CD.", "", CD_NOTE, "",
           f"Metric samples per side: N = {n_samples if n_samples else 'see the store'}. Time: the method's "
           "wall time in seconds on this machine (metrics excluded). CPU: its CPU seconds over all threads "
           "(DMesh's own count; for the other methods the worker's; blank for runs that did not record it). "
           "The sweeps run each method on one thread, so a wall time well above the CPU time means the run shared its "
           "core with other work, and the CPU time is the better estimate of its time alone.", ""]
    if rows:
        out.append(markdown(rows, cols))
        splits = [s for s in SPLITS if any(r["split"] == s for r in rows)]
        out += ["", "## Dev and test side by side", "", SPLIT_NOTE, "",
                markdown(side_by_side(rows), [("method", "method", None), ("category", "class", None)]
                         + [c for s in splits for c in ((f"{s}_n", f"{s} n", 1),
                                                        (f"{s}_cd_p2s", f"{s} CD p2s (x1e-3)", 1e3),
                                                        (f"{s}_cd_p2s_sd", f"{s} sd", 1e3))])]
        out += ["", "## Mesh quality by class", "", QUALITY_NOTE, "",
                markdown(rows, [("method", "method", None), ("category", "class", None), ("split", "split", None),
                                ("n", "n", 1)] + QUALITY_SUMMARY_COLUMNS)]
    else:
        out.append(f"_No {label} runs in the store yet._\n")
    if provenance:
        from eval.reports.provenance import provenance_markdown

        out += provenance_markdown(provenance)
    paper = paper_numbers.TABLE2.get(input_kind)
    if paper:
        prow = [{"method": m, **v} for m, v in paper.items()]
        out += ["", f"## Published: the paper's Table 2 ({label}, CD x1e-3 L1, time in seconds)", "",
                "For reference only: the paper's own shapes (Thingi32, DeepFashion3D, Objaverse) and hardware "
                "(A10 GPU); our classes use synthetic and shared stand-in meshes, so only trends compare.", "",
                markdown(prow, [("method", "method", None), ("closed", "closed", 1e3, ".2f"),
                                ("open", "open", 1e3, ".2f"), ("mixed", "mixed", 1e3, ".2f"),
                                ("time_s", "time (s)", 1, ".2f")])]
        out += [f"\nNote: {note}" for note in paper_numbers.TABLE2_NOTES.get(input_kind, ())]
    if details:
        out += ["", "## Runs", "",
                markdown(details, [("method", "method", None), ("shape", "shape", None),
                                   ("category", "class", None), ("seed", "seed", 1), ("status", "status", None),
                                   ("cd_p2s", "CD p2s (x1e-3)", 1e3), ("cd_l1", "CD L1 (x1e-3)", 1e3),
                                   ("time_s", "time (s)", 1), ("cpu_s", "CPU (s)", 1), ("faces", "faces", 1),
                                   ("error", "error", None)])]
        done = [d for d in details if d["status"] == "done"]
        if done:
            out += ["", "## Runs: mesh quality", "",
                    markdown(done, [("method", "method", None), ("shape", "shape", None), ("seed", "seed", 1)]
                             + QUALITY_RUN_COLUMNS)]
    out += ["", "_Generated from the results store by `eval.reports`; do not edit by hand._", ""]
    return "\n".join(out)


def write_table2(df, out: str | Path, input_kind: str, n_samples: int | None = None) -> tuple[Path, Path]:
    """Writes `table2_<kind>.md` and `.csv` under `out`; returns their paths."""
    out = Path(out)
    rows = table2(df, input_kind)
    md_path, csv_path = out / f"table2_{input_kind}.md", out / f"table2_{input_kind}.csv"
    from eval.reports.provenance import provenance_rows

    write_text(md_path, table2_markdown(rows, input_kind, per_shape(df, input_kind), n_samples,
                                        provenance=provenance_rows(df, input_kind)))
    write_text(csv_path, to_csv(rows, TABLE2_CSV_COLUMNS))
    return md_path, csv_path


# --------------------------------------------------------------------------------------------------- Table 1

_RE_NAMES = ("re", "RE", "recovery_ratio", "recovery")
_FP_NAMES = ("fp", "FP", "false_positive_ratio", "false_positive")
TABLE1_CSV_COLUMNS = ["shape", "method", "RE", "FP", "steps", "time_s", "paper_RE", "paper_FP"]
#: The columns of Table 1 (`table1` rows), in its Markdown report and on index.html alike.
TABLE1_COLUMNS = [("shape", "shape", None), ("method", "method", None), ("RE", "RE (%)", 100, ".2f"),
                  ("FP", "FP (%)", 100, ".2f"), ("steps", "steps", 1), ("time_s", "time (s)", 1),
                  ("paper_RE", "paper RE (%)", 100, ".2f"), ("paper_FP", "paper FP (%)", 100, ".2f")]


def table1(df) -> list[dict]:
    """Rows of Table 1 (RE / FP as fractions) from the done runs whose metrics hold RE and FP.

    `steps` comes from the run's info (`steps` or `iterations`); `time_s` is the method's wall time.
    """
    if df is None or len(df) == 0:
        return []
    rows = []
    done = df[df["status"] == "done"]
    for _, r in done.iterrows():
        re_ = next((num(r.get(n)) for n in _RE_NAMES if num(r.get(n)) is not None), None)
        fp = next((num(r.get(n)) for n in _FP_NAMES if num(r.get(n)) is not None), None)
        if re_ is None or fp is None:
            continue
        info = r.get("info") or {}
        steps = info.get("steps", info.get("iterations")) if isinstance(info, dict) else None
        paper = paper_numbers.table1_row(str(r["shape"]))
        rows.append({"shape": r["shape"], "method": method_label(r["method"], r["config_label"]), "RE": re_,
                     "FP": fp, "steps": int(steps) if steps is not None else None, "time_s": num(r.get("time_s")),
                     "paper_RE": paper[1]["RE"] if paper else None, "paper_FP": paper[1]["FP"] if paper else None})
    return sorted(rows, key=lambda x: (x["shape"], x["method"]))


def _table1_runs(df):
    """The done runs of `df` in Table 1 (those with RE / FP); None for an empty `df`."""
    if df is None or len(df) == 0:
        return None
    done = df[df["status"] == "done"]
    if not len(done):
        return done
    return done[done.apply(lambda r: any(num(r.get(n)) is not None for n in _RE_NAMES), axis=1)]


def _table1_quality(df) -> list[dict]:
    """`quality_row` of each done run in Table 1 (those with RE / FP), in Table 1's order."""
    runs = _table1_runs(df)
    if runs is None:
        return []
    rows = [{"shape": r["shape"], "method": method_label(r["method"], r["config_label"]), **quality_row(r)}
            for _, r in runs.iterrows()]
    return sorted(rows, key=lambda x: (x["shape"], x["method"]))


def write_table1(df, out: str | Path) -> tuple[Path, Path]:
    """Writes `table1.md` and `table1.csv` (RE / FP of mesh-to-DMesh runs) under `out`."""
    out = Path(out)
    rows = table1(df)
    md = ["# Table 1: mesh to DMesh, face recovery (RE) and false positives (FP)", "",
          "RE: fraction of the GT's unique sorted face triples present in the result; FP: fraction of the "
          "result's unique triples on GT vertices that are not GT faces. In percent (Markdown and CSV). "
          + FRAME_NOTE.replace("max vertex norm 1", "max vertex norm 0.8 (mesh to DMesh)"),
          ""]
    if rows:
        md.append(markdown(rows, TABLE1_COLUMNS))
    else:
        md.append("_No mesh-to-DMesh runs in the store yet._\n")
    quality = _table1_quality(df)
    if quality:
        md += ["", "## Mesh quality", "", QUALITY_NOTE, "",
               markdown(quality, [("shape", "shape", None), ("method", "method", None)] + QUALITY_RUN_COLUMNS)]
    from eval.reports.provenance import provenance_markdown, provenance_rows

    md += provenance_markdown(provenance_rows(_table1_runs(df)))
    prow = [{"shape": k, **v} for k, v in paper_numbers.TABLE1.items()]
    md += ["", "## Published: the paper's Table 1 (20K steps, Stanford models)", "",
           markdown(prow, [("shape", "model", None), ("RE", "RE (%)", 100, ".2f"), ("FP", "FP (%)", 100, ".2f")]),
           "", "_Generated from the results store by `eval.reports`; do not edit by hand._", ""]
    md_path, csv_path = out / "table1.md", out / "table1.csv"
    write_text(md_path, "\n".join(md))
    pct = ("RE", "FP", "paper_RE", "paper_FP")  # the CSV states RE and FP in percent, like the paper
    csv_rows = [{k: (100 * v if k in pct and v is not None else v) for k, v in r.items()} for r in rows]
    write_text(csv_path, to_csv(csv_rows, TABLE1_CSV_COLUMNS))
    return md_path, csv_path
