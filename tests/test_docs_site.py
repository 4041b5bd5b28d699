"""The documentation site: its generated references are what the code gives today (every
command and flag of the parsers is in the command reference, every topic and metadata record
of a run in the session format), the site builds with MkDocs strictly (a broken link, page or
API object fails) into a folder of its own and fetches nothing, and the README stays short
with every link resolving, on the repository's host as in the site."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from hil.cli import command_reference, session_reference
from hil.cli.main import build_parser
from tests.docs import DOCS, README, ROOT, page

#: how long the README may be ("at most about 250 lines")
README_LINES = 250


def test_the_command_reference_is_generated_from_the_parsers():
    committed = page("reference/commands.md")
    assert committed == command_reference.reference(), \
        "docs/reference/commands.md is stale: run `make docs`"


def test_every_command_and_flag_is_in_the_command_reference():
    """Every command and subcommand has its section and every argument its row: a flag added
    without `make docs` fails here, naming it."""
    committed = page("reference/commands.md")
    parsers = list(command_reference.walk(build_parser()))
    assert len(parsers) > 40
    for parser in parsers:
        assert f"`{parser.prog}`\n" in committed, f"command {parser.prog!r} is not documented"
        text = "\n".join(command_reference.section(parser))
        assert text in committed
        for action in command_reference.documented(parser):
            for name in action.option_strings or [str(action.metavar or action.dest)]:
                assert re.search(rf"\| `[^`]*{re.escape(name)}(?![\w-])", text), \
                    f"{parser.prog} {name} is not in the command reference"


def test_a_hidden_or_missing_flag_is_what_the_check_would_name():
    """The row check above fails for a flag the page lacks (it could fail)."""
    parser = build_parser()
    servo_run = command_reference.subcommands(command_reference.subcommands(parser)["servo"])[
        "run"]
    text = "\n".join(command_reference.section(servo_run))
    assert re.search(r"\| `[^`]*--umax(?![\w-])", text)
    assert not re.search(r"\| `[^`]*--no-such-flag(?![\w-])", text)
    assert not re.search(r"\| `[^`]*--um(?![\w-])", text)  # a prefix is not the flag


@pytest.mark.slow
def test_the_session_format_is_what_the_sample_runs_record(tmp_path):
    """docs/reference/sessions.md is what `make docs` writes today, from short lockstep runs
    (about 3 s): a topic, schema or metadata record added without it fails here."""
    generated = session_reference.reference(tmp_path)
    assert page("reference/sessions.md") == generated, \
        "docs/reference/sessions.md is stale: run `make docs`"
    for topic in ("/drive/feedback", "/axis/NAME/feedback", "/bench/power", "/events",
                  "/loop/TASK/timing", "/mpc/prediction", "/path/contour", "/drive/motion"):
        assert f"### `{topic}`" in generated


def test_a_metadata_record_nobody_described_is_refused():
    with pytest.raises(KeyError, match="not described"):
        session_reference.describe_metadata("something_new")
    assert session_reference.describe_metadata("reference/x")
    assert session_reference.describe_metadata("realtime.emulator")


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_the_site_builds_strictly_and_fetches_nothing(tmp_path):
    """`mkdocs build --strict` (what `make docs` runs), into a folder of its own: every link,
    anchor, page and API object resolves; no page asks the network for a font or a script."""
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet",
                           "--site-dir", str(site)], cwd=ROOT, capture_output=True, text=True,
                          env=env, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    pages = {p.relative_to(site).as_posix() for p in site.rglob("*.html")}
    assert {"index.html", "getting-started.html", "guides/drive.html",
            "reference/commands.html", "reference/api.html", "CONFIGURATION.html",
            "ARCHITECTURE.html"} <= pages
    assert "hil.api.run_servo" in (site / "reference" / "api.html").read_text()
    fetched = re.compile(r"""src=["']https?://|<link[^>]+href=["']https?://""")
    for html in site.rglob("*.html"):
        assert not fetched.search(html.read_text(encoding="utf-8")), html


def test_every_page_is_in_the_site():
    """Every Markdown file of docs/ is reachable from the site's navigation (mkdocs.yml):
    moved text is never left on a page nobody finds."""
    nav = (ROOT / "mkdocs.yml").read_text()
    for path in DOCS.rglob("*.md"):
        assert path.relative_to(DOCS).as_posix() in nav, path


def readme_links() -> list[str]:
    text = re.sub(r"```.*?```", "", page("README.md"), flags=re.S)
    return re.findall(r"\]\(([^)\s]+)\)", text)


def anchors(markdown: str) -> set[str]:
    """The anchors of a page's headings, as both GitHub and the site's toc make them."""
    found = set()
    for heading in re.findall(r"^#+ (.+)$", re.sub(r"```.*?```", "", markdown, flags=re.S),
                              re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.lower()).strip().replace(" ", "-")
        found.add(slug)
    return found


def test_the_readme_is_short_and_every_link_resolves():
    lines = page("README.md").splitlines()
    assert len(lines) <= README_LINES, f"the README has {len(lines)} lines"
    links = readme_links()
    assert len(links) > 20
    for link in links:
        assert not link.startswith(("http:", "https:", "/")), \
            f"{link}: the README links into the repository, relatively"
        target, _, anchor = link.partition("#")
        path = README.parent / target
        assert path.exists(), f"the README links to {link}, which is not there"
        if target.endswith(".md"):
            assert path.resolve().is_relative_to(DOCS), f"{link}: not a page of the site"
        if anchor:
            assert anchor in anchors(path.read_text()), f"{link}: no such heading"
