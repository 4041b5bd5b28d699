"""The recorder is part of the safety chain, tried from outside through the real file system:
a full disk (RLIMIT_FSIZE: the kernel refuses to grow the file) or a killed writer stops the
run within about a second, every relay of the bench at its safe level, exit 2, one line naming
the cause and the true count of what was recorded; an output path that cannot be written
refuses before any device is reached; two runs on one file never mix; a file with bytes after
its end is not called intact. The bench is pymodbus's own server (tests/pymodbus_bench.py)."""

import json
import os
import re
import resource
import signal
import time
from pathlib import Path

import pytest

from hil import api
from hil.bench.config import load_bench_config
from hil.core.recording.output import OutputError
from hil.core.recording.reader import read_session
from hil.core.recording.writer_fork import WRITER_NAME
from tests.cli import hil_here
from tests.pymodbus_bench import PymodbusBench, short_config, start_bench_run

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]

CONFIG = load_bench_config()


def bench_run(bench, out, *extra, cycles=10, config_dir=None, **popen):
    config = short_config(config_dir or Path(out).parent)
    return start_bench_run(bench.url, out, config, *extra, cycles=cycles, **popen)


def recorded(path):
    return sum(read_session(str(path)).topic_counts.values())


def check_failure_line(stderr, out, cause):
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    match = re.fullmatch(rf"hil: error: recording failed: {cause}.*; (\d+) message\(s\) "
                         rf"recorded in {re.escape(str(out))}.*", lines[0])
    assert match, lines[0]
    assert "Traceback" not in stderr
    return int(match.group(1))


def small_file_limit():
    # room for the file's start (its configuration metadata alone is about 18 kB) and for
    # several chunks, however many messages a loaded machine lets pile up in the first one
    resource.setrlimit(resource.RLIMIT_FSIZE, (120_000, 120_000))


def test_a_full_disk_stops_the_run_safely_with_the_true_count(tmp_path):
    out = tmp_path / "full.mcap"
    with PymodbusBench(CONFIG) as bench:
        run = bench_run(bench, out, preexec_fn=small_file_limit)
        _, stderr = run.communicate(timeout=120)
        assert run.returncode == 2, stderr
        assert not any(bench.relays().values())
    count = check_failure_line(stderr, out, "File too large")
    assert count == recorded(out) and count > 100
    first, last = read_session(str(out)).time_range_ns()
    assert (last - first) / 1e9 < 30  # the run was asked for 40 s: the full file ended it


def test_a_killed_writer_stops_the_run_within_a_second(tmp_path):
    out = tmp_path / "killed.mcap"
    with PymodbusBench(CONFIG) as bench:
        run = bench_run(bench, out)
        writer = None
        deadline = time.monotonic() + 30
        while writer is None and time.monotonic() < deadline:
            time.sleep(0.2)
            for pid in os.listdir("/proc"):
                if pid.isdigit():
                    try:  # the run's writer process: its child, by the name it goes by
                        comm = Path(f"/proc/{pid}/comm").read_text().strip()
                        parent = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")")[1]
                                     .split()[1])
                    except OSError:
                        continue
                    if comm == WRITER_NAME and parent == run.pid:
                        writer = int(pid)
        assert writer is not None
        while bench.meter_reads < 200:  # 2 s into the run
            time.sleep(0.05)
        os.kill(writer, signal.SIGKILL)
        killed = time.monotonic()
        reads_at_kill = bench.meter_reads
        _, stderr = run.communicate(timeout=30)
        assert run.returncode == 2, stderr
        # the loop stopped polling within ~1 s of the kill (100 polls a second)
        assert bench.meter_reads - reads_at_kill < 150, bench.meter_reads - reads_at_kill
        assert not any(bench.relays().values())
        assert time.monotonic() - killed < 10
    count = check_failure_line(stderr, out, r"the writer process was killed \(SIGKILL\)")
    assert count == recorded(out) and count > 0


@pytest.mark.parametrize(("out", "why"), [
    ("{tmp}", "is a folder"),
    ("{tmp}/a_file/x.mcap", "a_file is a file, not a folder"),
    ("/proc/hil-test/x.mcap", "cannot create (the|its) folder /proc/hil-test: "),
])
def test_an_unwritable_output_refuses_before_the_bench_is_reached(tmp_path, capfd, out, why):
    """The command line (``hil`` in this process) and the Python API alike."""
    (tmp_path / "a_file").write_text("not a folder")
    path = out.format(tmp=tmp_path)
    with PymodbusBench(CONFIG) as bench:
        run = hil_here(capfd, "bench", "run", "--controller", "bc", "--bench", bench.url,
                       "--config", short_config(tmp_path), "--out", path)
        stderr = run.stderr
        assert run.returncode == 2
        # the Python API checks the same before it opens the bench
        with pytest.raises(OutputError, match=why):
            api.run_bench("bc", bench=bench.url, out=path, realtime=True)
        assert bench.meter_reads == 0 and not any(bench.relays().values())
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and re.search(why, lines[0]), stderr
    assert lines[0].startswith("hil bench run: error: argument --out: ")


def test_two_runs_on_one_file_the_second_refuses_and_nothing_mixes(tmp_path):
    out = tmp_path / "one.mcap"
    with PymodbusBench(CONFIG) as bench:
        # the first run lasts 40 s, far beyond the second's start on a loaded machine; it is
        # interrupted once the second has been refused
        first = bench_run(bench, out, cycles=10)
        while bench.meter_reads < 50:
            time.sleep(0.05)
        second = bench_run(bench, out, cycles=1)
        _, stderr = second.communicate(timeout=60)
        assert first.poll() is None, first.communicate()[1]  # still writing the file
        assert second.returncode == 2, stderr
        assert f"session file {out} is being written by another run" in stderr
        first.send_signal(signal.SIGINT)
        assert first.wait(timeout=30) == 130, first.stderr.read()
    data = read_session(str(out))
    assert not data.recovered and not data.damage
    kinds = [event["kind"] for _, event in data.topic("/events")]
    assert kinds.count("session.start") == kinds.count("session.stop") == 1  # one run alone


def test_bytes_after_the_end_of_a_session_are_damage_not_intact(tmp_path, capfd):
    """A session of one 2 s cycle, recorded and reported by ``hil`` in this process (the
    session is what is looked at, not the process that wrote it)."""
    out = tmp_path / "s.mcap"
    config = short_config(tmp_path, period_s=2.0, dwell_s=0.5)
    with PymodbusBench(CONFIG) as bench:
        run = hil_here(capfd, "bench", "run", "--controller", "bc", "--bench", bench.url,
                       "--cycles", "1", "--config", config, "--out", out)
        assert run.returncode == 0, run.stderr
    with open(out, "ab") as file:
        file.write(b"\x89MCAP0\r\n" + bytes(100))  # another writer's start, mixed in
    report = hil_here(capfd, "report", out, "--json")
    summary = json.loads(report.stdout)
    assert summary["recovered"] is True
    assert [d["kind"] for d in summary["damage"]] == ["trailing"]
    assert "108 byte(s) after the end of the session" in summary["damage"][0]["reason"]
