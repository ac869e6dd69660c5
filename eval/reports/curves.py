"""CD p2s and loss against the step of DMesh runs that took gradient steps (one shape per class).

A DMesh point-cloud run records `info["curve"]` (`baselines/dmesh_pointcloud.py`): every 50 steps of each
phase, the loss and the harness monitor's CD p2s of the mesh extracted at that step against the GT. The
figure draws, for each configuration with curves, the first shape of each class that has one.
"""
from __future__ import annotations

from pathlib import Path

from eval.io import atomic_path

CLASSES = ("closed", "open", "mixed")


def curve_runs(df, input_kind: str = "pointcloud") -> list[dict]:
    """[{"label", "shape", "category", "curve"}]: one done run per (configuration, class) with a curve of at
    least two points."""
    from eval.reports.labels import method_label

    if not len(df) or "info" not in df.columns:
        return []
    sub = df[(df["input_kind"] == input_kind) & (df["status"] == "done")].sort_values(
        ["method", "config_label", "shape"])
    out, seen = [], set()
    for _, r in sub.iterrows():
        curve = (r["info"] or {}).get("curve") if isinstance(r["info"], dict) else None
        key = (r["method"], r["config_label"], r["category"])
        if not curve or len(curve) < 2 or key in seen:
            continue
        seen.add(key)
        out.append({"label": method_label(r["method"], r["config_label"], input_kind),
                    "shape": r["shape"], "category": r["category"], "curve": curve})
    return out


def _x(curve: list[dict]) -> list[int]:
    """Global step numbers: phase-2 steps continue after the last phase-1 step."""
    last1 = max((p["step"] for p in curve if p["phase"] == 1), default=-1)
    return [p["step"] + 1 + (last1 + 1 if p["phase"] == 2 else 0) for p in curve]


def curve_figure(runs: list[dict], out: str | Path, title: str) -> Path | None:
    """Two panels (CD p2s x1e-3, loss) against the step, one line per run; None without runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not runs:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    cmap = plt.get_cmap("tab10")
    for i, r in enumerate(runs):
        xs = _x(r["curve"])
        name = f"{r['label']}: {r['shape']} ({r['category']})"
        cd = [p.get("cd_p2s") for p in r["curve"]]
        axes[0].plot(xs, [c * 1e3 if c is not None else float("nan") for c in cd], "-o", ms=2.5,
                     color=cmap(i % 10), label=name)
        axes[1].plot(xs, [p["loss"] for p in r["curve"]], "-o", ms=2.5, color=cmap(i % 10), label=name)
        last1 = max((x for x, p in zip(xs, r["curve"]) if p["phase"] == 1), default=None)
        if last1 is not None and i == 0:
            for ax in axes:
                ax.axvline(last1, color="gray", lw=0.8, ls=":")
    axes[0].set_ylabel("CD p2s of the extracted mesh (x1e-3, log)")
    axes[1].set_ylabel("loss (expected Chamfer + regularisers, log)")
    for ax in axes:
        ax.set_yscale("log")
        ax.set_xlabel("step (dotted: end of phase 1)")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return out


__all__ = ["curve_runs", "curve_figure"]
