"""A run whose outputs are not known to be safe is an outcome of its own, whichever device
says so: here a bench-like device that reports its relays unconfirmed when it closes (the
event the bench's driver emits after a lost link, ``bench.safe_state_unconfirmed``), through
the run pipeline, the command line's end of a run and the session's reports. The drive's side
is tried over the wire in tests/integration/test_unsafe_stop.py."""

from __future__ import annotations

import argparse
import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any

import pytest

from hil.cli.verdict import EXIT_UNSAFE, finish
from hil.core.clock import SimClock
from hil.core.kpis import Kpis, kpi
from hil.core.loop import Task
from hil.core.recording.reader import read_session
from hil.core.report import format_summary, summarize
from hil.core.run import EventBuffer, Experiment, RunPlan, RunResult, run_experiment
from hil.core.session import Session
from hil.core.verdict import SignalWatch
from hil.errors import HilError, SafetyStopError

UNCONFIRMED = "relays P2 may still be on: read back on after the lost link"


@dataclass
class BenchLikeKpis(Kpis):
    controller: str | None = kpi(limit=False)
    ticks: int = kpi(0)
    stop_reason: str | None = kpi(limit=False)


class Tick(Task):
    def __init__(self, fail_at: int | None) -> None:
        super().__init__("tick")
        self.ticks, self.fail_at = 0, fail_at

    def read(self, t_ns: int) -> None:
        self.ticks += 1
        if self.ticks == self.fail_at:
            raise SafetyStopError("safety stop at tick 3")


class UnconfirmedBench(Experiment[RunPlan]):
    """One task ticking for 10 ms; its device, on closing, cannot confirm its relays."""

    def __init__(self, path: str, fail_at: int | None = None) -> None:
        self.path, self.fail_at = path, fail_at
        self.events: EventBuffer | None = None
        self.task = Tick(fail_at)

    def plan(self) -> RunPlan:
        return RunPlan("bench", "bc", self.path, SimClock(), 0.001, 0.01, (),
                       SignalWatch(()), {}, quiet=True)

    def open_devices(self, clock: Any, on_event: EventBuffer) -> None:
        self.events = on_event

    def build_controller(self, session: Session) -> None:
        return None

    def start(self, session: Session) -> None:
        session.add_task(self.task)

    def close_devices(self) -> None:
        if self.events is not None:
            self.events("bench.safe_state_unconfirmed", UNCONFIRMED, level="error",
                        source="bench", on=["P2"], unknown=[])
            self.events = None

    def kpis(self, session: Session, wall_s: float, error: HilError | None) -> BenchLikeKpis:
        return BenchLikeKpis("bc", self.task.ticks, session.loop.stop_reason)


def args(tmp_path) -> argparse.Namespace:
    return argparse.Namespace(json=True, junit=str(tmp_path / "run.xml"), controller="bc")


def junit_run_case(tmp_path) -> ET.Element:
    root = ET.parse(tmp_path / "run.xml").getroot()
    return next(case for case in root.iter("testcase") if case.get("name") == "run")


def test_a_completed_run_with_its_relays_unconfirmed_is_unsafe(tmp_path, capsys):
    path = str(tmp_path / "bench.mcap")
    status = finish(args(tmp_path), "bench run", lambda: UnconfirmedBench(path),
                    run_experiment, lambda _made, kpis: "summary")
    out, err = capsys.readouterr()
    assert status == EXIT_UNSAFE == 4
    kpis = json.loads(out)
    assert kpis["status"] == "unsafe" and kpis["unsafe"] == [UNCONFIRMED]
    assert err == f"hil: unsafe: {UNCONFIRMED}\n"  # when the device said so
    error = junit_run_case(tmp_path).find("error")
    assert error is not None and error.get("type") == "UnsafeStop"
    assert error.get("message") == UNCONFIRMED
    summary = summarize(read_session(path))
    assert summary["unsafe"] == [UNCONFIRMED] and summary["kpis"]["status"] == "unsafe"
    assert f"UNSAFE: {UNCONFIRMED}" in format_summary(summary).splitlines()


def test_an_error_and_an_unsafe_stop_give_both_lines_and_exit_4(tmp_path, capsys):
    path = str(tmp_path / "stopped.mcap")
    status = finish(args(tmp_path), "bench run", lambda: UnconfirmedBench(path, fail_at=3),
                    run_experiment, lambda _made, kpis: "summary")
    out, err = capsys.readouterr()
    assert status == EXIT_UNSAFE
    assert json.loads(out)["status"] == "unsafe"
    first, second = err.splitlines()
    assert first == f"hil: unsafe: {UNCONFIRMED}"
    assert second.startswith("hil: error: safety stop at tick 3 (session recorded to ")
    error = junit_run_case(tmp_path).find("error")
    assert error is not None and error.get("type") == "UnsafeStop"
    assert "(the run ended: SafetyStopError: safety stop at tick 3" in error.get("message", "")


def test_from_python_the_status_is_unsafe(tmp_path):
    result: RunResult = run_experiment(UnconfirmedBench(str(tmp_path / "api.mcap")))
    assert result.kpis["status"] == "unsafe" and result.kpis["unsafe"] == [UNCONFIRMED]
    with pytest.raises(SafetyStopError) as stopped:
        run_experiment(UnconfirmedBench(str(tmp_path / "api2.mcap"), fail_at=3))
    assert stopped.value.result.kpis["status"] == "unsafe"
