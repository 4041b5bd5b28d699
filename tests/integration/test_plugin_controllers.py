"""Plug-in controllers through the Python API: every spec form, controllers that misbehave
(the hardware ends in its safe state, the session says why), limits and their verdict."""

import pytest

from hil import api
from hil.core.recording.reader import read_session
from hil.errors import ConfigError, ControllerError

pytestmark = [pytest.mark.slow]


class AlwaysOn:
    """Asks for both peripherals, always."""

    def __init__(self, params):
        self.params = params

    def decide(self, obs):
        return {"P1": True, "P2": True}


class FailsOnThirdDecision:
    def __init__(self, params):
        self.calls = 0

    def decide(self, obs):
        self.calls += 1
        if self.calls == 3:
            raise RuntimeError("lost my lookup table")
        return {"P1": True}


class SwitchesMachining:
    def __init__(self, params):
        pass

    def decide(self, obs):
        return {"M1": True}


class Slow:
    def __init__(self, params):
        pass

    def decide(self, obs):
        import time
        time.sleep(0.05)
        return {}


class Hold:
    def __init__(self, reference, params):
        self.gain = params.get("gain", 100.0)

    def step(self, position_deg, t_s):
        return -self.gain * position_deg


class Explodes:
    def __init__(self, reference, params):
        self.reference = reference

    def step(self, position_deg, t_s):
        if t_s >= 0.1:
            raise ZeroDivisionError("division by zero")
        return 0.0


class RecordsItsOwnTopic:
    """Uses the run's context to record a signal of its own."""

    def __init__(self, params, context):
        self.topic = context.session.topic("/mine/levels", {"type": "object", "title": "Mine"})
        self.t0 = None

    def decide(self, obs):
        self.topic.log(round(obs.t_s * 1e9) + 1, {"q1": obs.levels["q1"]})
        return {"P1": obs.levels["q1"] < 80}


def events(path):
    return [m for _, m in read_session(path).topic("/events")]


def final_relays(path):
    return read_session(path).topic("/bench/relays")[-1][1]


def assert_made_safe_after(path, kind):
    """The safety layer drove every relay to its safe level (verified read-back: the
    ``bench.safe`` event) after the event ``kind`` that stopped the run."""
    timeline = [(t, m["kind"]) for t, m in read_session(path).topic("/events")]
    stopped = next(t for t, k in timeline if k == kind)
    assert any(k == "bench.safe" and t >= stopped for t, k in timeline), timeline


def test_a_class_passed_from_python_runs_and_its_params_arrive(tmp_path):
    kpis = api.run_bench(AlwaysOn, {"x": 1}, cycles=1, out=str(tmp_path / "on.mcap"))
    assert kpis["controller"].endswith("test_plugin_controllers:AlwaysOn")
    switches = kpis["switches"]
    assert switches["P1"] >= 1 and switches["P2"] >= 1  # asked once, switched once
    assert kpis["dwell_violations"] == 0
    assert read_session(tmp_path / "on.mcap").metadata["session"]  # a finished session


def test_builtin_names_module_specs_and_a_context_factory(tmp_path):
    bc = api.run_bench("bc", cycles=1, out=str(tmp_path / "bc.mcap"))
    assert bc["controller"] == "bc" and bc["level_violations"] == 0
    own = api.run_bench(RecordsItsOwnTopic, cycles=1, out=str(tmp_path / "own.mcap"))
    assert own["switches"]["P1"] >= 1
    assert len(read_session(tmp_path / "own.mcap").topic("/mine/levels")) == 28
    spec = "tests.integration.test_plugin_controllers:Hold"
    servo = api.run_servo(spec, {"gain": 50}, reference="hold:position=0", duration_s=0.1,
                          out=str(tmp_path / "hold.mcap"))
    assert servo["controller"] == spec and servo["ticks"] == 200


