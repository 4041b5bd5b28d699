"""What you configure is what runs, turns included: the following error is multi-turn (a
safety window or a limit of half a turn or more holds), a run can start where the axis stands
(``from_here``), a controller is given the position its contract asks for, and the drive's
safe stop after the ticks is in the session (``/drive/stop``).

``hil servo run`` runs in a subprocess from a folder outside the repository; the Python API
where the contract is a Python one (a controller's ``position_input``, ``from_here``). The
runaway pushes a constant 800 mA: about 210 deg of error after 0.43 s, at about 970 deg/s
(under the default velocity limit, so the following error is what stops it). Each flag runs
from outside at least once; its other cases run ``main`` in this process, in the same folder
(``hil_here``: the same exit status and output, without a second of interpreter start)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hil import api
from hil.core.recording.reader import read_session
from hil.errors import ConfigError, HilError
from hil.protocols.cia402 import QUICK_STOP_ACTIVE, SWITCH_ON_DISABLED, state_of
from tests.cli import hil_here as in_process
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

ROOT = Path(__file__).resolve().parents[2]
PERIOD_NS = 500_000
CONTROLLERS = textwrap.dedent("""
    import numpy as np

    class Runaway:
        '''800 mA, whatever the axis does: a wrong controller.'''
        def __init__(self, reference, params):
            pass
        def step(self, position_deg, t_s):
            return 800.0

    class TurnsPd:
        '''A PD on the multi-turn error: it needs the multi-turn position.'''
        position_input = "unwrapped"
        seen = []
        def __init__(self, reference, params):
            self.reference = reference
            self.last = None
        def step(self, position_deg, t_s):
            TurnsPd.seen.append(position_deg)
            error = float(self.reference.position(t_s)) - position_deg
            rate = 0.0 if self.last is None else (error - self.last) / 0.0005
            self.last = error
            return 300.0 * error + 6.0 * rate

    class WrappedTurnsPd(TurnsPd):
        '''The same PD given the spindle's angle (position % 360): wrong past one turn.'''
        position_input = "wrapped"

    class Misspelt(TurnsPd):
        position_input = "unwraped"

    class SamplesWhenBuilt(TurnsPd):
        '''Reads its reference in __init__, before the axis' start is known.'''
        def __init__(self, reference, params):
            super().__init__(reference, params)
            self.start = reference.position(0.0)

    class TurnsPdAxes:
        '''Every axis at once, multi-turn.'''
        multi_axis = True
        position_input = "unwrapped"
        seen = []
        def __init__(self, references, params):
            self.references = references
        def step(self, positions_deg, t_s):
            TurnsPdAxes.seen.append(np.array(positions_deg))
            wanted = np.array([float(r.position(t_s)) for r in self.references])
            return 300.0 * (wanted - positions_deg)
""")


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """A user's folder outside the repository with the controllers above, importable."""
    (tmp_path / "mine.py").write_text(CONTROLLERS)
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def hil(folder: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=folder,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True,
                          text=True, timeout=120)


def hil_here(folder, capsys, *args):
    """``hil ARGS`` run by ``main`` in this process from ``folder``, as :func:`hil` reports it."""
    return in_process(capsys, *args, cwd=folder)


def runaway(folder: Path, config: str, *args: str,
            capsys: pytest.CaptureFixture[str] | None = None
            ) -> subprocess.CompletedProcess[str]:
    """The runaway from rest at 0 deg, holding 0, its [safety] in a --config file: from
    outside, or in this process given ``capsys``."""
    (folder / "drive.toml").write_text(config)
    argv = ("servo", "run", "--controller", "mine.py:Runaway", "--reference",
            "hold:position=0", "--config", "drive.toml", *args)
    return hil(folder, *argv) if capsys is None else hil_here(folder, capsys, *argv)


