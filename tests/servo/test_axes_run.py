"""``hil servo run --axes``: several axes on one bus, from the command line as a user runs
it; a circular test on two emulated axes, one SYNC per tick for all, a stop for all. Each
flag runs from outside at least once; its other cases run ``main`` in this process, in the same
folder (``hil_here``: the same exit status and output, without a second of interpreter start)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from hil.core.recording.reader import read_session
from tests.cli import hil_here as in_process
from tests.drive_processes import patient_watchdogs

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def hil(cwd, *args):
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, capture_output=True,
                          text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=180)


def hil_here(cwd, capsys, *args):
    """``hil ARGS`` run by ``main`` in this process from ``cwd``, as :func:`hil` reports it."""
    return in_process(capsys, *args, cwd=cwd)


def test_a_circular_test_on_two_axes_reports_each_axis_and_the_contour_error(tmp_path, capsys):
    done = hil(tmp_path, "servo", "run", "--axes", "x=1,y=2", "--controller", "mpc",
               "--reference", "circle:radius=2,feed=20", "--duration", "0.5", "--settle",
               "0.1", "--out", "circle.mcap", "--json")
    assert done.returncode == 0, done.stderr
    kpis = json.loads(done.stdout)
    assert set(kpis["axes"]) == {"x", "y"} and kpis["ticks"] == 1000
    assert kpis["sync_cycles"] == 1000  # one SYNC a tick for both axes
    for axis in kpis["axes"].values():
        assert axis["max_error_deg"] < 0.05 and axis["stale_feedback"] == 0
        assert axis["late_frames"] == 0  # the set-up's TPDOs are no cycle's answer
    contour = kpis["contour"]
    assert contour["radius_deg"] == 2.0 and 0 < contour["max_contour_error_deg"] < 0.05
    data = read_session(tmp_path / "circle.mcap")
    x = [m for _, m in data.topic("/axis/x/feedback")]
    y = [m for _, m in data.topic("/axis/y/feedback")]
    assert len(x) == len(y) == 1000
    assert [m["cycle"] for m in x] == [m["cycle"] for m in y]  # the same SYNC, tick by tick
    # the axes drew the circle: the recorded points lie on it, as /path/contour says
    points = np.array([(m["position_deg"], n["position_deg"]) for m, n in zip(x, y,
                                                                              strict=True)])
    radius = np.hypot(points[200:, 0] + 2.0, points[200:, 1])
    assert np.abs(radius - 2.0).max() < 0.05
    # two axes do not fit 2 kHz on a real 1 Mbit/s bus: said once (the emulated one has no
    # bitrate), with the plan in the metadata
    warnings = [m for _, m in data.topic("/events") if m["kind"] == "bus.plan"]
    assert len(warnings) == 1 and "2 axes need" in warnings[0]["message"]
    plans = json.loads(data.metadata["bus_plan"]["json"])["buses"]
    assert [(p["url"], p["axes"], p["axis_names"]) for p in plans] == [("emulated", 2, ["x", "y"])]
    assert plans[0]["bus_time_us"] > plans[0]["period_us"] == 500  # the one figure
    contour_topic = [m for _, m in data.topic("/path/contour")]
    assert len(contour_topic) == 1000
    # one loop task ticks every axis and the bus (the loop's bookkeeping once a tick, not
    # once an axis), timed as the one axis of a run that names none
    assert sorted(t for t in data.topic_counts if t.startswith("/loop/")) == \
        ["/loop/servo/timing"]
    assert json.loads(data.metadata["loop"]["servo"])["runs"] == 1000
    assert max(abs(m["contour_error_deg"]) for m in contour_topic[200:]) == \
        pytest.approx(contour["max_contour_error_deg"], rel=1e-5)
    # the human summary names each axis and the contour error
    text = hil_here(tmp_path, capsys, "servo", "run", "--axes", "x=1,y=2", "--controller", "pid",
                    "--reference", "circle:radius=2,feed=20", "--duration", "0.2", "--out",
                    "pid.mcap")
    assert text.returncode == 0, text.stderr
    assert "axis x (node 1)" in text.stdout and "axis y (node 2)" in text.stdout
    assert "contour error (circle of 2 deg)" in text.stdout


PD_CONTROLLER = """
class PdPosition:
    def __init__(self, reference, params):
        self.reference = reference
        self.kp, self.kd = float(params.get("kp", 300.0)), float(params.get("kd", 6.0))
        self.last = None

    def step(self, position_deg, t_s):
        error = (float(self.reference.position(t_s)) - position_deg + 180.0) % 360.0 - 180.0
        rate = 0.0 if self.last is None else (error - self.last[1]) / (t_s - self.last[0])
        self.last = (t_s, error)
        return self.kp * error + self.kd * rate
