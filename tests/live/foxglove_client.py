"""A minimal Foxglove WebSocket protocol (v1) client for the tests, on the `websockets` package.

The foxglove-sdk server accepts the subprotocol ``foxglove.sdk.v1`` only (its handshake refuses
a client that offers ``foxglove.websocket.v1`` alone, HTTP 400); the messages are those of the
Foxglove WebSocket protocol spec, v1. The client offers both names, as the Foxglove app does.

Text frames are JSON (``serverInfo``, ``advertise``, ``status``...); the client subscribes with
a ``subscribe`` JSON message and receives binary ``messageData`` frames: opcode 1, a uint32
subscription id, a uint64 log time (little endian), then the payload (JSON here).

A subscription the server refuses as ``Unknown channel ID: N`` is sent again, once: the foxglove-sdk
server sends a channel's ``advertise`` to a connected client before it adds the channel to that
client's table (``ConnectedClient::advertise_channels``), so a client that subscribes at once to
a channel advertised while it is connected can be answered in between, on a loaded machine.
:func:`stalled_client`, which reads nothing once subscribed, first has each subscription
confirmed: it sends each twice, and the server answers the second "already subscribed" once
it holds one.

Parameters (capability ``parameters``): ``getParameters`` and ``setParameters`` (with an id, the
answer is a ``parameterValues`` with that id), ``subscribeParameterUpdates`` (later changes come
as ``parameterValues`` without an id), and ``status`` messages (level 1: warning).
"""

from __future__ import annotations

import base64
import json
import os
import re
import socket
import struct
import time
from collections.abc import Callable
from typing import Any

from websockets.sync.client import ClientConnection, connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 1
#: the server's answers to a subscription it refuses, and to one it holds already
UNKNOWN_CHANNEL = re.compile(r"Unknown channel ID: (\d+)")
ALREADY_SUBSCRIBED = re.compile(r"Client is already subscribed to channel: (\d+)")
_HEADER = struct.Struct("<BIQ")


