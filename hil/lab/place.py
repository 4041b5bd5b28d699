"""A labgrid place held for one run: :func:`hold_place` connects to the coordinator, acquires
the place unless the user already holds it (waiting for it through a labgrid reservation when
asked), hands over its hil resources, and releases the place on the way out (an error and
Ctrl-C included) if it acquired it. A process killed outright leaves the place acquired, as
labgrid does: ``labgrid-client -p NAME release`` frees it."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from labgrid.factory import target_factory
from labgrid.remote import client

from hil.errors import UsageError

#: labgrid's own default coordinator address (``LG_COORDINATOR`` says otherwise)
DEFAULT_COORDINATOR = "127.0.0.1:20408"
POLL_S = 0.5          # how often a wait asks the coordinator about its reservation
PROGRESS_EVERY_S = 5.0


class PlaceBusyError(UsageError):
    """The place is held by someone else (and stayed so for ``--wait``)."""


def coordinator_address(given: str | None) -> str:
    """``--coordinator``, else labgrid's ``LG_COORDINATOR``, else its default."""
    return given or os.environ.get("LG_COORDINATOR") or DEFAULT_COORDINATOR


@dataclass(frozen=True)
class PlaceResource:
    """One resource of a held place: its class and fields, and where it is published."""

    cls: str
    name: str
    args: dict[str, Any]
    exporter: str
    group: str
    host: str

    def record(self) -> dict[str, Any]:
        return {"cls": self.cls, "name": self.name, "path": f"{self.exporter}/{self.group}/"
                f"{self.cls}/{self.name}", "exporter": self.exporter, "host": self.host,
                **self.args}


@dataclass
class HeldPlace:
    """A place held for a run: its name, the coordinator, whether this run acquired it (and
    so releases it), and its resources."""

    name: str
    coordinator: str
    acquired_here: bool
    holder: str
    resources: list[PlaceResource] = field(default_factory=list)

    def one(self, cls: str) -> PlaceResource:
        """The place's one resource of class ``cls``; none or several is a UsageError."""
        found = [r for r in self.resources if r.cls == cls]
        if len(found) != 1:
            names = ", ".join(r.record()["path"] for r in found) or "none"
            raise UsageError(f"place {self.name} must hold one {cls} resource, it holds "
                             f"{len(found)} ({names}): labgrid-client -p {self.name} "
                             f"add-match EXPORTER/GROUP/{cls}/NAME")
        resource = found[0]
        try:  # the fields as the registered class takes them (an exporter forwards any)
            target_factory.resources[cls](None, resource.name, **resource.args)
        except TypeError as exc:
            reason = exc.args[0] if exc.args else exc
            raise UsageError(f"place {self.name}: resource {resource.record()['path']}: "
                             f"{reason}") from None
        return resource

    def record(self) -> dict[str, Any]:
        """What a session's metadata records of the place."""
        return {"place": self.name, "coordinator": self.coordinator, "holder": self.holder,
                "acquired_by_run": self.acquired_here,
                "resources": [r.record() for r in self.resources]}


@contextlib.contextmanager
def hold_place(name: str, coordinator: str | None = None, wait_s: float = 0.0,
               progress: Callable[[str], None] | None = None) -> Iterator[HeldPlace]:
    """The place ``name`` held for the block: acquired (after a wait of up to ``wait_s``
    seconds through a reservation, with a line to ``progress`` every few seconds) unless this
    user already holds it, released after the block if acquired here. A place held by someone
    else is a :class:`PlaceBusyError` naming the holder."""
    address = coordinator_address(coordinator)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    lease = _Lease.connect(name, address)
    try:
        with _quiet_labgrid():
            held = lease.acquire(wait_s, say)
    finally:
        lease.close()  # no connection idles through the run: a new one releases the place
    try:
        yield held
    finally:
        if held.acquired_here:
            _release(name, address, say)


def _release(name: str, address: str, say: Callable[[str], None]) -> None:
    """Release the place over a new connection; a coordinator gone meanwhile is a warning
    (the run's outcome stands) naming how to release it later."""
    try:
        lease = _Lease.connect(name, address)
        try:
            with _quiet_labgrid():
                lease.release()
        finally:
            lease.close()
    except UsageError as exc:
        say(f"hil: warning: place {name} not released ({exc}): labgrid-client -x {address} "
            f"-p {name} release frees it")


@contextlib.contextmanager
def _quiet_labgrid() -> Iterator[None]:
    """labgrid's client logs its failures on the root logger, which Python prints to stderr
    when nothing is configured: hil reports them itself, as one line."""
    root = logging.getLogger()
    quiet = logging.NullHandler()
    if not root.handlers:
        root.addHandler(quiet)
    try:
        yield
    finally:
        root.removeHandler(quiet)


