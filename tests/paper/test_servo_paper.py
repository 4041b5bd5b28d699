"""``hil paper servo``: the servo paper reproduced from lockstep sessions on the emulated drive.

The quick form runs once, from a folder outside the repository as a user runs it, and its
report is held to the paper's own list of tables and figures (written here from the paper, not
taken from the code); its values must show what the paper shows where the quick runs can
(FOH-ERT below ZOH-ERT, the explicit law equal to the online QP's optimum). The committed full
report is checked complete. The conditions file is refused key by key.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from hil.errors import ConfigError
from hil.paper.servo_conditions import load_conditions

REPO = Path(__file__).resolve().parents[2]
#: the servo paper's tables and figures, from the paper: what each is, and whether hil can
#: redraw it (the photographs it cannot)
PAPER_ITEMS = {
    "Table I": "table", "Fig. 1": "figure", "Fig. 2": "photograph", "Fig. 3": "photograph",
    "Fig. 4": "figure", "Fig. 5": "figure", "Fig. 6": "figure", "Fig. 7": "figure",
    "Fig. 8": "figure", "Fig. 9": "figure", "Fig. 10": "figure", "Fig. 11": "photograph",
    "Fig. 12": "diagram", "Fig. 13": "diagram", "Fig. 14": "figure", "Fig. 15": "figure",
    "Fig. 16": "figure",
}
#: the figures of its text: Figs. 5-6's max errors, the explicit MPC's counts (III-D), the
#: sequential-search limit (III-C)
PAPER_TEXT = ("Figs. 5-6", "Sec. III-D", "Sec. III-C")


def hil_from_outside(folder: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` in a process of its own, from ``folder`` (outside the repository)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=900)


@pytest.mark.slow
@pytest.mark.timeout(900)  # some 15 s of CPU; a shared machine may stretch it many times over
def test_the_quick_form_reports_every_table_and_figure_and_what_the_paper_shows(tmp_path):
    """One quick run (it is the test's whole cost), checked for completeness against the
    paper's list, then for values that could come out otherwise."""
    done = hil_from_outside(tmp_path, "paper", "servo", "--quick", "--json", "--out", "report")
    assert done.returncode == 0, done.stderr[-3000:]
    out = tmp_path / "report"
    summary = json.loads(done.stdout)
    report = json.loads((out / "servo.json").read_text())
    assert summary["missing"] == [] and report["missing"] == [] and report["quick"] is True
    assert_complete(out, report)
    assert "<img" in (out / "servo.html").read_text()  # the page (not committed) too
    assert re.search(r"hil paper servo: \[19/\d+\] ", done.stderr)  # a line per session
    assert len(list((out / "servo" / "sessions").glob("*.mcap"))) >= 19
    assert_what_the_paper_shows(report)


def assert_complete(out: Path, report: dict) -> None:
    """Every figure of the paper redrawn (a PNG), every table and diagram and every figure of
    its text a table with rows, the photographs said to be photographs."""
    for key, kind in PAPER_ITEMS.items():
        if kind == "figure":
            assert (out / report["figures"][key]).read_bytes()[:4] == b"\x89PNG", key
        elif kind in ("table", "diagram"):
            assert report["tables"][key]["rows"], key
    for key in PAPER_TEXT:
        assert report["tables"][key]["rows"], key
    markdown = (out / "servo.md").read_text()
    for key, kind in PAPER_ITEMS.items():
        if kind == "photograph":
            assert f"{key} shows" in markdown  # said why there is nothing to redraw
    for image in re.findall(r"!\[[^]]*\]\(([^)]+)\)", markdown):
        assert (out / image).is_file(), image


def assert_what_the_paper_shows(report: dict) -> None:
    results = report["results"]
    for panel in results["sine"]:
        if not panel["saturated"]:  # FOH-ERT beats ZOH-ERT (Figs. 7-8)
            by = {(row["ert"], row["ht"]): row for row in panel["mpc"]}
            assert by[("foh", 2)]["max_error_deg"] < by[("zoh", 2)]["max_error_deg"], panel
            assert by[("zoh", 1)]["normalised"] == 1.0
    limited = results["fig5"]["limit"]
    assert limited["peak_requested_mA"] == pytest.approx(1000.0)  # the 10 Hz sine saturates
    trapezoid = results["trapezoid"]  # the explicit law is the online QP's optimum
    assert trapezoid["empc"]["max_error_deg"] == pytest.approx(trapezoid["mpc"]["max_error_deg"],
                                                               rel=1e-6)
    assert trapezoid["empc"]["controllers"] == [1]  # Fig. 14: never leaves controller #1
    law = results["empc"]["hil"]
    assert law["regions"] > law["controllers"] >= 1 and law["tree_depth"] >= 1
    feedforward = {row["vff"]: row["max_error_deg"] for row in results["explain"]["vff"]}
    assert feedforward[1.0] < 0.2 * feedforward[0.0]  # --param vff reached the PID
    statements = report["tables"]["Statements"]["rows"]
    assert {row[-1] for row in statements} <= {"yes", "no", "not judged"}


def test_the_committed_report_is_the_full_run_and_complete():
    docs = REPO / "docs" / "papers"
    report = json.loads((docs / "servo.json").read_text())
    assert report["quick"] is False and report["missing"] == []
    assert_complete(docs, report)
    law = report["results"]["empc"]["hil"]  # the paper's explicit MPC, H_t = H_u = 3
    assert (law["ht"], law["controllers"]) == (3, 11)


@pytest.mark.parametrize(("edit", "message"), [
    (("hp = 50", "hp = 50\nhorizon = 3"), "unknown key 'mpc.horizon'"),
    (("horizons = [1, 2, 3, 4, 5, 6, 7, 8]", "horizons = [2, 3]"), "mpc.horizons' must hold 1"),
    (("current_limit_mA = 1000.0", "current_limit_mA = -5.0"), "drive.current_limit_mA"),
    (("cycle_period_us = 500", "cycle_period_us = 1000"), "cycle_period_us"),
    (("empc_ht = 3", "empc_ht = 7"), "mpc.empc_ht"),
    (("vff = [0.0, 0.25, 0.5, 0.75, 1.0]", "vff = [0.0, 2.0]"), "explain.vff"),
])
def test_a_wrong_condition_is_one_line_naming_its_key(edit, message):
    text = (REPO / "hil" / "configs" / "paper_servo.toml").read_text()
    old, new = edit
    assert old in text
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_conditions(text=text.replace(old, new, 1))


def test_quick_lays_its_shorter_runs_over_the_paper_s_conditions():
    full, quick = load_conditions(), load_conditions(quick=True)
    assert (full.hp, full.q, full.r, full.limit_ma) == (50, 1e6, 1.0, 1000.0)
    assert full.horizons == tuple(range(1, 9)) and full.empc_ht == 3
    assert quick.horizons == (1, 2) and quick.empc_ht == 2 and quick.quick
    assert (quick.hp, quick.limit_ma, quick.stroke_deg) == (full.hp, full.limit_ma,
                                                            full.stroke_deg)
