"""The frame the papers share (``hil.paper.report``, ``hil paper NAME``): the "paper | hil |
ratio" tables, the report written as Markdown, HTML and JSON, and the completeness check that
makes ``hil paper`` exit 1 naming what a report lacks. No experiment runs here: a small paper
module of the tests' own stands in for a paper."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.cli.paper import PAPERS, Paper
from hil.paper.report import (
    Compared,
    Figure,
    PaperOptions,
    PaperReport,
    Section,
    Table,
    cell_text,
    comparison_table,
    write_report,
)
from tests.cli import hil_here

PNG = bytes.fromhex("89504e470d0a1a0a")  # a PNG signature: the report only inlines the file


def small_report(out: Path, *, draw: bool = True) -> PaperReport:
    """A report of a made-up paper with one table and one figure (its PNG drawn or not)."""
    figure = out / "small" / "fig1.png"
    if draw:
        figure.parent.mkdir(parents=True, exist_ok=True)
        figure.write_bytes(PNG)
    table = comparison_table("Table I", "peaks", [Compared("J2 [VA]", 600.0, 450.0, "lower"),
                                                  Compared("t_c [s]", 1.74, None)])
    return PaperReport("small", "A small paper", "Someone, \"A paper\"", ("Table I", "Fig. 1"),
                       [Section("Results", ("Plain words with `code`.", table,
                                            Figure("Fig. 1", "a profile", figure, "Caption.")))],
                       {"J2": 450.0}, quick=True)


def reproduce(options: PaperOptions) -> PaperReport:
    """The paper module of ``hil paper small``: a report whose figure was never drawn."""
    return small_report(options.out, draw=False)


def test_a_comparison_row_holds_the_paper_hil_and_their_ratio():
    table = comparison_table("Table I", "peaks", [Compared("J2", 600.0, 450.0),
                                                  Compared("t_c", 1.74, None),
                                                  Compared("gain", 0.0, 3.0)])
    assert table.columns == ("", "paper", "hil", "hil / paper", "note")
    assert [row[3] for row in table.rows] == ["0.750", None, None]  # no ratio to nothing, to 0
    assert [cell_text(v) for v in (33416.0, 585.69, 0.0085, -0.0, None, 12)] == [
        "33,416", "585.7", "0.0085", "0", "–", "12"]


def test_the_report_is_written_three_ways_and_says_what_it_holds(tmp_path):
    report = small_report(tmp_path)
    files = write_report(report, tmp_path)
    markdown = files.markdown.read_text()
    assert "**Table I: peaks**" in markdown
    assert "| J2 [VA] | 600 | 450 | 0.750 | lower |" in markdown
    assert "![Fig. 1: a profile](small/fig1.png)" in markdown  # relative to the report
    page = files.html.read_text()
    assert "<code>code</code>" in page and "data:image/png;base64," in page
    assert "Content-Security-Policy" in page  # the HTML report's page: opens offline
    document = json.loads(files.json.read_text())
    assert document["missing"] == [] and document["figures"] == {"Fig. 1": "small/fig1.png"}
    assert document["tables"]["Table I"]["rows"][0][:3] == ["J2 [VA]", 600.0, 450.0]
    assert document["results"] == {"J2": 450.0}


def test_a_figure_without_its_png_is_missing():
    report = small_report(Path("/nonexistent"), draw=False)
    assert report.items() == ["Table I"]
    assert report.missing() == ["Fig. 1"]
    report.sections = [Section("Results", (Table("Table II", "other", ("a",), ()),))]
    assert report.missing() == ["Table I", "Fig. 1"]


def test_hil_paper_exits_1_naming_what_the_report_lacks(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(PAPERS, "small", Paper(__name__, "a small paper", "A small paper."))
    done = hil_here(capsys, "paper", "small", "--out", "report", "--json", cwd=tmp_path)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == ["hil: the report lacks Fig. 1"]
    summary = json.loads(done.stdout)
    assert summary["missing"] == ["Fig. 1"] and summary["items"] == ["Table I"]
    assert (tmp_path / "report" / "small.md").is_file()


def test_an_out_folder_that_cannot_be_made_is_one_line(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    done = hil_here(capsys, "paper", "energy", "--out", "file/report", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.startswith("hil: error: --out file/report: cannot create the folder")
    assert len(done.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("paper", sorted(PAPERS))
def test_every_paper_of_the_table_has_its_reproduce(paper):
    import importlib

    assert callable(importlib.import_module(PAPERS[paper].module).reproduce)
