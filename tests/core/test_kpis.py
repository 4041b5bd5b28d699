"""KPI documents as dataclasses: the names a --limit may use, the --json document and the JUnit
properties come from one declaration."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest

from hil.bench.kpis import BenchRunKpis
from hil.core.kpis import Kpis, kpi
from hil.core.verdict import kpi_properties, parse_limit, split_limits
from hil.errors import UsageError
from hil.servo.kpis import AxesKpis, AxisKpis, ServoKpis


@dataclass
class Part(Kpis):
    peak_ma: float | None = kpi(key="peak_mA")
    note: str = kpi("", limit=False)


@dataclass
class Whole(Kpis):
    label: str = kpi("", limit=False)
    error_deg: float | None = kpi()
    horizon: int | None = kpi(limit=False, optional=True)
    parts: dict[str, Part] | None = kpi()
    peak_ma: float | None = kpi(key="peak_mA")


def test_a_document_keeps_its_order_spells_keys_and_nests_groups():
    whole = Whole(label="pid", error_deg=0.5, parts={"x": Part(3.0, "a")}, peak_ma=None)
    assert whole.document() == {"label": "pid", "error_deg": 0.5,
                                "parts": {"x": {"peak_mA": 3.0, "note": "a"}}, "peak_mA": None}
    assert list(whole.document()) == ["label", "error_deg", "parts", "peak_mA"]  # no horizon
    whole.horizon = 8
    assert list(whole.document())[2] == "horizon"
    assert Whole.limit_names() == ("error_deg", "parts", "peak_mA")


def test_lay_copies_a_part_s_fields_by_name():
    whole = Whole(label="pid").lay(Part(peak_ma=7.0))
    assert whole.peak_ma == 7.0 and whole.label == "pid"


def test_the_limits_a_run_takes_are_the_document_s_limit_fields():
    kept, _ = split_limits([parse_limit("parts.x.peak_mA<=5"), parse_limit("peak_mA<=9")], (),
                           Whole.limit_names())
    assert [str(lim.kpi) for lim in kept] == ["parts.x.peak_mA", "peak_mA"]
    with pytest.raises(UsageError, match="KPIs: error_deg, parts, peak_mA"):
        split_limits([parse_limit("label<=1")], (), Whole.limit_names())


@pytest.mark.parametrize("document", [ServoKpis, AxesKpis, AxisKpis, BenchRunKpis])
def test_every_limit_name_is_a_key_and_context_is_not_a_limit(document):
    names = document.limit_names()
    keys = [f.metadata.get("key") or f.name for f in dataclasses.fields(document)]
    assert set(names) <= set(keys) and len(set(keys)) == len(keys)
    assert "controller" not in names and "mcap" not in names


def test_junit_properties_are_the_document_flattened():
    whole = Whole(label="pid", error_deg=0.5, parts={"x": Part(3.0, "a")}, peak_ma=1.0)
    properties = kpi_properties(whole.document())
    assert properties["parts.x.peak_mA"] == "3.0" and properties["error_deg"] == "0.5"
    assert "horizon" not in properties


def test_the_servo_document_keeps_the_readme_s_keys_in_order():
    keys = ServoKpis().document().keys()
    assert list(keys)[:6] == ["controller", "max_error_deg", "max_error_pct", "rms_error_deg",
                              "cumulative_error_deg", "step_us"]
    assert {"umax_mA", "current_limit_mA", "peak_current_mA", "peak_requested_mA"} <= set(keys)
    assert "ert" not in keys and "solver_paths" not in keys  # only with an MPC
