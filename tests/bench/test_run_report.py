"""What a bench run reports, checked from outside through the CLI: the relay-wear KPI
``starts_per_hour`` of every controller and the distribution of the EEC's solve times in
``hil report`` (text and ``--json``), against the recording itself."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hil.cli.main import main
from hil.core.recording.reader import read_session

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]


def run(tmp_path, capsys, controller: str) -> tuple[dict, str]:
    out = str(tmp_path / f"{controller}.mcap")
    assert main(["bench", "run", "--controller", controller, "--cycles", "1", "--json",
                 "--out", out]) == 0
    return json.loads(capsys.readouterr().out), out


def recorded_starts_per_hour(out: str) -> dict[str, float]:
    relays = read_session(out).arrays("/bench/relays")
    hours = (relays["log_time_ns"][-1] - relays["log_time_ns"][0]) / 1e9 / 3600.0
    rates = {}
    for name in ("P1", "P2"):
        on = relays[name].astype(bool)
        rates[name] = (int(np.sum(on[1:] & ~on[:-1])) + int(on[0])) / hours
    return rates


@pytest.mark.parametrize("controller", ["eec", "bc"])
def test_starts_per_hour_counts_the_recorded_switch_ons(tmp_path, capsys, controller):
    kpis, out = run(tmp_path, capsys, controller)
    expected = recorded_starts_per_hour(out)
    assert set(kpis["starts_per_hour"]) == {"P1", "P2"}
    assert sum(expected.values()) > 0, "no relay switched on: nothing was tested"
    for name, rate in expected.items():
        assert kpis["starts_per_hour"][name] == pytest.approx(rate, rel=0.02, abs=0.1)
    if controller == "bc":  # no solver: the report has no solve-time section
        assert main(["report", out, "--json"]) == 0
        assert "solve_times" not in json.loads(capsys.readouterr().out)


def test_report_shows_the_distribution_of_solve_times(tmp_path, capsys):
    kpis, out = run(tmp_path, capsys, "eec")
    solve_ms = read_session(out).arrays("/eec/plan")["solve_ms"]
    assert main(["report", out, "--json"]) == 0
    section = json.loads(capsys.readouterr().out)["solve_times"]
    assert section["count"] == solve_ms.size == 28
    assert section["ms"]["p50"] == pytest.approx(np.median(solve_ms), abs=1e-3)
    assert section["ms"]["max"] == pytest.approx(solve_ms.max(), abs=1e-3)
    # the run's KPI comes from the streaming histogram: within its stated 1 %
    assert section["ms"]["p50"] == pytest.approx(kpis["solve_ms"]["median"], rel=0.01)
    bins = section["histogram"]
    assert sum(b["count"] for b in bins) == solve_ms.size
    for b in bins:  # every bin holds exactly the recorded times in its range
        top = np.inf if b["to_ms"] is None else b["to_ms"]
        assert b["count"] == int(np.sum((solve_ms >= b["from_ms"]) & (solve_ms < top)))
    assert section["status"] == {"optimal": 28} and section["max_gap"] == 0.0
    assert main(["report", out]) == 0
    text = capsys.readouterr().out
    assert f"solve times (28 plans, /eec/plan)   p50 {section['ms']['p50']:.1f}" in text
    assert "status: 28 optimal" in text
