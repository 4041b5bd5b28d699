"""socketcand's text protocol both ways: commands into hil's socketcand server over a real TCP
socket, a gateway's replies into hil's socketcand bus (the client) over a real TCP socket,
and the three parsers of a command directly (the wire adds only time to them, and they take
thousands of cases a second).

The rule: the server answers only with replies of the protocol and hands its node only
valid frames; the client gives valid 11-bit frames or raises python-can's own
:class:`can.CanError`; a parser gives None or a valid frame, never another exception.
"""

from __future__ import annotations

import contextlib
import re
import socket
import threading
from collections.abc import Iterator

import can
from hypothesis import strategies as st

from hil.drivers.socketcand_bus import SocketcandBus, parse_frame, parse_reply
from hil.emulators.socketcand_server import SocketcandServer, parse_send
from tests.fuzz.harness import LIMITS, Check, HangError, Target, ThreadFailures, bound, clear_error
from tests.fuzz.strategies import Stream

#: what the server may say: its greeting, ok, echo, an error, a frame
SERVER_REPLY = re.compile(rb"< (hi|ok|echo|error [a-z ]+|frame [0-9A-F]{3,8} \d+\.\d{6} "
                          rb"[0-9A-F]*) >")
HEX = st.text("0123456789abcdefABCDEF", min_size=0, max_size=9)
WORDS = st.one_of(HEX, st.sampled_from(["-1", "+7", "0x10", "1_0", "FFFFFFFF", "800", "7FF",
                                        "nan", "inf", "1e3", "\u0661"]),
                  st.text(max_size=6))


def mostly(right: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    return st.one_of(right, right, right, WORDS)


IDS = st.one_of(st.integers(0, 0x7FF).map("{:03X}".format),
                st.integers(0, 0x1FFFFFFF).map("{:08X}".format),
                st.sampled_from(["-1", "-7FF", "+7FF", "800", "20000000", "0x7FF", "7ff"]))
BYTES = st.lists(st.integers(0, 255).map("{:02X}".format), max_size=9)


@st.composite
def commands(draw: st.DrawFn) -> str:
    """``< VERB WORD... >`` with a verb of the protocol (or any word), a frame or a send with
    fields mostly right, perhaps unterminated."""
    verb = draw(st.sampled_from(["send", "send", "frame", "frame", "error", "open", "rawmode",
                                 "echo", "bcmmode", "ok", "hi"]) | st.text(max_size=5))
    data = draw(BYTES)
    if verb == "frame" and draw(st.booleans()):
        words = [draw(mostly(IDS)), draw(mostly(st.just("1.000000"))),
                 draw(mostly(st.just("".join(data))))]
    elif verb == "send" and draw(st.booleans()):
        words = [draw(mostly(IDS)), draw(mostly(st.just(f"{len(data):X}"))),
                 *(draw(mostly(st.just(b))) for b in data)]
    else:
        words = draw(st.lists(WORDS, max_size=11))
    text = f"< {verb} {' '.join(words)} >"
    cut = draw(st.sampled_from([None, None, None, "open", "close", "spaces"]))
    if cut == "open":
        text = text[:-1]
    elif cut == "close":
        text = text[1:]
    elif cut == "spaces":
        text = text.replace(" ", draw(st.sampled_from(["", "  ", "\t", "\n"])))
    return text


def streams(preamble: tuple[str, ...]) -> st.SearchStrategy[Stream]:
    """A client's or a gateway's bytes: ``preamble`` (mostly), commands and junk, cut."""
    parts = st.lists(st.one_of(commands(), commands(), st.binary(max_size=16).map(
        lambda b: b.decode("latin-1"))), min_size=1, max_size=8)
    return st.builds(lambda lead, items, cuts: Stream(
        ("".join(preamble) if lead else "").encode("latin-1") + "".join(items).encode(
            "utf-8", "surrogateescape"), tuple(cuts)),
        st.sampled_from([True, True, True, False]), parts,
        st.lists(st.integers(0, 400), max_size=3))


def check_message(msg: can.Message | None) -> None:
    """None, or a message python-can's own checks take."""
    if msg is None:
        return
    can.Message(arbitration_id=msg.arbitration_id, data=msg.data, dlc=msg.dlc,
                is_extended_id=msg.is_extended_id, is_error_frame=msg.is_error_frame,
                check=True)


def check_frame(frame: tuple[int, bytes] | None) -> None:
    if frame is not None:
        can_id, data = frame
        assert 0 <= can_id <= 0x7FF and len(data) <= 8, f"not an 11-bit data frame: {frame}"


@contextlib.contextmanager
def server_rig() -> Iterator[Check]:
    received: list[can.Message] = []
    with ThreadFailures() as failures:
        server = SocketcandServer("127.0.0.1", 0, on_frame=received.append).start()

        def check(stream: Stream) -> None:
            received.clear()
            with socket.create_connection(server.address, timeout=LIMITS.hang_s) as sock:
                for chunk in stream.chunks():
                    sock.sendall(chunk)
                sock.shutdown(socket.SHUT_WR)
                replies = _until_closed(sock)
            failures.check()
            for msg in received:
                check_message(msg)
            rest = SERVER_REPLY.sub(b"", replies).strip()
            assert not rest, f"the server said what the protocol has not: {rest[:80]!r}"

        try:
            yield check
        finally:
            server.close()


def _until_closed(sock: socket.socket) -> bytes:
    received = b""
    while True:
        try:
            data = sock.recv(65536)
        except TimeoutError:
            raise HangError(f"no close within {LIMITS.hang_s:g} s") from None
        except ConnectionResetError:
            return received
        if not data:
            return received
        received += data


@contextlib.contextmanager
def client_rig() -> Iterator[Check]:
    """A gateway that greets, answers the handshake from the case's bytes (mostly a right
    one first), then closes; hil's bus reads every frame until the close."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def check(stream: Stream) -> None:
        def gateway() -> None:
            with contextlib.suppress(OSError):
                connection, _ = listener.accept()
                with connection:
                    for chunk in stream.chunks():
                        connection.sendall(chunk)
                    connection.shutdown(socket.SHUT_WR)
                    connection.settimeout(LIMITS.hang_s)
                    while connection.recv(4096):
                        pass

        thread = threading.Thread(target=gateway, name="fuzz-gateway", daemon=True)
        thread.start()
        with bound("hil's socketcand bus against a fuzzed gateway"):
            try:
                bus = SocketcandBus("can0", "127.0.0.1", port, timeout_s=0.5)
            except can.CanError as exc:
                clear_error(exc, can.CanError)
            else:
                try:
                    for _ in range(200):
                        frame = bus.recv_frame(0.5)
                        check_frame(frame)
                        if frame is None:
                            break
                except can.CanError as exc:
                    clear_error(exc, can.CanError)
                finally:
                    bus.shutdown()
        thread.join(timeout=LIMITS.hang_s)

    try:
        yield check
    finally:
        listener.close()


@contextlib.contextmanager
def parser_rig() -> Iterator[Check]:
    def check(command: str) -> None:
        raw = command.encode("utf-8", "surrogateescape")
        check_frame(parse_frame(raw))
        check_message(parse_reply(raw, "can0"))
        check_message(parse_send(command))

    yield check


TARGETS = (
    Target("socketcand-parsers", commands(), parser_rig, examples=500),
    Target("socketcand-server", streams(("< open can0 >", "< rawmode >")), server_rig,
           examples=120),
    Target("socketcand-client", streams(("< hi >", "< ok >", "< ok >")), client_rig,
           examples=100,
           regressions=(Stream(b"< send \n >", ()),)),  # found: a handshake error of 2 lines
)