class _Lease:
    """The coordinator calls of :func:`hold_place`, over one labgrid ClientSession."""

    @classmethod
    def connect(cls, name: str, address: str) -> _Lease:
        with _quiet_labgrid():
            try:
                session = client.start_session(address)
            except (client.Error, OSError):
                raise UsageError(f"--coordinator {address}: no labgrid coordinator answers "
                                 "there") from None
        return cls(session, name, address)

    def __init__(self, session: Any, name: str, address: str) -> None:
        from labgrid.remote.generated import labgrid_coordinator_pb2 as pb2

        self.session, self.name, self.address, self.pb2 = session, name, address, pb2
        self.me = f"{session.gethostname()}/{session.getuser()}"

    def _run(self, coroutine: Any) -> Any:
        return self.session.loop.run_until_complete(coroutine)

    def _call(self, method: str, request: Any) -> Any:
        """One coordinator RPC, then a sync (its effects are in the session's view)."""
        import grpc

        async def call() -> Any:
            response = await getattr(self.session.stub, method)(request)
            await self.session.sync_with_coordinator()
            return response

        try:
            return self._run(call())
        except grpc.aio.AioRpcError as exc:
            raise UsageError(f"place {self.name}: the coordinator at {self.address} refused "
                             f"{method}: {exc.details()}") from None

    def place(self) -> Any:
        place = self.session.places.get(self.name)
        if place is None:
            known = ", ".join(sorted(self.session.places)) or "none"
            raise UsageError(f"--place {self.name}: no such place at the coordinator "
                             f"{self.address} (its places: {known}; labgrid-client -p "
                             f"{self.name} create makes it)")
        return place

    def acquire(self, wait_s: float, say: Callable[[str], None]) -> HeldPlace:
        holder = self.place().acquired
        acquired_here = holder != self.me
        if holder and holder != self.me:
            if wait_s <= 0:
                raise PlaceBusyError(f"place {self.name} is held by {holder} (wait for it "
                                     "with --wait S)")
            self._wait(wait_s, say)
        elif not holder:
            self._call("AcquirePlace", self.pb2.AcquirePlaceRequest(placename=self.name))
        try:
            return HeldPlace(self.name, self.address, acquired_here, self.me, self._resources())
        except BaseException:
            if acquired_here:
                self.release()
            raise

    def _wait(self, wait_s: float, say: Callable[[str], None]) -> None:
        """A reservation for the place, polled until the coordinator allocates it to us
        (then the place is acquired) or ``wait_s`` passes (then the reservation is
        cancelled and the place is busy)."""
        from labgrid.remote.common import Reservation, ReservationState

        pb2 = self.pb2
        request = pb2.CreateReservationRequest(
            filters={"main": pb2.Reservation.Filter(filter={"name": self.name})}, prio=0)
        token = self._call("CreateReservation", request).reservation.token
        try:
            start = last = time.monotonic()
            say(f"place {self.name} is held by {self.place().acquired}: waiting up to "
                f"{wait_s:g} s (labgrid reservation {token})")
            while True:
                response = self._call("PollReservation", pb2.PollReservationRequest(token=token))
                state = Reservation.from_pb2(response.reservation).state
                if state is not ReservationState.waiting:
                    break
                now = time.monotonic()
                if now - start >= wait_s:
                    raise PlaceBusyError(f"place {self.name} is still held by "
                                         f"{self.place().acquired} after --wait {wait_s:g} s")
                if now - last >= PROGRESS_EVERY_S:
                    say(f"waiting for place {self.name} ({now - start:.0f} s of {wait_s:g} s), "
                        f"held by {self.place().acquired}")
                    last = now
                self._run(asyncio.sleep(POLL_S))
            self._call("AcquirePlace", pb2.AcquirePlaceRequest(placename=self.name))
            say(f"place {self.name} acquired after {time.monotonic() - start:.0f} s")
        finally:
            self._call("CancelReservation", pb2.CancelReservationRequest(token=token))

    def _resources(self) -> list[PlaceResource]:
        entries = []
        for exporter, group, cls, name in self.place().acquired_resources:
            entry = self.session.resources.get(exporter, {}).get(group, {}).get(name)
            if entry is None:
                raise UsageError(f"place {self.name}: resource {exporter}/{group}/{cls}/{name} "
                                 "is gone (its exporter disconnected?)")
            if not entry.avail:
                raise UsageError(f"place {self.name}: resource {exporter}/{group}/{cls}/{name} "
                                 "is not available")
            entries.append(PlaceResource(cls, name, dict(entry.args), exporter, group,
                                         str(entry.extra.get("proxy") or exporter)))
        return entries

    def release(self) -> None:
        self._call("ReleasePlace", self.pb2.ReleasePlaceRequest(placename=self.name))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._run(self.session.stop())
            self._run(self.session.close())
