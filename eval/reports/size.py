"""Do DMesh's gradient steps pay? Runs with steps against the gradient-free start at the same mesh size.

The `fast` preset's Table 2 rows have about 80K faces and the `paper` preset's 2K-5K (10K seeds), and CD p2s
falls with mesh size whatever made the mesh, so the two Table 2 rows compare sizes as much as recipes. The
size study (`eval/sweeps/recipes_size.yaml`) runs the fast start (no phase-1 step) at a few seed counts, and
once with phase-1 steps; this report puts each run with gradient steps on that size curve:

    recipes_size.md / .csv        per run with steps: the fast start interpolated to its face count (log-log
                                  between the two nearest sizes), and the ratio of the two CDs
    figures/recipes_size.png      CD p2s against faces, one panel per class: fast sizes (lines), paper preset
                                  (stars), fast start + steps (triangles); with a tangent weight: plus, diamond

Size-study runs are DMesh point-cloud runs whose overrides are `num_init` and optionally `steps_phase1`; they
are kept out of Table 2.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

from dmesh.recon.config import FAST_SEEDS
from eval.io import atomic_path, write_text
from eval.reports.render import markdown, num, to_csv
from eval.reports.tables import CD_SHORT_NOTE, FRAME_NOTE

CLASSES = ("closed", "open", "mixed")
SIZE_LABEL = re.compile(r"^num_init=\d+$")
STEPS_LABEL = re.compile(r"^num_init=(\d+),steps_phase1=(\d+)(?:,tangent_weight=([0-9.e-]+))?$")
PAPER_LABEL = re.compile(r"^preset=paper(?:,tangent_weight=([0-9.e-]+))?$")
CSV_COLUMNS = ["shape", "category", "recipe", "faces", "cd_p2s", "time_s", "fast_cd_p2s_at_faces", "ratio",
               "fast_sizes", "fast_default_faces", "fast_default_cd_p2s", "fast_default_time_s"]


def is_size_study(df):
    """(rows,) bool Series: the size-study runs of `df` (a `Store.dataframe()`): the fast start at some seed
    count, with or without phase-1 steps."""
    label = df["config_label"].astype(str)
    study = label.map(lambda s: bool(SIZE_LABEL.match(s) or STEPS_LABEL.match(s)))
    return (df["method"] == "dmesh") & (df["input_kind"] == "pointcloud") & study


def _recipe(label: str) -> str | None:
    """The recipe of a run with gradient steps ("paper preset", "fast start, 2500 seeds + 200 steps", either
    with ", tangent weight 0.2"), or None."""
    paper, steps = PAPER_LABEL.match(label), STEPS_LABEL.match(label)
    if paper:
        name, weight = "paper preset", paper.group(1)
    elif steps:
        name, weight = f"fast start, {steps.group(1)} seeds + {steps.group(2)} steps", steps.group(3)
    else:
        return None
    return name + (f", tangent weight {weight}" if weight else "")


def _fast_runs(df):
    """Done point-cloud DMesh runs of the fast start: the size study plus the default (label "")."""
    label = df["config_label"].fillna("").astype(str)
    keep = (df["method"] == "dmesh") & (df["input_kind"] == "pointcloud") & (df["status"] == "done")
    return df[keep & label.map(lambda s: s == "" or bool(SIZE_LABEL.match(s)))]


def size_points(df) -> dict[str, list[tuple[float, float]]]:
    """shape -> [(faces, cd_p2s)] of its fast runs, ascending in faces."""
    out: dict[str, list[tuple[float, float]]] = {}
    for _, r in _fast_runs(df).iterrows():
        faces, cd = num(r.get("faces")), num(r.get("cd_p2s"))
        if faces and cd:
            out.setdefault(r["shape"], []).append((faces, cd))
    return {s: sorted(p) for s, p in out.items()}


def interpolate(points: list[tuple[float, float]], faces: float) -> float | None:
    """CD at `faces` on the log-log polyline through `points` (faces ascending); None outside their range."""
    for (f0, c0), (f1, c1) in zip(points, points[1:]):
        if f0 <= faces <= f1 and f1 > f0:
            t = (math.log(faces) - math.log(f0)) / (math.log(f1) - math.log(f0))
            return math.exp(math.log(c0) + t * (math.log(c1) - math.log(c0)))
    return None


def size_rows(df) -> list[dict]:
    """One row per done run with gradient steps (the paper preset, the fast start + steps; raw units), by class,
    shape and recipe."""
    if df is None or not len(df):
        return []
    points = size_points(df)
    fast = _fast_runs(df)
    done = df[(df["method"] == "dmesh") & (df["input_kind"] == "pointcloud") & (df["status"] == "done")]
    rows = []
    for _, r in done.iterrows():
        recipe = _recipe(str(r["config_label"]))
        if recipe is None:
            continue
        pts = points.get(r["shape"], [])
        faces, cd = num(r.get("faces")), num(r.get("cd_p2s"))
        at = interpolate(pts, faces) if faces else None
        default = fast[(fast["shape"] == r["shape"]) & (fast["config_label"].fillna("") == "")]
        d = default.iloc[-1] if len(default) else {}
        rows.append({"shape": r["shape"], "category": r["category"], "recipe": recipe, "faces": faces, "cd_p2s": cd,
                     "time_s": num(r.get("time_s")), "fast_cd_p2s_at_faces": at,
                     "ratio": at / cd if at and cd else None,
                     "fast_sizes": " ".join(f"{int(f)}" for f, _ in pts),
                     "fast_default_faces": num(d.get("faces")) if len(default) else None,
                     "fast_default_cd_p2s": num(d.get("cd_p2s")) if len(default) else None,
                     "fast_default_time_s": num(d.get("time_s")) if len(default) else None})
    order = {c: i for i, c in enumerate(CLASSES)}
    return sorted(rows, key=lambda x: (order.get(x["category"], 9), x["shape"],
                                       not x["recipe"].startswith("paper preset"), x["recipe"]))


def failed_rows(df) -> list[dict]:
    """The failed runs of the study (the fast start at some seed count, or a recipe with gradient steps): shape,
    class, recipe and error, by class and shape. They have no CD, so the tables above leave them out."""
    if df is None or not len(df):
        return []
    sub = df[(df["method"] == "dmesh") & (df["input_kind"] == "pointcloud") & (df["status"] == "failed")]
    rows = []
    for _, r in sub.iterrows():
        label = str(r["config_label"])
        recipe = _recipe(label) or (f"fast start, {label.split('=')[1]} seeds" if SIZE_LABEL.match(label) else None)
        if recipe is not None:
            rows.append({"shape": r["shape"], "category": r["category"], "recipe": recipe,
                         "error": str(r.get("error") or "")})
    order = {c: i for i, c in enumerate(CLASSES)}
    return sorted(rows, key=lambda x: (order.get(x["category"], 9), x["shape"], x["recipe"]))


def size_plot(df, rows: list[dict], out: Path) -> Path | None:
    """CD p2s against faces (log-log), one panel per class; None without a shape that has both recipes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    shapes = {r["shape"] for r in rows if r["fast_sizes"]}
    if not shapes:
        return None
    points = size_points(df)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
    cmap = plt.get_cmap("tab10")
    for ax, cls in zip(axes, CLASSES):
        names = sorted({r["shape"] for r in rows if r["category"] == cls and r["shape"] in shapes})
        for i, shape in enumerate(names):
            pts = points[shape]
            ax.plot([f for f, _ in pts], [c * 1e3 for _, c in pts], "-o", ms=3, color=cmap(i % 10),
                    label=f"{shape}: fast start")
            for r in (x for x in rows if x["shape"] == shape):
                paper, weighted = r["recipe"].startswith("paper preset"), "tangent weight" in r["recipe"]
                marker = ("P" if weighted else "*") if paper else ("D" if weighted else "^")
                ax.plot([r["faces"]], [r["cd_p2s"] * 1e3], marker, ms=13 if marker == "*" else 8,
                        color=cmap(i % 10), markeredgecolor="k", label=f"{shape}: {r['recipe']}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(cls)
        if not ax.lines:
            ax.text(0.5, 0.5, "no paper-preset run yet", transform=ax.transAxes, ha="center", va="center",
                    color="gray")
        ax.set_xlabel("output faces (log)")
        ax.grid(alpha=0.3, which="both")
        if ax.lines:
            ax.legend(fontsize=7)
    axes[0].set_ylabel("CD p2s (x1e-3, log)")
    fig.suptitle("DMesh on point clouds: runs with gradient steps (star: paper preset; triangle: fast start + "
                 "steps; diamond / plus: the same with a tangent weight) against the gradient-free fast start at "
                 "several seed counts (lines)", fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return out


def _summary(rows: list[dict]) -> list[dict]:
    """Per recipe and class: shapes, and the geometric mean of the ratio (fast start / stepped at equal faces)."""
    out = []
    for recipe in sorted({r["recipe"] for r in rows}, key=lambda x: (not x.startswith("paper preset"), x)):
        for cls in CLASSES:
            ratios = [r["ratio"] for r in rows if r["recipe"] == recipe and r["category"] == cls and r["ratio"]]
            if ratios:
                out.append({"recipe": recipe, "category": cls, "n": len(ratios),
                            "ratio": math.exp(sum(math.log(x) for x in ratios) / len(ratios))})
    return out


def write_size(df, out: str | Path) -> list[Path]:
    """Writes `recipes_size.{md,csv}` (and the figure when it has points) under `out`; returns the paths."""
    out = Path(out)
    rows = size_rows(df)
    fig = size_plot(df, rows, out / "figures" / "recipes_size.png") if rows else None
    md = ["# DMesh's gradient steps at equal mesh size (point clouds)", "",
          "The `paper` preset (10K seeds, 1000 + 500 gradient steps) returns 2K-5K faces; the `fast` preset "
          f"(up to {FAST_SEEDS // 1000}K seeds, no phase-1 step) about {2 * FAST_SEEDS // 1000}K, and CD p2s "
          "falls with mesh size whatever made the mesh. Here "
          "the fast start also runs at fewer seeds, once with phase-1 steps (`eval/sweeps/recipes_size.yaml`), "
          "and each run with gradient steps is compared with the gradient-free fast start interpolated (log-log) "
          "to the run's face count. *ratio* = fast start's CD at that face count / the run's CD: above 1, the "
          "gradient steps give a more accurate mesh of the same size. Blank: the face count is outside the fast "
          "sizes run. "
          f"{FRAME_NOTE} {CD_SHORT_NOTE} CD p2s x1e-3; the CSV holds raw distances.", ""]
    if rows:
        summary = _summary(rows)
        if summary:
            md += ["Per recipe and class (geometric mean of the ratio over the shapes):", "",
                   markdown(summary, [("recipe", "recipe", None), ("category", "class", None), ("n", "shapes", 1),
                                      ("ratio", "ratio", 1, ".2f")]), ""]
        md.append(markdown(rows, [
            ("shape", "shape", None), ("category", "class", None), ("recipe", "recipe", None),
            ("faces", "faces", 1, ".0f"), ("cd_p2s", "CD p2s", 1e3), ("time_s", "time (s)", 1, ".0f"),
            ("fast_cd_p2s_at_faces", "fast start's CD p2s at these faces", 1e3), ("ratio", "ratio", 1, ".2f"),
            ("fast_default_faces", "fast preset faces", 1, ".0f"),
            ("fast_default_cd_p2s", "fast preset CD p2s", 1e3),
            ("fast_default_time_s", "fast time (s)", 1, ".0f")]))
        if fig:
            md += ["", f"![CD against faces](figures/{fig.name})"]
    else:
        md.append("_No paper-preset point-cloud run in the store yet: `make reproduce-recipes` (recipes.yaml and "
                  "recipes_size.yaml)._\n")
    failed = failed_rows(df)
    if failed:
        md += ["", "## Failed runs", "", "Runs of the study that ended without a mesh; the tables above leave them "
               "out, so a class there may count fewer shapes:", "",
               markdown(failed, [("shape", "shape", None), ("category", "class", None), ("recipe", "recipe", None),
                                 ("error", "error", None)])]
    md += ["", "_Generated from the results store by `eval.reports`; do not edit by hand._", ""]
    md_path, csv_path = out / "recipes_size.md", out / "recipes_size.csv"
    write_text(md_path, "\n".join(md))
    write_text(csv_path, to_csv(rows, CSV_COLUMNS))
    return [md_path, csv_path] + ([fig] if fig else [])


__all__ = ["is_size_study", "size_points", "interpolate", "size_rows", "failed_rows", "size_plot", "write_size"]
