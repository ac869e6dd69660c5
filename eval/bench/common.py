"""Shared benchmark helpers: timing statistics, machine description, table writing."""
from __future__ import annotations

import os
import platform
import statistics
import subprocess
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

from eval.io import write_text


def time_call(fn: Callable[[], object], repeats: int, warmup: int = 1) -> dict:
    """Median, min and max wall time (s) of fn over `repeats` calls after `warmup` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return {"median": statistics.median(times), "min": min(times), "max": max(times), "n": repeats}


def git_hash() -> str:
    try:
        return subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], text=True,
                                       stderr=subprocess.DEVNULL).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine_info() -> dict:
    import numpy
    import torch

    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu, "cores": os.cpu_count(), "threads": torch.get_num_threads(),
        "python": platform.python_version(), "torch": torch.__version__, "numpy": numpy.__version__,
        "git": git_hash(), "load_average_1min": round(os.getloadavg()[0], 2),
    }


def markdown_table(rows: list[dict], columns: list[str], formats: dict[str, str] | None = None) -> str:
    formats = formats or {}
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    body = ""
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c, "")
            cells.append(format(v, formats[c]) if c in formats and isinstance(v, (int, float)) else str(v))
        body += "| " + " | ".join(cells) + " |\n"
    return head + body


#: The command a report's "Regenerate" line names; `python -m studies` sets it for the studies it runs.
REGENERATE = "python -m eval.bench"


def write_report(out: str | Path, name: str, title: str, intro: str, table: str, rows: list[dict]) -> Path:
    """Writes <out>/<name>.md (with machine info) and <out>/<name>.csv."""
    import csv
    import io

    out = Path(out)
    info = machine_info()
    machine = ", ".join(f"{k} {v}" for k, v in info.items())
    md = (f"# {title}\n\n{intro}\n\n{table}\nMachine: {machine}.\n\n"
          f"Regenerate: `{REGENERATE} {name.removeprefix('bench_')}`.\n")
    write_text(out / f"{name}.md", md)
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    write_text(out / f"{name}.csv", buf.getvalue())
    return out / f"{name}.md"


def write_cd_report(out: str | Path, name: str, title: str, doc: str, rows: list[dict], cols: list[str],
                    fmt: dict) -> Path:
    """`write_report` for rows holding a raw `cd_p2s`: the table shows it x1e-3 (the CSV keeps raw distances)
    and the intro is the first two paragraphs of `doc` (a bench module's docstring)."""
    shown = [{**r, "cd_p2s": r["cd_p2s"] * 1e3} for r in rows]
    intro = "\n\n".join(doc.split("\n\n")[:2]) + "\n\nCD p2s in the table is x1e-3 (the CSV holds raw distances)."
    return write_report(out, name, title, intro, markdown_table(shown, cols, {"cd_p2s": ".3f", **fmt}), rows)


def run_mesh_rows(grid: list[tuple], one_run: Callable[..., dict], label: Callable[..., str]) -> list[dict]:
    """The rows `one_run(*args)` for each args tuple of `grid`, each printed as it lands: `label(*args)`, then
    its CD p2s (x1e-3), components, boundary edges and seconds (the keys of the mesh benches' rows)."""
    rows = []
    for args in grid:
        r = one_run(*args)
        rows.append(r)
        print(f"{label(*args)}: CD p2s {r['cd_p2s'] * 1e3:.3f} x1e-3, {r['components']} components, "
              f"{r['boundary_edges']} boundary edges, {r['seconds']:.0f} s", flush=True)
    return rows


def mesh_figures(mesh, gt_path) -> dict:
    """The figures of the mesh benches' rows: CD p2s against the GT at `gt_path` (100K samples per side, as the
    tables), faces, boundary edges and connected components."""
    from eval.metrics import chamfer_l1_p2s, mesh_stats
    from eval.inputs import load_gt

    stats = mesh_stats(mesh, self_intersections=False)
    return {"cd_p2s": chamfer_l1_p2s(mesh, load_gt(gt_path), n=100_000), "faces": stats["faces"],
            "boundary_edges": stats["boundary_edges"], "components": stats["components"]}
