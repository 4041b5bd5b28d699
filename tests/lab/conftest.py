"""A labgrid lab on 127.0.0.1 for one test: a real ``labgrid-coordinator`` on a free port, hil's
bench and drive emulators in processes of their own, a real ``labgrid-exporter`` publishing them
as HilBench / HilDrive resources, and the places ``bench``, ``drive`` and ``bad`` (a drive
published with a wrong field) that hold them. Every
process ends with the test (and with the test process, however it ends)."""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from hil.emulator_process import start_bench_emulator, start_drive_emulator
from hil.lab.local import BIN, local_lab

READY_TIMEOUT_S = 90.0  # generous: a busy 2-core machine starts gRPC processes slowly
EXPORTER = "hil-lab"
RESOURCES = (("bench-1", "HilBench"), ("drive-1", "HilDrive"))  # (group, resource name)

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
## a drive published with a node id that is no number (place "bad")
bad-1:
  HilDrive:
    url: {drive_url}
    node: one
"""


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "lab: starts a labgrid coordinator and exporter "
                            "(tests/lab)")


def user_env(**extra: str) -> dict[str, str]:
    """A user's shell: hil installed, the repository not on the path."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "LG_COORDINATOR", "LG_ENV")}
    return {**env, **extra}


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


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    """Coordinator, emulators, exporter and the places ``bench`` and ``drive``."""
    with start_bench_emulator() as bench, start_drive_emulator() as drive:
        text = EXPORTER_YAML.format(
            bench_url=bench.url, drive_url=drive.url,
            bench_hostport=bench.url.split("//")[1], drive_hostport=drive.url.split("//")[1])
        with local_lab(tmp_path / "lab", text, [*RESOURCES, ("bad-1", "HilDrive")],
                       exporter=EXPORTER,
                       timeout_s=READY_TIMEOUT_S, env=user_env()) as address:
            for place, (group, cls) in zip(("bench", "drive", "bad"),
                                           [*RESOURCES, ("bad-1", "HilDrive")], strict=True):
                client(address, "-p", place, "create")
                client(address, "-p", place, "add-match", f"{EXPORTER}/{group}/{cls}")
            yield Lab(address, tmp_path, bench.url, drive.url, text)