"""


def _contour(tmp_path, name, *params, capsys=None):
    """The contour error after a settling turn: from outside, or in this process given
    ``capsys``."""
    argv = ("servo", "run", "--axes", "x=1,y=2", "--controller", "pd.py:PdPosition", *params,
            "--reference", "circle:radius=2,feed=20", "--duration", "1.2", "--out",
            f"{name}.mcap", "--quiet")
    done = hil(tmp_path, *argv) if capsys is None else hil_here(tmp_path, capsys, *argv)
    assert done.returncode == 0, done.stderr
    rows = [m for _, m in read_session(tmp_path / f"{name}.mcap").topic("/path/contour")]
    return np.array([m["contour_error_deg"] for m in rows[800:]])  # after a settling turn


def test_a_gain_mismatch_between_axes_shows_as_an_ellipse(tmp_path, capsys):
    """The same gains on both axes lag both alike: the circle shrinks, evenly all round.
    A lower gain on y lags y more: the path becomes an ellipse, its contour error swings
    twice per turn. --param y.kp sets axis y's gain only."""
    (tmp_path / "pd.py").write_text(PD_CONTROLLER)
    matched = _contour(tmp_path, "matched", "--param", "kp=300", capsys=capsys)
    mismatched = _contour(tmp_path, "mismatched", "--param", "kp=300", "--param", "y.kp=100")
    swing_matched = matched.max() - matched.min()
    swing_mismatched = mismatched.max() - mismatched.min()
    assert swing_mismatched > 5 * swing_matched, (swing_matched, swing_mismatched)
    # twice per turn: the swing's dominant frequency is twice the path's (20 deg/s on 2 deg)
    spectrum = np.abs(np.fft.rfft(mismatched - mismatched.mean()))
    frequencies = np.fft.rfftfreq(mismatched.size, 500e-6)
    assert frequencies[np.argmax(spectrum)] == pytest.approx(2 * 10 / (2 * np.pi), rel=0.35)
    wrong = hil_here(tmp_path, capsys, "servo", "run", "--axes", "x=1,y=2", "--controller",
                     "pd.py:PdPosition", "--param", "z.kp=1", "--out", "z.mcap")
    assert wrong.returncode == 2 and "no axis 'z'" in wrong.stderr


def test_a_safety_stop_on_one_axis_stops_every_axis(tmp_path, capsys):
    done = hil_here(tmp_path, capsys, "servo", "run", "--axes", "x=1,y=2,z=3", "--controller",
                    "pid", "--reference", "sine:amplitude=20,frequency=1", "--duration", "1",
                    "--safety", "following_error_deg=1", "--out", "stop.mcap")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "safety stop" in done.stderr and "following error" in done.stderr
    events = [m for _, m in read_session(tmp_path / "stop.mcap").topic("/events")]
    stopped = sorted(m["source"] for m in events if m["kind"] == "drive.safe_stop")
    assert stopped == ["drive1", "drive2", "drive3"]  # every axis, not only the one that tripped
    assert all(m["data"]["state"] == "SWITCH ON DISABLED" for m in events
               if m["kind"] == "drive.safe_stop")