def test_a_controller_that_raises_stops_the_run_with_relays_safe_and_an_event(tmp_path):
    path = tmp_path / "raise.mcap"
    with pytest.raises(ControllerError, match=r"raised in decide\(\): RuntimeError: lost my "
                       r"lookup table \(test_plugin_controllers.py:\d+ in decide\)"):
        api.run_bench(FailsOnThirdDecision, cycles=1, out=str(path))
    recorded = events(path)
    error = next(e for e in recorded if e["kind"] == "controller.error")
    assert error["level"] == "error" and error["data"]["t_s"] == pytest.approx(2.0)
    assert final_relays(path)["P1"] == 1  # on when the controller failed...
    assert_made_safe_after(path, "controller.error")  # ...then driven to its safe level


@pytest.mark.parametrize(("controller", "message"), [
    (SwitchesMachining, r"decide\(\) named relay 'M1'; it may switch only P1, P2"),
    (Slow, r"took .* s in decide\(\), over its budget of 0.01 s"),
])
def test_wrong_answers_and_slow_answers_are_errors(tmp_path, controller, message):
    with pytest.raises(ControllerError, match=message):
        api.run_bench(controller, cycles=1, controller_budget_s=0.01,
                      out=str(tmp_path / "x.mcap"))
    assert any(e["kind"] == "controller.error" for e in events(tmp_path / "x.mcap"))


def test_a_servo_controller_that_raises_leaves_the_drive_stopped(tmp_path):
    path = tmp_path / "boom.mcap"
    with pytest.raises(ControllerError, match=r"raised in step\(\): ZeroDivisionError"):
        api.run_servo(Explodes, duration_s=0.5, out=str(path))
    kinds = [e["kind"] for e in events(path)]
    assert "controller.error" in kinds
    assert any((k.startswith("drive.") and "safe" in k) or k == "drive.disabled" for k in kinds), \
        kinds


def test_bad_specs_and_unknown_options_are_one_line_errors():
    with pytest.raises(ConfigError, match=r"'nothing_here': no such name \(registered: bc, "
                       r"eec, empc, mpc, pid"):
        api.run_bench("nothing_here")
    with pytest.raises(ConfigError, match=r"has no decide\(\) method: not a bench controller; "
                       r"it has step\(\): a servo controller"):
        api.run_bench(Hold)
    with pytest.raises(Exception, match=r"run_bench: unknown option 'cycels'"):
        api.run_bench("bc", cycels=2)


def test_a_signal_limit_stops_the_run_at_once_and_fails_the_verdict(tmp_path):
    path = tmp_path / "limit.mcap"
    kpis = api.run_bench(AlwaysOn, cycles=1, limits=["total_va<=450", "J2_VA<=2000"],
                         out=str(path))
    assert kpis["passed"] is False
    rows = {row["limit"]: row for row in kpis["limits"]}
    assert rows["total_va<=450"]["passed"] is False
    assert rows["total_va<=450"]["measured"] > 450
    assert kpis["stop_reason"] == "limit total_va<=450"
    abort = next(e for e in events(path) if e["kind"] == "limit.abort")
    assert abort["data"]["limit"] == "total_va<=450"
    assert read_session(path).topic("/bench/power")[-1][0] < 20e9  # long before 28 s
    assert final_relays(path)["P1"] == 1
    assert_made_safe_after(path, "limit.abort")


def test_servo_signal_and_kpi_limits(tmp_path):
    kpis = api.run_servo(Hold, {"gain": 0.0}, reference="sine:amplitude=2,frequency=1",
                         duration_s=0.5, limits=["abs_error_deg<=0.5", "ticks>=1"],
                         out=str(tmp_path / "s.mcap"))
    assert kpis["passed"] is False and kpis["stop_reason"] == "limit abs_error_deg<=0.5"
    assert kpis["ticks"] < 1000  # stopped when the error passed 0.5 deg (t ~ 0.04 s)
    loose = api.run_servo("pid", reference="sine:amplitude=2,frequency=1", duration_s=0.2,
                          limits=["abs_command_mA<=1000", "max_error_deg<=5"],
                          out=str(tmp_path / "p.mcap"))
    assert loose["passed"] is True and loose["stop_reason"] == "completed"
