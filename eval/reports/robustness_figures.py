"""The figures of the robustness report (`eval.reports.robustness`): CD p2s against the corruption level, CD p2s
against output faces at matched budgets, and renders of the realistic-scan setting.

    figures/robustness_<kind>.png          CD p2s against level, one panel per class and corruption (`line_plots`)
    figures/robustness_budget_<kind>.png   matched budget: CD p2s against output face count, one panel per class
                                           (`budget_plot`)
    figures/robustness_scan_<shape>.png    renders of the realistic-scan setting: GT, the scan, each method
                                           (`scan_renders`)
"""
from __future__ import annotations

import logging
from pathlib import Path

from eval.reports.corruptions import CLASSES, FACTORS, fmt_level, labelled, severity

log = logging.getLogger(__name__)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_levels(rows: list[dict], name: str) -> list:
    """The levels of one panel's `robustness_rows` (all methods of one class and corruption), clean first, then
    from the mildest to the harshest. Each method's rows are in that order already, but a method run on fewer
    levels (a study at 0.5 % noise only) would otherwise put its levels first."""
    clean = {r["level"] for r in rows if r.get("setting") == "clean"}
    return sorted({r["level"] for r in rows}, key=lambda v: (0, 0.0, "") if v in clean else severity(name, v, None))


def matched_values(rows: list[dict]) -> tuple[dict[int, float | None], list[str] | None]:
    """CD p2s of one panel's rows (all methods of one class and corruption) over the same shapes.

    A study may run on fewer shapes than the sweep beside it (one per class against two), and a mean over
    other shapes is no comparison. When the methods' shape sets differ, each row's value is its mean over the
    shapes every method of the panel ran (its `per_shape`); returns ({id(row): value}, those shapes), or the
    rows' own means and None when the sets agree (or have no shape in common).
    """
    sets: dict[str, set] = {}
    for r in rows:
        sets.setdefault(r["method"], set()).update(r.get("per_shape") or {})
    common = set.intersection(*sets.values()) if sets else set()
    if not common or all(v == common for v in sets.values()):
        return {id(r): r["cd_p2s"] for r in rows}, None
    out = {}
    for r in rows:
        vals = [r["per_shape"][s] for s in common if s in (r.get("per_shape") or {})]
        out[id(r)] = sum(vals) / len(vals) if vals else None
    return out, sorted(common)