def test_limits_name_an_axis_or_the_path(tmp_path, capsys):
    run = ("servo", "run", "--axes", "x=1,y=2", "--controller", "mpc", "--reference",
           "circle:radius=2,feed=20", "--duration", "0.15", "--out", "lim.mcap", "--json")
    holds = hil(tmp_path, *run, "--limit", "contour.max_contour_error_deg<=0.05",
                "--limit", "abs_error_deg<=0.2")  # a per-tick signal: on every axis
    assert holds.returncode == 0, holds.stderr
    assert json.loads(holds.stdout)["passed"] is True
    violated = hil_here(tmp_path, capsys, *run, "--limit", "axes.y.max_error_deg<=0.0001")
    assert violated.returncode == 1
    assert "limit violated: axes.y.max_error_deg<=0.0001" in violated.stderr


def test_axes_from_the_drive_config(tmp_path, capsys):
    config = tmp_path / "axes.toml"
    config.write_text('[[axis]]\nname = "x"\nnode = 1\n\n[[axis]]\nname = "c"\nnode = 5\n')
    # in this process: --config runs from outside in
    # test_an_installed_drive_scheme_opens_one_axis_or_several
    done = hil_here(tmp_path, capsys, "servo", "run", "--config", str(config), "--controller",
                    "pid", "--duration", "0.1", "--out", "cfg.mcap", "--json")
    assert done.returncode == 0, done.stderr
    kpis = json.loads(done.stdout)
    assert {name: axis["node"] for name, axis in kpis["axes"].items()} == {"x": 1, "c": 5}
    for body, problem in (('[[axis]]\nname = "x"\n', "missing key 'axis[0].node'"),
                          ('[[axis]]\nname = "X"\nnode = 1\n', "key 'axis[0].name'"),
                          ('[[axis]]\nname = "x"\nnode = 1\nspeed = 2\n',
                           "unknown key 'axis[0].speed'"),
                          ('[[axis]]\nname = "x"\nnode = 1\n', "name two axes or more")):
        config.write_text(body)
        bad = hil_here(tmp_path, capsys, "servo", "run", "--config", str(config),
                       "--controller", "pid", "--out", "bad.mcap")
        assert bad.returncode == 2 and problem in bad.stderr, bad.stderr


@pytest.mark.parametrize("args, problem, outside", [
    (["--axes", "x=1"], "name two axes or more", True),
    (["--axes", "x=1,x=2"], "a name given twice", False),
    (["--axes", "x=1,y=1"], "a node given twice", False),
    (["--axes", "X=1,y=200"], "is not NAME=NODE", False),
    (["--axes", "x=1,y=2,z=3", "--reference", "circle:radius=2"], "a circle needs two axes",
     False),
    (["--axes", "x=1,y=2", "--reference", "circle:radius=-1"], "radius must be a positive",
     False),
    (["--axes", "x=1,y=2", "--limit", "max_error_deg<=1"], "KPIs: axes, ticks", False),
    (["--axes", "x=1,y=2", "--drive", "virtual://plan"], "the bus plan does not fit", False),
])
def test_bad_axes_are_one_line_before_anything_runs(tmp_path, capsys, args, problem, outside):
    """The first case from outside (``outside``), the others in this process."""
    argv = ("servo", "run", "--controller", "pid", "--out", "bad.mcap", *args)
    done = hil(tmp_path, *argv) if outside else hil_here(tmp_path, capsys, *argv)
    assert done.returncode == 2 and problem in done.stderr, done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "bad.mcap").exists()


