"""The HTML document: escaped cells, tables, sections, and the page itself with plotly.js
inlined and a Content-Security-Policy under which the browser loads nothing from outside the
file (no URL, no server: it opens offline)."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

# inline scripts and styles only; images and fonts only from data: (plotly's own icons)
CSP = ("default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
       "img-src data: blob:; font-src data:")

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 1.5em auto; max-width: 1200px;
       padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; margin-bottom: .2em; } h2 { font-size: 1.2em; margin-top: 1.6em;
  border-bottom: 1px solid #ddd; } h3 { font-size: 1.05em; }
table { border-collapse: collapse; margin: .5em 0; font-size: 13px; }
th, td { border: 1px solid #ddd; padding: 2px 8px; text-align: left; vertical-align: top; }
th { background: #f4f4f4; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.fail td { background: #fde8e8; } tr.pass td.verdict { color: #176f2c; }
tr.fail td.verdict { color: #b00020; font-weight: 600; }
.badge { display: inline-block; padding: 2px 10px; border-radius: 4px; font-weight: 600;
  color: #fff; } .badge.pass { background: #2e7d32; } .badge.fail { background: #c62828; }
.badge.none { background: #757575; }
.note { background: #fff8e1; border-left: 4px solid #f9a825; padding: .4em .8em; }
.damage { background: #fdecea; border-left: 4px solid #c62828; padding: .4em .8em; }
pre { background: #f7f7f7; padding: .6em; overflow-x: auto; font-size: 12px; }
"""


def text(value: Any) -> str:
    """A value as the page shows it: numbers to 6 significant digits, none as a dash."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    return str(value)


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]],
          row_classes: Sequence[str] | None = None) -> str:
    """An HTML table; numbers right-aligned, a cell given as ``(value, css_class)`` gets that
    class (``verdict``)."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
    body = []
    for index, row in enumerate(rows):
        cells = []
        for cell in row:
            value, css = cell if isinstance(cell, tuple) else (cell, "")
            if not css and isinstance(value, int | float) and not isinstance(value, bool):
                css = "num"
            attr = f' class="{css}"' if css else ""
            cells.append(f"<td{attr}>{html.escape(text(value))}</td>")
        css = row_classes[index] if row_classes else ""
        attr = f' class="{css}"' if css else ""
        body.append(f"<tr{attr}>{''.join(cells)}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def section(title: str, *parts: str, anchor: str = "") -> str:
    """A titled section of the page."""
    ident = f' id="{html.escape(anchor)}"' if anchor else ""
    return f"<section{ident}><h2>{html.escape(title)}</h2>{''.join(parts)}</section>"


def paragraph(words: str, css: str = "") -> str:
    attr = f' class="{css}"' if css else ""
    return f"<p{attr}>{html.escape(words)}</p>"


def badge(passed: bool | None, words: str) -> str:
    """PASSED / FAILED (or a neutral word when there is no verdict) as a coloured label."""
    css = "none" if passed is None else "pass" if passed else "fail"
    return f'<span class="badge {css}">{html.escape(words)}</span>'


def document(title: str, body: Sequence[str], plotly_js: str) -> str:
    """The whole page: plotly.js in its head (before the figures' own scripts)."""
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<meta http-equiv=\"Content-Security-Policy\" content=\"{CSP}\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>{html.escape(title)}</title><style>{STYLE}</style>"
        f"<script>{plotly_js}</script></head>\n<body>\n" + "\n".join(body) +
        "\n</body></html>\n")
