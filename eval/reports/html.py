"""`reports/index.html`: one page linking and showing every table and figure of a report folder."""
from __future__ import annotations

import html
from pathlib import Path

from eval.io import write_text
from eval.reports.render import table_html  # noqa: F401 - re-exported

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:24px auto;max-width:1200px;
color:#222;padding:0 16px;line-height:1.4}
h1{font-size:1.5em;margin-bottom:4px} \
h2{font-size:1.2em;margin-top:28px;border-bottom:1px solid #ddd;padding-bottom:3px}
h3{font-size:1.0em;margin:18px 0 6px} p.note{color:#555;font-size:.88em;max-width:1000px}
table{border-collapse:collapse;font-size:.85em;margin:6px 0 10px}
th,td{border:1px solid #d6d6d6;padding:3px 8px;text-align:right;white-space:nowrap}
th{background:#f3f5f8} td.t{text-align:left} tr:nth-child(even) td{background:#fafbfc}
td.paper{color:#666;background:#f7f4ec!important} td.fail{color:#b22}
img{max-width:100%;border:1px solid #e3e3e3;margin:4px 0}
.links a{margin-right:14px} .meta{color:#666;font-size:.85em}
"""


def write_index(out: str | Path, sections: list[tuple[str, str]], title: str, meta: str) -> Path:
    """Writes `out/index.html`; `sections` are (heading, HTML body) pairs."""
    out = Path(out)
    body = [f"<h1>{html.escape(title)}</h1>", f"<div class='meta'>{meta}</div>"]
    toc = " ".join(f"<a href='#s{i}'>{html.escape(h)}</a>" for i, (h, _) in enumerate(sections))
    body.append(f"<p class='links'>{toc}</p>")
    for i, (heading, content) in enumerate(sections):
        body.append(f"<h2 id='s{i}'>{html.escape(heading)}</h2>\n{content}")
    page = ("<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")
    path = out / "index.html"
    write_text(path, page)
    return path