@pytest.mark.realtime
def test_two_axes_in_real_time_with_the_built_in_emulator(tmp_path, capsys):
    """``--realtime`` with the built-in emulator and two axes: the emulated drives in a
    process of their own (one node per axis, on socketcand), 1 kHz in real time, both axes
    recorded tick by tick on the same SYNCs. Two emulated drives in Python on a shared 2-core
    machine miss many deadlines: the link and the stale-share limit are made patient, so what
    is checked is the plumbing, and stale feedback makes it exit 3."""
    config = tmp_path / "patient.toml"
    config.write_text(patient_watchdogs("cycle_period_us = 1000\n", "enabled = false\n"))
    done = hil_here(tmp_path, capsys, "servo", "run", "--axes", "x=1,y=2", "--controller",
                    "pid", "--param", "ti_us=8000", "--reference", "circle:radius=2,feed=20",
                    "--duration", "0.5", "--realtime", "--config", str(config), "--out",
                    "rt.mcap", "--json")
    assert done.returncode in (0, 3), done.stderr
    kpis = json.loads(done.stdout)
    assert kpis["clock"] == "realtime" and kpis["sync_cycles"] == kpis["ticks"] > 450
    assert kpis["buses"] == ["emulated"]
    data = read_session(tmp_path / "rt.mcap")
    cycles = {name: [m["cycle"] for _, m in data.topic(f"/axis/{name}/feedback")]
              for name in ("x", "y")}
    assert cycles["x"] == cycles["y"] and len(cycles["x"]) == kpis["ticks"]
    started = [e for _, e in data.topic("/events") if e["kind"] == "emulator.process"]
    assert len(started) == 1  # one emulator process serves both axes


def test_can_log_with_two_axes_holds_both_drives_frames(tmp_path, capsys):
    """``--can-log`` with two axes: every frame of the bus, read back by python-can's own
    reader: each axis' RPDO and TPDOs, one SYNC a tick for both."""
    import can

    done = hil(tmp_path, "servo", "run", "--axes", "x=1,y=2", "--controller", "pid",
               "--duration", "0.05", "--can-log", "frames.asc", "--out", "log.mcap", "--json")
    assert done.returncode == 0, done.stderr
    kpis = json.loads(done.stdout)
    ids = [message.arbitration_id for message in can.LogReader(str(tmp_path / "frames.asc"))]
    for node in (1, 2):
        assert 0x200 + node in ids and 0x180 + node in ids  # RPDO1 out, TPDO1 back
    syncs = ids.count(0x080)
    assert syncs >= kpis["sync_cycles"] == kpis["ticks"] == 100


def test_an_axis_own_safety_limit_stops_the_run_and_cannot_loosen_the_run_s(tmp_path, capsys):
    """``[[axis]]`` with its own ``safety`` table: axis x's tighter following-error limit
    stops the run (exit 2, every axis in its safe state); axis y asks for a looser one than
    ``[safety]``, and the run's holds for it (recorded as it ran)."""
    config = tmp_path / "axes.toml"
    config.write_text(
        "[safety]\nfollowing_error_deg = 30.0\n"
        "[[axis]]\nname = \"x\"\nnode = 1\n[axis.safety]\nfollowing_error_deg = 0.05\n"
        "following_error_ms = 1.0\n"
        "[[axis]]\nname = \"y\"\nnode = 2\n[axis.safety]\nfollowing_error_deg = 90.0\n")
    done = hil_here(tmp_path, capsys, "servo", "run", "--config", str(config),
                    "--controller", "pid", "--reference", "sine:amplitude=20,frequency=2",
                    "--duration", "1.0", "--out", "safe.mcap", "--json")
    assert done.returncode == 2, done.stderr
    assert "following error" in done.stderr
    data = read_session(tmp_path / "safe.mcap")
    stops = [e for _, e in data.topic("/events") if e["kind"] == "safety.stop"]
    assert stops and all(e["message"].startswith("axis x: safety stop") for e in stops)
    axes = {a["name"]: a for a in json.loads(data.metadata["config"]["json"])["servo"]["axes"]}
    assert axes["x"]["safety"]["following_error_deg"] == 0.05
    assert axes["y"]["safety"]["following_error_deg"] == 30.0  # the run's: not loosened


class CoupledPd:
    """A multi-axis controller: every axis' position at once, every axis' current at once."""

    multi_axis = True
    calls = 0

    def __init__(self, references, params):
        self.references = references
        self.kp = float(params.get("kp", 300.0))

    def step(self, positions_deg, t_s):
        CoupledPd.calls += 1
        assert positions_deg.shape == (len(self.references),)
        wanted = np.array([float(r.position(t_s)) for r in self.references])
        return self.kp * ((wanted - positions_deg + 180.0) % 360.0 - 180.0)


class WrongShape(CoupledPd):
    def step(self, positions_deg, t_s):
        return [0.0]


