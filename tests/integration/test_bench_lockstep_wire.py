"""Lockstep over the wire: ``hil bench run --bench URL`` (no ``--realtime``) against ``hil emulate
bench`` in a process of its own, both from the command line in a folder outside the
repository for the reference sessions and the pauses (a gone emulator's process is killed or
frozen; the other cases run ``hil`` in this process, tests/cli.py, from the same folder, and
serve the emulator in this process too, tests/served_here.py). The emulator follows the
run's time (the clock unit 248 of hil/protocols/bench_clock.py, read here with pymodbus's own
client), so the sessions are those of the in-process lockstep, bit for bit, and one emulator
serves them one after the other; a pause of either side changes nothing; a dead or frozen
emulator ends the run with one line and exit status 3; a Modbus server hil did not write is
not taken for the emulator; ``--clock wall`` refuses a lockstep run (which then goes by the
wall clock, with a warning) and ``--clock master`` waits for one; over RTU too. (The
``hil_bench`` fixture's runs over the wire: tests/test_user_workflow.py.)"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from hil.bench.config import load_bench_config
from hil.core.recording.reader import read_session
from hil.emulators.null_modem import NullModem
from tests.cli import hil_here
from tests.pymodbus_bench import PymodbusBench, short_config
from tests.served_here import bench_served_here
from tests.session_digest import (
    EXPERIMENTS,
    LOOPBACK_PORT,
    REFERENCE_BLAS_KERNEL,
    kpi_digest,
    session_digest,
)

pytestmark = [pytest.mark.slow]

REFERENCE = json.loads((Path(__file__).parents[1] / "data" / "session_digests.json").read_text())
CLOCK_UNIT, ON_MASTER_TIME, WAITING_FOR_MASTER = 248, 1, 2
_CPU = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
#: whether this CPU runs OpenBLAS's kernel of the reference digests
#: (tests/core/test_same_sessions.py)
REFERENCE_KERNEL = {"avx2", "fma"} <= set(_CPU.split())
#: a run's environment: hil installed, the repository not on the path, OpenBLAS's kernel of the
#: reference digests where the CPU has it
ENV = {**{k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
       **({"OPENBLAS_CORETYPE": REFERENCE_BLAS_KERNEL} if REFERENCE_KERNEL else {})}
def hil(folder: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=folder, env=ENV,
                          capture_output=True, text=True, timeout=timeout)


def skip_without_avx2() -> None:
    if not REFERENCE_KERNEL:
        pytest.skip(f"the reference digests need OpenBLAS's {REFERENCE_BLAS_KERNEL} kernel")


def plant_clock(url: str) -> tuple[float, int]:
    """The plant's time [s] and whose time it follows (CONTROL) of the emulator at ``url``,
    read with pymodbus."""
    host, port = url.removeprefix("modbus-tcp://").split(":")
    client = ModbusTcpClient(host, port=int(port), timeout=2, retries=0)
    try:
        assert client.connect()
        words = client.read_holding_registers(0, count=5, device_id=CLOCK_UNIT).registers
    finally:
        client.close()
    t_ns = (words[0] << 48) | (words[1] << 32) | (words[2] << 16) | words[3]
    return t_ns / 1e9, words[4]


class Emulator:
    """``hil emulate bench FLAGS`` in a process of its own; its stderr kept in a file."""

    def __init__(self, folder: Path, *flags: str) -> None:
        self.err = folder / "emulator.err"
        with self.err.open("w") as err:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "hil", "emulate", "bench", *flags], cwd=folder, env=ENV,
                stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL, text=True)
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        match = re.search(r"listening on (modbus-\S+?) \(", line)
        assert match, (line, self.lines())
        self.url = match.group(1)

    def clock(self) -> tuple[float, int]:
        """The plant's time [s] and whose time it follows (CONTROL), read with pymodbus."""
        return plant_clock(self.url)

    def lines(self) -> list[str]:
        """Its stderr lines but the real-time hardening it reports as it starts."""
        return [line for line in self.err.read_text().splitlines()
                if not line.startswith("hil: real-time: ")]

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGCONT)
            self.process.terminate()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self.process.stdout is not None:
            self.process.stdout.close()

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


def run_argv(name: str, url: str, out: str) -> list[str]:
    """``hil bench run`` of a reference experiment of tests/session_digest.py against ``url``."""
    _function, arguments = EXPERIMENTS[name]
    limits = [arg for limit in arguments.get("limits", []) for arg in ("--limit", limit)]
    return ["bench", "run", "--controller", arguments["controller"], "--cycles",
            str(arguments["cycles"]), "--bench", url, "--json", "--out", out, *limits]


