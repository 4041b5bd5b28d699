"""A socketcand gateway that misbehaves, over real TCP on 127.0.0.1: after a correct handshake
it sends replies that are not frames (a flood of ``< error ... >``, a trickle of them, or random
bytes). Every receive deadline stays absolute, a flood is a link error naming it, and a run
against such a gateway ends within a few seconds with one line (exit 2), never hangs."""

import os
import random
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest

from hil.drivers.socketcand_bus import SocketcandBus

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]
ROOT = Path(__file__).resolve().parents[2]


class FloodingGateway:
    """Greets, accepts ``open`` and ``rawmode``, then sends ``payload()`` every ``pause_s``
    until the client goes away (each client in turn, so a reconnecting master meets it
    again)."""

    def __init__(self, payload, pause_s=0.0):
        self.payload, self.pause_s = payload, pause_s
        self.listener = socket.socket()
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(4)
        self.listener.settimeout(0.2)
        self.port = self.listener.getsockname()[1]
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self):
        while not self.stopping.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn:
                try:
                    conn.sendall(b"< hi >")
                    conn.recv(64)
                    conn.sendall(b"< ok >")
                    conn.recv(64)
                    conn.sendall(b"< ok >")
                    while not self.stopping.is_set():
                        conn.sendall(self.payload())
                        if self.pause_s:
                            time.sleep(self.pause_s)
                except OSError:
                    continue

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stopping.set()
        self.thread.join(5)
        self.listener.close()


def errors():
    return b"< error 20000004 1.0 >" * 50


def junk():
    return bytes(random.getrandbits(8) for _ in range(512)).replace(b"<", b"?")


def test_a_trickle_of_errors_does_not_extend_the_receive_deadline():
    with FloodingGateway(lambda: b"< error 20000004 1.0 >", pause_s=0.01) as gateway:
        bus = SocketcandBus("can0", "127.0.0.1", gateway.port)
        try:
            start = time.monotonic()
            assert bus.recv_frame(0.5) is None  # returns although the trickle goes on
            # (it used to wait as long as replies kept coming: forever; the bound is loose)
            assert time.monotonic() - start < 5
        finally:
            bus.shutdown()


@pytest.mark.parametrize(("payload", "named"), [
    (errors, "replies in a row that are not frames"),
    (junk, "bytes in a row that hold no socketcand reply"),
])
def test_a_flood_is_a_link_error_naming_it(payload, named):
    with FloodingGateway(payload) as gateway:
        bus = SocketcandBus("can0", "127.0.0.1", gateway.port)
        try:
            start = time.monotonic()
            with pytest.raises(can.CanOperationError, match=named):
                while time.monotonic() - start < 5:
                    bus.recv_frame(0.1)
            assert time.monotonic() - start < 5  # bounded, not extended by the flood
        finally:
            bus.shutdown()


@pytest.mark.parametrize("payload", [errors, junk])
def test_a_run_against_a_flooding_gateway_ends_with_one_line(tmp_path, payload):
    with FloodingGateway(payload) as gateway:
        start = time.monotonic()
        done = subprocess.run(
            [sys.executable, "-m", "hil", "servo", "run", "--controller", "pid", "--drive",
             f"socketcand://127.0.0.1:{gateway.port}/can0", "--duration", "2",
             "--out", str(tmp_path / "flood.mcap")],
            capture_output=True, text=True, timeout=40, check=False,
            env=dict(os.environ, PYTHONPATH=str(ROOT)))
        elapsed = time.monotonic() - start
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hil: error: "), done.stderr
    assert elapsed < 15
