"""The socketcand-protocol server: handshake, raw mode, frames both ways, several clients, bad
input. Real TCP sockets on 127.0.0.1 and python-can's stock ``socketcand`` client."""

import random
import re
import socket
import time

import can
import pytest

from hil.drivers.socketcand_bus import send_text
from hil.emulators.drive.node import DriveNode
from hil.emulators.socketcand_server import (
    SocketcandServer,
    format_frame,
    parse_send,
    parse_send_frame,
)
from hil.errors import HilError


@pytest.fixture
def server(socketcand_server):
    return socketcand_server


def connect(srv):
    sock = socket.create_connection(srv.address, timeout=5)
    sock.settimeout(5)
    return sock


def raw_client(srv):
    """A client of ``srv`` through the handshake, in raw mode."""
    sock = connect(srv)
    read_until(sock, "< hi >")
    sock.sendall(b"< open can0 >< rawmode >")
    read_until(sock, "< ok >< ok >")
    return sock


def read_until(sock, text, timeout=5.0):
    data, deadline = b"", time.monotonic() + timeout
    while text.encode() not in data and time.monotonic() < deadline:
        try:
            chunk = sock.recv(4096)
        except TimeoutError:
            break
        if not chunk:
            break
        data += chunk
    return data.decode()


def wait_for(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.005)
    return predicate()


def test_handshake_and_frames_in_the_socketcand_wire_format(server):
    sock = connect(server)
    assert read_until(sock, "< hi >") == "< hi >"
    sock.sendall(b"< open can0 >")
    assert read_until(sock, "< ok >") == "< ok >"
    sock.sendall(b"< rawmode >")
    assert read_until(sock, "< ok >") == "< ok >"
    sock.sendall(b"< echo >")
    assert read_until(sock, "< echo >") == "< echo >"
    sock.sendall(b"< send 601 8 40 0 10 0 0 0 0 0 >< send 1ABCDEF0 2 1 f1 >< send 080 0 >")
    assert wait_for(lambda: len(server.received) == 3)
    first, second, third = server.received
    assert (first.arbitration_id, bytes(first.data), first.is_extended_id) == \
        (0x601, bytes([0x40, 0, 0x10, 0, 0, 0, 0, 0]), False)
    assert (second.arbitration_id, bytes(second.data), second.is_extended_id) == \
        (0x1ABCDEF0, b"\x01\xf1", True)
    assert third.dlc == 0
    before = time.time()
    server.broadcast([(0x181, b"\x37\x02\x10")])
    text = read_until(sock, ">")
    match = re.fullmatch(r"< frame 181 (\d+\.\d{6}) 370210 >", text)
    assert match is not None, text
    assert before - 1e-6 <= float(match.group(1)) <= time.time()  # stamped when sent
    sock.close()


def test_a_node_takes_each_11_bit_frame_as_its_id_and_data_without_a_message():
    data: list[tuple[int, bytes]] = []
    messages: list[can.Message] = []
    srv = SocketcandServer("127.0.0.1", 0, on_data=lambda i, d: data.append((i, d))).start()
    try:
        sock = raw_client(srv)
        sock.sendall(b"< send 201 4 0F 00 E8 03 >< send 1ABCDEF0 2 1 f1 >< send 080 0 >"
                     b"< send 601 8 40 0 10 0 0 0 0 0 >< send 123 2 1 1ff >")
        assert wait_for(lambda: len(data) == 3)
        assert data == [(0x201, b"\x0f\x00\xe8\x03"), (0x080, b""),
                        (0x601, bytes([0x40, 0, 0x10, 0, 0, 0, 0, 0]))]  # 29-bit: not a node's
        srv.on_frame = messages.append  # both hooks: each hears what it takes
        sock.sendall(b"< send 1ABCDEF0 2 1 f1 >< send 181 1 05 >")
        assert wait_for(lambda: len(messages) == 2)
        assert [(m.arbitration_id, m.is_extended_id) for m in messages] == [
            (0x1ABCDEF0, True), (0x181, False)] and data[-1] == (0x181, b"\x05")
        sock.close()
    finally:
        srv.close()


def test_a_reads_frames_reach_on_frames_together_and_before_the_next_command_is_answered():
    """A master's transmission (its frames in one write) is one call of ``on_frames``; a
    command after frames in the same read is answered after they were taken (their answers
    come first)."""
    batches: list[list[tuple[int, bytes]]] = []

    def take(frames: list[tuple[int, bytes]]) -> None:
        batches.append(frames)
        srv.broadcast([(0x180 + len(batches), b"")])  # an answer to this batch
    srv = SocketcandServer("127.0.0.1", 0, on_frames=take).start()
    try:
        sock = raw_client(srv)
        sock.sendall(b"< send 201 4 0F 00 E8 03 >< send 1ABCDEF0 2 1 f1 >< send 080 0 >"
                     b"< echo >< send 202 1 07 >")
        text = read_until(sock, "< frame 182 ")
        assert re.match(r"< frame 181 [\d.]+  >< echo >< frame 182 ", text), text
        assert batches == [[(0x201, b"\x0f\x00\xe8\x03"), (0x080, b"")], [(0x202, b"\x07")]]
        sock.close()
    finally:
        srv.close()