def assert_reference_session(folder: Path, name: str, run: subprocess.CompletedProcess[str]
                             ) -> None:
    assert run.returncode == 0, run.stderr
    assert kpi_digest(json.loads(run.stdout)) == REFERENCE[name]["kpis"]
    assert session_digest(str(folder / f"{name}.mcap")) == REFERENCE[name]["topics"]


@pytest.fixture(scope="module")
def seeded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Emulator]:
    """``hil emulate bench --seed 7``, shared by the runs compared with the reference sessions:
    a lockstep session starts its plant again from t = 0, whatever the emulator did before."""
    with Emulator(tmp_path_factory.mktemp("seeded"), "--tcp", "127.0.0.1:0", "--seed",
                  "7") as emulator:
        yield emulator


@pytest.mark.parametrize("name", ["bench-bc", "bench-eec"])
def test_a_lockstep_run_over_the_wire_records_the_in_process_session(seeded, tmp_path, name):
    """The reference experiments, in lockstep against the emulator process: the messages and
    KPIs the in-process lockstep recorded (tests/data/session_digests.json), bit for bit. On
    any CPU, a script reads --json from stdout: nothing else may be printed there (the MILP
    solver's banner included)."""
    seen = len(seeded.lines())
    run = hil(tmp_path, *run_argv(name, seeded.url, f"{name}.mcap"))
    assert run.returncode == 0, run.stderr
    kpis = json.loads(run.stdout)  # the JSON document alone: nothing else was printed there
    assert kpis["controller"] == EXPERIMENTS[name][1]["controller"]
    assert kpis["solves_at_limit"] == 0
    assert seeded.clock()[1] != ON_MASTER_TIME  # let go: back on the wall clock
    metadata = read_session(str(tmp_path / f"{name}.mcap")).metadata
    assert metadata["session"]["clock"] == "sim"
    assert metadata["bench"]["identity"] == "hil hil-bench-emulator 2.0"
    assert metadata["bench"]["time"] == "the run's (lockstep over the wire)"
    lines = seeded.lines()[seen:]
    assert "took the plant's time; the plant starts again from t = 0" in lines[0]
    # one cycle is 28 s: the last tick gave the time of the tick after it
    assert "the lockstep master let go at plant time 28.00 s" in lines[1]
    skip_without_avx2()
    assert_reference_session(tmp_path, name, run)


class AtPlantTime:
    """Calls ``act()`` from a thread once the emulator's plant is past ``t_s`` on a master's
    time; ``at`` is the plant time it acted at (None: it never did)."""

    def __init__(self, emulator: Emulator, t_s: float, act: Callable[[], None]) -> None:
        self.emulator, self.t_s, self.act = emulator, t_s, act
        self.at: float | None = None
        self.thread = threading.Thread(target=self._watch, daemon=True)
        self.thread.start()

    def _watch(self) -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            plant_s, state = self.emulator.clock()
            if state == ON_MASTER_TIME and plant_s >= self.t_s:
                self.at = plant_s
                self.act()
                return
            time.sleep(0.01)

    def join(self) -> None:
        self.thread.join(5)


