"""The bench's safety layer: the only way to a relay. Controllers get a :class:`SafeBench`.

* Dwell: a relay changes at most once per ``dwell_s`` (its minimum on/off time). A request
  inside the dwell is deferred: it takes effect when the dwell ends unless a later request
  cancels it (asking for the current state cancels). The first deferral of a dwell window is
  recorded as an event, later ones are counted.
* Safe level: on stop, on error and on link loss every relay is driven to its ``safe`` level,
  whatever its dwell (a safety action is not chatter).
* Watchdog (a :class:`~hil.contracts.LinkWatchdog`): ``watchdog_polls`` failed polls in a
  row declare the link lost (event, safe level); the link is then retried every
  ``reconnect_interval_s``; on reconnection every relay is driven to its safe level first and
  the controllers start again from there.
* After the run (:meth:`SafeBench.confirm_safe`): unless the last safe state read every
  relay back at its safe level, the bench is reached again (a lost link's rules: up to
  ``watchdog_polls`` tries, ``reconnect_interval_s`` apart), its relays driven to their safe
  levels and read back; when they still cannot be confirmed, event
  ``bench.safe_state_unconfirmed`` (level error) says which may still be on.
* Another master: a relay found switched with no write of this run since it was last read is
  another master's doing (event ``relay.foreign_change``), unless a write of this run that was
  given up on (no answer) asked for that state within :data:`LATE_WRITE_S`: a slow peer
  carried it out late (event ``relay.late_write``).

Time is the loop clock's (a :class:`~hil.contracts.TimeSource`): dwell and reconnection
pacing run in simulated time in lockstep and in wall time in real time.

:class:`SafeBench` is a :class:`~hil.contracts.Device`: ``open()`` probes every unit and
drives the relays to their safe levels, ``close()`` does the safe state and releases the link.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from hil.contracts import Device, EventSink, LinkWatchdog, TimeSource, no_event
from hil.drivers.bench.modbus import DeviceError, LinkError, ModbusBenchDriver, RelayStuckError
from hil.drivers.errors import DriverError

#: how long (the run's clock) a relay write given up on (no answer) may still be carried out by
#: a slow peer: a Modbus server that serves a connection's requests in turn carries out the
#: ones it holds after the master gave up on them
LATE_WRITE_S = 10.0


class DwellGuard:
    """Minimum time between two changes of each relay. Pure: time is passed in (seconds)."""

    def __init__(self, dwell_s: Mapping[str, float], state: Mapping[str, bool]) -> None:
        self.dwell_s = dict(dwell_s)
        self.state = dict(state)
        self.last_change_s = {name: -math.inf for name in dwell_s}
        self.pending: dict[str, bool] = {}

    def ready_at(self, name: str) -> float:
        return self.last_change_s[name] + self.dwell_s[name]

    def request(self, name: str, on: bool, t_s: float) -> str:
        """'unchanged' (already so; cancels a pending change), 'apply' or 'deferred'."""
        if on == self.state[name]:
            self.pending.pop(name, None)
            return "unchanged"
        if t_s >= self.ready_at(name):
            self.pending.pop(name, None)
            return "apply"
        self.pending[name] = on
        return "deferred"

    def due(self, t_s: float) -> dict[str, bool]:
        """Deferred changes whose dwell is over (they stay pending until ``applied``)."""
        return {n: v for n, v in self.pending.items() if t_s >= self.ready_at(n)}

    def applied(self, name: str, on: bool, t_s: float) -> None:
        """The relay is now ``on`` (a verified write or a read-back); restart its dwell if it
        changed."""
        self.pending.pop(name, None)
        if self.state[name] != on:
            self.state[name] = on
            self.last_change_s[name] = t_s


@dataclass
class SafetyStats:
    polls: int = 0
    failed_polls: int = 0
    link_losses: int = 0
    reconnections: int = 0
    switches: int = 0
    deferred_requests: int = 0
    refused_requests: int = 0
    failed_writes: int = 0
    stuck_relays: int = 0  # verified writes the relay did not follow
    foreign_changes: int = 0  # relays found switched with no write of ours since last read
    late_writes: int = 0  # relays found switched by a write of ours given up on earlier
    per_relay_switches: dict[str, int] = field(default_factory=dict)


class SafeBench(Device):
    """The bench as tasks and controllers see it: readings, and relays through the guard.

    ``read_power()`` / ``read_levels()`` return None on a failed poll (the watchdog counts
    it). ``set_relays({name: on})`` returns what happened to each request. ``service()``
    (once per sample) applies deferred changes and retries a lost link. ``safe_state()``
    drives every relay to its safe level; register the bench as a loop component.
    """

    def __init__(self, driver: ModbusBenchDriver, clock: TimeSource, *,
                 on_event: EventSink | None = None, watchdog_polls: int = 5,
                 reconnect_interval_s: float = 0.5) -> None:
        self._driver = driver
        self._clock = clock
        self._event = on_event or no_event
        relays = driver.map.relays
        self.relay_names = list(relays)
        self.safe_levels = {name: r.safe for name, r in relays.items()}
        self._guard = DwellGuard({n: r.dwell_s for n, r in relays.items()}, self.safe_levels)
        self.watchdog = LinkWatchdog(watchdog_polls, "failed polls")
        self.reconnect_interval_s = reconnect_interval_s
        self._next_reconnect_s = -math.inf
        self._connections_seen = 0
        self._retries_reported = (0, 0)  # link retries, frames passed over
        self._next_retry_report_s = -math.inf
        self._deferral_reported: set[str] = set()
        self.stats = SafetyStats(per_relay_switches={n: 0 for n in relays})
        # each relay as last read with no write of ours since (None: unknown), to tell a
        # relay switched by someone else (another Modbus master) from one that did not follow
        self._seen: dict[str, bool | None] = dict.fromkeys(relays)
        # the states asked by writes given up on (no answer), by relay: when (s)
        self._given_up: dict[str, dict[bool, float]] = {name: {} for name in relays}
        #: every relay read back at its safe level by the last safe state, no write since
        self.confirmed_safe = False
        self._read_back: dict[str, bool] | None = None  # the last safe state's read, if any

    # -- state -----------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return self._driver.link.spec.url

    @property
    def retries(self) -> int:
        """Modbus requests tried again so far (timeouts, dropped or garbled answers)."""
        return self._driver.link.retries

    @property
    def requests(self) -> int:
        """Modbus requests asked so far (however many tries each took)."""
        return self._driver.link.requests

    def relays(self) -> dict[str, bool]:
        """Last known actual relay states (verified writes and read-backs)."""
        return dict(self._guard.state)

    def commanded(self) -> dict[str, bool]:
        """What the relays are or are about to be: actual state with deferred changes laid
        over it."""
        return {**self._guard.state, **self._guard.pending}

    def pending(self) -> dict[str, bool]:
        return dict(self._guard.pending)

    def _now_s(self, t_ns: int | None) -> float:
        return (self._clock.time_ns() if t_ns is None else t_ns) / 1e9

    def _emit(self, kind: str, message: str, level: str = "info", **data: Any) -> None:
        self._event(kind, message, level=level, source="bench", **data)

    # -- opening ---------------------------------------------------------------------------
    def open(self) -> None:
        """Check every unit answers, then drive every relay to its safe level (verified)."""
        self._driver.probe()
        self._connections_seen = self._driver.link.connections
        self._drive_safe(self._now_s(None), reason="open")
        self._emit("bench.open", f"bench at {self.url}: relays at their safe levels",
                   url=self.url)

    # -- polling ---------------------------------------------------------------------------
    def read_power(self) -> dict[str, float] | None:
        return self._poll(self._driver.read_power)

    def read_levels(self) -> dict[str, float] | None:
        return self._poll(self._driver.read_levels)

    def _poll(self, read: Callable[[], dict[str, float]]) -> dict[str, float] | None:
        if self.watchdog.lost:
            return None
        self.stats.polls += 1
        try:
            values = read()
        except LinkError as exc:
            self.stats.failed_polls += 1
            if self.watchdog.failure():
                self._link_lost(str(exc))
            return None
        self.watchdog.success()
        self._check_reconnected()
        self._report_retries()
        return values

    def _report_retries(self) -> None:
        """A request that needed more than one try is not lost, but it is news, and so is a
        frame passed over (an answer that came late, another's answer, noise): one
        ``link.retried`` event per second at most, with the counts since the last one
        (``retries``, ``passed_over``)."""
        link = self._driver.link
        counts = (link.retries, link.discarded)
        if counts == self._retries_reported:
            return
        t_s = self._now_s(None)
        if t_s < self._next_retry_report_s:
            return
        retries, passed_over = (now - before for now, before in
                                zip(counts, self._retries_reported, strict=True))
        message = (f"{retries} Modbus request(s) answered only on a later attempt or not at "
                   "all")
        if passed_over:
            message += (f"; {passed_over} frame(s) passed over (late answers, others' answers, "
                        "noise)")
        self._emit("link.retried", message, level="warning", retries=retries,
                   passed_over=passed_over)
        self._retries_reported = counts
        self._next_retry_report_s = t_s + 1.0

    def lose_link(self, reason: str) -> None:
        """The link is lost now, whatever the watchdog counted so far (lockstep over the wire:
        the emulator is gone); as a loss the watchdog declares."""
        if self.watchdog.lost:
            return
        self.watchdog.lost = True
        self.watchdog.losses += 1
        self._link_lost(reason, f"bench link lost: {reason}")

    def _link_lost(self, reason: str, message: str = "") -> None:
        self.stats.link_losses += 1
        t_s = self._now_s(None)
        self._emit("link.lost", message or f"bench link lost after {self.watchdog.run} failed "
                   f"polls: {reason}", level="error", url=self.url, reason=reason)
        self._guard.pending.clear()
        self._seen = dict.fromkeys(self._seen)
        with contextlib.suppress(DriverError):  # best effort: the relay module may still hear us
            self._drive_safe(t_s, reason="link lost")
        self._driver.link.close()
        self._next_reconnect_s = t_s + self.reconnect_interval_s

    def _check_reconnected(self) -> None:
        """The link reconnected inside a request (the device may have restarted): re-read."""
        connections = self._driver.link.connections
        if connections != self._connections_seen:
            self._connections_seen = connections
            self._seen = dict.fromkeys(self._seen)  # the device may have restarted
            self.readback()

    def readback(self, t_ns: int | None = None) -> dict[str, bool] | None:
        """Read every relay; adopt what the module says and record any disagreement. A relay
        that changed since it was last read, with no write of this bench in between, was
        switched by someone else: event ``relay.foreign_change``, ``stats.foreign_changes``."""
        try:
            actual = self._driver.read_relays()
        except LinkError:
            return None
        t_s = self._now_s(t_ns)
        for name, on in actual.items():
            seen = self._seen[name]
            if seen is not None and seen != on:
                given_up_at = self._given_up[name].pop(on, None)
                if given_up_at is not None and t_s - given_up_at <= LATE_WRITE_S:
                    self.stats.late_writes += 1
                    self._emit("relay.late_write", f"relay {name} switched "
                               f"{'on' if on else 'off'} by a write of this run given up on "
                               f"at t={given_up_at:.2f} s: the bench carried it out late",
                               level="warning", relay=name, actual=on)
                else:
                    self.stats.foreign_changes += 1
                    self._emit("relay.foreign_change", f"relay {name} switched "
                               f"{'on' if on else 'off'} with no write of this run: another "
                               "master on the bench?", level="error", relay=name, actual=on)
            self._seen[name] = on
        for name, on in actual.items():
            if self._guard.state[name] != on:
                self._emit("relay.mismatch", f"relay {name} reads {'on' if on else 'off'}, "
                           f"expected {'on' if self._guard.state[name] else 'off'}",
                           level="warning", relay=name, actual=on)
                self._guard.applied(name, on, t_s)
        return actual

    # -- relays ----------------------------------------------------------------------------
    def set_relays(self, changes: Mapping[str, bool], t_ns: int | None = None
                   ) -> dict[str, str]:
        """Ask for relay states; each answer is 'unchanged', 'switched', 'deferred',
        'refused' (link lost), 'failed' (the write failed) or 'stuck' (written, but the
        read-back says the relay did not follow: an event ``relay.stuck``)."""
        t_s = self._now_s(t_ns)
        out: dict[str, str] = {}
        for name, on in changes.items():
            if name not in self._guard.state:
                raise DriverError(f"unknown relay {name!r} (relays: {', '.join(self.relay_names)})")
            on = bool(on)
            if self.watchdog.lost:
                self.stats.refused_requests += 1
                out[name] = "refused"
                continue
            decision = self._guard.request(name, on, t_s)
            if decision == "apply":
                out[name] = self._switch(name, on, t_s)
            elif decision == "deferred":
                self._deferred(name, on, t_s)
                out[name] = "deferred"
            else:
                out[name] = "unchanged"
        return out

    def _deferred(self, name: str, on: bool, t_s: float) -> None:
        self.stats.deferred_requests += 1
        if name in self._deferral_reported:
            return
        self._deferral_reported.add(name)
        ready = self._guard.ready_at(name)
        self._emit("relay.deferred", f"relay {name} {'on' if on else 'off'} deferred "
                   f"{ready - t_s:.2f} s: inside its {self._guard.dwell_s[name]:g} s dwell",
                   level="warning", relay=name, requested=on, ready_at_s=ready)

    def _write(self, name: str, on: bool, t_s: float) -> None:
        """The relay's coil written; a write left unanswered is remembered (it may still be
        carried out)."""
        self.confirmed_safe = False
        try:
            self._driver.link.write_coil(self._driver.map.units["relays"],
                                         self._driver.map.relays[name].coil, on)
        except LinkError:
            self._given_up[name][on] = t_s
            raise

    def _switch(self, name: str, on: bool, t_s: float) -> str:
        try:
            self._write(name, on, t_s)
            self._driver.verify_relay(name, on)
        except RelayStuckError as exc:  # the link works: the relay does not
            self.stats.stuck_relays += 1
            self._emit("relay.stuck", str(exc), level="error", relay=name, requested=on,
                       actual=exc.actual)
            self._guard.applied(name, exc.actual, t_s)
            self._seen[name] = exc.actual
            return "stuck"
        except (LinkError, DeviceError) as exc:
            self.stats.failed_writes += 1
            self._emit("relay.write_failed", f"relay {name} {'on' if on else 'off'}: {exc}",
                       level="error", relay=name, requested=on)
            self._seen[name] = None
            if isinstance(exc, LinkError) and self.watchdog.failure():
                self._link_lost(str(exc))
            return "failed"
        self._guard.applied(name, on, t_s)
        self._seen[name] = on
        self._deferral_reported.discard(name)
        self.stats.switches += 1
        self.stats.per_relay_switches[name] += 1
        return "switched"

    def service(self, t_ns: int | None = None) -> None:
        """Once per sample: apply deferred changes that are due; retry a lost link."""
        t_s = self._now_s(t_ns)
        if self.watchdog.lost:
            if t_s >= self._next_reconnect_s:
                self._try_reconnect(t_s)
            return
        for name, on in self._guard.due(t_s).items():
            self._switch(name, on, t_s)

    def _try_reconnect(self, t_s: float) -> None:
        self._next_reconnect_s = t_s + self.reconnect_interval_s
        link = self._driver.link
        link.close()
        if not link.connect():
            return
        try:
            self._drive_safe(t_s, reason="link restored")
        except DriverError:
            link.close()
            return
        self._connections_seen = link.connections
        self.watchdog.success()
        self.stats.reconnections += 1
        self._emit("link.restored", f"bench link restored ({self.url}); relays at their safe "
                   "levels", url=self.url)

    def _drive_safe(self, t_s: float, reason: str) -> None:
        """Every relay to its safe level regardless of dwell, then verify all of them."""
        self._seen = dict.fromkeys(self._seen)
        self._read_back = None
        for name, level in self.safe_levels.items():
            self._write(name, level, t_s)
        actual = self._read_back = self._driver.read_relays()
        wrong = [n for n, level in self.safe_levels.items() if actual[n] != level]
        if wrong:
            raise LinkError(f"relays {wrong} did not reach their safe level ({reason})")
        for name, on in actual.items():
            self._guard.applied(name, on, t_s)
        self._seen = dict(actual)
        self._guard.pending.clear()
        self.confirmed_safe = True

    def safe_state(self) -> None:
        """Every relay to its safe level (ignores dwell). Idempotent; raises when it cannot."""
        if self.watchdog.lost:  # one more try: the bench may be back
            self._driver.link.close()
            if not self._driver.link.connect():
                self._emit("safe_state.unreachable", "relays not driven to their safe level: "
                           "the bench link is lost", level="error", url=self.url)
                return
        self._drive_safe(self._now_s(None), reason="safe state")
        self._emit("bench.safe", "relays at their safe levels")

    def confirm_safe(self) -> str | None:
        """After the run: None when every relay is confirmed at its safe level. The last safe
        state's read-back confirms them; else (a lost link, a failed safe state) the bench is
        reached again, as a lost link is: up to ``watchdog_polls`` tries, ``reconnect_interval_s``
        apart (wall clock), its relays driven to their safe levels and read back. Still not
        confirmed: event ``bench.safe_state_unconfirmed`` (level error; data: ``on`` and ``off``,
        the relays read away from their safe level, ``unknown``, those that could not be read)
        and its message, one line naming the relays that may still be on."""
        if self.confirmed_safe:
            return None
        link, tries = self._driver.link, self.watchdog.limit
        retries = link.retries  # the questions after the run are no retries of its polls
        try:
            for attempt in range(tries):
                if attempt:
                    time.sleep(self.reconnect_interval_s)
                link.close()
                if not link.connect():
                    continue
                try:
                    self._drive_safe(self._now_s(None), reason="after the run")
                except DriverError:
                    continue
                self._emit("bench.safe", "relays at their safe levels, read back after the "
                           "run")
                return None
        finally:
            link.retries = retries
        read = self._read_back
        away = [n for n, level in self.safe_levels.items() if read is not None
                and read[n] != level]
        unknown = [] if read is not None else list(self.safe_levels)
        still = self._may_still_be(away + unknown)
        why = (f"read back from {self.url} after the run, not at their safe level"
               if read is not None else f"the bench at {self.url} did not answer after the "
               f"run ({tries} tries, {self.reconnect_interval_s:g} s apart)")
        message = f"{still}: {why}"
        self._emit("bench.safe_state_unconfirmed", message, level="error", url=self.url,
                   on=[n for n in away if not self.safe_levels[n]],
                   off=[n for n in away if self.safe_levels[n]], unknown=unknown)
        return message

    def _may_still_be(self, names: list[str]) -> str:
        """``relays P1, P2 may still be on`` (``off`` for those whose safe level is on)."""
        parts = []
        for state, safe in (("on", False), ("off", True)):
            chosen = [n for n in names if self.safe_levels[n] == safe]
            if chosen:
                word = "relay" if len(chosen) == 1 else "relays"
                parts.append(f"{word} {', '.join(chosen)} may still be {state}")
        return "; ".join(parts)

    def disconnect(self) -> None:
        """Close the link (the driver's socket or serial port)."""
        self._driver.close()
