"""An emulator in its own process on loopback, as the hardware would be: ``hil emulate bench``
or ``hil emulate drive`` on 127.0.0.1 and a free port, started and stopped from Python.

Used by the Python API (:mod:`hil.api`) and the pytest fixtures (:mod:`hil.pytest_plugin`).
Every wait is bounded; the process is stopped with SIGTERM (then SIGKILL) whatever happens,
and dies with the process that started it even when that one is SIGKILLed.
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import tomli_w

from hil.core.lifeline import lifeline_env
from hil.core.realtime import (
    forget_helper_process,
    parse_step_lines,
    register_helper_process,
    report_helper_hardening,
)
from hil.emulators.faults import Fault, parse_fault
from hil.errors import HilError
from hil.protocols.bench_clock import CLOCKS as BENCH_CLOCKS

_BENCH_URL = re.compile(r"listening on (modbus-tcp://\S+?)[ ,;]")
_DRIVE_URL = re.compile(r"socketcand (\S+):(\d+)\b")
FAULT_PREFIX = "hil: fault: "


class EmulatorProcess:
    """A running ``hil emulate ...`` process; ``url`` is where a driver reaches it."""

    def __init__(self, argv: list[str], what: str, timeout_s: float = 30.0, *,
                 harden: bool = False) -> None:
        self.what = what
        self.hardening: dict[str, str] = {}  # what it was granted, when started with --harden
        self._faults_seen: list[str] = []
        self._stderr: IO[str] = tempfile.TemporaryFile("w+")  # noqa: SIM115 - closed by stop()
        # it dies with this process, even SIGKILLed (hil.core.lifeline); in a session of its
        # own, so a Ctrl-C at the terminal reaches the run, which stops it in order
        env = lifeline_env({**os.environ, "PYTHONUNBUFFERED": "1"})
        self.process = subprocess.Popen(
            [sys.executable, "-m", "hil", "emulate", *argv,
             "--harden" if harden else "--no-harden"], stdout=subprocess.PIPE,
            stderr=self._stderr, stdin=subprocess.DEVNULL, text=True, env=env,
            start_new_session=True)
        register_helper_process(self.process.pid)  # real-time hardening keeps it off the loop
        self.url = self._wait_for_url(timeout_s)
        if harden:  # reported on stderr before its ready line
            self.hardening = parse_step_lines(self.stderr_lines())
            report_helper_hardening(self.process.pid, self.hardening)

    def _wait_for_url(self, timeout_s: float) -> str:
        assert self.process.stdout is not None
        ready, _, _ = select.select([self.process.stdout], [], [], timeout_s)
        line = self.process.stdout.readline() if ready else ""
        bench, drive = _BENCH_URL.search(line), _DRIVE_URL.search(line)
        if bench:
            return bench.group(1)
        if drive:
            return f"socketcand://{drive.group(1)}:{drive.group(2)}"
        exited = False
        if ready and not line:  # stdout closed: the process is ending, let it write its error
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(5)
            exited = self.process.poll() is not None
        why = self.stderr_tail() or line.strip() or (
            f"it exited with status {self.process.returncode}" if exited
            else f"no answer within {timeout_s:g} s")
        self.stop()
        raise HilError(f"the {self.what} emulator did not start: {why}")

    @property
    def pid(self) -> int:
        return self.process.pid

    def stderr_tail(self, lines: int = 5) -> str:
        """The last lines the emulator wrote to stderr (for error messages)."""
        if self._stderr.closed:
            return ""
        self._stderr.seek(0)
        return " | ".join(self._stderr.read().strip().splitlines()[-lines:])

    def stderr_lines(self) -> list[str]:
        """Every line the emulator wrote to stderr so far."""
        if self._stderr.closed:
            return []
        self._stderr.seek(0)
        return self._stderr.read().splitlines()

    def fault_events(self) -> list[str]:
        """The faults the emulator reported injecting so far (its ``hil: fault:`` lines)."""
        if self._stderr.closed:
            return list(self._faults_seen)
        self._stderr.seek(0)
        self._faults_seen = [line.removeprefix(FAULT_PREFIX).strip()
                             for line in self._stderr.read().splitlines()
                             if line.startswith(FAULT_PREFIX)]
        return list(self._faults_seen)

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM (resuming a stopped process first), then SIGKILL; idempotent."""
        forget_helper_process(self.process.pid)
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGCONT)
            self.process.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout_s)
        if self.process.stdout is not None:
            self.process.stdout.close()
        if not self._stderr.closed:
            self.fault_events()
        self._stderr.close()

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