#: sends in the form hil's master writes them, and in every other form a read may hold
SENDS_OF_EVERY_FORM = (
    [send_text(can_id, bytes(range(size))) for can_id, size in
     ((0x201, 6), (0x080, 0), (0x7FF, 8), (0x000, 1), (0x601, 8), (0x17F, 2))]
    + [b"< send 1ab 2 0f e8 >",           # lower-case hex
       b"< send 201  2 0F E8 >",          # two spaces
       b"< send 201 2 0F E8>",            # no space before '>'
       b"< send 201 2 F E8 >",            # a byte of one digit
       b"< send 800 0  >",                # an 11-bit id beyond 0x7FF: ignored
       b"< send 123 3 01 02 >",           # a length that is not the data's: ignored
       b"< send 123 9 01 02 03 04 05 06 07 08 09 >",
       b"< send 1ABCDEF0 2 01 F1 >",      # 29-bit: not a node's
       b"< send 12 1 AA >",               # an id of two digits
       b"< send 80 0  >", b"< send 080 0 >",  # a SYNC as python-can writes it, one space
       b"garbage", b" ", b"\n"])


def test_a_reads_sends_reach_on_frames_as_each_command_parsed_alone_gives_them():
    """A lone raw-mode client's read of sends in the master's form is taken in one pass: the
    frames handed over are those each command parsed on its own gives, in order, whatever
    other forms and garbage the read mixes in."""
    batches: list[list[tuple[int, bytes]]] = []
    srv = SocketcandServer("127.0.0.1", 0, on_frames=batches.append).start()
    shuffle = random.Random(7)
    try:
        sock = raw_client(srv)
        sock.sendall(b"< echo >")  # the first command after rawmode: the hold is over
        read_until(sock, "< echo >")
        for _ in range(150):
            read = [shuffle.choice(SENDS_OF_EVERY_FORM)
                    for _ in range(shuffle.randint(1, 6))]
            expected = [sent[:2] for command in read
                        if (sent := parse_send_frame(command.decode())) and not sent[2]]
            done = len(batches)
            sock.sendall(b"".join(read) + b"< echo >")  # its frames are handed over first
            read_until(sock, "< echo >")
            assert [frame for batch in batches[done:] for frame in batch] == expected, read
            assert len(batches) - done == (1 if expected else 0), read
        sock.close()
    finally:
        srv.close()


def test_unknown_bus_is_refused_and_the_connection_closed(server):
    sock = connect(server)
    read_until(sock, "< hi >")
    sock.sendall(b"< open can7 >")
    assert read_until(sock, ">") == "< error could not open bus >"
    assert sock.recv(100) == b""  # closed by the server
    sock.close()


def test_bad_commands_are_answered_or_ignored_never_fatal(server):
    sock = connect(server)
    read_until(sock, "< hi >")
    sock.sendall(b"< rawmode >")  # before open
    assert read_until(sock, ">") == "< error unknown command >"
    sock.sendall(b"< open can0 >< rawmode >")
    assert read_until(sock, "< ok >< ok >").count("< ok >") == 2
    sock.sendall(b"< subscribe 0 0 123 >")  # BCM job: not supported
    assert read_until(sock, ">") == "< error unknown command >"
    sock.sendall(b"garbage< send 123 3 1 2 >< send 800 0 >< send 12 9 >< send xyz 1 1 >"
                 b"< send 123 1 1ff >" + b"x" * 300 + b"< send 7 1 aa >")
    assert wait_for(lambda: len(server.received) == 1)
    assert server.received[0].arbitration_id == 0x7 and bytes(server.received[0].data) == b"\xaa"
    sock.sendall(b"< echo >")
    assert read_until(sock, "< echo >") == "< echo >"
    sock.close()


@pytest.mark.slow
def test_frames_go_to_the_other_clients_in_raw_mode_only(server):
    a, b, bcm = connect(server), connect(server), connect(server)
    for sock in (a, b, bcm):
        read_until(sock, "< hi >")
        sock.sendall(b"< open can0 >")
        read_until(sock, "< ok >")
    for sock in (a, b):
        sock.sendall(b"< rawmode >")
        read_until(sock, "< ok >")
    b.sendall(b"< echo >")  # releases the post-handshake hold at once
    read_until(b, "< echo >")
    a.sendall(b"< send 222 1 5 >")
    frame = read_until(b, ">")
    assert frame.startswith("< frame 222 ") and frame.endswith(" 05 >")
    bcm.settimeout(0.3)
    assert read_until(bcm, ">", timeout=0.3) == ""  # BCM mode: no frames
    a.settimeout(0.3)
    assert read_until(a, ">", timeout=0.3) == ""  # not echoed to its sender
    for sock in (a, b, bcm):
        sock.close()
    assert wait_for(lambda: server.client_count == 0)