@pytest.fixture(scope="module")
def stopped_runaway(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """The runaway stopped by a 200 deg window, run once for the tests that read it: its
    folder (the session ``runaway.mcap``) and the finished command."""
    folder = tmp_path_factory.mktemp("runaway")
    (folder / "mine.py").write_text(CONTROLLERS)
    done = runaway(folder, "[safety]\nfollowing_error_deg = 200.0\n", "--duration", "3",
                   "--out", "runaway.mcap")
    return folder, done


def kpis_of(path: Path) -> dict:
    return json.loads(read_session(path).metadata["kpis"]["json"])


def test_a_runaway_past_half_a_turn_is_stopped_by_a_200_deg_window(stopped_runaway):
    folder, done = stopped_runaway
    assert done.returncode == 2, done.stderr
    [line] = done.stderr.strip().splitlines()
    assert line.startswith("hil: error: safety stop at t=")
    measured = float(line.split("following error ")[1].split(" deg beyond 200 deg")[0])
    assert 200.0 < measured < 230.0
    kpis = kpis_of(folder / "runaway.mcap")
    assert kpis["max_error_deg"] == pytest.approx(measured, abs=0.01)
    assert kpis["max_error_deg"] > 200.0 and kpis["ticks"] < 6000  # stopped, not completed


def test_the_stop_after_a_safety_stop_is_recorded_until_the_axis_stands(stopped_runaway,
                                                                         capsys):
    folder, _ = stopped_runaway
    data = read_session(folder / "runaway.mcap")
    last_tick_ns, last = data.topic("/drive/feedback")[-1]
    stop = data.topic("/drive/stop")
    times = [t for t, _ in stop]
    assert times == [last_tick_ns + (i + 1) * PERIOD_NS for i in range(len(stop))]
    first, final = stop[0][1], stop[-1][1]
    # the last tick read cycle c and sent the run's last command in c + 1; the stop follows
    assert first["cycle"] == last["cycle"] + 2
    assert first["velocity_deg_s"] > 500.0  # it was running away...
    states = [state_of(m["statusword"]) for _, m in stop]
    braking = states.count(QUICK_STOP_ACTIVE)
    assert braking > 100 and states[braking:] == [SWITCH_ON_DISABLED] * (len(states) - braking)
    assert abs(final["velocity_deg_s"]) < 2.5  # ...braked to standstill, then disabled
    assert final["position_deg"] > first["position_deg"] + 20.0
    # and the command line reads it (``main`` in this process: ``report --topic`` runs from
    # outside in tests/test_first_hour.py)
    shown = hil_here(folder, capsys, "report", "runaway.mcap", "--topic", "/drive/stop")
    assert shown.returncode == 0, shown.stderr
    lines = [json.loads(line) for line in shown.stdout.splitlines()]
    assert [m["cycle"] for m in lines] == [m["cycle"] for _, m in stop]


def test_a_limit_of_200_deg_on_the_error_is_violated_by_a_runaway(folder, capsys):
    free = "[safety]\nenabled = false\n"
    kpi = runaway(folder, free, "--duration", "0.6", "--limit", "max_error_deg<=200",
                  "--out", "kpi.mcap")
    assert kpi.returncode == 1, kpi.stderr
    assert "limit violated: max_error_deg<=200" in kpi.stderr
    assert kpis_of(folder / "kpi.mcap")["max_error_deg"] > 300.0
    tick = runaway(folder, free, "--duration", "0.6", "--limit", "abs_error_deg<=200",
                   "--out", "tick.mcap", capsys=capsys)
    assert tick.returncode == 1, tick.stderr
    assert "limit violated: abs_error_deg<=200" in tick.stderr
    command = read_session(folder / "tick.mcap").arrays("/drive/command")
    assert np.abs(command["error_deg"][:-1]).max() <= 200.0 < abs(command["error_deg"][-1])


def test_the_reference_runs_on_the_turn_nearest_the_start_and_from_here_from_the_start(
        folder):
    """Two runs on one emulator process: the first leaves the axis near 270 deg. Holding 0
    from there, the nearest turn is 360: 90 deg away, stopped at once. From here, the sine
    starts where the axis stands and is tracked (0.25 s of it: its start is what is
    checked)."""
    with api.start_drive_emulator() as drive:
        first = api.run_servo("pid", drive=drive.url, reference="trapezoid:stroke=270",
                              duration_s=1.2, out=str(folder / "first.mcap"))
        assert first["stop_reason"] == "completed"
        with pytest.raises(HilError, match=r"t=0\.0100 s: following error 9\d\.\d\d deg"):
            api.run_servo("pid", drive=drive.url, reference="hold:position=0",
                          duration_s=0.5, out=str(folder / "leaked.mcap"))
        leaked = read_session(folder / "leaked.mcap")
        assert leaked.arrays("/drive/command")["reference_deg"][0] == 360.0
        here = api.run_servo("pid", drive=drive.url, reference="sine:amplitude=2,frequency=1",
                             duration_s=0.25, from_here=True, out=str(folder / "here.mcap"))
    assert here["stop_reason"] == "completed" and here["max_error_deg"] < 1.0
    data = read_session(folder / "here.mcap")
    start = data.arrays("/drive/feedback")["position_deg"][0]
    assert 260.0 < start < 280.0
    assert data.arrays("/drive/command")["reference_deg"][0] == start
    placed = data.metadata["reference"]
    assert placed["placed"] == "from here" and float(placed["offset_deg"]) == start


def test_from_here_on_two_axes_runs_the_circle_from_where_they_stand(folder):
    # two axes fit one 1 Mbit/s bus at 1 kHz (the PID's integral time made long enough for it);
    # 0.2 s of the circle: its start is what is checked
    config = folder / "two.toml"
    config.write_text("[master]\ncycle_period_us = 1000\n")
    with drive_served_here(node=[1, 2]) as drive:
        api.run_servo("pid", {"ti_us": 8000}, drive=drive.url, axes="x=1,y=2",
                      drive_config=str(config),
                      reference="trapezoid:stroke=270", duration_s=1.2,
                      out=str(folder / "away.mcap"))
        kpis = api.run_servo("mpc", drive=drive.url, axes="x=1,y=2", from_here=True,
                             drive_config=str(config), reference="circle:radius=2,feed=20",
                             duration_s=0.2, out=str(folder / "circle.mcap"))
    assert kpis["stop_reason"] == "completed"
    assert kpis["contour"]["max_contour_error_deg"] < 2.0
    assert all(axis["max_error_deg"] < 2.0 for axis in kpis["axes"].values())
    data = read_session(folder / "circle.mcap")
    for name in ("x", "y"):
        start = data.arrays(f"/axis/{name}/feedback")["position_deg"][0]
        assert 260.0 < start < 280.0
        assert float(data.metadata[f"reference/{name}"]["offset_deg"]) == start
        assert len(data.topic(f"/axis/{name}/stop")) >= 2  # each axis' stop, recorded


def test_a_controller_asking_for_unwrapped_positions_gets_the_turns(folder):
    from mine import TurnsPd, WrappedTurnsPd

    TurnsPd.seen.clear()
    kpis = api.run_servo(TurnsPd, reference="trapezoid:stroke=720,speed=120", duration_s=2.0,
                         out=str(folder / "turns.mcap"))
    assert kpis["stop_reason"] == "completed" and kpis["max_error_deg"] < 5.0
    feedback = read_session(folder / "turns.mcap").arrays("/drive/feedback")["position_deg"]
    assert np.array_equal(np.array(TurnsPd.seen), feedback)  # the multi-turn position itself
    assert feedback.max() > 700.0
    TurnsPd.seen.clear()
    with pytest.raises(HilError, match=r"safety stop at t=.*following error"):
        api.run_servo(WrappedTurnsPd, reference="trapezoid:stroke=720,speed=120",
                      duration_s=2.0, out=str(folder / "wrapped.mcap"))
    assert max(TurnsPd.seen) < 360.0  # given position % 360, it lost the turn
    feedback = read_session(folder / "wrapped.mcap").arrays("/drive/feedback")["position_deg"]
    assert np.array_equal(np.array(TurnsPd.seen), feedback[:len(TurnsPd.seen)] % 360.0)


def test_a_multi_axis_controller_asking_for_unwrapped_positions_gets_the_turns(folder):
    from mine import TurnsPdAxes

    TurnsPdAxes.seen.clear()
    kpis = api.run_servo(TurnsPdAxes, axes="x=1,y=2", reference="trapezoid:stroke=720,speed=120",
                         duration_s=2.0, out=str(folder / "axes.mcap"))
    assert kpis["stop_reason"] == "completed"
    seen = np.array(TurnsPdAxes.seen)
    data = read_session(folder / "axes.mcap")
    for i, name in enumerate(("x", "y")):
        feedback = data.arrays(f"/axis/{name}/feedback")["position_deg"]
        assert np.array_equal(seen[:, i], feedback) and feedback.max() > 700.0


def test_a_bad_position_input_or_a_reference_read_when_built_is_one_clear_line(folder,
                                                                                capsys):
    def outside(*args: str) -> subprocess.CompletedProcess[str]:
        return hil(folder, *args)

    def here(*args: str) -> subprocess.CompletedProcess[str]:
        return hil_here(folder, capsys, *args)

    for name, message, run in (("Misspelt", "position_input = 'unwraped': a servo controller "
                                            "takes 'wrapped'", outside),
                               ("SamplesWhenBuilt", "a controller samples it in step(), not "
                                                    "when it is built", here)):
        done = run("servo", "run", "--controller", f"mine.py:{name}", "--duration", "0.1",
                   "--out", f"{name}.mcap")
        assert done.returncode == 2
        [line] = done.stderr.strip().splitlines()
        assert line.startswith("hil: error: ") and message in line
        assert not (folder / f"{name}.mcap").exists()  # nothing ran: no session left
    with pytest.raises(ConfigError, match=r"controller '.*mine.py:Misspelt': position_input"):
        api.run_servo(f"{folder / 'mine.py'}:Misspelt", duration_s=0.1,
                      out=str(folder / "api.mcap"))
