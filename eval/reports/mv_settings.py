"""How the multi-view presets' settings were chosen: DMesh multi-view runs with overrides, per shape.

Settings-study runs are multi-view DMesh runs (`dmesh_mv`) whose config overrides name anything beyond a
preset (`eval/sweeps/multiview_fast.yaml`, `multiview_schedule.yaml`, `multiview_depth.yaml`). They are kept
out of Table 2, which compares presets, and reported here beside the same shape's preset runs (Table 2's rows)
and its TSDF fusion run:

    multiview_fast.md / .csv     one row per run: shape, class, settings, CD p2s, CD L1, faces, time, CD p2s
                                 over TSDF fusion's on the same shape, components, boundary edges and
                                 self-intersecting faces
"""
from __future__ import annotations

import re
from pathlib import Path

from eval.io import write_text
from eval.reports.render import markdown, num, to_csv
from eval.reports.tables import CD_SHORT_NOTE, FRAME_NOTE

CLASSES = ("closed", "open", "mixed")
CSV_COLUMNS = ["shape", "category", "settings", "faces", "cd_p2s", "cd_l1", "time_s", "tsdf_cd_p2s", "over_tsdf",
               "components", "boundary_edges", "self_intersecting_faces"]


def _preset_row(label: str) -> str:
    """What the settings column says for a run of a preset as it is now ("" is the default, `fast`)."""
    return f"{label.split('=', 1)[1] if label else 'fast'} preset (as now)"


#: The override names in a config label ("a=1,b=[2, 3]": a, b; `eval.sweep.config_label`).
_KEY = re.compile(r"(?:^|,)([A-Za-z_][A-Za-z_0-9]*)=")


def _overrides(label) -> set:
    return set(_KEY.findall(label)) if isinstance(label, str) else set()


def is_study(label) -> bool:
    """Whether a config label names overrides beyond `preset`."""
    return bool(_overrides(label) - {"preset"})


def is_mv_settings_study(df):
    """(rows,) bool Series: the settings-study runs of `df` (a `Store.dataframe()`): multi-view DMesh runs whose
    overrides go beyond `preset`."""
    import pandas as pd

    if df is None or not len(df):
        return pd.Series(False, index=getattr(df, "index", None), dtype=bool)
    study = df["config_label"].map(is_study)
    return (df["method"] == "dmesh_mv") & (df["input_kind"] == "multiview") & study


def _counted(value):
    """A count, None where it was not computed (stored as -1) or is missing."""
    v = num(value)
    return v if v is not None and v >= 0 else None


def settings_rows(df) -> list[dict]:
    """One row per done DMesh run on the shapes of the study: its runs and the shape's preset runs (Table 2's
    rows), with its TSDF fusion run's CD as the reference; sorted by class, shape, then CD p2s."""
    if df is None or not len(df):
        return []
    study = df[is_mv_settings_study(df) & (df["status"] == "done")]
    shapes = set(study["shape"])
    if not shapes:
        return []
    mv = df[(df["input_kind"] == "multiview") & (df["status"] == "done") & df["shape"].isin(shapes)]
    label = mv["config_label"].fillna("").astype(str)
    tsdf = {r["shape"]: num(r.get("cd_p2s")) for _, r in mv[(mv["method"] == "tsdf") & (label == "")].iterrows()}
    runs = mv[mv["method"] == "dmesh_mv"]
    rows = []
    for _, r in runs.iterrows():
        cd, ref = num(r.get("cd_p2s")), tsdf.get(r["shape"])
        rows.append({"shape": r["shape"], "category": r["category"],
                     "settings": r["config_label"] if is_study(r["config_label"]) else _preset_row(r["config_label"]),
                     "faces": num(r.get("faces")), "cd_p2s": cd,
                     "cd_l1": num(r.get("cd_l1")), "time_s": num(r.get("time_s")), "tsdf_cd_p2s": ref,
                     "over_tsdf": cd / ref if cd is not None and ref else None,
                     "components": num(r.get("components")), "boundary_edges": num(r.get("boundary_edges")),
                     "self_intersecting_faces": _counted(r.get("self_intersecting_faces"))})
    order = {c: i for i, c in enumerate(CLASSES)}
    rows.sort(key=lambda x: (order.get(x["category"], len(order)), x["shape"], x["cd_p2s"] or float("inf")))
    return rows


def write_mv_settings(df, out: str | Path) -> list[Path]:
    """Writes `multiview_fast.{md,csv}` under `out` when the store has settings-study runs; returns the paths
    (none otherwise, so a committed report is not replaced by an empty one)."""
    rows = settings_rows(df)
    if not rows:
        return []
    out = Path(out)
    md = ["# The multi-view presets' settings, run by run", "",
          "DMesh on multi-view input (`dmesh_mv`) with settings that differ from a preset, beside the presets "
          "as they are now (Table 2's rows) and TSDF fusion on the same shape (`eval/sweeps/multiview_fast.yaml`, "
          "`multiview_schedule.yaml`, `multiview_depth.yaml`). *settings*: the overrides on top of the `fast` "
          "preset, or of the preset they name. */ TSDF*: CD p2s over TSDF fusion's on that shape (the target of issue "
          "[recipes] is at most 2 per class). Why each setting was chosen: `docs/preset_choices_multiview.md`. "
          f"{FRAME_NOTE} {CD_SHORT_NOTE} CD x1e-3; the CSV holds raw distances. Times are wall seconds on this "
          "machine, under "
          "whatever load the sweep ran beside.", "",
          markdown(rows, [("shape", "shape", None), ("category", "class", None), ("settings", "settings", None),
                          ("faces", "faces", 1, ".0f"), ("cd_p2s", "CD p2s", 1e3), ("cd_l1", "CD L1", 1e3),
                          ("time_s", "time (s)", 1, ".0f"), ("tsdf_cd_p2s", "TSDF CD p2s", 1e3),
                          ("over_tsdf", "/ TSDF", 1, ".2f"), ("components", "components", 1, ".0f"),
                          ("boundary_edges", "boundary edges", 1, ".0f"),
                          ("self_intersecting_faces", "self-int. faces", 1, ".0f")]),
          "", "_Generated from the results store by `eval.reports`; do not edit by hand._", ""]
    md_path, csv_path = out / "multiview_fast.md", out / "multiview_fast.csv"
    write_text(md_path, "\n".join(md))
    write_text(csv_path, to_csv(rows, CSV_COLUMNS))
    return [md_path, csv_path]


__all__ = ["is_mv_settings_study", "settings_rows", "write_mv_settings"]
