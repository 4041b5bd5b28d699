"""hil's socketcand client (drivers/socketcand_bus.py) over real TCP on 127.0.0.1: against the
project's socketcand server, and against a scripted peer that answers the way the socketcand
daemon does where our server differs (frames in the same read as the handshake's ``< ok >``).
The scripted peer is a real TCP server; only its replies are fixed."""

import socket
import threading
import time

import can
import pytest

from hil.drivers.socketcand_bus import (
    SocketcandBus,
    format_send,
    parse_frame,
    parse_reply,
    send_text,
)


@pytest.fixture
def server(socketcand_server):
    return socketcand_server


def wait_for(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.002)
    return predicate()


def frame(can_id, data=b"", extended=False):
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=extended)


def test_frames_both_ways_and_several_in_one_write(server):
    bus = SocketcandBus("can0", *server.address)
    try:
        bus.send_frames([(0x201, b"\x0f\x00\xe8\x03"), (0x80, b"")])
        bus.send(frame(0x1ABCDEF0, b"\x01\xf1", extended=True))
        assert wait_for(lambda: len(server.received) == 3)
        got = server.received
        assert [m.arbitration_id for m in got] == [0x201, 0x80, 0x1ABCDEF0]
        assert bytes(got[0].data) == b"\x0f\x00\xe8\x03" and got[1].dlc == 0
        assert got[2].is_extended_id and bytes(got[2].data) == b"\x01\xf1"
        server.broadcast([(0x181, b"\x37\x06\x00\x00\x10\x00"), (0x281, b"\x01"),
                          (0x182, b"")])
        first, second = bus.recv(2.0), bus.recv(2.0)
        assert (first.arbitration_id, bytes(first.data)) == (0x181, b"\x37\x06\x00\x00\x10\x00")
        assert (second.arbitration_id, bytes(second.data)) == (0x281, b"\x01")
        assert first.is_rx and first.channel == "can0" and not first.is_extended_id
        assert bus.recv_frame(2.0) == (0x182, b"")  # the same stream, as a tuple
        assert bus.recv(0) is None and bus.recv_frame(0) is None  # nothing more: at once
    finally:
        bus.shutdown()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_recv_frame_skips_error_and_29_bit_frames():
    port, thread = scripted_gateway([b"< error 20000004 1.0 >< frame 1ABCDEF0 1.0 01 >"
                                     b"< frame 281 1.5 0A0B >"])
    bus = SocketcandBus("can0", "127.0.0.1", port)
    try:
        assert bus.recv_frame(2.0) == (0x281, b"\x0a\x0b")
        assert bus.recv_frame(0) is None
    finally:
        bus.shutdown()
        thread.join(5)


def test_a_bus_the_gateway_does_not_serve_fails_the_handshake(server):
    with pytest.raises(can.CanInitializationError, match="could not open bus"):
        SocketcandBus("can9", *server.address)


def test_a_greeting_of_several_lines_is_quoted_on_one():
    # found by the fuzz campaign (benchmarks/fuzz.py): a gateway greeting '< send \n >' put
    # its line break into the handshake's error
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)

        def greet() -> None:
            conn, _ = listener.accept()
            with conn:
                conn.sendall(b"< send \n >")

        thread = threading.Thread(target=greet, daemon=True)
        thread.start()
        with pytest.raises(can.CanInitializationError) as refused:
            SocketcandBus("can0", *listener.getsockname())
        thread.join(5)
    assert str(refused.value).endswith("greeting: expected < hi >, got < send \\n >")


def test_nobody_listening_is_an_initialisation_error():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(can.CanInitializationError, match=f"127.0.0.1:{port}"):
        SocketcandBus("can0", "127.0.0.1", port, timeout_s=1.0)


def scripted_gateway(replies_after_rawmode: list[bytes], close_after: bool = False):
    """A TCP peer that greets, accepts open and rawmode, then writes ``replies_after_rawmode``
    in one write after the rawmode ``< ok >`` (the first one) and the rest one by one."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)

    def serve():
        conn, _ = listener.accept()
        with conn:
            conn.sendall(b"< hi >")
            conn.recv(64)  # < open can0 >
            conn.sendall(b"< ok >")
            conn.recv(64)  # < rawmode >
            conn.sendall(b"< ok >" + replies_after_rawmode[0])
            for reply in replies_after_rawmode[1:]:
                time.sleep(0.05)
                conn.sendall(reply)
            if not close_after:
                time.sleep(2.0)
        listener.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return listener.getsockname()[1], thread


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_frames_in_the_same_read_as_the_handshake_and_split_across_reads_are_kept():
    port, thread = scripted_gateway([b"< frame 181 1.000001 0102 >< frame 2",
                                     b"81 1.000002 03 04 >< ok >< error 20000004 1.0 >"])
    bus = SocketcandBus("can0", "127.0.0.1", port)
    try:
        first, second, error = bus.recv(2.0), bus.recv(2.0), bus.recv(2.0)
        assert (first.arbitration_id, bytes(first.data)) == (0x181, b"\x01\x02")
        assert (second.arbitration_id, bytes(second.data)) == (0x281, b"\x03\x04")
        assert second.timestamp == pytest.approx(1.000002)
        # the error flag (0x20000000) is not part of the id, as in python-can
        assert error.is_error_frame and error.arbitration_id == 0x4
    finally:
        bus.shutdown()
        thread.join(5)


def test_a_connection_closed_by_the_gateway_is_an_operation_error():
    port, thread = scripted_gateway([b""], close_after=True)
    bus = SocketcandBus("can0", "127.0.0.1", port)
    try:
        thread.join(5)
        with pytest.raises(can.CanOperationError, match="closed the connection"):
            bus.recv(2.0)
    finally:
        bus.shutdown()


def test_wire_format_of_one_frame_and_garbage_replies():
    assert format_send(frame(0x80)) == b"< send 080 0  >"
    assert format_send(frame(0x601, b"\x40\x00\x10")) == b"< send 601 3 40 00 10 >"
    assert send_text(0x181, b"\x01\xab") == b"< send 181 2 01 AB >"
    assert parse_frame(b"< frame 181 1.0 01AB >") == (0x181, b"\x01\xab")
    assert parse_frame(b"< frame 00000181 1.0 01 >") is None  # 29-bit, even if small
    assert parse_frame(b"< frame 181 1.0 000102030405060708 >") is None  # 9 bytes
    assert parse_frame(b"< error 20000004 1.0 >") is None
    assert parse_frame(b"< frame 1g1 1.0 >") is None
    assert parse_frame(b"< frame -1 1.000000 46 >") is None  # found by the fuzz campaign
    assert parse_reply(b"< ok >", "can0") is None
    assert parse_reply(b"< frame 18x 1.0 00 >", "can0") is None
    assert parse_reply(b"< frame 181 1.0 000102030405060708 >", "can0") is None  # 9 bytes
    # found by the fuzz campaign: a 9-digit identifier made a standard frame beyond 11 bits
    assert parse_reply(b"< frame 2C89BFBA0 1.000000  >", "can0") is None
    assert parse_reply(b"< frame -1 1.0 00 >", "can0") is None
