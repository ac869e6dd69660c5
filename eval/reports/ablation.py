"""Regulariser ablations like the paper's Tables 4 and 5 (appendix 10.2), from `eval/sweeps/ablation.yaml`.

An ablation run is a DMesh point-cloud run whose config overrides name `lambda_weight` and `lambda_quality`.
Table 4 varies lambda_weight with lambda_quality = 0; Table 5 varies lambda_quality with lambda_weight = 0.
Each row is the mean over the shapes run at that value: CD (point-to-surface and sample L1), face count,
mean aspect ratio (circumradius / (2 inradius), 1 for an equilateral triangle) and time. Ablation runs are
kept out of Table 2, which compares methods at their defaults.
"""
from __future__ import annotations

import math
from pathlib import Path

from eval.io import write_text
from eval.reports.render import markdown, md_text, num, to_csv
from eval.reports.tables import CD_SHORT_NOTE, FRAME_NOTE, _mean

#: knob -> (the swept coefficient, the one held at 0), output stem, paper table.
KNOBS = {"weight": ("lambda_weight", "lambda_quality", "ablation_weight", "Table 4"),
         "quality": ("lambda_quality", "lambda_weight", "ablation_quality", "Table 5")}
#: The paper's Tables 4 and 5 (its shapes and units; CD as printed there).
PAPER = {"weight": {1e-6: {"cd": 7.48, "faces": 4753}, 1e-5: {"cd": 8.08, "faces": 2809},
                    1e-4: {"cd": 10.82, "faces": 1786}},
         "quality": {1e-4: {"cd": 7.60, "faces": 8266, "aspect": 2.33},
                     1e-3: {"cd": 7.42, "faces": 8349, "aspect": 2.06},
                     1e-2: {"cd": 7.28, "faces": 10806, "aspect": 1.55}}}
CSV_COLUMNS = ["knob", "value", "n", "cd_p2s", "cd_l1", "faces", "aspect_ratio", "time_s", "paper_cd", "paper_faces",
               "paper_aspect_ratio"]


def is_ablation(df):
    """(rows,) bool Series: the ablation runs of `df` (a `Store.dataframe()`)."""
    label = df["config_label"].astype(str)
    return (df["method"] == "dmesh") & label.str.contains("lambda_weight=") & label.str.contains("lambda_quality=")


def ablation_rows(df, knob: str) -> list[dict]:
    """Rows of one ablation table (raw units), ascending in the swept value."""
    swept, held, _, _ = KNOBS[knob]
    if df is None or len(df) == 0:
        return []
    sub = df[is_ablation(df) & (df["status"] == "done")]
    value = sub["config"].map(lambda c: num((c or {}).get(swept)))
    other = sub["config"].map(lambda c: num((c or {}).get(held)))
    sub = sub[(other == 0) & (value > 0)].assign(_value=value)
    rows = []
    for v, g in sorted(sub.groupby("_value"), key=lambda kv: kv[0]):
        paper = next((row for p, row in PAPER[knob].items() if math.isclose(p, v, rel_tol=1e-9)), {})
        rows.append({"knob": swept, "value": float(v), "n": int(len(g)), "cd_p2s": _mean(g, "cd_p2s"),
                     "cd_l1": _mean(g, "cd_l1"), "faces": _mean(g, "faces"),
                     "aspect_ratio": _mean(g, "aspect_ratio_mean"), "time_s": _mean(g, "time_s"),
                     "paper_cd": paper.get("cd"),
                     "paper_faces": paper.get("faces"), "paper_aspect_ratio": paper.get("aspect")})
    return rows


def columns(knob: str) -> list[tuple]:
    """The columns of the ablation table of `knob` (`shown_rows`), in its Markdown report and on index.html
    alike."""
    cols = [("value", KNOBS[knob][0], None), ("n", "n", 1), ("cd_p2s", "CD p2s (x1e-3)", 1e3),
            ("cd_l1", "CD L1 (x1e-3)", 1e3), ("faces", "faces", 1), ("aspect_ratio", "aspect ratio", 1),
            ("time_s", "time (s)", 1), ("paper_cd", "paper CD", 1, ".2f"), ("paper_faces", "paper faces", 1)]
    if knob == "quality":
        cols.append(("paper_aspect_ratio", "paper aspect ratio", 1, ".2f"))
    return cols


def shown_rows(rows: list[dict]) -> list[dict]:
    """`ablation_rows` as a table shows them: the swept value as text."""
    return [{**r, "value": f"{r['value']:g}"} for r in rows]


def write_ablations(df, out: str | Path) -> list[Path]:
    """Writes `ablation_weight.{md,csv}` and `ablation_quality.{md,csv}` under `out`; returns the paths."""
    out = Path(out)
    written = []
    for knob, (swept, held, stem, paper_table) in KNOBS.items():
        rows = ablation_rows(df, knob)
        shapes = [md_text(s) for s in sorted(set(df[is_ablation(df)]["shape"]))] if df is not None and len(df) else []
        md = [f"# Ablation: {swept} (like the paper's {paper_table})", "",
              f"DMesh on point clouds, {held} = 0, the other settings from `eval/sweeps/ablation.yaml` (the paper "
              f"preset cut to a CPU budget). Means over the shapes {', '.join(shapes) or '(none yet)'}. "
              f"{FRAME_NOTE} {CD_SHORT_NOTE} CD x1e-3; aspect ratio: "
              "mean circumradius / (2 inradius). The paper's columns are its own shapes and units, for the trend "
              "only.", ""]
        md.append(markdown(shown_rows(rows), columns(knob)) if rows
                  else "_No ablation runs in the store yet: "
                       "`dmesh bench eval/sweeps/ablation.yaml --work runs/paper`._\n")
        md += ["", "_Generated from the results store by `eval.reports`; do not edit by hand._", ""]
        md_path, csv_path = out / f"{stem}.md", out / f"{stem}.csv"
        write_text(md_path, "\n".join(md))
        write_text(csv_path, to_csv(rows, CSV_COLUMNS))
        written += [md_path, csv_path]
    return written


__all__ = ["KNOBS", "is_ablation", "ablation_rows", "columns", "shown_rows", "write_ablations"]
