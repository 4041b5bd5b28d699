"""What a new user meets in the first hour, tried from a folder outside the repository with
the ``hil`` command: limits that name no KPI are refused before the run, current limits apply
to the current the drive is sent, output paths follow one rule, Ctrl-C is exit 130. Each
command is tried as a ``hil`` process; more cases of it run the command line in this process
(:func:`hil_here`), from the same folder."""

import argparse
import ast
import json
import os
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.cli import hil_here

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]


def hil(cwd, *args, timeout=90):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, capture_output=True,
                          text=True, env=env, timeout=timeout, check=False)


@pytest.mark.parametrize(("argv", "name", "outside"), [
    (["servo", "run", "--controller", "pid", "--limit", "rms_err<=0.5"], "rms_err", True),
    (["bench", "run", "--controller", "bc", "--limit", "J1<=5"], "J1", False),
    (["servo", "run", "--controller", "pid", "--limit", "fault.emcy<=0"], "fault.emcy", False),
])
def test_a_limit_on_no_kpi_is_refused_before_the_run(tmp_path, capfd, monkeypatch, argv, name,
                                                     outside):
    """The first case from a ``hil`` process, the others in this one."""
    start = time.monotonic()
    if outside:
        done = hil(tmp_path, *argv)
    else:
        monkeypatch.chdir(tmp_path)
        done = hil_here(capfd, *argv)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"no KPI or signal '{name}'; KPIs: " in lines[0]
    assert "per-tick signals: " in lines[0]
    assert not (tmp_path / "sessions").exists()  # nothing ran
    assert time.monotonic() - start < 30


PUSHY = textwrap.dedent("""
    class Pushy:
        '''The README's PdPosition with a stiffer P: asks for more current than the drive
        may take whenever the reference runs ahead.'''
        def __init__(self, reference, params):
            self.reference, self.last = reference, None
        def step(self, position_deg, t_s):
            error = (float(self.reference.position(t_s)) - position_deg + 180.0) % 360.0 - 180.0
            rate = 0.0 if self.last is None else (error - self.last[1]) / (t_s - self.last[0])
            self.last = (t_s, error)
            return 900.0 * error + 6.0 * rate
""")


def test_current_limits_and_the_peak_are_on_the_current_the_drive_is_sent(tmp_path):
    (tmp_path / "pushy.py").write_text(PUSHY)
    done = hil(tmp_path, "servo", "run", "--controller", "pushy.py:Pushy", "--duration", "0.5",
               "--reference", "sine:amplitude=2,frequency=10",  # the paper's fast case
               "--limit", "abs_command_mA<=1000", "--out", "pushy.mcap", "--json")
    assert done.returncode == 0, done.stderr
    kpis = json.loads(done.stdout)
    assert kpis["peak_current_mA"] == 1000.0 < kpis["peak_requested_mA"]
    assert kpis["clamped_commands"] > 0 and kpis["passed"] is True


def test_output_paths_follow_one_rule(tmp_path, capfd, monkeypatch):
    session = tmp_path / "s.mcap"
    monkeypatch.chdir(tmp_path)  # the session to report on, in this process
    assert hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.05",
                    "--out", str(session)).returncode == 0
    # missing folders are created, for every output
    done = hil(tmp_path, "report", str(session), "--out", "plots/new/s.png")
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "plots" / "new" / "s.png").stat().st_size > 0
    # the other cases in this process, from the same folder
    done = hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.05",
                    "--junit", "reports/junit.xml", "--limit", "rms_error_deg<=5", "--out",
                    "runs/a.mcap")
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "runs/a.mcap").exists()
    case = ET.parse(tmp_path / "reports" / "junit.xml").find(".//testcase")
    assert float(case.get("time")) > 0  # the run's duration, each limit judged on all of it
    properties = {p.get("name"): p.get("value") for p in case.iter("property")}
    assert properties["unit"] == "deg" and float(properties["measured"]) < 5
    # an output that cannot be written is refused before anything runs: no session left
    (tmp_path / "blocker").write_text("a file, not a folder")
    for flag, value in (("--junit", "blocker/j.xml"), ("--out", "blocker/b.mcap"),
                        ("--out", ".")):
        done = hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.05",
                        flag, value)
        assert done.returncode == 2, (flag, value, done.stderr)
        assert f"argument {flag}: " in done.stderr and "Traceback" not in done.stderr
    done = hil_here(capfd, "report", str(session), "--out", "blocker/x.png")
    assert done.returncode == 2 and "blocker is a file, not a folder" in done.stderr
    # a default session goes to ./sessions/, for the bench as for the servo
    done = hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.05")
    assert done.returncode == 0
    assert len(list((tmp_path / "sessions").glob("servo-pid-*.mcap"))) == 1


