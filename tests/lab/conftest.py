"""A labgrid lab on 127.0.0.1 for one test: a real ``labgrid-coordinator`` on a free port, hil's
bench and drive emulators in processes of their own, a real ``labgrid-exporter`` publishing them
as HilBench / HilDrive resources, and the places ``bench`` and ``drive`` that hold them. Every
process ends with the test (and with the test process, however it ends)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from hil.emulator_process import start_bench_emulator, start_drive_emulator

BIN = Path(sys.executable).parent
READY_TIMEOUT_S = 90.0  # generous: a busy 2-core machine starts gRPC processes slowly
EXPORTER = "hil-lab"

EXPORTER_YAML = """\
## what `hil emulate bench --tcp {bench_hostport}` and
## `hil emulate drive --socketcand {drive_hostport}` serve, published as hil resources
bench-1:
  HilBench:
    url: {bench_url}
drive-1:
  HilDrive:
    url: {drive_url}
    node: 1
"""


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "lab: starts a labgrid coordinator and exporter "
                            "(tests/lab)")


def _die_with_us() -> None:
    """In the child, before exec: SIGTERM when the test process dies."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)


def user_env(**extra: str) -> dict[str, str]:
    """A user's shell: hil installed, the repository not on the path."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "LG_COORDINATOR", "LG_ENV")}
    return {**env, **extra}


def start(argv: list[str], log: Path, **env: str) -> subprocess.Popen[str]:
    """``argv`` started in ``log``'s folder, its output to ``log`` (a pipe nobody reads
    would fill and stop it)."""
    with log.open("w") as out:
        return subprocess.Popen(argv, cwd=log.parent, env=user_env(**env), stdout=out,
                                stderr=subprocess.STDOUT, text=True, preexec_fn=_die_with_us)


def read_until(log: Path, marker: str, timeout_s: float) -> str:
    """The first line of ``log`` holding ``marker``, once it is written."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            if marker in line:
                return line
        time.sleep(0.1)
    raise AssertionError(f"{log.name} never said {marker!r}: {log.read_text()[-2000:]}")


def stop(process: subprocess.Popen[str]) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=30)


def client(address: str, *args: str, user: str | None = None,
           check: bool = True) -> subprocess.CompletedProcess[str]:
    """``labgrid-client -x ADDRESS ARGS`` (as ``user`` when given)."""
    env = user_env(**({"LG_USERNAME": user} if user else {}))
    out = subprocess.run([str(BIN / "labgrid-client"), "-x", address, *args], env=env,
                         capture_output=True, text=True, timeout=120)
    if check:
        assert out.returncode == 0, out.stdout + out.stderr
    return out


@dataclass
class Lab:
    address: str
    folder: Path
    bench_url: str
    drive_url: str
    exporter_yaml: str
    processes: list[subprocess.Popen[str]] = field(default_factory=list)

    def holder(self, place: str) -> str | None:
        """Who holds ``place``, as the coordinator says."""
        from labgrid.remote.client import start_session

        session = start_session(self.address)
        try:
            return session.places[place].acquired  # type: ignore[no-any-return]
        finally:
            session.loop.run_until_complete(session.stop())
            session.loop.run_until_complete(session.close())

    def wait_for_reservation(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Poll the coordinator until a reservation waits for a place."""
        deadline = time.monotonic() + timeout_s
        while "state: waiting" not in client(self.address, "reservations").stdout:
            assert time.monotonic() < deadline, "no reservation waits"
            time.sleep(0.2)

    def wait_for_session(self, session: Path, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Wait until a run has started writing ``session`` (the place is held by then)."""
        deadline = time.monotonic() + timeout_s
        while not session.exists():
            assert time.monotonic() < deadline, f"{session} never appeared"
            time.sleep(0.2)

    def wait_for(self, place: str, holder: str | None, timeout_s: float = READY_TIMEOUT_S
                 ) -> None:
        """Poll the coordinator until ``place`` is held by ``holder`` (None: free)."""
        deadline = time.monotonic() + timeout_s
        while (now := self.holder(place)) != holder:
            assert time.monotonic() < deadline, f"{place} held by {now}, not {holder}"
            time.sleep(0.2)


def _published(address: str) -> bool:
    """Whether the coordinator lists both hil resources of the exporter, available."""
    from labgrid.remote.client import start_session

    session = start_session(address)
    try:
        groups = session.resources.get(EXPORTER, {})
        entries = [groups.get(g, {}).get(c) for g, c in (("bench-1", "HilBench"),
                                                           ("drive-1", "HilDrive"))]
        return all(e is not None and e.avail for e in entries)
    finally:
        session.loop.run_until_complete(session.stop())
        session.loop.run_until_complete(session.close())


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    """Coordinator, emulators, exporter and the places ``bench`` and ``drive``."""
    folder = tmp_path / "coordinator"
    folder.mkdir()
    processes: list[subprocess.Popen[str]] = []
    with start_bench_emulator() as bench, start_drive_emulator() as drive:
        try:
            log = folder / "coordinator.log"
            processes.append(start([str(BIN / "labgrid-coordinator"), "--listen",
                                    "127.0.0.1:0"], log))
            port = read_until(log, "listening on", READY_TIMEOUT_S).rsplit(":", 1)[1]
            address = f"127.0.0.1:{port.strip()}"
            text = EXPORTER_YAML.format(
                bench_url=bench.url, drive_url=drive.url,
                bench_hostport=bench.url.split("//")[1], drive_hostport=drive.url.split("//")[1])
            (tmp_path / "exporter.yaml").write_text(text)
            processes.append(start([str(BIN / "labgrid-exporter"), "-c", address, "-n", EXPORTER,
                                    "--hostname", "127.0.0.1", "exporter.yaml"],
                                   tmp_path / "exporter.log"))
            deadline = time.monotonic() + READY_TIMEOUT_S
            while not _published(address):
                log = (tmp_path / "exporter.log").read_text()
                assert processes[-1].poll() is None, f"the exporter ended: {log[-2000:]}"
                assert time.monotonic() < deadline, f"nothing published: {log[-2000:]}"
                time.sleep(0.2)
            for place, group, cls in (("bench", "bench-1", "HilBench"),
                                      ("drive", "drive-1", "HilDrive")):
                client(address, "-p", place, "create")
                client(address, "-p", place, "add-match", f"{EXPORTER}/{group}/{cls}")
            yield Lab(address, tmp_path, bench.url, drive.url, text, processes)
        finally:
            for process in reversed(processes):
                stop(process)
