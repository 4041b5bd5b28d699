"""A labgrid lab on 127.0.0.1, one per test session (with xdist, one per worker: each its own
coordinator on a free port, state in its own temporary folder): a real
``labgrid-coordinator``, hil's bench and drive emulators in processes of their own, and a real
``labgrid-exporter`` publishing them as HilBench / HilDrive resources. A test makes places of
its own (:meth:`Lab.place`, a name no other test uses); a place holds the exporter's resources
while it is acquired, so each test's places are released when it ends (one a test left held
included). Every process ends with the session (and with the test process, however it
ends)."""

from __future__ import annotations

import itertools
import os
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from hil.emulator_process import start_bench_emulator, start_drive_emulator
from hil.lab.local import BIN, local_lab
from tests.pymodbus_bench import short_config

READY_TIMEOUT_S = 90.0  # generous: a busy 2-core machine starts gRPC processes slowly
EXPORTER = "hil-lab"
#: (group, resource name) the exporter publishes; bad-1 a drive with a wrong field
RESOURCES = (("bench-1", "HilBench"), ("drive-1", "HilDrive"), ("bad-1", "HilDrive"))

EXPORTER_YAML = """\
## what `hil emulate bench --tcp {bench_hostport}` and
## `hil emulate drive --socketcand {drive_hostport}` serve, published as hil resources
bench-1:
  HilBench:
    url: {bench_url}
    config: {bench_config}
drive-1:
  HilDrive:
    url: {drive_url}
    node: 1
## a drive published with a node id that is no number
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
    bench_config: Path  # the bench resource's config: a 4 s machining cycle
    exporter_yaml: str
    _names: Iterator[int] = field(default_factory=itertools.count)
    made: list[str] = field(default_factory=list)  # the places of the running test

    def place(self, *groups: str) -> str:
        """A new place holding the resources of ``groups`` (``bench-1``, ``drive-1``,
        ``bad-1``): its name, which no other test of the session uses."""
        name = f"p{next(self._names)}"
        self.made.append(name)
        self.rpc("AddPlace", name=name)
        for group in groups:
            self.rpc("AddPlaceMatch", placename=name,
                     pattern=f"{EXPORTER}/{group}/{dict(RESOURCES)[group]}")
        return name

    def rpc(self, method: str, user: str | None = None, **fields: Any) -> Any:
        """One call to the coordinator, as ``labgrid-client`` makes it (as labgrid user
        ``user`` when given), from this process: a client process costs a second of CPU."""
        from labgrid.remote.client import start_session
        from labgrid.remote.generated import labgrid_coordinator_pb2 as pb2

        with pytest.MonkeyPatch.context() as patch:  # a session names its user at the start
            if user is not None:
                patch.setenv("LG_USERNAME", user)
            session = self._session(start_session)
        try:
            request = getattr(pb2, f"{method}Request")(**fields)
            return session.loop.run_until_complete(getattr(session.stub, method)(request))
        finally:
            session.loop.run_until_complete(session.stop())
            session.loop.run_until_complete(session.close())

    def _session(self, start: Callable[[str], Any]) -> Any:
        """A client session to the coordinator. The coordinator refuses a stream from a peer
        address it still lists (``assert peer not in self.clients``): on a loaded machine the
        stream a call closed just before may not be gone yet, so a refused start is tried
        again (a few times, 0.2 s apart)."""
        from labgrid.remote.client import ServerError

        for _ in range(4):
            try:
                return start(self.address)
            except ServerError:
                time.sleep(0.2)
        return start(self.address)

    def acquire(self, place: str, user: str | None = None) -> None:
        self.rpc("AcquirePlace", user, placename=place)

    def release(self, place: str) -> None:
        """Release ``place``, whoever holds it (``labgrid-client release --kick``)."""
        self.rpc("ReleasePlace", placename=place)

    def holder(self, place: str) -> str | None:
        """Who holds ``place``, as the coordinator says."""
        [found] = [p for p in self.rpc("GetPlaces").places if p.name == place]
        return found.acquired or None  # type: ignore[no-any-return]

    def reservations(self) -> list[Any]:
        """The coordinator's reservations (labgrid's Reservation)."""
        from labgrid.remote.common import Reservation

        return [Reservation.from_pb2(r) for r in self.rpc("GetReservations").reservations]

    def wait_for_reservation(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Poll the coordinator until a reservation waits for a place."""
        from labgrid.remote.common import ReservationState

        deadline = time.monotonic() + timeout_s
        while not any(r.state is ReservationState.waiting for r in self.reservations()):
            assert time.monotonic() < deadline, "no reservation waits"
            time.sleep(0.2)

    def wait_for_session(self, session: Path, run: subprocess.Popen[str],
                         timeout_s: float = READY_TIMEOUT_S) -> None:
        """Wait until ``run`` has started writing ``session`` (the place is held by then)."""
        deadline = time.monotonic() + timeout_s
        while not session.exists():
            assert run.poll() is None, f"the run ended: {run.communicate()}"
            assert time.monotonic() < deadline, f"{session} never appeared"
            time.sleep(0.2)

    def release_made(self) -> None:
        """Release the running test's places that are still held, by whoever holds them."""
        for name in self.made:
            if self.holder(name) is not None:
                self.release(name)
        self.made.clear()


@pytest.fixture
def lab(shared_lab: Lab) -> Iterator[Lab]:
    """The session's lab; the places the test made, released after it."""
    try:
        yield shared_lab
    finally:
        shared_lab.release_made()


@pytest.fixture(scope="session")
def shared_lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    """Coordinator, emulators and exporter, shared by the session's (worker's) tests."""
    folder = tmp_path_factory.mktemp("lab")
    config = short_config(folder, period_s=4.0)
    with start_bench_emulator() as bench, start_drive_emulator() as drive:
        text = EXPORTER_YAML.format(
            bench_url=bench.url, drive_url=drive.url, bench_config=config,
            bench_hostport=bench.url.split("//")[1], drive_hostport=drive.url.split("//")[1])
        with local_lab(folder / "lab", text, RESOURCES, exporter=EXPORTER,
                       timeout_s=READY_TIMEOUT_S, env=user_env()) as address:
            yield Lab(address, folder, bench.url, drive.url, config, text)