def test_reading_a_session_events_messages_and_csv(tmp_path, capfd, monkeypatch):
    import csv

    monkeypatch.chdir(tmp_path)
    session = tmp_path / "s.mcap"
    assert hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.05",
                    "--out", str(session)).returncode == 0
    events = hil_here(capfd, "report", str(session), "--events")  # a process: above
    assert events.returncode == 0
    kinds = [line.split()[2] for line in events.stdout.splitlines()]
    assert kinds[:2] == ["drive.current_limit", "drive.configured"] and "session.stop" in kinds
    lines = hil_here(capfd, "report", str(session), "--topic", "/drive/feedback").stdout
    rows = [json.loads(line) for line in lines.splitlines()]
    assert len(rows) == 100 and rows[1]["t_s"] == 0.0005 and "position_deg" in rows[1]
    done = hil(tmp_path, "export", str(session), "--topic", "/drive/feedback",
               "--out", "csv/feedback.csv")
    assert done.returncode == 0 and "100 row(s)" in done.stderr
    with open(tmp_path / "csv" / "feedback.csv", newline="") as file:
        table = list(csv.DictReader(file))
    assert len(table) == 100
    assert [float(r["position_deg"]) for r in table] == [r["position_deg"] for r in rows]
    wrong = hil_here(capfd, "export", str(session), "--topic", "/drive/feedbak")
    assert wrong.returncode == 2 and "topics: /drive/command, /drive/feedback" in wrong.stderr


def imported(statement: str, *modules: str) -> list[str]:
    """Which of ``modules`` a fresh interpreter has imported after ``statement``."""
    code = f"import sys; {statement}; print(sorted(k for k in {modules!r} if k in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=60, check=True)
    return ast.literal_eval(done.stdout.strip())


def test_the_command_line_starts_without_the_numerical_stack():
    """`hil --help` stays fast because building the parser imports no numpy, scipy, cvxpy,
    Ray or the recorder (each command imports what it needs when it runs)."""
    assert imported("import hil.cli.main as m; m.build_parser()",
                    "numpy", "scipy", "cvxpy", "ray", "matplotlib", "hil.core.recording.recorder",
                    "hil.core.session") == []


def test_every_command_is_handled_by_a_function_named_for_it():
    """One way to name a command's handler (``NAME_command``), so that the next engineer finds
    what ``hil X Y`` runs by its name."""
    from hil.cli.main import build_parser

    def handlers(parser: argparse.ArgumentParser, path: str) -> dict[str, str]:
        found = {}
        handler = parser.get_default("handler")
        if handler is not None:
            found[path] = handler.__name__
        for action in parser._subparsers._group_actions if parser._subparsers else ():
            for name, sub in action.choices.items():
                found.update(handlers(sub, f"{path} {name}"))
        return found

    named = handlers(build_parser(), "hil")
    assert len(named) >= 20  # every command has its handler
    assert [path for path, name in named.items() if not name.endswith("_command")] == []


