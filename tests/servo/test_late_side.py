"""Stale feedback names the side that was late: the drive (its replies were not back when the
loop read them) or the loop (it did not keep its schedule for those ticks); the safety net
stays exactly as strict."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from hil.core.recording.reader import read_session
from hil.errors import HilError
from hil.servo.options import ServoRunOptions
from hil.servo.run import run_servo
from hil.servo.safety import SafetyMonitor, ServoSafety, judge_stale
from tests.cli import hil_here

PERIOD_S = 0.0005


def fresh(k: int, stale_from: int = 600) -> bool:
    """Three cycles of four stale from ``stale_from`` on."""
    return k < stale_from or k % 4 == 0


def feed(monitor: SafetyMonitor, late_us, ticks: int = 2000) -> int | None:
    """:func:`fresh`'s cycles with the loop's lateness ``late_us(k)``; the tick that trips."""
    for k in range(ticks):
        if monitor.check(k * PERIOD_S, 0.0, 0.0, 0.0, fresh(k), rtt_us=450.0,
                         late_us=late_us(k)) is not None:
            return k
    return None


def test_a_stale_share_stop_names_the_drive_when_the_loop_kept_its_schedule():
    monitor = SafetyMonitor(ServoSafety(), PERIOD_S)
    assert feed(monitor, lambda k: 3.0) is not None
    assert monitor.stopped is not None and "\n" not in monitor.stopped
    assert "cycles without fresh feedback (more than 50% in 200 ms): the drive was late" \
        in monitor.stopped
    assert "the loop was on time (0 of the" in monitor.stopped
    assert monitor.verdict is not None and monitor.verdict.side == "drive"


def test_a_stale_share_stop_names_the_loop_when_its_ticks_were_late():
    monitor = SafetyMonitor(ServoSafety(), PERIOD_S)
    assert feed(monitor, lambda k: 300.0 if k % 3 == 0 else 3.0) is not None
    assert monitor.stopped is not None and ": the loop was late (" in monitor.stopped
    assert "lateness p99 300 us" in monitor.stopped and "; the drive: " in monitor.stopped
    assert monitor.verdict is not None and monitor.verdict.side == "loop"


def test_a_drive_silent_for_many_cycles_is_the_drive_whatever_a_few_late_ticks():
    """A paused drive: 200 cycles in a row stale, while the loop had three late ticks among
    them (a busy machine): the cycles are the drive's."""
    monitor = SafetyMonitor(ServoSafety(), PERIOD_S)
    tripped = None
    for k in range(1000):
        late = 300.0 if k in (700, 750, 800) else 3.0
        if monitor.check(k * PERIOD_S, 0.0, 0.0, 0.0, k < 600, rtt_us=450.0,
                         late_us=late) is not None:
            tripped = k
            break
    assert tripped == 800  # the 201st stale cycle in a row
    assert monitor.verdict is not None and monitor.verdict.side == "drive"
    assert monitor.verdict.late_ticks == 3 and monitor.verdict.loop_stale == 5
    assert "the drive was late (201 replies" in (monitor.stopped or "")


def test_naming_the_side_leaves_the_net_exactly_as_strict():
    """The same cycles trip at the same tick, whatever the loop's lateness and the replies'
    times (the figures only name the side)."""
    named = feed(SafetyMonitor(ServoSafety(), PERIOD_S), lambda k: 250.0)
    plain = SafetyMonitor(ServoSafety(), PERIOD_S)
    tripped = next(k for k in range(2000)
                   if plain.check(k * PERIOD_S, 0.0, 0.0, 0.0, fresh(k)) is not None)
    assert named == tripped
    # the 201st stale cycle of the last 400 (three in four stale from tick 600 on)
    assert sum(not fresh(k) for k in range(tripped - 399, tripped + 1)) == 201
    assert sum(not fresh(k) for k in range(tripped - 400, tripped)) == 200
    loose = SafetyMonitor(ServoSafety(stale_share_max=0.8), PERIOD_S)
    assert feed(loose, lambda k: 3.0) is None  # three in four stale: within 80 %