def test_python_can_socketcand_client_reaches_an_emulated_drive():
    srv = SocketcandServer("127.0.0.1", 0)
    node = DriveNode(send=srv.broadcast)
    srv.on_frame, srv.on_tick = node.handle, node.service
    node.boot()
    srv.start()
    host, port = srv.address
    bus = can.Bus(interface="socketcand", host=host, port=port, channel="can0")
    try:
        bus.send(can.Message(arbitration_id=0x601, data=[0x40, 0x00, 0x10, 0, 0, 0, 0, 0],
                             is_extended_id=False))
        answer = bus.recv(5.0)
        assert answer is not None and answer.arbitration_id == 0x581
        assert bytes(answer.data) == bytes([0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00])
    finally:
        bus.shutdown()
        srv.close()


def test_format_and_parse_are_inverse_for_standard_and_extended_ids():
    for can_id, extended, data in ((0x7FF, False, b""), (0x1FFFFFFF, True, bytes(range(8)))):
        msg = can.Message(arbitration_id=can_id, data=data, is_extended_id=extended,
                          timestamp=1.0)
        text = format_frame(msg).decode()
        id_text = text.split()[2]
        command = f"< send {id_text} {len(data):X} {' '.join(f'{b:x}' for b in data)} >"
        parsed = parse_send(command)
        assert (parsed.arbitration_id, parsed.is_extended_id, bytes(parsed.data)) == \
            (can_id, extended, data)
    assert parse_send("< send -1 1 BB >") is None  # found by the fuzz campaign: id -1


def test_a_busy_port_is_one_clear_error(server):
    with pytest.raises(HilError, match=r"cannot listen on 127\.0\.0\.1:\d+"):
        SocketcandServer("127.0.0.1", server.address[1], channel="can0").close()


def test_polling_for_an_expected_frame_serves_the_same_bus():
    """With ``next_frame_ns`` the loop polls instead of sleeping from the margin before the
    frame is due; the bus works the same (here a frame is always due: it polls throughout)."""
    frames = []
    srv = SocketcandServer("127.0.0.1", 0, on_frame=frames.append,
                           next_frame_ns=lambda now: now, poll_margin_s=150e-6).start()
    try:
        assert srv._until_polling() == 0.0
        srv.next_frame_ns = lambda now: now + 1_000_000
        assert 0.0 < srv._until_polling() <= 850e-6
        srv.next_frame_ns = lambda now: None
        assert srv._until_polling() == float("inf")
        srv.next_frame_ns = lambda now: now
        bus = can.Bus(interface="socketcand", host="127.0.0.1", port=srv.address[1],
                      channel="can0")
        try:
            bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
            assert wait_for(lambda: len(frames) == 1)
            srv.broadcast([(0x181, b"\x01")])
            reply = bus.recv(2.0)
            assert reply is not None and reply.arbitration_id == 0x181
        finally:
            bus.shutdown()
    finally:
        srv.close()


@pytest.mark.realtime  # a window of 900 us on the wall clock: with the other timed tests
def test_a_poll_window_shorter_than_a_millisecond_is_polled():
    """The wait before the poll window is timed to the microsecond: epoll counts whole
    milliseconds (Python rounds a shorter wait up to one), which slept through a window of
    less than that and answered every SYNC from a blocking wake-up. Here the window opens
    50 us after the server starts and closes 900 us later: an epoll wait cannot end before a
    millisecond, so a server waiting that way never looks inside it; a loaded machine may
    wake this one late once, not in each of five tries."""

    def looks_inside_the_window() -> bool:
        due: list[int] = []
        inside: list[int] = []

        def next_frame_ns(now: int) -> int:
            if not due:
                due.append(now + 950_000)
            if due[0] - 900_000 <= now < due[0]:
                inside.append(now)
            return due[0]

        srv = SocketcandServer("127.0.0.1", 0, tick_period_s=1.0, next_frame_ns=next_frame_ns,
                               poll_margin_s=900e-6).start()
        try:
            assert wait_for(lambda: bool(due) and time.monotonic_ns() > due[0] + 1_000_000)
        finally:
            srv.close()
        return bool(inside)

    assert any(looks_inside_the_window() for _ in range(5))


@pytest.mark.slow
@pytest.mark.parametrize("follows", [True, False])
def test_the_time_service_can_follow_the_frames_instead_of_waking_up(follows):
    """A server on a real-time loop's core serves its time after the frame that comes when the
    service is due, rather than from a wake-up of its own that would interrupt the loop; a
    bus gone quiet gets it one period late. Here the service is due 0.5 s after the start,
    a frame comes at 0.6 s and the fallback would be at 1.0 s."""
    events: list[str] = []
    srv = SocketcandServer("127.0.0.1", 0, tick_period_s=0.5,
                           on_data=lambda *_: events.append("data"),
                           on_tick=lambda: events.append("tick"))
    srv.service_follows_frames = follows
    started = time.monotonic()
    srv.start()
    try:
        sock = connect(srv)
        sock.sendall(b"< open can0 >< rawmode >")
        time.sleep(max(0.0, started + 0.6 - time.monotonic()))
        sock.sendall(b"< send 080 0 >")
        assert wait_for(lambda: len(events) >= 3)
        sock.close()
    finally:
        srv.close()
    assert events[:3] == (["tick", "data", "tick"] if follows else ["tick", "tick", "data"])