def test_a_process_imports_what_its_command_uses():
    """The suite starts hundreds of `hil` and writer processes: each imports its own command's
    module (not the seventeen others'), a loop or an emulator process no MCAP writer (its
    writer process writes), no JUnit XML and no tuning port, and a writer without a live view
    no live view. The modules named are each imported where they are used (first lines)."""
    writer_side = ("mcap", "zstandard", "xml.etree.ElementTree", "socket",
                   "hil.core.recording.live", "hil.core.recording.tune_wire")
    assert imported("import hil.core.recording.writer", *writer_side) == ["mcap", "zstandard"]
    assert imported("import hil.core.recording.live", *writer_side) == [
        "hil.core.recording.live", "socket"]
    assert imported("import hil.core.verdict as v; v.junit_xml([], 's')",
                    "xml.etree.ElementTree") == ["xml.etree.ElementTree"]
    others = ("hil.cli.bench", "hil.cli.demo", "hil.cli.drive", "hil.cli.sweep",
              "hil.cli.servo", "hil.cli.emulate")
    assert imported("import hil.cli.main as m; m.build_parser('servo')", *others) == [
        "hil.cli.servo"]
    assert imported("import hil.cli.main as m; m.build_parser()", *others) == sorted(others)
    loop_side = ("mcap", "zstandard", "xml.etree.ElementTree", "hil.core.recording.tune_wire",
                 "hil.core.recording.in_process", "concurrent.futures.process")
    assert imported("import hil.servo.run, hil.bench.run, hil.emulation, hil.cli.emulate",
                    *loop_side) == []


def test_runs_that_build_no_estimator_import_no_scipy_stats():
    """A run's modules import filterpy and scipy.signal (each pulls in scipy.stats, about a
    second of every process start), scipy.linalg, HiGHS and daqp (half a second together)
    only when a controller needs them: a PID servo run or a baseline bench run does not wait
    for them."""
    assert imported("import hil.servo.run, hil.bench.run",
                    "filterpy", "scipy.stats", "scipy.signal", "scipy.linalg", "highspy",
                    "daqp", "cvxpy") == []
    # every recorded run starts a writer process: it imports numpy only for an array
    assert imported("import hil.core.recording.writer", "numpy") == []


def _stderr_on_a_terminal(cwd, *args):
    """Run ``hil ARGS`` with its stderr on a pseudo-terminal; what it wrote there."""
    import pty
    import select

    master, slave = pty.openpty()
    run = subprocess.Popen([sys.executable, "-m", "hil", *args], cwd=cwd, stderr=slave,
                           stdout=subprocess.DEVNULL, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    os.close(slave)
    seen = b""
    try:
        while select.select([master], [], [], 60)[0]:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # the terminal's other end closed: the run is over
                break
            if not chunk:
                break
            seen += chunk
    finally:
        os.close(master)
        assert run.wait(timeout=60) == 0
    return seen.decode()


@pytest.mark.realtime  # on the wall clock at 2 kHz: at nice 0, ahead of the niced rest
def test_a_long_run_shows_progress_on_a_terminal_only(tmp_path):
    from tests.pymodbus_bench import short_config

    # a real-time run of one 2 s machining cycle (2 s of wall time on any machine): the line
    # is rewritten every second
    config = short_config(tmp_path)
    config.write_text(config.read_text().replace("period_s = 4.0", "period_s = 2.0")
                      .replace("end_s = 2.0", "end_s = 1.0")
                      .replace("start_s = 2.0, end_s = 4.0", "start_s = 1.0, end_s = 2.0")
                      + "[relays.M1]\ndwell_s = 0.5\n[relays.M2]\ndwell_s = 0.5\n")
    run = ("bench", "run", "--controller", "bc", "--cycles", "1", "--config", str(config))
    # the three runs at once, each its own file (the emulated bench is no locked device): the
    # wall time of one
    with ThreadPoolExecutor(3) as runs:
        shown = runs.submit(_stderr_on_a_terminal, tmp_path, *run, "--realtime",
                            "--out", "shown.mcap")
        quiet = runs.submit(_stderr_on_a_terminal, tmp_path, *run, "--realtime", "--quiet",
                            "--out", "quiet.mcap")
        piped = runs.submit(hil, tmp_path, *run, "--out", "piped.mcap")
    assert "\rbench bc: " in shown.result() and " of 2 s (" in shown.result() \
        and shown.result().endswith("\r\x1b[K")
    assert quiet.result() == ""
    assert piped.result().returncode == 0 and piped.result().stderr == ""