def test_skipped_ticks_just_before_the_stale_cycles_count_against_the_loop():
    stale = [False, True, False, True, False, False]
    on_time = judge_stale(stale, [2.0] * 6, [450.0] * 6, PERIOD_S)
    assert (on_time.side, on_time.stale, on_time.ticks, on_time.late_ticks) == ("drive", 2, 4, 0)
    # tick 3 comes right after two skipped ones (1, 2, 5, 6, 7, 8 run)
    skipped = judge_stale(stale, [2.0] * 6, [450.0] * 6, PERIOD_S, [1, 2, 5, 6, 7, 8])
    assert (skipped.side, skipped.skipped, skipped.late_ticks) == ("loop", 2, 1)
    assert judge_stale([False] * 4, [900.0] * 4, [450.0] * 4, PERIOD_S).side == "none"


def _emulator_pid() -> int:
    """The drive emulator process a real-time run against ``emulated`` started."""
    for task in os.listdir(f"/proc/{os.getpid()}/task"):
        for child in Path(f"/proc/{os.getpid()}/task/{task}/children").read_text().split():
            if b"emulate\0drive" in Path(f"/proc/{child}/cmdline").read_bytes():
                return int(child)
    raise AssertionError("no drive emulator process")


@pytest.mark.slow
@pytest.mark.realtime
def test_an_emulator_paused_mid_run_is_named_as_the_late_side(tmp_path, capsys):
    """The drive emulator process stopped (SIGSTOP) for 0.4 s of a real-time run: the safety
    net stops the run and its message names the drive; `hil report` says the same."""
    config = tmp_path / "drive.toml"
    # only the safety net watches the pause: no link-loss give-up, no heartbeat or SYNC
    # watchdog in the drive that would end the run first
    config.write_text("[master]\nstale_cycles = 100000\nheartbeat_timeout_ms = 0\n"
                      "[emulator]\nsync_loss_timeout_ms = 5000\n")
    out = tmp_path / "paused.mcap"

    pausers: list[subprocess.Popen[bytes]] = []

    def pause(_master: object) -> None:
        # from a process of its own: a thread of the loop's process would take the loop's GIL
        # to send the signals, and make its ticks late
        pid = _emulator_pid()
        pausers.append(subprocess.Popen(
            ["sh", "-c", f"sleep 0.5; kill -STOP {pid}; sleep 0.4; kill -CONT {pid}"]))

    options = ServoRunOptions(controller="pid", realtime=True, duration_s=5.0, out=str(out),
                              drive_config=str(config))
    with pytest.raises(HilError) as stopped:
        run_servo(options, on_started=pause)
    pausers[0].wait(timeout=30)
    message = str(stopped.value)
    assert "cycles without fresh feedback" in message and "\n" not in message
    assert ": the drive was late (" in message and "the loop was on time" in message
    report = json.loads(hil_here(capsys, "report", str(out), "--json", cwd=tmp_path).stdout)
    feedback = report["feedback"]["/drive/feedback"]
    assert feedback["worst_window"]["late_side"] == "drive"
    assert feedback["worst_window"]["stale"] > 200  # what tripped the net: 201 of 400
    assert read_session(out).metadata["realtime.emulator"]["pid"] == str(
        report["realtime_helpers"]["emulator"]["pid"])


@pytest.mark.parametrize("cycles,window_ms", [(1, 10.0), (7, 1.0), (400, 20.0), (400, 200.0),
                                              (2000, 20.0)])
def test_the_worst_window_is_the_first_with_the_most_stale_cycles(cycles, window_ms):
    """``hil report``'s worst window: each window's count as a convolution gives it, the first
    of the largest taken."""
    import numpy as np

    from hil.servo.report import _worst_window

    rng = np.random.default_rng(cycles)
    stale = rng.random(cycles) < 0.3
    stale[cycles // 3: cycles // 3 + 15] = True  # a burst
    slots = np.arange(cycles)
    window = _worst_window(stale, np.zeros(cycles), np.full(cycles, 100.0), slots, PERIOD_S,
                           window_ms)
    size = min(cycles, max(1, round(window_ms / 1000 / PERIOD_S)))
    counts = np.convolve(stale.astype(np.int64), np.ones(size, np.int64), "valid")
    start = int(np.argmax(counts))
    assert (window["cycles"], window["stale"], window["t_s"]) == \
        (size, int(counts.max()), round(start * PERIOD_S, 4))
