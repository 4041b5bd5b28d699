"""The reverse channel of a live session: parameter requests from the writer process back to
the loop process, where the run's tuner lives.

The record stream only flows from the loop process to its writer process. With ``--live`` on a
run (a session with a tuner: ``Recorder(..., tunable=True)``), the
:class:`~hil.core.recording.recorder.Recorder` also creates a socket pair and passes one end to
the writer (``tune_fd``). Over it, JSON lines, one per message:

* writer -> loop: ``{"id": N, "op": "specs"}`` and
  ``{"id": N, "op": "set", "name": NAME, "value": VALUE, "client": WHO}``;
* loop -> writer: ``{"id": N, "specs": [SPEC...]}`` and ``{"id": N, "result": RESULT}``.

SPEC and RESULT carry the fields of ``hil.core.tuning``'s ``TunableSpec`` and ``TuneResult``.
:class:`RemotePort` is the writer's end (the live view's :class:`ParameterPort`);
:class:`PortServer` is the loop's end, a thread that asks the tuner (anything with ``specs()``
and ``request(name, value, client)``) and answers; each set waits for its tick boundary in a
small pool of threads, so a rebuild does not hold up a listing. Without ``--live``, or in a
session without a tuner, none of this exists and the live view offers no parameters.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import socket
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from hil.core.recording.live_params import Result, Spec

SPECS_TIMEOUT_S = 30.0     # a listing asked for while the run still starts waits for its loop
SET_TIMEOUT_S = 5.0        # the tuner's own wait for the tick boundary (or the rebuild)
ANSWER_MARGIN_S = 5.0      # on top of it, for the loop process to answer
SET_THREADS = 4            # sets waiting at once in the loop process (more wait their turn)


def _send(sock: socket.socket, lock: threading.Lock, message: dict[str, Any]) -> bool:
    """Write one JSON line; False when the other end is gone."""
    data = (json.dumps(message, separators=(",", ":")) + "\n").encode()
    with lock:
        try:
            sock.sendall(data)
        except OSError:
            return False
    return True


def _lines(sock: socket.socket) -> Any:
    """The JSON messages read from ``sock`` until it closes."""
    with sock.makefile("rb") as stream:
        for line in stream:
            with contextlib.suppress(ValueError):
                yield json.loads(line)


class RemotePort:
    """The writer's end: a :class:`ParameterPort` whose answers come from the loop process."""

    def __init__(self, sock: socket.socket, set_timeout_s: float = SET_TIMEOUT_S) -> None:
        self._sock = sock
        self._set_timeout_s = set_timeout_s
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._waiting: dict[int, tuple[threading.Event, list[dict[str, Any]]]] = {}
        self._closed = threading.Event()
        threading.Thread(target=self._read, name="tune-wire", daemon=True).start()

    def _read(self) -> None:
        with contextlib.suppress(OSError):
            for message in _lines(self._sock):
                waiter = self._waiting.get(message.get("id"))
                if waiter is not None:
                    waiter[1].append(message)
                    waiter[0].set()
        self._closed.set()
        for event, _ in list(self._waiting.values()):
            event.set()

    def _ask(self, message: dict[str, Any], timeout_s: float) -> dict[str, Any] | None:
        request_id = next(self._ids)
        event: threading.Event = threading.Event()
        answer: list[dict[str, Any]] = []
        self._waiting[request_id] = (event, answer)
        try:
            if self._closed.is_set():
                return None
            if not _send(self._sock, self._lock, {"id": request_id, **message}):
                self._closed.set()  # the loop's end is gone (its reader may not know yet)
                return None
            event.wait(timeout_s)
            return answer[0] if answer else None
        finally:
            del self._waiting[request_id]

    def specs(self) -> list[Spec]:
        answer = self._ask({"op": "specs"}, SPECS_TIMEOUT_S)
        return list(answer["specs"]) if answer else []

    def request(self, name: str, value: object, client: str) -> Result:
        timeout_s = self._set_timeout_s + ANSWER_MARGIN_S
        answer = self._ask({"op": "set", "name": name, "value": value, "client": client},
                           timeout_s)
        if answer:
            return dict(answer["result"])
        why = "the run has ended" if self._closed.is_set() else \
            f"no answer from the loop within {timeout_s:g} s"
        return {"name": name, "accepted": False, "value": None, "reason": why, "tick": None}


def _plain(item: Any) -> dict[str, Any]:
    """A spec or result as the dict that crosses the channel (its fields are plain values:
    no deep copy)."""
    if dataclasses.is_dataclass(item) and not isinstance(item, type):
        return {f.name: getattr(item, f.name) for f in dataclasses.fields(item)}
    return dict(item)


class PortServer:
    """The loop's end: answers the writer's requests from ``port`` (the run's tuner)."""

    def __init__(self, sock: socket.socket, port: Any,
                 set_timeout_s: float = SET_TIMEOUT_S) -> None:
        self._sock = sock
        self._port = port
        self._set_timeout_s = set_timeout_s
        self._lock = threading.Lock()
        # each set waits for its tick boundary (or rebuild) in a thread of the pool, so a
        # rebuild holds up neither a listing nor another client's set; no thread per set
        self._sets = ThreadPoolExecutor(SET_THREADS, thread_name_prefix="tune-set")
        self._thread = threading.Thread(target=self._serve, name="tune-port", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        with contextlib.suppress(OSError):
            for message in _lines(self._sock):
                if message.get("op") == "specs":
                    self._answer(message["id"], specs=[_plain(s) for s in self._port.specs()])
                elif message.get("op") == "set":
                    self._sets.submit(self._set, message)

    def _set(self, message: dict[str, Any]) -> None:
        name = str(message.get("name"))
        try:
            result = _plain(self._port.request(name, message.get("value"),
                                               str(message.get("client", "")),
                                               timeout_s=self._set_timeout_s))
        except Exception as exc:  # a failing tuner refuses; the loop and the server go on
            result = {"name": name, "accepted": False, "value": None,
                      "reason": f"{type(exc).__name__}: {exc}", "tick": None}
        self._answer(message["id"], result=result)

    def _answer(self, request_id: int, **answer: Any) -> None:
        _send(self._sock, self._lock, {"id": request_id, **answer})

    def close(self) -> None:
        """Stop answering (the writer's end then refuses every request)."""
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()
        self._thread.join(1.0)
        self._sets.shutdown(wait=False, cancel_futures=True)
