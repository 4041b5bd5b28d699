"""A client of a live session's parameters, over the Foxglove WebSocket protocol (``hil tune``).

It speaks to the live view as Foxglove's Parameters panel does: ``getParameters`` to list,
``setParameters`` with a request id to set, and reads the ``parameterValues`` answer (the value in
force afterwards) and the warning ``status`` a refusal sends
(:mod:`hil.core.recording.live_params`).
"""

from __future__ import annotations

import contextlib
import json
import time
import uuid
from dataclasses import dataclass
from typing import Any

from hil.core.recording.tune_wire import ANSWER_MARGIN_S, SET_TIMEOUT_S
from hil.errors import HilError

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
CONNECT_TIMEOUT_S = 5.0
ANSWER_TIMEOUT_S = SET_TIMEOUT_S + 2 * ANSWER_MARGIN_S
STATUS_GRACE_S = 1.0   # a refusal's status is sent before its answer; this much more at most


class TuneConnectionError(HilError):
    """The live view cannot be reached, serves no parameters, or did not answer."""


@dataclass(frozen=True)
class SetAnswer:
    """What became of one set: accepted, and the value in force afterwards (None: the
    server knows no such parameter), or refused and why."""

    name: str
    requested: Any
    accepted: bool
    value: Any
    reason: str


class TuneClient:
    """One connection to a live view that serves parameters."""

    def __init__(self, host: str, port: int, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
        from websockets.sync.client import connect

        where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        self._stack = contextlib.ExitStack()
        try:
            self._ws = self._stack.enter_context(connect(
                f"ws://{where}", subprotocols=SUBPROTOCOLS,  # type: ignore[arg-type]
                open_timeout=timeout_s, max_size=None, ping_interval=None, close_timeout=1))
        except (OSError, TimeoutError) as exc:
            raise TuneConnectionError(f"cannot connect to {where}: "
                                      f"{getattr(exc, 'strerror', None) or exc}") from None
        except Exception as exc:  # the handshake was refused: not a Foxglove live view
            raise TuneConnectionError(f"{where} is not a live view: {exc}") from None
        self.where = where
        self._statuses: dict[str, str] = {}
        self._answers: dict[str, list[dict[str, Any]]] = {}
        info = self._wait(lambda m: m.get("op") == "serverInfo", timeout_s)
        if "parameters" not in info.get("capabilities", []):
            self.close()
            raise TuneConnectionError(f"{where} serves no parameters (a live session of "
                                      "'hil bench|servo run --live' does)")

    def close(self) -> None:
        self._stack.close()

    def _wait(self, wanted: Any, timeout_s: float) -> dict[str, Any]:
        """Read messages (keeping answers and statuses) until one is ``wanted``."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            try:
                frame = self._ws.recv(timeout=max(remaining, 0.0))
            except TimeoutError:
                raise TuneConnectionError(f"{self.where}: no answer within {timeout_s:g} s") \
                    from None
            except Exception:
                raise TuneConnectionError(f"{self.where}: the live view closed the connection "
                                          "(the run has ended)") from None
            if not isinstance(frame, str):
                continue  # a topic's message
            message = json.loads(frame)
            if message.get("op") == "status" and message.get("id"):
                self._statuses[str(message["id"])] = str(message.get("message", ""))
            elif message.get("op") == "parameterValues" and message.get("id"):
                self._answers[str(message["id"])] = list(message.get("parameters", []))
            if wanted(message):
                return dict(message)

    def parameters(self) -> dict[str, Any]:
        """Every parameter's value now."""
        request_id = uuid.uuid4().hex
        self._ws.send(json.dumps({"op": "getParameters", "parameterNames": [],
                                  "id": request_id}))
        answer = self._wait(lambda m: m.get("id") == request_id, ANSWER_TIMEOUT_S)
        return {p["name"]: p.get("value") for p in answer.get("parameters", [])}

    def set(self, name: str, value: Any) -> SetAnswer:
        """Set one parameter; returns once the run applied or refused it."""
        request_id = uuid.uuid4().hex
        self._ws.send(json.dumps({"op": "setParameters", "id": request_id,
                                  "parameters": [{"name": name, "value": value}]}))
        answer = self._wait(lambda m: m.get("op") == "parameterValues"
                            and m.get("id") == request_id, ANSWER_TIMEOUT_S)
        values = {p["name"]: p.get("value") for p in answer.get("parameters", [])}
        now = values.get(name)
        key = next((k for k in self._statuses if k.endswith(f":{request_id}:{name}")), None)
        if key is None and now != value:
            deadline = time.monotonic() + STATUS_GRACE_S
            while key is None and time.monotonic() < deadline:
                try:
                    self._wait(lambda m: m.get("op") == "status",
                               deadline - time.monotonic())
                except TuneConnectionError:
                    break
                key = next((k for k in self._statuses
                            if k.endswith(f":{request_id}:{name}")), None)
        if key is None and now == value:
            return SetAnswer(name, value, True, now, "")
        reason = self._statuses[key].split("): ", 1)[-1] if key is not None else \
            f"the value stays {now!r}"
        return SetAnswer(name, value, False, now, reason)