def line_plots(rows: list[dict], kind: str, out: Path) -> Path | None:
    """CD p2s (x1e-3, log) against level, one panel per class (rows) and corruption (columns); in a panel
    whose methods ran on different shapes, over the shapes they all ran (`matched_values`, named in the
    panel's title)."""
    rows = [r for r in rows if r["input"] == kind and r["corruption"] in FACTORS]
    if not rows:
        return None
    plt = _pyplot()
    cats = [c for c in CLASSES if any(r["category"] == c for r in rows)]
    names = [f for f in FACTORS if any(r["corruption"] == f for r in rows)]
    methods = sorted({r["method"] for r in rows})
    cmap = plt.get_cmap("tab10")
    fig, axes = plt.subplots(len(cats), len(names), figsize=(max(6.5, 3.1 * len(names)), 2.6 * len(cats) + 0.8),
                             squeeze=False)
    for i, cat in enumerate(cats):
        for j, name in enumerate(names):
            ax = axes[i, j]
            rs = [r for r in rows if r["category"] == cat and r["corruption"] == name]
            levels = plot_levels(rs, name)
            value, common = matched_values(rs)
            for k, m in enumerate(methods):
                pts = [(levels.index(r["level"]), value[id(r)] * 1e3) for r in rs
                       if r["method"] == m and value[id(r)] is not None and value[id(r)] > 0]
                if pts:
                    ax.plot(*zip(*pts), marker="o", ms=3.5, lw=1.3, color=cmap(k % 10), label=m)
            ax.set_xticks(range(len(levels)), [fmt_level(v) for v in levels], fontsize=7)
            ax.set_yscale("log")
            _plain_ticks(ax)
            ax.grid(alpha=0.3, which="both")
            ax.set_title(f"{name} ({cat})" + (f"\n{', '.join(common)} only" if common else ""), fontsize=9)
            if j == 0:
                ax.set_ylabel("CD p2s (x1e-3)", fontsize=8)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(6, len(labels) or 1), fontsize=8)
    fig.suptitle(f"Robustness, {kind} input: CD p2s against the corruption level (clean level first)", fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    return _save(fig, plt, out)


def budget_plot(rows: list[dict], kind: str, out: Path) -> Path | None:
    """CD p2s against output faces (log-log), one panel per class: solid lines join a method's configs on the
    full input, dashed lines its default config at lower input densities."""
    rows = [r for r in rows if r["input"] == kind and r["faces"] and r["cd_p2s"]]
    sizes = {}
    for r in rows:
        sizes[(r["method"], r["category"])] = sizes.get((r["method"], r["category"]), 0) + 1
    if not sizes or max(sizes.values()) < 2:  # no method at two sizes: nothing to match
        return None
    plt = _pyplot()
    cats = [c for c in CLASSES if any(r["category"] == c for r in rows)]
    methods = sorted({r["method"] for r in rows})
    full = max(r["density"] or 0 for r in rows)
    cmap = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, len(cats), figsize=(4.2 * len(cats), 3.8), squeeze=False)
    for ax, cat in zip(axes[0], cats):
        for k, m in enumerate(methods):
            rs = [r for r in rows if r["category"] == cat and r["method"] == m]
            for sel, style in (([r for r in rs if r["density"] == full], "-"),
                               ([r for r in rs if r["config"] == "default"], "--")):
                sel = sorted(sel, key=lambda r: r["faces"])
                if sel:
                    ax.plot([r["faces"] for r in sel], [r["cd_p2s"] * 1e3 for r in sel], style, marker="o", ms=3.5,
                            color=cmap(k % 10), label=m if style == "-" else None)
        ax.set_xscale("log")
        ax.set_yscale("log")
        _plain_ticks(ax, "y")
        ax.grid(alpha=0.3, which="both")
        ax.set_xlabel("output faces")
        ax.set_title(cat, fontsize=9)
    axes[0, 0].set_ylabel("CD p2s (x1e-3)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"Matched budget, {kind} input: accuracy against mesh size (solid: configs at {full} points; "
                 "dashed: default config at lower densities)", fontsize=9)
    fig.tight_layout()
    return _save(fig, plt, out)


def _plain_ticks(ax, axes: str = "y") -> None:
    """Log-axis ticks at 1, 2, 5 x 10^k, labelled as plain numbers (0.2, 1, 5) instead of powers of ten."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for name in axes:
        axis = ax.yaxis if name == "y" else ax.xaxis
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


def _save(fig, plt, out: Path) -> Path:
    from eval.io import atomic_path

    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
    return out


def scan_renders(df, db: Path, work: Path, figdir: Path) -> list[tuple[str, Path]]:
    """One figure per shape of the realistic-scan runs (point clouds): GT, the scanned input, each method's mesh.

    A figure whose GT, input or a done run's mesh is missing here (a fresh clone with only the store export) is
    not redrawn: the figure already in `figdir`, if any, is kept and listed."""
    from eval.reports import figures, tables
    from eval.execute import resolve_mesh_path
    from eval.inputs import input_path, shape_dir
    from eval.shapes import ShapeRef

    sub = labelled(df)
    sub = sub[(sub["_name"] == "realistic_scan") & (sub["input_kind"] == "pointcloud")]
    cache, out = work / "renders", []
    for (cat, shape, setting), g in sub.groupby(["category", "shape", "_level"], sort=True):
        first = g.sort_values("seed").iloc[0]
        settings, name = first["inputs_json"], f"robustness_scan_{figures.safe_name(shape)}.png"
        title = f"{shape} ({cat}), realistic scan: {setting}, seed {int(first['seed'])}"
        ref = ShapeRef(id=shape, kind="file", source="", gt_hash=first["gt_hash"] or "")
        gt = shape_dir(work, ref, float(settings.get("radius", 1.0))) / "gt.ply"
        pc = input_path(work, ref, "pointcloud", settings, int(first["seed"]))
        runs = g[g["seed"] == first["seed"]].sort_values(["method", "config_label"])
        meshes = [resolve_mesh_path(r.to_dict(), db) for _, r in runs.iterrows()]
        missing = not gt.is_file() or not pc.is_file() or any(
            r["status"] == "done" and (p is None or not p.is_file()) for (_, r), p in zip(runs.iterrows(), meshes))
        if missing:
            if (figdir / name).is_file():
                out.append((title, figdir / name))
            continue
        try:
            panels = [("ground truth", figures.cached_render(gt, cache)),
                      (f"input: {len(_points(pc))} scanned points", figures.cached_render(pc, cache, "points"))]
            for (_, r), p in zip(runs.iterrows(), meshes):
                label = tables.method_label(r["method"], r["config_label"], r["input_kind"])
                if r["status"] == "done":
                    panels.append((f"{label}\nCD p2s {tables.fmt(float(r['cd_p2s']) * 1e3)}e-3",
                                   figures.cached_render(p, cache)))
                else:
                    panels.append((f"{label}\n{r['status']}", figures._placeholder(r["status"])))
            out.append((title, figures.side_by_side(panels, figdir / name, title, cache=cache)))
        except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not lose the tables
            log.warning("realistic-scan renders for %s skipped: %s", shape, exc)
    return out


def _points(path: Path):
    import numpy as np

    with np.load(path) as z:
        return z["points"]
