"""Checks across the stored runs: what went wrong between a method's last step and its output.

A DMesh run with gradient steps records the harness monitor's CD p2s of the mesh extracted every few steps
(`info["curve"]`, `baselines/dmesh_pointcloud.py`). That extraction is the raw one; the returned mesh has also
been through the surface step (inside/outside vote, hole filling, orientation). A final CD well above the last
monitored one means the post-process damaged the mesh, which no table shows by itself. CD p2s has no sampling
floor, so the two figures agree closely on an undamaged run although the monitor uses 20K samples per side
and the final metrics the sweep's count.

    checks.md / .csv    every done run whose final CD p2s exceeds its last monitored one by more than
                        `GAP_RATIO`, with the number of runs checked
"""
from __future__ import annotations

from pathlib import Path

from eval.io import write_text
from eval.reports.labels import method_label
from eval.reports.render import markdown, num, to_csv
from eval.reports.tables import CD_SHORT_NOTE, FRAME_NOTE

#: Final CD p2s / last monitored CD p2s above which a run is listed (README, "Damage after the last step").
GAP_RATIO = 1.25
CSV_COLUMNS = ["method", "shape", "category", "input_kind", "seed", "key", "last_step", "monitor_cd_p2s",
               "cd_p2s", "ratio", "earlier_code"]


def monitor_gap(info, cd_p2s) -> tuple[float, dict] | None:
    """(final CD / last monitored CD, that curve point), or None when the run has no monitored CD or no final
    one."""
    curve = info.get("curve") if isinstance(info, dict) else None
    points = [p for p in curve or [] if isinstance(p, dict) and p.get("cd_p2s")]
    final = num(cd_p2s)
    if not points or final is None:
        return None
    last = points[-1]
    return final / float(last["cd_p2s"]), last


def gap_rows(df, ratio: float = GAP_RATIO) -> tuple[list[dict], list[float]]:
    """(runs over `ratio`, worst first; the ratio of every done run with a monitored curve) of a
    `Store.dataframe()` selection."""
    if df is None or not len(df) or "info" not in df.columns:
        return [], []
    from eval.reports.recipes import current_code_version, made_by_earlier_code

    now = {m: current_code_version(m) for m in set(df["method"])}
    rows, ratios = [], []
    for _, r in df[df["status"] == "done"].iterrows():
        gap = monitor_gap(r["info"], r.get("cd_p2s"))
        if gap is None:
            continue
        ratios.append(gap[0])
        if gap[0] <= ratio:
            continue
        last = gap[1]
        rows.append({"method": method_label(r["method"], r["config_label"], r["input_kind"]),
                     "shape": r["shape"], "category": r["category"], "input_kind": r["input_kind"],
                     "seed": int(r["seed"]), "key": r["key"],
                     "last_step": f"phase {last.get('phase')}, step {last.get('step')}",
                     "monitor_cd_p2s": float(last["cd_p2s"]), "cd_p2s": float(r["cd_p2s"]), "ratio": gap[0],
                     "earlier_code": "yes" if made_by_earlier_code(r, now.get(r["method"])) else ""})
    rows.sort(key=lambda row: -row["ratio"])
    return rows, ratios


#: The columns of the checks table (`gap_rows`), in checks.md and on index.html alike (CD p2s x1e-3).
COLUMNS = [("method", "method", None), ("shape", "shape", None), ("category", "class", None),
           ("input_kind", "input", None), ("seed", "seed", 1), ("last_step", "last monitored", None),
           ("monitor_cd_p2s", "monitor CD p2s", 1e3), ("cd_p2s", "final CD p2s", 1e3), ("ratio", "ratio", 1, ".2f"),
           ("earlier_code", "earlier code", None)]


def summary(ratios: list[float]) -> str:
    """" The others: LO-HI." (the range of the ratios at most `GAP_RATIO`), or "" when there are none."""
    others = [r for r in ratios if r <= GAP_RATIO]
    return f" The others: {min(others):.2f}-{max(others):.2f}." if others else ""


def write_checks(rows: list[dict], ratios: list[float], out: str | Path) -> list[Path]:
    """Writes `checks.{md,csv}` under `out` from `gap_rows`' result; returns the paths."""
    out = Path(out)
    md = ["# Checks: final mesh against the last monitored mesh", "",
          "Every done run whose final CD p2s is more than "
          f"{GAP_RATIO:g}x the harness monitor's CD p2s of its last monitored mesh (the raw extraction during the "
          "steps, 20K samples per side; the final figure has the sweep's samples and comes after the surface "
          "step). A listed run lost accuracy after its last step: look at its render and its surface step. "
          "*earlier code*: the method's code has changed since the run. " + FRAME_NOTE + " " + CD_SHORT_NOTE
          + " CD p2s x1e-3.", ""]
    md.append(f"Runs with a monitored curve: {len(ratios)}; over {GAP_RATIO:g}x: {len(rows)}." + summary(ratios))
    md.append("")
    if rows:
        md.append(markdown(rows, COLUMNS))
    md += ["", "_Generated from the results store by `eval.reports`; do not edit by hand._", ""]
    md_path, csv_path = out / "checks.md", out / "checks.csv"
    write_text(md_path, "\n".join(md))
    write_text(csv_path, to_csv(rows, CSV_COLUMNS))
    return [md_path, csv_path]


__all__ = ["GAP_RATIO", "COLUMNS", "monitor_gap", "gap_rows", "summary", "write_checks"]
