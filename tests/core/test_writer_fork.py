"""The writer processes forked by a loop process's fork server (hil.core.recording.writer_fork):
each is the loop process's own child, named, in a session of its own, holding nothing of the
loop's but what it was given, and writes where the loop stood when its session started."""

import os
import socket
from pathlib import Path

from hil.core.recording.reader import read_session
from hil.core.recording.recorder import Recorder
from hil.core.recording.writer_fork import SERVER_NAME, WRITER_NAME

SCHEMA = {"type": "object", "properties": {"k": {"type": "integer"}}}


def parent_of(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def name_of(pid: int) -> str:
    return Path(f"/proc/{pid}/comm").read_text().strip()


def descriptors_of(pid: int) -> dict[int, str]:
    """What ``pid``'s open descriptors point at (``socket:[INODE]``, ``pipe:[INODE]``,
    paths...)."""
    fds = Path(f"/proc/{pid}/fd")
    return {int(fd): os.readlink(fds / fd) for fd in os.listdir(fds)}


def record(rec: Recorder, count: int) -> None:
    topic = rec.topic("/k", SCHEMA)
    for k in range(count):
        topic.log(k * 1000, {"k": k})


def test_a_writer_is_the_loop_process_child_and_holds_none_of_its_descriptors(tmp_path):
    """A connection the loop holds (a drive's socket, say) must see its end when the loop
    closes it: the writer has no copy of it."""
    held, _peer = socket.socketpair()
    with held, _peer:
        rec = Recorder(tmp_path / "a.mcap", wait_when_full=True)
        rec.wait_ready()  # its file open
        writer = rec.writer_pid
        assert writer is not None
        assert parent_of(writer) == os.getpid()
        assert name_of(writer) == WRITER_NAME
        assert os.getsid(writer) == writer != os.getsid(0)
        theirs = descriptors_of(writer)
        assert theirs[0].startswith("pipe:") and theirs[1].startswith("pipe:")
        beyond = {fd: what for fd, what in theirs.items() if fd > 2}
        assert beyond and all(what.startswith(str(tmp_path)) for what in beyond.values()), \
            beyond  # the session file alone: not the socket held, nor the server's
        assert f"socket:[{os.fstat(held.fileno()).st_ino}]" not in theirs.values()
        record(rec, 100)
        rec.close()
    assert read_session(str(tmp_path / "a.mcap")).topic_counts["/k"] == 100


def test_sessions_of_one_process_share_one_server_and_each_has_its_writer(tmp_path):
    first = Recorder(tmp_path / "1.mcap", wait_when_full=True)
    second = Recorder(tmp_path / "2.mcap", wait_when_full=True)
    servers = [pid for pid in map(int, filter(str.isdigit, os.listdir("/proc")))
               if _is_our_server(pid)]
    assert len(servers) == 1
    assert first.writer_pid != second.writer_pid
    assert {parent_of(w) for w in (first.writer_pid, second.writer_pid)} == {os.getpid()}
    for rec, count in ((first, 10), (second, 20)):
        record(rec, count)
        rec.close()
    assert read_session(str(tmp_path / "1.mcap")).topic_counts["/k"] == 10
    assert read_session(str(tmp_path / "2.mcap")).topic_counts["/k"] == 20


def _is_our_server(pid: int) -> bool:
    try:
        return name_of(pid) == SERVER_NAME and parent_of(pid) == os.getpid()
    except OSError:
        return False


def test_a_relative_path_is_where_the_loop_stood_when_its_session_started(tmp_path,
                                                                          monkeypatch):
    """The server started in one folder; a later session's writer opens its file from the
    folder the loop process is in then."""
    (tmp_path / "here").mkdir()
    (tmp_path / "there").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    with Recorder("first.mcap", wait_when_full=True) as rec:
        record(rec, 5)
    monkeypatch.chdir(tmp_path / "there")
    with Recorder("second.mcap", wait_when_full=True) as rec:
        record(rec, 7)
    assert read_session(str(tmp_path / "here" / "first.mcap")).topic_counts["/k"] == 5
    assert read_session(str(tmp_path / "there" / "second.mcap")).topic_counts["/k"] == 7
    assert not (tmp_path / "here" / "second.mcap").exists()


def test_a_killed_server_is_replaced_and_its_writers_write_on(tmp_path):
    from hil.core.recording import writer_fork

    before = Recorder(tmp_path / "before.mcap", wait_when_full=True)
    before.wait_ready()
    server = writer_fork._SERVER
    assert server is not None
    server.process.kill()
    server.process.wait()
    after = Recorder(tmp_path / "after.mcap", wait_when_full=True)
    assert writer_fork._SERVER is not server
    for rec, count in ((before, 3), (after, 4)):
        record(rec, count)
        rec.close()
    assert read_session(str(tmp_path / "before.mcap")).topic_counts["/k"] == 3
    assert read_session(str(tmp_path / "after.mcap")).topic_counts["/k"] == 4
