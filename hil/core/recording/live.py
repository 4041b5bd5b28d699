"""Live view: a session's topics served over the Foxglove WebSocket protocol, beside the file.

:class:`LiveSink` runs where messages are already off the loop: inside the session's writer
process (:mod:`hil.core.recording.writer`), in ``hil replay`` and in ``hil emulate --live``. It
serves every topic under the same name and JSON Schema as the file (CDR topics in the file are
served as JSON with their JSON Schema), through the Foxglove SDK's WebSocket server, which
Foxglove and PlotJuggler connect to.

* **Flattening.** For every top-level array of numbers ``x`` (the loop timing's
  ``lateness_us`` and the phase times, the MPC prediction, the EEC's plan power) the live message
  also carries ``x_min``, ``x_max`` and ``x_mean``: scalars that a plot draws over time, where
  the array itself would be drawn as one series per message. The arrays stay (index-mode plots).
* **Decimation** by log time, per topic: at most :data:`DEFAULT_RATE_HZ` messages per second of
  session time unless a rate is given (``{topic: hz}``, 0 = every message). ``/events`` is
  never decimated.
* **Slow clients.** The SDK queues at most ``backlog`` messages per client and drops the oldest
  when a client falls behind (it does not count them; it logs "outbox for client ... full",
  at most every 30 s, which :class:`LiveSink` counts as ``client_queue_full``). Nothing here
  waits for a client; with no subscriber a message costs one rate check.
* **Parameters.** Given a parameter port, the server also offers Foxglove's Parameters
  capability: a run's tunables, read and set from the Parameters panel or ``hil tune``, and
  every change the run applies pushed to the clients subscribed to it
  (:mod:`hil.core.recording.live_params`).
* **Who may set them.** A live view that listens on loopback can only have clients on this
  machine: they may set parameters. One that listens beyond loopback (``0.0.0.0``, a LAN
  address) is read-only, for every client, unless the run allows remote tuning
  (``remote_tuning``, ``--allow-remote-tuning``): the SDK tells its listener which connection
  asked (an id), never from which address, so the address the view listens on is what bounds
  who can ask (:func:`read_only_reason`). :attr:`LiveSink.exposure` is the one-line warning
  of a view that listens beyond loopback.
"""

from __future__ import annotations

import json
import logging
import math
import re
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, cast

from hil.core.exposure import beyond_loopback, exposure
from hil.core.notice import warn
from hil.core.recording.live_params import LiveParameters, ParameterPort
from hil.errors import UsageError

DEFAULT_PORT = 8765
DEFAULT_RATE_HZ = 100.0
NEVER_DECIMATED = ("/events",)
DEFAULT_BACKLOG = 1024
FLAT_SUFFIXES = ("min", "max", "mean")


