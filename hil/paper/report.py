"""What the papers' reproductions share: the options of a reproduction, the "paper | hil |
ratio" tables, the figures, and the report written three ways (Markdown with its PNGs, one
self-contained HTML page through :mod:`hil.core.html_report.page`, JSON), with the check that
every table and figure of the paper is in it.

A report's folder (``--out``, default ``papers``) holds ``NAME.md``, ``NAME.html`` and
``NAME.json``; the figures are PNGs in ``NAME/`` and the sessions behind them in
``NAME/sessions/``.
"""

from __future__ import annotations

import base64
import html
import json
import re
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from hil.core.html_report import page

COMPARISON_COLUMNS = ("", "paper", "hil", "hil / paper", "note")


@dataclass(frozen=True)
class PaperOptions:
    """How to reproduce a paper: ``quick`` (a shortened set of runs that still makes every
    table and figure), into the folder ``out``, progress on ``stream``."""

    name: str
    quick: bool = False
    out: Path = Path("papers")
    stream: TextIO = field(default_factory=lambda: sys.stderr)

    @property
    def figures(self) -> Path:
        """The folder of the report's PNGs."""
        return self.out / self.name

    @property
    def sessions(self) -> Path:
        """The folder of the sessions the report is drawn from."""
        return self.out / self.name / "sessions"

    def progress(self, text: str) -> None:
        """One line of progress on the terminal (stderr)."""
        self.stream.write(f"hil paper {self.name}: {text}\n")
        self.stream.flush()


@dataclass(frozen=True)
class Compared:
    """One cell of a paper's table: the paper's value beside hil's (None: not given)."""

    label: str
    paper: float | None
    hil: float | None
    note: str = ""

    @property
    def ratio(self) -> float | None:
        """hil / paper, when both are given and the paper's is not 0."""
        if self.paper is None or self.hil is None or self.paper == 0:
            return None
        return self.hil / self.paper


@dataclass(frozen=True)
class Table:
    """A table of the report; ``key`` names what of the paper it reproduces ("Table II")."""

    key: str
    title: str
    columns: tuple[str, ...]
    rows: tuple[tuple[Any, ...], ...]

    def markdown(self) -> str:
        head = "| " + " | ".join(self.columns) + " |"
        rule = "|" + "|".join("---" if n == 0 else "---:" if self._numeric(n) else "---"
                              for n in range(len(self.columns))) + "|"
        body = ["| " + " | ".join(cell_text(c).replace("|", "\\|") for c in row) + " |"
                for row in self.rows]
        return "\n".join([f"**{self.key}: {self.title}**", "", head, rule, *body])

    def html(self) -> str:
        rows = [[cell_text(c) if not _is_number(c) else c for c in row] for row in self.rows]
        return (f"<h3>{html.escape(f'{self.key}: {self.title}')}</h3>"
                + page.table(list(self.columns), rows))

    def _numeric(self, column: int) -> bool:
        return any(_is_number(row[column]) for row in self.rows if column < len(row))


def comparison_table(key: str, title: str, cells: Sequence[Compared]) -> Table:
    """The paper's cells as rows: the cell, the paper's value, hil's, hil / paper, a note."""
    rows = tuple((c.label, c.paper, c.hil, None if c.ratio is None else f"{c.ratio:.3f}",
                  c.note) for c in cells)
    return Table(key, title, COMPARISON_COLUMNS, rows)


@dataclass(frozen=True)
class Figure:
    """A figure of the report: ``key`` the paper's ("Fig. 4a"), ``file`` the PNG."""

    key: str
    title: str
    file: Path
    caption: str = ""


Part = str | Table | Figure   # a paragraph (Markdown), a table or a figure


@dataclass(frozen=True)
class Section:
    title: str
    parts: tuple[Part, ...]


@dataclass
class PaperReport:
    """A paper reproduced: ``expected`` lists its tables and figures (the paper's names),
    ``sections`` hold hil's, ``results`` the figures as data (the JSON's ``results``)."""

    name: str
    title: str
    source: str
    expected: tuple[str, ...]
    sections: list[Section]
    results: dict[str, Any]
    quick: bool
    started: float = field(default_factory=time.monotonic)
    wall_s: float = 0.0

    def items(self) -> list[str]:
        """The keys of the tables and figures in the report (a figure only if its PNG is)."""
        return [part.key for section in self.sections for part in section.parts
                if isinstance(part, Table) or (isinstance(part, Figure) and part.file.is_file())]

    def missing(self) -> list[str]:
        """The paper's tables and figures the report lacks."""
        present = set(self.items())
        return [key for key in self.expected if key not in present]