@pytest.mark.parametrize("paused", ["emulator", "run"])
def test_a_second_long_pause_of_either_side_changes_nothing(seeded, tmp_path, paused):
    skip_without_avx2()
    run = subprocess.Popen([sys.executable, "-m", "hil", *run_argv(
        "bench-bc", seeded.url, "bench-bc.mcap")], cwd=tmp_path, env=ENV,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pid = {"emulator": seeded.process.pid, "run": run.pid}[paused]

    def pause() -> None:
        os.kill(pid, signal.SIGSTOP)
        time.sleep(1.0)
        os.kill(pid, signal.SIGCONT)

    watcher = AtPlantTime(seeded, 3.0, pause)
    stdout, stderr = run.communicate(timeout=300)
    watcher.join()
    assert watcher.at is not None and watcher.at < 27.0  # paused mid-run
    assert_reference_session(tmp_path, "bench-bc", subprocess.CompletedProcess(
        run.args, run.returncode, stdout, stderr))


@pytest.mark.parametrize("how", ["killed", "frozen"])
def test_a_gone_emulator_ends_the_run_with_its_relays_unconfirmed_unsafe(tmp_path, capfd, how):
    """Killed (its connection refused) or frozen for longer than bus.lockstep_timeout_s (2 s
    here): one line naming the emulator, the run stopped within the bound; and one saying the
    relays may still be on (they cannot be read back): the run is unsafe, exit 4."""
    config = tmp_path / "patient.toml"
    config.write_text("[bus]\nlockstep_timeout_s = 2.0\n")
    with Emulator(tmp_path, "--tcp", "127.0.0.1:0") as emulator:
        pid = emulator.process.pid
        end = {"killed": signal.SIGKILL, "frozen": signal.SIGSTOP}[how]
        watcher = AtPlantTime(emulator, 3.0, lambda: os.kill(pid, end))
        run = hil_here(capfd, "bench", "run", "--controller", "bc", "--cycles", "1", "--bench",
                       emulator.url, "--config", config, "--out", "gone.mcap", cwd=tmp_path)
        watcher.join()
    assert watcher.at is not None
    assert run.returncode == 4, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 2, lines
    # the relays could not be read back after the run (tried as a lost link is)
    assert lines[0] == (f"hil: unsafe: relays M1, M2, P1, P2 may still be on: the bench at "
                        f"{emulator.url} did not answer after the run (5 tries, 0.5 s apart)")
    assert lines[1].startswith("hil: run disturbed (link lost: the bench emulator is gone (")
    assert emulator.url in lines[1] and "link_losses 1" in lines[1]
    events = [m for _, m in read_session(str(tmp_path / "gone.mcap")).topic("/events")]
    if how == "frozen":  # the session's events, to tell why if it ever is not (seen once)
        assert "no answer from" in lines[1] and "within 2 s (bus.lockstep_timeout_s)" in \
            lines[1], [(event["kind"], event["message"]) for event in events]
    kinds = [event["kind"] for event in events]
    assert kinds.index("link.lost") < kinds.index("link.gave_up")
    unconfirmed = events[kinds.index("bench.safe_state_unconfirmed")]
    assert unconfirmed["level"] == "error" and unconfirmed["data"]["unknown"] == \
        ["M1", "M2", "P1", "P2"] and unconfirmed["data"]["on"] == []


def test_faults_play_on_the_runs_time_and_never_leave_it_waiting(tmp_path, capfd):
    """Late answers (300 ms, over timeout_s) and dropped ones are answered at once with
    exception 0x0B: retried, the link lost (and restored), then given up after give_up_s of the
    run's time; never the 60 s bound a silence would take to mean a gone emulator."""
    config = tmp_path / "faults.toml"
    config.write_text("[bus]\ngive_up_s = 5.0\nlockstep_timeout_s = 60.0\n")
    with bench_served_here(faults=["delay@2-2.5:ms=300", "drop@10"]) as emulator:
        run = hil_here(capfd, "bench", "run", "--controller", "bc", "--cycles", "1", "--bench",
                       emulator.url, "--config", config, "--json", "--out", "faults.mcap",
                       cwd=tmp_path)
    assert run.returncode == 4, run.stderr  # dropped for good: the relays unconfirmed
    kpis = json.loads(run.stdout)
    assert kpis["stop_reason"] == "link lost for 5 s"
    # late answers for 0.5 s: lost, then restored; dropped ones from 10 s: lost for good
    assert (kpis["faults"]["link_losses"], kpis["faults"]["reconnections"]) == (2, 1)
    injected = emulator.fault_events()
    assert [line.split(" injected at ")[1].split(" ")[0] for line in injected] == \
        ["t=2.000", "t=10.000"]  # on the run's time, from its start


def test_a_modbus_server_hil_did_not_write_is_not_taken_for_the_emulator(tmp_path, capfd):
    """pymodbus's own server answers Read Device Identification with an identity that is not
    hil's: the run (no --realtime) follows the wall clock, as against any real bench (a 1 s
    cycle)."""
    config = short_config(tmp_path, period_s=1.0, dwell_s=0.25)
    with PymodbusBench(load_bench_config(str(config))) as peer:
        run = hil_here(capfd, "bench", "run", "--controller", "bc", "--cycles", "1", "--bench",
                       peer.url, "--config", config, "--out", "peer.mcap", cwd=tmp_path)
    assert run.returncode in (0, 3), run.stderr  # 3: a loaded machine answered late
    metadata = read_session(str(tmp_path / "peer.mcap")).metadata
    assert metadata["session"]["clock"] == "realtime"
    assert metadata["bench"] == {"url": peer.url, "identity": "", "time": "its own"}


def test_an_emulator_on_its_wall_clock_refuses_a_lockstep_run_in_one_line(tmp_path, capfd):
    """The run is then on the wall clock, as against a real bench (a 1 s cycle)."""
    config = short_config(tmp_path, period_s=1.0, dwell_s=0.25)
    with bench_served_here(clock="wall") as emulator:
        run = hil_here(capfd, "bench", "run", "--controller", "bc", "--cycles", "1", "--bench",
                       emulator.url, "--config", config, "--out", "wall.mcap", cwd=tmp_path)
        assert plant_clock(emulator.url)[1] == 0  # still on its wall clock
    warning = (f"hil: warning: the bench emulator at {emulator.url} keeps its wall clock (hil "
               "emulate bench --clock wall): this run follows the wall clock too, as against "
               "a real bench")
    assert run.returncode in (0, 3), run.stderr  # 3: a loaded machine answered late
    assert run.stderr.splitlines()[0] == warning
    data = read_session(str(tmp_path / "wall.mcap"))
    assert data.metadata["session"]["clock"] == "realtime"
    assert [m["message"] for _, m in data.topic("/events") if m["kind"] == "bench.clock"] == \
        [warning.removeprefix("hil: warning: ")]
    assert any(line.endswith("asked for the plant's time: refused (--clock wall)")
               for line in emulator.clock_lines)


def test_an_emulator_on_master_time_waits_for_a_master_before_and_after(tmp_path, capfd):
    """A 1 s cycle: the plant stays where the run left it."""
    config = short_config(tmp_path, period_s=1.0, dwell_s=0.25)
    with bench_served_here(clock="master") as emulator:
        time.sleep(0.3)  # what the wall clock would have stepped
        assert plant_clock(emulator.url) == (0.0, WAITING_FOR_MASTER)
        run = hil_here(capfd, "bench", "run", "--controller", "bc", "--cycles", "1", "--bench",
                       emulator.url, "--config", config, "--out", "run.mcap", cwd=tmp_path)
        assert run.returncode == 0, run.stderr
        time.sleep(0.3)
        assert plant_clock(emulator.url) == (1.0, WAITING_FOR_MASTER)
    assert emulator.clock_lines[-1].endswith("let go at plant time 1.00 s; the plant waits for "
                                         "a master")


SHORT_RUN = ["--controller", "bc", "--cycles", "1", "--limit", "total_va<=5000", "--json"]


def test_lockstep_over_rtu_records_the_in_process_session(tmp_path, capfd):
    """Over Modbus RTU (a pty pair) too; the sessions differ only by the bench URL in the
    events. A 1 s cycle: pymodbus' serial client polls its port every millisecond, so a
    lockstep RTU run goes about as fast as real time."""
    config = str(short_config(tmp_path, period_s=1.0, dwell_s=0.25))
    inside = hil_here(capfd, "bench", "run", *SHORT_RUN, "--config", config, "--out", "in.mcap",
                      cwd=tmp_path)
    assert inside.returncode == 0, inside.stderr
    with NullModem() as modem, bench_served_here(config, serial=modem.ports[1]) as emulator:
        url = f"modbus-rtu://{modem.ports[0]}?baud=115200&parity=N"
        wire = hil_here(capfd, "bench", "run", *SHORT_RUN, "--config", config, "--bench", url,
                        "--out", "rtu.mcap", cwd=tmp_path)
    assert wire.returncode == 0, wire.stderr
    assert kpi_digest(json.loads(wire.stdout)) == kpi_digest(json.loads(inside.stdout))
    ours, theirs = (session_digest(str(tmp_path / f)) for f in ("rtu.mcap", "in.mcap"))
    assert ours.keys() == theirs.keys()
    assert {t: d for t, d in ours.items() if t != "/events"} == \
        {t: d for t, d in theirs.items() if t != "/events"}
    assert events_digest(tmp_path / "rtu.mcap", url) == events_digest(tmp_path / "in.mcap")
    assert "took the plant's time" in emulator.clock_lines[0]


def events_digest(path: Path, url: str = "") -> str:
    """The ``/events`` of a session, the bench URL ``url`` written as a loopback one."""
    digest = hashlib.sha256()
    for t_ns, message in read_session(str(path)).topic("/events"):
        text = json.dumps([t_ns, message], sort_keys=True)
        if url:
            text = text.replace(json.dumps(url)[1:-1], "modbus-tcp://127.0.0.1:PORT")
        digest.update(LOOPBACK_PORT.sub("127.0.0.1:PORT", text).encode())
    return digest.hexdigest()