def parse_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` of ``--live`` (host 127.0.0.1 unless given; IPv6 as ``[::1]:PORT``)."""
    host, sep, port_text = text.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    try:
        port = int(port_text)
    except ValueError:
        raise UsageError(f"--live: expected [HOST:]PORT, got {text!r}") from None
    if not 0 <= port <= 65535 or (sep and not host):
        raise UsageError(f"--live: expected [HOST:]PORT with PORT 0-65535, got {text!r}")
    return host, port


def check_bindable(host: str, port: int) -> None:
    """Fail with one line now, rather than serve nothing later, when ``host:port`` is taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise UsageError(f"--live: cannot serve on {host}:{port}: "
                             f"{exc.strerror or exc}") from None


def read_only_reason(host: str, remote_tuning: bool) -> str:
    """Why the parameters of a live view listening on ``host`` are read-only for its clients
    ("": they are not): it listens beyond loopback, and the run did not allow remote tuning."""
    if remote_tuning or not beyond_loopback(host):
        return ""
    return (f"this live view listens beyond loopback ({host}), where hil cannot tell a client "
            "on this machine from one on another: its parameters are read-only unless the run "
            "is started with --allow-remote-tuning")


def live_exposure(url: str, host: str, *, parameters: bool = False,
                  remote_tuning: bool = False) -> str | None:
    """The one-line warning of a live view at ``url`` listening on ``host`` beyond loopback
    (None on loopback): who may watch it, and (``parameters``) set its parameters."""
    if not parameters:
        reach = "watch it"
    elif remote_tuning:
        reach = "watch it and set the run's parameters (--allow-remote-tuning)"
    else:
        reach = "watch it, not set the run's parameters (--allow-remote-tuning would let them)"
    return exposure(f"the live view on {url}", host, reach)


def announce(url: str, warning: str | None = None) -> None:
    """The live view's URL on stderr, and its warning (:func:`live_exposure`) if any."""
    print(f"hil: live view on {url} (Foxglove: Open connection > Foxglove WebSocket)",
          file=sys.stderr, flush=True)
    if warning is not None:
        warn(warning)


def parse_rate(text: str) -> tuple[str, float]:
    """``/TOPIC=HZ`` of ``--live-rate`` (0: every message)."""
    topic, sep, hz_text = text.partition("=")
    try:
        hz = float(hz_text)
    except ValueError:
        hz = -1.0
    if not sep or not topic.startswith("/") or not (hz >= 0 and math.isfinite(hz)):
        raise UsageError(f"--live-rate: expected /TOPIC=HZ with HZ >= 0, got {text!r}")
    return topic, hz


def live_schema(schema: dict[str, Any]) -> dict[str, Any]:
    """The file's JSON Schema plus the flattened ``x_min``/``x_max``/``x_mean`` properties."""
    properties = dict(schema.get("properties", {}))
    for name, prop in list(properties.items()):
        if isinstance(prop, dict) and prop.get("type") == "array" and \
                isinstance(prop.get("items"), dict) and \
                prop["items"].get("type") in ("number", "integer"):
            for suffix in FLAT_SUFFIXES:
                properties[f"{name}_{suffix}"] = {
                    "type": "number", "description": f"{suffix} of {name} (live view only)"}
    return {**schema, "properties": properties}


def flatten(message: Any) -> Any:
    """``message`` with numpy values as lists and number arrays summarised (see module doc)."""
    if not isinstance(message, dict):
        return message
    out: dict[str, Any] = {}
    for name, value in message.items():
        if hasattr(value, "tolist"):
            value = value.tolist()
        out[name] = value
        if isinstance(value, list) and value and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            out[f"{name}_min"] = min(value)
            out[f"{name}_max"] = max(value)
            out[f"{name}_mean"] = sum(value) / len(value)
    return out


@dataclass
class _Topic:
    channel: Any
    period_ns: int
    next_ns: int = -1
    sent: int = 0
    decimated: int = 0


@dataclass
class LiveStats:
    """What the live view did: messages sent and decimated per topic, slow-client notices."""

    sent: dict[str, int] = field(default_factory=dict)
    decimated: dict[str, int] = field(default_factory=dict)
    client_queue_full: int = 0
    failed: int = 0
    client_errors: dict[str, int] = field(default_factory=dict)  # reason -> count


class _SdkLog(logging.Handler):
    """The SDK's log (forwarded from Rust): counts its throttled notices that a client's
    outbox was full and dropped messages, and its warnings and errors per reason (the text
    without addresses and numbers); prints the first of each reason on stderr, once."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.queue_full = 0
        self.errors: dict[str, int] = {}

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if "outbox for client" in text:
            self.queue_full += 1
        elif record.levelno >= logging.WARNING:
            reason = _reason(text)
            self.errors[reason] = self.errors.get(reason, 0) + 1
            if self.errors[reason] == 1:
                print(f"hil: live view: {text} (more like it are only counted: the session's "
                      "'live' metadata)", file=sys.stderr, flush=True)


def _reason(text: str) -> str:
    """A log line without what differs between clients: addresses, ports, ids, numbers."""
    return re.sub(r"\d+", "N", re.sub(r"\[?[0-9a-fA-F:.]+\]?:\d+", "ADDRESS", text))[:120]


def _sdk_log() -> _SdkLog:
    """The one handler of the SDK's log in this process (installed before its first sink)."""
    global _SDK_LOG
    if _SDK_LOG is None:
        import foxglove

        _SDK_LOG = _SdkLog()
        logger = logging.getLogger("foxglove")
        logger.addHandler(_SDK_LOG)
        logger.setLevel(logging.INFO)
        logger.propagate = False  # INFO chatter (connections) stays off the user's terminal
        foxglove.set_log_level("INFO")
    return _SDK_LOG


_SDK_LOG: _SdkLog | None = None


class _Subscriptions:
    """The SDK's server listener: notes that some client subscribed to something, and
    answers parameter requests and follows parameter subscriptions when the server offers
    parameters (the SDK calls every method of its ``ServerListener`` for its capabilities: a
    missing one is an error in its log)."""

    def __init__(self, parameters: LiveParameters | None = None) -> None:
        self.first = threading.Event()
        self.parameters = parameters

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.first.set()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        pass

    def on_get_parameters(self, client: Any, param_names: list[str],
                          request_id: str | None = None) -> list[Any]:
        return self.parameters.get(param_names) if self.parameters is not None else []

    def on_set_parameters(self, client: Any, parameters: list[Any],
                          request_id: str | None = None) -> list[Any]:
        if self.parameters is None:
            return []
        return self.parameters.set(int(client.id), parameters, request_id)

    def on_parameters_subscribe(self, param_names: list[str]) -> None:
        if self.parameters is not None:
            self.parameters.subscribed(param_names)

    def on_parameters_unsubscribe(self, param_names: list[str]) -> None:
        if self.parameters is not None:
            self.parameters.unsubscribed(param_names)


class LiveSink:
    """A Foxglove WebSocket server for one session's topics (its own SDK context)."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *,
                 rates: dict[str, float] | None = None, backlog: int = DEFAULT_BACKLOG,
                 name: str = "hil", parameters: ParameterPort | None = None,
                 remote_tuning: bool = False) -> None:
        import foxglove
        from foxglove.websocket import Capability

        self._foxglove = foxglove
        self.rates = dict(rates or {})
        self._context = foxglove.Context()
        self._log = _sdk_log()
        self._queue_full_before = self._log.queue_full
        self._errors_before = dict(self._log.errors)
        self.parameters = LiveParameters(parameters, read_only_reason(host, remote_tuning)) \
            if parameters is not None else None
        self._changes_key: Any = None  # the key of the tuner's /params topic, once added
        self._subscriptions = _Subscriptions(self.parameters)
        self.server = foxglove.start_server(
            name=name, host=host, port=port, context=self._context,
            message_backlog_size=backlog, server_listener=cast(Any, self._subscriptions),
            capabilities=[Capability.Parameters] if parameters is not None else None)
        if self.parameters is not None:
            self.parameters.server = self.server
        self.host = host
        self.port = int(self.server.port)
        self._by_key: dict[Any, _Topic] = {}
        self._closed = False
        self._failed = 0
        #: the warning of a view that listens beyond loopback (None on loopback)
        self.exposure = live_exposure(self.url, host, parameters=parameters is not None,
                                      remote_tuning=remote_tuning)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def wait_for_subscriber(self, timeout_s: float, grace_s: float = 0.3) -> bool:
        """Wait until a client subscribes (then ``grace_s`` more, for the rest of its
        subscriptions); False after ``timeout_s`` without one."""
        if not self._subscriptions.first.wait(timeout_s):
            return False
        time.sleep(grace_s)
        return True

    def add_topic(self, key: Any, name: str, schema: dict[str, Any]) -> None:
        """Advertise ``name`` with (the live form of) its JSON Schema; ``key`` logs to it."""
        if self.parameters is not None:
            from hil.core.tuning import PARAMS_TOPIC

            if name == PARAMS_TOPIC:  # each change the run applied: pushed to subscribers
                self._changes_key = key
        try:
            data = json.dumps(live_schema(schema)).encode()
            channel = self._foxglove.Channel(
                name, message_encoding="json", context=self._context,
                schema=self._foxglove.Schema(name=str(schema.get("title", name)),
                                             encoding="jsonschema", data=data))
        except Exception:  # a topic the live view cannot serve never costs the recording
            self._failed += 1
            return
        hz = 0.0 if name in NEVER_DECIMATED else self.rates.get(name, DEFAULT_RATE_HZ)
        self._by_key[key] = _Topic(channel, round(1e9 / hz) if hz > 0 else 0)

    def log(self, key: Any, t_ns: int, message: Any) -> None:
        """Serve ``message`` of topic ``key`` unless decimated away or nobody subscribed."""
        if key == self._changes_key and not self._closed:
            self._push_change(message)
        topic = self._by_key.get(key)
        if topic is None or self._closed:
            return
        if topic.period_ns:
            if t_ns < topic.next_ns:
                topic.decimated += 1
                return
            # the next slot on the topic's grid; after a gap, a period from now (no burst)
            topic.next_ns += topic.period_ns
            if topic.next_ns <= t_ns:
                topic.next_ns = t_ns + topic.period_ns
        if not topic.channel.has_sinks():
            return
        try:
            payload = json.dumps(flatten(message), separators=(",", ":"), default=_plain)
            topic.channel.log(payload.encode(), log_time=t_ns)
        except Exception:  # a message the live view cannot serve never costs the recording
            self._failed += 1
            return
        topic.sent += 1

    def _push_change(self, change: Any) -> None:
        """A ``/params`` message (a change the run applied) to the parameter's subscribers."""
        assert self.parameters is not None
        try:
            self.parameters.changed(change["parameter"], change["new"], int(change["tick"]),
                                    str(change.get("client", "")))
        except Exception:  # a change the live view cannot push never costs the recording
            self._failed += 1

    def stats(self) -> LiveStats:
        sent = {t.channel.topic(): t.sent for t in self._by_key.values() if t.sent}
        decimated = {t.channel.topic(): t.decimated for t in self._by_key.values() if t.decimated}
        errors = {reason: count - self._errors_before.get(reason, 0)
                  for reason, count in self._log.errors.items()
                  if count > self._errors_before.get(reason, 0)}
        return LiveStats(sent, decimated, self._log.queue_full - self._queue_full_before,
                         self._failed, errors)

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop serving (clients see the connection close). The SDK's stop waits for every
        client to take its close frame, which a stalled client never does: this waits at most
        ``timeout_s`` and leaves the rest to the process's exit."""
        if self._closed:
            return
        self._closed = True
        stopper = threading.Thread(target=self.server.stop, name="live-stop", daemon=True)
        stopper.start()
        stopper.join(timeout_s)


def _plain(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot serve a {type(value).__name__} as JSON")