def test_a_multi_axis_controller_is_stepped_once_a_tick_with_every_axis(tmp_path):
    from hil import api
    from hil.errors import ControllerError

    CoupledPd.calls = 0
    kpis = api.run_servo(CoupledPd, {"kp": 300}, axes="x=1,y=2",
                         reference="circle:radius=2,feed=20", duration_s=0.1,
                         out=str(tmp_path / "coupled.mcap"))
    assert CoupledPd.calls == kpis["ticks"] == 200  # once a tick, not once per axis
    assert kpis["stop_reason"] == "completed" and kpis["contour"]["max_contour_error_deg"] < 2.0
    with pytest.raises(ControllerError, match=r"one current per axis \(2\), got shape \(1,\)"):
        api.run_servo(WrongShape, axes="x=1,y=2", duration_s=0.01,
                      out=str(tmp_path / "wrong.mcap"))



class Answers:
    """Steps each axis to ``kinds[name]`` of a current: the step's answer as that type."""

    kinds: ClassVar[dict[str, Any]] = {}

    def __init__(self, reference, params):
        self.kind = self.kinds[params.get("kind", "float")]

    def step(self, position_deg, t_s):
        return self.kind(10.0)


class Milliamps(float):
    """A float of another class: taken as the float it is."""


@pytest.mark.parametrize("kind", ["float", "int", "float64", "float32", "subclass"])
def test_every_kind_of_number_a_step_returns_is_the_float_it_is(tmp_path, kind):
    """A step's finite float is taken as it is; any other number as its float, on every axis
    as with one."""
    from hil import api

    Answers.kinds = {"float": float, "int": int, "float64": np.float64,
                     "float32": np.float32, "subclass": Milliamps}
    for axes in (None, "x=1,y=2"):
        out = tmp_path / f"{kind}-{axes is not None}.mcap"
        kpis = api.run_servo(Answers, {"kind": kind}, axes=axes, duration_s=0.01, out=str(out))
        assert kpis["stop_reason"] == "completed"
        session = read_session(out)
        for topic in ("/drive/command",) if axes is None else ("/axis/x/command",
                                                              "/axis/y/command"):
            assert {m["command_mA"] for _, m in session.topic(topic)} == {10.0}


@pytest.mark.parametrize(("kind", "got"), [
    ("nan", "float nan"), ("inf", "float -inf"), ("bool", "bool True"), ("text", "str '10.0'"),
    ("none", "NoneType None")])
def test_a_step_that_is_not_a_finite_number_stops_every_axis(tmp_path, kind, got):
    from hil import api
    from hil.errors import ControllerError

    Answers.kinds = {"nan": lambda u: math.nan, "inf": lambda u: -math.inf,
                     "bool": lambda u: True, "text": str, "none": lambda u: None}
    for axes in (None, "x=1,y=2"):
        out = tmp_path / f"{kind}-{axes is not None}.mcap"
        with pytest.raises(ControllerError, match=rf"step\(\) must return a finite current "
                           rf"in mA, got {got}"):
            api.run_servo(Answers, {"kind": kind}, axes=axes, duration_s=0.01, out=str(out))
        errors = [m for _, m in read_session(out).topic("/events")
                  if m["kind"] == "controller.error"]
        assert len(errors) == 1 and errors[0]["data"]["t_s"] == 0.0



def test_a_step_that_raises_or_overruns_its_budget_stops_every_axis(tmp_path):
    from hil import api
    from hil.errors import ControllerError

    def fails(u):
        raise ZeroDivisionError("no gain")

    Answers.kinds = {"raises": fails, "float": float}
    for axes in (None, "x=1,y=2"):
        out = tmp_path / f"raises-{axes is not None}.mcap"
        with pytest.raises(ControllerError, match=r"raised in step\(\): ZeroDivisionError: "
                           r"no gain") as raised:
            api.run_servo(Answers, {"kind": "raises"}, axes=axes, duration_s=0.01, out=str(out))
        assert isinstance(raised.value.__cause__, ZeroDivisionError)
        with pytest.raises(ControllerError, match=r"took .* s in step\(\), over its budget of "
                           r"1e-09 s"):
            api.run_servo(Answers, axes=axes, duration_s=0.01, controller_budget_s=1e-9,
                          out=str(tmp_path / "slow.mcap"))
        for path in (out, tmp_path / "slow.mcap"):
            assert [m["kind"] for _, m in read_session(path).topic("/events")
                    ].count("controller.error") == 1


