"""The servo run's safety limits, on by default: the built-in controllers never reach them in
the papers' scenarios; a runaway controller is stopped within 50 ms of the breach, the drive
quick-stopped and disabled, the limit named on one line, exit status 2; each limit can be
moved for a run (--safety KEY=VALUE) and all of them switched off."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hil import api
from hil.core.recording.reader import read_session
from hil.errors import HilError
from hil.servo.run import ServoRunOptions, run_servo
from tests.cli import hil_here

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
RUNAWAY = textwrap.dedent("""
    class Runaway:
        '''Full current, whatever the axis does: a wrong controller.'''
        def __init__(self, reference, params):
            self.current = float(params.get("current", 1000.0))
        def step(self, position_deg, t_s):
            return self.current
""")


@pytest.mark.parametrize(("controller", "reference", "seconds"), [
    ("mpc", "sine:amplitude=2,frequency=10", 0.5),
    ("pid", "sine:amplitude=2,frequency=10", 0.5),
    ("pid", "disturbance:torque=1200,start=0.1,end=0.35", 0.6),
    ("mpc", "disturbance:torque=1200,start=0.1,end=0.35", 0.6),
    ("pid", "trapezoid:stroke=270,speed=60", 1.6),
])
def test_built_in_controllers_never_reach_the_default_limits(tmp_path, controller, reference,
                                                            seconds):
    kpis = api.run_servo(controller, reference=reference, duration_s=seconds,
                         out=str(tmp_path / "run.mcap"))
    assert kpis["stop_reason"] == "completed"


def runaway_file(tmp_path):
    path = tmp_path / "runaway.py"
    path.write_text(RUNAWAY)
    return f"{path}:Runaway"


def test_a_runaway_is_stopped_within_50_ms_of_the_breach_and_the_drive_is_safe(tmp_path):
    out = tmp_path / "runaway.mcap"
    options = ServoRunOptions(controller=runaway_file(tmp_path), reference="hold:position=0",
                              duration_s=5.0, out=str(out))
    stopped = []
    with pytest.raises(HilError) as error:
        run_servo(options, on_started=lambda master: stopped.append(master))
    message = str(error.value)
    assert "safety stop at t=" in message and "following error" in message
    assert "beyond 45 deg for more than 10 ms" in message and "\n" not in message
    assert stopped[0].emulator.node.state == "SWITCH ON DISABLED"
    data = read_session(str(out))
    command = data.arrays("/drive/command")
    breach = command["t_s"][np.argmax(np.abs(command["error_deg"]) > 45.0)]
    assert command["t_s"][-1] - breach <= 0.050
    events = [m for _, m in data.topic("/events")]
    assert [e["kind"] for e in events].count("safety.stop") == 1
    assert any(e["kind"] == "drive.safe_stop" for e in events)


@pytest.mark.parametrize(("safety", "named"), [
    ({"following_error_deg": 1e6, "velocity_max_deg_s": 100.0}, "velocity"),
    ({"following_error_deg": 1e6, "position_max_deg": 5.0}, "position"),
])
def test_each_limit_can_be_moved_for_a_run_and_stops_on_its_own(tmp_path, safety, named):
    with pytest.raises(HilError, match=f"safety stop at t=.*: {named}"):
        api.run_servo(runaway_file(tmp_path), reference="hold:position=0", duration_s=5.0,
                      drive_overrides={"safety": safety}, out=str(tmp_path / "x.mcap"))


@pytest.mark.realtime
def test_driving_blind_is_stopped_by_the_stale_share(tmp_path):
    config = tmp_path / "drive.toml"
    # the safe stop that follows, which the blind drive cannot confirm, gives up after 300 ms
    # instead of 3 s: what is tested is the stop
    config.write_text("[master]\nstale_cycles = 100000\nquick_stop_timeout_ms = 300\n"
                      "[emulator]\nsync_loss_timeout_ms = 5000\n")
    with (api.start_drive_emulator(config, faults=["drop_tpdo@0.3"], harden=True) as emulator,
          pytest.raises(HilError, match="cycles without fresh feedback")):
        api.run_servo("pid", drive=emulator.url, realtime=True, duration_s=5.0,
                      drive_config=str(config), out=str(tmp_path / "blind.mcap"))


def test_from_the_command_line_exit_2_and_the_limits_can_be_switched_off(tmp_path, capfd):
    """A safety stop and the limits switched off as ``hil`` processes; the refusals, more cases
    of --safety, run the command line in this process (:func:`hil_here`), from the same
    folder."""
    spec = runaway_file(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    argv = ("servo", "run", "--controller", spec, "--reference", "hold:position=0")

    def hil(*args):
        return subprocess.run([sys.executable, "-m", "hil", *argv, *args], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=120)

    stopped = hil("--duration", "3", "--out", "a.mcap")
    assert stopped.returncode == 2
    [line] = stopped.stderr.strip().splitlines()
    assert line.startswith("hil: error: safety stop at t=") and "a.mcap" in line
    loose = hil_here(capfd, *argv, "--duration", "0.3", "--safety", "enabled=false", "--out",
                     "b.mcap", cwd=tmp_path)
    assert loose.returncode == 2 and "--allow-looser-safety" in loose.stderr  # never silently
    free = hil("--duration", "0.3", "--safety", "enabled=false", "--allow-looser-safety",
               "--json", "--out", "b.mcap")
    assert free.returncode == 0, free.stderr
    assert "hil: warning: safety limits loosened by --safety: enabled true -> false" \
        in free.stderr
    bad = hil_here(capfd, *argv, "--duration", "0.3", "--safety", "following_error_dg=3",
                   "--out", "c.mcap", cwd=tmp_path)
    assert bad.returncode == 2 and "safety.following_error_dg" in bad.stderr


def first_stop(monitor, ticks):
    """The tick whose check first names a limit, and its line; ticks: (error, position,
    velocity, fresh) per tick, 1 ms apart."""
    for k, (error, position, velocity, fresh) in enumerate(ticks):
        stop = monitor.check(k * 1e-3, error, position, velocity, fresh, rtt_us=300.0,
                             late_us=5.0)
        if stop is not None:
            return k, stop
    return None, None


def test_each_limit_stops_at_the_tick_it_is_crossed_and_in_order():
    from hil.servo.safety import SafetyMonitor, ServoSafety

    limits = ServoSafety(following_error_deg=1.0, following_error_ms=3.0, stale_window_ms=10.0,
                         stale_share_max=0.5)
    calm = (0.0, 0.0, 0.0, True)
    # beyond the window for 3 ms, back in (the count starts again), then beyond for good
    ticks = [(2.0, 0, 0, True)] * 3 + [calm] + [(-2.0, 0, 0, True)] * 5
    assert first_stop(SafetyMonitor(limits, 1e-3), ticks)[0] == 7
    # the first limit crossed is named: the following error before the position and the speed
    k, stop = first_stop(SafetyMonitor(limits, 1e-3, axis="x"),
                         [(2.0, 0.0, 0.0, True)] * 3 + [(2.0, 1e5, 1e5, True)])
    assert k == 3 and stop.startswith("axis x: safety stop at t=0.0030 s: following error")
    for tick, named in (((0.0, 1e5, 1e5, True), "position 100000.00 deg outside"),
                        ((0.0, 0.0, -1e5, True), "velocity 100000.0 deg/s above"),
                        ((0.0, 0.0, np.inf, True), "velocity inf deg/s above"),
                        ((0.0, 0.0, np.nan, True), "non-finite feedback (position 0.0, "
                                                   "velocity nan)")):
        k, stop = first_stop(SafetyMonitor(limits, 1e-3), [calm, tick])
        assert k == 1 and named in stop, stop
    # the stale share: over half of a full window of 10 cycles, not before the window is full
    stale = (0.0, 0.0, 0.0, False)
    assert first_stop(SafetyMonitor(limits, 1e-3), [stale] * 9)[0] is None
    assert first_stop(SafetyMonitor(limits, 1e-3), [stale] * 10)[0] == 9
    # a stale cycle leaving the window is no longer counted: 5 of 10 is not over half
    assert first_stop(SafetyMonitor(limits, 1e-3), ([stale] * 5 + [calm] * 5) * 4)[0] is None
    tightened = SafetyMonitor(limits, 1e-3)
    assert first_stop(tightened, ([stale] * 5 + [calm] * 5) * 2)[0] is None
    tightened.tighten("stale_share_max", 0.3)  # the oldest stale cycle leaves: 4 of 10
    assert first_stop(tightened, [calm])[0] == 0
    assert tightened.verdict is not None and tightened.verdict.stale == 4
    assert SafetyMonitor(ServoSafety(enabled=False), 1e-3).check(0.0, 1e9, 1e9, 1e9,
                                                                  False) is None
