"""The ``hil_baseline`` fixture of hil's pytest plugin: a run held against a baseline session
kept beside the test file (``baselines/TEST.mcap``), recorded on first use or with
``--hil-update-baselines``, compared by :func:`hil.compare.compare_data` afterwards."""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import pytest

from hil.compare import Comparison, Tolerance, compare_data
from hil.compare.baseline import write_baseline
from hil.compare.table import format_table, summary_line
from hil.compare.tolerances import fixture_spelling, parse_named
from hil.core.recording.reader import SessionData, read_session
from hil.core.report import session_kind
from hil.errors import HilError
from hil.pytest_html import html_folder, write_comparison_report

#: the signals a baseline keeps and compares unless the test names its own, by session kind
DEFAULT_SIGNALS = {
    "servo": ("/drive/feedback:position_deg", "/drive/command:command_mA"),
    "bench": ("/bench/power:total_va", "/bench/levels:q1", "/bench/levels:q2"),
}


class BaselineRecorded(UserWarning):
    """A test recorded its baseline instead of comparing with one."""


class Baseline:
    """The baseline of one test. ``check(session=None, *, signals=None, tolerances=None,
    name="", every=1)`` holds the session (default: the last run of the test's ``hil_drive`` or
    ``hil_bench``) against ``baselines/TEST[-NAME].mcap`` beside the test file and fails the
    test with the comparison's table when it is outside tolerance. Without that file, or with
    ``--hil-update-baselines``, it records it instead (keeping ``signals`` at every
    ``every``-th tick) and warns :class:`BaselineRecorded`. ``tolerances``: ``{NAME: SPEC}``
    with the specs of ``hil compare --tolerance`` (one-sided ``worse:5%`` too); without one,
    lockstep runs are held exact. A failure is one assertion: the comparison's table, or
    one line that spells a tolerance as ``tolerances=`` does."""

    def __init__(self, request: pytest.FixtureRequest, tmp_path: Path) -> None:
        self._request, self._tmp_path = request, tmp_path
        self.folder = Path(str(request.node.path)).parent / "baselines"
        self.update = bool(request.config.getoption("hil_update_baselines"))

    def path(self, name: str = "") -> Path:
        """The baseline file of this test (and of ``name``, for a test with several)."""
        stem = re.sub(r"[^\w.-]+", "_", self._request.node.name + (f"-{name}" if name else ""))
        return self.folder / f"{stem}.mcap"

    def check(self, session: str | Path | None = None, *, signals: Sequence[str] | None = None,
              tolerances: Mapping[str, str | Tolerance] | None = None, name: str = "",
              every: int = 1) -> Comparison | None:
        """Compare (or record, see the class); the comparison, None when recorded."""
        run = str(session) if session is not None else self._last_session()
        path = self.path(name)
        try:
            ran = read_session(run)  # once: for its kind, the comparison and its page
            chosen = list(signals) if signals is not None else \
                list(DEFAULT_SIGNALS.get(session_kind(ran), ()))
            if self.update or not path.exists():
                size = write_baseline(run, path, chosen, every)
                warnings.warn(BaselineRecorded(f"hil_baseline: recorded {path} ({size} "
                                               "bytes) from this run"), stacklevel=2)
                return None
            limits = {key: value if isinstance(value, Tolerance) else
                      parse_named(key, value, fixture_spelling)
                      for key, value in (tolerances or {}).items()}
            baseline = read_session(path)
            compared: Comparison | str = compare_data(baseline, ran, chosen, limits,
                                                      fixture_spelling)
        except HilError as exc:
            compared = f"hil_baseline: {exc}"
        if isinstance(compared, str):  # failed here, not in the handler: no chained error
            pytest.fail(compared, pytrace=False)
        return self._held(compared, path, baseline, ran)

    def _held(self, comparison: Comparison, path: Path, baseline: SessionData,
              ran: SessionData) -> Comparison:
        """The comparison written (JSON, and its page when asked or failed); the test failed
        with its table when it is outside tolerance."""
        document = comparison.to_json()
        report = self._tmp_path / f"{path.stem}.compare.json"
        report.write_text(json.dumps(document, indent=1) + "\n")
        folder = html_folder(self._request)
        if folder is not None:
            write_comparison_report(self._request, baseline, ran, document,
                                    Path(folder) / f"{path.stem}.compare.html")
        if not comparison.passed:
            page = write_comparison_report(self._request, baseline, ran, document,
                                           report.with_suffix(".html"))
            pytest.fail(f"{format_table(comparison)}\n{summary_line(comparison)}\n"
                        f"comparison: {report} (report: {page})", pytrace=False)
        return comparison

    def _last_session(self) -> str:
        funcargs = getattr(self._request.node, "funcargs", {})
        for fixture in ("hil_drive", "hil_bench"):
            sessions = getattr(funcargs.get(fixture), "sessions", None)
            if sessions:
                return str(sessions[-1])
        pytest.fail("hil_baseline.check(): no session to check - run hil_drive or hil_bench "
                    "first, or pass the session file", pytrace=False)


@pytest.fixture
def hil_baseline(request: pytest.FixtureRequest, tmp_path: Path) -> Baseline:
    """This test's baseline beside its file (see :class:`Baseline`)."""
    return Baseline(request, tmp_path)
