"""What a robustness run's input was: its corruption, the level of it, and how levels sort and read.

A run's corruption and level (`corruption_of`): a variant with one setting (`{noise: 0.005}`) is that
corruption at that level; the clean variant (`{}`) is every corruption at its clean level; a variant with
several settings is a combined setting, named "realistic_scan" when it holds a scan, its level being the
settings themselves. Used by the robustness report's rows (`eval.reports.robustness`) and figures
(`eval.reports.robustness_figures`).
"""
from __future__ import annotations

from eval.reports.labels import method_label

#: Corruptions in the order the report shows them.
FACTORS = ("noise", "outliers", "density", "nonuniform", "normals", "scan", "depth_noise", "views", "resolution")


#: Corruptions where a smaller level is the harder one (fewer points, cameras, views, pixels).
_DESCENDING = ("density", "scan", "views", "resolution")


CLASSES = ("closed", "open", "mixed")


def is_robustness(df):
    """(rows,) bool Series: the runs of `df` (a `Store.dataframe()`) made on a sweep variant."""
    if df is None or not len(df) or "inputs_json" not in df.columns:
        import pandas as pd

        return pd.Series(False, index=getattr(df, "index", None), dtype=bool)
    return df["inputs_json"].map(lambda s: isinstance(s, dict) and isinstance(s.get("corruption"), dict))


def has_runs(df) -> bool:
    """Whether `df` holds a run on a corrupted (not clean) input."""
    if df is None or not len(df):
        return False
    sub = df[is_robustness(df)]
    return bool(len(sub)) and any(corruption_of(s)[0] != "clean" for s in sub["inputs_json"])


def setting_label(corruption: dict) -> str:
    """"noise=0.005,outliers=0.01" ("clean" for {})."""
    return ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in sorted(corruption.items())) \
        or "clean"


def corruption_of(settings: dict) -> tuple[str, object]:
    """(corruption name, level) of a run's input settings (module docstring)."""
    c = dict(settings.get("corruption") or {})
    factors = [k for k in c if not (k == "normals" and "scan" in c)]
    if not factors:
        return "clean", None
    if len(factors) == 1:
        return factors[0], c[factors[0]]
    return ("realistic_scan" if "scan" in c else "combined"), setting_label(c)


def severity(factor: str, level, clean) -> tuple:
    """Sort key: the clean level first, then from the mildest to the harshest level."""
    if level == clean:
        return (0, 0.0, "")
    if isinstance(level, str):
        return (1, 0.0, level)
    return (1, -float(level) if factor in _DESCENDING else float(level), "")


def fmt_level(level) -> str:
    return f"{level:g}" if isinstance(level, float) else str(level)


def labelled(df):
    """The robustness runs of `df` with columns _kind_label (method label), _name and _level."""
    sub = df[is_robustness(df)].copy()
    named = sub["inputs_json"].map(corruption_of)
    sub["_name"] = named.map(lambda x: x[0])
    sub["_level"] = named.map(lambda x: x[1])
    sub["_label"] = [method_label(m, c, k) for m, k, c in
                     zip(sub["method"], sub["input_kind"], sub["config_label"])]
    return sub