PLUGIN = '''
from hil.servo.rig import emulated_drives


def open_twin(url, drive, axes, *, on_event, trace=None):
    """A lab's own scheme: here, hil's emulated drives under another name."""
    return emulated_drives(url, drive, axes, on_event=on_event, trace=trace)
'''


def test_an_installed_drive_scheme_opens_one_axis_or_several(tmp_path):
    """A package installed beside hil (a dist-info folder on the path, as pip leaves it)
    declares ``twin`` in the ``hil.drive_devices`` entry points; ``hil servo run`` opens its
    drives through it, from outside, for one axis and for two."""
    plugin = tmp_path / "site"
    (plugin / "my_lab").mkdir(parents=True)
    (plugin / "my_lab" / "__init__.py").write_text("")
    (plugin / "my_lab" / "drives.py").write_text(PLUGIN)
    info = plugin / "my_lab-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-lab\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        "[hil.drive_devices]\ntwin = my_lab.drives:open_twin\n")
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{plugin}")

    def run(*args: str) -> dict:
        done = subprocess.run([sys.executable, "-m", "hil", "servo", "run", "--controller",
                               "pid", "--drive", "twin://cell-3", "--duration", "0.05",
                               "--json", *args], cwd=tmp_path, capture_output=True, text=True,
                              env=env, timeout=180)
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    lone = run("--out", "one.mcap")
    assert lone["drive"] == "twin://cell-3" and lone["ticks"] == 100
    # a plug-in's bus is held to the bus plan as a real one: two axes need a 1 kHz cycle
    (tmp_path / "1khz.toml").write_text("[master]\ncycle_period_us = 1000\n")
    two = run("--axes", "x=1,y=2", "--config", "1khz.toml", "--param", "ti_us=8000",
              "--out", "two.mcap")
    assert two["buses"] == ["twin://cell-3"] and set(two["axes"]) == {"x", "y"}
    assert two["sync_cycles"] == two["ticks"] == 50


def test_an_axis_own_eds_is_the_one_its_drive_is_checked_against(tmp_path, capsys):
    """``[[axis]] eds``: that axis' drive is checked against it (a path beside the config file);
    the other axis keeps ``[master]``'s (none here)."""
    folder = tmp_path / "cell"
    folder.mkdir()
    config = folder / "axes.toml"
    config.write_text("[[axis]]\nname = \"x\"\nnode = 1\n[[axis]]\nname = \"y\"\nnode = 2\n"
                      "eds = \"y-drive.eds\"\n")
    done = hil_here(tmp_path, capsys, "servo", "run", "--config", str(config), "--controller",
                    "pid", "--duration", "0.05", "--out", "eds.mcap")
    assert done.returncode == 2 and str(folder / "y-drive.eds") in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_the_disturbance_scenario_pushes_every_axis(tmp_path):
    """The scenario's torque reaches each axis' drive by SDO (0x2003): the drives are checked
    for it before their cycles are held together, where an SDO answer would wait for a SYNC."""
    from hil import api

    kpis = api.run_servo("pid", axes="x=1,y=2", duration_s=0.3,
                         reference="disturbance:torque=300,start=0.1,end=0.2",
                         out=str(tmp_path / "pushed.mcap"))
    assert kpis["stop_reason"] == "completed"
    data = read_session(tmp_path / "pushed.mcap")
    for name in ("x", "y"):
        pushed = [m["disturbance_mA"] for _, m in data.topic(f"/axis/{name}/command")]
        assert pushed[0] == 0 and max(pushed) == 300 and pushed[-1] == 0
        # the axis moved under the torque and the controller pushed back
        assert kpis["axes"][name]["max_error_deg"] > 0.001
