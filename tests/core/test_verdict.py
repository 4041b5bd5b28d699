"""Limits on KPIs, their verdict and the JUnit report."""

import xml.etree.ElementTree as ET

import pytest

from hil.core.config import Table, parse_toml
from hil.core.verdict import (
    STATUSES,
    Limit,
    RunCase,
    check_limits,
    junit_xml,
    kpi_properties,
    limits_from_table,
    parse_limit,
    run_status,
)
from hil.errors import (
    ConfigError,
    ControllerError,
    RunInterruptedError,
    SafetyStopError,
    UsageError,
)

KPIS = {"J2_VA": 523.5, "switches": 12, "solve_ms": {"median": 40.0, "p99": 71.7},
        "controller": "eec", "nan_kpi": float("nan")}


def test_parse_limit_forms_and_errors():
    assert parse_limit("J2_VA<=560") == Limit("J2_VA", "<=", 560.0)
    assert parse_limit(" solve_ms.p99 >= 1e-3 ") == Limit("solve_ms.p99", ">=", 0.001)
    for bad in ("J2_VA=560", "<=5", "J2_VA<=abc", "J2_VA<=inf"):
        with pytest.raises(UsageError, match="--limit"):
            parse_limit(bad)


def test_check_limits_on_flat_and_nested_kpis():
    results = check_limits([parse_limit("J2_VA<=560"), parse_limit("J2_VA<=500"),
                            parse_limit("solve_ms.p99<100"), parse_limit("switches>=20"),
                            parse_limit("missing<=1"), parse_limit("controller<=1"),
                            parse_limit("nan_kpi<=1")], KPIS)
    assert [r.passed for r in results] == [True, False, True, False, False, False, False]
    assert results[1].describe() == "J2_VA<=500: measured 523.5 (violated)"
    assert results[0].describe() == "J2_VA<=560: measured 523.5 (holds)"
    assert results[4].describe() == "missing<=1: no KPI 'missing' in this run (violated)"


def test_limits_table():
    table = Table(parse_toml('[limits]\nJ2_VA = { max = 560 }\n"solve_ms.p99" = '
                             '{ min = 1, max = 100 }\n', "l.toml"), "l.toml").table("limits")
    assert limits_from_table(table) == [Limit("J2_VA", "<=", 560.0),
                                        Limit("solve_ms.p99", ">=", 1.0),
                                        Limit("solve_ms.p99", "<=", 100.0)]
    bad = Table({"limits": {"J2_VA": {"maximum": 3}}}, "l.toml").table("limits")
    with pytest.raises(ConfigError, match=r"unknown key 'limits\.J2_VA\.maximum'"):
        limits_from_table(bad)
    empty = Table({"limits": {"J2_VA": {}}}, "l.toml").table("limits")
    with pytest.raises(ConfigError, match=r"'limits\.J2_VA' needs min, max or both"):
        limits_from_table(empty)


def test_junit_has_one_case_per_limit_and_marks_failures():
    results = check_limits([parse_limit("J2_VA<=560"), parse_limit("J2_VA<=500")], KPIS)
    root = ET.fromstring(junit_xml(results, "bench run eec", duration_s=2.5,
                                   properties={"mcap": "/tmp/x.mcap"}))
    suite = root.find("testsuite")
    assert suite is not None and suite.get("tests") == "2" and suite.get("failures") == "1"
    assert suite.get("errors") == "0"
    cases = suite.findall("testcase")
    assert [c.get("name") for c in cases] == ["J2_VA<=560", "J2_VA<=500"]
    assert cases[0].find("failure") is None
    failure = cases[1].find("failure")
    assert failure is not None and "measured 523.5" in failure.get("message", "")
    assert suite.find("properties/property").get("value") == "/tmp/x.mcap"


def test_junit_run_case_is_an_error_naming_its_cause_or_passes():
    results = check_limits([parse_limit("J2_VA<=560")], KPIS)
    stopped = ET.fromstring(junit_xml(results, "hil bench run eec", run=RunCase(
        "safety stop at t=2 s: total_va 1300 VA", "SafetyStopError")))
    assert stopped.tag == "testsuites" and stopped.get("errors") == "1"
    suite = stopped.find("testsuite")
    assert suite is not None
    assert (suite.get("tests"), suite.get("failures"), suite.get("errors")) == ("2", "0", "1")
    run = suite.findall("testcase")[-1]
    assert run.get("name") == "run" and run.get("classname") == "hil bench run eec"
    error = run.find("error")
    assert error is not None and error.get("type") == "SafetyStopError"
    assert error.get("message") == error.text == "safety stop at t=2 s: total_va 1300 VA"
    completed = ET.fromstring(junit_xml([], "hil servo run pid", run=RunCase("completed")))
    suite = completed.find("testsuite")
    assert suite is not None and (suite.get("tests"), suite.get("errors")) == ("1", "0")
    case = suite.find("testcase")
    assert case is not None and list(case) and case[0].tag == "system-out"
    assert case[0].text == "completed"


def test_kpis_become_flat_properties_nested_keys_joined_by_dots():
    kpis = {**KPIS, "mcap": "s.mcap", "stop_reason": None, "disturbed": False,
            "limits": [{"limit": "J2_VA<=560", "measured": 523.5, "passed": True}],
            "faults": {"emcy": 0, "link": {"losses": 2}}}
    properties = kpi_properties(kpis)
    assert properties["solve_ms.p99"] == "71.7" and properties["J2_VA"] == "523.5"
    assert properties["faults.link.losses"] == "2" and properties["controller"] == "eec"
    assert properties["mcap"] == "s.mcap" and properties["stop_reason"] == "null"
    assert properties["disturbed"] == "false" and properties["nan_kpi"] == "NaN"
    assert "limits" not in properties  # the limits are test cases of their own
    assert kpi_properties({"ticks": 3}, "servo-1.") == {"servo-1.ticks": "3"}


@pytest.mark.parametrize(("kpis", "error", "status"), [
    ({}, None, "completed"),
    ({"passed": True, "disturbed": True}, None, "disturbed"),
    ({"passed": False, "disturbed": True}, None, "violated"),
    ({"passed": False}, SafetyStopError("safety stop"), "stopped"),
    ({}, ControllerError("controller 'x' raised"), "failed"),
    ({}, RunInterruptedError("interrupted by SIGTERM", 143), "interrupted"),
    ({}, KeyboardInterrupt(), "interrupted"),
    ({"unsafe": ["drive node 1: safe stop incomplete ..."]}, None, "unsafe"),
    ({"unsafe": ["relays P2 ..."], "passed": False}, SafetyStopError("safety stop"),
     "unsafe"),
    ({"unsafe": ["drive node 1 ..."]}, RunInterruptedError("interrupted", 130), "unsafe"),
])
def test_the_status_of_a_run(kpis, error, status):
    assert run_status(kpis, error) == status
    assert status in STATUSES
