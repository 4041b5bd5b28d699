"""The documentation as the tests read it: the README and the pages of docs/ (the site), their
code blocks found by what they hold, not by their place (a page's blocks move as it grows)."""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"


def page(name: str) -> str:
    """The text of ``docs/NAME`` (``"guides/drive.md"``), or of the README."""
    return (README if name == "README.md" else DOCS / name).read_text(encoding="utf-8")


def pages() -> dict[str, str]:
    """The README and every page of the site, by name."""
    found = {"README.md": page("README.md")}
    found.update({str(path.relative_to(DOCS)): path.read_text(encoding="utf-8")
                  for path in sorted(DOCS.rglob("*.md"))})
    return found


def blocks(text: str, language: str) -> list[str]:
    """The code blocks of ``text`` in ``language``, in order (those indented in a list too)."""
    found = re.findall(rf"^( *)```{language}\n(.*?)^ *```", text, re.M | re.S)
    return [textwrap.dedent("".join(line.removeprefix(indent) for line in
                                    block.splitlines(keepends=True)))
            for indent, block in found]


def block(name: str, language: str, containing: str) -> str:
    """The one code block in ``language`` of page ``name`` that holds ``containing``."""
    [found] = [text for text in blocks(page(name), language) if containing in text]
    return found


def section(name: str, heading: str) -> str:
    """The part of page ``name`` from the heading that starts with ``heading`` (any level) to
    the next heading of the same or a higher level."""
    text = page(name)
    match = re.search(rf"^(#+) {re.escape(heading)}", text, re.M)
    assert match, f"{name} has no heading {heading!r}"
    level = len(match.group(1))
    rest = text[match.end():]
    end = re.search(rf"^#{{1,{level}}} ", _outside_code(rest), re.M)
    return text[match.start():match.end() + (end.start() if end else len(rest))]


def _outside_code(text: str) -> str:
    """``text`` with the lines of its code blocks blanked, each to as many spaces (a ``#
    comment`` is no heading; offsets stay those of ``text``)."""
    lines, fence = [], False
    for line in text.splitlines(keepends=True):
        marker = line.lstrip().startswith("```")
        fence = fence != marker
        blank = fence or marker
        lines.append(" " * len(line.rstrip("\n")) + line[len(line.rstrip("\n")):] if blank
                     else line)
    return "".join(lines)