def connect_when_up(url: str, timeout_s: float = 10.0,
                    alive: Callable[[], int | None] = lambda: None) -> ClientConnection:
    """Connect with the Foxglove subprotocol, retrying until the server listens (or the
    server's process has exited: ``alive()`` returns its exit status, like ``Popen.poll``)."""
    deadline = time.monotonic() + timeout_s
    while True:
        status = alive()
        if status is not None:
            raise ConnectionError(f"the server's process exited with status {status}")
        try:
            # no keep-alive pings, and a bounded close: a closing client would wait for either
            return connect(url, subprotocols=SUBPROTOCOLS, open_timeout=2, max_size=None,
                           legacy=True, ping_interval=None, close_timeout=1)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class FoxgloveClient:
    """Collects advertised channels and received messages of one connection."""

    def __init__(self, url: str, timeout_s: float = 10.0,
                 alive: Callable[[], int | None] = lambda: None) -> None:
        self.ws = connect_when_up(url, timeout_s, alive)
        self.server_info: dict[str, Any] = {}
        self.channels: dict[int, dict[str, Any]] = {}   # channel id -> advertised channel
        self.subscriptions: dict[int, str] = {}         # subscription id -> topic
        self.subscribed: dict[int, int] = {}            # channel id -> subscription id
        self.resubscribed: set[int] = set()             # channel ids subscribed again
        self.messages: dict[str, list[tuple[int, Any]]] = {}
        self.answers: dict[str, list[dict[str, Any]]] = {}   # request id -> its parameters
        self.updates: list[dict[str, Any]] = []   # parameterValues without an id, in order
        self.statuses: list[dict[str, Any]] = []
        self.closed = False

    def close(self) -> None:
        self.ws.close()

    def topics(self) -> dict[str, dict[str, Any]]:
        return {c["topic"]: c for c in self.channels.values()}

    def pump(self, timeout_s: float) -> bool:
        """Handle one frame; False when none came within ``timeout_s`` or the server closed."""
        try:
            frame = self.ws.recv(timeout=timeout_s)
        except TimeoutError:
            return False
        except Exception:  # the connection closed (the session ended)
            self.closed = True
            return False
        if isinstance(frame, str):
            message = json.loads(frame)
            if message["op"] == "serverInfo":
                self.server_info = message
            elif message["op"] == "advertise":
                self.channels.update({c["id"]: c for c in message["channels"]})
            elif message["op"] == "unadvertise":
                for cid in message["channelIds"]:
                    self.channels.pop(cid, None)
            elif message["op"] == "parameterValues":
                if message.get("id") is not None:
                    self.answers[message["id"]] = message["parameters"]
                else:
                    self.updates.extend(message["parameters"])
            elif message["op"] == "status":
                self.statuses.append(message)
                self._subscribe_again(message)
            return True
        opcode, sub_id, log_time = _HEADER.unpack_from(frame)
        if opcode == MESSAGE_DATA:
            topic = self.subscriptions[sub_id]
            payload = json.loads(bytes(frame[_HEADER.size:]))
            self.messages.setdefault(topic, []).append((log_time, payload))
        return True

    def wait_for(self, condition: Any, timeout_s: float) -> bool:
        """Pump frames until ``condition()`` holds or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self.closed:
                return bool(condition())
            self.pump(min(remaining, 0.5))
        return True

    def subscribe(self, topics: list[str]) -> None:
        """Subscribe to the advertised channels of ``topics``."""
        by_topic = {c["topic"]: cid for cid, c in self.channels.items()}
        subs = []
        for topic in topics:
            sub_id = len(self.subscriptions) + 1
            self.subscriptions[sub_id] = topic
            self.subscribed[by_topic[topic]] = sub_id
            subs.append({"id": sub_id, "channelId": by_topic[topic]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def _subscribe_again(self, status: dict[str, Any]) -> None:
        """A subscription refused for a channel this client was advertised, sent again (see
        the module's doc: by then the server knows the channel)."""
        refused = UNKNOWN_CHANNEL.fullmatch(str(status.get("message", "")))
        channel_id = int(refused.group(1)) if refused else None
        if channel_id in self.subscribed and channel_id in self.channels and \
                channel_id not in self.resubscribed:
            self.resubscribed.add(channel_id)
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": self.subscribed[channel_id], "channelId": channel_id}]}))


    def get_parameters(self, names: list[str], request_id: str,
                       timeout_s: float = 30.0) -> dict[str, Any]:
        """``getParameters``: the named parameters (all for ``[]``) by name."""
        self.ws.send(json.dumps({"op": "getParameters", "parameterNames": names,
                                 "id": request_id}))
        assert self.wait_for(lambda: request_id in self.answers, timeout_s), request_id
        return {p["name"]: p for p in self.answers[request_id]}

    def set_parameters(self, values: dict[str, Any], request_id: str,
                       timeout_s: float = 30.0) -> dict[str, Any]:
        """``setParameters``: the values in force afterwards, by name."""
        self.ws.send(json.dumps({"op": "setParameters", "id": request_id, "parameters": [
            {"name": name, "value": value} for name, value in values.items()]}))
        assert self.wait_for(lambda: request_id in self.answers, timeout_s), request_id
        return {p["name"]: p["value"] for p in self.answers[request_id]}

    def subscribe_parameter_updates(self, names: list[str]) -> None:
        self.ws.send(json.dumps({"op": "subscribeParameterUpdates", "parameterNames": names}))


def _read_frame(sock: socket.socket) -> tuple[int, bytes]:
    """One unmasked server frame: (opcode, payload)."""
    def exactly(n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("the server closed the connection")
            data += chunk
        return data
    first, second = exactly(2)
    length = second & 0x7F
    if length == 126:
        (length,) = struct.unpack(">H", exactly(2))
    elif length == 127:
        (length,) = struct.unpack(">Q", exactly(8))
    return first & 0x0F, exactly(length)


def stalled_client(host: str, port: int, topics: list[str], timeout_s: float = 10.0
                   ) -> socket.socket:
    """A client that connects, subscribes to ``topics`` and then never reads again.

    A raw socket with a 4 KiB receive buffer, so the server's queue for it fills fast.
    The caller closes the returned socket.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.settimeout(max(0.1, deadline - time.monotonic()))
        try:
            sock.connect((host, port))
            break
        except OSError:
            sock.close()
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall((f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                  f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                  f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {SUBPROTOCOLS[0]}"
                  "\r\n\r\n").encode())
    response = b""
    while b"\r\n\r\n" not in response:
        response += sock.recv(1)
    if b" 101 " not in response.split(b"\r\n")[0]:
        raise ConnectionError(f"handshake refused: {response[:80]!r}")
    channels: dict[str, int] = {}
    while not set(topics) <= set(channels):
        opcode, payload = _read_frame(sock)
        if opcode == 1:
            message = json.loads(payload)
            if message.get("op") == "advertise":
                channels.update({c["topic"]: c["id"] for c in message["channels"]})
    subscriptions = {channels[t]: {"id": i + 1, "channelId": channels[t]}
                     for i, t in enumerate(topics)}
    # each subscription sent twice: the second is answered "already subscribed" once the
    # server took one; one refused in the server's race (see the module's doc) is sent twice
    # again. Then it never reads
    _send_text(sock, {"op": "subscribe", "subscriptions": list(subscriptions.values())})
    _send_text(sock, {"op": "subscribe", "subscriptions": list(subscriptions.values())})
    unconfirmed = set(subscriptions)
    while unconfirmed:
        opcode, payload = _read_frame(sock)
        status = json.loads(payload).get("message", "") if opcode == 1 else ""
        if (taken := ALREADY_SUBSCRIBED.match(status)) is not None:
            unconfirmed.discard(int(taken.group(1)))
        elif (refused := UNKNOWN_CHANNEL.fullmatch(status)) is not None and \
                int(refused.group(1)) in unconfirmed:
            again = [subscriptions[int(refused.group(1))]]
            _send_text(sock, {"op": "subscribe", "subscriptions": again})
            _send_text(sock, {"op": "subscribe", "subscriptions": again})
    return sock


def _send_text(sock: socket.socket, message: dict[str, Any]) -> None:
    """``message`` as a masked text frame, as a client sends it."""
    text = json.dumps(message).encode()
    mask = os.urandom(4)
    header = bytes([0x81]) + (bytes([0x80 | len(text)]) if len(text) < 126 else
                              bytes([0x80 | 126]) + struct.pack(">H", len(text)))
    sock.sendall(header + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(text)))