@dataclass(frozen=True)
class ReportFiles:
    markdown: Path
    html: Path
    json: Path


def write_report(report: PaperReport, out: Path) -> ReportFiles:
    """Write ``NAME.md``, ``NAME.html`` and ``NAME.json`` of ``report`` into ``out``."""
    if not report.wall_s:
        report.wall_s = time.monotonic() - report.started
    files = ReportFiles(out / f"{report.name}.md", out / f"{report.name}.html",
                        out / f"{report.name}.json")
    files.markdown.write_text(markdown(report, out), encoding="utf-8")
    files.html.write_text(html_page(report), encoding="utf-8")
    files.json.write_text(json.dumps(report_json(report, out), indent=2, allow_nan=False) + "\n",
                          encoding="utf-8")
    return files


def markdown(report: PaperReport, out: Path) -> str:
    lines = [f"# {report.title}", "", _provenance(report), ""]
    for section in report.sections:
        lines += [f"## {section.title}", ""]
        for part in section.parts:
            if isinstance(part, Table):
                lines += [part.markdown(), ""]
            elif isinstance(part, Figure):
                relative = part.file.relative_to(out).as_posix()
                lines += [f"![{part.key}: {part.title}]({relative})", "",
                          f"*{part.key}: {part.title}.* {part.caption}".rstrip(), ""]
            else:
                lines += [part, ""]
    return "\n".join(lines).rstrip() + "\n"


def html_page(report: PaperReport) -> str:
    """The report as one page that opens offline (figures inlined as data: URIs)."""
    body = [f"<h1>{html.escape(report.title)}</h1>", _html_text(_provenance(report))]
    for section in report.sections:
        parts = []
        for part in section.parts:
            if isinstance(part, Table):
                parts.append(part.html())
            elif isinstance(part, Figure):
                data = base64.b64encode(part.file.read_bytes()).decode("ascii") \
                    if part.file.is_file() else ""
                parts.append(f'<figure><img alt="{html.escape(part.key)}" style="max-width:100%"'
                             f' src="data:image/png;base64,{data}"><figcaption>'
                             f"<b>{html.escape(f'{part.key}: {part.title}.')}</b> "
                             f"{_inline(part.caption)}</figcaption></figure>")
            else:
                parts.append(_html_text(part))
        body.append(page.section(section.title, *parts))
    return page.document(report.title, body, plotly_js="")


def report_json(report: PaperReport, out: Path) -> dict[str, Any]:
    """``NAME.json``: what was reproduced, what is missing, every table and the results."""
    tables = {part.key: {"title": part.title, "columns": list(part.columns),
                         "rows": [list(row) for row in part.rows]}
              for section in report.sections for part in section.parts
              if isinstance(part, Table)}
    figures = {part.key: part.file.relative_to(out).as_posix()
               for section in report.sections for part in section.parts
               if isinstance(part, Figure)}
    return {"paper": report.name, "title": report.title, "quick": report.quick,
            "wall_s": round(report.wall_s, 1), "expected": list(report.expected),
            "missing": report.missing(), "tables": tables, "figures": figures,
            "results": report.results}


def cell_text(value: Any) -> str:
    """A cell as the report prints it: thousands grouped, else 4 significant digits."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        value += 0.0  # -0.0 reads 0
        return f"{value:,.0f}" if abs(value) >= 1000 else f"{value:.4g}"
    return str(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _provenance(report: PaperReport) -> str:
    mode = ("a quick run (`--quick`: shortened runs; every table and figure, figures not "
            "worth quoting)" if report.quick else "the full run")
    return (f"Paper: {report.source}. Reproduced by `hil paper {report.name}`, {mode}, in "
            f"{report.wall_s:.0f} s, every experiment in lockstep on hil's emulators.")


def _inline(text: str) -> str:
    """Markdown's `code` and **bold** of a paragraph, as HTML (the rest escaped)."""
    escaped = html.escape(text)
    escaped = re.sub(r"`([^`]+)`", r"<code>\1</code>", escaped)
    return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", escaped)


def _html_text(text: str) -> str:
    """A Markdown paragraph (or a list of ``- `` lines) as HTML."""
    lines = text.splitlines()
    if lines and all(line.startswith("- ") for line in lines):
        return "<ul>" + "".join(f"<li>{_inline(line[2:])}</li>" for line in lines) + "</ul>"
    return f"<p>{_inline(text)}</p>"



def pyplot() -> Any:
    """matplotlib's pyplot on its file backend (imported when a figure is drawn)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path | str, dpi: int) -> Path:
    """``fig`` laid out, written to ``path`` and closed; the path."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return Path(path)
