"""The one renderer of report tables, for Markdown and for HTML, so that the two cannot drift.

A table is its rows (dicts) and its columns: (key, header, scale[, format spec]), scale None for text. The same
column list renders as Markdown (`markdown`, the .md reports) and as HTML (`table_html`, index.html), and every
cell of both is the text of `cell` (3 significant digits via `fmt`, or the format spec). Each report defines its
columns once, beside its rows (`eval.reports.tables.table2_columns`, `TABLE1_COLUMNS`, ...), and hands the same
list to both. CSV files (`to_csv`) keep raw values.
"""
from __future__ import annotations

import html
import io
import math


def text(value) -> str:
    """A stored text field for display: "" for None and for NaN (what pandas puts in an empty text column)."""
    return value if isinstance(value, str) else ""


def fmt(v, digits: int = 3) -> str:
    """`digits` significant digits, never in exponent form below 1e6; "" for None / NaN."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "" if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)
    v = float(v)
    if v == 0:
        return "0"
    if abs(v) >= 1e6:
        return f"{v:.{digits - 1}e}"
    decimals = max(0, digits - 1 - int(math.floor(math.log10(abs(v)))))
    return f"{v:.{decimals}f}"


def num(v):
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(v) else v


def cell(v, scale: float | None, spec: str | None = None) -> str:
    """Text of one table cell: `v * scale` with 3 significant digits (or the format `spec`); text as is."""
    if v is None:
        return ""
    if scale is None or isinstance(v, str):
        return str(v)
    if isinstance(v, (int, bool)) and scale == 1 and spec is None:
        return str(int(v))
    if isinstance(v, float) and math.isnan(v):
        return ""
    return format(v * scale, spec) if spec else fmt(v * scale)


def md_text(text) -> str:
    """`text` (a name, a message, any value from data) as literal Markdown text on one line: `&`, `<` and `>`
    as HTML entities, so that no shape name or error message becomes HTML in a report (a shape file named
    `<img src=x onerror=...>.obj` shows as that text), and `|` escaped, so that it stays in its table cell."""
    return html.escape(" ".join(str(text).split()), quote=False).replace("|", "\\|")


def markdown(rows: list[dict], columns: list[tuple]) -> str:
    """A Markdown table; columns are (key, header, scale[, format spec]) with scale None for text. Every
    header and cell goes through `md_text`: the one place Markdown cells are formatted."""
    head = "| " + " | ".join(md_text(c[1]) for c in columns) + " |\n"
    sep = "|" + "|".join("---" if c[2] is None else "---:" for c in columns) + "|\n"
    body = ""
    for r in rows:
        cells = [md_text(cell(r.get(c[0]), c[2], c[3] if len(c) > 3 else None)) for c in columns]
        body += "| " + " | ".join(cells) + " |\n"
    return head + sep + body


def table_html(rows: list[dict], columns: list[tuple], paper_cols=None) -> str:
    """An HTML table of the same columns as `markdown` (text cells left aligned). Columns named in `paper_cols`
    (default: those whose key starts with "paper_") are shaded, as published numbers; failure cells are red."""
    if paper_cols is None:
        paper_cols = [c[0] for c in columns if c[0].startswith("paper_")]
    out = ["<table><tr>" + "".join(f"<th>{html.escape(c[1])}</th>" for c in columns) + "</tr>"]
    for r in rows:
        cells = []
        for c in columns:
            key, scale = c[0], c[2]
            v = r.get(key)
            cls = []
            if scale is None or isinstance(v, str):
                cls.append("t")
            if key in paper_cols:
                cls.append("paper")
            if key in ("failed", "status") and v not in (0, "done", None):
                cls.append("fail")
            attr = f' class="{" ".join(cls)}"' if cls else ""
            cells.append(f"<td{attr}>{html.escape(cell(v, scale, c[3] if len(c) > 3 else None))}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def to_csv(rows: list[dict], columns: list[str]) -> str:
    import csv

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: ("" if r.get(c) is None else (repr(r[c]) if isinstance(r[c], float) else r[c]))
                    for c in columns})
    return buf.getvalue()
