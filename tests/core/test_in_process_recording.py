"""A session recorded in the loop's own process (``RecordingOptions.in_process``, what ``hil
sweep`` gives its trials on Ray) keeps every guarantee of one recorded by a writer process: the
same session bit for bit (tests/session_digest.py), a finished and indexed file, a full disk
that stops the writing with the true count, a SIGKILL that leaves a file the reader recovers
with counts; and it is refused where it cannot keep them (real time, a live view)."""

import os
import signal
import time

import pytest
from mcap.reader import make_reader

from hil.core.recording.reader import read_session
from hil.core.recording.recorder import Recorder
from hil.core.recording.recording_options import RecordingOptions
from hil.core.run import run_experiment
from hil.errors import HilError, RecordingError
from hil.servo.run import ServoExperiment, ServoRunOptions
from tests.session_digest import session_digest

pytestmark = [pytest.mark.timeout(120)]

IN_PROCESS = RecordingOptions(in_process=True)
SCHEMA = {"type": "object", "title": "Seq"}

# a lockstep loop recording in its own process: 2000 messages a second of session time,
# handed over as the loop does after every tick; the file's size limited when asked
CHILD = """
import resource, sys
from hil.core.recording.recorder import Recorder
from hil.core.recording.recording_options import RecordingOptions
from hil.errors import RecordingError
if {limit}:
    resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
rec = Recorder({path!r}, wait_when_full=True, options=RecordingOptions(in_process=True))
rec.wait_ready()
print("writer", rec.writer_pid, flush=True)
topic = rec.topic("/seq", {{"type": "object", "title": "Seq"}})
k = 0
try:
    while True:
        topic.log(k * 500_000, {{"k": k, "pad": "x" * 40}})
        rec.flush_if_due()
        if k % 500 == 0:
            print(k, flush=True)
        k += 1
except RecordingError as exc:
    print("stopped", k, exc, flush=True)
try:
    rec.close()
except RecordingError as exc:
    print("closed", exc, flush=True)
"""


def servo_run(path, recording: RecordingOptions) -> dict:
    options = ServoRunOptions(controller="mpc", reference="sine:amplitude=2,frequency=10",
                              duration_s=0.3, out=str(path), quiet=True, recording=recording)
    return dict(run_experiment(ServoExperiment(options)).kpis)


@pytest.mark.slow
def test_a_run_recorded_in_process_records_the_session_a_writer_process_records(tmp_path):
    with_process = servo_run(tmp_path / "process.mcap", RecordingOptions())
    in_process = servo_run(tmp_path / "inline.mcap", IN_PROCESS)
    assert in_process["rms_error_deg"] == with_process["rms_error_deg"]
    assert session_digest(str(tmp_path / "inline.mcap")) == \
        session_digest(str(tmp_path / "process.mcap"))
    data = read_session(str(tmp_path / "inline.mcap"))
    assert not data.recovered and data.damage == []
    assert data.topic_counts["/drive/feedback"] == 600
    assert "recorder" not in data.metadata   # nothing dropped, nothing cut
    # finished: the stock indexed reader finds every message through the summary
    with open(tmp_path / "inline.mcap", "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages()) == \
            sum(data.topic_counts.values())


def test_no_writer_process_and_the_file_grows_as_the_loop_hands_over(tmp_path):
    path = tmp_path / "inline.mcap"
    rec = Recorder(path, wait_when_full=True, options=IN_PROCESS, chunk_span_s=1.0)
    rec.wait_ready()
    assert rec.writer_pid is None
    topic = rec.topic("/seq", SCHEMA)
    for k in range(3 * 2000):   # 3 s of session time: two chunks closed on the way
        topic.log(k * 500_000, {"k": k})
    rec.flush()
    size_before_close = path.stat().st_size
    stats = rec.close()
    assert size_before_close > 10_000
    assert stats.messages_written == 3 * 2000 and stats.messages_dropped == {}
    assert [m["k"] for _, m in read_session(path).topic("/seq")] == list(range(6000))


def test_a_sigkilled_loop_leaves_a_file_the_reader_recovers_with_counts(tmp_path, run_python):
    path = tmp_path / "killed.mcap"
    child = run_python(CHILD.format(path=str(path), limit=0))
    try:
        assert child.stdout.readline().split() == ["writer", "None"], child.stderr.read()
        last = -1
        while last < 12_000:   # 6 s of session time: several chunks on disk
            line = child.stdout.readline()
            assert line, child.stderr.read()
            last = int(line)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=10)
    data = read_session(str(path))
    assert data.recovered and "not finished" in str(data.error)   # never called intact
    assert [d.kind for d in data.damage] in ([], ["truncated"])   # cut in a chunk, or after
    ks = [m["k"] for _, m in data.topic("/seq")]
    assert ks == list(range(len(ks)))   # a gap-free prefix
    # lost at most the chunk in progress (1 s of session time) and the queue not handed over
    assert last - len(ks) <= 2000 + 512, (last, len(ks))


@pytest.mark.slow
def test_a_full_disk_ends_the_writing_with_the_true_count(tmp_path, run_python):
    path = tmp_path / "full.mcap"
    child = run_python(CHILD.format(path=str(path), limit=120_000))
    out, err = child.communicate(timeout=100)
    assert "Traceback" not in err, err
    lines = out.splitlines()
    stopped = next(line for line in lines if line.startswith("stopped "))
    assert "recording failed: File too large" in stopped and "the run stopped" in stopped
    closed = next(line for line in lines if line.startswith("closed "))
    count = int(closed.split("; ")[1].split()[0])
    assert count == sum(read_session(str(path)).topic_counts.values()) > 1000
    assert "later message(s) lost" in closed


@pytest.mark.parametrize("kwargs, refused", [
    ({"wait_when_full": False}, "in-process recording is for lockstep sessions"),
    ({"wait_when_full": True, "options": RecordingOptions(in_process=True, live="0")},
     "in-process recording has no live view"),
])
def test_in_process_recording_is_refused_where_it_cannot_keep_its_promises(tmp_path, kwargs,
                                                                           refused):
    options = kwargs.pop("options", IN_PROCESS)
    with pytest.raises(HilError, match=refused):
        Recorder(tmp_path / "x.mcap", options=options, **kwargs)
    assert not (tmp_path / "x.mcap").exists()


def test_a_file_that_cannot_be_opened_fails_at_the_start_in_one_line(tmp_path):
    folder = tmp_path / "taken"
    folder.mkdir()
    rec = Recorder(folder, wait_when_full=True, options=IN_PROCESS)
    with pytest.raises(RecordingError, match=r"the writer failed to start \(Is a directory"):
        rec.wait_ready()
    started = time.monotonic()
    with pytest.raises(RecordingError):
        rec.close()
    assert time.monotonic() - started < 5