def _fault_flags(faults: Iterable[str | Fault]) -> list[str]:
    flags = []
    for fault in faults:
        text = str(fault)
        parse_fault(text, "fault")  # a bad one is refused here, not in the child's stderr
        flags += ["--fault", text]
    return flags


@contextlib.contextmanager
def _config_file(config: str | Path | None, tables: Mapping[str, Any] | None
                 ) -> Iterator[str | None]:
    """The config a process reads: ``config``, or ``tables`` (a run's effective tables, its
    flags laid in) written to a temporary file for as long as the process starts."""
    if tables is None:
        yield None if config is None else str(config)
        return
    if config is not None:
        raise HilError("give an emulator process a config file or tables, not both")
    with tempfile.NamedTemporaryFile("wb", prefix="hil-config-", suffix=".toml") as file:
        file.write(tomli_w.dumps(dict(tables)).encode())
        file.flush()
        yield file.name


def start_bench_emulator(config: str | Path | None = None, *, seed: int | None = None,
                         disturbance: bool = False, host: str = "127.0.0.1",
                         faults: Iterable[str | Fault] = (), timeout_s: float = 30.0,
                         tables: Mapping[str, Any] | None = None,
                         clock: str = "auto", harden: bool = False) -> EmulatorProcess:
    """The relay-bench emulator over Modbus TCP on ``host`` and a free port; ``faults``
    (``KIND@START[-END][:KEY=VALUE,...]`` or :class:`~hil.emulators.faults.Fault`) are played on
    its plant clock, seconds after it starts (or after a lockstep master's session starts).
    Its config: the file ``config``, or ``tables`` (the effective tables of a run). ``clock``:
    what its plant's time follows (``hil emulate bench --clock``): ``auto`` (the wall clock
    until a lockstep run takes the time, as ``run_bench(bench=url)`` does), ``wall`` or
    ``master``; a master taking or letting go of it is a ``hil: clock:`` line on its stderr
    (:meth:`EmulatorProcess.stderr_tail`). ``harden``: as for :func:`start_drive_emulator`
    (``hil emulate bench --harden``, the command's default, not this function's)."""
    if clock not in BENCH_CLOCKS:
        raise HilError(f"clock must be one of {', '.join(BENCH_CLOCKS)}, got {clock!r}")
    argv = ["bench", "--tcp", f"{host}:0", "--clock", clock, *_fault_flags(faults)]
    if seed is not None:
        argv += ["--seed", str(seed)]
    if disturbance:
        argv.append("--disturbance")
    with _config_file(config, tables) as path:
        return EmulatorProcess([*argv, *(["--config", path] if path else [])], "bench",
                               timeout_s, harden=harden)


def start_drive_emulator(config: str | Path | None = None, *, node: int | Iterable[int] = 1,
                         host: str = "127.0.0.1", faults: Iterable[str | Fault] = (),
                         timeout_s: float = 30.0,
                         tables: Mapping[str, Any] | None = None,
                         harden: bool = False, clock: str = "auto",
                         model: str | Path | None = None) -> EmulatorProcess:
    """The CiA 402 drive emulator over socketcand on ``host`` and a free port (``node``: its
    node id, or several, one drive and axis each, on the one bus); ``faults`` as for
    :func:`start_bench_emulator`, seconds after it starts (each drive plays them). Its
    config: the file ``config``, or ``tables`` (the effective tables of a run). ``harden``:
    it serves as a real-time process where the OS allows (``--harden``, the command's
    default; ``--no-harden`` here otherwise: an emulator for tests and lockstep runs stays an
    ordinary process); what it was granted
    is its ``hardening`` (``{step: "granted: ..." | "refused: ..."}``), which the next
    real-time session of this process records as ``realtime.emulator`` metadata. ``clock``:
    ``auto`` (its own, until a lockstep master asks for its SYNC time), ``sync`` or ``wall``
    (``hil emulate drive --clock``). ``model``: its axis as a model file (``--model``, over the
    config's ``[emulator] model``; made absolute here, as the tables of a run are read from a
    temporary file whose folder is not the run's)."""
    nodes = [node] if isinstance(node, int) else list(node)
    argv = ["drive", "--socketcand", f"{host}:0", "--clock", clock,
            *[arg for n in nodes for arg in ("--node", str(n))], *_fault_flags(faults),
            *(["--model", os.path.abspath(model)] if model is not None else [])]
    with _config_file(config, tables) as path:
        return EmulatorProcess([*argv, *(["--config", path] if path else [])], "drive",
                               timeout_s, harden=harden)
