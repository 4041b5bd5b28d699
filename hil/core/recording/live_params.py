"""The live view's Parameters capability: a run's tunables as Foxglove parameters.

:class:`LiveParameters` answers the Foxglove WebSocket server's ``getParameters`` and
``setParameters`` from a :class:`ParameterPort`: in a session's writer process, the reverse
channel to the loop process (:mod:`hil.core.recording.tune_wire`); in a test, any object with the
two methods. Specs and results are plain dicts with the fields of ``hil.core.tuning``'s
``TunableSpec`` and ``TuneResult`` (what crosses the reverse channel).

* ``getParameters`` lists every parameter (or the ones named) with the value in force now.
* ``setParameters`` hands each value to the port, which checks it (its type too: JSON has one
  number type, so ``300`` for a decimal parameter is taken as ``300.0``) and returns once the
  loop applied it at a tick boundary or refused it. The answer (sent back to the client and, by the
  SDK, published to every client subscribed to the parameter) holds the value in force
  afterwards: the new one, or the one that stays. A refusal's reason reaches the clients as a
  warning status (the SDK's ``publish_status`` goes to every client: it names the parameter
  and the client). Its id is ``tune:CLIENT:REQUEST_ID:NAME``, so a client finds the status
  of its own request.
* ``subscribeParameterUpdates``: the server keeps who subscribed to what;
  :meth:`LiveParameters.changed` pushes every change the run applied, whatever asked for it (a
  client, ``hil tune``, a script's tuner, a rebuild), to the clients subscribed to that
  parameter. The live view calls it for each message on the tuner's ``/params`` topic, so what
  subscribers are told is what the file records. A change a live client's set made is not
  pushed again: the server itself sends the set's answer to the subscribers. A value older than
  the last one sent is never pushed.
* **Read-only.** Given a reason (``read_only``), every set is refused with it and changes
  nothing: listing and subscribing still work (:mod:`hil.core.recording.live` makes a live view
  that listens beyond loopback read-only unless the run allows its clients to set).
* Who asked is ``live client N`` (the server's id of the connection), recorded with the change.
"""

from __future__ import annotations

import threading
from typing import Any, Protocol

Spec = dict[str, Any]     # TunableSpec's fields: name, value, unit, minimum, maximum, step...
Result = dict[str, Any]   # TuneResult's fields: name, accepted, value, reason, tick


class ParameterPort(Protocol):
    """Where the parameters live: their specs now, and a checked, applied change."""

    def specs(self) -> list[Spec]: ...

    def request(self, name: str, value: object, client: str) -> Result: ...


CLIENT_PREFIX = "live client "


def client_name(client_id: int) -> str:
    """Who asked, as recorded with a change."""
    return f"{CLIENT_PREFIX}{client_id}"


def status_id(client_id: int, request_id: str | None, name: str) -> str:
    """The id of the warning status of a refused set (see the module doc)."""
    return f"tune:{client_id}:{request_id or ''}:{name}"


class LiveParameters:
    """The server listener's parameter half (see the module doc)."""

    def __init__(self, port: ParameterPort, read_only: str = "") -> None:
        import foxglove

        self._foxglove = foxglove
        self.port = port
        self.read_only = read_only  # why every set is refused ("": sets go to the port)
        self.server: Any = None  # set once the server runs: statuses and pushes go through it
        self._lock = threading.Lock()
        self._subscribed: set[str] = set()  # parameters some client subscribed to
        self._sent_tick: dict[str, int] = {}  # the tick of the newest value subscribers got

    def parameter(self, name: str, value: object) -> Any:
        """A Foxglove parameter; a float stays a float on the wire (``300.0``, not ``300``)."""
        foxglove = self._foxglove
        if isinstance(value, float):
            return foxglove.Parameter(name, value=value, type=foxglove.ParameterType.Float64)
        return foxglove.Parameter(name, value=value)  # type: ignore[arg-type]

    def get(self, names: list[str]) -> list[Any]:
        """Every parameter, or those of ``names``, with its value now."""
        wanted = set(names)
        return [self.parameter(spec["name"], spec["value"]) for spec in self.port.specs()
                if not wanted or spec["name"] in wanted]

    def set(self, client_id: int, parameters: list[Any], request_id: str | None) -> list[Any]:
        """Apply each parameter through the port; the values in force afterwards (which the
        server also sends to the parameter's subscribers)."""
        if self.read_only:
            return self._refuse_all(client_id, parameters, request_id)
        answers = []
        for parameter in parameters:
            name, value = parameter.name, parameter.get_value()
            result = self.port.request(name, value, client_name(client_id))
            if not result["accepted"]:
                self.refused(client_id, request_id, name, value, result["reason"])
            elif result["tick"] is not None:
                self._note_sent(name, int(result["tick"]))
            if result["value"] is not None:  # None: an unknown name, or no answer (the status)
                answers.append(self.parameter(name, result["value"]))
        return answers

    def _refuse_all(self, client_id: int, parameters: list[Any], request_id: str | None
                    ) -> list[Any]:
        """A read-only live view's answer to a set: each refused, the values that stay."""
        for parameter in parameters:
            self.refused(client_id, request_id, parameter.name, parameter.get_value(),
                         self.read_only)
        return self.get([parameter.name for parameter in parameters]) if parameters else []

    def subscribed(self, names: list[str]) -> None:
        """The server's notice that some client subscribed to ``names`` (the first one)."""
        with self._lock:
            self._subscribed.update(names)

    def unsubscribed(self, names: list[str]) -> None:
        """The server's notice that the last subscriber of ``names`` left."""
        with self._lock:
            self._subscribed.difference_update(names)

    def changed(self, name: str, value: object, tick: int, client: str) -> None:
        """The run applied ``name = value`` at ``tick``, asked for by ``client``: pushed to the
        parameter's subscribers, unless nobody subscribed or they have it (a live client's set:
        the server sends them its answer) or a newer value already."""
        if client.startswith(CLIENT_PREFIX):
            return
        with self._lock:
            if self.server is None or name not in self._subscribed or \
                    self._sent_tick.get(name, -1) >= tick:
                return
            self._sent_tick[name] = tick
        self.server.publish_parameter_values([self.parameter(name, value)])

    def _note_sent(self, name: str, tick: int) -> None:
        with self._lock:
            self._sent_tick[name] = max(tick, self._sent_tick.get(name, -1))

    def refused(self, client_id: int, request_id: str | None, name: str, value: object,
                reason: str) -> None:
        if self.server is None:
            return
        self.server.publish_status(
            f"{name} = {value!r} refused ({client_name(client_id)}): {reason}",
            self._foxglove.StatusLevel.Warning, id=status_id(client_id, request_id, name))
