"""A minimal Foxglove WebSocket protocol (v1) client for the tests, on the `websockets` package.

The foxglove-sdk server accepts the subprotocol ``foxglove.sdk.v1`` only (its handshake refuses
a client that offers ``foxglove.websocket.v1`` alone, HTTP 400); the messages are those of the
Foxglove WebSocket protocol spec, v1. The client offers both names, as the Foxglove app does.

Text frames are JSON (``serverInfo``, ``advertise``, ``status``...); the client subscribes with
a ``subscribe`` JSON message and receives binary ``messageData`` frames: opcode 1, a uint32
subscription id, a uint64 log time (little endian), then the payload (JSON here).
"""

from __future__ import annotations

import json
import struct
import time
from typing import Any

from websockets.sync.client import ClientConnection, connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 1
_HEADER = struct.Struct("<BIQ")


def connect_when_up(url: str, timeout_s: float = 10.0) -> ClientConnection:
    """Connect with the Foxglove subprotocol, retrying until the server listens."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return connect(url, subprotocols=SUBPROTOCOLS, open_timeout=2, max_size=None)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class FoxgloveClient:
    """Collects advertised channels and received messages of one connection."""

    def __init__(self, url: str, timeout_s: float = 10.0) -> None:
        self.ws = connect_when_up(url, timeout_s)
        self.server_info: dict[str, Any] = {}
        self.channels: dict[int, dict[str, Any]] = {}   # channel id -> advertised channel
        self.subscriptions: dict[int, str] = {}         # subscription id -> topic
        self.messages: dict[str, list[tuple[int, Any]]] = {}
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
            subs.append({"id": sub_id, "channelId": by_topic[topic]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
