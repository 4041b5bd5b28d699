"""``--hil-html DIR`` of hil's pytest plugin: a self-contained HTML report of every session a
test's ``hil_bench`` / ``hil_drive`` ran, and of every ``hil_baseline`` comparison, written to
``DIR/TEST-NAME.html`` and named in the test's properties (``servo-1.html``)."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from hil.core.recording.reader import SessionData


def add_option(group: Any) -> None:
    group.addoption("--hil-html", metavar="DIR", default=None,
                    help="write an HTML report of every session the hil fixtures run, and of "
                    "every hil_baseline comparison, to DIR (one file per session: TEST-NAME.html)")


def report_path(request: pytest.FixtureRequest, folder: str | Path, name: str) -> Path:
    """``folder/TEST-NAME.html`` for this test (characters a file name cannot hold replaced)."""
    stem = re.sub(r"[^\w.-]+", "_", f"{request.node.name}-{name}")
    return Path(folder) / f"{stem}.html"


def html_folder(request: pytest.FixtureRequest) -> str | None:
    """The ``--hil-html`` folder, or None."""
    folder = request.config.getoption("hil_html")
    return str(folder) if folder else None


def write_session_reports(request: pytest.FixtureRequest, sessions: Sequence[str]) -> None:
    """With ``--hil-html DIR``: the report of each of ``sessions`` that was written."""
    folder = html_folder(request)
    if folder is None:
        return
    from hil.core.html_report import write_session_html

    for session in sessions:
        if Path(session).exists():
            name = Path(session).stem
            path = report_path(request, folder, name)
            write_session_html(session, str(path))
            request.node.user_properties.append((f"{name}.html", str(path)))


def write_comparison_report(request: pytest.FixtureRequest, baseline: SessionData,
                            run: SessionData, comparison: Mapping[str, Any], path: Path) -> Path:
    """The comparison's report at ``path`` (of the sessions as read for the comparison),
    named in the test's properties."""
    from hil.core.html_report import write_comparison_data_html

    write_comparison_data_html(baseline, run, comparison, str(path))
    request.node.user_properties.append((f"{path.stem}.html", str(path)))
    return path
